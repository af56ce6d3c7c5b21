"""Smooth planar robot trajectories, one per scenario, in the world frame of the scene.

A trajectory is sampled densely (1 kHz) from a unicycle model driven by smooth speed and
yaw-rate profiles, so position, yaw and their rates are mutually consistent; frame poses are
interpolated from the dense samples. The robot moves on the floor: z is fixed (base_link on
the floor), roll and pitch are zero.
"""
from dataclasses import dataclass

import numpy as np

DENSE_DT = 1e-3


@dataclass
class Trajectory:
    t: np.ndarray        # dense sample times (s), starting at 0
    x: np.ndarray        # world position (m)
    y: np.ndarray
    yaw: np.ndarray      # unwrapped heading (rad)
    speed: np.ndarray    # forward speed in base_link (m/s)
    yaw_rate: np.ndarray  # rad/s

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    @property
    def path_length(self) -> float:
        return float(np.sum(np.hypot(np.diff(self.x), np.diff(self.y))))

    def sample(self, times):
        """(x, y, yaw, speed, yaw_rate) at `times`, linearly interpolated."""
        times = np.asarray(times, dtype=float)
        return tuple(np.interp(times, self.t, a)
                     for a in (self.x, self.y, self.yaw, self.speed, self.yaw_rate))

    def start_pose(self):
        return float(self.x[0]), float(self.y[0]), float(self.yaw[0])


