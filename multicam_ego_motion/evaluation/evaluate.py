"""`ego-motion evaluate`: score an estimated trajectory against the reference.

    ego-motion evaluate --reference bags/default:/ground_truth/odom \\
                        --estimate out/default/estimate:/odom --out out/default/eval

A source is a TUM file, `BAG:/topic`, or `BAG` with `--reference-topic`/`--estimate-topic`.
Poses are associated by nearest stamp within `--max-time-diff` seconds. Writes to the
output folder: report.md (metrics table and both figures), trajectory.png,
error_over_distance.png, reference.tum and estimate.tum (the associated poses; the estimate
as given, not aligned). The metrics are defined in `multicam_ego_motion.evaluation.metrics`.

Python API (for `replay` and regression tests)::

    ref = load_trajectory('bags/default:/ground_truth/odom')
    est = load_trajectory('out/estimate', topic='/odom')
    metrics = evaluate_trajectories(ref, est)             # -> dict of floats
    metrics = evaluate_trajectories(ref, est, out_dir='out/eval')  # + report files
"""
import sys
from pathlib import Path

import numpy as np

from multicam_ego_motion.evaluation.alignment import align_origin
from multicam_ego_motion.evaluation.association import associate
from multicam_ego_motion.evaluation.metrics import DEFAULT_RPE_DISTANCES_M, compute_metrics
from multicam_ego_motion.evaluation.trajectory_io import Trajectory, load_trajectory, save_tum

SUMMARY_ROWS = [  # (key, label, format) of the printed table and the report
    ('poses', 'associated poses', '{:d}'),
    ('path_length_m', 'path length [m]', '{:.3f}'),
    ('ate_rmse_m', 'ATE RMSE, aligned on first pose [m]', '{:.4f}'),
    ('ate_pct', 'ATE RMSE, aligned on first pose [% of path]', '{:.3f}'),
    ('ate_se3_rmse_m', 'ATE RMSE after SE(3) fit [m]', '{:.4f}'),
    ('ate_sim3_rmse_m', 'ATE RMSE after Sim(3) fit [m]', '{:.4f}'),
    ('scale_error_pct', 'scale error [%]', '{:+.3f}'),
    ('final_drift_pct', 'final drift [% of path]', '{:.3f}'),
    ('rotation_drift_deg_per_m', 'rotation drift [deg/m]', '{:.4f}'),
    ('rpe_trans_pct', 'RPE translation, mean over distances [%]', '{:.3f}'),
    ('rpe_rot_deg_per_m', 'RPE rotation, mean over distances [deg/m]', '{:.4f}'),
]


def evaluate_trajectories(ref: Trajectory, est: Trajectory, max_time_diff: float = 0.01,
                          rpe_distances=DEFAULT_RPE_DISTANCES_M, out_dir=None) -> dict:
    """Associate, compute the metrics; with out_dir also write the report and figures."""
    ref, est = associate(ref, est, max_time_diff)
    ref_poses, est_poses = ref.poses(), est.poses()
    metrics = compute_metrics(ref_poses, est_poses, rpe_distances)
    moved = np.flatnonzero(np.linalg.norm(est_poses[:, :3, 3] - est_poses[0, :3, 3], axis=1) > 0.01)
    metrics['first_odometry_s'] = (float(est.stamps[moved[0]] - est.stamps[0]) if len(moved)
                                   else float('nan'))
    if out_dir is not None:
        write_report(Path(out_dir), ref, est, metrics)
    return metrics


def summary_rows(metrics: dict):
    rows = [(label, fmt.format(metrics[key])) for key, label, fmt in SUMMARY_ROWS]
    for key in metrics:  # per-distance RPE, in the order computed
        if key.endswith('m_trans_pct') and key != 'rpe_trans_pct':
            d = key[len('rpe_'):-len('m_trans_pct')]
            rows.append((f'RPE over {d} m: translation [%] / rotation [deg/m]',
                         f'{metrics[key]:.3f} / {metrics[f"rpe_{d}m_rot_deg_per_m"]:.4f}'))
    return rows


def write_report(out_dir: Path, ref: Trajectory, est: Trajectory, metrics: dict):
    from multicam_ego_motion.evaluation.plots import plot_error_over_distance, plot_trajectory
    out_dir.mkdir(parents=True, exist_ok=True)
    ref_poses = ref.poses()
    aligned = align_origin(est.poses(), ref_poses)
    plot_trajectory(ref_poses, aligned, out_dir / 'trajectory.png')
    plot_error_over_distance(ref_poses, aligned, out_dir / 'error_over_distance.png')
    save_tum(ref, out_dir / 'reference.tum')
    save_tum(est, out_dir / 'estimate.tum')
    lines = ['# Ego-motion evaluation', '',
             'Metric definitions: `multicam_ego_motion/evaluation/metrics.py`.', '',
             '| metric | value |', '|---|---|']
    lines += [f'| {label} | {value} |' for label, value in summary_rows(metrics)]
    lines += ['', '## Trajectory (top view, aligned on the first pose)', '',
              '![trajectory](trajectory.png)', '',
              '## Position error over travelled distance', '',
              '![error over distance](error_over_distance.png)', '']
    (out_dir / 'report.md').write_text('\n'.join(lines))


def configure_parser(parser):
    parser.add_argument('--reference', required=True, help='TUM file, BAG:/topic or BAG')
    parser.add_argument('--estimate', required=True, help='TUM file, BAG:/topic or BAG')
    parser.add_argument('--reference-topic', help='topic of the reference in its bag')
    parser.add_argument('--estimate-topic', help='topic of the estimate in its bag')
    parser.add_argument('--out', required=True, help='folder for report.md, figures, TUM files')
    parser.add_argument('--max-time-diff', type=float, default=0.01, metavar='S',
                        help='largest stamp difference of an associated pair (default 0.01 s)')
    parser.add_argument('--rpe-distances', type=float, nargs='+',
                        default=list(DEFAULT_RPE_DISTANCES_M), metavar='M',
                        help='RPE segment lengths in metres (those longer than the path are skipped)')


def run(args) -> int:
    ref = load_trajectory(args.reference, args.reference_topic)
    est = load_trajectory(args.estimate, args.estimate_topic)
    metrics = evaluate_trajectories(ref, est, args.max_time_diff, args.rpe_distances,
                                    out_dir=args.out)
    width = max(len(label) for label, _ in summary_rows(metrics))
    for label, value in summary_rows(metrics):
        print(f'{label:<{width}}  {value}')
    print(f'report: {Path(args.out) / "report.md"}', file=sys.stderr)
    return 0
