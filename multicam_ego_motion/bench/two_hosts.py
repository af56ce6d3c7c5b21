"""The bench's two-host row: the default bag in lockstep on M = 2 with one worker on the
coordinator's host and one on a second host (two network namespaces of this machine,
bench/netns.py: UDPv4 between them, the control channel over TCP with the shared key).
Wall and CPU per frame (workers on both hosts, and the replay process), beside the one-host
M = 2 row (each ran twice; the faster two-host run and the counted one-host run): the difference is what crossing hosts costs (UDP through a network stack instead
of shared memory, the control channel over TCP). Skipped, with the reason printed, where
namespaces cannot be made (not root, no `ip`).

The run itself is a child process inside the first namespace (`python -m
multicam_ego_motion.bench.two_hosts --child ...`): a process cannot leave its network
namespace for one run and come back cleanly."""
import argparse
import json
import os
import secrets
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

PORT = 7452
WORKERS = 2


@dataclass
class TwoHostFigures:
    wall_ms: float = float('nan')
    frames: int = 0
    odom: int = 0
    cpu_workers_ms: float = float('nan')
    cpu_replay_ms: float = float('nan')
    skipped: Optional[str] = None

    def lines(self, one_host) -> List[str]:
        """one_host: the one-host M = 2 row's (wall ms, frames, graph CPU ms, player... CPU ms)."""
        if self.skipped:
            return [f'Two-host row skipped: {self.skipped}.']
        wall1, _, cpu1, cpu_r1 = one_host
        return ['| lockstep, M = 2 | wall per frame [ms] | CPU per frame: workers [ms] '
                '| CPU per frame: player, recorder, coordinator [ms] | frames with /odom |',
                '|---|---:|---:|---:|---:|',
                f'| one host (shared memory) | {wall1:.1f} | {cpu1:.1f} | {cpu_r1:.1f} | |',
                f'| two hosts (namespaces, UDP + TCP control), one worker each | {self.wall_ms:.1f} '
                f'| {self.cpu_workers_ms:.1f} | {self.cpu_replay_ms:.1f} | {self.odom} of {self.frames} |',
                f'| crossing hosts costs | {self.wall_ms - wall1:+.1f} | {self.cpu_workers_ms - cpu1:+.1f} '
                f'| {self.cpu_replay_ms - cpu_r1:+.1f} | |']


def two_hosts(bag, out: Path, rig_file, params, duration=None) -> TwoHostFigures:
    from multicam_ego_motion.bench import netns
    from multicam_ego_motion.ros_plumbing.ros_domain import free_domain
    reason = netns.unavailable()
    if reason:
        print(f'bench: two-host row skipped: {reason}', flush=True)
        return TwoHostFigures(skipped=reason)
    print(f'bench: graph on {Path(bag).name}, M = {WORKERS}, lockstep, two hosts (network namespaces) ...',
          flush=True)
    repo = Path(__file__).resolve().parents[2]
    env = dict(os.environ, EGO_MOTION_CONTROL_KEY=secrets.token_hex(32),
               PYTHONPATH=os.pathsep.join([str(repo)] + [p for p in [os.environ.get('PYTHONPATH')] if p]))
    address = f'{netns.SUBNET}.1:{PORT}'
    runs = []
    with netns.Hosts(2, free_domain()) as hosts:
        # twice, the faster counts, as for the one-host rows (timing.py says why)
        for suffix in ('', '_again'):
            run_dir = (out / f'two_hosts_m2{suffix}').resolve()
            run_dir.mkdir(parents=True)
            with open(run_dir / 'remote_worker.log', 'w') as log:
                hosts.run(1, [sys.executable, '-m', 'multicam_ego_motion.cli', 'worker', '--coordinator', address],
                          env=env, stdout=log, stderr=subprocess.STDOUT)
                child = hosts.run(0, [sys.executable, '-m', 'multicam_ego_motion.bench.two_hosts', '--child',
                                      bag, run_dir, rig_file, params, address]
                                  + (['--duration', duration] if duration else []),
                                  env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                text, _ = child.communicate(timeout=1800)
            (run_dir / 'run.log').write_text(text)
            result = [l for l in text.splitlines() if l.startswith('{')]
            if child.returncode or not result:
                raise RuntimeError(f'two-host run failed (exit {child.returncode}): {text[-2000:]}')
            runs.append(TwoHostFigures(**json.loads(result[-1])))
    return min(runs, key=lambda f: f.wall_ms)


def _child(argv=None):
    from multicam_ego_motion.bench.measures import per_frame_ms
    from multicam_ego_motion.coordinator import control
    from multicam_ego_motion.geometry.rig import load_rig
    from multicam_ego_motion.replay import run_graph
    ap = argparse.ArgumentParser()
    ap.add_argument('--child', action='store_true')
    ap.add_argument('bag')
    ap.add_argument('out')
    ap.add_argument('rig_file')
    ap.add_argument('params')
    ap.add_argument('address')
    ap.add_argument('--duration', type=float)
    a = ap.parse_args(argv)
    g = run_graph(a.bag, Path(a.out), load_rig(a.rig_file), a.rig_file, a.params, WORKERS, lockstep=True,
                  duration=a.duration, rebalance=False, logger=print, record_topics=['/odom'],
                  remote={'listen': a.address, 'remote_workers': 1, 'key': control.load_key()},
                  remote_cpu=True)
    frames = len(g.playback.published_at)
    print(json.dumps({'wall_ms': g.frames_wall_s / max(frames, 1) * 1e3, 'frames': frames,
                      'odom': g.counts.get('/odom', 0),
                      'cpu_workers_ms': per_frame_ms(g.cpu_workers_s, frames),
                      'cpu_replay_ms': per_frame_ms(g.cpu_replay_s, frames)}), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(_child())
