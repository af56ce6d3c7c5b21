"""Camera arbiter core (paper T_k5): fuse one camera's quarter estimates into the camera's.

Fusion is information-form (covariance-weighted) in the se3 error convention, linearised
about a robust reference (the medoid: the informative quarter with the smallest summed,
capped Mahalanobis distance to the others), after rejecting quarters that are more than a
chi-square gate (6 dof) away from it. So one bad quarter cannot drag the camera estimate.

Why a correlation inflation: the quarters of one camera are not independent. They share the
camera's image timing and, above all, their landmarks are triangulated from the same fused
body poses, so their errors are positively correlated. Plain information fusion of n
estimates with pairwise correlation rho shrinks the covariance by n where the truth is
n / (1 + (n - 1) rho) (variance of a mean of equicorrelated variables). `correlation` is rho;
the fused covariance is multiplied by 1 + (n - 1) rho so that downstream gates stay honest.
"""
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np
from scipy.stats import chi2

from arbiter_node.covariance import condition_covariance, safe_inverse
from camera_pose_nodes.pose_estimate import UNINFORMATIVE_VARIANCE, PoseEstimate, uninformative
from multicam_ego_motion.geometry import se3

CHI2_6DOF_999 = float(chi2.ppf(0.999, 6))   # 22.46
DEFAULT_CORRELATION = 0.5
_MEDOID_CAP = 4.0 * CHI2_6DOF_999           # one far outlier must not dominate the medoid sums

# name -> (default, description, min, max): the camera arbiter declares its fusion parameters
# from this, and the ROS-free runs take the same values from the params file.
PARAMETERS = {
    'outlier_chi2': (CHI2_6DOF_999, 'reject a quarter this far (6-dof Mahalanobis^2) from the robust reference', 1.0, 1e6),
    'correlation': (DEFAULT_CORRELATION, 'assumed error correlation between quarters (shared landmarks); inflates the fused covariance', 0.0, 1.0),
}


@dataclass
class FusionReport:
    estimate: PoseEstimate
    used: List[str] = field(default_factory=list)
    rejected: Dict[str, str] = field(default_factory=dict)     # source -> reason
    uninformative: List[str] = field(default_factory=list)


def _usable(e: PoseEstimate) -> Optional[str]:
    """None if e can be fused, else the reason why not."""
    if not e.informative:
        return 'uninformative'
    if not (np.all(np.isfinite(e.T_odom_base)) and np.all(np.isfinite(e.covariance))):
        return 'non-finite'
    if not se3.is_valid_covariance(e.covariance):
        return 'covariance not positive definite'
    return None


def information_fusion(poses: Sequence[np.ndarray], covs: Sequence[np.ndarray],
                       T_ref: np.ndarray, iterations: int = 3):
    """Covariance-weighted mean of poses in the se3 error convention, relinearised about the
    running mean. Returns (T, covariance) with covariance = (sum C_i^-1)^-1 (conditioned)."""
    infos = [safe_inverse(C) for C in covs]
    Lam = sum(infos)
    cov = safe_inverse(Lam)
    T = T_ref.copy()
    for _ in range(iterations):
        eta = sum(I @ se3.pose_error(Ti, T) for I, Ti in zip(infos, poses))
        delta = cov @ eta
        T = se3.perturb(T, delta)
        if np.linalg.norm(delta) < 1e-12:
            break
    return T, condition_covariance(cov)


def pair_d2_matrix(estimates: Sequence[PoseEstimate]) -> List[List[float]]:
    """d2[i][j] = mahalanobis2(pose_error(T_i, T_j), C_i + C_j), 0 on the diagonal. C_i + C_j
    and C_j + C_i are the same matrix (float addition commutes), so its inverse is computed
    once per pair: the same numbers at half the cost."""
    n = len(estimates)
    d2 = [[0.0] * n for _ in range(n)]
    for i in range(n):
        a = estimates[i]
        for j in range(i + 1, n):
            b = estimates[j]
            info = safe_inverse(a.covariance + b.covariance)
            for r, c, Ta, Tb in ((i, j, a.T_odom_base, b.T_odom_base),
                                 (j, i, b.T_odom_base, a.T_odom_base)):
                e = se3.pose_error(Ta, Tb)
                d2[r][c] = float(e @ info @ e)      # covariance.mahalanobis2's arithmetic
    return d2


