"""The bench's transport-floor rows: what the graph costs when its quarters do no work.

A measurement, never a configuration. With `EGO_MOTION_NULL_ESTIMATOR=1` in the environment
every quarter estimator, in the sequential pipeline and in every worker alike (`install`,
called by the worker at start-up), answers each image at once with a constant estimate: no
tracking, no filter, no landmarks. The nodes, their messages, /diagnostics, state snapshots,
the player, recorder and coordinator all run as usual, and so do the arbiters' fusion and the
message conversions, which the sequential pipeline does too. What the graph at M = 2 then costs
over the sequential pipeline is the transport's floor for this graph's shape: no change to the
estimator can take the graph below it.

A speedup S at M = 2 needs the graph's transport (its CPU per frame over the sequential
pipeline's, player and recorder included) at most Ts (2 / S - 1): for the paper's 1.8, a
ninth of the sequential time per frame. The rows print the floor, the speedup it leaves the
measured pipeline, and the sequential time per frame that 1.8 would need over it.

The runs go into a child process (`python -m multicam_ego_motion.bench.transport_floor`), so
the bench's own runs never see the null estimator.
"""
import argparse
import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

ENV = 'EGO_MOTION_NULL_ESTIMATOR'
PAPER_SPEEDUP = 1.8


def install():
    """Make every QuarterEstimator of this process do no work (module docstring)."""
    import numpy as np
    from camera_pose_nodes import quarter_estimator as qe
    from camera_pose_nodes.pose_estimate import PoseEstimate

    def process_image(self, stamp_ns, gray):
        # (its own stamps: the node still applies only the fused poses of frames it took)
        self.own_stamps = self.own_stamps[-(qe.OWN_STAMPS_KEPT - 1):] + [int(stamp_ns)]
        return PoseEstimate(int(stamp_ns), np.eye(4), np.eye(6) * 1e-4, source=self.source,
                            state='tracking', stage_ms=dict.fromkeys(qe.STAGES, 0.0))

    cls = qe.QuarterEstimator
    cls.process_image = process_image
    cls.apply_fused_pose = lambda self, *a, **k: 0.0
    cls.extraction_due = lambda self: False
    cls.extract_pending = lambda self: None
    cls.prefetch = lambda self, *a, **k: None
    cls.prefetched = lambda self, stamp_ns: False


def installed_from_environment() -> bool:
    """Install when the environment asks for it (a worker's start-up)."""
    if os.environ.get(ENV):
        install()
        return True
    return False


@dataclass
class FloorRuns:
    seq_cpu_ms: List[float]                   # sequential pipeline, CPU per frame: before, between
                                              # and after the graph's runs (one more than those)
    graph_cpu_ms: List[Tuple[float, float]]   # M = 2 lockstep: (workers, player...) per frame
    frames: int

    @property
    def floors_ms(self) -> List[float]:
        """Each graph run's CPU per frame over the sequential runs just before and after it
        (their mean: the host's speed drifts within minutes)."""
        s = self.seq_cpu_ms
        return [w + r - (s[i] + s[i + 1]) / 2 for i, (w, r) in enumerate(self.graph_cpu_ms)]

    @property
    def floor_ms(self) -> float:
        """The lowest of them: a floor, so the cheapest run is the one that bounds."""
        return min(self.floors_ms)

    def allowed_speedup(self, Ts_ms: float) -> float:
        """The speedup at M = 2 that the floor alone leaves a pipeline of Ts ms per frame."""
        return 2 * Ts_ms / (Ts_ms + self.floor_ms) if Ts_ms + self.floor_ms > 0 else float('nan')

    def lines(self, Ts_ms: float) -> List[str]:
        """The bench's rows, against the real pipeline's Ts (ms per frame)."""
        f, allowed = self.floor_ms, self.allowed_speedup(Ts_ms)
        k = self.floors_ms.index(f)
        w, r = self.graph_cpu_ms[k]
        return ['| transport floor: M = 2, lockstep, the quarters doing no work (' + ENV + ') | value |',
                '|---|---:|',
                f'| sequential pipeline, CPU per frame [ms] | {(self.seq_cpu_ms[k] + self.seq_cpu_ms[k + 1]) / 2:.1f} |',
                f'| graph at M = 2, CPU per frame: workers + player, recorder, coordinator [ms] '
                f'| {w:.1f} + {r:.1f} |',
                f'| the floor: graph over sequential [ms] | {f:.1f} |',
                f'| speedup at M = 2 the floor alone leaves the pipeline (Ts {Ts_ms:.1f} ms) '
                f'| {allowed:.2f} |',
                f'| transport a speedup of {PAPER_SPEEDUP} allows this pipeline: Ts (2 / {PAPER_SPEEDUP} - 1) [ms] '
                f'| {Ts_ms * (2 / PAPER_SPEEDUP - 1):.1f} |',
                f'| sequential time per frame that a speedup of {PAPER_SPEEDUP} needs at least over this floor: '
                f'floor / (2 / {PAPER_SPEEDUP} - 1) [ms] | {f / (2 / PAPER_SPEEDUP - 1):.0f} |',
                f'(The graph ran {len(self.graph_cpu_ms)} times over {self.frames} frames, each against the '
                'sequential runs just before and after it: floors '
                + ' / '.join(f'{x:.1f}' for x in self.floors_ms) + ' ms; the lowest counts. Minutes '
                'apart from the rows above, so on this host\'s drifting speed the two can differ by '
                'a millisecond or two either way.)']


