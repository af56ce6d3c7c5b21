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
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from arbiter_node.covariance import mahalanobis2
from arbiter_node.quarter_fusion import CHI2_6DOF_999
from camera_pose_nodes.pose_estimate import PoseEstimate
from multicam_ego_motion import se3


@dataclass
class MedianResult:
    T_median: Optional[np.ndarray]                       # None when no camera was informative
    inliers: Dict[str, PoseEstimate] = field(default_factory=dict)
    rejected: Dict[str, str] = field(default_factory=dict)   # name -> reason
    uninformative: List[str] = field(default_factory=list)


def weiszfeld(points: np.ndarray, iterations: int = 50, eps: float = 1e-9,
              weights: Optional[np.ndarray] = None) -> np.ndarray:
    """Geometric median of row vectors (minimises the sum of Euclidean distances, each times
    its weight when weights are given)."""
    x = np.median(points, axis=0)
    for _ in range(iterations):
        d = np.linalg.norm(points - x, axis=1)
        if np.any(d < eps):           # sitting on a sample: that sample is a fine answer
            return points[np.argmin(d)].copy()
        w = 1.0 / d if weights is None else weights / d
        x_new = (w[:, None] * points).sum(axis=0) / w.sum()
        if np.linalg.norm(x_new - x) < eps:
            return x_new
        x = x_new
    return x


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
