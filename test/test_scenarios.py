"""Scenario generator: bag contents checked with an independent reader (rosbags), the
trajectories, texture quality for the tracker, determinism and bad input."""
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import read_bag

from multicam_ego_motion.bag.rig_bag_writer import STAMP_EPOCH_NS
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import load_rig
from multicam_ego_motion.scenarios.generator import evenly_spaced_rig, generate
from multicam_ego_motion.scenarios.scene import scene_for
from multicam_ego_motion.scenarios.trajectories import SCENARIOS

REPO = Path(__file__).resolve().parents[1]
CAMERAS = ('front', 'left', 'back', 'right')
WIDTH, HEIGHT, RATE, DURATION = 320, 240, 10.0, 2.0


@pytest.fixture(scope='module')
def loop_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp('gen') / 'loop'
    generate('loop', out, seed=3, duration=DURATION, rate=RATE, width=WIDTH, height=HEIGHT,
             progress=False)
    return out


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_topics_types_and_counts(loop_bag):
    topics, _ = read_bag(loop_bag)
    n = int(DURATION * RATE) + 1
    for cam in CAMERAS:
        assert topics[f'/{cam}/image_raw'] == ('sensor_msgs/msg/Image', n)
        assert topics[f'/{cam}/camera_info'] == ('sensor_msgs/msg/CameraInfo', n)
    assert topics['/ground_truth/odom'] == ('nav_msgs/msg/Odometry', n)
    assert topics['/wheel/odom'] == ('nav_msgs/msg/Odometry', n)
    assert topics['/tf_static'] == ('tf2_msgs/msg/TFMessage', 1)


def test_stamps_frames_and_camera_info(loop_bag):
    _, messages = read_bag(loop_bag)
    by_stamp = {}
    for topic, log_time, msg in messages:
        if hasattr(msg, 'header') and topic != '/tf_static':
            assert stamp_ns(msg) == log_time, topic
        if topic.endswith('/image_raw'):
            cam = topic.split('/')[1]
            assert msg.encoding == 'mono8' and msg.header.frame_id == f'{cam}_optical'
            assert (msg.width, msg.height, msg.step) == (WIDTH, HEIGHT, WIDTH)
            by_stamp.setdefault(log_time, set()).add(cam)
        if topic.endswith('/camera_info'):
            assert msg.distortion_model == 'plumb_bob'
            K, P = msg.k.reshape(3, 3), msg.p.reshape(3, 4)
            np.testing.assert_allclose(P[:, :3], K)
            assert K[0, 0] == pytest.approx(200.0) and K[0, 2] == pytest.approx((WIDTH - 1) / 2)
    assert min(by_stamp) == STAMP_EPOCH_NS
    assert all(cams == set(CAMERAS) for cams in by_stamp.values())
    stamps = np.array(sorted(by_stamp))
    np.testing.assert_allclose(np.diff(stamps), 1e9 / RATE, atol=1)


def test_static_transforms_match_rig(loop_bag):
    _, messages = read_bag(loop_bag)
    tf = [m for t, _, m in messages if t == '/tf_static'][0]
    rig = load_rig(loop_bag / 'rig.yaml')
    assert {t.child_frame_id for t in tf.transforms} == {c.frame_id for c in rig.cameras}
    for t in tf.transforms:
        assert t.header.frame_id == 'base_link'
        cam = [c for c in rig.cameras if c.frame_id == t.child_frame_id][0]
        tr = t.transform.translation
        np.testing.assert_allclose([tr.x, tr.y, tr.z], cam.translation, atol=1e-9)


def test_ground_truth_follows_trajectory_and_wheel_odometry_drifts(loop_bag):
    _, messages = read_bag(loop_bag)
    gt = [m for t, _, m in messages if t == '/ground_truth/odom']
    wheel = [m for t, _, m in messages if t == '/wheel/odom']
    assert gt[0].header.frame_id == 'odom' and gt[0].child_frame_id == 'base_link'
    p0 = gt[0].pose.pose
    assert (p0.position.x, p0.position.y, p0.orientation.w) == pytest.approx((0, 0, 1), abs=1e-9)
    traj = SCENARIOS['loop'](DURATION)
    x0, y0, yaw0 = traj.start_pose()
    for i, m in enumerate(gt):
        x, y, yaw, v, w = traj.sample(i / RATE)
        dx, dy = x - x0, y - y0   # start heading is +x in the world: odom == world shifted
        assert yaw0 == 0.0
        assert m.pose.pose.position.x == pytest.approx(dx, abs=1e-6)
        assert m.pose.pose.position.y == pytest.approx(dy, abs=1e-6)
        assert m.twist.twist.linear.x == pytest.approx(v, abs=1e-6)
        assert m.twist.twist.angular.z == pytest.approx(w, abs=1e-6)
        assert np.all(np.diag(np.reshape(m.pose.covariance, (6, 6))) > 0)
    v_gt = np.array([m.twist.twist.linear.x for m in gt])
    v_wheel = np.array([m.twist.twist.linear.x for m in wheel])
    moving = v_gt > 0.2
    rel = np.abs(v_wheel[moving] / v_gt[moving] - 1)
    assert 0.003 < rel.mean() < 0.15
    assert not np.allclose([m.pose.pose.position.x for m in wheel],
                           [m.pose.pose.position.x for m in gt], atol=1e-4)


