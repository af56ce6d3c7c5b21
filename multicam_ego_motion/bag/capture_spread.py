"""How far apart a rig's cameras capture one frame, read from a bag's image stamps: the
grouping window free-running cameras need (the general arbiter's `sync_window_s`, the lockstep
player's `--sync-window`), so that a user replaying a recording of cameras that are not
hardware-triggered need not measure it first.

A frame is built as the player builds it: stamps in time order, each camera at most once,
all within half the shortest frame period of the frame's first. The spread is the largest
first-to-last distance of a frame; the window is that spread with room for jitter. Cameras
at different rates (30 and 15 Hz) with common capture instants have a spread of 0, which
identical-stamp grouping already handles.
"""
import math
from dataclasses import dataclass
from typing import Dict, List, Sequence

from multicam_ego_motion.bag.header_stamp import header_stamp_ns

SAMPLE_S = 3.0          # image stamps read from the start of the bag
MARGIN = 1.25           # the window is the largest spread seen times this, plus JITTER_NS
JITTER_NS = 1_000_000


@dataclass
class CaptureSpread:
    spread_ns: int          # largest first-to-last distance of one frame's capture stamps
    period_ns: int          # shortest frame period of any camera (0: unknown)
    window_s: float         # grouping window to use: 0 for identical stamps
    groupable: bool         # a window below half the shortest period exists

    def describe(self) -> str:
        return (f'cameras capture up to {self.spread_ns / 1e6:.1f} ms apart '
                f'(shortest frame period {self.period_ns / 1e6:.1f} ms)')


def capture_spread(stamps: Dict[str, Sequence[int]]) -> CaptureSpread:
    """The spread of the cameras' capture instants and the window that groups them.
    stamps: image topic -> its header stamps [ns]."""
    periods = [min(b - a for a, b in zip(s, s[1:]) if b > a)
               for s in (sorted(set(v)) for v in stamps.values()) if len(s) > 1]
    period = min(periods) if periods else 0
    if period <= 0 or len(stamps) < 2:
        return CaptureSpread(0, period, 0.0, True)
    events = sorted((t, topic) for topic, ts in stamps.items() for t in ts)
    spread, first, seen = 0, None, set()
    for t, topic in events:
        if first is None or topic in seen or 2 * (t - first) >= period:
            first, seen = t, set()
        seen.add(topic)
        spread = max(spread, t - first)
    if spread == 0:
        return CaptureSpread(0, period, 0.0, True)
    window_ns = math.ceil((spread * MARGIN + JITTER_NS) / 1e6) * 1_000_000   # whole ms
    return CaptureSpread(spread, period, window_ns / 1e9, 2 * window_ns < period)


def bag_capture_spread(reader, image_topics: List[str], sample_s: float = SAMPLE_S) -> CaptureSpread:
    """capture_spread of the first `sample_s` seconds of the bag's images (header stamps read
    from the serialized messages: nothing is decoded)."""
    topics = [t for t in image_topics if t in reader.topics]
    stamps = {t: [] for t in topics}
    if not topics or reader.start_ns is None:
        return capture_spread(stamps)
    for m in reader.messages(topics, end_ns=reader.start_ns + int(sample_s * 1e9)):
        stamps[m.topic].append(header_stamp_ns(m.data))
    return capture_spread(stamps)
