import numpy as np
import pytest

from arbiter_node.body_ekf import BodyEKF, BodyEkfParams
from multicam_ego_motion.geometry import se3

POSE_COV = np.diag([0.01, 0.01, 0.01, 0.005, 0.005, 0.005]) ** 2


def healthy(f):
    return (np.all(np.isfinite(f.T)) and se3.is_valid_covariance(f.pose_covariance)
            and np.all(np.isfinite(f.twist)) and se3.is_valid_covariance(f.twist_covariance))


def truth(t, v=0.5, w=0.3):
    """Unicycle at body speed v, yaw rate w (exact arc)."""
    yaw = w * t
    p = np.array([v / w * np.sin(yaw), v / w * (1 - np.cos(yaw)), 0.0])
    return se3.make_T(se3.rotvec_to_R([0, 0, yaw]), p)


def test_prediction_integrates_body_twist():
    f = BodyEKF()
    T0 = se3.make_T(se3.rotvec_to_R([0, 0, np.pi / 2]), [1.0, 0, 0])
    f.reinitialize(T0, POSE_COV, twist=np.r_[1.0, 0, 0, 0, 0, 0.0])
    f.predict(2.0)
    # heading +y in odom, forward body speed 1 m/s: 2 m along odom +y
    np.testing.assert_allclose(f.T[:3, 3], [1.0, 2.0, 0.0], atol=1e-12)
    f.reinitialize(np.eye(4), POSE_COV, twist=np.r_[0, 0, 0, 0, 0, 0.5])
    for _ in range(10):
        f.predict(0.1)
    assert se3.yaw_of(f.T[:3, :3]) == pytest.approx(0.5, abs=1e-12)


def test_constant_twist_prediction_follows_the_arc():
    # One 1 s step through a quarter turn lands on the circle (the arc), where the chord
    # along the start heading (Euler) would put it 0.5 m ahead and on the x axis.
    v, w = 0.5, np.pi / 2
    for params, expect in ((BodyEkfParams(), truth(1.0, v, w)[:3, 3]), (BodyEkfParams(arc_integration=False), [v, 0, 0])):
        f = BodyEKF(params)
        f.reinitialize(np.eye(4), POSE_COV, twist=np.r_[v, 0, 0, 0, 0, w])
        f.predict(1.0)
        np.testing.assert_allclose(f.T[:3, 3], expect, atol=1e-12)
        assert se3.yaw_of(f.T[:3, :3]) == pytest.approx(w, abs=1e-12)


def test_tracks_circle_consistently_and_recovers_body_twist():
    rng = np.random.default_rng(0)
    f = BodyEKF()
    dt = 0.05
    nees = []
    for k in range(1, 301):
        f.predict(dt)
        meas = se3.perturb(truth(k * dt), rng.normal(0, np.sqrt(np.diag(POSE_COV))))
        ok, _ = f.update_pose(meas, POSE_COV, gate_chi2=30.0)
        assert ok
        err = se3.pose_error(f.T, truth(k * dt))
        if k > 100:
            nees.append(err @ np.linalg.solve(f.pose_covariance, err))
    # consistent filter: mean NEES of a 6-dof error is about 6
    assert 4.0 < np.mean(nees) < 8.5, np.mean(nees)
    err = se3.pose_error(f.T, truth(300 * dt))
    assert np.linalg.norm(err[:3]) < 0.03 and np.linalg.norm(err[3:]) < 0.015
    np.testing.assert_allclose(f.twist, [0.5, 0, 0, 0, 0, 0.3], atol=0.15)
    assert healthy(f)
    assert f.twist_covariance[0, 0] < 0.02           # shrank from the initial 1 (m/s)^2


def test_thousand_predictions_without_update_stay_finite():
    f = BodyEKF()
    f.reinitialize(np.eye(4), POSE_COV, twist=np.r_[1.0, 0, 0, 0, 0, 0.2])
    traces = []
    for _ in range(1000):
        f.predict(0.1)
        traces.append(np.trace(f.pose_covariance))
    assert healthy(f)
    assert np.all(np.diff(traces) > 0)                 # uncertainty grows monotonically
    f.predict(1e7)                                     # an absurd gap: clamped, not overflowing
    assert healthy(f) and f.pose_covariance.max() <= 1e8 * 1.0001


def test_absurd_measurements_are_refused_or_harmless():
    f = BodyEKF()
    f.reinitialize(np.eye(4), POSE_COV)
    far = se3.make_T(se3.rotvec_to_R([0, 0, 3.0]), [1e9, 0, 0])
    ok, d2 = f.update_pose(far, POSE_COV, gate_chi2=22.5)
    assert not ok and d2 > 1e6
    np.testing.assert_allclose(f.T, np.eye(4), atol=1e-12)
    bad = np.eye(4); bad[0, 3] = np.nan
    assert f.update_pose(bad, POSE_COV) == (False, float('inf'))
    assert not f.update_twist([np.inf, 0, 0, 0, 0, 0], np.eye(6))[0]
    # ungated absurd update with a singular covariance: accepted but state stays valid
    ok, _ = f.update_pose(far, np.zeros((6, 6)))
    assert ok and healthy(f)
    assert f.T[0, 3] == pytest.approx(1e9, rel=1e-6)


