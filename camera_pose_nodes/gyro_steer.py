"""The rig's gyro between a quarter's frames (ROS-free): where the camera turned since its
last frame, for the feature search's start (flow_prediction) and the filter's prediction.

A quarter's own motion prior is its last angular rate held constant: a spin starting at
several rad/s^2 turns the camera 10 to 15 deg a frame at 8 Hz, the prediction lags by
degrees, Lucas-Kanade loses every track and the cameras give no fix for seconds. The gyro
measured the turn itself. Its bias and whether it may be used at all are the general
arbiter's (its body EKF estimates the bias, imu_health judges the samples): the arbiter
says both after each frame (`set_bias`), and without a finite bias the gyro is not used
here either, so a bad IMU steers at most the frame or two before the arbiter says it.

One per process and IMU topic may serve every quarter: each sample is taken once (the
quarters check `is_new` on the sample's stamp before reading the rest of its bytes, so a
process reads each sample once).
"""
from collections import deque
from typing import Deque, Dict, Optional, Tuple

import numpy as np

from multicam_ego_motion.imu.imu_buffer import ImuBuffer

KEEP_S = 2.0          # samples kept: a frame step and the wait for the arbiter's word
WORDS_KEPT = 8        # the arbiter's newest words (a frame or two back is the one used)
RATES_KEPT = 8        # steps remembered (cameras at their own stamps ask for several)


class GyroSteer:
    def __init__(self, frame_id: str, R_base_imu: np.ndarray, max_gap_s: float = 0.05):
        self.frame_id = frame_id
        self.buffer = ImuBuffer(R_base_imu, max_gap_s=max_gap_s, keep_s=KEEP_S)
        # the arbiter's words, (frame stamp, bias in base_link (rad/s) or None: do not use)
        self.words: Deque[Tuple[int, Optional[np.ndarray]]] = deque(maxlen=WORDS_KEPT)
        # rate()'s latest results: every quarter of a rig asks for the same steps
        self._rates: Dict[Tuple[int, int], np.ndarray] = {}

    @classmethod
    def for_rig(cls, rig) -> Optional['GyroSteer']:
        """For the rig's IMU, or None when the rig has none."""
        imu = getattr(rig, 'imu', None)
        return None if imu is None else cls(imu.frame_id, imu.rotation)

    def add(self, stamp_ns: int, frame_id: Optional[str], gyro) -> Optional[str]:
        """One sample (rad/s in its frame); why it was not taken, None when taken. The
        arbiter says the IMU's faults; here a sample is only kept or not. frame_id None:
        the rig's IMU frame."""
        if frame_id is not None and frame_id != self.frame_id:
            return f'sample in frame {frame_id!r}, the rig\'s IMU is {self.frame_id!r}'
        return self.buffer.add(int(stamp_ns), gyro)

    def is_new(self, stamp_ns: int) -> bool:
        """A sample at stamp_ns would be taken as to its time: after the newest kept (the
        quarters that share this steer skip, before reading it, a sample one of them gave)."""
        stamps = self.buffer.stamps
        return not stamps or stamp_ns > stamps[-1]

    def set_bias(self, stamp_ns: int, bias):
        """The arbiter's word after its frame `stamp_ns`: the gyro's bias (base_link, rad/s),
        or None (or not finite): the gyro is out. A word older than the newest is ignored."""
        stamp_ns = int(stamp_ns)
        if self.words and stamp_ns < self.words[-1][0]:
            return
        b = None if bias is None else np.asarray(bias, float).reshape(3)
        word = (stamp_ns, b if b is not None and np.all(np.isfinite(b)) else None)
        if self.words and self.words[-1][0] == stamp_ns:
            self.words[-1] = word
            self._rates.clear()           # (a step may have used the word replaced)
        else:
            self.words.append(word)

    @property
    def in_use(self) -> bool:
        """The newest word lets the gyro be used."""
        return bool(self.words) and self.words[-1][1] is not None

    def settled(self, stamp_ns: int) -> bool:
        """Nothing to wait for at `stamp_ns`: its samples are in, or the gyro is out."""
        return not self.in_use or self.buffer.settled(int(stamp_ns))

    def rate(self, t0_ns: int, t1_ns: int) -> Optional[np.ndarray]:
        """The body's mean angular rate over [t0, t1] (base_link, rad/s), less the bias of
        the arbiter's newest word from before t0; None when that word says the gyro is out,
        there is none, or the samples do not cover the step.

        Why a word from before t0, the quarter's last frame: the arbiter says its word with
        the fused pose of a frame, and a quarter computes the next frame's flow ahead, while
        that fused pose may or may not have come (prefetch). The words before its last frame
        were all there when it processed that frame, so the flow is the same either way, and
        the same as the sequential pipeline's."""
        key = (int(t0_ns), int(t1_ns))
        if key in self._rates:
            return self._rates[key]
        bias = next((b for s, b in reversed(self.words) if s < key[0]), None)
        if bias is None:
            return None
        m = self.buffer.mean_rate(*key)
        if m is None:
            return None
        rate = m[0] - bias
        rate.flags.writeable = False      # shared by the quarters that asked
        self._rates[key] = rate
        while len(self._rates) > RATES_KEPT:
            del self._rates[next(iter(self._rates))]
        return rate
