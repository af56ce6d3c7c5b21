"""The IMU's health (arbiter_node/imu_health), without ROS: each bad IMU of the generator
(scenarios/imu.publish: wrong frame, saturated, stuck, silent, stamps out of order) is
detected and named soon after it starts, a drifted bias estimate is, the gyro comes back
only after recover_s without a problem, and a healthy IMU (the generator's MEMS noise,
bias and walk) is never flagged over whole scenarios."""
import numpy as np
import pytest

from multicam_ego_motion.imu.imu_buffer import ImuBuffer
from multicam_ego_motion.imu.imu_health import ImuHealth, ImuHealthLimits
from multicam_ego_motion.scenarios.imu import (IMU_FAULTS, IMU_FRAME, IMU_ROTATION, SATURATED_RANGE,
                                              WRONG_FRAME, publish, simulate_imu)
from multicam_ego_motion.scenarios.trajectories import SCENARIOS

RATE = 200.0
FRAME_S = 0.125                 # frames at 8 Hz
FAULT_AT = 3.0


def run_monitor(published, duration, bias=lambda t: np.zeros(3)):
    """Feeds the samples as a fusion does (through an ImuBuffer for its refusals), checks at
    every frame; returns [(t, usable, problem)] per frame."""
    buf = ImuBuffer(IMU_ROTATION)
    health = ImuHealth(IMU_FRAME)
    out, k = [], 0
    n = len(published.log_times)
    for t in np.arange(0.0, duration + 1e-9, FRAME_S):
        while k < n and published.log_times[k] <= t + 1e-9:
            stamp = int(round(published.stamps[k] * 1e9))
            frame = published.frame_ids[k]
            refused = buf.add(stamp, published.gyro[k]) if frame == IMU_FRAME else 'wrong frame'
            health.sample(stamp, frame, published.gyro[k], refused)
            k += 1
        usable = health.check(int(round(t * 1e9)), bias(t))
        out.append((round(t, 3), usable, health.problem))
    return out, health


@pytest.mark.parametrize('scenario', ['spin_then_drive', 'loop', 'corridor'])
def test_a_healthy_imu_is_never_flagged(scenario):
    traj = SCENARIOS[scenario](20.0)
    for seed in range(3):
        imu = simulate_imu(traj, RATE, np.random.default_rng(seed))
        frames, health = run_monitor(publish(imu), 20.0)
        assert all(usable for _, usable, _ in frames), [f for f in frames if not f[1]][:3]
        assert health.faults == 0 and health.refused == 0 and health.status()[0] == 'ok'


@pytest.mark.parametrize('fault', [f for f in IMU_FAULTS if f != 'bias_drift'])
def test_each_bad_imu_is_detected_soon_and_named(fault):
    traj = SCENARIOS['spin_then_drive'](10.0)       # turns faster than SATURATED_RANGE to 3.3 s
    imu = simulate_imu(traj, RATE, np.random.default_rng(1))
    frames, health = run_monitor(publish(imu, fault, 2.0, np.random.default_rng(2)), 10.0)
    before = [f for f in frames if f[0] < 2.0]
    assert all(usable for _, usable, _ in before)
    flagged = [(t, p) for t, usable, p in frames if p is not None]
    assert flagged and flagged[0][1] == fault, flagged[:3]
    # detected within two frames (0.25 s)
    assert 2.0 <= flagged[0][0] <= 2.25 + 1e-9 + (0.2 if fault == 'silent' else 0.0), flagged[0]
    assert health.faults >= 1
    level, message, values = health.status() if health.problem else (None, None, None)
    if fault != 'saturated':          # (the clip ends with the spin: recovered by the end)
        assert level == 'error' and f'imu: {fault}:' in message, message
        assert values['imu_state'] == 'fault' and values['imu_problem'] == fault
        assert not values['imu_gyro_used']


def test_saturation_at_the_range_and_the_clip_s_repeats():
    health = ImuHealth(IMU_FRAME, ImuHealthLimits(gyro_saturation=5.0))
    rng = np.random.default_rng(0)
    for k in range(10):
        health.sample(k * 5_000_000, IMU_FRAME, rng.standard_normal(3) * 0.01)
    assert health.check(50_000_000)
    health.sample(55_000_000, IMU_FRAME, [0.0, 0.0, -5.0])
    assert not health.check(60_000_000) and health.problem == 'saturated'
    assert 'gyro z at -5.000 rad/s (limit 5)' in health.detail
    # a clip below any range set: one axis held at one value while the others move
    health = ImuHealth(IMU_FRAME)
    for k in range(30):
        health.sample(k * 5_000_000, IMU_FRAME, [rng.standard_normal() * 0.01, 0.01, SATURATED_RANGE])
    assert not health.check(150_000_000) and health.problem == 'saturated'
    assert 'for 30 samples' in health.detail


