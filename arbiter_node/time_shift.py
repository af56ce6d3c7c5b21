"""Move a pose estimate in time with the body EKF's motion model, ROS-free.

Free-running cameras capture a few milliseconds apart, so one frame's camera estimates are
poses of the body at different instants. Fused as they are, a camera 24 ms early at 2.5 m/s
would pull the fused pose 6 cm back. Each is moved to the group's common time first, along
the arc of a constant body twist (body_ekf's process model), and the fused pose is moved back
to each camera's own instant for the quarters' triangulation.

Covariance (se3 convention of multicam_ego_motion.geometry.se3: position and rotation errors
in odom): the pose error is carried through the step (a rotation error swings the step's
translation), the twist's own uncertainty adds R dt Sigma_twist dt R^T, and the white
accelerations of the EKF's process noise add their q |dt|^3 / 3.
"""
import numpy as np

from multicam_ego_motion.geometry import se3


def shift_pose(T: np.ndarray, cov: np.ndarray, dt: float, twist: np.ndarray,
               twist_cov: np.ndarray, accel_noise: float = 0.0,
               angular_accel_noise: float = 0.0):
    """(T, cov) of base_link in odom at t, -> (T', cov') at t + dt (dt may be negative) under
    the constant body twist (vx, vy, vz, wx, wy, wz) with 6x6 covariance twist_cov.
    dt == 0 returns the inputs unchanged (the same objects)."""
    if dt == 0.0:
        return T, cov
    v, w = np.asarray(twist[:3], float), np.asarray(twist[3:], float)
    R = T[:3, :3]
    phi = w * dt
    RJ = R @ se3.so3_left_jacobian(phi)
    step = RJ @ v * dt
    T_new = se3.make_T(R @ se3.rotvec_to_R(phi), T[:3, 3] + step)
    F = np.eye(6)
    F[0:3, 3:6] = -se3.skew(step)
    G = np.zeros((6, 6))
    G[0:3, 0:3] = RJ * dt
    G[3:6, 3:6] = R * dt
    a = abs(dt) ** 3 / 3.0
    Q = np.diag([accel_noise * a] * 3 + [angular_accel_noise * a] * 3)
    cov_new = F @ cov @ F.T + G @ np.asarray(twist_cov, float) @ G.T + Q
    return T_new, 0.5 * (cov_new + cov_new.T)
