"""General arbiter, first step (paper T_5): median filter across the cameras.

The geometric median (Weiszfeld) of the informative cameras' positions and, in the tangent
space of the rotation, of their rotation vectors (re-centred on the running median so the
chordal/L1 distance is well approximated) is a consensus that up to half of the cameras can
not move. Cameras far from it are rejected by a Mahalanobis gate (their own covariance) or an
absolute gate (metres / radians, which catches over-confident covariances), with a reason.
An optional prior (the general arbiter's prediction) joins the vote, without becoming an
inlier itself: with fewer than three cameras the median cannot out-vote anyone, and with an
even count it cannot break a tie (after a blackout two cameras with young maps can pull one
way and two the other; the median then sat on one young camera and rejected the rest).
Weighted (optional): each vote counts by its precision (1 / RMS std, position and rotation
separately), so a camera whose quarters only see epipolar lines, with a position "unknown" at
10 m std, cannot move the position median, and a tracked camera outweighs a loose one.
"""
import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from arbiter_node.covariance import mahalanobis2
from arbiter_node.quarter_fusion import CHI2_6DOF_999
from camera_pose_nodes.pose_estimate import PoseEstimate
from multicam_ego_motion.geometry import se3


@dataclass
class MedianResult:
    T_median: Optional[np.ndarray]                       # None when no camera was informative
    inliers: Dict[str, PoseEstimate] = field(default_factory=dict)
    rejected: Dict[str, str] = field(default_factory=dict)   # name -> reason
    uninformative: List[str] = field(default_factory=list)


def weiszfeld(points: np.ndarray, iterations: int = 50, eps: float = 1e-9,
              weights: Optional[np.ndarray] = None) -> np.ndarray:
    """Geometric median of finite 3-vectors (rows; minimises the sum of Euclidean distances,
    each times its weight when weights are given).
    In plain floats: it runs up to 50 iterations on 3 to 5 points, 4 times a frame, and numpy's
    per-call overhead on such tiny arrays was half the general arbiter's time. The operations
    are those of the array formulation, in numpy's order (start at the component-wise median;
    sums of up to 7 terms left to right), hence the same bits (test_camera_median checks it)."""
    pts = [tuple(p) for p in np.asarray(points, dtype=float).tolist()]
    ws = [1.0] * len(pts) if weights is None else [float(v) for v in weights]
    x, y, z = (_median(c) for c in zip(*pts))
    for _ in range(iterations):
        d = []
        for px, py, pz in pts:
            dx, dy, dz = px - x, py - y, pz - z
            d.append(math.sqrt(dx * dx + dy * dy + dz * dz))
        nearest = min(d)
        if nearest < eps:                 # sitting on a sample: that sample is a fine answer
            return np.array(pts[d.index(nearest)])
        # weighted mean, weights (weight) / distance, summed left to right from the first point
        (px, py, pz), rest = pts[0], zip(pts[1:], d[1:], ws[1:])
        w_sum = ws[0] / d[0]
        sx, sy, sz = w_sum * px, w_sum * py, w_sum * pz
        for (px, py, pz), di, wi in rest:
            w = wi / di
            w_sum += w
            sx, sy, sz = sx + w * px, sy + w * py, sz + w * pz
        nx, ny, nz = sx / w_sum, sy / w_sum, sz / w_sum
        dx, dy, dz = nx - x, ny - y, nz - z
        x, y, z = nx, ny, nz
        if math.sqrt(dx * dx + dy * dy + dz * dz) < eps:
            break
    return np.array([x, y, z])


def _median(values) -> float:
    """np.median of a few numbers: the middle one, or the mean of the middle two."""
    s = sorted(values)
    n = len(s)
    return s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2


def median_pose(poses: List[np.ndarray], rounds: int = 3,
                covariances: Optional[List[np.ndarray]] = None) -> np.ndarray:
    """Position: geometric median. Rotation: geometric median of rotation vectors taken about
    the current estimate, re-centred `rounds` times (starts at the first pose). With
    covariances, each pose's vote is weighted by 1 / RMS std (position, rotation apart)."""
    wp = wr = None
    if covariances is not None:
        wp = np.array([1.0 / np.sqrt(np.trace(C[:3, :3]) / 3.0) for C in covariances])
        wr = np.array([1.0 / np.sqrt(np.trace(C[3:, 3:]) / 3.0) for C in covariances])
    p = weiszfeld(np.array([T[:3, 3] for T in poses]), weights=wp)
    R = poses[0][:3, :3]
    for _ in range(rounds):
        rv = np.array([se3.R_to_rotvec(T[:3, :3] @ R.T) for T in poses])
        R = se3.rotvec_to_R(weiszfeld(rv, weights=wr)) @ R
    return se3.make_T(R, p)


def median_filter(estimates: Dict[str, PoseEstimate],
                  mahalanobis_gate: float = CHI2_6DOF_999,
                  max_translation_m: float = 0.5,
                  max_rotation_rad: float = 0.2,
                  prior: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                  prior_max_cameras: int = 2, weighted: bool = False) -> MedianResult:
    """Split cameras into inliers / rejected (with reasons) around their median pose.
    `prior` = (T, covariance) of the predicted body pose; it votes when at most
    `prior_max_cameras` cameras are informative. `weighted`: votes count by precision."""
    res = MedianResult(T_median=None)
    cand = {}
    for name, e in estimates.items():
        if not e.informative:
            res.uninformative.append(name)
        elif not (np.all(np.isfinite(e.T_odom_base)) and np.all(np.isfinite(e.covariance))):
            res.rejected[name] = 'non-finite'
        elif not se3.is_valid_covariance(e.covariance):
            res.rejected[name] = 'covariance not positive definite'
        else:
            cand[name] = e
    if not cand:
        return res
    poses = [e.T_odom_base for e in cand.values()]
    covs = [e.covariance for e in cand.values()]
    if prior is not None and len(cand) <= prior_max_cameras and np.all(np.isfinite(prior[0])) \
            and se3.is_valid_covariance(prior[1]):
        poses.append(prior[0])
        covs.append(prior[1])
        # The bounds are about the cameras' spread, not the prior's own uncertainty: a car
        # at speed whose velocity is not known yet (no wheel) moves farther from its
        # prediction than max_translation_m, and was rejected against a prior it was right
        # to disagree with (KITTI at 5 m/s: every camera pose for 5 frames).
        sd = np.sqrt(np.clip(np.linalg.eigvalsh(np.asarray(prior[1], float)[:3, :3]), 0.0, None))
        sr = np.sqrt(np.clip(np.linalg.eigvalsh(np.asarray(prior[1], float)[3:, 3:]), 0.0, None))
        max_translation_m += 3.0 * float(sd.max())
        max_rotation_rad += 3.0 * float(sr.max())
    res.T_median = median_pose(poses, covariances=covs if weighted else None)
    for name, e in cand.items():
        err = se3.pose_error(e.T_odom_base, res.T_median)
        d2 = mahalanobis2(err, e.covariance)
        dt, dr = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
        if dt > max_translation_m:
            res.rejected[name] = f'{dt:.3f} m from the median (> {max_translation_m} m)'
        elif dr > max_rotation_rad:
            res.rejected[name] = f'{dr:.3f} rad from the median (> {max_rotation_rad} rad)'
        elif d2 > mahalanobis_gate:
            res.rejected[name] = f'mahalanobis {d2:.1f} > {mahalanobis_gate:.1f} from the median'
        else:
            res.inliers[name] = e
    return res