def test_out_of_order_jitter_below_the_fraction_is_tolerated():
    buf, health = ImuBuffer(np.eye(3)), ImuHealth(IMU_FRAME)
    rng = np.random.default_rng(3)
    stamps = np.arange(2000) * 5_000_000
    # one sample in 50 comes after its successor: 2 % refused, under the 5 % limit
    for k in range(0, 2000, 50):
        stamps[k], stamps[k + 1] = stamps[k + 1], stamps[k]
    for k, s in enumerate(stamps):
        g = rng.standard_normal(3) * 0.01
        health.sample(int(s), IMU_FRAME, g, buf.add(int(s), g))
        if k % 25 == 0:
            assert health.check(int(s)), health.status()
    assert health.refused == 40 and health.faults == 0
    assert 'out of order' in health.reason


def test_a_drifted_bias_estimate_keeps_the_gyro_out_until_a_reset():
    health = ImuHealth(IMU_FRAME)
    rng = np.random.default_rng(4)
    frames = []
    for k in range(2001):
        health.sample(k * 5_000_000, IMU_FRAME, rng.standard_normal(3) * 0.01)
        if k % 25 == 0:
            t = k * 0.005
            bias = np.array([0.0, 0.0, 0.01 + (0.02 * (t - 4.0) if t > 4.0 else 0.0)])
            frames.append((t, health.check(k * 5_000_000, bias), health.problem))
    first = next(f for f in frames if not f[1])
    assert first[2] == 'bias_drift' and 6.0 < first[0] <= 6.125, first
    assert not any(usable for t, usable, _ in frames if t >= first[0])
    assert health.detail == 'gyro bias estimate 0.130 rad/s (limit 0.05)'


def test_the_gyro_comes_back_after_recover_s_without_a_problem():
    health = ImuHealth(IMU_FRAME, ImuHealthLimits(recover_s=1.0))
    rng = np.random.default_rng(5)
    said = {}
    for k in range(1201):                            # 6 s; the samples stop from 2 to 3 s
        t = k * 0.005
        if not 2.0 <= t < 3.0:
            health.sample(k * 5_000_000, IMU_FRAME, rng.standard_normal(3) * 0.01)
        if k % 25 == 0:
            health.check(k * 5_000_000)
            said[round(t, 3)] = health.state
    assert said[2.0] == 'ok' and said[2.125] == 'ok' and said[2.25] == 'fault'
    assert said[3.0] == 'recovering'                 # heard again, not yet 1 s without a problem
    assert said[3.75] == 'recovering' and said[3.875] == 'ok'      # the last fault at 2.875
    assert health.faults == 1 and health.status()[0] == 'ok'


def test_silent_from_the_start_and_waiting():
    health = ImuHealth(IMU_FRAME)
    assert not health.check(0) and health.state == 'waiting'
    assert health.status()[:2] == ('warn', 'imu: waiting for the first sample')
    assert not health.check(250_000_000) and health.problem == 'silent'
    assert health.status()[1].startswith('imu: silent: no sample since the start')


def test_samples_after_a_frame_s_stamp_wait_for_their_frame():
    """A check takes what was seen up to its stamp only: a replay's result does not depend
    on how far ahead of the frames the samples came."""
    early, late = ImuHealth(IMU_FRAME), ImuHealth(IMU_FRAME)
    g = [0.1, 0.2, 0.3]
    for k in range(40):                              # stuck from the start, to 0.195 s
        early.sample(k * 5_000_000, IMU_FRAME, g)
        if k <= 20:
            late.sample(k * 5_000_000, IMU_FRAME, g)
    # the run reaches 20 identical samples at 0.095 s: seen at 0.1 s by both, not at 0.05 s
    assert early.check(50_000_000) and late.check(50_000_000)
    assert not early.check(100_000_000) and not late.check(100_000_000)


