"""Metric translation from a rigid rig of non-overlapping cameras (Clipp et al. 2008;
Kim, Li, Hartley).

Body poses (R1, p1) and (R2, p2) in odom at two instants; R = R1^T R2 and t = R1^T (p2 - p1)
are the body motion expressed in base_link at the first instant. Camera k (centre c_k in
base_link) then moves by t_k = t + (R - I) c_k. A monocular camera only knows the direction
d_k of t_k, so t_k = s_k d_k with s_k >= 0 unknown:

        s_k d_k - t = (R - I) c_k          (3 equations per camera, unknowns t and s_1..s_N)

The right-hand side is what carries metric scale: it vanishes when R = I (pure translation,
every s_k d_k = t and the overall scale is free) and it needs at least two cameras (one camera
gives 3 equations for 4 unknowns). We solve by weighted least squares via the SVD and report
the smallest singular value of the whitened system relative to the largest (reciprocal
condition) so that the caller only trusts well-conditioned solutions.
"""
from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence

import numpy as np

from multicam_ego_motion.geometry import se3


@dataclass
class RigScaleResult:
    t: np.ndarray                     # body translation in base_link at the first instant (m)
    s: np.ndarray                     # per-camera metric translation lengths (m)
    observed: bool                    # rotated enough, well conditioned, precise enough
    condition: float                  # sigma_max / sigma_min of the whitened system
    relative_std: float               # predicted std of |t| error / |t| from direction noise
    t_covariance: np.ndarray = field(default_factory=lambda: np.eye(3))
    reason: str = ''                  # why not observed
    cameras: Sequence[str] = field(default_factory=tuple)
    residual_rms: float = 0.0         # m, after the fit


def _whitened_system(R, D, C, w):
    N = len(D)
    A = np.zeros((3 * N, 3 + N))
    b = np.zeros(3 * N)
    for k in range(N):
        sw = np.sqrt(w[k])
        A[3 * k:3 * k + 3, :3] = -np.eye(3) * sw
        A[3 * k:3 * k + 3, 3 + k] = D[k] * sw
        b[3 * k:3 * k + 3] = (R - np.eye(3)) @ C[k] * sw
    return A, b


def solve_rig_translation(R: np.ndarray, directions: Sequence[Optional[np.ndarray]],
                          centres: Sequence[np.ndarray],
                          direction_sigma_rad=0.01, min_rotation_rad: float = 0.02,
                          max_condition: float = 1e3, max_relative_std: float = 0.1,
                          names: Sequence[str] = ()) -> RigScaleResult:
    """Solve s_k d_k = t + (R - I) c_k for t and s (see module doc).

    directions: camera translation directions in base_link at the first instant; a None or
    zero entry means that camera saw no motion and is skipped. direction_sigma_rad: angular
    std of each direction (scalar or per camera). The residual of camera k has std about
    s_k * sigma_k, so the fit is weighted by 1 / sigma_k^2, then re-weighted once by
    1 / (s_k sigma_k)^2; the same model gives t's covariance and `relative_std`."""
    R = np.asarray(R, dtype=float)
    names = list(names) if names else [str(i) for i in range(len(directions))]
    sig = np.broadcast_to(np.asarray(direction_sigma_rad, dtype=float), (len(directions),))
    D, C, S, used = [], [], [], []
    for k, d in enumerate(directions):
        if d is None:
            continue
        d = np.asarray(d, dtype=float)
        n = np.linalg.norm(d)
        if not np.isfinite(n) or n < 1e-9 or not np.isfinite(sig[k]) or sig[k] <= 0:
            continue
        D.append(d / n)
        C.append(np.asarray(centres[k], dtype=float))
        S.append(float(sig[k]))
        used.append(names[k])
    N = len(D)
    out = RigScaleResult(np.zeros(3), np.zeros(N), False, float('inf'), float('inf'),
                         np.eye(3) * 1e6, cameras=tuple(used))
    if N < 2:
        out.reason = f'{N} camera(s) with a motion direction; need 2'
        return out
    if not np.all(np.isfinite(R)):
        out.reason = 'non-finite rotation'
        return out
    S = np.array(S)
    w = 1.0 / S ** 2
    for _ in range(2):
        A, b = _whitened_system(R, D, C, w)
        U, sv, Vt = np.linalg.svd(A, full_matrices=False)
        x = Vt.T @ ((U.T @ b) / np.maximum(sv, 1e-300))
        lengths = np.maximum(np.abs(x[3:]), 1e-3 * max(np.abs(x[3:]).max(), 1e-9))
        w = 1.0 / (lengths * S) ** 2
    # with w = 1 / (s_k sigma_k)^2 the whitened residual noise is ~ unit per direction:
    # the 2 directions orthogonal to d_k carry noise, so cov(x) ~ (A^T A)^-1 up to that projection
    cov_x = Vt.T @ np.diag(1.0 / np.maximum(sv, 1e-300) ** 2) @ Vt
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float('inf')
    t, s = x[:3], x[3:]
    cov_t = 0.5 * (cov_x[:3, :3] + cov_x[:3, :3].T)
    tn = float(np.linalg.norm(t))
    rel = float(np.sqrt(np.trace(cov_t)) / tn) if tn > 0 else float('inf')
    res = (A @ x - b) / np.repeat(np.sqrt(w), 3)
    angle = float(np.linalg.norm(se3.R_to_rotvec(R)))
    # |(R - I) c| is the metric signal; with R = I the exact solution is t = 0, s = 0
    reason = ''
    if angle < min_rotation_rad:
        reason = f'rotation {angle:.4f} rad < {min_rotation_rad} rad: scale unobservable'
    elif cond > max_condition:
        reason = f'condition {cond:.3g} > {max_condition:.3g}'
    elif np.any(s < -1e-6):
        reason = 'negative camera translation length (directions inconsistent)'
    elif rel > max_relative_std:
        reason = f'predicted relative error {rel:.3f} > {max_relative_std}'
    return RigScaleResult(t, s, reason == '', cond, rel, cov_t, reason, tuple(used),
                          float(np.sqrt(np.mean(res ** 2))))


def relative_motion(T1: np.ndarray, T2: np.ndarray):
    """(R, t) of the body from T1 to T2 (base_link in odom), expressed in base_link at T1."""
    R1 = T1[:3, :3]
    return R1.T @ T2[:3, :3], R1.T @ (T2[:3, 3] - T1[:3, 3])


def camera_direction(T1: np.ndarray, T2: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Unit direction of camera centre c's motion from T1 to T2, in base_link at T1 (what a
    camera's own up-to-scale motion estimate provides; used to build synthetic data)."""
    R, t = relative_motion(T1, T2)
    tk = t + (R - np.eye(3)) @ c
    n = np.linalg.norm(tk)
    return tk / n if n > 0 else tk


def scale_correction(t_estimate: np.ndarray, result: RigScaleResult, min_length_m: float = 1e-3) -> Optional[float]:
    """Factor k so that k * t_estimate best matches the rig's metric t (least squares along
    t_estimate), or None when the rig did not observe scale or the motion is too short."""
    t_estimate = np.asarray(t_estimate, dtype=float)
    nn = float(t_estimate @ t_estimate)
    if not result.observed or nn < min_length_m ** 2 or np.linalg.norm(result.t) < min_length_m:
        return None
    k = float(t_estimate @ result.t) / nn
    return k if k > 0 and np.isfinite(k) else None
