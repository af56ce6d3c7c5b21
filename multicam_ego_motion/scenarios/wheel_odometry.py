"""Simulated wheel odometry: true body speed and yaw rate corrupted the way wheels slip
(a constant scale error, a few percent of per-sample multiplicative noise, a yaw-rate bias),
then dead-reckoned, so its pose drifts away from ground truth."""
import numpy as np


class WheelOdometry:
    SPEED_NOISE = 0.03       # relative, per sample
    YAW_RATE_NOISE = 0.03    # relative, per sample

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.speed_scale = 1.0 + rng.uniform(0.01, 0.03) * rng.choice([-1.0, 1.0])
        self.yaw_rate_bias = rng.uniform(0.004, 0.008) * rng.choice([-1.0, 1.0])   # rad/s

    def measure(self, speed: np.ndarray, yaw_rate: np.ndarray):
        n = len(speed)
        v = speed * self.speed_scale * (1.0 + self.SPEED_NOISE * self.rng.standard_normal(n))
        w = yaw_rate * (1.0 + self.YAW_RATE_NOISE * self.rng.standard_normal(n)) + self.yaw_rate_bias
        return v, w

    @staticmethod
    def dead_reckon(times: np.ndarray, v: np.ndarray, w: np.ndarray):
        """(x, y, yaw) in odom from the start, midpoint integration between samples."""
        dt = np.diff(times)
        v_mid, w_mid = 0.5 * (v[1:] + v[:-1]), 0.5 * (w[1:] + w[:-1])
        yaw = np.concatenate([[0.0], np.cumsum(w_mid * dt)])
        heading = yaw[:-1] + 0.5 * w_mid * dt
        x = np.concatenate([[0.0], np.cumsum(v_mid * dt * np.cos(heading))])
        y = np.concatenate([[0.0], np.cumsum(v_mid * dt * np.sin(heading))])
        return x, y, yaw

    def variances(self, t: float, x: float, y: float, v: float, w: float):
        """(pose, twist) diagonal variances a wheel driver would publish with a reading: the
        pose's grow with the distance and time dead-reckoned, the twist's are the noise model's
        (relative noise, a floor, and the yaw-rate bias it cannot know the sign of)."""
        drift = 0.02 * (abs(x) + abs(y)) + 1e-4
        pose = (drift ** 2, drift ** 2, 1e-6, 1e-6, 1e-6, (0.01 + 0.01 * t) ** 2)
        twist = (max(abs(v) * self.SPEED_NOISE, 0.01) ** 2, 1e-4, 1e-6, 1e-6, 1e-6,
                 (max(abs(w) * self.YAW_RATE_NOISE, 0.005) + abs(self.yaw_rate_bias)) ** 2)
        return pose, twist
