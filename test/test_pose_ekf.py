"""The per-quarter EKF on synthetic landmarks seen through a known rig along a known path."""
import numpy as np

from camera_pose_nodes.landmark_map import LandmarkMap
from camera_pose_nodes.pose_ekf import PoseEKF
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.geometry.rig import paper_rig

RATE = 30.0
F_PX = 400.0


def true_pose(t):
    """Constant forward speed with a steady turn and a little vertical bob."""
    yaw = 0.15 * t
    p = np.array([0.5 * t, 0.4 * np.sin(0.3 * t), 0.02 * t])
    return se3.make_T(se3.rotvec_to_R([0, 0, yaw]), p)


def observe(T_ob, T_bc, X, rng, sigma_px, outlier_frac=0.0):
    T_oc = T_ob @ T_bc
    Xc = (X - T_oc[:3, 3]) @ T_oc[:3, :3]
    uv = Xc[:, :2] / Xc[:, 2:3]
    vis = (Xc[:, 2] > 0.5) & np.all(np.abs(uv) < 0.8, axis=1)
    z = uv + rng.normal(0, sigma_px / F_PX, uv.shape)
    out = vis & (rng.random(len(X)) < outlier_frac)
    z[out] += rng.choice([-1, 1], (out.sum(), 2)) * rng.uniform(15, 60, (out.sum(), 2)) / F_PX
    return vis, z, out


def test_jacobian_matches_numeric():
    ekf = PoseEKF()
    cam = paper_rig().camera('left')
    ekf.reset(se3.make_T(se3.rotvec_to_R([0.1, -0.2, 0.7]), [1.0, 2.0, 0.3]))
    T_oc = ekf.T_odom_base @ cam.T_base_cam
    rng = np.random.default_rng(0)
    X = T_oc[:3, :3] @ np.column_stack([rng.uniform(-1, 1, (5, 2)), rng.uniform(3, 6, 5)]).T
    X = X.T + T_oc[:3, 3]
    uv0, _, H = ekf.project(X, cam.T_base_cam)
    eps = 1e-7
    for k in range(6):
        e = np.zeros(12)
        e[k] = eps
        ekf2 = PoseEKF()
        ekf2.reset(se3.perturb(ekf.T_odom_base, e[:6]))
        uv1, _, _ = ekf2.project(X, cam.T_base_cam)
        assert np.allclose((uv1 - uv0) / eps, H[:, :, k], atol=1e-5)


def test_tracks_true_pose_after_landmarks_from_fused_poses():
    rng = np.random.default_rng(1)
    cam = paper_rig().camera('front')
    T_bc = cam.T_base_cam
    # Landmarks in a broad band ahead of the front camera, 4..12 m away.
    n = 400
    ang = rng.uniform(-1.0, 1.3, n)
    rad = rng.uniform(4, 12, n)
    X = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), rng.uniform(-1.5, 2.5, n)])

    sigma_px = 0.2                    # KLT-grade sub-pixel noise
    n_init, n_total = 45, 150          # 1.5 s with fused poses, then 3.5 s alone
    ekf = PoseEKF(accel_sigma=1.0, alpha_sigma=1.0)
    lm = LandmarkMap(parallax_deg=1.5, max_reproj_px=2.0, focal_px=F_PX)
    obs = []
    pos_err, rot_err, sizes, outl_rejected, outl_total, inl_total = [], [], [], 0, 0, 0
    for k in range(n_total):
        stamp = int(1e9 * k / RATE)
        T = true_pose(k / RATE)
        ekf.predict(stamp)
        if k < n_init:
            vis, z, _ = observe(T, T_bc, X, rng, sigma_px)
            obs.append((T, vis, z))
            ekf.set_pose(T, np.eye(6) * 1e-8)           # the arbiters' fused pose
            continue
        if k == n_init:
            # Structure from the fused poses: five views from oldest to newest.
            sel = [obs[j] for j in np.linspace(0, n_init - 1, 5).round().astype(int)]
            common = np.flatnonzero(np.all([o[1] for o in sel], axis=0))
            Tb = np.array([o[0] for o in sel]) @ T_bc
            R_oc = np.broadcast_to(Tb[:, :3, :3], (len(common), 5, 3, 3))
            c_o = np.broadcast_to(Tb[:, :3, 3], (len(common), 5, 3))
            xy = np.stack([o[2][common] for o in sel], axis=1)
            ok = lm.triangulate(common, R_oc, c_o, xy)
            assert ok.sum() > 60
        vis, z, out = observe(T, T_bc, X, rng, sigma_px, outlier_frac=0.1)
        has = lm.rows(np.arange(n))[0] & vis
        ids = np.flatnonzero(has)
        inl = ekf.update(lm.lookup(ids)[1], z[ids],
                         (sigma_px / F_PX,) * 2, T_bc, gate_chi2=9.21)
        sizes.append(len(ids))
        outl_total += out[ids].sum()
        outl_rejected += (out[ids] & ~inl).sum()
        inl_total += inl.sum()
        e = se3.pose_error(ekf.T_odom_base, T)
        pos_err.append(np.linalg.norm(e[:3]))
        rot_err.append(np.degrees(np.linalg.norm(e[3:])))
        P = ekf.kf.P
        assert np.all(np.isfinite(P)) and np.allclose(P, P.T)
        assert np.linalg.eigvalsh(P).min() > 0
    print(f'\nEKF: max pos err {1e3 * max(pos_err):.2f} mm, mean {1e3 * np.mean(pos_err):.2f} mm;'
          f' max rot err {max(rot_err):.4f} deg; measurements/frame {min(sizes)}..{max(sizes)};'
          f' outliers rejected {outl_rejected}/{outl_total}; inliers {inl_total}')
    assert max(pos_err) < 0.01
    assert max(rot_err) < 0.1
    assert len(set(sizes)) > 5                          # measurement size varies
    assert outl_rejected >= 0.95 * outl_total
    v, w, _ = ekf.twist
    assert abs(w[2] - 0.15) < 0.03                      # yaw rate (body z) recovered


