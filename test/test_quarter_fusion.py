import numpy as np
import pytest

from arbiter_node.quarter_fusion import fuse_quarters, fuse_quarters_report, information_fusion
from camera_pose_nodes.pose_estimate import UNINFORMATIVE_VARIANCE, PoseEstimate, uninformative
from multicam_ego_motion.geometry import se3

T_TRUE = se3.make_T(se3.rotvec_to_R([0.02, -0.01, 0.7]), [1.0, 2.0, 0.1])
SIG = np.array([0.02, 0.02, 0.02, 0.01, 0.01, 0.01])


def quarter(i, delta=None, sig=SIG, **kw):
    d = np.zeros(6) if delta is None else np.asarray(delta, float)
    return PoseEstimate(100 + i, se3.perturb(T_TRUE, d), np.diag(sig ** 2), source=f'front/q{i}',
                        state='tracking', n_features=10, n_landmarks=8, n_inliers=7,
                        stage_ms={'extract': 1.0 + i, 'track': 2.0}, **kw)


def test_equal_weights_average_and_inflation():
    deltas = [np.r_[0.01, 0, 0, 0, 0, 0.005], np.r_[-0.01, 0, 0, 0, 0, -0.005],
              np.r_[0, 0.01, 0, 0, 0, 0], np.r_[0, -0.01, 0, 0, 0, 0]]
    qs = [quarter(i + 1, d) for i, d in enumerate(deltas)]
    e = fuse_quarters(qs, 'front', correlation=0.0)
    assert np.abs(se3.pose_error(e.T_odom_base, T_TRUE)).max() < 1e-6
    np.testing.assert_allclose(np.diag(e.covariance), SIG ** 2 / 4, rtol=1e-9)
    e5 = fuse_quarters(qs, 'front', correlation=0.5)
    np.testing.assert_allclose(np.diag(e5.covariance), SIG ** 2 / 4 * 2.5, rtol=1e-9)
    assert e.state == 'tracking' and e.source == 'front' and e.stamp_ns == 104
    assert e.n_features == 40 and e.n_inliers == 28
    assert e.stage_ms['extract'] == 5.0 and e.stage_ms['extract_sum'] == 14.0
    assert e.stage_ms['track_sum'] == 8.0


def test_weights_follow_covariance():
    a = quarter(1, np.r_[0.1, 0, 0, 0, 0, 0], sig=SIG)
    b = quarter(2, np.r_[0.0, 0, 0, 0, 0, 0], sig=SIG * 3)   # 9x less information
    T, _ = information_fusion([a.T_odom_base, b.T_odom_base], [a.covariance, b.covariance], b.T_odom_base)
    assert se3.pose_error(T, T_TRUE)[0] == pytest.approx(0.1 * 9 / 10, abs=1e-9)


def test_one_bad_quarter_rejected():
    rng = np.random.default_rng(0)
    qs = [quarter(i + 1, rng.normal(0, SIG)) for i in range(3)]
    qs.append(quarter(4, np.r_[0.5, -0.3, 0, 0, 0, 0.2]))       # a lost-track quarter
    rep = fuse_quarters_report(qs, 'front')
    assert 'front/q4' in rep.rejected and rep.used == ['front/q1', 'front/q2', 'front/q3']
    err = se3.pose_error(rep.estimate.T_odom_base, T_TRUE)
    assert np.abs(err[:3]).max() < 0.05 and np.abs(err[3:]).max() < 0.03


def test_uninformative_ignored_and_all_uninformative():
    good = quarter(1, np.r_[0.01, 0, 0, 0, 0, 0])
    un = uninformative(101, np.eye(4), 'front/q2', 'initializing')
    e = fuse_quarters([good, un], 'front', correlation=0.0)
    np.testing.assert_allclose(e.T_odom_base, good.T_odom_base, atol=1e-12)
    np.testing.assert_allclose(e.covariance, good.covariance, rtol=1e-9)
    none = fuse_quarters([un, uninformative(102, T_TRUE, 'front/q3', 'lost')], 'front')
    assert not none.informative and none.state == 'lost'
    assert np.all(np.diag(none.covariance) == UNINFORMATIVE_VARIANCE)


def test_never_nan_on_bad_input():
    bad = quarter(1)
    bad.T_odom_base = bad.T_odom_base.copy(); bad.T_odom_base[0, 3] = np.nan
    sing = quarter(2); sing.covariance = np.zeros((6, 6)); sing.covariance[0, 0] = 1e-4
    ok = quarter(3)
    rep = fuse_quarters_report([bad, sing, ok], 'front')
    assert set(rep.rejected) == {'front/q1', 'front/q2'}
    assert np.all(np.isfinite(rep.estimate.T_odom_base))
    assert se3.is_valid_covariance(rep.estimate.covariance)
    assert rep.estimate.informative


def test_two_disagreeing_keep_most_confident():
    a = quarter(1, np.r_[1.0, 0, 0, 0, 0, 0], sig=SIG * 2)
    b = quarter(2, sig=SIG)
    rep = fuse_quarters_report([a, b], 'front')
    assert rep.used == ['front/q2'] and 'front/q1' in rep.rejected


def test_params_file_gives_the_camera_arbiters_the_sequential_pipelines_values():
    # The graph's camera arbiters read config/params.yaml; the sequential pipeline (the graph's
    # ROS-free twin, which lockstep replays must equal) takes the same values from it, and the
    # file holds the table's exact ones: with a rounded gate (22.46 for 22.4577) a quarter
    # whose distance fell between was kept by one and rejected by the other.
    from pathlib import Path

    from arbiter_node.quarter_fusion import PARAMETERS
    from multicam_ego_motion.params_file import camera_fusion_params_from
    params = camera_fusion_params_from(Path(__file__).resolve().parents[1] / 'config' / 'params.yaml')
    assert params == {k: v[0] for k, v in PARAMETERS.items()}
