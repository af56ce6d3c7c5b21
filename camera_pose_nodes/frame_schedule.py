"""Which frames the graph processes when it cannot keep up with the cameras (ROS-free; the
general arbiter decides, the quarter nodes follow).

Live, a graph slower than its cameras must skip frames, or a queue of them grows into
seconds of latency. Every quarter must skip the *same* frames: the arbiters fuse a frame's
estimates by stamp, and a frame some cameras skipped and others did not is fused from part
of the rig (when each quarter simply took the newest image it had, only a fifth of the
frames of a 30 Hz run were fused from the whole rig, and the ATE grew from 0.2 to 6.7 %).
So the general arbiter decides (FrameGovernor, from the lag of its fused poses behind the
frame stamps) and publishes a FrameSchedule on /ego_motion/frame_schedule: from a frame that
no quarter has taken yet (two frames of the old schedule after the newest estimate the
general arbiter has received, so that the schedule reaches every quarter before it applies: a
worker's executor may hand its quarters the fused pose before the schedule published just
ahead of it, and a quarter may run ahead of the fused poses), every `stride`-th frame.
Quarters apply it to the frames they take (ScheduleBook), so the choice depends on stamps
alone.
"""
from dataclasses import dataclass
from typing import List, Optional

LEAD_FRAMES = 2      # frames of the old schedule before a new one applies


@dataclass(frozen=True)
class FrameSchedule:
    """From `from_ns` on (a frame every quarter processed), the frames at from_ns + k *
    stride * period_ns (nearest stamp) are processed."""
    from_ns: int
    period_ns: int
    stride: int

    def takes(self, stamp_ns: int) -> bool:
        if self.stride <= 1 or stamp_ns <= self.from_ns:
            return True
        k = round((stamp_ns - self.from_ns) / self.period_ns)
        return k % self.stride == 0

    def to_list(self) -> List[int]:
        return [int(self.from_ns), int(self.period_ns), int(self.stride)]

    @classmethod
    def from_list(cls, values) -> 'FrameSchedule':
        values = [int(v) for v in values]
        if len(values) != 3 or values[1] <= 0 or values[2] < 1:
            raise ValueError(f'a frame schedule is [from_ns, period_ns > 0, stride >= 1], got {values}')
        return cls(*values)


class ScheduleBook:
    """A quarter's schedules: each applies from its from_ns until the next one's."""

    def __init__(self):
        self.schedules: List[FrameSchedule] = []

    def add(self, s: FrameSchedule):
        if s in self.schedules:
            return
        self.schedules = sorted(self.schedules + [s], key=lambda x: x.from_ns)[-4:]

    def takes(self, stamp_ns: int) -> bool:
        current = None
        for s in self.schedules:
            if s.from_ns < stamp_ns:
                current = s
        return current is None or current.takes(stamp_ns)

    def get_state(self):
        return [s.to_list() for s in self.schedules]

    def set_state(self, state):
        self.schedules = [FrameSchedule.from_list(v) for v in state or []]


class FrameGovernor:
    """The stride that lets the graph keep up with its cameras.

    The lag is the node's clock at fusion minus the frame's stamp: the driver's stamps and
    the clock agree live, and a replay in rate mode runs the general arbiter on the bag's
    /clock. A lag over `max_lag_s` that is still growing (the graph is slower than the
    frames it takes) raises the stride to one that covers a frame's cost as the growth shows
    it; a lag over twice `max_lag_s` that no longer grows (a backlog) raises it by one until
    the backlog drains. A steady lag is the time one frame takes
    through the graph (a frame waits for the fused pose of the one before it), so a frame
    every floor(lag / period) + 1 periods is what the graph can take: the stride comes down
    to that. Changes are at least `hold_frames` fused frames apart (a change takes that long
    to show). Clocks that disagree by more than `clock_sanity_s` (a bag played without
    /clock) turn the governor off rather than skip frames on a wrong reading."""

    def __init__(self, max_lag_s: float, max_stride: int = 6, hold_frames: int = 6,
                 clock_sanity_s: float = 10.0):
        self.max_lag_s = float(max_lag_s)
        self.max_stride = int(max_stride)
        self.hold_frames = int(hold_frames)
        self.clock_sanity_s = float(clock_sanity_s)
        self.stride = 1
        self.period_ns: Optional[int] = None
        self.last_stamp_ns: Optional[int] = None
        # since the last change, oldest first; the last 2 * hold_frames are all the rules read
        # (the general arbiter snapshots this state every frame: it must not grow with the run)
        self.lags: List[float] = []
        self.clock_mismatch = False

    @property
    def enabled(self) -> bool:
        return self.max_lag_s > 0.0 and not self.clock_mismatch

    def update(self, stamp_ns: int, now_ns: int, newest_ns: Optional[int] = None) -> Optional[FrameSchedule]:
        """After fusing frame `stamp_ns` at clock `now_ns`: a new schedule, or None.
        `newest_ns`: the newest stamp of any estimate the arbiter has received (quarters
        may be ahead of the fused frame)."""
        # The frame period: the shortest step between fused frames (the graph starts on
        # every frame; a schedule's frames are whole periods apart whatever it is).
        if self.last_stamp_ns is not None and stamp_ns > self.last_stamp_ns:
            step = stamp_ns - self.last_stamp_ns
            if self.period_ns is None or step < self.period_ns:
                self.period_ns = int(step)
        self.last_stamp_ns = stamp_ns
        if not self.enabled:
            return None
        lag = (now_ns - stamp_ns) * 1e-9
        if abs(lag) > self.clock_sanity_s:
            self.clock_mismatch = True
            return None
        self.lags = self.lags[-(2 * self.hold_frames - 1):] + [lag]
        if self.period_ns is None or len(self.lags) < self.hold_frames:
            return None
        recent = self.lags[-self.hold_frames:]
        growing = recent[-1] - recent[0] > 0.5 * self.period_ns * 1e-9
        stride = self.stride
        if growing:
            if lag > self.max_lag_s:
                # a frame costs the graph its stride's periods plus what the lag grows by
                # per frame: go straight to a stride that covers it
                cost_ns = self.stride * self.period_ns + (recent[-1] - recent[0]) * 1e9 / (len(recent) - 1)
                stride = min(max(self.stride + 1, int(cost_ns // self.period_ns) + 1), self.max_stride)
        elif lag > 2 * self.max_lag_s:
            stride = min(self.stride + 1, self.max_stride)      # keeping up: drain the backlog
        elif len(self.lags) >= 2 * self.hold_frames:
            steady = sorted(recent)[len(recent) // 2] * 1e9
            stride = max(1, min(self.stride, int(steady // self.period_ns) + 1))
        if stride == self.stride:
            return None
        # From a frame of the old schedule after the newest estimate received, not after the
        # fused frame: a quarter whose fused poses time out runs ahead of them, and a schedule
        # starting behind it left frames it had processed and the others skipped (fused from
        # part of the rig). Not after the clock's now either: under load that is seconds
        # ahead, and the stride would come that much too late.
        step = self.stride * self.period_ns
        ahead = max(0, int(newest_ns) - int(stamp_ns)) if newest_ns is not None else 0
        start = int(stamp_ns) + (LEAD_FRAMES + -(-ahead // step)) * step
        self.stride = stride
        self.lags = []
        return FrameSchedule(start, self.period_ns, stride)

    def get_state(self) -> dict:
        return {k: (list(v) if isinstance(v, list) else v) for k, v in vars(self).items()}

    def set_state(self, s: dict):
        vars(self).update(s)
