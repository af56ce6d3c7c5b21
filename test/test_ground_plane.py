"""Floor landmarks: depth from the camera height, the floor test, the floor's covariance."""
import numpy as np

from camera_pose_nodes.ground_plane import floor_plane, floor_points, snap_to_floor
from camera_pose_nodes.landmark_map import bearings_odom
from multicam_ego_motion.geometry import se3

HEIGHT = 0.5
# a forward-looking optical frame (z forward, x right, y down) on a body at the origin
R_BASE_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera(yaw=0.0, xy=(0.0, 0.0), pitch=0.0):
    T = np.eye(4)
    T[:3, :3] = se3.rotvec_to_R([0.0, 0.0, yaw]) @ se3.rotvec_to_R([0.0, pitch, 0.0])
    T[:2, 3] = xy
    T_bc = np.eye(4)
    T_bc[:3, :3] = R_BASE_CAM
    T_bc[2, 3] = HEIGHT
    T_oc = T @ T_bc
    return T, T_oc[:3, :3], T_oc[:3, 3]


def observe(R_oc, c_o, X):
    Xc = (X - c_o) @ R_oc
    return Xc[:, :2] / Xc[:, 2:3]


def test_floor_points_are_where_the_rays_meet_the_floor():
    rng = np.random.default_rng(0)
    T, R, c = camera(yaw=0.7, xy=(3.0, -2.0))
    # floor points 1..6 m ahead of the camera, spread sideways
    fwd, side = R[:, 2], R[:, 0]
    X = c + np.outer(rng.uniform(1, 6, 50), fwd) + np.outer(rng.uniform(-2, 2, 50), side)
    X[:, 2] = 0.0
    xy = observe(R, c, X)
    n, d = floor_plane(np.broadcast_to(T, (50, 4, 4)), 0.0)
    valid, Xf, lam, C = floor_points(bearings_odom(np.broadcast_to(R, (50, 3, 3)), xy),
                                     np.broadcast_to(c, (50, 3)), n, d, 1e-3)
    assert valid.all()
    np.testing.assert_allclose(Xf, X, atol=1e-9)
    np.testing.assert_allclose(lam, np.linalg.norm(X - c, axis=1), rtol=1e-12)
    # farther points (shallower rays) are less certain along the ray
    along = np.sqrt(np.einsum('ni,nij,nj->n', (X - c) / lam[:, None], C, (X - c) / lam[:, None]))
    order = np.argsort(lam)
    assert np.all(np.diff((along / lam)[order]) > 0)


def test_rays_at_or_above_the_horizon_and_low_cameras_are_not_floor():
    T, R, c = camera()
    X = np.array([[5.0, 0.0, HEIGHT], [5.0, 1.0, 1.0], [100.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    xy = observe(R, c, X)
    n, d = floor_plane(np.broadcast_to(T, (4, 4, 4)), 0.0)
    valid, *_ = floor_points(bearings_odom(np.broadcast_to(R, (4, 3, 3)), xy),
                             np.broadcast_to(c, (4, 3)), n, d, 1e-3)
    # horizon, above it, 0.3 deg below it (> MIN_DEPRESSION away), and a good floor point
    assert valid.tolist() == [False, False, False, True]
    # the same rays with the floor raised to 5 cm under the camera: too low to use
    n, d = floor_plane(np.broadcast_to(T, (4, 4, 4)), HEIGHT - 0.05)
    valid, *_ = floor_points(bearings_odom(np.broadcast_to(R, (4, 3, 3)), xy),
                             np.broadcast_to(c, (4, 3)), n, d, 1e-3)
    assert not valid.any()


def snap(X_tri, C_tri, R, c, xy, T, floor_z=0.0, tolerance=0.3, scale_std=0.03):
    N = len(X_tri)
    return snap_to_floor(X_tri, C_tri, np.broadcast_to(R, (N, 3, 3)), np.broadcast_to(c, (N, 3)),
                         xy, np.broadcast_to(T, (N, 4, 4)), floor_z, tolerance, scale_std, 1e-3)


def test_snap_moves_only_points_that_agree_with_the_floor():
    """A map 4 % too large (the fused poses' scale error) puts floor points 4 % too far along
    their rays: well-triangulated, they are still snapped back onto the floor (the gate
    allows for the map's scale). A floor point 15 % off and a box-face point 20 cm above
    the floor are not: their depths disagree beyond the gate."""
    T, R, c = camera(yaw=-0.3, xy=(1.0, 1.0))
    fwd, side = R[:, 2], R[:, 0]
    floor = c + np.outer([1.5, 2.0, 3.0, 4.0], fwd) + np.outer([0.3, -0.5, 0.8, 0.0], side)
    floor[:, 2] = 0.0
    box = c + 3.0 * fwd
    box[2] = 0.2
    truth = np.vstack([floor, box])
    xy = observe(R, c, truth)
    X_tri = c + 1.04 * (truth - c)
    X_tri[3] = c + 1.15 * (truth[3] - c)
    sharp = np.broadcast_to(np.eye(3) * 1e-6, (5, 3, 3))          # 1 mm: a long baseline
    on, Xs, Cs = snap(X_tri, sharp, R, c, xy, T)
    assert on.tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(Xs, truth[:3], atol=1e-9)
    assert Cs.shape == (3, 3, 3) and np.all(np.linalg.eigvalsh(Cs) > 0)
    # without room for the map's scale error, 4 % is too much where the floor depth is known
    # best (the nearest point: 1.5 % along its ray)
    on0 = snap(X_tri, sharp, R, c, xy, T, scale_std=0.0)[0]
    assert not on0[0] and on0.sum() < 3
    # young landmarks (0.5 m std along the ray) are judged by the tolerance alone
    on, *_ = snap(X_tri, np.broadcast_to(np.eye(3) * 0.25, (5, 3, 3)), R, c, xy, T)
    assert on.tolist() == [True, True, True, True, False]
    on, *_ = snap(X_tri, np.broadcast_to(np.eye(3) * 0.25, (5, 3, 3)), R, c, xy, T, tolerance=0.1)
    assert on.tolist() == [True, True, True, False, False]


def test_floor_follows_the_body_pitch_and_floor_z():
    """The floor is the body's: on a body pitched 3 degrees (a ramp) with base_link 0.1 m
    above the floor (floor_z = -0.1), floor points are still found where they are."""
    T = np.eye(4)
    T[:3, :3] = se3.rotvec_to_R([0.0, 0.05, 0.0])
    T[:3, 3] = [0.5, 0.2, 0.3] + T[:3, 2] * 0.1
    R_oc = T[:3, :3] @ R_BASE_CAM
    c_o = T[:3, 3] + T[:3, :3] @ np.array([0.0, 0.0, HEIGHT])
    n, d = T[:3, 2], T[:3, 2] @ T[:3, 3] - 0.1
    X = np.array([c_o + dist * R_oc[:, 2] + lat * R_oc[:, 0]
                  for dist, lat in [(2.0, 0.0), (3.0, 0.5), (1.5, -0.4)]])
    X -= np.outer(X @ n - d, n)                          # drop them onto that floor
    xy = observe(R_oc, c_o, X)
    on, Xs, _ = snap(X, np.broadcast_to(np.eye(3) * 1e-6, (3, 3, 3)), R_oc, c_o, xy, T,
                     floor_z=-0.1, tolerance=0.01, scale_std=0.0)
    assert on.all()
    np.testing.assert_allclose(Xs, X, atol=1e-9)
