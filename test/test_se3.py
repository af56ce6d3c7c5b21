"""The closed-form SO(3) logarithm agrees with scipy at every angle, including near 0 and pi."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from multicam_ego_motion.se3 import R_to_rotvec, pose_error, perturb


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
