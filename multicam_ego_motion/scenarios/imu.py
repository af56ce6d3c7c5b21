"""A simulated IMU on a scenario's trajectory, as a robot's driver publishes it
(sensor_msgs/Imu on /imu/data, REP-145: angular velocity and specific force in the IMU's own
frame, no orientation).

The robot moves on a level floor (trajectories.py): its body rate is (0, 0, yaw rate) and
the acceleration of base_link's origin, in base_link, is (dv/dt, v * yaw rate, 0). An IMU
mounted at r with rotation R (base_link -> imu_link) feels, in its own frame,

    w_imu = R^T w
    f_imu = R^T (a + dw/dt x r + w x (w x r) + g_up)

(g_up: the floor's reaction to gravity, +9.81 m/s^2 along base_link's z), plus white noise,
a turn-on bias and a bias random walk per axis. The figures are those of a MEMS IMU of the
kind robots carry (a BMI088's noise densities are 2.4e-4 rad/s/sqrt(Hz) and 1.7e-3
m/s^2/sqrt(Hz)), its turn-on gyro bias a few tenths of a degree per second.
"""
from dataclasses import dataclass
from typing import Tuple

import numpy as np
from scipy.spatial.transform import Rotation

GRAVITY = 9.80665               # m/s^2
IMU_FRAME = 'imu_link'
# Where the generated IMU sits: off base_link's origin and turned (a board in the robot's
# body), so that a consumer that took the IMU frame for base_link would fail.
IMU_TRANSLATION = (0.12, -0.05, 0.25)                 # m, in base_link
IMU_ROTATION = Rotation.from_euler('xyz', (0.02, -0.03, np.pi / 2)).as_matrix()


@dataclass(frozen=True)
class ImuNoise:
    gyro_noise_density: float = 3e-4     # rad/s/sqrt(Hz): white noise
    accel_noise_density: float = 2e-3    # m/s^2/sqrt(Hz)
    gyro_bias_std: float = 0.005         # rad/s: turn-on bias per axis (0.3 deg/s)
    accel_bias_std: float = 0.05         # m/s^2
    gyro_bias_walk: float = 2e-5         # rad/s^2/sqrt(Hz): bias random walk
    accel_bias_walk: float = 3e-4        # m/s^3/sqrt(Hz)

    def sample_variances(self, rate_hz: float) -> Tuple[float, float]:
        """(gyro, accel) white-noise variance of one sample at rate_hz, as the message's
        covariance diagonals say it."""
        return self.gyro_noise_density ** 2 * rate_hz, self.accel_noise_density ** 2 * rate_hz


NOISELESS = ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass
class ImuSamples:
    times: np.ndarray         # (N,) s from the trajectory's start
    gyro: np.ndarray          # (N, 3) rad/s, imu_link
    accel: np.ndarray         # (N, 3) m/s^2 specific force, imu_link
    gyro_bias: np.ndarray     # (N, 3) the true biases (for tests and diagnosis)
    accel_bias: np.ndarray


def true_motion(trajectory, times):
    """(w, dw/dt, a) of base_link at `times` in base_link: (N, 3) each."""
    t = trajectory.t
    dv = np.interp(times, t, np.gradient(trajectory.speed, t))
    dw = np.interp(times, t, np.gradient(trajectory.yaw_rate, t))
    v = np.interp(times, t, trajectory.speed)
    w = np.interp(times, t, trajectory.yaw_rate)
    zero = np.zeros_like(times)
    return (np.column_stack([zero, zero, w]), np.column_stack([zero, zero, dw]),
            np.column_stack([dv, v * w, zero]))


