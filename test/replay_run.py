"""Run `ego-motion replay` on a bag and read back what the graph recorded: odometry,
per-camera estimates and /diagnostics, as plain numpy / dicts for the fault tests."""
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

import process_table
from conftest import REPO
from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
from multicam_ego_motion.ros_plumbing.pose_messages import pose_to_T, stamp_to_ns

NS = 1_000_000_000


@dataclass
class Diag:
    t: float          # header stamp, seconds since the bag start
    name: str         # 'ego_motion/front/q1', 'ego_motion/general_arbiter', ...
    level: int        # 0 OK, 1 WARN, 2 ERROR
    message: str
    values: dict


class ReplayRun:
    def __init__(self, bag, out, returncode, stdout, stderr, wall_s):
        self.bag, self.out = Path(bag), Path(out)
        self.returncode, self.stdout, self.stderr, self.wall_s = returncode, stdout, stderr, wall_s

    @property
    def start_ns(self):
        return Rosbag2Reader(self.bag).start_ns

    def leftover_processes(self):
        """Processes of this replay (itself, its workers) still alive after it ended."""
        return process_table.wait_gone(process_table.marked(str(self.out)), 5.0)

    def __repr__(self):   # what pytest shows when an assertion on the run fails
        return f'ReplayRun({self.bag}, rc={self.returncode}, stderr={self.stderr[-2000:]!r})'

    @property
    def output(self) -> Path:
        return self.out / 'output'

    def messages(self, topic):
        """[(log_ns, msg)] of a recorded topic ([] when it was never recorded)."""
        reader = Rosbag2Reader(self.output)
        if topic not in reader.topics:
            return []
        return [(t, m) for _, m, t in reader.decoded([topic])]

    def odometry(self):
        """(stamps [s since bag start], 4x4 poses, pose covariances, twist covariances)."""
        msgs = [m for _, m in self.messages('/odom')]
        stamps = np.array([(stamp_to_ns(m.header.stamp) - self.start_ns) / NS for m in msgs])
        T = np.array([pose_to_T(m.pose.pose) for m in msgs]).reshape(-1, 4, 4)
        P = np.array([m.pose.covariance for m in msgs], dtype=float).reshape(-1, 6, 6)
        Q = np.array([m.twist.covariance for m in msgs], dtype=float).reshape(-1, 6, 6)
        return stamps, T, P, Q

    def odom_problems(self):
        """Every /odom message with a non-finite pose or a covariance that is not positive
        definite (the fault tests require none, whatever was injected)."""
        stamps, T, P, Q = self.odometry()
        bad = []
        for t, pose, pc, tc in zip(stamps, T, P, Q):
            if not np.all(np.isfinite(pose)):
                bad.append((t, 'pose not finite'))
            for what, C in (('pose', pc), ('twist', tc)):
                if not np.all(np.isfinite(C)) or np.linalg.eigvalsh(0.5 * (C + C.T)).min() <= 0:
                    bad.append((t, f'{what} covariance not finite/positive definite'))
        return bad

    def diagnostics(self, name_prefix=''):
        out = []
        for _, m in self.messages('/diagnostics'):
            t = (stamp_to_ns(m.header.stamp) - self.start_ns) / NS
            for s in m.status:
                if s.name.startswith(name_prefix):
                    level = s.level[0] if isinstance(s.level, (bytes, bytearray)) else int(s.level)
                    out.append(Diag(t, s.name, level, s.message,
                                    {kv.key: kv.value for kv in s.values}))
        return out


def replay_env(out, **overrides):
    """The test's environment (PYTHONPATH to this tree) plus the marker that finds this
    replay's processes later; an override of None removes the variable.

    Without an override the replay picks its own free ROS_DOMAIN_ID when it starts: the
    test process's domain looks free to other test sessions between two replays."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    env.pop('ROS_DOMAIN_ID', None)
    env[process_table.MARKER] = str(out)
    env.update(overrides)
    return {k: v for k, v in env.items() if v is not None}


def replay_command(bag, out, *extra, workers=2):
    return [sys.executable, '-m', 'multicam_ego_motion.cli', 'replay', str(bag), '--out', str(out),
            '--workers', str(workers), *map(str, extra)]


def replay(bag, out, *extra, workers=2, timeout=300, env=None) -> ReplayRun:
    """Run a replay to its end (or failure)."""
    t0 = time.monotonic()
    r = subprocess.run(replay_command(bag, out, *extra, workers=workers), capture_output=True,
                       text=True, timeout=timeout, env=env or replay_env(out))
    return ReplayRun(bag, out, r.returncode, r.stdout, r.stderr, time.monotonic() - t0)


def start_replay(bag, out, *extra, workers=2, env=None) -> subprocess.Popen:
    """A replay in the background, in its own session (a terminal's Ctrl-C reaches the
    whole process group: os.killpg(proc.pid, SIGINT) does the same)."""
    return subprocess.Popen(replay_command(bag, out, *extra, workers=workers),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env or replay_env(out), start_new_session=True)


def recorded_counts(out) -> dict:
    """Messages per topic the recorder has flushed so far (metadata.yaml, rewritten every
    second while the replay runs); {} before the first flush."""
    meta = Path(out) / 'output' / 'metadata.yaml'
    try:
        info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
    except (OSError, yaml.YAMLError, TypeError, KeyError):
        return {}
    return {t['topic_metadata']['name']: t['message_count'] for t in info['topics_with_message_count']}


def wait_for_odom(proc, out, n: int, timeout_s: float = 120.0):
    """Until the running replay has recorded n /odom messages (fails if it ends first)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if recorded_counts(out).get('/odom', 0) >= n:
            return
        assert proc.poll() is None, f'replay ended early: {proc.communicate()}'
        time.sleep(0.2)
    raise AssertionError(f'no {n} /odom messages within {timeout_s} s')


def ground_truth(bag, start_ns):
    """{stamp [s since start]: 4x4 pose} of /ground_truth/odom."""
    reader = Rosbag2Reader(bag)
    return {round((stamp_to_ns(m.header.stamp) - start_ns) / NS, 6): pose_to_T(m.pose.pose)
            for _, m, _ in reader.decoded(['/ground_truth/odom'])}


def segment_drift(run: ReplayRun, t_from: float, t_to: float) -> float:
    """Translation error [m] of the estimated motion between two frames, relative to ground
    truth: how far the odometry went wrong over [t_from, t_to] alone."""
    stamps, T, _, _ = run.odometry()
    gt = ground_truth(run.bag, run.start_ns)
    i = int(np.argmin(np.abs(stamps - t_from)))
    j = int(np.argmin(np.abs(stamps - t_to)))
    est = np.linalg.inv(T[i]) @ T[j]
    ref = np.linalg.inv(gt[round(stamps[i], 6)]) @ gt[round(stamps[j], 6)]
    return float(np.linalg.norm(est[:3, 3] - ref[:3, 3]))
