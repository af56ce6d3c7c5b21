"""The camera-rate part of `ego-motion bench`: four 640x480 cameras at 30, 15 and 10 Hz in
rate mode.

The VGA bags (loop, seed 7, 10 s, fx = 400) are generated on demand into a cache folder and
reused: they are too large to commit (about as many MB as frames). `vga_bag` makes or finds
one; `camera_rate` replays each rate's in rate mode on M = 2 and makes their table. At 15 and
10 Hz the motion between frames is two and three times that at 30 Hz: more pyramid levels'
worth of flow, shorter tracks, more extraction (docs/performance.md).

Cores needed: the graph's and the player's CPU per frame times the camera rate. Machines
differ by 2x, so it is also given at the reference speed of LK_REFERENCE_US per
Lucas-Kanade point (machine_speed), scaled by this machine's.
"""
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from multicam_ego_motion.bench.measures import (RateFigures, bag_window, graph_run, per_frame_ms,
                                                rate_figures, write_latency_csv)

VGA = dict(scenario='loop', seed=7, duration=10.0, width=640, height=480, fx=400.0)
CAMERA_RATE_HZ = 30.0            # the row the 30 Hz targets and live vs offline reuse
CAMERA_RATES_HZ = (30.0, 15.0, 10.0)
WORKERS = 2
LK_REFERENCE_US = 6.0            # the machine the cores-needed target is meant for


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


def cores_needed(cpu_per_frame_ms: float, rate_hz: float) -> float:
    return cpu_per_frame_ms * rate_hz / 1000.0


@dataclass
class RateRun:
    figures: RateFigures
    run_dir: Path          # the rate-mode run (its /odom is the live side)
    bag: Path
    how: str               # 'reused' or 'generated in N s'
    n_frames: int
    bag_s: float
    cpu_per_image_ms: float     # the graph's (workers'), per image processed
    replay_cpu_per_image_ms: float   # player + recorder + coordinator, per image processed
    peak_rss_mb: float

    def cores(self, cameras: int, rate_hz: float) -> float:
        return cores_needed((self.cpu_per_image_ms + self.replay_cpu_per_image_ms) * cameras, rate_hz)


@dataclass
class CameraRate:
    lines: list
    runs: dict             # rate Hz -> RateRun
    cameras: int

    # the 30 Hz row, as the targets and live vs offline take it
    @property
    def figures(self) -> RateFigures:
        return self.runs[CAMERA_RATE_HZ].figures

    @property
    def run_dir(self) -> Path:
        return self.runs[CAMERA_RATE_HZ].run_dir

    @property
    def cpu_per_image_ms(self) -> float:
        return self.runs[CAMERA_RATE_HZ].cpu_per_image_ms

    def cores(self, rate_hz: float) -> float:
        return self.runs[rate_hz].cores(self.cameras, rate_hz)

    def cores_line(self, lk_us_per_point: float) -> str:
        """Beside the machine line: cores needed per rate, here and at the reference speed."""
        at = lambda r: self.cores(r) * LK_REFERENCE_US / lk_us_per_point
        return ('Cores needed, 4 x 640x480 (graph + player CPU per frame x rate): '
                + ', '.join(f'{r:g} Hz {self.cores(r):.2f}' for r in self.runs)
                + f'; at {LK_REFERENCE_US:g} us per Lucas-Kanade point: '
                + ', '.join(f'{r:g} Hz {at(r):.2f}' for r in self.runs))


def camera_rate(bags_folder: Path, out: Path, params, rates=CAMERA_RATES_HZ) -> CameraRate:
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.replay import resolve_rig

    runs, cams = {}, 4
    for rate in rates:
        bag, how = vga_bag(bags_folder, rate)
        rig, rig_file = resolve_rig(Rosbag2Reader(bag), None)
        cams = len(rig.cameras)
        n_frames, bag_s = bag_window(bag)
        run_dir = out / f'vga{rate:g}hz_rate_m{WORKERS}'
        g, _, _ = graph_run(bag, run_dir, rig, rig_file, params, WORKERS, lockstep=False)
        fig = rate_figures(g.playback.published_at, g.odom_received, bag_s, n_frames)
        write_latency_csv(run_dir / 'latency.csv', g.playback.published_at, g.odom_received)
        # per frame processed: frames the governor skipped cost nothing, and the cores
        # needed are what every frame would take
        done = max(1, fig.frames - fig.dropped)
        runs[rate] = RateRun(fig, run_dir, bag, how, n_frames, bag_s, per_frame_ms(g.cpu_workers_s, done, cams),
                             per_frame_ms(g.cpu_replay_s, done, cams), g.peak_rss_kb / 1024)
    head = ' | '.join(f'{r:g} Hz' for r in rates)
    row = lambda label, fmt: f'| {label} | ' + ' | '.join(fmt(r, runs[r]) for r in rates) + ' |'
    lines = [f'| camera rate: {cams} x {VGA["width"]}x{VGA["height"]}, {VGA["scenario"]} (turns), rate mode, '
             f'M = {WORKERS} | {head} |', '|---|' + '---:|' * len(rates),
             row('bag frames, s; MB', lambda r, x: f'{x.n_frames}, {x.bag_s:.1f}; {bag_size_mb(x.bag):.0f} ({x.how})'),
             row('real-time factor (bag s / wall s, first frame published -> last /odom)',
                 lambda r, x: f'{x.figures.rtf:.2f}'),
             row('dropped frames (no /odom)', lambda r, x: f'{x.figures.dropped} of {x.figures.frames}'),
             row('latency image -> /odom p50 / p99 [ms]',
                 lambda r, x: f'{x.figures.p50:.1f} / {x.figures.p99:.1f}'),
             row(f'CPU per image processed ({cams} per frame), graph [ms]', lambda r, x: f'{x.cpu_per_image_ms:.1f}'),
             row('CPU per image processed, player + recorder + coordinator [ms]',
                 lambda r, x: f'{x.replay_cpu_per_image_ms:.1f}'),
             row('cores needed (graph + player CPU per frame x rate)', lambda r, x: f'{x.cores(cams, r):.2f}'),
             row('peak memory, workers + coordinator [MB]', lambda r, x: f'{x.peak_rss_mb:.0f}')]
    return CameraRate(lines, runs, cams)
