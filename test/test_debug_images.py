"""Debug images (`debug_images`, `ego-motion replay --debug-images`): off by default with
nothing extra subscribed or published; on, every camera's /<cam>/tracks is recorded, one per
frame, the camera's size, its pixels the camera's own except where features are drawn."""
from pathlib import Path

import numpy as np
import pytest

from camera_pose_nodes.track_image import COLORS
from conftest import REPO, read_bag, run_cli
from multicam_ego_motion.replay import graph_overrides, recorded_topics
from multicam_ego_motion.geometry.rig import load_rig

DEFAULT_BAG = REPO / 'bags' / 'default'
RIG = DEFAULT_BAG / 'rig.yaml'
DURATION_S, RATE_HZ = 2, 8
FRAMES = DURATION_S * RATE_HZ
CAPTION_ROWS = 25                   # each quarter's caption, top-left of its part


def test_off_by_default_nothing_subscribed_or_published(rclpy_context):
    from rclpy.parameter import Parameter

    from arbiter_node.camera_arbiter_node import CameraArbiterNode
    from camera_pose_nodes.quarter_node import QuarterNode
    nodes = [QuarterNode(shared_inputs=True, namespace='/front/q1', parameter_overrides=[
                 Parameter('camera', value='front'), Parameter('rig_file', value=str(RIG))]),
             CameraArbiterNode(namespace='/front')]
    try:
        for n in nodes:
            assert n.get_parameter('debug_images').value is False
            topics = [e.topic_name for e in list(n.publishers) + list(n.subscriptions)]
            assert topics and not [t for t in topics if t.endswith('tracks')], topics
    finally:
        for n in nodes:
            n.destroy_node()
    rig = load_rig(RIG)
    off = graph_overrides(True, True)
    assert all('debug_images' not in v for v in off.values())
    assert not [t for t in recorded_topics(rig) if 'tracks' in t]
    on = graph_overrides(True, True, debug_images=True)
    assert on['quarter']['debug_images'] and on['camera_arbiter']['debug_images']
    assert [t for t in recorded_topics(rig, True) if 'tracks' in t] == \
        ['/front/tracks', '/left/tracks', '/back/tracks', '/right/tracks']


@pytest.fixture(scope='module')
def replayed(tmp_path_factory):
    """--migrate-every: the front quarters move one by one to the other worker, so their
    camera arbiter takes tiles by a call from the quarters it hosts and by subscription
    from the others."""
    out = tmp_path_factory.mktemp('debug_images') / 'run'
    r = run_cli('replay', DEFAULT_BAG, '--out', out, '--workers', 2, '--duration', DURATION_S,
                '--debug-images', '--migrate-every', 3, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return out, r.stdout


def ns(stamp):
    return stamp.sec * 10**9 + stamp.nanosec


def test_replay_records_every_cameras_tracks_one_per_frame(replayed):
    out, stdout = replayed
    assert 'moved ' in stdout
    topics, messages = read_bag(out / 'output')
    for cam in ('front', 'left', 'back', 'right'):
        assert topics[f'/{cam}/tracks'] == ('sensor_msgs/msg/Image', FRAMES), topics
    odom = sorted(ns(m.header.stamp) for t, _, m in messages if t == '/odom')
    for cam in ('front', 'left', 'back', 'right'):
        stamps = [ns(m.header.stamp) for t, _, m in messages if t == f'/{cam}/tracks']
        assert stamps == odom


def test_front_tracks_are_the_camera_image_with_the_features_drawn(replayed):
    out, _ = replayed
    _, bag = read_bag(DEFAULT_BAG)
    plain = {ns(m.header.stamp): np.frombuffer(m.data, np.uint8).reshape(m.height, m.width)
             for t, _, m in bag if t == '/front/image_raw'}
    _, messages = read_bag(out / 'output')
    tracks = [m for t, _, m in messages if t == '/front/tracks']
    features = {}                           # (stamp, quarter) -> features it reported
    for t, _, m in messages:
        if t == '/diagnostics':
            for s in m.status:
                v = {kv.key: kv.value for kv in s.values}
                if s.name.startswith('ego_motion/front/q') and 'features' in v:
                    features[ns(m.header.stamp), int(s.name[-1])] = int(v['features'])
    colors = np.array(list(COLORS.values()), np.uint8)
    drawn_frames = complete = 0
    for m in tracks:
        assert (m.encoding, m.width, m.height, m.step) == ('bgr8', 320, 240, 960)
        assert m.header.frame_id == 'front_optical'
        img = np.frombuffer(m.data, np.uint8).reshape(240, 320, 3)
        gray = plain[ns(m.header.stamp)]
        same = np.all(img == gray[:, :, None], axis=2)        # the camera's own pixel
        status_color = np.any(np.all(img[:, :, None, :] == colors, axis=3), axis=2)
        quarters_ok = []
        for q, (y0, x0) in enumerate(((0, 0), (0, 160), (120, 0), (120, 160)), start=1):
            part = np.s_[y0 + CAPTION_ROWS:y0 + 120, x0:x0 + 160]
            # outside its caption a quarter's part is the image, or a feature or its flow line
            n_feat = features[ns(m.header.stamp), q]
            quarters_ok.append(not (~same[part] & ~status_color[part]).any()
                               and same[part].mean() > 0.85
                               and status_color[part].sum() >= 8 * n_feat)
            drawn_frames += n_feat > 0
        complete += all(quarters_ok)
    assert drawn_frames >= 4 * (FRAMES - 1)       # the first frame has no tracks yet
    # a tile published just as its quarter moved may miss its arbiter (a dark quarter)
    assert complete >= FRAMES - 1, complete