def robust_reference(estimates: Sequence[PoseEstimate], d2: Optional[List[List[float]]] = None) -> int:
    """Index of the medoid (smallest summed capped pairwise Mahalanobis distance); ties go to
    the most confident (smallest log-det covariance), which decides the 2-estimate case.
    d2: pair_d2_matrix(estimates) when the caller has it already."""
    n = len(estimates)
    if d2 is None:
        d2 = pair_d2_matrix(estimates)
    scores = [round(sum(min(d2[i][j], _MEDOID_CAP) for j in range(n) if j != i), 9) for i in range(n)]
    best = min(scores)
    tied = [i for i in range(n) if scores[i] == best]
    if len(tied) == 1:
        return tied[0]
    return min((float(np.linalg.slogdet(estimates[i].covariance)[1]), i) for i in tied)[1]


def aggregate_stage_ms(estimates: Sequence[PoseEstimate]) -> Dict[str, float]:
    """Per stage: max across quarters (the critical path when quarters run in parallel) under
    the stage's name, and the sum (the sequential cost) under '<stage>_sum'."""
    out: Dict[str, float] = {}
    keys = sorted({k for e in estimates for k in e.stage_ms})
    for k in keys:
        vals = [float(e.stage_ms[k]) for e in estimates if k in e.stage_ms and np.isfinite(e.stage_ms[k])]
        if vals:
            out[k] = max(vals)
            out[k + '_sum'] = sum(vals)
    return out


def fuse_quarters_report(estimates: List[PoseEstimate], source: str,
                         outlier_chi2: float = CHI2_6DOF_999,
                         correlation: float = DEFAULT_CORRELATION) -> FusionReport:
    if not estimates:
        raise ValueError('fuse_quarters needs at least one estimate (uninformative ones count)')
    stamp = max(e.stamp_ns for e in estimates)
    kw = dict(n_features=sum(e.n_features for e in estimates),
              n_landmarks=sum(e.n_landmarks for e in estimates),
              n_floor=sum(e.n_floor for e in estimates),
              stage_ms=aggregate_stage_ms(estimates))
    report = FusionReport(estimate=None)
    good = []
    for e in estimates:
        why = _usable(e)
        if why == 'uninformative':
            report.uninformative.append(e.source)
        elif why is not None:
            report.rejected[e.source] = why
        else:
            good.append(e)

    if not good:
        # Carry the first finite prior pose so that downstream has something to show.
        prior = next((e.T_odom_base for e in estimates if np.all(np.isfinite(e.T_odom_base))), np.eye(4))
        state = 'lost' if any(e.state in ('lost', 'tracking') for e in estimates) else 'initializing'
        report.estimate = uninformative(stamp, prior, source, state, **kw)
        return report

    d2_pairs = pair_d2_matrix(good)
    r = robust_reference(good, d2_pairs)
    ref = good[r]
    inliers = []
    for i, e in enumerate(good):
        d2 = d2_pairs[i][r]
        if d2 > outlier_chi2:
            report.rejected[e.source] = f'mahalanobis {d2:.1f} > {outlier_chi2:.1f} to {ref.source}'
        else:
            inliers.append(e)
    T, cov = information_fusion([e.T_odom_base for e in inliers], [e.covariance for e in inliers],
                                ref.T_odom_base)
    n = len(inliers)
    cov = condition_covariance(cov * (1.0 + (n - 1) * float(np.clip(correlation, 0.0, 1.0))),
                               max_eig=UNINFORMATIVE_VARIANCE)
    report.used = [e.source for e in inliers]
    report.estimate = PoseEstimate(stamp, T, cov, source=source, state='tracking',
                                   n_inliers=sum(e.n_inliers for e in inliers), **kw)
    return report


def fuse_quarters(estimates: List[PoseEstimate], source: str,
                  outlier_chi2: float = CHI2_6DOF_999,
                  correlation: float = DEFAULT_CORRELATION) -> PoseEstimate:
    """Fused camera estimate from its quarters' (see module doc). Never NaN; covariance PD."""
    return fuse_quarters_report(estimates, source, outlier_chi2, correlation).estimate
