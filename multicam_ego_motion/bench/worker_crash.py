"""The bench's crash row: the default bag in lockstep on M = 2 with the last worker killed
(SIGKILL) a third of the way in, as a crash would. How long until its nodes ran again on the
hot spare (restored from their last snapshots), the longest wait for /odom it caused, how many
frames the player had to publish again, and whether every frame still got its odometry from
the whole rig. A figure, never a test bound: on a loaded host the same restore took 3.3 s
instead of 0.7 s."""
from dataclasses import dataclass
from pathlib import Path
from typing import List

WORKERS = 2


@dataclass
class CrashFigures:
    frames: int
    odom: int
    restore_s: List[float]
    republished: int
    wall_ms_per_frame: float
    longest_gap_s: float = 0.0           # between two /odom, wall
    partial: int = 0                     # frames fused without some camera
    hosted_general: bool = False         # the killed worker hosted the general arbiter
    published_ahead: int = 0             # frames the player let out while an older one stalled

    def lines(self) -> List[str]:
        restore = ', '.join(f'{t:.2f}' for t in self.restore_s) or 'none (not restored)'
        return ['| worker killed (SIGKILL), lockstep, M = 2 | value |', '|---|---:|',
                f'| killed after frame | {self.frames // 3} of {self.frames} |',
                f'| it hosted the general arbiter | {"yes" if self.hosted_general else "no"} |',
                f'| time to restore its nodes on the spare [s] | {restore} |',
                f'| longest wait between two /odom [s] | {self.longest_gap_s:.2f} |',
                f'| frames published again | {self.republished} |',
                f'| frames let out while an older one stalled (2 s without /odom) | {self.published_ahead} |',
                f'| frames with /odom | {self.odom} of {self.frames} |',
                f'| of those, fused without some camera | {self.partial} |',
                f'| wall per frame, whole run [ms] | {self.wall_ms_per_frame:.1f} |']


def partial_frames(run_out: Path) -> int:
    """Frames the general arbiter fused without some camera (its /diagnostics)."""
    from multicam_ego_motion.bench.measures import read_statuses
    return sum(1 for name, values in read_statuses(Path(run_out) / 'output')
               if name == 'ego_motion/general_arbiter' and values.get('cameras_missing'))


def worker_crash(bag, out: Path, rig, rig_file, params, n_frames: int, duration=None) -> CrashFigures:
    from multicam_ego_motion.replay import run_graph
    print(f'bench: graph on {Path(bag).name}, M = {WORKERS}, lockstep, a worker killed ...', flush=True)
    run_out = out / 'worker_killed_m2'
    g = run_graph(bag, run_out, rig, rig_file, params, WORKERS, lockstep=True,
                  duration=duration, rebalance=False, logger=None,
                  record_topics=['/odom', '/diagnostics'], kill_worker_at=max(1, n_frames // 3))
    frames = len(g.playback.published_at)
    received = sorted(g.odom_received.values())
    gap = max((b - a for a, b in zip(received, received[1:])), default=0.0)
    # (the restored worker has the killed one's index and nodes)
    hosted = g.coordinator.placement.get('general_arbiter') == WORKERS - 1
    return CrashFigures(frames, g.counts.get('/odom', 0), list(g.coordinator.stats.restore_s),
                        int(g.playback.republished), g.frames_wall_s / max(frames, 1) * 1e3,
                        gap, partial_frames(run_out), hosted, int(g.playback.published_ahead))
