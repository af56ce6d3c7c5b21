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


def _quat_to_R(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """scipy's Rotation.as_matrix of a unit quaternion, its operations in its order."""
    x2, y2, z2, w2 = qx * qx, qy * qy, qz * qz, qw * qw
    xy, zw, xz, yw, yz, xw = qx * qy, qz * qw, qx * qz, qy * qw, qy * qz, qx * qw
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])


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
    return _quat_to_R(s * x, s * y, s * z, math.cos(angle / 2))


def R_to_rotvec(R) -> np.ndarray:
    """SO(3) logarithm in closed form: scipy's from_matrix (which re-orthonormalises) cost
    0.2 ms a call, 90 % of the camera arbiter's time. Near pi the closed form loses
    precision, so scipy takes those. Plain floats: numpy's per-call overhead on 3-vectors
    was most of the rest (numpy's norm agrees with math's to the last bits; its BLAS kernel
    depends on the CPU)."""
    R = np.asarray(R, dtype=float)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    vx, vy, vz = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    sin = math.sqrt(vx * vx + vy * vy + vz * vz)
    cos = 0.5 * (r00 + r11 + r22 - 1.0)
    angle = math.atan2(sin, cos)                # precise at every angle, unlike acos
    if angle < 1e-8:
        return np.array([vx, vy, vz])           # sin(angle) ~ angle
    if angle > math.pi - 1e-3:
        return Rotation.from_matrix(R).as_rotvec()
    k = angle / sin
    return np.array([vx * k, vy * k, vz * k])


def quat_xyzw_to_R(q) -> np.ndarray:
    """Quaternion (x, y, z, w; normalised here) -> matrix. scipy's operations written out
    (from_quat normalises, then as_matrix), so the same bits without its ~20 us a call:
    every pose message received in the graph goes through this (~40 a frame)."""
    x, y, z, w = (float(c) for c in q)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(norm) and norm > 0.0):
        return Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()   # scipy's NaN / error
    return _quat_to_R(x / norm, y / norm, z / norm, w / norm)


# R_to_quat_xyzw runs Markley's formulas itself only for a matrix this close to orthonormal
# (every entry of R R^T within 1e-13 of I): scipy's from_matrix orthonormalises (SVD) only
# beyond 1e-12, so inside the margin both take the same path whatever the rounding.
_ORTHONORMAL_TOL = 1e-13


def R_to_quat_xyzw(R) -> np.ndarray:
    """Matrix -> quaternion (x, y, z, w), as scipy's from_matrix(R).as_quat(): for a proper
    rotation its own operations in its order (Markley's method, then normalisation), the
    same bits without its ~120 us a call (determinant, Gramian check): every pose message
    published goes through this. Anything else (not orthonormal, reflection, NaN) goes to
    scipy itself."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        return Rotation.from_matrix(R).as_quat()
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = R.tolist()
    rows = ((m00, m01, m02), (m10, m11, m12), (m20, m21, m22))
    for i in range(3):
        for j in range(i, 3):
            g = rows[i][0] * rows[j][0] + rows[i][1] * rows[j][1] + rows[i][2] * rows[j][2]
            if not abs(g - (1.0 if i == j else 0.0)) <= _ORTHONORMAL_TOL:    # NaN lands here too
                return Rotation.from_matrix(R).as_quat()
    det = (m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20)
           + m02 * (m10 * m21 - m11 * m20))
    if det < 0.5:                               # a reflection: scipy raises
        return Rotation.from_matrix(R).as_quat()
    trace = m00 + m11 + m22
    # scipy's choice: the first maximum of (m00, m11, m22, trace)
    choice, best = 0, m00
    for c, v in ((1, m11), (2, m22), (3, trace)):
        if v > best:
            choice, best = c, v
    q = [0.0, 0.0, 0.0, 0.0]
    if choice != 3:
        i = choice
        j = (i + 1) % 3
        k = (j + 1) % 3
        q[i] = 1 - trace + 2 * rows[i][i]
        q[j] = rows[j][i] + rows[i][j]
        q[k] = rows[k][i] + rows[i][k]
        q[3] = rows[k][j] - rows[j][k]
    else:
        q = [m21 - m12, m02 - m20, m10 - m01, 1 + trace]
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return np.array([q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm])


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