def test_epipolar_update_corrects_rotation_without_landmarks():
    """Tracks with no depth: only their earlier view (fused pose) and the current pixel. The
    epipolar lines pull a wrong yaw prior back; the residual is zero at the true pose."""
    rng = np.random.default_rng(3)
    cam = paper_rig().camera('right')
    T_bc = cam.T_base_cam
    T1, T2 = true_pose(0.0), true_pose(0.5)          # ~0.25 m between the views
    X = (T2 @ T_bc)[:3, :3] @ np.column_stack([rng.uniform(-0.6, 0.6, (60, 2)),
                                               rng.uniform(2, 8, 60)]).T
    X = X.T + (T2 @ T_bc)[:3, 3]
    T_oc1, T_oc2 = T1 @ T_bc, T2 @ T_bc
    xy1 = ((X - T_oc1[:3, 3]) @ T_oc1[:3, :3])
    xy1 = xy1[:, :2] / xy1[:, 2:3]
    _, xy2, _ = observe(T2, T_bc, X, rng, 0.0)
    rays = np.column_stack([xy1, np.ones(len(X))]) @ T_oc1[:3, :3].T
    c1 = np.tile(T_oc1[:3, 3], (len(X), 1))
    ekf = PoseEKF()
    e0, _ = ekf.epipolar_residual(T2[:3, :3], T2[:3, 3], c1, rays, xy2, T_bc)
    assert np.abs(e0).max() < 1e-9
    wrong = se3.make_T(se3.rotvec_to_R([0, 0, np.radians(1.5)]) @ T2[:3, :3], T2[:3, 3])
    ekf.reset(wrong)
    ekf.kf.P[:6, :6] = np.diag([0.02 ** 2] * 3 + [np.radians(3) ** 2] * 3)
    inl = ekf.update_epipolar(c1, rays, xy2, 0.5 / F_PX, T_bc, gate_chi2=1e6)
    assert inl.sum() == len(X)
    yaw_err = se3.pose_error(ekf.T_odom_base, T2)[5]
    assert abs(np.degrees(yaw_err)) < 0.15
    # standing still: no baseline, no measurement
    ekf.reset(T1)
    assert not ekf.update_epipolar(c1, rays, xy2, 0.5 / F_PX, T_bc).any()


def test_landmark_covariance_lowers_the_weight_of_poorly_known_landmarks():
    """Half the landmarks are well known (long baseline: exact here); the other half are
    young, triangulated 30 cm back along the path over a short baseline, and 5 % too far along
    that view's rays. Taken as exact, the young ones drag the pose; with their covariance
    ("known along that ray to 10 %") the old ones hold it. Gating keeps every feature."""
    cam = paper_rig().camera('left')
    T_bc = cam.T_base_cam
    rng = np.random.default_rng(5)
    T0 = se3.make_T(np.eye(3), [0.0, 0.0, 0.0])
    T_oc = T0 @ T_bc
    n = 60
    dirs = np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), np.ones(n)])
    Xc = dirs * rng.uniform(2, 6, n)[:, None]
    X = Xc @ T_oc[:3, :3].T + T_oc[:3, 3]
    z = Xc[:, :2] / Xc[:, 2:3]
    young = np.arange(n) % 2 == 1
    c_then = T_oc[:3, 3] - np.array([0.3, 0.0, 0.0])              # the young ones' view
    ray = X - c_then
    dist = np.linalg.norm(ray, axis=1)
    ray /= dist[:, None]
    X[young] = c_then + ray[young] * (1.05 * dist[young])[:, None]
    C = np.array([(0.1 * d) ** 2 * np.outer(r, r) if y else np.zeros((3, 3))
                  for d, r, y in zip(dist, ray, young)]) + 1e-10 * np.eye(3)
    moved = {}
    for name, cov in (('exact', None), ('with covariance', C)):
        ekf = PoseEKF()
        ekf.reset(T0)
        ekf.kf.P[:6, :6] = np.eye(6) * 0.05 ** 2
        inl = ekf.update(X, z, (1 / F_PX, 1 / F_PX), T_bc, gate_chi2=1e6, X_cov=cov)
        assert inl.all()
        moved[name] = np.linalg.norm(se3.pose_error(ekf.T_odom_base, T0))
    assert moved['exact'] > 3e-3, moved
    assert moved['with covariance'] < 0.4 * moved['exact'], moved      # measured 0.32x