def smooth_step(u):
    """0 -> 1 with zero slope and curvature at both ends (quintic)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def ramped_profile(t, t0, t1, ramp):
    """1 inside [t0, t1], 0 outside, with smooth ramps of length `ramp` inside the interval."""
    return smooth_step((t - t0) / ramp) * smooth_step((t1 - t) / ramp)


def integrate_unicycle(t, speed, yaw_rate, x0, y0, yaw0) -> Trajectory:
    dt = np.diff(t)
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * dt)])
    vx, vy = speed * np.cos(yaw), speed * np.sin(yaw)
    x = x0 + np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * dt)])
    y = y0 + np.concatenate([[0.0], np.cumsum(0.5 * (vy[1:] + vy[:-1]) * dt)])
    return Trajectory(t, x, y, yaw, speed, yaw_rate)


def follow_path(t, distance, path_s, path_x, path_y, path_yaw, path_kappa) -> Trajectory:
    """Move along a path given by arc length samples; `distance(t)` is the travelled length."""
    speed = np.gradient(distance, t)
    kappa = np.interp(distance, path_s, path_kappa)
    return Trajectory(t, np.interp(distance, path_s, path_x), np.interp(distance, path_s, path_y),
                      np.interp(distance, path_s, path_yaw), speed, speed * kappa)


def rounded_rectangle_path(half_x=4.2, half_y=2.6, turn_length=3.2, ds=1e-3):
    """Closed counter-clockwise loop: four straights joined by 90-degree turns whose curvature
    rises and falls smoothly (no yaw-rate steps). Starts mid bottom straight heading +x.
    Returns arc-length samples (s, x, y, yaw, kappa)."""
    # Curvature bump kappa(s) = A sin^2(pi s / Lt) integrates to A Lt / 2 = pi / 2.
    amp = np.pi / turn_length
    # Lateral and longitudinal extent of one turn, measured numerically.
    st = np.arange(0.0, turn_length + ds / 2, ds)
    kt = amp * np.sin(np.pi * st / turn_length) ** 2
    yt = np.concatenate([[0.0], np.cumsum(0.5 * (kt[1:] + kt[:-1]) * ds)])
    along = np.trapezoid(np.cos(yt), st)   # advance along the initial heading
    side = np.trapezoid(np.sin(yt), st)    # advance to the left
    straight_x = 2 * half_x - along - side
    straight_y = 2 * half_y - along - side
    if straight_x <= 0 or straight_y <= 0:
        raise ValueError('loop too small for its turns')
    segments = [(straight_x / 2, 0.0)]
    for straight in (straight_y, straight_x, straight_y):
        segments += [(turn_length, amp), (straight, 0.0)]
    segments += [(turn_length, amp), (straight_x / 2, 0.0)]
    total = sum(length for length, _ in segments)
    s = np.arange(0.0, total + ds / 2, ds)
    kappa = np.zeros_like(s)
    start = 0.0
    for length, a in segments:
        inside = (s >= start) & (s < start + length)
        kappa[inside] = a * np.sin(np.pi * (s[inside] - start) / length) ** 2
        start += length
    yaw = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(yaw[1:]) + np.cos(yaw[:-1])) * ds)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(yaw[1:]) + np.sin(yaw[:-1])) * ds)])
    return s, x, y - half_y, yaw, kappa


def _dense_times(duration):
    return np.arange(0.0, duration + DENSE_DT / 2, DENSE_DT)


def _distance_profile(t, total, t_start, t_end, ramp):
    """Travelled distance: 0 before t_start, `total` after t_end, smooth speed ramps."""
    shape = ramped_profile(t, t_start, t_end, ramp)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (shape[1:] + shape[:-1]) * np.diff(t))])
    return dist * (total / dist[-1])


def loop(duration=30.0):
    """One full closed loop (about 24 m) around the middle of the room; ends at its start."""
    path = rounded_rectangle_path()
    t = _dense_times(duration)
    ramp = min(2.0, duration / 4)
    return follow_path(t, _distance_profile(t, path[0][-1], 0.0, duration, ramp), *path)


def corridor(duration=30.0):
    """A right turn of 90 degrees into the corridor axis, then a long straight along +x."""
    t = _dense_times(duration)
    cruise = 1.0
    speed = cruise * ramped_profile(t, 0.0, duration, min(1.5, duration / 4))
    turn_end = min(4.0, duration / 3)
    yaw_rate = -(np.pi / 2) * _bump(t, 0.3, turn_end)
    # Start so that the straight lies on the corridor axis y = 0, near its west end.
    probe = integrate_unicycle(t, speed, yaw_rate, 0.0, 0.0, np.pi / 2)
    i_end = np.searchsorted(t, turn_end)
    return integrate_unicycle(t, speed, yaw_rate, -15.0, -probe.y[i_end], np.pi / 2)


def spin_then_drive(duration=30.0):
    """Rotate in place one full turn (scale becomes observable), then drive the loop path."""
    t = _dense_times(duration)
    spin_end = min(8.0, duration / 3)
    yaw_rate = 2 * np.pi * _bump(t, 0.0, spin_end)
    yaw = np.concatenate([[0.0], np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * DENSE_DT)])
    path = rounded_rectangle_path()
    cruise = 0.8
    drive_time = duration - spin_end
    distance = min(path[0][-1], cruise * max(drive_time - 1.5, 0.0))
    dist = _distance_profile(t, distance, spin_end + 0.5, duration, min(1.5, drive_time / 4))
    drive = follow_path(t, dist, *path)
    spinning = t < spin_end + 0.5
    drive.yaw = np.where(spinning, yaw, drive.yaw + 2 * np.pi)
    drive.yaw_rate = np.where(spinning, yaw_rate, drive.yaw_rate)
    return drive


def lighting(duration=30.0):
    """The loop path; the photometric changes are applied by the renderer's post-processing."""
    return loop(duration)


def bare_wall(duration=30.0):
    """Drive east along the north wall (left cameras see: texture, a bare stretch, texture),
    then turn right away from the wall."""
    t = _dense_times(duration)
    speed = 0.5 * ramped_profile(t, 0.0, duration, min(1.5, duration / 4))
    turn_start = min(17.5, 0.6 * duration)
    yaw_rate = -(np.pi / 2) * _bump(t, turn_start, min(duration, turn_start + 5.0))
    return integrate_unicycle(t, speed, yaw_rate, -6.0, 3.6, 0.0)


def _bump(t, t0, t1):
    """Smooth pulse on [t0, t1] whose integral is 1 (sin^2 shape)."""
    length = t1 - t0
    inside = (t >= t0) & (t <= t1)
    return np.where(inside, (2.0 / length) * np.sin(np.pi * (t - t0) / length) ** 2, 0.0)


SCENARIOS = {
    'loop': loop,
    'corridor': corridor,
    'spin_then_drive': spin_then_drive,
    'lighting': lighting,
    'bare_wall': bare_wall,
}
