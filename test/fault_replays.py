"""Session fixtures of the fault-injection suite: the faulty bags and one replay of each.

A replay costs about half a minute on a loaded 2-core machine, so faults that do not
interfere share one bag (and one replay), and every test module reads the same runs.
All bags are the first 6 s (48 frames at 8 Hz) of bags/default; times are seconds from the
start of the bag. Registered as a plugin in conftest.py (pytest_plugins).
"""
import math

import pytest
import yaml

import fault_injection as fi
from multicam_ego_motion.ros_plumbing import ros_domain
from replay_run import replay, replay_env

SECONDS = 6
FRAMES = SECONDS * 8

# Camera faults that leave at least one camera working at every moment.
CAMERA_FAULTS = dict(
    float_camera='front',            # 32FC1 (a depth image's encoding) for the whole run
    mono16_camera='left',            # 16UC1 for the whole run
    resized_camera='back', resized=(1.0, 2.0),   # 160x120 images, CameraInfo says 320x240
    stopped_camera='right', stopped=(2.5, 4.0),  # no image, no CameraInfo, then back
)
# Photometric faults, all cameras but `right` at once.
PHOTOMETRIC = {'front': 'black', 'left': 'saturated', 'back': 'blurred'}
PHOTOMETRIC_WINDOW = (1.5, 3.5)
# Timing faults: the front driver drops every third frame (only over a window: in lockstep
# each drop costs the general arbiter's sync timeout, see test_faults_images.py), one frame
# is delivered twice, two frames arrive swapped.
DROP_WINDOW = (3.5, 5.5)
DUPLICATED_FRAME, SWAPPED_FRAME = 10, 20
# Calibration: front fx = NaN, left fx = 0, back without CameraInfo, rig names a 5th camera.
EXTRA_CAMERA = 'top'


@pytest.fixture(scope='session')
def fault_dir(tmp_path_factory):
    return tmp_path_factory.mktemp('faults')


@pytest.fixture(scope='session')
def clean_run(fault_dir):
    """The reference: the same 6 s without faults, on a ROS_DOMAIN_ID the user set."""
    bag = fi.rewrite_bag(fault_dir / 'clean', SECONDS)
    out = fault_dir / 'clean_out'
    domain = str(ros_domain.reserve_domain())
    run = replay(bag, out, env=replay_env(out, ROS_DOMAIN_ID=domain))
    run.user_domain = domain
    return run


@pytest.fixture(scope='session')
def camera_faults_run(fault_dir):
    c = CAMERA_FAULTS
    bag = fi.rewrite_bag(fault_dir / 'camera_faults', SECONDS,
                         fi.encoding(c['float_camera'], '32FC1'),
                         fi.encoding(c['mono16_camera'], '16UC1'),
                         fi.resize(c['resized_camera'], 160, 120, *c['resized']),
                         fi.stop_stream(c['stopped_camera'], *c['stopped']))
    return replay(bag, fault_dir / 'camera_faults_out')


@pytest.fixture(scope='session')
def photometric_run(fault_dir):
    edits = [fi.photometric(cam, kind, *PHOTOMETRIC_WINDOW) for cam, kind in PHOTOMETRIC.items()]
    bag = fi.rewrite_bag(fault_dir / 'photometric', SECONDS, *edits)
    return replay(bag, fault_dir / 'photometric_out')


@pytest.fixture(scope='session')
def timing_run(fault_dir):
    # Swap before duplicating: a duplicate adds a frame and would shift the indices.
    bag = fi.rewrite_bag(fault_dir / 'timing', SECONDS, fi.drop_every('front', 3, *DROP_WINDOW),
                         fi.swap_frames(SWAPPED_FRAME), fi.duplicate_frame(DUPLICATED_FRAME))
    return replay(bag, fault_dir / 'timing_out')


@pytest.fixture(scope='session')
def calibration_run(fault_dir):
    bag = fi.rewrite_bag(fault_dir / 'calibration', SECONDS,
                         fi.focal_length('front', math.nan), fi.focal_length('left', 0.0),
                         fi.drop_topic('/back/camera_info'))
    rig = yaml.safe_load((bag / 'rig.yaml').read_text())
    extra = dict(rig['cameras'][0], name=EXTRA_CAMERA, image_topic=f'/{EXTRA_CAMERA}/image_raw',
                 camera_info_topic=f'/{EXTRA_CAMERA}/camera_info', frame_id=f'{EXTRA_CAMERA}_optical')
    rig['cameras'].append(extra)
    (bag / 'rig.yaml').write_text(yaml.safe_dump(rig, sort_keys=False))
    return replay(bag, fault_dir / 'calibration_out')
