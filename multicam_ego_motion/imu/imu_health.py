"""The health of the rig's IMU (ROS-free): fed every sample, consulted at every frame step;
it says whether the gyro may be used and, when not, which problem it has.

Problems, each with a name the diagnostics say:
- wrong_frame: a sample in another frame than the rig's IMU (its rotation would be wrong);
- saturated: a gyro component at or beyond `gyro_saturation`, or one component reading the
  same non-zero value `saturation_repeats` times in a row while the others move (a range
  that clips);
- stuck: the gyro repeating one sample exactly, all three axes, `stuck_samples` times in a
  row (a MEMS gyro's noise never repeats);
- silent: no sample for more than `silent_s` at a frame's stamp, or none at all since the
  first frame;
- out_of_order / not_finite: more than `refused_fraction` of the last `refused_window`
  samples refused by the ImuBuffer (fewer is jitter, tolerated; a sample taken already and
  delivered again is counted as refused, not as a problem);
- bias_drift: the filter's gyro-bias estimate beyond `gyro_bias_max` (a MEMS gyro's
  turn-on bias is a few tenths of a degree per second; more is a gyro gone wrong), or the
  cameras' fixes turning away from the gyro's prediction by more than `gyro_disagreement`,
  plus `disagreement_per_rotation` of the rotation (the cameras' own error grows with it:
  4 % in the 10 s loop's turns), on average over `disagreement_window_s` (the innovation
  test: a bias running away faster than the filter's bias walk lets it follow).

Hysteresis: after any problem the gyro stays out until none was seen for `recover_s`. A
bias_drift holds until the fusion is reset: with the gyro out nothing tells it again.
"""
from collections import deque
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from multicam_ego_motion.imu.imu_buffer import plain_floats

AXES = 'xyz'


@dataclass(frozen=True)
class ImuHealthLimits:
    gyro_saturation: float = 34.9        # rad/s (2000 deg/s, a MEMS gyro's widest range)
    saturation_repeats: int = 20
    stuck_samples: int = 20
    silent_s: float = 0.2
    refused_fraction: float = 0.05
    refused_window: int = 100            # samples
    gyro_bias_max: float = 0.05          # rad/s
    gyro_disagreement: float = 0.03      # rad/s
    disagreement_per_rotation: float = 0.05
    disagreement_window_s: float = 1.0
    recover_s: float = 2.0


