"""Group estimates of one frame from several sources (quarters, or cameras) by stamp.

A group is released when every source that is alive has reported, or when it has waited
`timeout_s`. A source that missed a release is marked absent and no longer waited for until
it reports again; so a camera whose topics are missing costs one timeout, not one per frame.
Groups are released in stamp order and a stamp older than the last release is dropped.
"""
from dataclasses import dataclass, field
from typing import Dict, List


@dataclass
class Group:
    stamp_ns: int
    items: Dict[str, object]
    missing: List[str] = field(default_factory=list)
    timed_out: bool = False


class StampSynchronizer:
    def __init__(self, sources, timeout_s: float):
        self.sources = list(sources)
        self.timeout_s = float(timeout_s)
        self.absent = set()
        self._groups: Dict[int, Dict[str, object]] = {}
        self._first_seen: Dict[int, float] = {}
        self.last_released_ns = None
        self.dropped_late = 0

    def add(self, source: str, stamp_ns: int, item, now: float) -> List[Group]:
        # Even a late estimate proves the source is alive: wait for it from the next frame on.
        self.absent.discard(source)
        if self.last_released_ns is not None and stamp_ns <= self.last_released_ns:
            self.dropped_late += 1
            return self.poll(now)
        self._groups.setdefault(stamp_ns, {})[source] = item
        self._first_seen.setdefault(stamp_ns, now)
        return self.poll(now)

    def expected(self):
        return [s for s in self.sources if s not in self.absent]

    def poll(self, now: float) -> List[Group]:
        out = []
        while self._groups:
            stamp = min(self._groups)
            items = self._groups[stamp]
            complete = all(s in items for s in self.expected())
            newer_complete = any(all(s in g for s in self.expected())
                                 for st, g in self._groups.items() if st > stamp)
            waited = now - self._first_seen[stamp] >= self.timeout_s
            if not (complete or waited or newer_complete):
                break
            missing = [s for s in self.sources if s not in items]
            self.absent.update(missing)
            out.append(Group(stamp, items, missing, timed_out=not complete))
            del self._groups[stamp]
            del self._first_seen[stamp]
            self.last_released_ns = stamp
        return out
