"""ROS-free: the two-view initialisation (camera_pose_nodes/two_view), the map rescale
(camera_pose_nodes/map_scale) and the scale state (arbiter_node/scale_state)."""
import math

import numpy as np
import pytest

from arbiter_node.body_ekf import BodyEKF
from arbiter_node.rig_scale import camera_direction
from arbiter_node.scale_state import ScaleState, metric_source, rescale_body_ekf
from arbiter_node.general_fusion import default_params
from camera_pose_nodes.map_scale import MapScaleCommand, rescale_pose_ekf, scale_positions
from camera_pose_nodes.pose_ekf import PoseEKF
from camera_pose_nodes.two_view import body_pose_from_two_view, two_view
from multicam_ego_motion.geometry.rig import load_rig
from multicam_ego_motion.geometry.se3 import R_to_rotvec, rotvec_to_R
from conftest import REPO


def _views(R, t, n=60, seed=3, noise=0.0):
    """Points in front of camera 1; their normalized coordinates in views 1 and 2 (x2 = R x1 + t)."""
    rng = np.random.default_rng(seed)
    X1 = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 10, n)])
    X2 = X1 @ R.T + t
    xy1, xy2 = X1[:, :2] / X1[:, 2:], X2[:, :2] / X2[:, 2:]
    return xy1 + rng.normal(0, noise, xy1.shape), xy2 + rng.normal(0, noise, xy2.shape)


def test_two_view_recovers_rotation_and_direction():
    # Exact correspondences: exact motion. Noisy ones in a quarter's narrow view: rotation
    # and direction trade against each other (why the general arbiter waits for cameras
    # that agree, start_min_cameras), so the tolerances are wide.
    R = rotvec_to_R(np.array([0.0, 0.05, 0.01]))
    t = np.array([0.3, 0.0, 0.2])
    for noise, rot_tol, deg_tol in ((0.0, 1e-9, 1e-6), (0.1 / 200, 0.05, 15.0)):
        xy1, xy2 = _views(R, t, n=200, noise=noise)
        res = two_view(xy1, xy2, threshold=2.0 / 200, min_points=12, min_parallax_deg=1.0)
        assert res is not None and res.inliers.sum() >= 150
        assert np.linalg.norm(R_to_rotvec(res.R @ R.T)) < rot_tol
        assert math.degrees(math.acos(min(1.0, res.t @ (t / np.linalg.norm(t))))) < deg_tol


def test_two_view_refuses_without_parallax():
    R = rotvec_to_R(np.array([0.0, 0.05, 0.0]))
    xy1, xy2 = _views(R, np.array([0.005, 0.0, 0.0]))       # a turn, next to no travel
    assert two_view(xy1, xy2, 2.0 / 200, 12, 1.0) is None
    assert two_view(xy1[:5], xy2[:5], 2.0 / 200, 12, 1.0) is None


def test_body_pose_from_two_view_moves_the_camera_by_the_gauge():
    rig = load_rig(REPO / 'config' / 'rig_default.yaml')
    T_bc = rig.cameras[1].T_base_cam
    R, t = rotvec_to_R(np.array([0.0, 0.02, 0.0])), np.array([0.6, 0.0, 0.8])
    xy1, xy2 = _views(R, t)
    res = two_view(xy1, xy2, 2.0 / 200, 12, 1.0)
    T2 = body_pose_from_two_view(np.eye(4), T_bc, res, 0.5)
    c1, c2 = T_bc[:3, 3], (T2 @ T_bc)[:3, 3]
    assert np.linalg.norm(c2 - c1) == pytest.approx(0.5)


