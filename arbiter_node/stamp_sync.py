"""Group estimates of one frame from several sources (quarters, or cameras) by stamp.

A group holds at most one estimate per source whose stamps lie within `window_ns` of one
another (0: identical stamps, a hardware-synchronised rig; free-running cameras capture a
few milliseconds apart). A group is released when every source that is alive and due has
reported, when a later group is complete, or when it has waited `timeout_s`. A source that
missed a release it was due for is marked absent and no longer waited for until it reports
again; so a camera whose topics are missing costs one timeout, not one per frame.

Due: a source's frame period is the shortest step between its stamps; a group that ends
before the source's next frame can come (its stamp before the group plus most of its period)
is not waited for. Nor is a group older than a stamp the source already reported (a source's
stamps only grow: with two frames in flight, a 15 Hz camera's next frame can come while the
30 Hz frame before it is still open). Cameras at different rates (30 and 15 Hz) then fill the groups of their own
frames and no other. Until a source has two stamps its period is unknown: it is waited for,
and a first miss does not mark it absent (it may be a slower camera, not a dead one).

Frames a frame schedule skips (the graph is behind its cameras) do not come: with `takes(source,
stamp_ns)` given, a source is due at its next frame the schedule takes, not at the next one.

Groups are released in stamp order and a stamp not after the last release is dropped. A
group's `missing` names the sources that were due in it and did not report; not one whose next
frame came after the group where its period put it (a free-running camera due within the
jitter allowance that captured a few ms later: it was never going to be in this group).
"""
from dataclasses import dataclass, field
from typing import Dict, List, Optional

from camera_pose_nodes.frame_schedule import learn_period

# A source is not due in a group that ends more than this share of its period before its
# next expected stamp: frame-to-frame jitter of a free-running camera stays well below it.
DUE_JITTER_SHARE = 0.125
RECENT_STAMPS = 8
MAX_SKIPPED = 64     # frames in a row a schedule may skip (its stride is at most this)


@dataclass
class Group:
    stamp_ns: int                      # the common time: the latest stamp of the group
    items: Dict[str, object]
    missing: List[str] = field(default_factory=list)
    timed_out: bool = False
    stamps: Dict[str, int] = field(default_factory=dict)   # source -> its own stamp

    @property
    def first_ns(self) -> int:
        return min(self.stamps.values()) if self.stamps else self.stamp_ns


class _Open:
    # lo / hi kept as stamps come in: they are read for every source at every poll.
    __slots__ = ('items', 'stamps', 'first_seen', 'lo', 'hi')

    def __init__(self, now):
        self.items: Dict[str, object] = {}
        self.stamps: Dict[str, int] = {}
        self.first_seen = now
        self.lo = self.hi = None

    def put(self, source: str, stamp_ns: int, item):
        self.items[source] = item
        self.stamps[source] = stamp_ns
        self.lo = stamp_ns if self.lo is None else min(self.lo, stamp_ns)
        self.hi = stamp_ns if self.hi is None else max(self.hi, stamp_ns)


