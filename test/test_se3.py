"""The closed-form SO(3) logarithm agrees with scipy at every angle, including near 0 and pi."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from multicam_ego_motion.geometry.se3 import R_to_rotvec, pose_error, perturb


@pytest.mark.parametrize('angle', [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.1, 1.0, 2.0, 3.0,
                                   np.pi - 2e-3, np.pi - 1e-4, np.pi])
def test_log_matches_scipy(angle):
    rng = np.random.default_rng(int(angle * 1e6) % 1000)
    for _ in range(30):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = Rotation.from_rotvec(axis * angle).as_matrix()
        got = Rotation.from_rotvec(R_to_rotvec(R))
        ref = Rotation.from_matrix(R)
        assert np.linalg.norm((got.inv() * ref).as_rotvec()) < 1e-12


def test_pose_error_inverts_perturb():
    T = perturb(np.eye(4), [1.0, -2.0, 0.5, 0.3, -0.2, 1.1])
    delta = np.array([0.01, 0.02, -0.03, 0.004, -0.002, 0.05])
    np.testing.assert_allclose(pose_error(perturb(T, delta), T), delta, atol=1e-12)


def test_quaternion_conversions_have_scipys_bits():
    # pose messages go through these in the graph and in the sequential pipeline alike; they
    # write scipy's operations out, so the odometry does not depend on which one ran
    from multicam_ego_motion.geometry.se3 import R_to_quat_xyzw, quat_xyzw_to_R, rotvec_to_R
    rng = np.random.default_rng(3)
    for k in range(3000):
        if k % 3 == 0:
            R = Rotation.random(random_state=rng).as_matrix()
        elif k % 3 == 1:
            R = rotvec_to_R(rng.normal(size=3) * 10 ** rng.uniform(-9, 0.5))
        else:                                    # near pi: every branch of Markley's method
            axis = rng.normal(size=3)
            R = rotvec_to_R(axis / np.linalg.norm(axis) * (np.pi - 10 ** rng.uniform(-8, -1)))
        q = Rotation.from_matrix(R).as_quat()
        assert np.array_equal(R_to_quat_xyzw(R), q)
        assert np.array_equal(quat_xyzw_to_R(q), Rotation.from_quat(q).as_matrix())
        q4 = rng.normal(size=4) * 10 ** rng.uniform(-3, 3)      # not normalised
        assert np.array_equal(quat_xyzw_to_R(q4), Rotation.from_quat(q4).as_matrix())
    # not a rotation: scipy's own answer (orthonormalised) or error
    np.testing.assert_array_equal(R_to_quat_xyzw(np.eye(3) * 1.001), [0, 0, 0, 1])
    with pytest.raises(ValueError):
        R_to_quat_xyzw(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError):
        quat_xyzw_to_R([0.0, 0.0, 0.0, 0.0])


def _log_numpy(R):
    """The array formulation R_to_rotvec replaces (kept as the reference for its bits)."""
    vee = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = float(np.linalg.norm(vee))
    angle = np.arctan2(sin, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0))
    if angle < 1e-8:
        return vee
    if angle > np.pi - 1e-3:
        return Rotation.from_matrix(R).as_rotvec()
    return vee * (angle / sin)


def test_log_agrees_with_the_numpy_formulation_to_the_last_bits():
    # To a few units in the last place, not bit for bit: np.linalg.norm goes through the
    # BLAS dot product, whose kernel (and so its rounding) depends on the CPU it runs on.
    rng = np.random.default_rng(4)
    for k in range(3000):
        v = rng.normal(size=3) * 10 ** rng.uniform(-10, 0.4)
        R = Rotation.from_rotvec(v).as_matrix()
        np.testing.assert_array_max_ulp(R_to_rotvec(R), _log_numpy(R), maxulp=4)
