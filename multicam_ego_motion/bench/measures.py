"""What `ego-motion bench` measures on one run of the graph.

`graph_run` runs the graph over a bag recording only what the bench reads (/odom and
/diagnostics); the functions below turn a run into figures: the rate-mode real-time factor,
latency and drops (`rate_figures`), the track CPU per tracked point from /diagnostics
(`track_cost`), the accuracy against the bag's ground truth (`score_run`) and how far
two such scores are apart (`relative_difference`). The computations take plain values, so a
test can feed them small inputs.
"""
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np

GROUND_TRUTH_TOPIC = '/ground_truth/odom'


def graph_run(bag, out: Path, rig, rig_file, params, workers: int, lockstep: bool, duration=None):
    """One run of the graph at rate 1.0 (or lockstep) without rebalancing: (run, frames
    published, wall s per frame from the first frame published to the last /odom)."""
    from multicam_ego_motion.replay import run_graph
    print(f'bench: graph on {Path(bag).name}, M = {workers}, {"lockstep" if lockstep else "rate 1.0"} ...',
          flush=True)
    g = run_graph(bag, out, rig, rig_file, params, workers, lockstep=lockstep, rate=1.0,
                  duration=duration, rebalance=False, logger=None,
                  # The bench times the graph, not the recorder: record only what it reads.
                  record_topics=['/odom', '/diagnostics'])
    frames = len(g.playback.published_at)
    return g, frames, g.frames_wall_s / max(frames, 1)


def sequential_run(bag, rig, params, n_frames) -> Tuple[float, float]:
    """One run of the sequential pipeline over the bag's first n_frames: (wall, CPU) ms per frame.
    OpenCV on one thread, as in the paper (and as in each worker)."""
    import time

    import cv2

    from multicam_ego_motion.params_file import camera_fusion_params_from, fusion_params_from, quarter_params_from
    from multicam_ego_motion.sequential_pipeline import run_sequential
    print(f'bench: sequential baseline ({n_frames} frames) ...', flush=True)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        seq = run_sequential(bag, rig, quarter_params_from(params), fusion_params_from(params),
                             max_frames=n_frames, camera_fusion_params=camera_fusion_params_from(params))
    finally:
        cv2.setNumThreads(threads)
    n = max(len(seq.fused), 1)
    return (time.perf_counter() - t0) / n * 1e3, (time.process_time() - c0) / n * 1e3


def bag_window(bag, duration=None) -> Tuple[int, float]:
    """(trigger frames, bag seconds) of the window the player plays; the seconds count one
    period past the last frame, so frames / seconds is the bag's rate."""
    from multicam_ego_motion.bag.player import BagPlayer, PlayOptions
    stamps = [f.log_time_ns for f in BagPlayer(bag, PlayOptions(lockstep=True, duration_s=duration)).frames()
              if f.is_trigger]
    if not stamps:
        return 0, 0.0
    period = (stamps[1] - stamps[0]) / 1e9 if len(stamps) > 1 else 0.0
    return len(stamps), (stamps[-1] - stamps[0]) / 1e9 + period


@dataclass
class RateFigures:
    """A rate-mode run: frames published, latency of each frame that got its /odom."""
    frames: int
    rtf: float
    latencies_ms: List[float] = field(default_factory=list)

    @property
    def dropped(self) -> int:
        return self.frames - len(self.latencies_ms)

    def percentile(self, q) -> float:
        return float(np.percentile(self.latencies_ms, q)) if self.latencies_ms else float('nan')

    @property
    def p50(self) -> float:
        return self.percentile(50)

    @property
    def p99(self) -> float:
        return self.percentile(99)