class StampSynchronizer:
    def __init__(self, sources, timeout_s: float, window_ns: int = 0, takes=None):
        self.sources = list(sources)
        self.takes = takes                         # (source, stamp_ns) -> the schedule takes it
        self.timeout_s = float(timeout_s)
        self.window_ns = int(window_ns)
        if self.window_ns < 0:
            raise ValueError(f'sync window must be >= 0 ns, got {window_ns}')
        self.absent = set()
        self._open: List[_Open] = []               # by first stamp
        self.last_released_ns = None
        self.dropped_late = 0
        self.last_stamp: Dict[str, int] = {}       # newest stamp per source
        self.period_ns: Dict[str, int] = {}        # shortest step between a source's stamps
        self.unknown_misses: Dict[str, int] = {}   # misses while the period was unknown
        self.recent: Dict[str, List[int]] = {}     # a source's last RECENT_STAMPS stamps

    def add(self, source: str, stamp_ns: int, item, now: float) -> List[Group]:
        self.saw(source, stamp_ns)
        if self.last_released_ns is not None and stamp_ns <= self.last_released_ns:
            self.dropped_late += 1
            return self.poll(now)
        group = self._group_for(source, stamp_ns, now)
        group.put(source, stamp_ns, item)
        self._open.sort(key=lambda g: g.lo)
        return self.poll(now)

    def saw(self, source: str, stamp_ns: int):
        """The source reported this stamp (added, or left out by the caller): it is alive
        (waited for from the next frame on), and past every earlier group."""
        self.absent.discard(source)
        self.unknown_misses.pop(source, None)
        self._note_stamp(source, stamp_ns)

    def _note_stamp(self, source, stamp_ns):
        last = self.last_stamp.get(source)
        period = learn_period(self.period_ns.get(source), last, stamp_ns)
        if period is not None:
            self.period_ns[source] = period
        if last is None or stamp_ns > last:
            self.last_stamp[source] = int(stamp_ns)
            self.recent.setdefault(source, []).append(int(stamp_ns))
            del self.recent[source][:-RECENT_STAMPS]

    def _group_for(self, source, stamp_ns, now) -> _Open:
        fits = []
        for g in self._open:
            if source in g.items:
                if g.stamps[source] == stamp_ns:
                    return g               # the same estimate again (a republished frame)
                continue
            if max(g.hi, stamp_ns) - min(g.lo, stamp_ns) <= self.window_ns:
                fits.append(g)
        if fits:
            # (a window wider than the rig's spread can fit two: the nearest stamps win)
            return min(fits, key=lambda g: max(abs(t - stamp_ns) for t in g.stamps.values()))
        g = _Open(now)
        self._open.append(g)
        return g

    def expected(self):
        return [s for s in self.sources if s not in self.absent]

    def due(self, source: str, g: _Open) -> bool:
        """Whether the source can have a frame in the group (see the module docstring)."""
        if source in g.items:
            return True
        period = self.period_ns.get(source)
        prev = self._before(source, g)
        if period is None or prev is None:
            return True
        return self._next_due(source, prev, period) - DUE_JITTER_SHARE * period <= g.lo + self.window_ns

    def _next_due(self, source, prev, period) -> int:
        """The stamp of the source's next frame after `prev` that the schedule takes."""
        nxt = prev + period
        if self.takes is not None:
            for _ in range(MAX_SKIPPED):
                if self.takes(source, nxt):
                    break
                nxt += period
        return nxt

    def _before(self, source: str, g: _Open) -> Optional[int]:
        """The source's last recent stamp before the group."""
        return max((t for t in self.recent.get(source, ()) if t < g.lo), default=None)

    def past(self, source: str, g: _Open) -> bool:
        """The source reported a later frame already: it has nothing more for this group (a
        source's stamps only grow), e.g. while lockstep has two frames in flight."""
        return source not in g.items and self.last_stamp.get(source, -1) > g.lo + self.window_ns

    def _next_came_after(self, source: str, g: _Open) -> bool:
        """The source's first stamp after the group is the one its period puts there (within
        the jitter allowance), i.e. its frame was not due inside the group after all."""
        period = self.period_ns.get(source)
        prev = self._before(source, g)
        nxt = min((t for t in self.recent.get(source, ()) if t > g.hi + self.window_ns), default=None)
        if period is None or prev is None or nxt is None:
            return False
        return nxt <= self._next_due(source, prev, period) + DUE_JITTER_SHARE * period

    def _waits_for(self, source: str, g: _Open) -> bool:
        return source not in self.absent and self.due(source, g) and not self.past(source, g)

    def _complete(self, g: _Open) -> bool:
        if all(s in g.items for s in self.sources):
            return True                    # every source reported (a synchronised rig's case)
        return all(s in g.items for s in self.sources if self._waits_for(s, g))

    def poll(self, now: float) -> List[Group]:
        out = []
        while self._open:
            g = self._open[0]
            complete = self._complete(g)
            waited = now - g.first_seen >= self.timeout_s
            if not (complete or waited or any(self._complete(h) for h in self._open[1:])):
                break
            missing = [s for s in self.sources
                       if s not in g.items and self.due(s, g) and not self._next_came_after(s, g)]
            for s in missing:
                if self.past(s, g):
                    continue               # alive: it skipped this frame
                if s in self.last_stamp and s not in self.period_ns:
                    # Reported once so far: maybe a slower camera; absent on its second miss.
                    self.unknown_misses[s] = self.unknown_misses.get(s, 0) + 1
                    if self.unknown_misses[s] < 2:
                        continue
                self.absent.add(s)
            out.append(Group(g.hi, g.items, missing, timed_out=not complete, stamps=dict(g.stamps)))
            self._open.pop(0)
            self.last_released_ns = g.hi
        return out