def transport_floor(bag, out: Path, rig_file, params, duration: Optional[float] = None,
                    runs: int = 3) -> FloorRuns:
    """Run the sequential pipeline and the graph (M = 2, lockstep) with the null estimator in
    a child process; raises RuntimeError with its output when it fails."""
    out = Path(out)
    cmd = [sys.executable, '-m', 'multicam_ego_motion.bench.transport_floor', str(bag),
           '--out', str(out), '--rig', str(rig_file), '--params', str(params), '--runs', str(runs)]
    if duration:
        cmd += ['--duration', str(duration)]
    print(f'bench: transport floor (the quarters doing no work), {runs} graph runs ...', flush=True)
    p = subprocess.run(cmd, env=dict(os.environ, **{ENV: '1'}), capture_output=True, text=True)
    result = next((l for l in reversed(p.stdout.splitlines()) if l.startswith('{')), None)
    if p.returncode != 0 or result is None:
        raise RuntimeError(f'transport floor run failed (exit {p.returncode}):\n{p.stdout[-2000:]}{p.stderr[-3000:]}')
    d = json.loads(result)
    return FloorRuns(d['seq_cpu_ms'], [tuple(x) for x in d['graph_cpu_ms']], d['frames'])


def _measure(args) -> dict:
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.bench.measures import bag_window, graph_run, per_frame_ms, sequential_run
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.ros_plumbing import dds_transport, ros_domain

    if not installed_from_environment():
        raise SystemExit(f'{ENV}=1 must be set: the workers install the null estimator from it')
    ros_domain.isolate()
    dds_transport.use_graph_profile()
    out = Path(args.out)
    rig, rig_file = resolve_rig(Rosbag2Reader(args.bag), args.rig)
    n_frames, _ = bag_window(args.bag, args.duration)

    def sequential():
        return sequential_run(args.bag, rig, args.params, n_frames)[1]

    seq, graph, frames = [sequential()], [], 0
    for i in range(args.runs):        # each graph run between two sequential ones
        g, frames, _ = graph_run(args.bag, out / f'graph{i}', rig, rig_file, args.params, 2, True, args.duration)
        graph.append((per_frame_ms(g.cpu_workers_s, frames), per_frame_ms(g.cpu_replay_s, frames)))
        seq.append(sequential())
    return {'seq_cpu_ms': seq, 'graph_cpu_ms': graph, 'frames': frames}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('bag')
    ap.add_argument('--out', required=True)
    ap.add_argument('--rig', required=True, help='rig YAML (the bench\'s)')
    ap.add_argument('--params', required=True)
    ap.add_argument('--duration', type=float)
    ap.add_argument('--runs', type=int, default=3, help='graph runs (each between two sequential ones)')
    print(json.dumps(_measure(ap.parse_args(argv))), flush=True)


if __name__ == '__main__':
    main()
