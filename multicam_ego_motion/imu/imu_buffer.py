"""An IMU's samples between the general arbiter's frames (ROS-free): the gyro's mean rate
over a frame step in base_link, with its covariance, for BodyEKF.update_gyro; and the
accelerometer's mean specific force over the step at base_link's origin, for
BodyEKF.update_gravity.

Samples come in the IMU's own frame (REP-145: the message's frame_id); the mount, base_link
-> IMU frame from /tf_static or the rig file, turns them into base_link. The step's rotation
is the product of the samples' rotations, each held over the time to the next sample and
clipped to the step; its mean rate, log(dR) / dt, is what the body's w + b_g was on average.
Its covariance is the white noise's: a sample's variance (the message's covariance, else
`gyro_variance`) over the samples averaged. The bias is the filter's business.

A sample that is not finite or not after the newest one is refused with the reason; a step
the samples do not cover (a gap longer than `max_gap_s`) has no rate. An accelerometer reading
that is missing (REP-145: -1 in its covariance) or not finite leaves the gyro's sample in use
and the step without a specific force.

The specific force is moved from the IMU's place (`translation`, in base_link) to base_link's
origin: an IMU 0.28 m off the origin feels 1 m/s^2 of centripetal acceleration in a 1.9 rad/s
spin, a 6 deg tilt of the gravity it reads. The step's mean of w x (w x r) is taken sample by
sample, and of dw/dt x r from the rates at the step's two ends (the mean of a derivative).
"""
import math
from bisect import bisect_right
from typing import Dict, List, Optional, Tuple

import numpy as np

from multicam_ego_motion.geometry import se3

MEANS_KEPT = 4                 # mean_rate's results remembered (the latest steps)


def plain_floats(values) -> tuple:
    """A sample's numbers (a sequence, or an array of any shape) as a flat tuple of floats:
    200 samples a second, where a numpy call per 3 or 9 numbers costs more than reading them."""
    if type(values) is tuple and all(type(v) is float for v in values):
        return values
    if isinstance(values, np.ndarray):
        return tuple(values.astype(float, copy=False).ravel().tolist())
    return tuple(map(float, values))


