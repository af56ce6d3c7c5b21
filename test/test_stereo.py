"""Overlapping cameras (stereo pairs): the matching and triangulation on synthetic images of
known depth, the rig's stereo_pairs, the floor from /tf_static's base_footprint, and a
generated stereo pair replayed in lockstep without wheel and without floor: metric from the
first frames, the same /odom as the sequential pipeline."""
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import yaml

from camera_pose_nodes.camera_model import CameraIntrinsics
from camera_pose_nodes.stereo_match import StereoConfig, StereoPair, overlapping_pairs
from conftest import run_cli
from multicam_ego_motion.bag.rig_from_tf import rig_from_bag
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import load_rig, optical_rotation, paper_rig, parse_rig
from multicam_ego_motion.scenarios.generator import stereo_pair_rig
from replay_run import replay

W, H, F = 640, 480, 400.0


def textured(seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (H, W)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def plane_pair(depth, baseline, dy=0.0):
    """A fronto-parallel textured plane at `depth` seen by a rectified pair: the right image
    is the left one shifted by the disparity f b / depth (and by dy rows)."""
    left = textured()
    d = F * baseline / depth
    M = np.float32([[1, 0, -d], [0, 1, dy]])
    right = cv2.warpAffine(left, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return left, right, d


def pair_geometry(baseline):
    rig = stereo_pair_rig(baseline)
    intr = CameraIntrinsics.pinhole(F, F, W / 2, H / 2, W, H)
    return rig, intr


@pytest.mark.parametrize('depth', [3.0, 8.0, 20.0])
def test_matches_triangulate_the_known_depth(depth):
    rig, intr = pair_geometry(0.3)
    left, right, disparity = plane_pair(depth, 0.3)
    pair = StereoPair(rig.cameras[0].T_base_cam, rig.cameras[1].T_base_cam, intr, intr, StereoConfig())
    px = cv2.goodFeaturesToTrack(left, 200, 0.01, 10).reshape(-1, 2).astype(float)
    inner = (px[:, 0] > 60) & (px[:, 0] < W - 60) & (px[:, 1] > 30) & (px[:, 1] < H - 30)
    px = px[inner]
    ok, px_b, X, C = pair.match(left, (0, 0), right, px, 10.0)   # the prior is off on purpose
    assert ok.mean() > 0.8, f'{ok.sum()} of {len(px)} matched (disparity {disparity:.1f} px)'
    assert np.median(np.abs(X[ok, 2] - depth)) / depth < 0.01
    assert np.all(np.abs(X[ok, 2] - depth) / depth < 0.05)
    # the covariance says how well the depth is known: sigma_z = z^2 sigma_d / (f b)
    sigma_z = np.sqrt(C[ok, 2, 2])
    expected = depth ** 2 * 0.5 / (F * 0.3)
    assert np.all((sigma_z > 0.3 * expected) & (sigma_z < 3.0 * expected))
    assert np.all(np.isnan(X[~ok]))


def test_matches_off_the_epipolar_line_are_rejected():
    rig, intr = pair_geometry(0.3)
    left, right, _ = plane_pair(5.0, 0.3, dy=6.0)     # the right camera is not where the rig says
    pair = StereoPair(rig.cameras[0].T_base_cam, rig.cameras[1].T_base_cam, intr, intr, StereoConfig())
    px = cv2.goodFeaturesToTrack(left, 200, 0.01, 10).reshape(-1, 2).astype(float)
    px = px[(px[:, 0] > 60) & (px[:, 0] < W - 60) & (px[:, 1] > 30) & (px[:, 1] < H - 30)]
    ok, _, _, _ = pair.match(left, (0, 0), right, px, 5.0)
    assert ok.sum() <= 0.05 * len(px)


def test_a_crop_matches_like_the_whole_image():
    rig, intr = pair_geometry(0.3)
    left, right, _ = plane_pair(6.0, 0.3)
    pair = StereoPair(rig.cameras[0].T_base_cam, rig.cameras[1].T_base_cam, intr, intr, StereoConfig())
    px = np.array([[400.0, 300.0], [500.0, 350.0], [450.0, 420.0]])
    crop = left[200:, 300:]                         # a bottom-right quarter with its margin
    ok, _, X, _ = pair.match(np.ascontiguousarray(crop), (300, 200), right, px, 6.0)
    assert ok.all() and np.allclose(X[:, 2], 6.0, rtol=0.02)


def test_overlapping_pairs_found_from_extrinsics_and_intrinsics():
    rig, intr = pair_geometry(0.3)
    assert overlapping_pairs(rig, {'left': intr, 'right': intr}) == (('left', 'right'),)
    ring = paper_rig()                  # four cameras 90 degrees apart: no overlap
    assert overlapping_pairs(ring, {c.name: intr for c in ring.cameras}) == ()
    assert overlapping_pairs(rig, {'left': intr}) == ()


def rig_data(pairs):
    cams = [{'name': n, 'translation': [0.0, y, 0.5],
             'rotation_xyzw': [0.5, -0.5, 0.5, -0.5]} for n, y in (('left', 0.15), ('right', -0.15))]
    d = {'cameras': cams}
    if pairs is not None:
        d['stereo_pairs'] = pairs
    return d


def test_rig_stereo_pairs_parse_and_round_trip(tmp_path):
    rig = parse_rig(rig_data([['left', 'right']]))
    assert rig.stereo_pairs == (('left', 'right'),) and not rig.detect_stereo
    assert rig.stereo_partners('left') == ['right'] and rig.stereo_partners('right') == ['left']
    rig.save(tmp_path / 'rig.yaml')
    again = load_rig(tmp_path / 'rig.yaml')
    assert again.stereo_pairs == rig.stereo_pairs
    plain = parse_rig(rig_data(None))
    assert plain.stereo_pairs == () and plain.detect_stereo
    plain.save(tmp_path / 'plain.yaml')
    assert 'stereo_pairs' not in yaml.safe_load((tmp_path / 'plain.yaml').read_text())
    assert not parse_rig(rig_data([])).detect_stereo       # named as none: no detection


@pytest.mark.parametrize('pairs, message', [
    ([['left', 'middle']], "names camera 'middle'"),
    ([['left', 'left']], 'with itself'),
    ([['left', 'right'], ['right', 'left']], 'twice'),
    ([['left']], 'must be [camera, camera]'),
    ('left right', 'must be a list'),
])
def test_rig_stereo_pairs_errors_name_the_problem(pairs, message):
    with pytest.raises(UserError, match='stereo_pairs') as e:
        parse_rig(rig_data(pairs), 'my_rig.yaml')
    assert message in str(e.value) and 'my_rig.yaml' in str(e.value)


def tf(parent, child, xyz, R):
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(R).as_quat()
    return SimpleNamespace(header=SimpleNamespace(frame_id=parent), child_frame_id=child,
                           transform=SimpleNamespace(
                               translation=SimpleNamespace(x=xyz[0], y=xyz[1], z=xyz[2]),
                               rotation=SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3])))