def simulate_imu(trajectory, rate_hz: float, rng: np.random.Generator, noise: ImuNoise = ImuNoise(),
                 translation=IMU_TRANSLATION, rotation=IMU_ROTATION) -> ImuSamples:
    """IMU samples every 1 / rate_hz over the trajectory (both ends included)."""
    if not rate_hz > 0:
        raise ValueError(f'IMU rate must be > 0 Hz, got {rate_hz}')
    n = int(np.floor(trajectory.duration * rate_hz + 1e-9)) + 1
    times = np.arange(n) / rate_hz
    w, dw, a = true_motion(trajectory, times)
    r = np.broadcast_to(np.asarray(translation, float), w.shape)
    f = a + np.cross(dw, r) + np.cross(w, np.cross(w, r)) + np.array([0.0, 0.0, GRAVITY])
    R = np.asarray(rotation, float)
    dt = 1.0 / rate_hz

    def bias(std, walk):
        start = rng.standard_normal(3) * std
        steps = rng.standard_normal((n, 3)) * walk * np.sqrt(dt)
        steps[0] = 0.0
        return start + np.cumsum(steps, axis=0)

    gyro_bias = bias(noise.gyro_bias_std, noise.gyro_bias_walk)
    accel_bias = bias(noise.accel_bias_std, noise.accel_bias_walk)
    gyro_var, accel_var = noise.sample_variances(rate_hz)
    gyro = w @ R + gyro_bias + rng.standard_normal((n, 3)) * np.sqrt(gyro_var)
    accel = f @ R + accel_bias + rng.standard_normal((n, 3)) * np.sqrt(accel_var)
    return ImuSamples(times, gyro, accel, gyro_bias, accel_bias)


# --- a bad IMU (`ego-motion generate --imu-fault F --imu-fault-at S`) -------------------
IMU_FAULTS = ('wrong_frame', 'saturated', 'stuck', 'silent', 'out_of_order', 'bias_drift')
WRONG_FRAME = 'base_link'         # a driver that stamps its samples in the robot's frame
SATURATED_RANGE = 0.5             # rad/s: a gyro whose range was set below the robot's turns
BIAS_DRIFT_RATE = 0.02            # rad/s per second: a bias running away (a failing gyro)
OUT_OF_ORDER_JITTER = 1.5         # sample periods: each stamp moved by up to this either way


@dataclass
class PublishedImu:
    """What a driver publishes, sample by sample in publishing order."""
    log_times: np.ndarray     # (M,) s: when each is published (the bag's log time)
    stamps: np.ndarray        # (M,) s: its header stamp
    frame_ids: list           # (M,) its header frame_id
    gyro: np.ndarray          # (M, 3)
    accel: np.ndarray         # (M, 3)


def publish(samples: ImuSamples, fault: str = None, at_s: float = 0.0,
            rng: np.random.Generator = None) -> PublishedImu:
    """The samples as a driver publishes them, from `at_s` on with `fault` (one of
    IMU_FAULTS; None: a healthy IMU). rng: the fault's own stream (out_of_order)."""
    t = samples.times
    gyro, accel = samples.gyro.copy(), samples.accel.copy()
    stamps = t.copy()
    frames = [IMU_FRAME] * len(t)
    keep = np.ones(len(t), bool)
    bad = t >= at_s
    if fault is None:
        pass
    elif fault == 'wrong_frame':
        frames = [WRONG_FRAME if b else IMU_FRAME for b in bad]
    elif fault == 'saturated':
        gyro[bad] = np.clip(gyro[bad], -SATURATED_RANGE, SATURATED_RANGE)
    elif fault == 'stuck':
        k = int(np.argmax(bad)) if bad.any() else len(t)
        gyro[k:], accel[k:] = gyro[k], accel[k]
    elif fault == 'silent':
        keep = ~bad
    elif fault == 'out_of_order':
        jitter = rng.uniform(-OUT_OF_ORDER_JITTER, OUT_OF_ORDER_JITTER, len(t)) * np.median(np.diff(t))
        stamps = np.where(bad, t + jitter, t)
    elif fault == 'bias_drift':
        ramp = np.clip(t - at_s, 0.0, None) * BIAS_DRIFT_RATE / np.sqrt(3.0)
        gyro += ramp[:, None]
    else:
        raise ValueError(f'unknown IMU fault {fault!r} (one of: {", ".join(IMU_FAULTS)})')
    return PublishedImu(t[keep], stamps[keep], [f for f, k in zip(frames, keep) if k],
                        gyro[keep], accel[keep])