class ImuBuffer:
    def __init__(self, R_base_imu: np.ndarray, gyro_variance: float = 1e-5,
                 max_gap_s: float = 0.05, keep_s: float = 5.0, translation=(0.0, 0.0, 0.0),
                 accel_variance: float = 1e-3):
        R = np.asarray(R_base_imu, float)
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise ValueError('IMU mount: not a rotation')
        self.R = R
        self.gyro_variance = float(gyro_variance)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.keep_ns = int(keep_s * 1e9)
        self.stamps: List[int] = []
        self.rates: List[tuple] = []               # rad/s in the IMU's frame
        self.variances: List[float] = []           # per axis, of one sample
        self.r = np.asarray(translation, float).reshape(3)
        self.accel_variance = float(accel_variance)
        self.accels: List[Optional[tuple]] = []    # m/s^2 in the IMU's frame; None: no reading
        self.accel_variances: List[float] = []
        self._means: Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray]] = {}   # mean_rate's latest

    def add(self, stamp_ns: int, gyro, gyro_covariance=None, accel=None,
            accel_covariance=None) -> Optional[str]:
        """One sample (gyro in the IMU's frame, rad/s; its 3x3 covariance or None; the
        accelerometer's specific force, m/s^2, and its covariance, or None). Returns why it
        was refused, None when taken."""
        # (plain floats, turned into base_link when a step is integrated: 200 samples a
        # second, where small numpy operations per sample cost more than the integration)
        g = plain_floats(gyro)
        if len(g) != 3:
            raise ValueError(f'gyro sample: 3 values expected, got {len(g)}')
        isfinite = math.isfinite
        if not (isfinite(g[0]) and isfinite(g[1]) and isfinite(g[2])):
            return f'gyro sample at {stamp_ns / 1e9:.6f} s is not finite'
        stamps = self.stamps
        if stamps and stamp_ns <= stamps[-1]:
            return (f'gyro sample at {stamp_ns / 1e9:.6f} s is not after the newest '
                    f'({stamps[-1] / 1e9:.6f} s): out of order or repeated')
        var = self.gyro_variance
        if gyro_covariance is not None:
            c = plain_floats(gyro_covariance)
            # REP-145: all zeros is "unknown", -1 in the first element "not measured"
            if len(c) == 9 and c[0] > 0 and all(map(isfinite, c)):
                var = max(c[0], c[4], c[8])
        a, a_var = None, self.accel_variance
        if accel is not None:
            a = plain_floats(accel)
            if len(a) != 3 or not (isfinite(a[0]) and isfinite(a[1]) and isfinite(a[2])):
                a = None
            if accel_covariance is not None:
                c = plain_floats(accel_covariance)
                if len(c) == 9 and c[0] == -1.0:
                    a = None                     # REP-145: not measured
                elif len(c) == 9 and c[0] > 0 and all(map(isfinite, c)):
                    a_var = max(c[0], c[4], c[8])
        stamp_ns = int(stamp_ns)
        stamps.append(stamp_ns)
        self.rates.append(g)
        self.variances.append(var)
        self.accels.append(a)
        self.accel_variances.append(a_var)
        if stamps[0] <= stamp_ns - self.keep_ns:
            cut = bisect_right(stamps, stamp_ns - self.keep_ns)
            del (stamps[:cut], self.rates[:cut], self.variances[:cut], self.accels[:cut],
                 self.accel_variances[:cut])
        return None

    def settled(self, stamp_ns: int) -> bool:
        """A sample at or after the stamp is in: a step ending there is covered."""
        return bool(self.stamps) and self.stamps[-1] >= stamp_ns

    def mean_rate(self, t0_ns: int, t1_ns: int) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(mean rate in base_link over [t0, t1], its 3x3 covariance), or None when the
        samples do not cover the step."""
        if t1_ns <= t0_ns or not self.stamps:
            return None
        key = (int(t0_ns), int(t1_ns))
        if key in self._means:
            return self._means[key]
        i = bisect_right(self.stamps, t0_ns) - 1      # the sample in force at t0
        if i < 0 or self.stamps[-1] < t1_ns:
            return None
        # The samples' rotations composed as unit quaternions in plain floats (a 3x3 numpy
        # product and exponential per sample cost 10 us, 25 samples a step, 3 steps a frame)
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self.R.tolist()
        stamps, rates, variances = self.stamps, self.rates, self.variances
        qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        used, var = 0, 0.0
        t = t0_ns
        last = len(stamps) - 1
        while t < t1_ns:
            nxt = stamps[i + 1] if i < last else t1_ns
            if nxt - stamps[i] > self.max_gap_ns:
                return None
            end = min(nxt, t1_ns)
            h = (end - t) * 1e-9
            gx, gy, gz = rates[i]
            x = (r00 * gx + r01 * gy + r02 * gz) * h
            y = (r10 * gx + r11 * gy + r12 * gz) * h
            z = (r20 * gx + r21 * gy + r22 * gz) * h
            angle = math.sqrt(x * x + y * y + z * z)
            if angle <= 1e-3:                    # sin(a/2)/a by its series (as se3)
                a2 = angle * angle
                k = 0.5 - a2 / 48 + a2 * a2 / 3840
            else:
                k = math.sin(angle / 2) / angle
            bw, bx, by, bz = math.cos(angle / 2), k * x, k * y, k * z
            # q <- q * b: the step's rotation is the product in time order, the first on the left
            qw, qx, qy, qz = (qw * bw - qx * bx - qy * by - qz * bz,
                              qw * bx + qx * bw + qy * bz - qz * by,
                              qw * by - qx * bz + qy * bw + qz * bx,
                              qw * bz + qx * by - qy * bx + qz * bw)
            used += 1
            var += variances[i]
            t, i = end, i + 1
        dt = (t1_ns - t0_ns) * 1e-9
        if qw < 0.0:
            qw, qx, qy, qz = -qw, -qx, -qy, -qz
        vn = math.sqrt(qx * qx + qy * qy + qz * qz)
        angle = 2.0 * math.atan2(vn, qw)
        k = angle / vn if vn > 1e-12 else 2.0 / math.hypot(qw, vn)   # (small: 2 / |q|)
        rate = np.array([k * qx / dt, k * qy / dt, k * qz / dt])
        # the mean of `used` samples' white noise
        out = rate, np.eye(3) * (var / used) / used
        # (a step covered stays as it is: samples come in order. The fusion asks for each
        # step twice: its prediction, and a frame later the gyro bias from the tracks)
        self._means[key] = out
        while len(self._means) > MEANS_KEPT:
            del self._means[next(iter(self._means))]
        return out

    def mean_specific_force(self, t0_ns: int, t1_ns: int) -> Optional[Tuple[np.ndarray, float]]:
        """(the mean specific force over (t0, t1] at base_link's origin, in base_link (m/s^2),
        the variance per axis of that mean's white noise), or None when the samples do not
        cover the step or one of them has no accelerometer reading."""
        if t1_ns <= t0_ns or not self.stamps or self.stamps[-1] < t1_ns:
            return None
        i0 = bisect_right(self.stamps, t0_ns)
        i1 = bisect_right(self.stamps, t1_ns)
        if i0 == 0 or i1 - i0 < 2:
            return None
        acc = self.accels[i0:i1]
        if any(a is None for a in acc):
            return None
        stamps = self.stamps[i0 - 1:i1]
        if max(b - a for a, b in zip(stamps, stamps[1:])) > self.max_gap_ns:
            return None
        f = np.asarray(acc) @ self.R.T                        # (n, 3) in base_link
        w = np.asarray(self.rates[i0:i1]) @ self.R.T
        r = self.r
        # at the origin: f_origin = f_imu - dw/dt x r - w x (w x r)
        centripetal = np.cross(w, np.cross(w, r)).mean(axis=0)
        dt = (self.stamps[i1 - 1] - self.stamps[i0]) * 1e-9
        angular = np.cross((w[-1] - w[0]) / dt, r) if dt > 0 else np.zeros(3)
        n = len(acc)
        return f.mean(axis=0) - centripetal - angular, float(np.mean(self.accel_variances[i0:i1])) / n
