"""Moving a pose estimate in time with the body EKF's constant-twist model (free-running
cameras: each camera's estimate to the frame's common time, the fused pose back to each
camera's capture time)."""
import numpy as np
import pytest

from arbiter_node.body_ekf import BodyEKF, BodyEkfParams
from arbiter_node.general_fusion import GeneralFusion
from arbiter_node.time_shift import shift_pose
from camera_pose_nodes.pose_estimate import PoseEstimate
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.geometry.rig import paper_rig

MS = 1_000_000


def yaw_pose(x, y, yaw):
    return se3.make_T(se3.rotvec_to_R([0, 0, yaw]), [x, y, 0.0])


def test_shift_follows_the_arc_of_a_constant_twist():
    # 2 m/s forward, 1 rad/s yaw for 0.1 s from the origin: the unicycle's arc
    twist = np.array([2.0, 0, 0, 0, 0, 1.0])
    T, _ = shift_pose(np.eye(4), np.eye(6) * 1e-6, 0.1, twist, np.eye(6) * 1e-4)
    r = 2.0 / 1.0
    expected = yaw_pose(r * np.sin(0.1), r * (1 - np.cos(0.1)), 0.1)
    assert np.allclose(T, expected, atol=1e-12)


def test_shift_back_and_forth_returns_and_zero_shift_is_identity():
    twist = np.array([1.5, 0.1, 0, 0, 0, -0.7])
    T0, C0 = yaw_pose(1.0, -2.0, 0.4), np.diag([1e-4] * 3 + [1e-5] * 3)
    T1, _ = shift_pose(T0, C0, 0.024, twist, np.eye(6) * 1e-3)
    T2, _ = shift_pose(T1, C0, -0.024, twist, np.eye(6) * 1e-3)
    assert np.allclose(T2, T0, atol=1e-12)
    T, C = shift_pose(T0, C0, 0.0, twist, np.eye(6))
    assert T is T0 and C is C0                       # bit for bit: synchronised rigs


def test_covariance_grows_with_the_twist_uncertainty_and_the_offset():
    T0, C0 = np.eye(4), np.diag([1e-4] * 3 + [1e-5] * 3)
    twist = np.array([2.0, 0, 0, 0, 0, 0.5])
    _, C_tight = shift_pose(T0, C0, 0.02, twist, np.eye(6) * 1e-4)
    _, C_loose = shift_pose(T0, C0, 0.02, twist, np.eye(6) * 1e-2)
    _, C_far = shift_pose(T0, C0, 0.04, twist, np.eye(6) * 1e-2)
    assert np.all(np.linalg.eigvalsh(C_loose - C_tight) > -1e-15)   # same step, looser twist
    for a, b in ((C0, C_tight), (C_tight, C_loose), (C_loose, C_far)):
        assert np.all(np.diag(b) >= np.diag(a)) and np.trace(b) > np.trace(a)
    # a std of 0.1 m/s over 40 ms: 4 mm more along x
    assert np.sqrt(C_far[0, 0]) == pytest.approx(np.sqrt(1e-4 + (0.1 * 0.04) ** 2), rel=0.05)
    assert np.allclose(C_far, C_far.T)


def test_fusion_moves_early_cameras_to_the_common_time():
    """Four cameras seeing the true motion at their own capture times (0, 8, 16, 24 ms) give
    the true pose at 24 ms: unshifted, the early ones would pull it back."""
    fusion = GeneralFusion(paper_rig(), {'planar_motion': False})
    v = 2.0
    cov = np.diag([1e-6] * 3 + [1e-7] * 3)
    # a converged filter: moving at v along x
    fusion.ekf.reinitialize(np.eye(4), cov, twist=np.array([v, 0, 0, 0, 0, 0]),
                            twist_cov=np.eye(6) * 1e-6)
    fusion.has_tracked, fusion.last_stamp_ns = True, 0
    t0 = 100 * MS
    offsets = {'front': 0, 'left': 8 * MS, 'back': 16 * MS, 'right': 24 * MS}
    ests = {n: PoseEstimate(t0 + o, yaw_pose(v * (t0 + o) * 1e-9, 0, 0), cov, source=n, state='tracking')
            for n, o in offsets.items()}
    fused = fusion.process(t0 + 24 * MS, ests)
    assert fused.cameras_used == sorted(offsets)
    assert fused.T_odom_base[0, 3] == pytest.approx(v * 0.124, abs=2e-4)
    # and the pose fed back to the front camera is the one at its own capture time
    T_front, _ = fusion.pose_at(fused, t0)
    assert T_front[0, 3] == pytest.approx(v * 0.1, abs=2e-4)
    T_same, C_same = fusion.pose_at(fused, fused.stamp_ns)
    assert T_same is fused.T_odom_base and C_same is fused.pose_covariance
