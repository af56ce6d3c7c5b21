"""The camera-rate part of `ego-motion bench`: four 640x480 cameras at 30 Hz in rate mode.

The VGA bags (loop, seed 7, 10 s, fx = 400) are generated on demand into a cache folder and
reused: they are too large to commit (about as many MB as frames). `vga_bag` makes or finds
one; `camera_rate` replays the 30 Hz one in rate mode on M = 2 and makes its table.
"""
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from multicam_ego_motion.bench.measures import (RateFigures, bag_window, graph_run, per_frame_ms,
                                                rate_figures, write_latency_csv)

VGA = dict(scenario='loop', seed=7, duration=10.0, width=640, height=480, fx=400.0)
CAMERA_RATE_HZ = 30.0
WORKERS = 2


def bag_size_mb(bag: Path) -> float:
    return sum(f.stat().st_size for f in Path(bag).iterdir()) / 1e6


def vga_bag(folder: Path, rate_hz: float):
    """(bag, how it came: 'reused' or 'generated in N s'). Generated into .partial/NAME and
    moved when complete, so an interrupted generation is never taken for a bag (the bag's
    file is named after its folder: NAME_0.mcap)."""
    v = VGA
    bag = Path(folder) / f'vga{rate_hz:g}hz_{v["scenario"]}_s{v["seed"]}_{v["duration"]:g}s'
    if (bag / 'metadata.yaml').exists():
        return bag, 'reused'
    from multicam_ego_motion.scenarios.generator import generate
    partial = bag.parent / '.partial' / bag.name
    shutil.rmtree(partial, ignore_errors=True)
    partial.parent.mkdir(parents=True, exist_ok=True)
    print(f'bench: generating {bag} (4 x {v["width"]}x{v["height"]} at {rate_hz:g} Hz, '
          f'{v["duration"]:g} s) ...', flush=True)
    t0 = time.monotonic()
    generate(v['scenario'], str(partial), v['seed'], v['duration'], rate_hz, v['width'], v['height'],
             v['fx'], 0.0, 4, None, 'zstd')
    partial.rename(bag)
    try:
        partial.parent.rmdir()
    except OSError:          # another bag being generated beside
        pass
    return bag, f'generated in {time.monotonic() - t0:.0f} s'


@dataclass
class CameraRate:
    lines: list
    figures: RateFigures
    run_dir: Path          # the rate-mode run (its /odom is the live side at 30 Hz)
    bag: Path
    cpu_per_image_ms: float    # the graph's (workers')


def camera_rate(bags_folder: Path, out: Path, params) -> CameraRate:
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.replay import resolve_rig

    bag, how = vga_bag(bags_folder, CAMERA_RATE_HZ)
    rig, rig_file = resolve_rig(Rosbag2Reader(bag), None)
    n_frames, bag_s = bag_window(bag)
    run_dir = out / f'vga{CAMERA_RATE_HZ:g}hz_rate_m{WORKERS}'
    g, frames, _ = graph_run(bag, run_dir, rig, rig_file, params, WORKERS, lockstep=False)
    fig = rate_figures(g.playback.published_at, g.odom_received, bag_s, n_frames)
    write_latency_csv(run_dir / 'latency.csv', g.playback.published_at, g.odom_received)
    cams = len(rig.cameras)
    cpu_image = per_frame_ms(g.cpu_workers_s, frames, cams)
    lines = [f'| camera rate: {cams} x {VGA["width"]}x{VGA["height"]} at {CAMERA_RATE_HZ:g} Hz, '
             f'rate mode, M = {WORKERS} | value |', '|---|---:|',
             f'| bag ({n_frames} frames, {bag_s:.1f} s; {how}) [MB] | {bag_size_mb(bag):.0f} |',
             f'| real-time factor (bag s / wall s, first frame published -> last /odom) | {fig.rtf:.2f} |',
             f'| dropped frames (no /odom) | {fig.dropped} of {fig.frames} |',
             f'| latency image -> /odom p50 / p99 [ms] | {fig.p50:.1f} / {fig.p99:.1f} |',
             f'| CPU per image ({cams} per frame), graph [ms] | {cpu_image:.1f} |',
             f'| CPU per image, player + recorder + coordinator [ms] '
             f'| {per_frame_ms(g.cpu_replay_s, frames, cams):.1f} |',
             f'| peak memory, workers + coordinator [MB] | {g.peak_rss_kb / 1024:.0f} |']
    return CameraRate(lines, fig, run_dir, bag, cpu_image)
