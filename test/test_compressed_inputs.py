"""Bags as robots record them: JPEG CompressedImage on image_transport's
`<image topic>/compressed`, replayed through the real graph (real nodes, DDS, MCAP).

The default bag's scene (the loop, seed 7, 20 s at 8 Hz, 320x240) generated raw and JPEG
(quality 90), the first 6 s of each replayed: the JPEG replay's ATE at most 10 % above the raw
one's (JPEG's loss must not cost accuracy; over 6 s it came out lower, 0.014 against 0.016 m). The JPEG bag's rig file says `raw` (as a rig written for the robot's raw
stream would): replay takes the compressed stream the bag has. A bag with corrupt JPEGs on
one camera and no rig file (the rig from /tf_static and the compressed topics): that camera
is reported naming the topic, the graph keeps publishing /odom for every frame.
"""
import re
import shutil

import pytest

from fault_injection import Item, load_items
from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
from multicam_ego_motion.bag.rosbag2_writer import Rosbag2Writer
from multicam_ego_motion.scenarios.generator import generate
from replay_run import replay

# (the whole loop is generated: a shorter duration would drive the loop faster)
SCENE = dict(scenario='loop', seed=7, duration=20.0, rate=8.0, width=320, height=240, progress=False)
SECONDS, FRAMES = 6, 48
CORRUPT_CAMERA, CORRUPT_WINDOW = 'left', (2.0, 3.0)   # seconds from the bag's start


def ate_m(run) -> float:
    assert run.returncode == 0, run
    m = re.search(r'ATE RMSE, aligned on first pose \[m\]\s+([0-9.]+)', run.stdout)
    assert m, run.stdout[-2000:]
    return float(m.group(1))


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    d = tmp_path_factory.mktemp('compressed')
    generate(out=d / 'raw', **SCENE)
    generate(out=d / 'jpeg', image_codec='jpeg', jpeg_quality=90, **SCENE)
    shutil.copy(d / 'raw' / 'rig.yaml', d / 'jpeg' / 'rig.yaml')     # a rig that says raw
    return d


@pytest.fixture(scope='module')
def raw_run(bags):
    return replay(bags / 'raw', bags / 'raw_out', '--duration', SECONDS)


@pytest.fixture(scope='module')
def jpeg_run(bags):
    return replay(bags / 'jpeg', bags / 'jpeg_out', '--duration', SECONDS)


def test_the_generated_bag_holds_compressed_images(bags):
    reader = Rosbag2Reader(bags / 'jpeg')
    assert reader.topics['/front/image_raw/compressed'] == 'sensor_msgs/msg/CompressedImage'
    assert '/front/image_raw' not in reader.topics
    _, msg, _ = next(iter(reader.decoded(['/front/image_raw/compressed'])))
    assert msg.format == 'mono8; jpeg compressed mono8' and bytes(msg.data[:2]) == b'\xff\xd8'


def test_jpeg_bag_replays_no_more_than_ten_percent_above_the_raw_ate(raw_run, jpeg_run):
    assert 'camera front: the bag has its compressed images' in jpeg_run.stdout, jpeg_run.stdout[-3000:]
    assert len(jpeg_run.odometry()[0]) == FRAMES and jpeg_run.odom_problems() == []
    raw, jpeg = ate_m(raw_run), ate_m(jpeg_run)
    assert raw < 0.05, raw          # the raw run tracks (else the comparison would say nothing)
    assert jpeg <= 1.10 * raw, (raw, jpeg)


def test_corrupt_jpegs_are_reported_and_the_graph_goes_on(bags, tmp_path):
    def corrupt(it):
        if it.topic == f'/{CORRUPT_CAMERA}/image_raw/compressed' and \
                CORRUPT_WINDOW[0] <= it.t < CORRUPT_WINDOW[1]:
            it.msg.data = it.msg.data[:64]        # a cut-off JPEG: its header and nothing else
        return it
    bag = tmp_path / 'corrupt'
    with Rosbag2Writer(bag) as w:     # no rig file: the rig comes from /tf_static
        for it in load_items(SECONDS, src=bags / 'jpeg'):
            w.write(it.topic, corrupt(Item(it.topic, it.log_ns, it.t, it.msg)).msg, it.log_ns)
    run = replay(bag, tmp_path / 'out')
    assert run.returncode == 0, run
    assert len(run.odometry()[0]) == FRAMES and run.odom_problems() == []
    assert run.leftover_processes() == []
    bad = [d for d in run.diagnostics(f'ego_motion/{CORRUPT_CAMERA}/q') if d.level == 2]
    assert bad and all(f'/{CORRUPT_CAMERA}/image_raw/compressed' in d.message for d in bad)
    assert {round(d.t, 3) for d in bad} <= {round(t / 8, 3) for t in range(16, 24)}
    assert all(d.level < 2 for d in run.diagnostics('ego_motion/front/q'))
