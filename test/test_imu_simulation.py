"""The generator's IMU (scenarios/imu.py): what it measures is the trajectory's motion as an
IMU off base_link feels it, its noise is the model's, and `generate(imu_rate=...)` writes it
as a driver does (sensor_msgs/Imu in imu_link, base_link -> imu_link in /tf_static) without
changing anything else of the bag. Bags read with the independent rosbags reader."""
import numpy as np
import pytest
from conftest import read_bag

from multicam_ego_motion.scenarios.generator import generate
from multicam_ego_motion.geometry.rig import IMU_TOPIC
from multicam_ego_motion.scenarios.imu import (GRAVITY, IMU_FRAME, IMU_ROTATION, IMU_TRANSLATION,
                                              NOISELESS, ImuNoise, simulate_imu, true_motion)
from multicam_ego_motion.scenarios.trajectories import SCENARIOS

RATE = 200.0


@pytest.fixture(scope='module')
def spin():
    return SCENARIOS['spin_then_drive'](20.0)


def test_a_noiseless_imu_measures_the_motion_in_its_own_frame(spin):
    s = simulate_imu(spin, RATE, np.random.default_rng(0), NOISELESS)
    assert len(s.times) == 20 * 200 + 1 and s.times[-1] == pytest.approx(20.0)
    w_base = s.gyro @ IMU_ROTATION.T               # back into base_link
    assert np.abs(w_base[:, :2]).max() < 1e-12
    # the gyro integrates to the trajectory's heading change (the spin and part of the loop)
    turned = np.sum(0.5 * (w_base[1:, 2] + w_base[:-1, 2]) / RATE)
    assert turned == pytest.approx(spin.yaw[-1] - spin.yaw[0], abs=2e-3) and turned > 2 * np.pi
    # at rest: the floor's push against gravity, along base_link's z, seen turned
    f_base = s.accel @ IMU_ROTATION.T
    np.testing.assert_allclose(f_base[0], [0.0, 0.0, GRAVITY], atol=1e-4)
    # spinning in place at the fastest rate: the IMU off the axis feels the centripetal pull
    k = int(np.argmax(np.abs(w_base[:s.times.searchsorted(8.0), 2])))
    w, dw, _ = true_motion(spin, s.times[k:k + 1])
    assert abs(dw[0, 2]) < 1e-2 and abs(w[0, 2]) > 1.0
    r = np.asarray(IMU_TRANSLATION)
    np.testing.assert_allclose(f_base[k, :2], -w[0, 2] ** 2 * r[:2], atol=2e-3)


def test_noise_and_bias_are_the_model_s(spin):
    noise = ImuNoise()
    clean = simulate_imu(spin, RATE, np.random.default_rng(1), NOISELESS)
    s = simulate_imu(spin, RATE, np.random.default_rng(1), noise)
    gyro_var, accel_var = noise.sample_variances(RATE)
    white_g = s.gyro - clean.gyro - s.gyro_bias
    white_a = s.accel - clean.accel - s.accel_bias
    assert np.std(white_g, axis=0) == pytest.approx([np.sqrt(gyro_var)] * 3, rel=0.05)
    assert np.std(white_a, axis=0) == pytest.approx([np.sqrt(accel_var)] * 3, rel=0.05)
    # a turn-on bias that then wanders by about walk * sqrt(T) over the run
    assert np.all(np.abs(s.gyro_bias[0]) < 5 * noise.gyro_bias_std) and np.any(s.gyro_bias[0] != 0)
    wander = np.abs(s.gyro_bias[-1] - s.gyro_bias[0])
    assert np.all(wander < 5 * noise.gyro_bias_walk * np.sqrt(20.0)) and np.all(wander > 0)
    with pytest.raises(ValueError, match='rate'):
        simulate_imu(spin, 0.0, np.random.default_rng(1))


