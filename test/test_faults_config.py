"""Fault injection, calibration and configuration: bad intrinsics, a rig that does not fit
the bag or is not a rigid transform, a params file value out of its declared range.

Bad intrinsics degrade only their camera (reported in /diagnostics); a bad rig or params
file is rejected at start with one line naming the problem, without waiting for the graph.
"""
import pytest
import yaml

import fault_injection as fi
from fault_replays import EXTRA_CAMERA, FRAMES
from replay_run import replay
from test_faults_bags import assert_one_line_error

ERROR = 2


def camera_diags(run, camera):
    return run.diagnostics(f'ego_motion/{camera}/q')


@pytest.mark.parametrize('camera,problem', [('front', 'CameraInfo has NaN/inf in k or d'),
                                            ('left', 'focal length must be > 0 (fx=0.0')])
def test_bad_focal_length_degrades_only_that_camera(calibration_run, camera, problem):
    diags = camera_diags(calibration_run, camera)
    assert {d.name for d in diags} == {f'ego_motion/{camera}/q{q}' for q in range(1, 5)}
    assert all(d.level == ERROR and 'bad CameraInfo' in d.message and problem in d.message
               for d in diags), {d.message for d in diags}
    assert calibration_run.messages(f'/{camera}/pose') == []   # never fused


def test_rig_camera_without_topics_runs_on_the_others(calibration_run):
    run = calibration_run
    assert run.returncode == 0, run
    assert f'cameras without topics in the bag (the graph runs on the others): {EXTRA_CAMERA}' in run.stdout
    arbiter = run.diagnostics('ego_motion/general_arbiter')
    assert len(arbiter) == FRAMES
    assert all(EXTRA_CAMERA in d.values['cameras_missing'].split(',') for d in arbiter)
    stamps = run.odometry()[0]
    assert len(stamps) == FRAMES and run.odom_problems() == []
    assert run.leftover_processes() == []


@pytest.mark.parametrize('rotation,words', [
    ({'rotation': [[0, 0, 1], [-1, 0, 0], [0, -0.5, 0.2]]}, ['camera front', 'rotation is not orthonormal']),
    ({'rotation_xyzw': [0.5, -0.5, 0.5, -0.9]}, ['camera front', 'not a unit quaternion']),
])
def test_rig_rotation_that_is_not_a_rotation_is_a_clear_error(tmp_path, rotation, words):
    bag = fi.rewrite_bag(tmp_path / 'bag', 1)
    rig = yaml.safe_load((bag / 'rig.yaml').read_text())
    front = rig['cameras'][0]
    front.pop('rotation_xyzw')
    front.update(rotation)
    (bag / 'rig.yaml').write_text(yaml.safe_dump(rig))
    run = replay(bag, tmp_path / 'out', timeout=60)
    assert_one_line_error(run, str(bag / 'rig.yaml'), *words)


def test_params_value_out_of_range_fails_fast_with_the_range(tmp_path):
    params = (fi.REPO / 'config' / 'params.yaml').read_text()
    assert 'min_features: 40' in params
    bad = tmp_path / 'params.yaml'
    bad.write_text(params.replace('min_features: 40', 'min_features: 0'))
    bag = fi.rewrite_bag(tmp_path / 'bag', 1)
    run = replay(bag, tmp_path / 'out', '--params', bad, timeout=120)
    # The worker rejects the value while creating its nodes; the replay surfaces its message
    # (naming the parameter and its range) instead of waiting for a graph that will never come
    # up and reporting that.
    assert_one_line_error(run, 'min_features', 'allowed range [4, 1000]', 'quarter_node',
                          graph_started=True)
    assert run.leftover_processes() == []
