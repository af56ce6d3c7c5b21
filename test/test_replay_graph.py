"""The whole graph over real DDS: generate a short bag, `ego-motion replay` it in lockstep,
and check what the graph published (every frame, finite, positive-definite covariances,
odometry near the ground truth)."""
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from conftest import run_cli

REPO = Path(__file__).resolve().parents[1]
DEFAULT_BAG = REPO / 'bags' / 'default'
DURATION_S, RATE_HZ = 5, 8       # the first 5 s of the committed default bag (8 Hz)
FRAMES = DURATION_S * RATE_HZ          # --duration is a half-open window


@pytest.fixture(scope='module')
def replayed(tmp_path_factory):
    out = tmp_path_factory.mktemp('replay_out') / 'run'
    r = run_cli('replay', DEFAULT_BAG, '--out', out, '--workers', 2, '--duration', DURATION_S,
                timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return out, r.stdout


def read_topic(bag, topic):
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]


def test_every_frame_has_odometry_with_valid_covariance(replayed):
    out, _ = replayed
    odom = read_topic(out / 'output', '/odom')
    assert len(odom) == FRAMES
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in odom]
    assert stamps == sorted(set(stamps))
    for m in odom:
        assert m.header.frame_id == 'odom' and m.child_frame_id == 'base_link'
        for cov in (m.pose.covariance, m.twist.covariance):
            C = np.asarray(cov).reshape(6, 6)
            assert np.all(np.isfinite(C))
            assert np.linalg.eigvalsh(0.5 * (C + C.T)).min() > 0


def test_quarter_and_camera_estimates_and_diagnostics_recorded(replayed):
    out, _ = replayed
    for cam in ('front', 'left', 'back', 'right'):
        assert len(read_topic(out / 'output', f'/{cam}/pose')) == FRAMES
        for q in range(1, 5):
            assert len(read_topic(out / 'output', f'/{cam}/q{q}/pose')) == FRAMES
    diag = read_topic(out / 'output', '/diagnostics')
    names = {s.name for m in diag for s in m.status}
    assert 'ego_motion/general_arbiter' in names and 'ego_motion/front/q1' in names
    q_values = [{kv.key: kv.value for kv in s.values} for m in diag for s in m.status
                if s.name == 'ego_motion/front/q1' and s.values]
    assert {'features', 'acquire_ms', 'extract_ms', 'track_ms', 'pose_ms', 'structure_ms'} <= set(q_values[-1])
    assert any(v['state'] == 'tracking' for v in q_values)


def test_bottom_quarters_report_floor_landmarks(replayed):
    """The default rig stands on a floor (rig floor_z): the bottom quarters (3, 4), which
    see it, put landmarks on it (ground_plane) and say how many they track; the top quarters
    look above the horizon and never do."""
    out, _ = replayed
    diag = read_topic(out / 'output', '/diagnostics')
    most = {}
    for m in diag:
        for st in m.status:
            v = {kv.key: kv.value for kv in st.values}
            if st.name.startswith('ego_motion/') and '/q' in st.name and 'floor_landmarks' in v:
                most[st.name] = max(most.get(st.name, 0), int(v['floor_landmarks']))
    assert len(most) == 16, sorted(most)
    for name, n in most.items():
        if name.endswith(('q3', 'q4')):
            assert n >= 5, (name, n)
        else:
            assert n == 0, (name, n)


def test_summary_and_report(replayed):
    out, stdout = replayed
    assert len([l for l in (out / 'odometry.tum').read_text().splitlines() if not l.startswith('#')]) == FRAMES
    assert (out / 'report.md').exists() and (out / 'trajectory.png').stat().st_size > 10_000
    assert 'ATE' in stdout and 'real-time factor' in stdout


def test_odometry_follows_ground_truth(replayed):
    """A loose plumbing check (the accuracy regression tests are in test_accuracy.py)."""
    out, _ = replayed
    odom = read_topic(out / 'output', '/odom')
    with AnyReader([DEFAULT_BAG]) as reader:
        conns = [c for c in reader.connections if c.topic == '/ground_truth/odom']
        gt = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m for m in
              (reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns))}
    last = odom[-1]
    truth = gt[last.header.stamp.sec * 10**9 + last.header.stamp.nanosec]
    p = np.array([last.pose.pose.position.x, last.pose.pose.position.y])
    q = np.array([truth.pose.pose.position.x, truth.pose.pose.position.y])
    travelled = 5.0   # about 1 m/s for 5 s
    assert np.linalg.norm(p - q) < 0.05 * travelled, (p, q)


def test_path_is_decimated_and_ends_at_the_odometry(replayed):
    # /ego_motion/path: a pose every 5 cm (or 0.1 rad), republished at most once a second of
    # bag time (its cost grows with its length), ending where /odom was at that stamp.
    out, _ = replayed
    paths = read_topic(out / 'output', '/ego_motion/path')
    assert 1 <= len(paths) <= DURATION_S + 1
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in paths]
    assert all(b - a >= 1.0 - 1e-9 for a, b in zip(stamps, stamps[1:]))
    odom = {(m.header.stamp.sec, m.header.stamp.nanosec): m.pose.pose.position
            for m in read_topic(out / 'output', '/odom')}
    last = paths[-1]
    assert last.header.frame_id == 'odom' and len(last.poses) < FRAMES
    end = odom[(last.header.stamp.sec, last.header.stamp.nanosec)]
    p = last.poses[-1].pose.position
    assert (p.x, p.y, p.z) == (end.x, end.y, end.z)
    xyz = np.array([[q.pose.position.x, q.pose.position.y] for q in last.poses])
    steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    assert len(last.poses) >= 5 and (steps >= 0.05 - 1e-9).mean() > 0.8
