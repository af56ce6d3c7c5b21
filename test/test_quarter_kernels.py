"""The native kernel (camera_pose_nodes._quarter_kernels) against the numpy/filterpy reference:
each step on random well-conditioned inputs and on degenerate ones, and a whole quarter run."""
import numpy as np
import pytest

from camera_pose_nodes import kernel
from camera_pose_nodes.landmark_map import LandmarkMap
from camera_pose_nodes.pose_ekf import PoseEKF
from camera_pose_nodes.quarter_estimator import QuarterEstimator
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import paper_rig
from test_landmark_map import views
from test_quarter_estimator import N_TRUE, PARAMS, scene, step  # noqa: F401  (scene: fixture)

native_only = pytest.mark.skipif(
    not kernel.native_available(),
    reason='native kernel camera_pose_nodes._quarter_kernels is not built '
           '(python setup.py build_ext --inplace)')

REL = 1e-9      # native vs numpy: the same arithmetic up to summation order and factorisations
F_PX = 400.0


def made_with(monkeypatch, kind, make):
    monkeypatch.setenv(kernel.ENV, kind)
    return make()


def pair(monkeypatch, make):
    """(numpy, native) instances of make()."""
    return made_with(monkeypatch, 'numpy', make), made_with(monkeypatch, 'native', make)


def assert_cov_close(a, b, rel=REL):
    """Covariances equal to `rel` of each entry's scale sqrt(P_ii P_jj): the pose block
    (1e-6) and the twist block (1e2) are each held to it. (Plus rounding of the largest
    entry: an eigenvalue clamped to 1e-12 is only known to that.)"""
    d = np.sqrt(np.abs(np.diagonal(b, axis1=-2, axis2=-1)))
    scale = rel * d[..., :, None] * d[..., None, :] + 1e-14 * np.abs(b).max()
    assert np.all(np.abs(a - b) <= scale), np.max(np.abs(a - b) / scale)


def assert_same_filter(nat: PoseEKF, ref: PoseEKF, rel=REL):
    assert nat.kf.x.shape == (12, 1) and nat.kf.P.shape == (12, 12)
    sd = np.sqrt(np.diag(ref.kf.P))
    # the state to `rel` of its size, or of its standard deviation when near zero
    tol = rel * np.maximum(np.abs(ref.kf.x[:, 0]), sd)
    assert np.all(np.abs(nat.kf.x[:, 0] - ref.kf.x[:, 0]) <= tol), \
        np.max(np.abs(nat.kf.x[:, 0] - ref.kf.x[:, 0]) / tol)
    assert_cov_close(nat.kf.P, ref.kf.P, rel)
    assert np.abs(nat.R_nom - ref.R_nom).max() <= 10 * rel
    assert nat.stamp_ns == ref.stamp_ns


def random_state(rng, pose_sigma=0.05, twist_sigma=1.0):
    """A filter state as the quarters have them: pose known to centimetres, twist loosely,
    correlated."""
    A = rng.normal(size=(12, 12))
    corr = A @ A.T / 12 + np.eye(12)
    d = np.array([pose_sigma] * 6 + [twist_sigma] * 6) * rng.uniform(0.5, 2.0, 12)
    x = np.zeros((12, 1))
    x[:3, 0] = rng.normal(0, 3, 3)
    x[6:, 0] = rng.normal(0, 0.5, 6)
    return {'x': x, 'P': corr * np.outer(d, d),
            'R_nom': se3.rotvec_to_R(rng.normal(0, 1.0, 3)), 'stamp_ns': 10 ** 9}


def ekf_pair(monkeypatch, state):
    ref, nat = pair(monkeypatch, lambda: PoseEKF(accel_sigma=1.5, alpha_sigma=0.8))
    assert not ref._native and nat._native
    ref.set_state(state)
    nat.set_state(state)
    return ref, nat


def landmarks_in_view(rng, ekf, T_bc, n, depth=(2.0, 9.0), sigma_px=0.5):
    """Landmarks in front of the camera at the filter's pose, their slightly noisy
    normalized observations and landmark covariances."""
    T_oc = ekf.T_odom_base @ T_bc
    Xc = np.column_stack([rng.uniform(-0.7, 0.7, (n, 2)), np.ones(n)]) * rng.uniform(*depth, n)[:, None]
    X = Xc @ T_oc[:3, :3].T + T_oc[:3, 3]
    z = Xc[:, :2] / Xc[:, 2:3] + rng.normal(0, sigma_px / F_PX, (n, 2))
    L = rng.normal(0, 0.02, (n, 3, 3))
    return X, z, L @ L.transpose(0, 2, 1) + 1e-6 * np.eye(3)


