"""Rigid transforms as 4x4 numpy arrays, and the pose-error convention used everywhere.

Convention (matches ROS PoseWithCovariance, 6x6 order x, y, z, rot x, rot y, rot z):
a pose T = (R, p) of base_link in odom is perturbed as p = p_hat + dp and
R = exp([dtheta]_x) R_hat, with dp and dtheta expressed in the odom frame.
"""
import math

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R=None, p=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if p is not None:
        T[:3, 3] = p
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    R, p = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ p)


def rotvec_to_R(v) -> np.ndarray:
    """SO(3) exponential. A single vector goes through scipy's own formulas (rotvec ->
    quaternion -> matrix, same operations in the same order, hence the same bits), written
    out: the EKFs call this ~100 times a frame and scipy's per-call overhead was 80 % of it."""
    v = np.asarray(v, dtype=float)
    if v.shape != (3,):
        return Rotation.from_rotvec(v).as_matrix()
    x, y, z = v.tolist()
    angle = math.sqrt(x * x + y * y + z * z)
    if not math.isfinite(angle):
        return Rotation.from_rotvec(v).as_matrix()      # NaN out, as scipy (math.sin raises)
    if angle <= 1e-3:                           # scipy's series below 1e-3 rad
        a2 = angle * angle
        s = 0.5 - a2 / 48 + a2 * a2 / 3840
    else:
        s = math.sin(angle / 2) / angle
    qx, qy, qz, qw = s * x, s * y, s * z, math.cos(angle / 2)
    x2, y2, z2, w2 = qx * qx, qy * qy, qz * qz, qw * qw
    xy, zw, xz, yw, yz, xw = qx * qy, qz * qw, qx * qz, qy * qw, qy * qz, qx * qw
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])


def R_to_rotvec(R) -> np.ndarray:
    """SO(3) logarithm in closed form: scipy's from_matrix (which re-orthonormalises) cost
    0.2 ms a call, 90 % of the camera arbiter's time. Near pi the closed form loses
    precision, so scipy takes those."""
    R = np.asarray(R, dtype=float)
    vee = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = float(np.linalg.norm(vee))
    cos = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    angle = np.arctan2(sin, cos)                # precise at every angle, unlike arccos
    if angle < 1e-8:
        return vee                              # sin(angle) ~ angle
    if angle > np.pi - 1e-3:
        return Rotation.from_matrix(R).as_rotvec()
    return vee * (angle / sin)


def quat_xyzw_to_R(q) -> np.ndarray:
    return Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()


def R_to_quat_xyzw(R) -> np.ndarray:
    return Rotation.from_matrix(R).as_quat()


def skew(v) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_left_jacobian(phi) -> np.ndarray:
    """J(phi) = sum_n [phi]x^n / (n+1)!: for a constant body rate w over dt (phi = w dt), the
    displacement of a constant body velocity v is R J(phi) v dt (the arc, not the chord along
    the start heading)."""
    phi = np.asarray(phi, dtype=float)
    th = float(np.linalg.norm(phi))
    K = skew(phi)
    if th < 1e-4:                                # series: the closed form cancels badly
        return np.eye(3) + K / 2.0 + K @ K / 6.0
    return np.eye(3) + (1.0 - np.cos(th)) / th ** 2 * K + (th - np.sin(th)) / th ** 3 * K @ K


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """6-vector [dp, dtheta] with T_a = perturb(T_b, [dp, dtheta]) (odom-frame convention)."""
    dp = T_a[:3, 3] - T_b[:3, 3]
    dth = R_to_rotvec(T_a[:3, :3] @ T_b[:3, :3].T)
    return np.concatenate([dp, dth])


def perturb(T: np.ndarray, delta) -> np.ndarray:
    """Apply a 6-vector [dp, dtheta] to T in the odom-frame convention."""
    delta = np.asarray(delta, dtype=float)
    return make_T(rotvec_to_R(delta[3:]) @ T[:3, :3], T[:3, 3] + delta[:3])


def yaw_of(R: np.ndarray) -> float:
    return float(np.arctan2(R[1, 0], R[0, 0]))


def is_valid_covariance(C: np.ndarray, min_eig: float = 1e-12) -> bool:
    """Finite, symmetric and positive definite: what may be published."""
    if not np.all(np.isfinite(C)):
        return False
    if np.abs(C - C.T).max() > 1e-9 * max(1.0, np.abs(C).max()):
        return False
    return bool(np.linalg.eigvalsh(0.5 * (C + C.T)).min() > min_eig)