class TfReader:
    def __init__(self, transforms):
        self.path = 'fake_bag'
        self.topics = {'/tf_static': 'tf2_msgs/msg/TFMessage', '/front/image_raw': 'sensor_msgs/msg/Image'}
        self.transforms = transforms

    def decoded(self, topics):
        yield '/tf_static', SimpleNamespace(transforms=self.transforms), 0


@pytest.mark.parametrize('footprint, floor_z', [
    (tf('base_link', 'base_footprint', (0.0, 0.0, -0.42), np.eye(3)), -0.42),
    (tf('base_footprint', 'base_link', (0.0, 0.0, 0.42), np.eye(3)), -0.42),
    (None, None),
])
def test_rig_from_tf_takes_the_floor_from_base_footprint(footprint, floor_z):
    cam = tf('base_link', 'front_optical', (0.2, 0.0, 0.5), optical_rotation(0.0))
    rig = rig_from_bag(TfReader([cam] + ([footprint] if footprint is not None else [])))
    assert rig.names == ['front']
    if floor_z is None:
        assert rig.floor_z is None
    else:
        assert rig.floor_z == pytest.approx(floor_z)


# ---- the generated stereo pair through the graph ----------------------------------------

@pytest.fixture(scope='module')
def stereo_bag(tmp_path_factory):
    """A forward stereo pair (0.3 m) down the corridor, 10 s at 10 Hz; the rig file without
    floor_z, so that nothing but the pair can give the scale (no wheel either)."""
    bag = tmp_path_factory.mktemp('stereo') / 'bag'
    r = run_cli('generate', '--scenario', 'corridor', '--rig', 'stereo', '--baseline', '0.3',
                '--duration', '10', '--rate', '10', '--out', bag, timeout=300)
    assert r.returncode == 0, r.stderr
    rig = yaml.safe_load((bag / 'rig.yaml').read_text())
    assert rig['stereo_pairs'] == [['left', 'right']]
    rig.pop('floor_z')
    (bag / 'rig.yaml').write_text(yaml.safe_dump(rig, sort_keys=False))
    return bag