# ----- the selector ------------------------------------------------------------------------
def test_selector_follows_the_environment(monkeypatch):
    monkeypatch.setenv(kernel.ENV, 'numpy')
    assert kernel.selected() == 'numpy' and not PoseEKF()._native and not LandmarkMap()._native
    monkeypatch.delenv(kernel.ENV)
    assert kernel.selected() == ('native' if kernel.native_available() else 'numpy')
    monkeypatch.setenv(kernel.ENV, 'fortran')
    with pytest.raises(UserError, match='expected one of native, numpy'):
        PoseEKF()
    # native requested but not built: says so and how to build it
    monkeypatch.setattr(kernel, 'native', None)
    monkeypatch.setenv(kernel.ENV, 'native')
    assert not kernel.native_available()
    with pytest.raises(UserError, match='does not import.*build_ext --inplace'):
        LandmarkMap()


@native_only
def test_native_is_the_default_when_built(monkeypatch):
    monkeypatch.delenv(kernel.ENV, raising=False)
    assert kernel.selected() == 'native' and PoseEKF()._native and LandmarkMap()._native


# ----- filter steps ------------------------------------------------------------------------
@native_only
def test_predict(monkeypatch):
    rng = np.random.default_rng(0)
    for trial in range(20):
        ref, nat = ekf_pair(monkeypatch, random_state(rng))
        for stamp in (10 ** 9, 10 ** 9 + 33_000_000, 10 ** 9 + 250_000_000, 10 ** 9 + 200_000_000):
            ref.predict(stamp)          # (the last one is out of order: a no-op in both)
            nat.predict(stamp)
            assert_same_filter(nat, ref)
    # a covariance that lost definiteness is clamped the same way (_condition)
    s = random_state(rng)
    U, _ = np.linalg.qr(rng.normal(size=(12, 12)))
    s['P'] = (U * np.r_[-1e-9, 1e-14, np.logspace(-4, 1, 10)]) @ U.T
    ref, nat = ekf_pair(monkeypatch, s)
    ref.predict(s['stamp_ns'] + 1000)
    nat.predict(s['stamp_ns'] + 1000)
    assert_same_filter(nat, ref)
    assert np.linalg.eigvalsh(nat.kf.P).min() > 0


@native_only
@pytest.mark.parametrize('with_cov', [False, True])
def test_reprojection_update(monkeypatch, with_cov):
    rng = np.random.default_rng(1)
    T_bc = paper_rig().camera('left').T_base_cam
    for trial in range(15):
        ref, nat = ekf_pair(monkeypatch, random_state(rng, pose_sigma=0.005))
        n = int(rng.integers(1, 90))
        X, z, C = landmarks_in_view(rng, ref, T_bc, n)
        out = rng.random(n) < 0.15                       # gross outliers: gated out
        z[out] += rng.choice([-1, 1], (out.sum(), 2)) * 150 / F_PX
        behind = rng.random(n) < 0.05                    # behind the camera
        c = (ref.T_odom_base @ T_bc)[:3, 3]
        X[behind] = c - (X[behind] - c)
        z[rng.random(n) < 0.03] = np.nan                 # a lost observation
        args = (X, z, (0.5 / F_PX, 0.6 / F_PX), T_bc, 9.21, 0.05, C if with_cov else None)
        inl_ref = ref.update(*args)
        inl_nat = nat.update(*args)
        assert np.array_equal(inl_nat, inl_ref)
        assert not (inl_nat & (behind | out)).any()
        assert_same_filter(nat, ref)


