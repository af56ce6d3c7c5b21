"""Free-running cameras, a part of `ego-motion bench`: the loop (10 s at 15 Hz, 320x240, fx
200, seed 7) synchronised, with the cameras capturing 0, 8, 16, 24 ms after the frame clock,
and with two cameras at 30 Hz and two at 15 Hz, each through the graph (M = 2) in lockstep
and in rate mode, scored against the bag's ground truth. Rate-mode accuracy depends on the
machine's load, so it is measured here, not asserted by a test. Rate mode plays at RATE_MODE
(half speed): at full speed two shared cores keep up with none of these rigs (the
synchronised one too lost two thirds of its frames), and the row would measure the load, not
the cameras' timing.
"""
import shutil
from pathlib import Path

from multicam_ego_motion.bench.camera_rate import WORKERS
from multicam_ego_motion.bench.measures import score_run

RATE_MODE = 0.5
LOOP = dict(scenario='loop', seed=7, duration=10.0, width=320, height=240, fx=200.0)
# name -> (frame rate, camera offsets ms, camera rates, sync window s)
RIGS = {'synchronised 15 Hz': (15.0, None, None, 0.0),
        'offsets 0/8/16/24 ms at 15 Hz': (15.0, [0, 8, 16, 24], None, 0.03),
        'rates 30/30/15/15 Hz': (30.0, None, [30, 30, 15, 15], 0.01)}


def rig_bag(folder: Path, name: str) -> Path:
    rate, offsets, rates, _ = RIGS[name]
    tag = name.split(' ')[0]
    bag = Path(folder) / f'free_running_{tag}_loop_s7_10s'
    if (bag / 'metadata.yaml').exists():
        return bag
    from multicam_ego_motion.scenarios.generator import generate
    partial = bag.parent / '.partial' / bag.name
    shutil.rmtree(partial, ignore_errors=True)
    partial.parent.mkdir(parents=True, exist_ok=True)
    generate(LOOP['scenario'], str(partial), LOOP['seed'], LOOP['duration'], rate, LOOP['width'],
             LOOP['height'], LOOP['fx'], progress=False, camera_offsets_ms=offsets, camera_rates=rates)
    partial.rename(bag)
    return bag


def sync_timeouts(run_out: Path) -> int:
    """Frames the general arbiter released on its sync timeout (its /diagnostics)."""
    from multicam_ego_motion.bench.measures import read_statuses
    return sum(1 for name, values in read_statuses(Path(run_out) / 'output')
               if name == 'ego_motion/general_arbiter' and values.get('sync_timed_out') == 'True')


def free_running(bags_folder: Path, out: Path, params) -> list:
    """The table's lines."""
    from tqdm import tqdm

    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.replay import resolve_rig, run_graph

    results = {}
    jobs = [(name, lockstep) for name in RIGS for lockstep in (True, False)]
    for name, lockstep in tqdm(jobs, desc='bench: free-running cameras', unit='run'):
        bag = rig_bag(bags_folder, name)
        rig, rig_file = resolve_rig(Rosbag2Reader(bag), None)
        folder = out / f'{bag.name}_{"lockstep" if lockstep else "rate"}_m{WORKERS}'
        shutil.rmtree(folder, ignore_errors=True)
        run_graph(bag, folder, rig, rig_file, params, WORKERS, lockstep=lockstep, rate=RATE_MODE,
                  rebalance=False, logger=None, record_topics=['/odom', '/diagnostics'],
                  sync_window_s=RIGS[name][3])
        m = score_run(folder, bag)
        results[(name, lockstep)] = (m['ate_pct'], m['final_drift_pct'], m['odom_poses'], sync_timeouts(folder))
    lines = [f'| free-running cameras, loop 10 s, M = {WORKERS} | mode | ATE [%] | final drift [%] '
             '| /odom poses | sync timeouts |', '|---|---|---:|---:|---:|---:|']
    for (name, lockstep), (ate, drift, poses, timeouts) in results.items():
        lines.append(f'| {name} | {"lockstep" if lockstep else f"rate {RATE_MODE:g}"} | {ate:.3f} | {drift:.3f} '
                     f'| {poses} | {timeouts} |')
    return lines