def rate_figures(published_at: Dict[int, float], odom_received: Dict[int, float], bag_s: float,
                 n_frames: int) -> RateFigures:
    """Latency from the player publishing a frame to its /odom arriving (monotonic s, keyed
    by stamp); real-time factor over the frames: bag seconds over the wall time from the first
    frame's publish to the last /odom, plus one period as bag_s counts one (the player's
    pre-roll is not processing, and a graph that falls behind delivers its last /odom late)."""
    lat = [(odom_received[s] - t) * 1e3 for s, t in published_at.items() if s in odom_received]
    done = [odom_received[s] for s in published_at if s in odom_received]
    wall = (max(done) - min(published_at.values()) + bag_s / max(n_frames, 1)) if done else float('nan')
    rtf = bag_s / wall if wall > 0 else float('nan')
    return RateFigures(len(published_at), rtf, lat)


def write_latency_csv(path: Path, published_at: Dict[int, float], odom_received: Dict[int, float]):
    """Per frame, for finding which frames make the p99 (start-up, a snapshot, a host hiccup)."""
    with open(path, 'w') as f:
        f.write('stamp_ns,latency_ms\n')
        for s_ns, t in sorted(published_at.items()):
            if s_ns in odom_received:
                f.write(f'{s_ns},{(odom_received[s_ns] - t) * 1e3:.3f}\n')


def read_statuses(output_bag) -> List[Tuple[str, Dict[str, str]]]:
    """Every DiagnosticStatus recorded on /diagnostics: (name, {key: value})."""
    from rosbags.highlevel import AnyReader
    out = []
    with AnyReader([Path(output_bag)]) as reader:
        conns = [c for c in reader.connections if c.topic == '/diagnostics']
        for c, _, raw in reader.messages(connections=conns):
            for st in reader.deserialize(raw, c.msgtype).status:
                out.append((st.name, {kv.key: kv.value for kv in st.values}))
    return out


def is_quarter(name: str) -> bool:
    """ego_motion/<camera>/q<l>: a quarter node's status."""
    parts = name.split('/')
    return len(parts) == 3 and parts[0] == 'ego_motion' and parts[2][:1] == 'q' and parts[2][1:].isdigit()


@dataclass
class TrackCost:
    track_ms: float        # the quarters' track_ms, summed over quarters and frames
    points: int            # their `features` (tracked points), summed the same way
    reports: int           # quarter statuses that had both

    @property
    def us_per_point(self) -> float:
        return self.track_ms * 1e3 / self.points if self.points else float('nan')

    @property
    def points_per_report(self) -> float:
        return self.points / self.reports if self.reports else float('nan')


def track_cost(statuses: Iterable[Tuple[str, Dict[str, str]]]) -> TrackCost:
    """Track CPU per tracked point from the quarters' /diagnostics (track_ms, features)."""
    track_ms, points, reports = 0.0, 0, 0
    for name, values in statuses:
        if is_quarter(name) and 'track_ms' in values and 'features' in values:
            track_ms += float(values['track_ms'])
            points += int(values['features'])
            reports += 1
    return TrackCost(track_ms, points, reports)


def score_run(run_out: Path, bag, gt_topic: str = GROUND_TRUTH_TOPIC) -> dict:
    """The run's recorded /odom against the bag's ground truth (also writes run_out/odometry.tum)."""
    from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories
    from multicam_ego_motion.evaluation.trajectory_io import read_bag_topic, save_tum
    est = read_bag_topic(Path(run_out) / 'output', '/odom')
    save_tum(est, Path(run_out) / 'odometry.tum')
    metrics = evaluate_trajectories(read_bag_topic(bag, gt_topic), est)
    metrics['odom_poses'] = len(est)
    return metrics


def relative_difference(live: float, offline: float) -> float:
    """|live - offline| / |offline| (NaN when offline is 0 or either is not a number)."""
    if not (math.isfinite(live) and math.isfinite(offline)) or offline == 0:
        return float('nan')
    return abs(live - offline) / abs(offline)


def per_frame_ms(seconds: float, frames: int, per: Optional[int] = None) -> float:
    """seconds / frames in ms, and further / per (e.g. per image: per = cameras)."""
    return seconds / max(frames, 1) / (per or 1) * 1e3