def test_the_generator_s_faults():
    traj = SCENARIOS['loop'](4.0)
    imu = simulate_imu(traj, RATE, np.random.default_rng(0))
    healthy = publish(imu)
    assert healthy.frame_ids == [IMU_FRAME] * len(imu.times)
    np.testing.assert_array_equal(healthy.stamps, imu.times)
    np.testing.assert_array_equal(healthy.gyro, imu.gyro)
    bad = imu.times >= 1.0
    f = publish(imu, 'wrong_frame', 1.0)
    assert [x == WRONG_FRAME for x in f.frame_ids] == list(bad)
    f = publish(imu, 'silent', 1.0)
    assert f.log_times[-1] < 1.0 and len(f.gyro) == int(np.sum(~bad))
    f = publish(imu, 'stuck', 1.0)
    assert np.all(f.gyro[bad] == f.gyro[bad][0]) and np.array_equal(f.gyro[~bad], imu.gyro[~bad])
    f = publish(imu, 'saturated', 1.0)
    assert np.abs(f.gyro[bad]).max() <= SATURATED_RANGE
    f = publish(imu, 'out_of_order', 1.0, np.random.default_rng(1))
    assert np.any(np.diff(f.stamps[bad]) < 0) and np.array_equal(f.log_times, imu.times)
    again = publish(imu, 'out_of_order', 1.0, np.random.default_rng(1))
    np.testing.assert_array_equal(f.stamps, again.stamps)           # seeded
    f = publish(imu, 'bias_drift', 1.0)
    np.testing.assert_allclose(np.linalg.norm(f.gyro[-1] - imu.gyro[-1]), 0.02 * 3.0)
    with pytest.raises(ValueError, match='unknown IMU fault'):
        publish(imu, 'tired', 1.0)


def test_cameras_turning_away_from_the_gyro_is_a_drifting_bias():
    """The innovation test: fixes that turn 0.04 rad/s away from the gyro's prediction, on
    average over imu_disagreement_window_s, are a bias running away; camera noise of a few
    mrad a frame around the gyro is not (a healthy spin_then_drive replay: at most 0.012)."""
    rng = np.random.default_rng(6)
    for drift, flagged in ((0.0, False), (0.04, True)):
        health = ImuHealth(IMU_FRAME)
        said = []
        for k in range(1, 81):                          # 10 s at 8 Hz
            t = k * FRAME_S
            for j in range(25):
                health.sample(int(round((t - FRAME_S + j * 0.005) * 1e9)), IMU_FRAME, rng.standard_normal(3) * 0.01)
            said.append((t, health.check(int(round(t * 1e9)), np.zeros(3)), health.problem))
            noise = rng.standard_normal(3) * 0.0015        # (the fused fixes: 1-2 mrad)
            error = noise + (np.array([0.0, 0.0, drift * FRAME_S]) if t >= 4.0 else 0.0)
            health.camera_residual(int(round(t * 1e9)), error, FRAME_S, 0.0)
        bad = [s for s in said if not s[1]]
        if not flagged:
            assert bad == [] and health.disagreement < 0.03
        else:
            assert bad[0][2] == 'bias_drift' and 4.5 <= bad[0][0] <= 5.25, bad[0]
            assert 'the cameras turn 0.0' in health.detail and 'away from the gyro (limit 0.030)' in health.detail
            assert all(p == 'bias_drift' for _, _, p in said if _ >= bad[0][0])     # held


def test_a_sample_delivered_twice_is_no_problem():
    """A graph that hands the general arbiter to another worker may deliver samples again:
    refused by the buffer (not after the newest), counted, not a fault."""
    buf, health = ImuBuffer(np.eye(3)), ImuHealth(IMU_FRAME)
    rng = np.random.default_rng(7)
    gyro = rng.standard_normal((400, 3)) * 0.01
    for k in range(400):
        health.sample(k * 5_000_000, IMU_FRAME, gyro[k], buf.add(k * 5_000_000, gyro[k]))
        if k == 200:
            for j in range(150, 201):             # 51 samples again
                health.sample(j * 5_000_000, IMU_FRAME, gyro[j], buf.add(j * 5_000_000, gyro[j]))
        if k % 25 == 0:
            assert health.check(k * 5_000_000), health.status()
    assert health.refused == 51 and health.faults == 0


def test_the_cameras_own_error_in_turns_is_allowed_for():
    """In fast turns the cameras' fixes are off by a few percent of the rotation (the 10 s
    loop: 0.061 rad/s turning at 1.6): disagreement_per_rotation allows for it; the same
    disagreement at rest is a drifting bias."""
    said, rng = {}, np.random.default_rng(8)
    for rate in (1.6, 0.0):
        health = ImuHealth(IMU_FRAME)
        for k in range(1, 17):                          # 2 s at 8 Hz
            t = k * FRAME_S
            for j in range(25):
                health.sample(int(round((t - FRAME_S + j * 0.005) * 1e9)), IMU_FRAME,
                              [0.0, 0.0, rate] + rng.standard_normal(3) * 0.004)
            health.check(int(round(t * 1e9)))
            health.camera_residual(int(round(t * 1e9)), [0.0, 0.0, 0.06 * FRAME_S], FRAME_S, rate * FRAME_S)
        said[rate] = (health.problem, health.disagreement, health.disagreement_limit)
    assert said[1.6][0] is None and said[1.6][1] == pytest.approx(0.06) and said[1.6][2] == pytest.approx(0.11)
    assert said[0.0][0] == 'bias_drift' and said[0.0][2] == pytest.approx(0.03)