def test_images_have_corners_in_every_quarter(loop_bag):
    _, messages = read_bag(loop_bag)
    images = [m for t, _, m in messages if t.endswith('/image_raw')][::5]
    for msg in images:
        img = msg.data.reshape(msg.height, msg.width)
        h, w = img.shape
        for q in (img[:h // 2, :w // 2], img[:h // 2, w // 2:], img[h // 2:, :w // 2],
                  img[h // 2:, w // 2:]):
            corners = cv2.goodFeaturesToTrack(q, 100, 0.01, 5)
            assert corners is not None and len(corners) >= 30, msg.header.frame_id


def test_bare_wall_is_nearly_bare_for_the_left_camera(tmp_path):
    out = tmp_path / 'bare'
    generate('bare_wall', out, seed=1, duration=30.0, rate=0.2, width=WIDTH, height=HEIGHT,
             progress=False)
    _, messages = read_bag(out)
    left = {t: m for topic, t, m in messages if topic == '/left/image_raw'}

    def strength(t):
        """Strongest Shi-Tomasi response: what an absolute corner threshold sees."""
        m = left[STAMP_EPOCH_NS + int(t * 1e9)]
        return cv2.cornerMinEigenVal(m.data.reshape(m.height, m.width), 3).max()

    textured = min(strength(0.0), strength(20.0))    # before and after the bare stretch
    assert strength(10.0) < 0.02 * textured          # the bare stretch


def test_same_seed_same_bytes(loop_bag, tmp_path):
    again = tmp_path / 'again'
    generate('loop', again, seed=3, duration=DURATION, rate=RATE, width=WIDTH, height=HEIGHT,
             progress=False)
    assert (loop_bag / 'loop_0.mcap').read_bytes() == (again / 'again_0.mcap').read_bytes()
    assert (loop_bag / 'rig.yaml').read_bytes() == (again / 'rig.yaml').read_bytes()


def test_loop_trajectory_is_a_closed_loop_of_20_m():
    traj = SCENARIOS['loop'](30.0)
    assert traj.duration >= 30.0 and traj.path_length >= 20.0
    x, y, yaw, v, w = traj.sample([0.0, 30.0])
    assert np.hypot(x[1] - x[0], y[1] - y[0]) < 0.01
    assert abs(yaw[1] - yaw[0] - 2 * np.pi) < 1e-3
    assert v[0] == pytest.approx(0, abs=1e-6) and v[1] == pytest.approx(0, abs=1e-6)


@pytest.mark.parametrize('name', sorted(SCENARIOS))
def test_trajectories_stay_in_free_space_and_are_consistent(name):
    traj = SCENARIOS[name](30.0)
    scene = scene_for(name)
    t = np.arange(0, 30.0, 0.1)
    x, y, yaw, v, w = traj.sample(t)
    assert all(scene.contains_free_point(a, b) for a, b in zip(x, y)), name
    # Rates agree with the pose derivatives.
    np.testing.assert_allclose(np.gradient(traj.yaw, traj.t)[10:-10], traj.yaw_rate[10:-10],
                               atol=1e-2)
    speed = np.hypot(np.gradient(traj.x, traj.t), np.gradient(traj.y, traj.t))
    np.testing.assert_allclose(speed[10:-10], np.abs(traj.speed[10:-10]), atol=1e-2)


def test_rig_layouts():
    assert evenly_spaced_rig(4).names == list(CAMERAS)
    assert len(evenly_spaced_rig(1).cameras) == 1 and len(evenly_spaced_rig(8).cameras) == 8
    with pytest.raises(UserError):
        evenly_spaced_rig(9)


def test_rig_floor_is_saved_loaded_and_checked(tmp_path):
    """Generated rigs stand on the renderer's floor (floor_z 0 in base_link); a rig file
    without floor_z has no floor (floor landmarks and planar motion off); a NaN is rejected."""
    from multicam_ego_motion.geometry.rig import load_rig, parse_rig
    rig = evenly_spaced_rig(3)
    assert rig.floor_z == 0.0
    rig.save(tmp_path / 'rig.yaml')
    assert load_rig(tmp_path / 'rig.yaml').floor_z == 0.0
    d = rig.to_dict()
    d.pop('floor_z')
    assert parse_rig(d).floor_z is None
    with pytest.raises(UserError, match='floor_z must be a finite number'):
        parse_rig(dict(d, floor_z=float('nan')), 'x.yaml')


def run_cli(*args):
    return subprocess.run([sys.executable, '-m', 'multicam_ego_motion.cli', *args],
                          capture_output=True, text=True, cwd=REPO, timeout=120)


def test_cli_unknown_scenario(tmp_path):
    r = run_cli('generate', '--scenario', 'moonwalk', '--out', str(tmp_path / 'b'))
    assert r.returncode != 0
    assert 'unknown scenario' in r.stderr and 'moonwalk' in r.stderr
    assert 'Traceback' not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_cli_output_exists(tmp_path):
    out = tmp_path / 'b'
    out.mkdir()
    (out / 'something').write_text('x')
    r = run_cli('generate', '--scenario', 'loop', '--out', str(out))
    assert r.returncode != 0 and 'already exists' in r.stderr and 'Traceback' not in r.stderr


def test_cli_generates_small_bag(tmp_path):
    out = tmp_path / 'b'
    r = run_cli('generate', '--scenario', 'spin_then_drive', '--out', str(out), '--duration', '1',
                '--rate', '5', '--width', '64', '--height', '48', '--cameras', '2',
                '--rig-out', str(tmp_path / 'rig.yaml'), '--k1', '-0.05')
    assert r.returncode == 0, r.stderr
    assert load_rig(tmp_path / 'rig.yaml').names == ['cam0', 'cam1']
    topics, _ = read_bag(out)
    assert topics['/cam1/image_raw'][1] == 6
