"""The two figures of an evaluation report (matplotlib, Agg backend: no display needed)."""
import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (backend first)
import numpy as np  # noqa: E402

from multicam_ego_motion.evaluation.metrics import travelled_distances, translation_errors  # noqa: E402


def plot_trajectory(ref_poses, est_poses, path, title='trajectory (top view)'):
    """Top view (x, y in odom) of the reference and the origin-aligned estimate."""
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(ref_poses[:, 0, 3], ref_poses[:, 1, 3], 'k-', label='reference')
    ax.plot(est_poses[:, 0, 3], est_poses[:, 1, 3], 'C1-', label='estimate')
    ax.plot(ref_poses[0, 0, 3], ref_poses[0, 1, 3], 'go', label='start')
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(True, alpha=0.3)
    ax.legend()
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_error_over_distance(ref_poses, est_poses, path):
    """Position error of the origin-aligned estimate against the reference's travelled distance."""
    distances = travelled_distances(ref_poses[:, :3, 3])
    errors = translation_errors(ref_poses, est_poses)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(distances, errors, 'C3-')
    ax.set_xlabel('travelled distance [m]')
    ax.set_ylabel('position error [m]')
    ax.set_ylim(bottom=0.0, top=max(float(np.max(errors)) * 1.1, 1e-3))
    ax.grid(True, alpha=0.3)
    ax.set_title('position error over distance (aligned on the first pose)')
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
