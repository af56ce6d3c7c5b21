"""Triangulation from known (fused) poses: accuracy, parallax threshold, pruning."""
import numpy as np

from camera_pose_nodes.landmark_map import LandmarkMap
from multicam_ego_motion.geometry import se3

F_PX = 400.0


def views(rng, n, baseline, rotation_only=False, sigma_px=0.2, V=5):
    """n points 3..8 m in front of a camera moving sideways over `baseline` metres."""
    X = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1, 1, n), rng.uniform(3, 8, n)])
    R, c = [], []
    for s in np.linspace(0, 1, V):
        R.append(se3.rotvec_to_R([0, 0.05 * s if rotation_only else 0.02 * s, 0]))
        c.append(np.zeros(3) if rotation_only else np.array([baseline * s, 0, 0]))
    R, c = np.array(R), np.array(c)
    Xc = np.einsum('vji,nvj->nvi', R, X[:, None, :] - c[None])
    xy = Xc[..., :2] / Xc[..., 2:3] + rng.normal(0, sigma_px / F_PX, (n, V, 2))
    return X, np.broadcast_to(R, (n, V, 3, 3)), np.broadcast_to(c, (n, V, 3)), xy


def test_recovers_points_to_one_percent_of_depth():
    rng = np.random.default_rng(0)
    X, R, c, xy = views(rng, 200, baseline=1.0, sigma_px=0.1)
    lm = LandmarkMap(parallax_deg=2.0, focal_px=F_PX)
    ok = lm.triangulate(np.arange(200), R, c, xy)
    assert ok.mean() > 0.95
    err = np.array([np.linalg.norm(lm.point(i) - X[i]) / X[i, 2] for i in np.flatnonzero(ok)])
    print(f'\ntriangulation: median {100 * np.median(err):.3f} %, max {100 * err.max():.3f} % of depth')
    assert err.max() < 0.01


def test_no_landmark_without_parallax():
    rng = np.random.default_rng(1)
    lm = LandmarkMap(parallax_deg=2.0, focal_px=F_PX)
    assert not lm.triangulate(np.arange(50), *views(rng, 50, 0.0, rotation_only=True)[1:]).any()
    assert not lm.triangulate(np.arange(50), *views(rng, 50, 0.05)[1:]).any()   # < 1 deg
    assert len(lm) == 0
    assert not lm.want(3, 1.0) and lm.want(3, 2.5)


def test_bad_reprojection_and_behind_camera_are_dropped():
    rng = np.random.default_rng(2)
    X, R, c, xy = views(rng, 20, baseline=1.0, sigma_px=0.0)
    lm = LandmarkMap(parallax_deg=2.0, focal_px=F_PX, max_reproj_px=2.0)
    assert lm.triangulate(np.arange(20), R, c, xy).all()
    obs = xy[:, -1].copy()
    obs[3] += 10 / F_PX                                  # 10 px off: drifted track
    lm.X[5] = c[5, -1] - 2 * (lm.point(5) - c[5, -1])   # behind the camera (row 5: ids 0..19)
    bad = lm.check(np.arange(20), R[0, -1], c[0, -1], obs)
    assert set(np.flatnonzero(bad)) == {3, 5}
    assert 3 not in lm and 5 not in lm and len(lm) == 18


def test_covariance_matches_the_scatter_of_repeated_triangulations():
    """triangulation_covariance predicts how the DLT's points scatter under pixel noise
    (Monte Carlo over 400 noisy copies of one point); the short-baseline point is known far
    worse along its ray (depth) than across it, and a repeated view adds nothing."""
    rng = np.random.default_rng(3)
    sigma_px, n = 0.5, 400
    X0 = np.array([0.3, -0.2, 4.0])
    for baseline in (0.2, 1.0):
        R = np.broadcast_to(np.eye(3), (n, 2, 3, 3))
        c = np.broadcast_to(np.array([[0, 0, 0], [baseline, 0, 0]], float), (n, 2, 3))
        Xc = X0[None, None, :] - c
        xy = Xc[..., :2] / Xc[..., 2:3] + rng.normal(0, sigma_px / F_PX, (n, 2, 2))
        lm = LandmarkMap(parallax_deg=0.5, focal_px=F_PX, pixel_sigma=sigma_px, max_reproj_px=50)
        assert lm.triangulate(np.arange(n), R, c, xy).all()
        P = lm.lookup(np.arange(n))[1]
        emp = np.cov(P.T)
        pred = np.mean(lm.covariances_of(np.arange(n)), axis=0)
        # depth variance to 25 %, the correlation structure to 0.1
        assert abs(pred[2, 2] / emp[2, 2] - 1) < 0.25, (baseline, pred[2, 2], emp[2, 2])
        corr = lambda C: C / np.sqrt(np.outer(np.diag(C), np.diag(C)))
        assert np.max(np.abs(corr(pred) - corr(emp))) < 0.1
        assert pred[2, 2] > 20 * max(pred[0, 0], pred[1, 1])        # along the ray
        if baseline == 0.2:
            short = pred[2, 2]
    assert short > 10 * pred[2, 2]              # 5x the baseline: ~25x less depth variance
    # a view listed twice (short tracks in the fixed-size DLT list) counts once
    R = np.broadcast_to(np.eye(3), (1, 3, 3, 3))
    c = np.array([[[0, 0, 0], [0, 0, 0], [1.0, 0, 0]]])
    xy = (X0[None, None, :] - c)[..., :2] / (X0[2] - c[..., 2:3])
    once = LandmarkMap(parallax_deg=0.5, focal_px=F_PX)
    twice = LandmarkMap(parallax_deg=0.5, focal_px=F_PX)
    once.triangulate([0], R, c, xy, view_weights=[[1, 0, 1]])
    twice.triangulate([0], R, c, xy)
    assert np.trace(once.covariances_of([0])[0]) > 1.3 * np.trace(twice.covariances_of([0])[0])
    # hand-over carries the covariances; forgetting drops them
    moved = LandmarkMap(parallax_deg=0.5, focal_px=F_PX)
    moved.set_state(once.get_state())
    assert np.array_equal(moved.covariances_of([0])[0], once.covariances_of([0])[0])
    moved.forget(0)
    assert len(moved) == 0 and len(moved.C) == 0


def test_arrays_stay_sorted_by_id_through_inserts_updates_and_floor_placement():
    rng = np.random.default_rng(4)
    X, R, c, xy = views(rng, 10, baseline=1.0, sigma_px=0.0)
    lm = LandmarkMap(parallax_deg=2.0, focal_px=F_PX)
    order = np.array([7, 2, 9, 0, 5])
    lm.triangulate(order, R[:5], c[:5], xy[:5])
    assert np.array_equal(lm.ids, np.sort(order))
    assert np.allclose(lm.point(7), X[0], atol=1e-6)
    # placing on the floor keeps the parallax record of a triangulated landmark and marks it
    lm.place([7, 11], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)))
    assert np.array_equal(lm.ids, [0, 2, 5, 7, 9, 11])
    assert lm.floor_count([7, 11, 0]) == 2 and lm.floor_count([3]) == 0
    assert not np.isnan(lm.parallax[3]) and np.isnan(lm.parallax[5])
    # a landmark placed but never triangulated is wanted as soon as it has the parallax
    assert list(lm.want([11, 11], [1.0, 2.5])) == [False, True]
    lm.keep_only([11, 2, 40])
    assert np.array_equal(lm.ids, [2, 11])