@native_only
def test_reprojection_update_degenerate(monkeypatch):
    rng = np.random.default_rng(2)
    T_bc = paper_rig().camera('front').T_base_cam
    s = random_state(rng, pose_sigma=0.005)
    ref, nat = ekf_pair(monkeypatch, s)
    X, z, _ = landmarks_in_view(rng, ref, T_bc, 30)
    sig = (1 / F_PX, 1 / F_PX)
    # no features: nothing happens
    for ekf in (ref, nat):
        assert ekf.update(np.zeros((0, 3)), np.zeros((0, 2)), sig, T_bc).shape == (0,)
    x, P, R, inl, ok = kernel.native.ekf_update_reprojection(
        s['x'], s['P'], s['R_nom'], np.zeros((0, 3)), np.zeros((0, 2)), *sig, T_bc, 9.21, 0.05)
    assert ok and inl.shape == (0,)
    assert np.array_equal(x, s['x'][:, 0]) and np.array_equal(P, s['P']) and np.array_equal(R, s['R_nom'])
    # all gated out: the prior stays, bit for bit
    for ekf in (ref, nat):
        assert not ekf.update(X, z + 0.5, sig, T_bc).any()
        assert np.array_equal(ekf.kf.x, s['x']) and np.array_equal(ekf.kf.P, s['P'])
    # every landmark behind the camera, or NaN ones
    c = (ref.T_odom_base @ T_bc)[:3, 3]
    for Xb, zb in ((c - (X - c), z), (np.full_like(X, np.nan), z), (X, np.full_like(z, np.nan))):
        for ekf in (ref, nat):
            assert not ekf.update(Xb, zb, sig, T_bc).any()
            assert np.array_equal(ekf.kf.x, s['x']) and np.array_equal(ekf.kf.P, s['P'])
    # an update that would not be finite (NaN velocity in the state): prediction kept, no inliers
    bad = dict(s, x=s['x'].copy())
    bad['x'][7, 0] = np.nan
    ref.set_state(bad)
    nat.set_state(bad)
    for ekf in (ref, nat):
        assert not ekf.update(X, z, sig, T_bc).any()
        assert np.array_equal(ekf.kf.P, s['P']) and np.array_equal(ekf.R_nom, s['R_nom'])
        assert np.array_equal(np.isnan(ekf.kf.x), np.isnan(bad['x']))
    *_, ok = kernel.native.ekf_update_reprojection(
        bad['x'], bad['P'], bad['R_nom'], X, z, *sig, T_bc, 9.21, 0.05)
    assert not ok
    with pytest.raises(ValueError, match=r'z: expected shape \(30, 2\)'):
        kernel.native.ekf_update_reprojection(s['x'], s['P'], s['R_nom'], X, z[:5], *sig, T_bc, 9.21, 0.05)
    with pytest.raises(ValueError, match='sigma_v: expected a positive noise sigma'):
        kernel.native.ekf_update_reprojection(s['x'], s['P'], s['R_nom'], X, z, 1e-3, 0.0, T_bc, 9.21, 0.05)


def epipolar_scene(rng, ekf, T_bc, n, baseline=0.4, sigma_px=0.5):
    """Tracks seen from an earlier camera centre `baseline` m back along a random direction,
    and now from the filter's pose (noisy)."""
    T_oc2 = ekf.T_odom_base @ T_bc
    Xc = np.column_stack([rng.uniform(-0.6, 0.6, (n, 2)), np.ones(n)]) * rng.uniform(2, 8, n)[:, None]
    X = Xc @ T_oc2[:3, :3].T + T_oc2[:3, 3]
    xy2 = Xc[:, :2] / Xc[:, 2:3] + rng.normal(0, sigma_px / F_PX, (n, 2))
    back = rng.normal(size=3)
    c1 = np.tile(T_oc2[:3, 3] - baseline * back / np.linalg.norm(back), (n, 1))
    rays = X - c1 + rng.normal(0, 0.002, (n, 3))
    return c1, rays / np.linalg.norm(rays, axis=1, keepdims=True), xy2


@native_only
def test_epipolar_update(monkeypatch):
    rng = np.random.default_rng(3)
    T_bc = paper_rig().camera('right').T_base_cam
    sigma = np.sqrt(2) * 0.5 / F_PX
    for trial in range(15):
        ref, nat = ekf_pair(monkeypatch, random_state(rng, pose_sigma=0.01))
        n = int(rng.integers(1, 80))
        c1, r1, xy2 = epipolar_scene(rng, ref, T_bc, n)
        out = rng.random(n) < 0.15
        xy2[out] += 20 / F_PX
        xy2[rng.random(n) < 0.03] = np.nan
        short = rng.random(n) < 0.1                      # some from a centre too close
        c1[short] = (ref.T_odom_base @ T_bc)[:3, 3] + 0.005
        inl_ref = ref.update_epipolar(c1, r1, xy2, sigma, T_bc, gate_chi2=6.63)
        inl_nat = nat.update_epipolar(c1, r1, xy2, sigma, T_bc, gate_chi2=6.63)
        assert np.array_equal(inl_nat, inl_ref) and not (inl_nat & short).any()
        # the Jacobian is a finite difference (step 1e-6): rounding shows through it at ~1e-10
        assert_same_filter(nat, ref, rel=1e-8)


