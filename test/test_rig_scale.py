import numpy as np
import pytest

from arbiter_node.rig_scale import (camera_direction, relative_motion, scale_correction,
                                    solve_rig_translation)
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.geometry.rig import paper_rig

C = [c.translation for c in paper_rig().cameras]
T1 = se3.make_T(se3.rotvec_to_R([0.0, 0.0, 0.4]), [2.0, 1.0, 0.0])


def motion(yaw_deg, t_body):
    """T2 = T1 moved by t_body (in base_link at T1) and yawed."""
    R = se3.rotvec_to_R([0.0, 0.0, np.radians(yaw_deg)])
    return se3.make_T(T1[:3, :3] @ R, T1[:3, 3] + T1[:3, :3] @ np.asarray(t_body, float))


def noisy(rng, d, sig):
    ax = np.cross(d, rng.normal(size=3))
    ax /= np.linalg.norm(ax)
    return se3.rotvec_to_R(ax * rng.normal(0.0, sig)) @ d


def test_exact_recovery_paper_rig_and_3d_motion():
    T2 = motion(10, [0.3, 0.02, 0.0])
    R, t = relative_motion(T1, T2)
    r = solve_rig_translation(R, [camera_direction(T1, T2, c) for c in C], C)
    assert r.observed, r.reason
    np.testing.assert_allclose(r.t, [0.3, 0.02, 0.0], atol=1e-12)
    assert r.residual_rms < 1e-12
    # s_k are the true camera displacement lengths
    for c, s in zip(C, r.s):
        assert s == pytest.approx(np.linalg.norm(t + (R - np.eye(3)) @ c), abs=1e-12)
    # general 3-D motion with two cameras only
    T3 = se3.make_T(T1[:3, :3] @ se3.rotvec_to_R([0.1, -0.2, 0.3]), T1[:3, 3] + [0.1, -0.2, 0.05])
    R, t = relative_motion(T1, T3)
    r2 = solve_rig_translation(R, [camera_direction(T1, T3, c) for c in C[:2]], C[:2])
    assert r2.observed and np.allclose(r2.t, t, atol=1e-12)


def test_noise_robustness_figures():
    rng = np.random.default_rng(3)
    T2 = motion(10, [0.3, 0.02, 0.0])
    R, t = relative_motion(T1, T2)
    D = [camera_direction(T1, T2, c) for c in C]
    for sig_deg, max_rms in ((0.1, 0.01), (0.5, 0.04), (1.0, 0.08)):
        sig = np.radians(sig_deg)
        errs = [np.linalg.norm(solve_rig_translation(R, [noisy(rng, d, sig) for d in D], C,
                                                     direction_sigma_rad=sig).t - t) / 0.3
                for _ in range(200)]
        rms = np.sqrt(np.mean(np.square(errs)))
        assert rms < max_rms, (sig_deg, rms)
        pred = solve_rig_translation(R, D, C, direction_sigma_rad=sig).relative_std
        assert 0.7 * rms < pred < 2.0 * rms       # the predicted error is honest


def test_pure_translation_not_observed():
    T2 = motion(0, [0.3, 0.0, 0.0])
    R, _ = relative_motion(T1, T2)
    r = solve_rig_translation(R, [camera_direction(T1, T2, c) for c in C], C)
    assert not r.observed and 'unobservable' in r.reason


def test_one_camera_or_static_cameras_not_observed():
    T2 = motion(10, [0.3, 0.0, 0.0])
    R, _ = relative_motion(T1, T2)
    D = [camera_direction(T1, T2, c) for c in C]
    r = solve_rig_translation(R, [D[0]], [C[0]])
    assert not r.observed and 'need 2' in r.reason
    r = solve_rig_translation(R, [D[0], None, np.zeros(3), None], C)
    assert not r.observed and r.cameras == ('0',)


def test_noisy_large_error_flagged_unobserved():
    T2 = motion(5, [0.3, 0.0, 0.0])
    R, _ = relative_motion(T1, T2)
    D = [camera_direction(T1, T2, c) for c in C]
    r = solve_rig_translation(R, D, C, direction_sigma_rad=np.radians(2.0))
    assert not r.observed and 'relative error' in r.reason


def test_scale_correction():
    T2 = motion(15, [0.3, 0.05, 0.0])
    R, t = relative_motion(T1, T2)
    r = solve_rig_translation(R, [camera_direction(T1, T2, c) for c in C], C)
    assert scale_correction(t * 0.5, r) == pytest.approx(2.0, rel=1e-9)
    r.observed = False
    assert scale_correction(t, r) is None
