"""Fault injection, images: bad pixels, bad timing and missing frames on some cameras.

Expected: the affected camera is reported degraded in /diagnostics (naming the problem),
the rest of the graph keeps publishing /odom for every frame, never NaN nor a singular
covariance, and once good input returns the odometry drifts no more than twice as much as
in the clean run over the same stretch.
"""
import numpy as np
import pytest

from fault_replays import (CAMERA_FAULTS, DROP_WINDOW, DUPLICATED_FRAME, FRAMES, PHOTOMETRIC,
                           PHOTOMETRIC_WINDOW, SWAPPED_FRAME)
from replay_run import segment_drift

ERROR, WARN = 2, 1
FRAME_S = 0.125
END = (FRAMES - 1) * FRAME_S
# Clean-run drift over a couple of metres is a few centimetres: below this, "2x" is noise.
DRIFT_FLOOR_M = 0.05


def quarter_diags(run, camera):
    return run.diagnostics(f'ego_motion/{camera}/q')


def states_by_frame(run, camera):
    """{t: [state of each quarter that reported a state]}."""
    out = {}
    for d in quarter_diags(run, camera):
        if 'state' in d.values:
            out.setdefault(round(d.t, 3), []).append(d.values['state'])
    return out


def arbiter_values(run):
    return [(round(d.t, 3), d.values) for d in run.diagnostics('ego_motion/general_arbiter')]


def assert_odometry_sane(run, frames=FRAMES):
    assert run.returncode == 0, run
    stamps = run.odometry()[0]
    assert len(stamps) == frames and list(stamps) == sorted(set(stamps))
    assert run.odom_problems() == []
    assert run.leftover_processes() == []


def assert_recovered_drift(run, clean_run, t_from, factor=2.0):
    fault = segment_drift(run, t_from, END)
    clean = segment_drift(clean_run, t_from, END)
    assert fault <= max(factor * clean, DRIFT_FLOOR_M), (fault, clean)


# ---- camera faults (one replay: 32FC1, 16UC1, wrong size for 1 s, a stream that stops) ----

def test_camera_faults_leave_the_rest_running(camera_faults_run):
    assert_odometry_sane(camera_faults_run)


@pytest.mark.parametrize('camera,encoding', [(CAMERA_FAULTS['float_camera'], '32FC1'),
                                             (CAMERA_FAULTS['mono16_camera'], '16UC1')])
def test_unknown_encoding_is_reported_for_that_camera(camera_faults_run, camera, encoding):
    diags = quarter_diags(camera_faults_run, camera)
    assert {d.name for d in diags} == {f'ego_motion/{camera}/q{q}' for q in range(1, 5)}
    assert len(diags) == 4 * FRAMES               # every frame, every quarter
    assert all(d.level == ERROR and f"encoding '{encoding}' is not supported" in d.message
               for d in diags)
    for _, v in arbiter_values(camera_faults_run):
        assert camera in v['cameras_missing'].split(',')


def test_image_size_disagreeing_with_camera_info_is_reported_then_recovers(camera_faults_run):
    camera, (t0, t1) = CAMERA_FAULTS['resized_camera'], CAMERA_FAULTS['resized']
    diags = quarter_diags(camera_faults_run, camera)
    bad = [d for d in diags if 'image is 160x120 but CameraInfo says 320x240' in d.message]
    assert bad and all(d.level == ERROR for d in bad)
    assert {round(d.t, 3) for d in bad} == set(np.arange(t0, t1, FRAME_S).round(3))
    used_after = [t for t, v in arbiter_values(camera_faults_run)
                  if t >= t1 and camera in v['cameras_used'].split(',')]
    assert used_after, 'the camera is never fused again after its images fit again'


def test_stopped_camera_is_reported_missing_then_used_again(camera_faults_run):
    camera, (t0, t1) = CAMERA_FAULTS['stopped_camera'], CAMERA_FAULTS['stopped']
    values = arbiter_values(camera_faults_run)
    during = [v for t, v in values if t0 <= t < t1]
    assert during and all(camera in v['cameras_missing'].split(',') for v in during)
    # Right after the stream returns, a frame may still be released without it: an absent
    # camera is not waited for, so its first estimates (re-extracting after the gap) race
    # the others'. Once one of them has arrived it is awaited again (measured: 2 frames late
    # here; allow up to 1 s on a loaded machine), and from then on never missing.
    rejoin = 1.0
    after = [v for t, v in values if t >= t1 + rejoin]
    assert after and all(camera not in v['cameras_missing'].split(',') for v in after)
    assert any(camera in v['cameras_used'].split(',') for v in after)


# ---- photometric faults (black, saturated, blurred for 2 s at once) ---------------------

def test_photometric_faults_survive_and_recover(photometric_run, clean_run):
    run = photometric_run
    assert_odometry_sane(run)
    t0, t1 = PHOTOMETRIC_WINDOW
    recovered_at = t1
    for camera, kind in PHOTOMETRIC.items():
        states = states_by_frame(run, camera)
        if kind in ('black', 'saturated'):    # nothing to track: never claims to track
            inside = [s for t, ss in states.items() if t0 + FRAME_S <= t < t1 for s in ss]
            assert inside and 'tracking' not in inside, (camera, inside)
        recovered = [t for t, ss in states.items() if t >= t1 and ss.count('tracking') == 4]
        assert recovered, f'{camera} ({kind}) never tracks in all quarters again'
        recovered_at = max(recovered_at, min(recovered))
    # "Drift after recovery": from the frame every faulted camera tracks in all quarters
    # again (the cameras must first re-triangulate their landmarks), to the end.
    assert recovered_at <= t1 + 1.0, recovered_at
    # Measured 0.006 m vs 0.029 m clean (was 0.101 m, 3.3x, before the EKF prediction broke
    # the cameras' 2-2 ties in the median and the votes were weighted by precision).
    assert_recovered_drift(run, clean_run, recovered_at)


# ---- timing faults (every third frame dropped for 2 s, a duplicate, a swapped pair) -----

def test_timing_faults(timing_run, clean_run):
    run = timing_run
    # The older frame of the swapped pair arrives after its successor: dropped as stale.
    assert_odometry_sane(run, frames=FRAMES - 1)
    stamps = np.round(run.odometry()[0], 3)
    assert SWAPPED_FRAME * FRAME_S not in stamps
    stale = [d for d in run.diagnostics('ego_motion/') if 'duplicate or out of order' in d.message]
    assert {round(d.t, 3) for d in stale} == {DUPLICATED_FRAME * FRAME_S, SWAPPED_FRAME * FRAME_S}
    assert all(d.level == WARN for d in stale)
    assert len(stale) == 2 * 16                       # every quarter of every camera, twice
    dropped = [t for t, v in arbiter_values(run) if 'front' in v['cameras_missing'].split(',')]
    assert dropped and all(DROP_WINDOW[0] <= t < DROP_WINDOW[1] for t in dropped)
    assert_recovered_drift(run, clean_run, 0.0)