@native_only
def test_epipolar_update_degenerate(monkeypatch):
    rng = np.random.default_rng(4)
    T_bc = paper_rig().camera('left').T_base_cam
    s = random_state(rng, pose_sigma=0.01)
    ref, nat = ekf_pair(monkeypatch, s)
    c1, r1, xy2 = epipolar_scene(rng, ref, T_bc, 40)
    sigma = 1e-3
    cases = {
        # rotation only: the earlier view from the same centre
        'no baseline': (np.tile((ref.T_odom_base @ T_bc)[:3, 3], (40, 1)), r1, xy2),
        'all gated out': (c1, r1, xy2 + 0.5),
        'NaN observations': (c1, r1, np.full_like(xy2, np.nan)),
        'no tracks': (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2))),
    }
    for name, (a, b, c) in cases.items():
        for ekf in (ref, nat):
            assert not ekf.update_epipolar(a, b, c, sigma, T_bc).any(), name
            assert np.array_equal(ekf.kf.x, s['x']) and np.array_equal(ekf.kf.P, s['P']), name
    # along the baseline the epipolar line is undefined (|n_xy| / |n| < 0.1): not used
    c2 = (ref.T_odom_base @ T_bc)[:3, 3]
    axis = (ref.T_odom_base @ T_bc)[:3, 2]
    for ekf in (ref, nat):
        assert not ekf.update_epipolar(np.tile(c2 - 0.5 * axis, (3, 1)), np.tile(axis, (3, 1)),
                                       np.zeros((3, 2)), sigma, T_bc).any()


@native_only
def test_set_pose(monkeypatch):
    rng = np.random.default_rng(5)
    for trial in range(20):
        ref, nat = ekf_pair(monkeypatch, random_state(rng))
        T = se3.make_T(se3.rotvec_to_R(rng.normal(0, 1, 3)), rng.normal(0, 3, 3))
        L = rng.normal(0, 0.01, (6, 6))
        C = L @ L.T + 1e-8 * np.eye(6)
        ref.set_pose(T, C)
        nat.set_pose(T, C)
        assert_same_filter(nat, ref)
    # a rotation by ~pi from the nominal one (R_to_rotvec's other branch), a covariance with a
    # negative eigenvalue (clamped), and a prior without pose-twist correlation
    s = random_state(rng)
    s['P'][6:, :6] = s['P'][:6, 6:] = 0.0
    ref, nat = ekf_pair(monkeypatch, s)
    T = se3.make_T(se3.rotvec_to_R([0.0, 0.0, np.pi - 1e-4]) @ s['R_nom'], [1.0, 2.0, 3.0])
    C = np.diag([1e-4, 1e-4, -1e-9, 1e-6, 1e-6, 1e-6])
    ref.set_pose(T, C)
    nat.set_pose(T, C)
    assert_same_filter(nat, ref)
    assert np.linalg.eigvalsh(nat.kf.P).min() > 0
    # a prior with no pose information (zero block): the ridge keeps the solve defined
    s = random_state(rng)
    s['P'][:6, :] = s['P'][:, :6] = 0.0
    ref, nat = ekf_pair(monkeypatch, s)
    ref.set_pose(T, np.eye(6) * 1e-6)
    nat.set_pose(T, np.eye(6) * 1e-6)
    assert_same_filter(nat, ref)


@native_only
def test_filter_sequence_and_hand_over_across_kernels(monkeypatch):
    """Steps chained as a quarter chains them; halfway the state moves between kernels."""
    rng = np.random.default_rng(6)
    T_bc = paper_rig().camera('front').T_base_cam
    ref, nat = ekf_pair(monkeypatch, random_state(rng))
    stamp = 10 ** 9
    for k in range(40):
        stamp += 33_333_333
        for ekf in (ref, nat):
            ekf.predict(stamp)
        X, z, C = landmarks_in_view(rng, ref, T_bc, 60)
        assert np.array_equal(ref.update(X, z, (1 / F_PX,) * 2, T_bc, X_cov=C),
                              nat.update(X, z, (1 / F_PX,) * 2, T_bc, X_cov=C))
        if k % 3 == 0:
            T = ref.T_odom_base @ se3.make_T(se3.rotvec_to_R(rng.normal(0, 1e-3, 3)), rng.normal(0, 1e-3, 3))
            for ekf in (ref, nat):
                ekf.set_pose(T, np.eye(6) * 1e-6)
        assert_same_filter(nat, ref, rel=1e-8)
        if k == 20:                     # hand over: each continues from the other's state
            ref_state, nat_state = ref.get_state(), nat.get_state()
            ref.set_state(nat_state)
            nat.set_state(ref_state)


# ----- triangulation ---------------------------------------------------------------------
def landmark_pair(monkeypatch, **kw):
    return pair(monkeypatch, lambda: LandmarkMap(focal_px=F_PX, **kw))


