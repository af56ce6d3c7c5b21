"""How far apart a rig's cameras capture one frame, from their stamps: the grouping window
free-running cameras need (the general arbiter's `sync_window_s`, the lockstep player's
`--sync-window`), so that a user of cameras that are not hardware-triggered need not measure
it first. `replay` reads it from the bag's image stamps; a live general arbiter learns it from
its cameras' first estimates (WindowLearner).

A frame is built as the player builds it: stamps in time order, each camera at most once,
all within half the shortest frame period of the frame's first. The spread is the largest
first-to-last distance of a frame; the window is that spread with room for jitter. Cameras
at different rates (30 and 15 Hz) with common capture instants have a spread of 0, which
identical-stamp grouping already handles.
"""
import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

MARGIN = 1.25           # the window is the largest spread seen times this, plus JITTER_NS
JITTER_NS = 1_000_000


@dataclass
class CaptureSpread:
    spread_ns: int          # largest first-to-last distance of one frame's capture stamps
    period_ns: int          # shortest frame period of any camera (0: unknown)
    window_s: float         # grouping window to use: 0 for identical stamps
    groupable: bool         # a window below half the shortest period exists
    # frames a lockstep player must have out at once while the cameras' periods are still
    # unknown (start_depth)
    start_frames: int = 1

    def describe(self) -> str:
        return (f'cameras capture up to {self.spread_ns / 1e6:.1f} ms apart '
                f'(shortest frame period {self.period_ns / 1e6:.1f} ms)')

    def verdict(self) -> Tuple[Optional[float], Optional[str]]:
        """(the window to group by, what to tell the user): (None, None) for identical stamps;
        (None, a warning) when no window under half the period groups them."""
        if self.window_s == 0:
            return None, None
        if not self.groupable:
            return None, (f'{self.describe()}: no sync window groups them into frames (it would have '
                          'to stay under half the period); each image is fused on its own')
        return self.window_s, (f'{self.describe()}: free-running, grouped by a sync window of '
                               f'{self.window_s:g} s')


def capture_spread(stamps: Dict[str, Sequence[int]]) -> CaptureSpread:
    """The spread of the cameras' capture instants and the window that groups them.
    stamps: image topic -> its header stamps [ns]."""
    periods = [min(b - a for a, b in zip(s, s[1:]) if b > a)
               for s in (sorted(set(v)) for v in stamps.values()) if len(s) > 1]
    period = min(periods) if periods else 0
    start = start_depth(stamps)
    if period <= 0 or len(stamps) < 2:
        return CaptureSpread(0, period, 0.0, True, start)
    events = sorted((t, topic) for topic, ts in stamps.items() for t in ts)
    spread, first, seen = 0, None, set()
    for t, topic in events:
        if first is None or topic in seen or 2 * (t - first) >= period:
            first, seen = t, set()
        seen.add(topic)
        spread = max(spread, t - first)
    if spread == 0:
        return CaptureSpread(0, period, 0.0, True, start)
    window_ns = math.ceil((spread * MARGIN + JITTER_NS) / 1e6) * 1_000_000   # whole ms
    return CaptureSpread(spread, period, window_ns / 1e9, 2 * window_ns < period, start)


def start_depth(stamps: Dict[str, Sequence[int]]) -> int:
    """Capture instants a lockstep player must have out at once at the start: until a
    camera's second image its period is unknown, so the general arbiter waits for it in every
    group, until an image of it after the group comes (stamp_sync). For each group before a
    camera's second image, the instants from the group to that camera's next image. Cameras
    at 30 and 10 Hz with common instants: 0, 33, 67, 100 ms, the 33 ms group waits for the 10
    Hz camera's 100 ms image: 3 (1 for identical rates and stamps)."""
    instants = sorted({t for v in stamps.values() for t in v})
    index = {t: i for i, t in enumerate(instants)}
    need = 1
    for ts in stamps.values():
        own = set(ts)
        ts = sorted(own)
        for t_next in ts[1:2]:              # (cameras with a second image in the sample)
            for i, g in enumerate(instants):
                if g >= t_next:
                    break
                if g in own:
                    continue                # its own image is in that group
                nxt = next(t for t in ts if t > g)
                need = max(need, index[nxt] - i + 1)
    return need


class WindowLearner:
    """Collects each camera's first stamps; once one camera has `frames` of them (and another
    camera at least two), `add` returns their CaptureSpread, once."""

    def __init__(self, frames: int = 20):
        self.frames = int(frames)
        self.stamps: Dict[str, List[int]] = {}
        self.done = False

    def add(self, source: str, stamp_ns: int):
        if self.done:
            return None
        seen = self.stamps.setdefault(source, [])
        if not seen or stamp_ns > seen[-1]:
            seen.append(int(stamp_ns))
        if len(seen) < self.frames or sum(len(v) >= 2 for v in self.stamps.values()) < 2:
            return None
        self.done = True
        return capture_spread(self.stamps)
