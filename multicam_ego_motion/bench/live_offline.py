"""Accuracy live equals accuracy offline, a part of `ego-motion bench`.

On the VGA bags at 10, 15 and 30 Hz (camera_rate.vga_bag), the graph on M = 2 in lockstep
(offline: every frame, in order) and in rate mode (live: at the bag's rate, frames the graph
cannot keep up with are dropped), both scored against the bag's ground truth: ATE and final
drift of each, and how far live is from offline relative to offline.
"""
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Tuple

from multicam_ego_motion.bench.camera_rate import WORKERS, vga_bag
from multicam_ego_motion.bench.measures import graph_run, per_frame_ms, relative_difference, score_run

RATES_HZ = (10.0, 15.0, 30.0)


@dataclass
class LiveOffline:
    lines: list
    relative: Dict[float, Tuple[float, float]]     # rate -> (ATE, final drift) live vs offline
    lockstep_runs: Dict[float, Path]               # rate -> the offline run's folder


def run_dir(out: Path, rate_hz: float, lockstep: bool) -> Path:
    return out / f'vga{rate_hz:g}hz_{"lockstep" if lockstep else "rate"}_m{WORKERS}'


def live_vs_offline(bags_folder: Path, out: Path, params,
                    live_runs: Dict[float, Tuple[Path, float]] = None) -> LiveOffline:
    """live_runs: rate-mode runs already made, not run again: rate -> (folder, graph CPU per
    image [ms])."""
    from tqdm import tqdm

    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.replay import resolve_rig

    live_runs = dict(live_runs or {})
    bags = {r: vga_bag(bags_folder, r) for r in RATES_HZ}      # generated first: their own progress
    runs = {(r, False): live_runs[r] for r in RATES_HZ if r in live_runs}
    jobs = [(r, lockstep) for r in RATES_HZ for lockstep in (True, False) if (r, lockstep) not in runs]
    for rate, lockstep in tqdm(jobs, desc='bench: live vs offline', unit='run'):
        bag = bags[rate][0]
        rig, rig_file = resolve_rig(Rosbag2Reader(bag), None)
        folder = run_dir(out, rate, lockstep)
        g, frames, _ = graph_run(bag, folder, rig, rig_file, params, WORKERS, lockstep)
        runs[(rate, lockstep)] = folder, per_frame_ms(g.cpu_workers_s, frames, len(rig.cameras))
    print('bench: scoring live and offline runs ...', flush=True)
    lines = [f'| VGA bag, M = {WORKERS} | ATE offline [%] | ATE live [%] | ATE apart | '
             'final drift offline [%] | final drift live [%] | final drift apart | /odom poses offline / live '
             '| graph CPU per image offline / live [ms] |',
             '|---|---:|---:|---:|---:|---:|---:|---:|---:|']
    relative = {}
    for rate in RATES_HZ:
        bag, how = bags[rate]
        off, live = (score_run(runs[(rate, lockstep)][0], bag) for lockstep in (True, False))
        rel = tuple(relative_difference(live[k], off[k]) for k in ('ate_pct', 'final_drift_pct'))
        relative[rate] = rel
        lines.append(f'| {rate:g} Hz ({how}) | {off["ate_pct"]:.3f} | {live["ate_pct"]:.3f} | {100 * rel[0]:.1f} % '
                     f'| {off["final_drift_pct"]:.3f} | {live["final_drift_pct"]:.3f} | {100 * rel[1]:.1f} % '
                     f'| {off["odom_poses"]} / {live["odom_poses"]} '
                     f'| {runs[(rate, True)][1]:.1f} / {runs[(rate, False)][1]:.1f} |')
    return LiveOffline(lines, relative, {r: runs[(r, True)][0] for r in RATES_HZ})