def test_generated_bag_has_the_imu_as_a_driver_publishes_it_and_nothing_else_changes(tmp_path):
    scene = dict(scenario='loop', seed=5, duration=2.0, rate=10.0, width=160, height=120, progress=False)
    generate(out=tmp_path / 'with', imu_rate=RATE, **scene)
    generate(out=tmp_path / 'without', **scene)
    topics, msgs = read_bag(tmp_path / 'with')
    topics0, msgs0 = read_bag(tmp_path / 'without')
    assert topics[IMU_TOPIC] == ('sensor_msgs/msg/Imu', 401) and IMU_TOPIC not in topics0
    imu = [(t, m) for topic, t, m in msgs if topic == IMU_TOPIC]
    gyro_var, accel_var = ImuNoise().sample_variances(RATE)
    for t, m in imu:
        assert m.header.frame_id == IMU_FRAME and m.orientation_covariance[0] == -1.0
        assert m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec == t
        np.testing.assert_allclose(np.diag(m.angular_velocity_covariance.reshape(3, 3)), gyro_var)
        np.testing.assert_allclose(np.diag(m.linear_acceleration_covariance.reshape(3, 3)), accel_var)
    stamps = [t for t, _ in imu]
    assert np.all(np.diff(stamps) == 5_000_000)
    # written in log-time order with the frames
    assert [t for _, t, _ in msgs] == sorted(t for _, t, _ in msgs)
    # the specific force in the IMU's frame (turned by the mount) is the motion's, to the
    # bias (0.05 m/s^2 a side) and the noise
    times = (np.array(stamps) - stamps[0]) / 1e9
    w, dw, a = true_motion(SCENARIOS['loop'](2.0), times)
    r = np.broadcast_to(np.asarray(IMU_TRANSLATION), w.shape)
    f_true = a + np.cross(dw, r) + np.cross(w, np.cross(w, r)) + [0.0, 0.0, GRAVITY]
    f = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                  for _, m in imu])
    np.testing.assert_allclose(np.mean(f @ IMU_ROTATION.T - f_true, axis=0), 0.0, atol=0.3)
    assert np.abs(f_true[:, :2]).max() > 5.0          # (a motion to measure: not only gravity)
    tf = next(m for topic, _, m in msgs if topic == '/tf_static')
    mount = next(x for x in tf.transforms if x.child_frame_id == IMU_FRAME)
    assert mount.header.frame_id == 'base_link'
    t = mount.transform.translation
    np.testing.assert_allclose([t.x, t.y, t.z], IMU_TRANSLATION)
    # the images, camera infos, wheel and ground truth are the bag without an IMU's
    rest = [(topic, t, bytes(m.data) if hasattr(m, 'data') else repr(m)) for topic, t, m in msgs
            if topic not in (IMU_TOPIC, '/tf_static')]
    rest0 = [(topic, t, bytes(m.data) if hasattr(m, 'data') else repr(m)) for topic, t, m in msgs0
             if topic != '/tf_static']
    assert rest == rest0


def test_the_rig_file_keeps_the_imu_and_refuses_a_bad_one(tmp_path):
    """The generated rig file names the IMU as the bag places it; a rig file whose imu is
    not a mount is refused, naming the problem."""
    import yaml

    from multicam_ego_motion.errors import UserError
    from multicam_ego_motion.geometry.rig import load_rig
    generate(out=tmp_path / 'bag', scenario='loop', seed=5, duration=1.0, rate=5.0, width=160,
             height=120, progress=False, imu_rate=RATE)
    rig = load_rig(tmp_path / 'bag' / 'rig.yaml')
    assert rig.imu.frame_id == IMU_FRAME and rig.imu.topic == IMU_TOPIC
    np.testing.assert_allclose(rig.imu.translation, IMU_TRANSLATION)
    np.testing.assert_allclose(rig.imu.rotation, IMU_ROTATION, atol=1e-9)
    data = yaml.safe_load((tmp_path / 'bag' / 'rig.yaml').read_text())
    for imu, words in (({'frame_id': 'imu_link', 'translation': [0, 0], 'rotation_xyzw': [0, 0, 0, 1]},
                        'translation must be 3 finite numbers'),
                       ({'frame_id': 'imu_link', 'translation': [0, 0, 0], 'rotation_xyzw': [0, 0, 0, 2]},
                        'not a unit quaternion'),
                       ('imu_link', 'expected a mapping with frame_id')):
        (tmp_path / 'bad.yaml').write_text(yaml.safe_dump({**data, 'imu': imu}))
        with pytest.raises(UserError, match=words):
            load_rig(tmp_path / 'bad.yaml')


def test_a_bad_imu_changes_the_imu_and_nothing_else(tmp_path):
    """`generate --imu-fault`: the IMU's samples go bad from --imu-fault-at on (here stamps
    out of order, drawn from the seed: the same twice), every other message is the bag's
    without the fault, to the byte."""
    scene = dict(scenario='loop', seed=5, duration=2.0, rate=10.0, width=160, height=120,
                 progress=False, imu_rate=RATE)
    generate(out=tmp_path / 'healthy', **scene)
    generate(out=tmp_path / 'bad', imu_fault='out_of_order', imu_fault_at=1.0, **scene)
    generate(out=tmp_path / 'again', imu_fault='out_of_order', imu_fault_at=1.0, **scene)
    bags = {k: read_bag(tmp_path / k)[1] for k in ('healthy', 'bad', 'again')}

    def rest(msgs):
        return [(topic, t, bytes(m.data) if hasattr(m, 'data') else repr(m)) for topic, t, m in msgs
                if topic != IMU_TOPIC]

    def imu(msgs):
        return [(t, m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec) for topic, t, m in msgs
                if topic == IMU_TOPIC]
    assert rest(bags['bad']) == rest(bags['healthy'])
    assert imu(bags['bad']) == imu(bags['again'])
    log_times = [t for t, _ in imu(bags['bad'])]
    assert log_times == [t for t, _ in imu(bags['healthy'])]
    stamps = np.array([s for _, s in imu(bags['bad'])])
    start = log_times[0]
    before = np.array(log_times) < start + 1_000_000_000
    assert np.array_equal(stamps[before], np.array(log_times)[before])
    assert np.any(np.diff(stamps[~before]) < 0)
    with pytest.raises(Exception, match='needs an IMU'):
        generate(out=tmp_path / 'none', **{**scene, 'imu_rate': 0.0}, imu_fault='stuck')
