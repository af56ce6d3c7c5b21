"""An IMU through the whole graph (real nodes over DDS, 2 workers, lockstep): spin_then_drive
(seed 7, 20 s at 8 Hz, 320x240: it spins in place for its first 6.7 s, then drives) without
wheel and without a floor, so nothing but the cameras and the gyro. The rig file names no IMU:
replay finds it from the bag (/imu/data in imu_link, placed in /tf_static, off and turned from
base_link). With it the spin ends within 2 deg of the truth (17 deg without: the quarters'
maps do not hold through a 1.9 rad/s spin) and the drive keeps its heading. The IMU is
opt-in (`--imu`, the general arbiter's use_imu): without it the cameras-only run."""
import math

import numpy as np
import pytest
import yaml

from conftest import run_cli
from replay_run import ground_truth, replay

END_OF_SPIN_S = 7.25          # the spin ends at 6.67 s; the first frames at rest after it
FRAMES = 20 * 8 + 1


@pytest.fixture(scope='module')
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp('imu')
    bag = root / 'spin'
    r = run_cli('generate', '--scenario', 'spin_then_drive', '--seed', 7, '--duration', 20, '--rate', 8,
                '--width', 320, '--height', 240, '--fx', 200, '--imu-rate', 200, '--out', bag, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    rig = yaml.safe_load((bag / 'rig.yaml').read_text())
    rig.pop('floor_z')
    rig.pop('imu')                    # as a rig file written for the cameras only
    (root / 'rig.yaml').write_text(yaml.safe_dump(rig))
    return {k: replay(bag, root / k, '--no-wheel', '--rig', root / 'rig.yaml', *extra, timeout=600)
            for k, extra in (('imu', ('--imu',)), ('cameras', ()))}


def heading_errors(run):
    """{t: heading error in deg} of every /odom."""
    t, T, _, _ = run.odometry()
    gt = ground_truth(run.bag, run.start_ns)
    yaw = lambda P: math.atan2(P[1, 0], P[0, 0])
    return {round(s, 6): math.degrees(math.remainder(yaw(P) - yaw(gt[round(s, 6)]), 2 * math.pi))
            for s, P in zip(t, T)}


def tilt_errors(run):
    """The angle (deg) between each /odom's up axis and the truth's."""
    t, T, _, _ = run.odometry()
    gt = ground_truth(run.bag, run.start_ns)
    return [math.degrees(math.acos(min(1.0, float(P[:3, 2] @ gt[round(s, 6)][:3, 2])))) for s, P in zip(t, T)]


def final_drift_pct(run) -> float:
    t, T, _, _ = run.odometry()
    gt = ground_truth(run.bag, run.start_ns)
    p_gt = np.array([gt[round(s, 6)][:3, 3] for s in t])
    path = np.sum(np.linalg.norm(np.diff(p_gt, axis=0), axis=1))
    return 100.0 * np.linalg.norm(T[-1][:3, 3] - p_gt[-1]) / path


def test_the_gyro_carries_the_heading_through_the_spin(runs):
    run = runs['imu']
    assert run.returncode == 0, run
    assert 'rig: IMU on /imu/data in imu_link' in run.stdout
    err = heading_errors(run)
    assert len(err) == FRAMES
    at = min(err, key=lambda s: abs(s - END_OF_SPIN_S))
    assert abs(err[at]) <= 2.0, (at, err[at])               # measured -0.58 (-1.17 without imu_gravity)
    assert max(abs(e) for e in err.values()) <= 3.0
    # the whole drive on it: 2.54 % (2.68 without imu_gravity, cameras only 18.4 %; the target is 3 %)
    assert final_drift_pct(run) <= 3.0


def test_the_accelerometer_holds_roll_and_pitch_without_a_floor(runs):
    """No floor: nothing but the accelerometer says which way is up (imu_gravity). The spin
    tells its bias from a tilt (sequential pipeline: at most 0.22 deg off the truth's up over
    the run; 0.61 deg without imu_gravity, the cameras' own tilt)."""
    run = runs['imu']
    tilt = tilt_errors(run)
    assert len(tilt) == FRAMES
    assert max(tilt) <= 0.4, max(tilt)
    # said on /diagnostics: the steps whose accelerometer measured up (72 of 160 in the
    # sequential pipeline; the others accelerate, or turn, beyond what the filter's twist has)
    last = run.diagnostics('ego_motion/general_arbiter')[-1].values
    assert int(last['gravity_fixes']) >= 40, last
    assert len(last['accel_bias_m_s2'].split()) == 3


def test_without_the_imu_the_cameras_alone_lose_the_spin(runs):
    run = runs['cameras']
    assert run.returncode == 0, run
    assert 'rig: IMU on /imu/data' in run.stdout          # found, and left out (use_imu off)
    err = heading_errors(run)
    at = min(err, key=lambda s: abs(s - END_OF_SPIN_S))
    assert abs(err[at]) > 10.0, (at, err[at])               # measured 17.2
    assert final_drift_pct(run) > 10.0                      # measured 18.4
