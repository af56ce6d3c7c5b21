"""Metric body motion between two frames from every camera's feature tracks at once: the
generalised epipolar constraint of a rigid multi-camera rig (Pless 2003; Kneip and Li 2014).
ROS-free.

Body motion (R, t) from frame a to frame b, in base_link at a. Camera k (optical rotation
Rc_k, centre c_k in base_link) then moves by R_k = Rc^T R Rc and b_k = Rc^T (R c_k + t - c_k),
and a track seen at the normalised points x_a and x_b satisfies x_a^T [b_k]x R_k x_b = 0.
The lever arms c_k are metric, so t is: in a turn, (R - I) c_k differs from camera to camera
and fixes |t|; without rotation every b_k is t and only its direction is seen.

Why this and not each camera's own motion (rig_scale): a camera's pose comes from landmarks
triangulated from the fused poses, so its motion carries the map's scale, and the rig fit on
those motions gives back mostly the map's own scale. Tracks are image measurements alone.

Fitted by robust least squares (scipy, Huber) of Sampson errors in units of each point's
std, from the fused motion (any scale: the fit does not depend on it), R and t jointly: a
fixed R's error of a few mrad would leak into t's direction.
"""
import os
from dataclasses import dataclass
from typing import List, Sequence

import numpy as np
from scipy.optimize import least_squares

from camera_pose_nodes.kernel import ENV as KERNEL_ENV
from multicam_ego_motion.geometry import se3

try:
    from arbiter_node import _rig_motion_kernel as native
except ImportError:                 # not built: the numpy reference below
    native = None

# Steps per fit, at most (scipy's default is 600): it runs on the general arbiter's thread.
# Measured: median 5-6, at most 36 (loop) and 46 (spin_then_drive's start, from rest), 40 ms;
# a cap of 12 lost the spin's start. One that has not converged by 50 is rejected.
MAX_EVALUATIONS = 50


@dataclass
class CameraTracks:
    """One camera's tracks seen in both frames."""
    R_base_cam: np.ndarray      # optical frame -> base_link
    centre: np.ndarray          # camera centre in base_link (m)
    xa: np.ndarray              # (N, 2) normalised undistorted points at frame a
    xb: np.ndarray              # (N, 2) at frame b
    sigma: np.ndarray           # (N,) std of a point, normalised units (pixel std / focal)


@dataclass
class RigMotionFit:
    R: np.ndarray
    t: np.ndarray               # metric translation, base_link at frame a (m)
    relative_std: float         # predicted std of |t| along t, relative
    covariance: np.ndarray      # 6x6 of (rotation correction, rotation vector; t)
    n_points: int
    n_inliers: int
    rms: float                  # inliers' residual RMS, in point stds
    ok: bool
    reason: str = ''


def _residuals(x, R0, cameras: Sequence[CameraTracks]):
    R = se3.rotvec_to_R(x[:3]) @ R0
    t = x[3:]
    out = []
    for c in cameras:
        Rc = c.R_base_cam
        E = se3.skew(Rc.T @ (R @ c.centre + t - c.centre)) @ (Rc.T @ R @ Rc)
        ha = np.column_stack([c.xa, np.ones(len(c.xa))])
        hb = np.column_stack([c.xb, np.ones(len(c.xb))])
        Exb = hb @ E.T
        Eta = ha @ E
        e = np.einsum('ij,ij->i', ha, Exb)
        # Sampson: the algebraic error over its gradient in the four image coordinates
        grad2 = Exb[:, 0] ** 2 + Exb[:, 1] ** 2 + Eta[:, 0] ** 2 + Eta[:, 1] ** 2
        out.append(e / (np.sqrt(grad2 + 1e-30) * c.sigma))
    return np.concatenate(out)


def fit_rig_motion(R0: np.ndarray, t0: np.ndarray, cameras: List[CameraTracks],
                   min_points: int = 30, inlier_sigmas: float = 3.0, min_cameras: int = 2) -> RigMotionFit:
    """(R, t) of the body from frame a to b, metric; R0, t0: a start (the fused motion, t0 in
    any scale, not zero). relative_std from the Jacobian at the inliers, scaled by their
    residual RMS (in point stds). min_cameras 1: for the rotation alone (one camera's |t| is
    not metric)."""
    cameras = [c for c in cameras if len(c.xa)]
    n = sum(len(c.xa) for c in cameras)
    fail = RigMotionFit(np.asarray(R0, float), np.zeros(3), float('inf'), np.eye(6) * 1e6, n, 0,
                        float('nan'), False)
    if len(cameras) < min_cameras:
        fail.reason = f'{len(cameras)} camera(s) with tracks in both frames; need {min_cameras}'
        return fail
    if n < min_points:
        fail.reason = f'{n} tracks in both frames; need {min_points}'
        return fail
    t0 = np.asarray(t0, float)
    if not np.all(np.isfinite(t0)) or np.linalg.norm(t0) < 1e-9:
        fail.reason = 'no start translation'
        return fail
    sol = least_squares(_residuals, np.r_[np.zeros(3), t0], args=(np.asarray(R0, float), cameras),
                        loss='huber', f_scale=1.0, max_nfev=MAX_EVALUATIONS)
    r = sol.fun
    inl = np.abs(r) < inlier_sigmas
    R = se3.rotvec_to_R(sol.x[:3]) @ R0
    t = sol.x[3:]
    tn = float(np.linalg.norm(t))
    if inl.sum() < min_points:
        fail.reason = f'{int(inl.sum())} inliers; need {min_points}'
        return fail
    rms = float(np.sqrt(np.mean(r[inl] ** 2)))
    J = sol.jac[inl]
    try:
        # scaled by the residuals' own RMS: tracks are often better than the nominal std
        cov = np.linalg.inv(J.T @ J) * rms ** 2
    except np.linalg.LinAlgError:
        fail.reason = 'singular fit'
        return fail
    rel = float(np.sqrt(max(t @ cov[3:, 3:] @ t, 0.0)) / tn ** 2) if tn > 1e-9 else float('inf')
    return RigMotionFit(R, t, rel, cov, n, int(inl.sum()), rms, bool(sol.success and np.isfinite(rel)),
                        '' if sol.success else f'not converged: {sol.message}')


