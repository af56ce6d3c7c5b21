"""Accuracy figures of an estimated trajectory against the reference.

Inputs are associated pose pairs (Q_i reference, P_i estimate, i = 0..N-1, 4x4 poses of
base_link in odom). L_i is the reference's travelled distance sum_{k<=i} |q_k - q_(k-1)| and
L = L_(N-1) its path length; ang(R) is the angle of a rotation (norm of its rotation vector).

* ate_rmse_m: absolute trajectory error after aligning on the first pose (P' = Q_0 P_0^-1 P,
  no fit, no scale: what a robot starting at a known pose gets),
  sqrt(mean_i |p'_i - q_i|^2); ate_pct = 100 ate_rmse_m / L (the issue's "% of path length").
* ate_se3_rmse_m, ate_sim3_rmse_m: the same after a least-squares Umeyama fit of the
  positions, rigid (SE(3)) and rigid plus scale (Sim(3)).
* ate_sim3_pct: ate_sim3_rmse_m in % of the path (the figure of a run without a scale
  source before it was measured: its shape, whatever its scale).
* first_odometry_s (evaluate_trajectories): seconds from the first pose to the first estimate
  that moved 1 cm from its start (odometry that stays at the origin does not count).
* sim3_scale: the Sim(3) factor s with q ~ s R p + t; scale_error_pct = 100 (1/s - 1): the
  estimate's scale error, +2 when it measures every distance 2 % too long.
* final_drift_m = |p'_(N-1) - q_(N-1)|, final_drift_pct = 100 final_drift_m / L.
* rotation_drift_deg_per_m = ang(R'_(N-1)^T R^q_(N-1)) in degrees / L (origin-aligned).
* RPE over a travelled distance d (KITTI-style segments; only the d <= L that give at least
  one pair): for every start i the end j > i whose L_j - L_i is nearest to d, kept when
  within 10 % of d (evo's "all pairs" rule with rel_delta_tol 0.1). With
  E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) on the unaligned estimate (RPE ignores rigid alignment,
  scale errors count) and l_ij = L_j - L_i the segment's actual length:
  rpe_<d>m_trans_pct = 100 mean |t(E_ij)| / l_ij and rpe_<d>m_rot_deg_per_m =
  mean ang(E_ij) in degrees / l_ij (dividing by the actual rather than the nominal length
  keeps the segments at the end of the path, up to 10 % short, unbiased);
  rpe_trans_pct and rpe_rot_deg_per_m average these over the distances evaluated (like the
  KITTI benchmark). |t(E_ij)| and ang(E_ij) are exactly evo's RPE errors for
  delta_unit=meters, all_pairs=True, pairs_from_reference=True, rel_delta_tol=0.1.
"""
import numpy as np
from scipy.spatial.transform import Rotation

from multicam_ego_motion.evaluation.alignment import align_origin, align_se3, align_sim3

DEFAULT_RPE_DISTANCES_M = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
RPE_REL_TOLERANCE = 0.1


def travelled_distances(positions: np.ndarray) -> np.ndarray:
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(R).magnitude())


def translation_errors(ref_poses, est_poses) -> np.ndarray:
    return np.linalg.norm(est_poses[:, :3, 3] - ref_poses[:, :3, 3], axis=1)


def rmse(errors) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def segment_pairs(distances: np.ndarray, d: float, rel_tol: float = RPE_REL_TOLERANCE):
    """(i, j) pairs whose travelled distance is nearest to d, within rel_tol * d."""
    pairs = []
    for i in range(len(distances) - 1):
        ahead = distances[i + 1:] - distances[i]
        k = int(np.argmin(np.abs(ahead - d)))
        if abs(ahead[k] - d) <= rel_tol * d:
            pairs.append((i, i + 1 + k))
    return pairs


def relative_errors(ref_poses, est_poses, pairs) -> np.ndarray:
    """E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) for each pair, (M, 4, 4)."""
    i, j = np.array(pairs).T
    ref_rel = np.linalg.inv(ref_poses[i]) @ ref_poses[j]
    est_rel = np.linalg.inv(est_poses[i]) @ est_poses[j]
    return np.linalg.inv(ref_rel) @ est_rel


def rpe_segments(ref_poses, est_poses, distances, d: float):
    """Per segment of length about d: (pairs, |t(E)| in m, ang(E) in deg, length l_ij in m)."""
    pairs = segment_pairs(distances, d)
    if not pairs:
        return [], np.empty(0), np.empty(0), np.empty(0)
    E = relative_errors(ref_poses, est_poses, pairs)
    i, j = np.array(pairs).T
    return (pairs, np.linalg.norm(E[:, :3, 3], axis=1), rotation_angles_deg(E[:, :3, :3]),
            distances[j] - distances[i])


def compute_metrics(ref_poses, est_poses, rpe_distances=DEFAULT_RPE_DISTANCES_M) -> dict:
    """The figures defined in the module docstring, as a flat dict of floats."""
    ref_poses, est_poses = np.asarray(ref_poses, float), np.asarray(est_poses, float)
    distances = travelled_distances(ref_poses[:, :3, 3])
    length = float(distances[-1])
    origin = align_origin(est_poses, ref_poses)
    sim3, scale = align_sim3(est_poses, ref_poses)
    final_m = float(translation_errors(ref_poses[-1:], origin[-1:])[0])
    final_rot = float(rotation_angles_deg(origin[-1, :3, :3].T @ ref_poses[-1, :3, :3]))
    per_metre = (lambda x: x / length) if length > 0 else (lambda x: float('nan'))
    ate_m = rmse(translation_errors(ref_poses, origin))
    out = {
        'poses': len(ref_poses),
        'path_length_m': length,
        'ate_rmse_m': ate_m,
        'ate_pct': 100.0 * per_metre(ate_m),
        'ate_se3_rmse_m': rmse(translation_errors(ref_poses, align_se3(est_poses, ref_poses))),
        'ate_sim3_rmse_m': rmse(translation_errors(ref_poses, sim3)),
        'ate_sim3_pct': 100.0 * per_metre(rmse(translation_errors(ref_poses, sim3))),
        'sim3_scale': scale,
        'scale_error_pct': 100.0 * (1.0 / scale - 1.0),
        'final_drift_m': final_m,
        'final_drift_pct': 100.0 * per_metre(final_m),
        'rotation_drift_deg_per_m': per_metre(final_rot),
    }
    trans, rot = [], []
    for d in rpe_distances:
        if d > length:
            continue
        pairs, trans_m, rot_deg, seg_m = rpe_segments(ref_poses, est_poses, distances, d)
        if not pairs:
            continue
        out[f'rpe_{d:g}m_pairs'] = len(pairs)
        out[f'rpe_{d:g}m_trans_pct'] = 100.0 * float(np.mean(trans_m / seg_m))
        out[f'rpe_{d:g}m_rot_deg_per_m'] = float(np.mean(rot_deg / seg_m))
        trans.append(out[f'rpe_{d:g}m_trans_pct'])
        rot.append(out[f'rpe_{d:g}m_rot_deg_per_m'])
    out['rpe_trans_pct'] = float(np.mean(trans)) if trans else float('nan')
    out['rpe_rot_deg_per_m'] = float(np.mean(rot)) if rot else float('nan')
    return out