def test_wheel_twist_update_planar_axes():
    f = BodyEKF(BodyEkfParams(initial_twist_std=1.0))
    cov = np.diag([0.01, 0.01, 1e-4, 1e-4, 1e-4, 0.01]) ** 2
    for _ in range(20):
        f.predict(0.05)
        ok, _ = f.update_twist([0.8, 0.0, 9.9, 9.9, 9.9, 0.1], cov, axes=(0, 1, 5))
        assert ok
    np.testing.assert_allclose(f.twist[[0, 1, 5]], [0.8, 0.0, 0.1], atol=1e-3)
    assert abs(f.twist[2]) < 1e-6                       # unused axes untouched by the 9.9s
    # dead reckoning on the wheel prior moves the pose forward about 0.8 m/s * 1 s
    assert 0.6 < f.T[0, 3] < 0.9


def test_reinitialize_sets_pose_and_covariance():
    f = BodyEKF()
    T = se3.make_T(se3.rotvec_to_R([0.1, 0.2, 0.3]), [1, 2, 3])
    f.reinitialize(T, POSE_COV * 4)
    np.testing.assert_allclose(f.T, T, atol=1e-12)
    np.testing.assert_allclose(f.pose_covariance, POSE_COV * 4, rtol=1e-9)
    np.testing.assert_allclose(f.twist, 0)


def test_pose_clone_follows_later_updates_as_a_filter_over_both_would():
    """A clone of the pose, then a predict and a pose fix: the clone's correction and
    covariance are those of one Kalman filter over the state and the clone together."""
    f = BodyEKF()
    f.reinitialize(truth(0.0), POSE_COV, twist=np.r_[0.5, 0, 0, 0, 0, 0.3])
    f.predict(0.1)
    f.clone_pose('a')
    T_a, P0 = f.T, f.kf.P.copy()
    f.predict(0.1)
    F, Q = f.kf.F, f.kf.Q
    n = f.dim
    # the joint covariance of (state, clone) after the predict
    J = np.zeros((n + 6, n + 6))
    J[:n, :n] = F @ P0 @ F.T + Q
    J[:n, n:] = F @ P0[:, :6]
    J[n:, :n] = J[:n, n:].T
    J[n:, n:] = P0[:6, :6]
    np.testing.assert_allclose(J[:n, :n], f.kf.P, atol=1e-15)
    meas = truth(0.2) @ se3.make_T(se3.rotvec_to_R([0, 0, 0.01]), [0.02, -0.01, 0.0])
    y = se3.pose_error(meas, f.T)
    ok, _ = f.update_pose(meas, POSE_COV)
    assert ok
    H = np.zeros((6, n + 6))
    H[:, :6] = np.eye(6)
    S = H @ J @ H.T + POSE_COV
    K = J @ H.T @ np.linalg.inv(S)
    T_c, C_c = f.cloned_pose('a')
    d = (K @ y)[n:]
    assert np.linalg.norm(d) > 1e-3                           # the fix moved the clone
    np.testing.assert_allclose(se3.pose_error(T_c, T_a), d, atol=1e-9)
    np.testing.assert_allclose(C_c, (J - K @ S @ K.T)[n:, n:], atol=1e-12)


def test_rotation_between_clones_tells_the_turn_rate():
    """A body turning at 1.5 rad/s, the filter at rest: the rotation between clones of
    consecutive frames (as a camera's tracks measure it) brings the twist to the turn, where
    the prediction alone stays at rest."""
    w, dt = 1.5, 1.0 / 15
    out = {}
    for measured in (False, True):
        f = BodyEKF()
        f.reinitialize(np.eye(4), POSE_COV)
        f.clone_pose(0)
        for k in range(1, 16):
            f.predict(dt)
            f.clone_pose(k)
            if measured:
                ok, _ = f.update_relative_rotation(k - 1, k, se3.rotvec_to_R([0, 0, w * dt]),
                                                   np.eye(3) * 1e-3 ** 2)
                assert ok
            f.drop_clone(k - 1)
        assert f.clone_keys == [15]
        out[measured] = (f.twist[5], se3.yaw_of(f.T[:3, :3]))
    assert out[False][0] == pytest.approx(0.0, abs=1e-9)
    assert out[True][0] == pytest.approx(w, abs=0.1)
    assert out[True][1] == pytest.approx(w * 15 * dt, abs=0.05)


def test_clones_go_with_a_restart_and_refuse_what_they_cannot_measure():
    f = BodyEKF()
    f.clone_pose('a')
    f.predict(0.1)
    f.clone_pose('b')
    assert f.update_relative_rotation('a', 'missing', np.eye(3), np.eye(3) * 1e-4) == (False, float('inf'))
    assert not f.update_relative_rotation('a', 'b', np.full((3, 3), np.nan), np.eye(3) * 1e-4)[0]
    f.reinitialize(np.eye(4), POSE_COV)
    assert f.clone_keys == [] and f.cloned_pose('a') is None
