"""The bench's crash row: the default bag in lockstep on M = 2 with the last worker killed
(SIGKILL) a third of the way in, as a crash would. How long until its nodes ran again on the
hot spare (restored from their last snapshots), how many frames the player had to publish
again, and whether every frame still got its odometry. A figure, never a test bound: on a
loaded host the same restore took 3.3 s instead of 0.7 s."""
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

    def lines(self) -> List[str]:
        restore = ', '.join(f'{t:.2f}' for t in self.restore_s) or 'none (not restored)'
        return ['| worker killed (SIGKILL), lockstep, M = 2 | value |', '|---|---:|',
                f'| killed after frame | {self.frames // 3} of {self.frames} |',
                f'| time to restore its nodes on the spare [s] | {restore} |',
                f'| frames published again | {self.republished} |',
                f'| frames with /odom | {self.odom} of {self.frames} |',
                f'| wall per frame, whole run [ms] | {self.wall_ms_per_frame:.1f} |']


def worker_crash(bag, out: Path, rig, rig_file, params, n_frames: int, duration=None) -> CrashFigures:
    from multicam_ego_motion.replay import run_graph
    print(f'bench: graph on {Path(bag).name}, M = {WORKERS}, lockstep, a worker killed ...', flush=True)
    g = run_graph(bag, out / 'worker_killed_m2', rig, rig_file, params, WORKERS, lockstep=True,
                  duration=duration, rebalance=False, logger=None,
                  record_topics=['/odom'], kill_worker_at=max(1, n_frames // 3))
    frames = len(g.playback.published_at)
    return CrashFigures(frames, g.counts.get('/odom', 0), list(g.coordinator.stats.restore_s),
                        int(g.playback.republished), g.frames_wall_s / max(frames, 1) * 1e3)
