"""Real roads: the KITTI regression suite, test/suites/kitti.yaml, run through `ego-motion
check` when ../shared/datasets holds the sequences (KITTI may not be committed; without them
the tests are skipped with the reason). Each case is imported as `ego-motion import-kitti`
does (monocular, every second frame, image halves, a stereo pair with or without knowing it
overlaps), replayed through the whole graph in lockstep on 2 workers without a wheel, and
must keep its ATE and final drift and give every frame its /odom; where the road is the only
scale source, by the mean of three replays (the suite's `repeat`: one replay is chaotic there).
One road replay is also run through the sequential pipeline, which must give its /odom bit for
bit. About 6 minutes on two cores."""
from pathlib import Path

import pytest

from conftest import assert_suite_bag, check_suite
from multicam_ego_motion.check.suite import load_suite

SUITE = Path(__file__).resolve().parent / 'suites' / 'kitti.yaml'
DATASETS = Path(__file__).resolve().parents[2] / 'shared' / 'datasets'
SEQUENCES = ('kitti07_mono', 'kitti_seq1')
BAGS = ('kitti07_mono', 'kitti07_mono_5hz', 'kitti07_mono_halves', 'kitti_seq1_stereo',
        'kitti_seq1_stereo_5hz', 'kitti_seq1_road', 'kitti_seq1_halves')
FRAMES = {'kitti07_mono': 160, 'kitti07_mono_5hz': 80, 'kitti07_mono_halves': 160, 'kitti_seq1_stereo': 51,
          'kitti_seq1_stereo_5hz': 26, 'kitti_seq1_road': 51, 'kitti_seq1_halves': 51}

missing = [s for s in SEQUENCES if not (DATASETS / s / 'poses.txt').is_file()]
pytestmark = pytest.mark.skipif(bool(missing), reason=f'KITTI sequences not in {DATASETS}: {", ".join(missing)}')


@pytest.fixture(scope='module')
def check_root(tmp_path_factory):
    return tmp_path_factory.mktemp('kitti')


@pytest.fixture(scope='module')
def results(check_root):
    return check_suite(SUITE, check_root, timeout=1200)


def road_warp_tracks(output_bag):
    """Per quarter, the tracks it found on the road-warped image over the replay (its
    /diagnostics' road_warp_tracks)."""
    from rosbags.highlevel import AnyReader
    total = {}
    with AnyReader([output_bag]) as reader:
        conns = [c for c in reader.connections if c.topic == '/diagnostics']
        for c, _, raw in reader.messages(connections=conns):
            for st in reader.deserialize(raw, c.msgtype).status:
                v = {kv.key: kv.value for kv in st.values}
                if 'road_warp_tracks' in v:
                    total[st.name] = total.get(st.name, 0) + int(v['road_warp_tracks'])
    return total


def test_suite_holds_every_case_of_the_real_road_targets():
    suite = load_suite(SUITE)
    assert tuple(b.name for b in suite.bags) == BAGS
    assert all(b.no_wheel and b.workers == 2 and b.limits['odometry_share'] == 1.0 for b in suite.bags)
    assert all({'ate_pct', 'final_drift_pct'} <= set(b.limits) for b in suite.bags)
    kinds = {b.name: b.import_kitti for b in suite.bags}
    assert kinds['kitti07_mono_5hz'].every == 2 and kinds['kitti_seq1_road'].no_stereo
    assert kinds['kitti_seq1_halves'].halves and kinds['kitti07_mono_halves'].halves
    # the road cases, chaotic one replay at a time, by the mean of three
    road = {b.name for b in suite.bags if b.repeat is not None}
    assert road == set(BAGS) - {'kitti_seq1_stereo', 'kitti_seq1_stereo_5hz'}
    assert all(len(b.repeat.values) == 3 for b in suite.bags if b.repeat)


@pytest.mark.parametrize('name', BAGS)
def test_real_road_accuracy(results, name):
    assert_suite_bag(results, name, FRAMES[name])


def test_lost_road_tracks_are_found_on_the_road_warped_image(results, check_root):
    """A car's step at 10 Hz makes the near road patches grow and shear: the lower quarters'
    road tracks that Lucas-Kanade loses are searched again on the road-warped image
    (floor_warp_min_flow_px) and the quarters say how many they found (203 over the drive at
    quality_level 0.01); the upper quarters (above the horizon) and a stereo rig (not a road
    rig: no warp) find none."""
    check = check_root / 'check'
    mono = road_warp_tracks(check / 'kitti07_mono' / 'quality_level=0.01' / 'output')
    assert len(mono) == 4, sorted(mono)
    print(f'\nKITTI 07, tracks found on the road-warped image: {mono}')
    assert mono['ego_motion/left/q3'] + mono['ego_motion/left/q4'] >= 100
    assert mono['ego_motion/left/q1'] == mono['ego_motion/left/q2'] == 0
    stereo = road_warp_tracks(check / 'kitti_seq1_stereo' / 'output')
    assert len(stereo) == 8 and not any(stereo.values()), stereo


def test_a_road_replay_is_the_sequential_pipeline_bit_for_bit(results, check_root):
    """The lockstep graph (quarter nodes on 2 workers, camera arbiters, the general arbiter,
    over DDS) and the sequential pipeline, given the params file the replay used, publish the
    same /odom on a road rig, bit for bit. On a road a difference in the last bit of any
    number moves a drive's figures by up to 2x, so a parameter that one of them reads
    differently (the camera arbiters' gate once was) or an order that differs would make the
    sequential pipeline's measurements those of another product. kitti_seq1's outer halves:
    two cameras, each fused from its quarters, the road the only scale source."""
    import numpy as np
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.check.bags import cached_bag
    from multicam_ego_motion.params_file import (camera_fusion_params_from, fusion_params_from,
                                                 quarter_params_from, sync_window_from)
    from multicam_ego_motion.replay import resolve_rig
    from multicam_ego_motion.ros_plumbing.pose_messages import estimate_to_msg, msg_to_estimate, pose_to_T
    from multicam_ego_motion.sequential_pipeline import run_sequential
    from camera_pose_nodes.pose_estimate import PoseEstimate

    entry = next(b for b in load_suite(SUITE).bags if b.name == 'kitti_seq1_halves')
    bag = cached_bag(check_root / 'bags', entry.import_kitti)
    replay = check_root / 'check' / entry.name / 'quality_level=0.01'
    params = replay / 'params.yaml'
    assert quarter_params_from(params)['quality_level'] == 0.01
    graph = np.array([pose_to_T(m.pose.pose)
                      for _, m, _ in Rosbag2Reader(replay / 'output').decoded(['/odom'])])
    rig, _ = resolve_rig(Rosbag2Reader(bag), None)
    res = run_sequential(bag, rig, quarter_params_from(params), fusion_params_from(params),
                         use_wheel=False, sync_window_s=sync_window_from(params),
                         camera_fusion_params=camera_fusion_params_from(params))
    # as /odom carries it: a quaternion
    sequential = np.array([msg_to_estimate(estimate_to_msg(
        PoseEstimate(f.stamp_ns, f.T_odom_base, f.pose_covariance))).T_odom_base for f in res.fused])
    assert len(graph) == len(sequential) == FRAMES[entry.name]
    print(f'\nkitti_seq1 halves: largest difference graph - sequential '
          f'{np.abs(graph - sequential).max():.3g} m over {len(graph)} poses')
    assert np.array_equal(graph, sequential)
