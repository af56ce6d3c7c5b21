"""The rig's metric motion from every camera's tracks (arbiter_node/rig_motion_fit), on points
seen by the paper's four-camera rig: metric in a turn from any start scale, unobservable
without rotation, and said so when the tracks cannot tell."""
import numpy as np
import pytest

from arbiter_node.rig_motion_fit import CameraTracks, fit_rig_motion
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.geometry.rig import paper_rig

RIG = paper_rig()
FOCAL = 200.0


def tracks(R, t, rng, noise_px=0.2, per_camera=60):
    """Points 2-8 m in front of each camera at frame a, seen again after the body moved by
    (R, t) (base_link at a): normalised points with noise."""
    out = []
    for cam in RIG.cameras:
        Rc, c = cam.rotation, cam.translation
        depth = rng.uniform(2.0, 8.0, per_camera)
        xa = rng.uniform(-0.7, 0.7, (per_camera, 2))
        X_cam = np.column_stack([xa * depth[:, None], depth])
        X_body = X_cam @ Rc.T + c                       # base_link at a
        # at b: camera centre R c + t, rotation R Rc
        X_cam_b = (X_body - (R @ c + t)) @ (R @ Rc)
        front = X_cam_b[:, 2] > 0.5
        xb = X_cam_b[front, :2] / X_cam_b[front, 2:]
        sigma = noise_px / FOCAL
        out.append(CameraTracks(Rc, c, xa[front] + rng.normal(0, sigma, (front.sum(), 2)),
                                xb + rng.normal(0, sigma, xb.shape), np.full(front.sum(), sigma)))
    return out


@pytest.mark.parametrize('start_scale', [0.5, 1.0, 1.7])
def test_a_turn_gives_the_metric_translation_from_any_start_scale(start_scale):
    rng = np.random.default_rng(3)
    R = se3.rotvec_to_R([0.0, 0.0, 0.15])
    t = np.array([0.17, 0.012, 0.0])
    fit = fit_rig_motion(se3.rotvec_to_R([0.003, -0.002, 0.0]) @ R, t * start_scale, tracks(R, t, rng))
    assert fit.ok, fit.reason
    assert np.linalg.norm(fit.t) == pytest.approx(np.linalg.norm(t), rel=0.03)
    assert np.degrees(np.arccos(fit.t @ t / np.linalg.norm(fit.t) / np.linalg.norm(t))) < 1.0
    assert np.linalg.norm(se3.R_to_rotvec(fit.R.T @ R)) < 1e-3
    assert fit.relative_std < 0.05 and fit.n_inliers >= 0.95 * fit.n_points


def test_its_predicted_error_matches_the_scatter():
    rng = np.random.default_rng(4)
    R = se3.rotvec_to_R([0.0, 0.0, 0.12])
    t = np.array([0.15, 0.0, 0.0])
    fits = [fit_rig_motion(R, t, tracks(R, t, rng)) for _ in range(12)]
    errors = np.array([np.linalg.norm(f.t) / np.linalg.norm(t) - 1.0 for f in fits])
    predicted = np.mean([f.relative_std for f in fits])
    assert 0.3 * predicted < np.sqrt(np.mean(errors ** 2)) < 3.0 * predicted


def test_without_rotation_the_scale_is_not_observable():
    rng = np.random.default_rng(5)
    t = np.array([0.17, 0.0, 0.0])
    fit = fit_rig_motion(np.eye(3), t, tracks(np.eye(3), t, rng))
    assert fit.relative_std > 0.3          # the lever arms carry nothing: any length fits


def test_too_few_cameras_or_tracks_are_named():
    rng = np.random.default_rng(6)
    R = se3.rotvec_to_R([0.0, 0.0, 0.15])
    t = np.array([0.17, 0.0, 0.0])
    cams = tracks(R, t, rng)
    one = fit_rig_motion(R, t, cams[:1])
    assert not one.ok and 'need 2' in one.reason
    few = fit_rig_motion(R, t, [CameraTracks(c.R_base_cam, c.centre, c.xa[:5], c.xb[:5], c.sigma[:5])
                                for c in cams])
    assert not few.ok and 'tracks in both frames' in few.reason
    assert not fit_rig_motion(R, np.zeros(3), cams).ok


def test_bearings_message_bytes_are_rosbags_serializers():
    from multicam_ego_motion.ros_plumbing import bearing_messages
    rng = np.random.default_rng(3)
    for frame_id in ('', 'c', 'cam', 'rear_left_optical'):
        for n in (0, 1, 3, 40):
            args = (1_700_000_000_000_000_001 + n, frame_id, rng.integers(0, 2 ** 33, n),
                    rng.normal(0, 0.5, (n, 2)), rng.random(n))
            assert bearing_messages.bearings_to_cdr(*args) == bearing_messages._bearings_to_cdr_rosbags(*args)


def test_bearings_go_through_their_message_unchanged_and_a_wrong_layout_is_named():
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2, PointField
    from multicam_ego_motion.ros_plumbing.bearing_messages import bearings_from_cdr, bearings_to_cdr
    rng = np.random.default_rng(7)
    ids = np.array([3, 4, 17, 90_000])
    xy = rng.normal(0, 0.5, (4, 2))
    data = bearings_to_cdr(1_700_000_000_123_456_789, 'front_optical', ids, xy, np.full(4, 0.005))
    # the standard PointCloud2 on the wire: rclpy (a viewer, a recorder) reads it as usual
    msg = deserialize_message(data, PointCloud2)
    assert msg.header.frame_id == 'front_optical' and msg.width == 4 and msg.header.stamp.nanosec == 123_456_789
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'sigma', 'id']
    stamp, ids2, xy2, sigma = bearings_from_cdr(serialize_message(msg))
    assert stamp == 1_700_000_000_123_456_789
    assert np.array_equal(ids2, ids) and np.array_equal(xy2, xy) and np.all(sigma == 0.005)
    msg.fields = msg.fields[:3] + [PointField(name='intensity', offset=24, datatype=PointField.FLOAT32, count=1)]
    with pytest.raises(ValueError, match='bearings: expected fields'):
        bearings_from_cdr(serialize_message(msg))
    with pytest.raises(ValueError, match='do not read as sensor_msgs/msg/PointCloud2'):
        bearings_from_cdr(data[:40])