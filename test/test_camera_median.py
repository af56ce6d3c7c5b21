import numpy as np

from arbiter_node.camera_median import median_filter, median_pose, weiszfeld
from camera_pose_nodes.pose_estimate import PoseEstimate, uninformative
from multicam_ego_motion.geometry import se3

T0 = se3.make_T(se3.rotvec_to_R([0.0, 0.0, 1.2]), [3.0, -1.0, 0.0])
COV = np.diag([0.03, 0.03, 0.03, 0.01, 0.01, 0.01]) ** 2


def cam(name, delta):
    return PoseEstimate(1, se3.perturb(T0, delta), COV.copy(), source=name, state='tracking')


def test_weiszfeld_is_robust_to_one_far_point():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [100, 100, 100.0]])
    m = weiszfeld(pts)
    assert np.linalg.norm(m) < 1.0           # the mean would be at ~25
    sym = weiszfeld(np.array([[-1.0, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0]]))
    np.testing.assert_allclose(sym, 0, atol=1e-7)


def test_median_pose_rotation_near_pi_wrap():
    Ts = [se3.make_T(se3.rotvec_to_R([0, 0, a])) for a in (np.pi - 0.01, -np.pi + 0.01, np.pi - 0.02)]
    m = median_pose(Ts)
    # all three are within 0.02 rad of yaw = pi; a component-wise median of yaw would give ~-pi/0
    assert abs(abs(se3.yaw_of(m[:3, :3])) - np.pi) < 0.021


def test_one_bad_camera_rejected_with_reason():
    rng = np.random.default_rng(1)
    ests = {n: cam(n, rng.normal(0, np.sqrt(np.diag(COV)))) for n in ('front', 'left', 'back')}
    ests['right'] = cam('right', [0.8, 0, 0, 0, 0, 0])
    ests['dead'] = uninformative(1, np.eye(4), 'dead', 'lost')
    r = median_filter(ests)
    assert set(r.inliers) == {'front', 'left', 'back'}
    assert 'right' in r.rejected and 'm from the median' in r.rejected['right']
    assert r.uninformative == ['dead']
    assert np.linalg.norm(se3.pose_error(r.T_median, T0)[:3]) < 0.05


def test_mahalanobis_and_rotation_gates():
    ests = {'a': cam('a', 0 * np.ones(6)), 'b': cam('b', np.zeros(6)),
            'c': cam('c', [0.2, 0, 0, 0, 0, 0]),        # 6.7 sigma: mahalanobis 44 > 22.5
            'd': cam('d', [0, 0, 0, 0, 0, 0.3])}        # 0.3 rad > 0.2 rad absolute gate
    r = median_filter(ests)
    assert set(r.inliers) == {'a', 'b'}
    assert 'mahalanobis' in r.rejected['c'] and 'rad' in r.rejected['d']
    loose = median_filter(ests, mahalanobis_gate=1e9, max_rotation_rad=1.0)
    assert set(loose.inliers) == {'a', 'b', 'c', 'd'}


def test_prior_breaks_tie_between_two_cameras():
    ests = {'a': cam('a', np.zeros(6)), 'b': cam('b', [0.4, 0, 0, 0, 0, 0])}
    no_prior = median_filter(ests, max_translation_m=0.15)
    assert set(no_prior.rejected) == {'a', 'b'}          # midpoint is 0.2 m from both
    with_prior = median_filter(ests, max_translation_m=0.15, prior=(T0, COV))
    assert set(with_prior.inliers) == {'a'} and 'b' in with_prior.rejected


def test_prior_breaks_two_two_tie():
    # After a blackout two cameras with young maps may agree with each other and not with
    # the two others: the plain median sits between the pairs and rejects all four (or keeps
    # whichever pair rounding favours); the prediction's vote decides.
    ests = {'a': cam('a', np.zeros(6)), 'b': cam('b', np.zeros(6)),
            'c': cam('c', [0.3, 0, 0, 0, 0, 0]), 'd': cam('d', [0.3, 0, 0, 0, 0, 0])}
    tie = median_filter(ests, max_translation_m=0.12)
    assert set(tie.rejected) == {'a', 'b', 'c', 'd'}
    assert set(median_filter(ests, max_translation_m=0.12, prior=(T0, COV), prior_max_cameras=2).rejected) \
        == {'a', 'b', 'c', 'd'}                        # 4 cameras > 2: the prior does not vote
    voted = median_filter(ests, max_translation_m=0.12, prior=(T0, COV), prior_max_cameras=8)
    assert set(voted.inliers) == {'a', 'b'} and set(voted.rejected) == {'c', 'd'}


def test_weighted_median_is_not_moved_by_loose_cameras():
    # Two cameras tracked (1 cm) and two whose position is unknown (10 m std, rotation only,
    # as when their quarters see nothing but epipolar lines), 10 cm apart.
    tight = np.diag([0.01] * 3 + [0.01] * 3) ** 2
    loose = np.diag([10.0] * 3 + [0.01] * 3) ** 2
    ests = {'a': PoseEstimate(1, T0, tight, source='a', state='tracking'),
            'b': PoseEstimate(1, T0, tight, source='b', state='tracking'),
            'c': PoseEstimate(1, se3.perturb(T0, [0.1, 0, 0, 0, 0, 0]), loose, source='c', state='tracking'),
            'd': PoseEstimate(1, se3.perturb(T0, [0.1, 0, 0, 0, 0, 0]), loose, source='d', state='tracking')}
    plain = median_filter(ests)
    assert {'a', 'b'} <= set(plain.rejected)             # 5 cm from the midpoint = 5 sigma
    weighted = median_filter(ests, weighted=True)
    assert set(weighted.inliers) == {'a', 'b', 'c', 'd'}
    assert np.linalg.norm(se3.pose_error(weighted.T_median, T0)[:3]) < 1e-3


def test_no_informative_camera():
    r = median_filter({'a': uninformative(1, np.eye(4), 'a', 'initializing')})
    assert r.T_median is None and not r.inliers and r.uninformative == ['a']


def _weiszfeld_numpy(points, iterations=50, eps=1e-9):
    """The array formulation weiszfeld() replaces (kept as the reference for its bits)."""
    x = np.median(points, axis=0)
    for _ in range(iterations):
        d = np.linalg.norm(points - x, axis=1)
        if np.any(d < eps):
            return points[np.argmin(d)].copy()
        w = 1.0 / d
        x_new = (w[:, None] * points).sum(axis=0) / w.sum()
        if np.linalg.norm(x_new - x) < eps:
            return x_new
        x = x_new
    return x


def test_weiszfeld_has_the_bits_of_the_numpy_formulation():
    # The graph and the sequential pipeline must give the same odometry bit for bit, and
    # runs before the plain-float rewrite too: same operations, same order.
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 4, 5):
        for _ in range(400):
            pts = rng.normal(size=(n, 3)) * 10 ** rng.uniform(-6, 1)
            if rng.random() < 0.1:
                pts[-1] = pts[0]                 # a duplicate: the "sitting on a sample" exit
            assert np.array_equal(weiszfeld(pts), _weiszfeld_numpy(pts))
            assert np.array_equal(weiszfeld(pts, iterations=3), _weiszfeld_numpy(pts, iterations=3))
