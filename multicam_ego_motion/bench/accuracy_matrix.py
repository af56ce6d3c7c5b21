"""`ego-motion matrix --bags DIR --out DIR`: the accuracy matrix a change to the estimator is
judged by (seeds x scenarios, the default bag's settings: 20 s at 8 Hz, 320 x 240, fx = 200).

Bags are generated into DIR on first use and reused (deterministic for the seed). Each runs
through the sequential pipeline, which gives the lockstep graph's odometry bit for bit, and
is scored against its ground truth. Prints one table (markdown) with the mean and worst final
drift, and writes it to OUT/matrix.md. `--params` scores another params file, `--set
key=value` a single quarter-parameter change, `--imu-rate 200` the same scenes with an IMU.
"""
from pathlib import Path

from multicam_ego_motion.errors import UserError

SCENARIOS = ('loop', 'corridor', 'spin_then_drive', 'lighting')
SEEDS = (7, 8)
BAG_SETTINGS = {'duration': 20, 'rate': 8, 'width': 320, 'height': 240, 'fx': 200}
COLUMNS = (('ate_pct', 'ATE % path', '{:.3f}'), ('final_drift_pct', 'final drift %', '{:.3f}'),
           ('rotation_drift_deg_per_m', 'rot drift deg/m', '{:.4f}'),
           ('scale_error_pct', 'scale err %', '{:+.3f}'), ('cpu_ms', 'CPU ms/frame', '{:.1f}'))


def configure_parser(p):
    p.add_argument('--bags', required=True, help='folder of the matrix bags (generated when missing)')
    p.add_argument('--out', required=True, help='output folder (matrix.md)')
    p.add_argument('--params', help="ROS params file (default: the package's config/params.yaml)")
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='override a quarter parameter (repeatable)')
    p.add_argument('--seeds', type=int, nargs='+', default=list(SEEDS))
    p.add_argument('--scenarios', nargs='+', default=list(SCENARIOS), choices=SCENARIOS)
    p.add_argument('--imu-rate', type=float, default=0.0, metavar='HZ',
                   help='the bags with an IMU at this rate (generate --imu-rate; their own folder '
                        'names), fused by the general arbiter; default 0: without')


def ensure_bag(folder: Path, scenario: str, seed: int, imu_rate: float = 0.0) -> Path:
    # (the same scene with an IMU: the images and the wheel are the bag without one's)
    bag = folder / (f'{scenario}_s{seed}' + (f'_imu{imu_rate:g}' if imu_rate > 0 else ''))
    if not (bag / 'metadata.yaml').exists():
        from multicam_ego_motion.scenarios.generator import generate
        s = BAG_SETTINGS
        generate(scenario, str(bag), seed, s['duration'], s['rate'], s['width'], s['height'],
                 s['fx'], 0.0, 4, None, 'zstd', imu_rate=imu_rate)
    return bag


def parse_overrides(items) -> dict:
    import yaml
    from camera_pose_nodes.quarter_estimator import PARAMETERS
    out = {}
    for item in items:
        key, sep, value = item.partition('=')
        if not sep or key not in PARAMETERS:
            raise UserError(f'--set {item!r}: expected KEY=VALUE with KEY a quarter parameter')
        out[key] = yaml.safe_load(value)
    return out


def run(args) -> int:
    import time

    from tqdm import tqdm

    from multicam_ego_motion.ablation import score
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.params_file import camera_fusion_params_from, fusion_params_from, quarter_params_from
    from multicam_ego_motion.ros_plumbing.package_share import default_params
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.sequential_pipeline import run_sequential

    import cv2
    cv2.setNumThreads(1)        # CPU per frame as one worker sees it
    params_file = Path(args.params) if args.params else default_params()
    qp = {**quarter_params_from(params_file), **parse_overrides(args.set)}
    fp = fusion_params_from(params_file)
    if args.imu_rate > 0:
        fp['use_imu'] = True          # (the IMU is opt-in: the bags have one to fuse)
    folder = Path(args.bags)
    folder.mkdir(parents=True, exist_ok=True)
    cells = [(sc, seed) for seed in args.seeds for sc in args.scenarios]
    results = {}
    for scenario, seed in tqdm(cells, desc='matrix', unit='run'):
        bag = ensure_bag(folder, scenario, seed, args.imu_rate)
        rig, _ = resolve_rig(Rosbag2Reader(bag), None)
        c0 = time.process_time()
        res = run_sequential(bag, rig, qp, fp, camera_fusion_params=camera_fusion_params_from(params_file))
        m = score(bag, res.fused, '/ground_truth/odom')
        m['cpu_ms'] = (time.process_time() - c0) / max(len(res.fused), 1) * 1e3
        results[f'{scenario} s{seed}'] = m
    head = '| run | ' + ' | '.join(t for _, t, _ in COLUMNS) + ' |'
    lines = [head, '|---|' + '---:|' * len(COLUMNS)]
    lines += ['| ' + k + ' | ' + ' | '.join(f.format(m[c]) for c, _, f in COLUMNS) + ' |'
              for k, m in results.items()]
    drifts = [m['final_drift_pct'] for m in results.values()]
    worst = max(results, key=lambda k: results[k]['final_drift_pct'])
    lines += ['', f'mean final drift {sum(drifts) / len(drifts):.3f} %, worst {worst} '
                  f'{results[worst]["final_drift_pct"]:.3f} %'
                  + (f'; overrides {parse_overrides(args.set)}' if args.set else '')
                  + (f'; with an IMU at {args.imu_rate:g} Hz' if args.imu_rate > 0 else '')]
    text = '\n'.join(lines) + '\n'
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'matrix.md').write_text(text)
    print(text, end='')
    return 0
