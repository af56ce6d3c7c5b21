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
ahead of it, and a quarter may run ahead of the fused poses), `keep` frames of every
`stride`, spread evenly. Quarters apply it to the frames they take (ScheduleBook), so the
choice depends on stamps alone.

Why fractions: a graph that needs 1.4 frame periods per frame can take 5 frames of 7; every
second frame (the only integer stride that keeps up) dropped half of them where 2 in 7 had
to go. Kept frames spread evenly (k * keep mod stride < keep): the gaps between them differ
by one period at most.
"""
from dataclasses import dataclass
from fractions import Fraction
from typing import List, Optional

LEAD_FRAMES = 2      # frames of the old schedule before a new one applies
MAX_DENOMINATOR = 8  # kept fractions are keep / stride with stride up to this (or max_stride)
# A camera whose period is this share or more off the schedule's runs at another rate than the
# rig's fastest (30 / 20 Hz: 0.5); frame-to-frame jitter stays far below it.
OWN_RATE_SHARE = 0.2
MAX_LAGS = 256       # lags the governor keeps (free-running cameras: several per frame gap)
CEILING_MEMORY_S = 30.0   # how long a fraction the lag outgrew caps the free-running climb


def learn_period(period_ns: Optional[int], last_ns: Optional[int], stamp_ns: int) -> Optional[int]:
    """A source's frame period after one more of its stamps: the shortest step between its
    stamps so far (a skipped, dropped or late frame only lengthens a step)."""
    if last_ns is None or stamp_ns <= last_ns:
        return period_ns
    step = int(stamp_ns - last_ns)
    return step if period_ns is None else min(period_ns, step)


@dataclass(frozen=True)
class FrameSchedule:
    """From `from_ns` on (a frame every quarter processed), of the frames at from_ns + k *
    period_ns (nearest stamp) those with k * keep mod stride < keep are processed: `keep` of
    every `stride`, evenly spread (keep 1: every stride-th)."""
    from_ns: int
    period_ns: int
    stride: int
    keep: int = 1

    def takes(self, stamp_ns: int, period_ns: Optional[int] = None) -> bool:
        """`period_ns`: the camera's own frame period where it is not the rig's (a 15 Hz
        camera in a 30 Hz rig counts its own frames; by the rig's it would keep all or none)."""
        if self.keep >= self.stride or stamp_ns <= self.from_ns:
            return True
        k = round((stamp_ns - self.from_ns) / (period_ns or self.period_ns))
        return (k * self.keep) % self.stride < self.keep

    @property
    def fraction(self) -> Fraction:
        return Fraction(min(self.keep, self.stride), self.stride)

    def to_list(self) -> List[int]:
        return [int(self.from_ns), int(self.period_ns), int(self.stride), int(self.keep)]

    @classmethod
    def from_list(cls, values) -> 'FrameSchedule':
        values = [int(v) for v in values]
        if len(values) == 3:
            values.append(1)
        if len(values) != 4 or values[1] <= 0 or values[2] < 1 or not 1 <= values[3] <= values[2]:
            raise ValueError('a frame schedule is [from_ns, period_ns > 0, stride >= 1, '
                             f'1 <= keep <= stride], got {values}')
        return cls(*values)


def kept_fractions(max_stride: int) -> List[Fraction]:
    """The fractions of frames a schedule may keep, ascending: keep / stride with stride up
    to MAX_DENOMINATOR, none below 1 / max_stride."""
    den = max(MAX_DENOMINATOR, max_stride)
    return sorted({Fraction(k, d) for d in range(1, den + 1) for k in range(1, d + 1)
                   if Fraction(k, d) >= Fraction(1, max_stride)})


def own_period(schedule_period_ns: int, camera_period_ns: Optional[int]) -> Optional[int]:
    """The period a camera counts its frames by: its own where its rate is not the rig's
    (more than OWN_RATE_SHARE apart), else the schedule's, so that the cameras of a
    synchronised rig, whose shortest steps differ by their jitter, count the same frames."""
    if camera_period_ns is None or abs(camera_period_ns - schedule_period_ns) <= OWN_RATE_SHARE * schedule_period_ns:
        return None
    return int(camera_period_ns)


class ScheduleBook:
    """One camera's schedules (a quarter's), each applying from its from_ns until the next
    one's; or the general arbiter's, for every camera, each with its frame period."""

    def __init__(self):
        self.schedules: List[FrameSchedule] = []
        self.period_ns: Optional[int] = None    # the camera's: the shortest step between its stamps
        self.last_ns: Optional[int] = None

    def add(self, s: FrameSchedule):
        if s in self.schedules:
            return
        self.schedules = sorted(self.schedules + [s], key=lambda x: x.from_ns)[-4:]

    def saw(self, stamp_ns: int):
        """A frame of the camera came (taken or not): its period."""
        self.period_ns = learn_period(self.period_ns, self.last_ns, stamp_ns)
        if self.last_ns is None or stamp_ns > self.last_ns:
            self.last_ns = int(stamp_ns)

    def takes(self, stamp_ns: int, camera_period_ns: Optional[int] = None) -> bool:
        current = None
        for s in self.schedules:
            if s.from_ns < stamp_ns:
                current = s
        if current is None:
            return True
        return current.takes(stamp_ns, own_period(current.period_ns, camera_period_ns or self.period_ns))

    def get_state(self):
        return {'schedules': [s.to_list() for s in self.schedules], 'period_ns': self.period_ns,
                'last_ns': self.last_ns}

    def set_state(self, state):
        if isinstance(state, dict):
            self.period_ns, self.last_ns = state.get('period_ns'), state.get('last_ns')
            state = state.get('schedules')
        self.schedules = [FrameSchedule.from_list(v) for v in state or []]


class FrameGovernor:
    """The fraction of frames that lets the graph keep up with its cameras.

    The lag is the node's clock at fusion minus the frame's stamp: the driver's stamps and
    the clock agree live, and a replay in rate mode runs the general arbiter on the bag's
    /clock. A lag over `max_lag_s` that is still growing (the graph is slower than the
    frames it takes) lowers the fraction to one whose mean gap between frames covers a
    frame's cost as the growth shows it; a lag over twice `max_lag_s` that no longer grows (a
    backlog) lowers it a step until the backlog drains. A steady lag is the time one frame
    takes through the graph (a frame waits for the fused pose of the one before it), so the
    largest fraction whose mean gap is `margin` longer than that is what the graph can take:
    the fraction comes back up to that. Changes are at least `hold_frames` fused frames apart
    (a change takes that long to show). Clocks that disagree by more than `clock_sanity_s` (a
    bag played without /clock) turn the governor off rather than skip frames on a wrong
    reading."""

    def __init__(self, max_lag_s: float, max_stride: int = 6, hold_frames: int = 6,
                 clock_sanity_s: float = 10.0, margin: float = 0.1):
        self.max_lag_s = float(max_lag_s)
        self.max_stride = int(max_stride)
        self.hold_frames = int(hold_frames)
        self.clock_sanity_s = float(clock_sanity_s)
        self.margin = float(margin)
        self.stride = 1                  # the kept fraction is keep / stride
        self.keep = 1
        self.period_ns: Optional[int] = None
        self.last_stamp_ns: Optional[int] = None
        # since the last change, oldest first, with their frames' stamps; the last 2 *
        # hold_frames frame gaps are all the rules read (the general arbiter snapshots this
        # state every frame: it must not grow with the run)
        self.lags: List[float] = []
        self.lag_stamps: List[int] = []
        self.clock_mismatch = False
        # the lowest fraction the lag outgrew (free-running cameras' climb stays below it for
        # CEILING_MEMORY_S of stamps), and the stamp then
        self.ceiling: Optional[Fraction] = None
        self.ceiling_ns: Optional[int] = None

    @property
    def enabled(self) -> bool:
        return self.max_lag_s > 0.0 and not self.clock_mismatch

    @property
    def fraction(self) -> Fraction:
        return Fraction(self.keep, self.stride)

    def achieved_rate_hz(self) -> Optional[float]:
        """Frames processed per second of camera time (None before the period is known)."""
        return None if self.period_ns is None else float(self.fraction) * 1e9 / self.period_ns

    def camera_rate_hz(self) -> Optional[float]:
        return None if self.period_ns is None else 1e9 / self.period_ns

    def _at_most(self, f: float) -> Fraction:
        fits = [x for x in kept_fractions(self.max_stride) if x <= f]
        return fits[-1] if fits else Fraction(1, self.max_stride)

    def _step(self, up: bool) -> Fraction:
        """The kept fraction one step above (or below) the current one; the current at the end."""
        steps = kept_fractions(self.max_stride)
        if up:
            return next((x for x in steps if x > self.fraction), self.fraction)
        return next((x for x in reversed(steps) if x < self.fraction), self.fraction)

    def _climb(self) -> Fraction:
        """A step up for free-running cameras. While the lag has outgrown no fraction below
        every frame (for CEILING_MEMORY_S), half the frames skipped are taken again, up to the
        fraction below every frame, then every frame: an overload that passed (a node's move,
        a burst of extraction) left a graph with room, where one fraction at a time cost a
        0.5 s burst a fifth of the next 20 s of frames. Below a fraction the lag outgrew, one
        fraction at a time: a graph at its limit is not overshot again."""
        step = self._step(up=True)
        if self.ceiling is not None and self.ceiling < 1:
            return step
        bold = self._at_most(1.0 - 0.5 * (1.0 - float(self.fraction)))
        return max(step, min(bold, max(x for x in kept_fractions(self.max_stride) if x < 1)))

    def _free_running(self) -> bool:
        """Several estimates fused within one frame period: cameras at their own phases."""
        st = self.lag_stamps
        return any(0 < b - a < 0.5 * self.period_ns for a, b in zip(st, st[1:]))

    def update(self, stamp_ns: int, now_ns: int, newest_ns: Optional[int] = None,
               frame_period_ns: Optional[int] = None) -> Optional[FrameSchedule]:
        """After fusing frame `stamp_ns` at clock `now_ns`: a new schedule, or None.
        `newest_ns`: the newest stamp of any estimate the arbiter has received (quarters
        may be ahead of the fused frame). `frame_period_ns`: the cameras' frame period (the
        shortest of their own); without it, the shortest step between fused frames, which is
        the same for a synchronised rig but a fraction of it for free-running cameras, whose
        estimates are fused at their own stamps."""
        if frame_period_ns is not None:
            self.period_ns = int(frame_period_ns)
        elif self.last_stamp_ns is not None and stamp_ns > self.last_stamp_ns:
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
        if self.period_ns is None:
            return None
        if self.ceiling is not None and (stamp_ns - self.ceiling_ns) * 1e-9 > CEILING_MEMORY_S:
            self.ceiling = self.ceiling_ns = None      # (forgotten before any rule reads it)
        P = self.period_ns * 1e-9
        gap = P / float(self.fraction)             # the mean gap between a camera's frames processed
        # The rules read lags over stamp time: hold_frames of a camera's processed frames (a
        # synchronised rig's fused frames; free-running cameras fuse several in that time).
        self.lags.append(lag)
        self.lag_stamps.append(int(stamp_ns))
        keep_from = len(self.lags) - 2 * self.hold_frames
        while keep_from > 0 and (self.lag_stamps[-1] - self.lag_stamps[keep_from]) * 1e-9 < (2 * self.hold_frames - 1) * gap:
            keep_from -= 1
        keep_from = max(keep_from, len(self.lags) - MAX_LAGS)
        if keep_from > 0:
            del self.lags[:keep_from], self.lag_stamps[:keep_from]
        span_s = (self.lag_stamps[-1] - self.lag_stamps[0]) * 1e-9
        if len(self.lags) < self.hold_frames or span_s < (self.hold_frames - 1) * gap - 0.5 * P:
            return None
        first = len(self.lags) - self.hold_frames
        while first > 0 and (self.lag_stamps[-1] - self.lag_stamps[first]) * 1e-9 < (self.hold_frames - 1) * gap - 0.5 * P:
            first -= 1
        recent = self.lags[first:]
        recent_span_s = (self.lag_stamps[-1] - self.lag_stamps[first]) * 1e-9
        growing = recent[-1] - recent[0] > 0.5 * P
        fraction = self.fraction
        if growing:
            if lag > self.max_lag_s:
                # a frame costs the graph its gap plus what the lag grows by in that gap: go
                # straight to a fraction that covers it
                cost = gap * (1.0 + (recent[-1] - recent[0]) / max(recent_span_s, 1e-9))
                fraction = min(self._at_most(P / (cost * (1.0 + self.margin))), self._step(up=False))
                if self.ceiling is None or self.fraction <= self.ceiling:
                    self.ceiling, self.ceiling_ns = self.fraction, int(stamp_ns)
        elif lag > 2 * self.max_lag_s:
            fraction = self._step(up=False)          # keeping up: drain the backlog
        elif len(self.lags) >= 2 * self.hold_frames and span_s >= (2 * self.hold_frames - 1) * gap - 0.5 * P:
            steady = sorted(recent)[len(recent) // 2]
            # (a lag of zero or less: a clock that reads the frames' stamps, e.g. /clock from
            # the player: every frame)
            cap = P / (steady * (1.0 + self.margin)) if steady > 0.0 else 1.0
            up = self._at_most(cap)
            if self._free_running():
                # one estimate's lag is one camera's image and its wait behind the others',
                # not the rig's frame: it cannot say how much more the graph can take, so the
                # fraction goes up by steps and the growing rule finds the cost
                up = min(up, self._climb())
            fraction = min(max(self.fraction, up), Fraction(1))
        if fraction == self.fraction:
            return None
        # From a frame of the old schedule after the newest estimate received, not after the
        # fused frame: a quarter whose fused poses time out runs ahead of them, and a schedule
        # starting behind it left frames it had processed and the others skipped (fused from
        # part of the rig). Not after the clock's now either: under load that is seconds
        # ahead, and the stride would come that much too late. (Whole old strides from a
        # processed frame land on frames the old schedule processes.)
        step = self.stride * self.period_ns
        ahead = max(0, int(newest_ns) - int(stamp_ns)) if newest_ns is not None else 0
        start = int(stamp_ns) + (LEAD_FRAMES + -(-ahead // step)) * step
        self.stride, self.keep = fraction.denominator, fraction.numerator
        self.lags, self.lag_stamps = [], []
        return FrameSchedule(start, self.period_ns, self.stride, self.keep)

    def get_state(self) -> dict:
        return {k: (list(v) if isinstance(v, list) else v) for k, v in vars(self).items()}

    def set_state(self, s: dict):
        s = dict(s)
        s.setdefault('keep', 1)
        s.setdefault('margin', 0.1)
        s.setdefault('ceiling', None)
        s.setdefault('ceiling_ns', None)
        if len(s.get('lag_stamps', ())) != len(s.get('lags', ())):
            s['lags'], s['lag_stamps'] = [], []
        vars(self).update(s)
