"""Align an estimated trajectory to the reference before measuring errors.

Umeyama (1991) least squares on the positions, in three flavours: origin (first poses
coincide: the pose a real robot starts from, no fit), SE(3) (rigid fit) and Sim(3) (rigid
fit plus one scale factor). Our own Umeyama rather than evo's `umeyama_alignment` (which the
tests check it against): evo refuses collinear positions ("degenerate covariance rank"),
and a robot driving a straight line is a case we must score. For collinear positions the
rotation about the line is unobservable and any minimizer is returned (the positions, and
so every ATE figure, do not depend on the choice). All functions return new (N, 4, 4)
arrays; inputs are not modified.
"""
import numpy as np


def umeyama(src_positions: np.ndarray, dst_positions: np.ndarray, with_scale: bool):
    """(R, t, s) minimizing sum ||dst_i - (s R src_i + t)||^2; s = 1 without scale."""
    x = np.asarray(src_positions, float)
    y = np.asarray(dst_positions, float)
    mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mean_x, y - mean_y
    var_x = np.mean(np.sum(xc ** 2, axis=1))
    cov = yc.T @ xc / len(x)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # a reflection is not a rotation
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_x) if with_scale and var_x > 0 else 1.0
    t = mean_y - s * R @ mean_x
    return R, t, s


def apply_sim3(poses: np.ndarray, R, t, s: float = 1.0) -> np.ndarray:
    """Poses mapped by x -> s R x + t (orientations rotated by R)."""
    out = np.array(poses, dtype=float)
    out[:, :3, :3] = R @ out[:, :3, :3]
    out[:, :3, 3] = s * out[:, :3, 3] @ np.asarray(R).T + t
    return out


def align_origin(est_poses: np.ndarray, ref_poses: np.ndarray) -> np.ndarray:
    """Move the estimate rigidly so that its first pose equals the reference's first pose."""
    correction = ref_poses[0] @ np.linalg.inv(est_poses[0])
    return correction @ est_poses


def align_se3(est_poses, ref_poses):
    R, t, _ = umeyama(est_poses[:, :3, 3], ref_poses[:, :3, 3], with_scale=False)
    return apply_sim3(est_poses, R, t)


def align_sim3(est_poses, ref_poses):
    """(aligned poses, scale s): the estimate times s best fits the reference."""
    R, t, s = umeyama(est_poses[:, :3, 3], ref_poses[:, :3, 3], with_scale=True)
    return apply_sim3(est_poses, R, t, s), s
