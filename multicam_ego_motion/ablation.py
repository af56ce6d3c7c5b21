"""`ego-motion ablation BAG`: does fusion help? The same estimator (the sequential pipeline,
which reproduces the graph's odometry) on the whole rig, on each camera alone and on each
single quarter alone, every one scored against the bag's ground truth, with its CPU per
frame (the estimation's process CPU, OpenCV on one thread, not reading the bag). Prints one
table (markdown) and writes it to OUT/ablation.md.

The single-camera and single-quarter runs keep the rest of the estimator (general arbiter,
wheel prior when the bag has one): they answer "what if this were the only camera / quarter".
"""
from dataclasses import replace
from pathlib import Path

from multicam_ego_motion.errors import UserError

COLUMNS = (('ate_pct', 'ATE % path', '{:.2f}'), ('final_drift_pct', 'final drift %', '{:.2f}'),
           ('rotation_drift_deg_per_m', 'rot drift deg/m', '{:.3f}'),
           ('scale_error_pct', 'scale err %', '{:+.2f}'),
           ('cpu_ms_per_frame', 'CPU ms/frame', '{:.1f}'))


def configure_parser(p):
    p.add_argument('bag', help='rosbag2 MCAP bag (folder) with /ground_truth/odom')
    p.add_argument('--out', required=True, help='output folder (ablation.md)')
    p.add_argument('--rig', help='rig YAML (default: from the bag\'s /tf_static or rig.yaml)')
    p.add_argument('--params', help='ROS params file (default: the package\'s config/params.yaml)')
    p.add_argument('--no-quarters', action='store_true', help='skip the 4 x N single-quarter runs')
    p.add_argument('--ground-truth-topic', default='/ground_truth/odom')


def score(bag, fused, gt_topic) -> dict:
    from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories
    from multicam_ego_motion.evaluation.trajectory_io import Trajectory, load_trajectory
    est = Trajectory.from_poses([f.stamp_ns / 1e9 for f in fused], [f.T_odom_base for f in fused])
    return evaluate_trajectories(load_trajectory(f'{bag}:{gt_topic}'), est)


def row(label, m) -> str:
    return '| ' + label + ' | ' + ' | '.join(fmt.format(m[k]) for k, _, fmt in COLUMNS) + ' |'


def summary_lines(label, rows):
    """Best and worst of a group of runs by final drift."""
    ranked = sorted(rows, key=lambda r: r[1]['final_drift_pct'])
    return [row(f'{label}: best ({ranked[0][0]})', ranked[0][1]),
            row(f'{label}: worst ({ranked[-1][0]})', ranked[-1][1])]


def run(args) -> int:
    import cv2
    import numpy as np
    from tqdm import tqdm

    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.params_file import camera_fusion_params_from, fusion_params_from, quarter_params_from
    from multicam_ego_motion.ros_plumbing.package_share import default_params
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.sequential_pipeline import run_sequential

    reader = Rosbag2Reader(args.bag)
    if args.ground_truth_topic not in reader.topics:
        raise UserError(f'bag {args.bag} has no {args.ground_truth_topic}: nothing to score against')
    rig, _ = resolve_rig(reader, args.rig)
    params_file = Path(args.params) if args.params else default_params()
    qp = quarter_params_from(params_file)
    fp = fusion_params_from(params_file)
    cp = camera_fusion_params_from(params_file)
    present = [c for c in rig.cameras if c.input_topic in reader.topics]
    runs = [('fused (whole rig)', rig, (1, 2, 3, 4))]
    runs += [(c.name, replace(rig, cameras=[c]), (1, 2, 3, 4)) for c in present]
    if not args.no_quarters:
        runs += [(f'{c.name}/q{q}', replace(rig, cameras=[c]), (q,)) for c in present for q in range(1, 5)]
    results = {}
    cv2.setNumThreads(1)        # the CPU per frame as one worker spends it
    for label, sub_rig, quarters in tqdm(runs, desc='ablation', unit='run'):
        res = run_sequential(args.bag, sub_rig, qp, fp, quarters=quarters, camera_fusion_params=cp)
        results[label] = score(args.bag, res.fused, args.ground_truth_topic)
        results[label]['cpu_ms_per_frame'] = float(np.mean(res.frame_cpu_ms))
    head = '| configuration | ' + ' | '.join(t for _, t, _ in COLUMNS) + ' |'
    lines = [f'Ablation on {args.bag} ({len(present)} cameras):', '', head,
             '|---|' + '---:|' * len(COLUMNS), row('fused (whole rig)', results['fused (whole rig)'])]
    lines += summary_lines('single camera', [(c.name, results[c.name]) for c in present])
    if not args.no_quarters:
        lines += summary_lines('single quarter', [(k, v) for k, v in results.items() if '/q' in k])
    lines += ['', 'every run:', '', head, '|---|' + '---:|' * len(COLUMNS)]
    lines += [row(k, v) for k, v in results.items()]
    text = '\n'.join(lines) + '\n'
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'ablation.md').write_text(text)
    print(text, end='')
    return 0