@pytest.fixture(scope='module')
def stereo_replay(stereo_bag, tmp_path_factory):
    run = replay(stereo_bag, tmp_path_factory.mktemp('stereo_out') / 'run', '--no-wheel', timeout=600)
    assert run.returncode == 0, run
    return run


def test_stereo_pair_without_wheel_or_floor_is_metric_from_the_first_frames(stereo_replay):
    from replay_run import ground_truth
    run = stereo_replay
    stamps, T, _, _ = run.odometry()
    assert len(stamps) == 101 and not run.odom_problems()
    gt = ground_truth(run.bag, run.start_ns)
    # metric from the first frames: after 1 s the distance travelled matches the truth
    i = int(np.argmin(np.abs(stamps - 1.0)))
    est_d = np.linalg.norm(T[i, :3, 3] - T[0, :3, 3])
    gt_d = np.linalg.norm(gt[round(stamps[i], 6)][:3, 3] - gt[round(stamps[0], 6)][:3, 3])
    assert gt_d > 0.2 and abs(est_d / gt_d - 1.0) < 0.05, (est_d, gt_d)
    # and over the whole run: final drift at most 1 % of the path
    path = sum(np.linalg.norm(gt[round(b, 6)][:3, 3] - gt[round(a, 6)][:3, 3])
               for a, b in zip(stamps[:-1], stamps[1:]))
    end_err = np.linalg.norm((T[-1, :3, 3] - T[0, :3, 3]) - (gt[round(stamps[-1], 6)][:3, 3]
                                                               - gt[round(stamps[0], 6)][:3, 3]))
    assert end_err / path < 0.01, (end_err, path)


def test_stereo_pair_lockstep_graph_equals_the_sequential_pipeline(stereo_bag, stereo_replay):
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.params_file import fusion_params_from, quarter_params_from
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.ros_plumbing.package_share import default_params
    from multicam_ego_motion.sequential_pipeline import run_sequential
    rig, _ = resolve_rig(Rosbag2Reader(stereo_bag), None)
    pf = default_params()
    seq = run_sequential(stereo_bag, rig, quarter_params_from(pf), fusion_params_from(pf), use_wheel=False)
    stamps, T, _, _ = stereo_replay.odometry()
    assert len(seq.fused) == len(T)
    for f, t in zip(seq.fused, T):
        assert np.array_equal(f.T_odom_base[:3, 3], t[:3, 3])
        assert np.allclose(f.T_odom_base[:3, :3], t[:3, :3], atol=1e-12, rtol=0)


def test_stereo_pair_quarters_migrate_with_identical_odometry(stereo_bag, stereo_replay, tmp_path):
    """--migrate-every 3: quarters of both cameras move between workers (their state carries
    the partner's intrinsics and any partner image that came ahead of its frame) and the
    odometry stays the same bit for bit."""
    moved = replay(stereo_bag, tmp_path / 'moved', '--no-wheel', '--migrate-every', 3, timeout=600)
    assert moved.returncode == 0, moved
    import re
    n = re.search(r'coordinator: (\d+) migrations', moved.stdout + moved.stderr)
    assert n and int(n.group(1)) >= 10, moved.stdout[-2000:]
    _, T0, _, _ = stereo_replay.odometry()
    _, T1, _, _ = moved.odometry()
    assert len(T1) == len(T0)
    differ = [k for k in range(len(T0)) if not np.array_equal(T0[k], T1[k])]
    # (on a failure: where it began and how far, with the coordinator's moves to match)
    assert not differ, (differ[0], float(np.abs(T0[differ[0]] - T1[differ[0]]).max()),
                        [l for l in moved.stdout.splitlines() if l.startswith('coordinator: moved')][:40])


def test_rig_floor_level_parses_and_is_checked(tmp_path):
    d = rig_data(None)
    d['floor_z'] = 0.0
    d['floor_level'] = False
    rig = parse_rig(d)
    assert rig.floor_level is False
    rig.save(tmp_path / 'road.yaml')
    assert load_rig(tmp_path / 'road.yaml').floor_level is False
    assert parse_rig(rig_data(None)).floor_level is True
    d['floor_level'] = 'no'
    with pytest.raises(UserError, match='floor_level must be true or false'):
        parse_rig(d, 'road.yaml')