@native_only
def test_triangulation(monkeypatch):
    rng = np.random.default_rng(7)
    ref, nat = landmark_pair(monkeypatch, parallax_deg=2.0, max_reproj_px=1.0)
    n = 300
    X, R, c, xy = views(rng, n, baseline=0.8, sigma_px=0.3)
    xy = xy.copy()
    xy[rng.random(n) < 0.1, 2] += 3 / F_PX                       # a bad middle view
    w = np.ones((n, 5))
    rep = rng.random(n) < 0.3                                    # short tracks repeat views
    xy[rep, 1], w[rep, 1] = xy[rep, 0], 0.0
    ids = rng.permutation(10 * n)[:n]
    ok_ref = ref.triangulate(ids, R, c, xy, view_weights=w)
    ok_nat = nat.triangulate(ids, R, c, xy, view_weights=w)
    assert np.array_equal(ok_nat, ok_ref) and 0.5 < ok_ref.mean() < 0.99
    a, b = nat.get_state(), ref.get_state()
    assert np.array_equal(a['ids'], b['ids']) and np.array_equal(a['on_floor'], b['on_floor'])
    assert np.allclose(a['X'], b['X'], rtol=REL, atol=0)
    assert np.allclose(a['parallax'], b['parallax'], rtol=REL, atol=0)
    assert_cov_close(a['C'], b['C'], rel=1e-8)      # ~1e6 condition number along the rays
    # no weights given: every view counts
    assert np.array_equal(nat.triangulate(ids, R, c, xy), ref.triangulate(ids, R, c, xy))
    assert_cov_close(nat.C, ref.C, rel=1e-8)


@native_only
def test_triangulation_degenerate(monkeypatch):
    rng = np.random.default_rng(8)
    ref, nat = landmark_pair(monkeypatch, parallax_deg=2.0)
    for lm in (ref, nat):
        assert lm.triangulate([], np.zeros((0, 5, 3, 3)), np.zeros((0, 5, 3)), np.zeros((0, 5, 2))).shape == (0,)
    # rotation only, and too little parallax
    for args in (views(rng, 40, 0.0, rotation_only=True)[1:], views(rng, 40, 0.05)[1:]):
        assert not ref.triangulate(np.arange(40), *args).any()
        assert not nat.triangulate(np.arange(40), *args).any()
    # behind the cameras: the same rays through the centres, reversed
    X, R, c, xy = views(rng, 20, baseline=1.0, sigma_px=0.0)
    R_flip = R @ np.diag([-1.0, 1.0, -1.0])                     # looking the other way
    xy_flip = xy * [1.0, -1.0]
    assert not ref.triangulate(np.arange(20), R_flip, c, xy_flip).any()
    assert not nat.triangulate(np.arange(20), R_flip, c, xy_flip).any()
    assert len(ref) == len(nat) == 0
    # a NaN row is rejected on its own (numpy's SVD refuses the whole batch)
    xy_nan = xy.copy()
    xy_nan[3, 2] = np.nan
    ok = nat.triangulate(np.arange(20), R, c, xy_nan)
    assert not ok[3] and ok[np.arange(20) != 3].all()
    *_, ok_direct = kernel.native.triangulate_checked(R, c, xy_nan, np.ones((20, 5)), 1 / F_PX, 0.1, 200.0,
                                                      2.0, F_PX, 2.0)
    assert np.array_equal(ok, ok_direct)


# ----- a whole quarter -----------------------------------------------------------------------
@native_only
def test_quarter_estimates_match_across_kernels(monkeypatch, scene):  # noqa: F811
    cam, intr, frames, images = scene
    ref, nat = pair(monkeypatch, lambda: QuarterEstimator(cam, 1, intr, PARAMS))
    assert nat.ekf._native and nat.landmarks._native and not ref.ekf._native
    informative = 0
    for k in range(30):
        stamp, T = frames[k]
        e_ref = step(ref, k, stamp, images[k], T)
        e_nat = step(nat, k, stamp, images[k], T)
        assert (e_nat.state, e_nat.n_features, e_nat.n_landmarks, e_nat.n_inliers) == \
            (e_ref.state, e_ref.n_features, e_ref.n_landmarks, e_ref.n_inliers), k
        assert np.allclose(e_nat.T_odom_base, e_ref.T_odom_base, rtol=0, atol=1e-6), k
        assert_cov_close(e_nat.covariance, e_ref.covariance, rel=1e-6)
        informative += e_nat.state == 'tracking'
    assert informative > 20
    assert np.array_equal(nat.landmarks.ids, ref.landmarks.ids)
    assert np.allclose(nat.landmarks.X, ref.landmarks.X, rtol=0, atol=1e-6)