def test_a_rescaled_map_reprojects_the_same():
    rng = np.random.default_rng(5)
    X = rng.uniform(-5, 5, (40, 3)) + [0, 0, 8]
    T = np.eye(4)
    T[:3, :3] = rotvec_to_R(np.array([0.1, -0.2, 0.3]))
    T[:3, 3] = [1.0, -2.0, 0.5]
    k, c = 1.37, np.array([0.3, 0.2, -0.1])

    def project(T, X):
        Xc = (X - T[:3, 3]) @ T[:3, :3]
        return Xc[:, :2] / Xc[:, 2:]
    T2 = T.copy()
    T2[:3, 3] = scale_positions(T[:3, 3], k, c)
    assert np.allclose(project(T, X), project(T2, scale_positions(X, k, c)), atol=1e-12)


def test_the_ekfs_rescale_position_velocity_and_covariance():
    ekf = PoseEKF()
    ekf.reset(np.eye(4))
    ekf.stamp_ns = 0
    ekf.kf.x[0:3, 0] = [1.0, 2.0, 3.0]
    ekf.kf.x[6:9, 0] = [0.5, 0.0, 0.0]
    P0 = ekf.kf.P.copy()
    rescale_pose_ekf(ekf, 2.0, (0.0, 0.0, 0.0))
    assert np.allclose(ekf.kf.x[0:3, 0], [2, 4, 6]) and np.allclose(ekf.kf.x[6:9, 0], [1, 0, 0])
    assert np.allclose(ekf.kf.P[0:3, 0:3], 4 * P0[0:3, 0:3]) and np.allclose(ekf.kf.P[3:6, 3:6], P0[3:6, 3:6])
    body = BodyEKF()
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]
    body.reinitialize(T, np.eye(6) * 1e-4, twist=np.array([1.0, 0, 0, 0, 0, 0.1]))
    rescale_body_ekf(body, 0.5, (1.0, 0.0, 0.0))
    assert np.allclose(body.T[:3, 3], [1, 0, 0]) and np.allclose(body.twist, [0.5, 0, 0, 0, 0, 0.1])


def test_map_scale_command_round_trip_and_bad_input():
    c = MapScaleCommand(123, 2, 0.8123456789, (0.1, -2.0, 3.5))
    assert MapScaleCommand.from_list(c.to_list()) == c
    with pytest.raises(ValueError, match='epoch'):
        MapScaleCommand.from_list([1, 0] + c.to_list()[2:])
    with pytest.raises(ValueError, match='factor'):
        MapScaleCommand.from_list(MapScaleCommand(1, 1, -1.0, (0, 0, 0)).to_list())


def test_the_scale_source_and_the_rig_rotation_estimate():
    rig = load_rig(REPO / 'config' / 'rig_default.yaml')
    assert metric_source(rig, False) == 'floor'
    rig.floor_z = None
    assert metric_source(rig, True) == 'wheel' and metric_source(rig, False) is None
    # A map at 0.5 of the metric scale, a turn: the cameras' centres (their own measurement)
    # move as the true ones do, scaled by 0.5; the state observes k = 2 and snaps.
    st = ScaleState(rig, default_params())
    true, est = [], []
    for i in range(40):
        yaw, x = 0.05 * i, 0.1 * i
        T = np.eye(4)
        T[:3, :3] = rotvec_to_R(np.array([0, 0, yaw]))
        T[:3, 3] = [x * math.cos(0.5 * yaw), x * math.sin(0.5 * yaw), 0]
        true.append(T)
    cmd = None
    for i, T in enumerate(true):
        Tm = T.copy()
        Tm[:3, 3] *= 0.5
        cams = {}
        for cam in rig.cameras:
            c = (T @ cam.T_base_cam)[:3, 3] * 0.5
            Tc = Tm.copy()
            Tc[:3, 3] = c - T[:3, :3] @ cam.T_base_cam[:3, 3]
            cams[cam.name] = Tc
        st.observe(i * 125_000_000, Tm, cams)
        cmd = cmd or st.decide(i * 125_000_000, Tm)
    assert st.observed and cmd is not None and cmd.factor == pytest.approx(2.0, rel=0.02)
    assert camera_direction is not None