def test_stereo_rig_starts_with_its_speed_open():
    """The general arbiter's first camera fix on a stereo rig without a wheel leaves the
    linear velocity open: a car already at 12 m/s is followed from the next frame."""
    from arbiter_node.general_fusion import GeneralFusion
    from camera_pose_nodes.pose_estimate import PoseEstimate
    from multicam_ego_motion.geometry.se3 import make_T

    def run(rig):
        fusion = GeneralFusion(rig, {})
        states = []
        for k in range(6):
            T = make_T(np.eye(3), [1.2 * k, 0.0, 0.0])
            est = {n: PoseEstimate(k * 100_000_000, T, np.eye(6) * 1e-4, source=n, state='tracking')
                   for n in rig.names}
            if k == 0:
                est = {}
            states.append(fusion.process(k * 100_000_000, est).state)
        return states, fusion.ekf.T[0, 3]
    stereo = stereo_pair_rig(0.3)
    states, x = run(stereo)
    assert states[1:] == ['tracking'] * 5 and x == pytest.approx(6.0, abs=0.05)
    from dataclasses import replace
    # the floor is a scale source of its own too (a car over a road): the same start
    assert stereo.floor_z is not None
    states, x = run(replace(stereo, stereo_pairs=()))
    assert states[1:] == ['tracking'] * 5 and x == pytest.approx(6.0, abs=0.05)
    # without either the start is at rest: the later frames gated out
    states, _ = run(replace(stereo, stereo_pairs=(), floor_z=None))
    assert 'dead_reckoning' in states


def test_a_rig_without_named_pairs_gets_them_from_the_bag(stereo_bag, tmp_path):
    """Named pairs win; without any, the overlapping pair is found from the extrinsics and the
    bag's CameraInfos, and the nodes get a rig file that names it."""
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.replay import resolve_rig
    data = yaml.safe_load((stereo_bag / 'rig.yaml').read_text())
    data.pop('stereo_pairs')
    (tmp_path / 'unnamed.yaml').write_text(yaml.safe_dump(data))
    rig, path = resolve_rig(Rosbag2Reader(stereo_bag), str(tmp_path / 'unnamed.yaml'))
    assert rig.stereo_pairs == (('left', 'right'),)
    assert path != tmp_path / 'unnamed.yaml' and load_rig(path).stereo_pairs == (('left', 'right'),)
    data['stereo_pairs'] = []                               # named as none
    (tmp_path / 'none.yaml').write_text(yaml.safe_dump(data))
    rig, path = resolve_rig(Rosbag2Reader(stereo_bag), str(tmp_path / 'none.yaml'))
    assert rig.stereo_pairs == () and path == tmp_path / 'none.yaml'


def test_quarter_state_carries_its_stereo_partner(stereo_bag):
    """get_state/set_state (migration, crash recovery) mid-run: the quarter continues with its
    partner and the same stereo landmarks, bit for bit."""
    import pickle
    from camera_pose_nodes.camera_model import intrinsics_from_msg
    from camera_pose_nodes.image_conversion import image_msg_to_gray
    from camera_pose_nodes.quarter_estimator import QuarterEstimator, QuarterParams
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.ros_plumbing.pose_messages import pose_to_T, stamp_to_ns
    rig = load_rig(stereo_bag / 'rig.yaml')
    reader = Rosbag2Reader(stereo_bag)
    info, frames, gt = {}, {}, {}
    for topic, msg, _ in reader.decoded(['/left/camera_info', '/right/camera_info', '/left/image_raw',
                                         '/right/image_raw', '/ground_truth/odom']):
        if topic.endswith('camera_info'):
            info.setdefault(topic.split('/')[1], intrinsics_from_msg(msg))
        elif topic == '/ground_truth/odom':
            gt[stamp_to_ns(msg.header.stamp)] = pose_to_T(msg.pose.pose)
        else:
            frames.setdefault(stamp_to_ns(msg.header.stamp), {})[topic.split('/')[1]] = image_msg_to_gray(msg)
    stamps = sorted(frames)[:12]

    def make():
        q = QuarterEstimator(rig.camera('left'), 3, info['left'], QuarterParams(), floor_z=None)
        q.set_partner(rig.camera('right'), info['right'])
        return q

    def step(q, t):
        e = q.process_image(t, frames[t]['left'])
        q.apply_fused_pose(t, gt[t], np.eye(6) * 1e-6, frames[t]['right'])
        return e

    a, b = make(), make()
    ests_a = [step(a, t) for t in stamps]
    for t in stamps[:6]:
        step(b, t)
    c = QuarterEstimator(rig.camera('left'), 3, info['left'], QuarterParams(), floor_z=None)
    c.set_state(pickle.loads(pickle.dumps(b.get_state())))
    assert c.wants_partner_image
    ests_c = [step(c, t) for t in stamps[6:]]
    assert all(e.n_landmarks > 10 for e in ests_a[2:])      # stereo landmarks from the start
    for ea, ec in zip(ests_a[6:], ests_c):
        assert np.array_equal(ea.T_odom_base, ec.T_odom_base) and ea.n_landmarks == ec.n_landmarks
