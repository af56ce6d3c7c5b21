"""Triangulation from known (fused) poses: accuracy, parallax threshold, pruning."""
import numpy as np

from camera_pose_nodes.landmark_map import LandmarkMap
from multicam_ego_motion import se3

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
    err = np.array([np.linalg.norm(lm.points[i] - X[i]) / X[i, 2] for i in np.flatnonzero(ok)])
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
    lm.points[5] = c[5, -1] - 2 * (lm.points[5] - c[5, -1])   # behind the camera
    bad = lm.check(np.arange(20), R[0, -1], c[0, -1], obs)
    assert set(np.flatnonzero(bad)) == {3, 5}
    assert 3 not in lm.points and 5 not in lm.points and len(lm) == 18