class ImuHealth:
    def __init__(self, frame_id: str, limits: ImuHealthLimits = ImuHealthLimits()):
        self.frame_id = frame_id
        self.limits = limits
        self.received = 0               # every sample handed in
        self.refused = 0                # of them refused (wrong frame, out of order, not finite)
        self.reason: Optional[str] = None    # why the last refused one was
        self.last_heard_ns: Optional[int] = None   # newest stamp of any sample
        self.first_check_ns: Optional[int] = None
        self.problem: Optional[str] = None   # the problem's name while one is seen
        self.detail = ''                     # what was seen of it
        self.last_fault_ns: Optional[int] = None
        self.faults = 0                      # times a healthy IMU turned faulty
        self.last_problem: Optional[str] = None
        self.last_check_ns: Optional[int] = None
        self._previous: Optional[tuple] = None
        self._repeats = [0, 0, 0]            # per axis: samples equal to the one before
        self._identical = 0                  # samples equal to the one before on all axes
        self._arrivals = deque(maxlen=limits.refused_window)   # refusal kind or '' per sample
        # (stamp, problem, detail) seen and not yet checked; a check takes those up to its
        # stamp only, so a replay's result does not depend on how far ahead samples came
        self._seen: List[Tuple[int, str, str]] = []
        self._heard = deque()                # stamps heard after the last check's
        self._newest: Optional[int] = None   # the newest stamp heard up to the last check
        self._stamp = 0                      # the sample's being looked at
        self._accepted = {}                  # stamp -> gyro (x, y, z) of the latest samples taken
        self._residuals = deque()            # (stamp, rotation error, step s) of camera fixes
        self.disagreement = 0.0              # rad/s: their mean over the window
        self.disagreement_limit = limits.gyro_disagreement   # rad/s: its limit there

    # ------------------------------------------------------------------ per sample
    def sample(self, stamp_ns: int, frame_id: str, gyro, refused: Optional[str] = None):
        """One sample as it came (gyro in its own frame, rad/s) and why the fusion refused
        it, None when taken."""
        self.received += 1
        stamp_ns = int(stamp_ns)
        self.last_heard_ns = stamp_ns if self.last_heard_ns is None else max(self.last_heard_ns, stamp_ns)
        self._heard.append(stamp_ns)
        self._stamp = stamp_ns
        lim = self.limits
        if frame_id != self.frame_id:
            self._refuse(f'sample in frame {frame_id!r}, the rig\'s IMU is {self.frame_id!r}', 'wrong_frame')
            self._see('wrong_frame', f'{self._count("wrong_frame")} of the last {len(self._arrivals)} '
                                     f'samples in frame {frame_id!r}, the rig\'s IMU is {self.frame_id!r}')
            return
        # (plain floats: 200 samples a second, where 3-element numpy operations cost 4x)
        g = plain_floats(gyro)
        if refused is not None:
            if self._accepted.get(stamp_ns) == g:
                # a sample taken already, delivered again (a graph's hand-over of the
                # arbiter between workers): not the IMU's fault
                self._refuse(refused, '')
                return
            kind = 'not_finite' if 'not finite' in refused else 'out_of_order'
            self._refuse(refused, kind)
            n = self._count(kind)
            if n > lim.refused_fraction * lim.refused_window:
                self._see(kind, f'{n} of the last {len(self._arrivals)} samples refused ({refused})')
            return
        self._arrivals.append('')
        self._accepted[stamp_ns] = g
        if len(self._accepted) > 2 * lim.refused_window:
            del self._accepted[next(iter(self._accepted))]
        if self._previous is not None:
            self._repeats = [r + 1 if a == b else 0 for a, b, r in zip(g, self._previous, self._repeats)]
            self._identical = self._identical + 1 if g == self._previous else 0
        self._previous = g
        if self._identical + 1 >= lim.stuck_samples:
            self._see('stuck', f'{self._identical + 1} identical samples')
            return
        at_limit = [abs(v) >= lim.gyro_saturation for v in g]
        if not any(at_limit) and max(self._repeats) + 1 < lim.saturation_repeats:
            return
        # one axis held while another moved within its run: clipped, not stuck
        low = min(self._repeats)
        clipped = [r + 1 >= lim.saturation_repeats and v != 0.0 and low < r
                   for r, v in zip(self._repeats, g)]
        if any(at_limit) or any(clipped):
            i = next(k for k in range(3) if at_limit[k] or clipped[k])
            self._see('saturated', f'gyro {AXES[i]} at {g[i]:+.3f} rad/s'
                                   + (f' (limit {lim.gyro_saturation:g})' if at_limit[i] else
                                      f' for {self._repeats[i] + 1} samples'))

    def _count(self, kind: str) -> int:
        return sum(1 for k in self._arrivals if k == kind)

    def _refuse(self, reason: str, kind: str):
        self.refused += 1
        self.reason = reason
        self._arrivals.append(kind)

    def _see(self, problem: str, detail: str):
        if self._seen and self._seen[-1][1] == problem and self._seen[-1][0] <= self._stamp:
            self._seen[-1] = (self._seen[-1][0], problem, detail)   # the same run, its latest detail
        else:
            self._seen.append((self._stamp, problem, detail))

    # ------------------------------------------------------------------ per frame step
    def camera_residual(self, stamp_ns: int, rotation_error, step_s: float, turned_rad: float):
        """A camera fix's rotation against the filter's prediction with the gyro (rad,
        base_link), the step since the frame before (s) and the body's rotation over it (rad)."""
        if step_s > 0 and np.all(np.isfinite(rotation_error)) and np.isfinite(turned_rad):
            self._residuals.append((int(stamp_ns), np.asarray(rotation_error, float), float(step_s),
                                    abs(float(turned_rad))))

    def check(self, stamp_ns: int, gyro_bias: Optional[np.ndarray] = None) -> bool:
        """At a frame's stamp (its samples up to it in): whether the gyro may be used.
        gyro_bias: the filter's bias estimate (rad/s), while the gyro is used."""
        stamp_ns = int(stamp_ns)
        if self.first_check_ns is None:
            self.first_check_ns = stamp_ns
        self.last_check_ns = stamp_ns
        lim = self.limits
        due = [e for e in self._seen if e[0] <= stamp_ns]
        self._seen = [e for e in self._seen if e[0] > stamp_ns]
        seen = None
        if due:
            # the first problem since the last check names it, with its latest detail
            seen = (due[0][1], [d for _, p, d in due if p == due[0][1]][-1])
        # the newest sample up to this stamp (those after it wait for their frame)
        self._newest = max((h for h in self._heard if h <= stamp_ns), default=self._newest)
        self._heard = deque(h for h in self._heard if h > stamp_ns)
        if seen is None:
            window_ns = int(lim.silent_s * 1e9)
            if self._newest is None:
                if stamp_ns - self.first_check_ns > window_ns:
                    seen = ('silent', 'no sample since the start')
            elif stamp_ns - self._newest > window_ns:
                seen = ('silent', f'no sample for {(stamp_ns - self._newest) * 1e-9:.2f} s')
        if seen is None and gyro_bias is not None:
            b = float(np.linalg.norm(gyro_bias))
            if b > lim.gyro_bias_max:
                seen = ('bias_drift', f'gyro bias estimate {b:.3f} rad/s (limit {lim.gyro_bias_max:g})')
        window_ns = int(lim.disagreement_window_s * 1e9)
        while self._residuals and self._residuals[0][0] <= stamp_ns - window_ns:
            self._residuals.popleft()
        span = sum(r[2] for r in self._residuals)
        full = span >= 0.5 * lim.disagreement_window_s
        self.disagreement = float(np.linalg.norm(sum(r[1] for r in self._residuals))) / span if full else 0.0
        self.disagreement_limit = lim.gyro_disagreement + (
            lim.disagreement_per_rotation * sum(r[3] for r in self._residuals) / span if full else 0.0)
        if seen is None and self.disagreement > self.disagreement_limit:
            seen = ('bias_drift', f'the cameras turn {self.disagreement:.3f} rad/s away from the gyro '
                                  f'(limit {self.disagreement_limit:.3f})')
        if seen is None and self.problem == 'bias_drift':
            seen = (self.problem, self.detail)     # held: with the gyro out, nothing tells it again
        if seen is not None and seen[0] != 'bias_drift':
            self._residuals.clear()
        if seen is not None:
            if self.problem is None:
                self.faults += 1
            self.problem, self.detail = seen
            self.last_problem = seen[0]
            self.last_fault_ns = stamp_ns
        else:
            self.problem = None
        return self.usable(stamp_ns)

    def usable(self, stamp_ns: int) -> bool:
        return (self._newest is not None and self.problem is None
                and (self.last_fault_ns is None
                     or (int(stamp_ns) - self.last_fault_ns) * 1e-9 >= self.limits.recover_s))

    @property
    def silent(self) -> bool:
        """Said silent at the last check: a frame need not wait for its samples."""
        return self.problem == 'silent'

    # ------------------------------------------------------------------ what is said
    @property
    def state(self) -> str:
        """At the last check: 'ok', 'fault' (a problem now: the gyro is out), 'recovering'
        (none for less than recover_s: still out) or 'waiting' (no sample yet)."""
        if self.problem is not None:
            return 'fault'
        if self._newest is None:
            return 'waiting'
        if self.last_check_ns is not None and not self.usable(self.last_check_ns):
            return 'recovering'
        return 'ok'

    def status(self):
        """(level 'ok' | 'warn' | 'error', message, key/values) as of the last check."""
        state = self.state
        if state == 'fault':
            level, message = 'error', f'imu: {self.problem}: {self.detail}; gyro not used (cameras only)'
        elif state == 'waiting':
            level, message = 'warn', 'imu: waiting for the first sample'
        elif state == 'recovering':
            level = 'warn'
            message = (f'imu: recovering from {self.last_problem}: gyro not used until '
                       f'{self.limits.recover_s:g} s without a problem')
        else:
            level, message = 'ok', 'imu: ok'
        values = {'imu_state': state, 'imu_problem': self.problem or '',
                  'imu_last_problem': self.last_problem or '', 'imu_gyro_used': state == 'ok',
                  'imu_samples': self.received, 'imu_refused': self.refused,
                  'imu_refused_reason': self.reason or '', 'imu_faults': self.faults,
                  'imu_disagreement': round(self.disagreement, 4),
                  'imu_disagreement_limit': round(self.disagreement_limit, 4)}
        return level, message, values
