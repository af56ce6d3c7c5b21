"""Pair the poses of two trajectories by time stamp.

Nearest stamp within a tolerance, starting from the trajectory with fewer poses (the
estimate when both have as many) so that none of its poses is lost; a pose of the longer
one may serve two neighbours. Same rule as evo's `sync.associate_trajectories`.
"""
import numpy as np

from multicam_ego_motion.errors import UserError
from multicam_ego_motion.evaluation.trajectory_io import Trajectory


def nearest_stamp_indices(stamps, candidates, max_diff: float):
    """For each stamp, the index of the nearest candidate within max_diff (or it is skipped).

    `candidates` must be sorted. Returns (indices into stamps, indices into candidates).
    """
    stamps, candidates = np.asarray(stamps, float), np.asarray(candidates, float)
    upper = np.minimum(np.searchsorted(candidates, stamps, side='right'), len(candidates) - 1)
    lower = np.maximum(upper - 1, 0)
    diff_up = candidates[upper] - stamps
    diff_low = np.where(upper > 0, stamps - candidates[lower], np.inf)
    # diff_up can be negative when the stamp lies past the last candidate (index clamped)
    take_up = (np.abs(diff_up) <= max_diff) & (np.abs(diff_up) < diff_low)
    take_low = ~take_up & (diff_low <= max_diff)
    chosen = np.where(take_up, upper, lower)
    keep = take_up | take_low
    return np.flatnonzero(keep), chosen[keep]


def associate(ref: Trajectory, est: Trajectory, max_diff: float = 0.01):
    """(ref, est) reduced to pairs of poses with (nearly) equal stamps, in time order."""
    if len(est) <= len(ref):
        i_est, i_ref = nearest_stamp_indices(est.stamps, ref.stamps, max_diff)
    else:
        i_ref, i_est = nearest_stamp_indices(ref.stamps, est.stamps, max_diff)
    if len(i_ref) < 2:
        raise UserError(f'only {len(i_ref)} pose(s) of the estimate and the reference have '
                        f'stamps within {max_diff} s of each other: are they the same run?')
    return ref.subset(i_ref), est.subset(i_est)