# refine_rig_motion's Gauss-Newton: steps, Huber threshold and its Jacobian's forward difference
REFINE_ITERATIONS = 4
HUBER_SIGMAS = 1.0
_JACOBIAN_STEP = 1e-7


def _residuals_and_jacobian(x, R0, cameras):
    """_residuals at x and their forward-difference Jacobian (the native kernel's steps)."""
    r = _residuals(x, R0, cameras)
    J = np.empty((len(r), 6))
    for k in range(6):
        xk = x.copy()
        xk[k] += _JACOBIAN_STEP
        J[:, k] = (_residuals(xk, R0, cameras) - r) / _JACOBIAN_STEP
    return r, J


def _refine_numpy(R0, t0, cameras, iterations, huber, inlier_sigmas, min_points):
    """The native kernel's refinement in numpy: (ok, R, t, covariance, n_inliers, rms, reason)."""
    failed = lambda reason: (False, None, None, None, 0, float('nan'), reason)
    x = np.r_[np.zeros(3), t0]
    for _ in range(iterations):
        r, J = _residuals_and_jacobian(x, R0, cameras)
        w = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-12))
        try:
            x = x - np.linalg.solve(J.T @ (J * w[:, None]) + 1e-12 * np.eye(6), J.T @ (w * r))
        except np.linalg.LinAlgError:
            return failed('singular fit')
        if not np.all(np.isfinite(x)):
            return failed('not finite')
    r, J = _residuals_and_jacobian(x, R0, cameras)
    inl = np.abs(r) < inlier_sigmas
    if inl.sum() < min_points:
        return failed(f'{int(inl.sum())} inliers; need {min_points}')
    rms = float(np.sqrt(np.mean(r[inl] ** 2)))
    try:
        cov = np.linalg.inv(J[inl].T @ J[inl]) * rms ** 2
    except np.linalg.LinAlgError:
        return failed('singular fit')
    return True, se3.rotvec_to_R(x[:3]) @ R0, x[3:], cov, int(inl.sum()), rms, ''


def refine_rig_motion(R0: np.ndarray, t0: np.ndarray, cameras: List[CameraTracks],
                      iterations: int = REFINE_ITERATIONS, min_points: int = 30,
                      inlier_sigmas: float = 3.0) -> RigMotionFit:
    """fit_rig_motion's problem by a fixed few Gauss-Newton steps (Huber weights) from a start
    near the answer (a gyro's rotation): about 0.1 ms for 400 tracks with the native kernel
    (3 ms in numpy) where the trust-region fit takes 12 ms. The rotation is what it is for
    (relative_std is not computed: infinite). The native kernel when built, else numpy
    (EGO_MOTION_KERNEL=numpy forces it); both the same steps."""
    cameras = [c for c in cameras if len(c.xa)]
    n = sum(len(c.xa) for c in cameras)
    R0 = np.asarray(R0, float)
    t0 = np.asarray(t0, float)
    failed = lambda reason: RigMotionFit(R0, np.zeros(3), float('inf'), np.eye(6) * 1e6, n, 0, float('nan'),
                                         False, reason)
    if not np.all(np.isfinite(t0)) or np.linalg.norm(t0) < 1e-9:
        return failed('no start translation')
    if n < min_points:
        return failed(f'{n} tracks in both frames; need {min_points}')
    if native is not None and os.environ.get(KERNEL_ENV, '').strip().lower() != 'numpy':
        out = native.refine_rig_motion(
            R0, t0, np.stack([c.R_base_cam for c in cameras]),
            np.stack([np.asarray(c.centre, float) for c in cameras]),
            np.repeat(np.arange(len(cameras)), [len(c.xa) for c in cameras]),
            np.concatenate([c.xa for c in cameras]), np.concatenate([c.xb for c in cameras]),
            np.concatenate([np.broadcast_to(c.sigma, (len(c.xa),)) for c in cameras]),
            int(iterations), HUBER_SIGMAS, float(inlier_sigmas), int(min_points))
    else:
        out = _refine_numpy(R0, t0, cameras, int(iterations), HUBER_SIGMAS, float(inlier_sigmas), int(min_points))
    ok, R, t, cov, n_in, rms, reason = out
    if not ok:
        return failed(reason)
    return RigMotionFit(R, t, float('inf'), cov, n, n_in, rms, True)
