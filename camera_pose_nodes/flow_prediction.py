"""Where each track should be in the next image: the camera's motion since the last estimate
applied to what the quarter knows of the point's depth.

Lucas-Kanade converges from a start within about its window at the coarsest pyramid level;
a car moves a metre and more between frames, and a road point 5 m ahead then moves 100 px.
Rotation alone (the last estimate's angular rate) steers far points; near points need the
translation and a depth: the point's landmark where it has one, the floor where its ray
meets it (the rig's floor under the body: road and floor points, the fastest-moving ones),
else none (far: rotation only). The motion and the landmarks' camera-frame points are taken
when an estimate is made (MotionPrior), so a flow computed early, while the fused pose is on
its way, is the same as one computed late.
"""
from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np

from camera_pose_nodes.ground_plane import MIN_DEPRESSION_RAD
from multicam_ego_motion.geometry.se3 import rotvec_to_R

MAX_FLOOR_DEPTH_M = 80.0      # farther floor intersections: as good as at infinity
# A known point within this fraction of the camera's height of the floor plane is on the floor
# (road landmarks are placed on it; triangulated ones scatter by a few %).
ON_FLOOR_TOLERANCE = 0.1


@dataclass
class MotionPrior:
    stamp_ns: int
    w_body: np.ndarray                  # angular rate in base_link (rad/s)
    v_body: Optional[np.ndarray] = None  # velocity in base_link (m/s); None: rotation only
    ids: np.ndarray = None              # tracks whose camera-frame point is known ...
    Xc: np.ndarray = None               # ... (K, 3), at stamp_ns

    def to_list(self):
        return [self.stamp_ns, self.w_body.copy(), None if self.v_body is None else self.v_body.copy(),
                None if self.ids is None else self.ids.copy(), None if self.Xc is None else self.Xc.copy()]

    @classmethod
    def from_list(cls, s):
        arr = (lambda a: None if a is None else np.array(a))
        return cls(int(s[0]), np.array(s[1], float), arr(s[2]), arr(s[3]), arr(s[4]))


def camera_motion(prior: MotionPrior, dt: float, T_base_cam: np.ndarray):
    """(R, t): camera 2's pose in camera 1's frame after dt at the prior's twist
    (X1 = R X2 + t)."""
    R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
    Rb = rotvec_to_R(prior.w_body * dt)
    tb = np.zeros(3) if prior.v_body is None else prior.v_body * dt
    return R_bc.T @ Rb @ R_bc, R_bc.T @ (Rb @ t_bc + tb - t_bc)


class FloorWarp(NamedTuple):
    """The floor's homography between the previous and the new image (full-image pixels,
    previous -> new) at the prior's motion, and which tracks are known to lie on the floor."""
    H: np.ndarray
    on_floor: np.ndarray        # bool per track row


def _known_points(prior: MotionPrior, track_ids: np.ndarray) -> np.ndarray:
    """The tracks' camera-frame points at the prior's stamp (N, 3), NaN where unknown."""
    known = np.full((len(track_ids), 3), np.nan)
    if prior.ids is not None and len(prior.ids) and len(track_ids):
        i = np.minimum(np.searchsorted(prior.ids, track_ids), len(prior.ids) - 1)
        hit = prior.ids[i] == track_ids
        known[hit] = prior.Xc[i[hit]]
    return known


def floor_warp(prior: MotionPrior, stamp_ns: int, T_base_cam: np.ndarray, intrinsics,
               track_ids: np.ndarray, floor_z: Optional[float]) -> Optional[FloorWarp]:
    """The floor's plane-induced homography from the prior's motion, for Lucas-Kanade on the
    previous image warped onto the new one (KLTTracker.flow): a road patch a car approaches
    grows and shears by 15-35 % between frames at 5-10 Hz, which a translation-only search
    does not follow from any start. None without a velocity, a floor, or with the camera
    not above it. Pixels are undistorted pinhole ones (rectified images)."""
    if prior.v_body is None or floor_z is None or np.any(np.asarray(intrinsics.D) != 0):
        return None
    R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
    h = t_bc[2] - floor_z
    if h <= 0:
        return None
    dt = (int(stamp_ns) - prior.stamp_ns) * 1e-9
    R, t = camera_motion(prior, dt, T_base_cam)
    n = -R_bc.T @ np.array([0.0, 0.0, 1.0])          # the body's down in the camera
    # a floor point X1 (n.X1 = h) in camera 2: X2 = R^T (X1 - t) = R^T (I - t n^T / h) X1
    K = intrinsics.K
    H = K @ R.T @ (np.eye(3) - np.outer(t, n) / h) @ np.linalg.inv(K)
    known = _known_points(prior, track_ids)
    with np.errstate(invalid='ignore'):
        on_floor = np.all(np.isfinite(known), axis=1) & (np.abs(known @ n - h) < ON_FLOOR_TOLERANCE * h)
    return FloorWarp(H / H[2, 2], on_floor)


def floor_points_cam(rays: np.ndarray, T_base_cam: np.ndarray, floor_z: Optional[float]) -> np.ndarray:
    """Where camera rays (N, 3) meet the rig's floor (camera frame), NaN where they do not
    (above or near the horizon, beyond MAX_FLOOR_DEPTH_M, no floor)."""
    out = np.full(rays.shape, np.nan)
    if floor_z is None:
        return out
    R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
    height = t_bc[2] - floor_z
    d = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    down = -(d @ R_bc.T)[:, 2]                          # sine of the depression in the body
    ok = (height > 0) & (down >= np.sin(MIN_DEPRESSION_RAD))
    lam = np.where(ok, height / np.where(ok, down, 1.0), np.nan)
    ok &= lam <= MAX_FLOOR_DEPTH_M
    out[ok] = d[ok] * lam[ok, None]
    return out


def predictor(prior: MotionPrior, stamp_ns: int, T_base_cam: np.ndarray, intrinsics,
              track_ids: np.ndarray, floor_z: Optional[float]):
    """(forward, backward) maps for KLTTracker.flow: full-image pixels (N, 2) of the tracks
    `rows` (indices into track_ids) -> where they should be in the new / previous image.
    The prior has a velocity (rotation alone: the quarter's own rotation map)."""
    dt = (int(stamp_ns) - prior.stamp_ns) * 1e-9
    R, t = camera_motion(prior, dt, T_base_cam)
    known = _known_points(prior, track_ids)

    def rays(px):
        xy = intrinsics.undistort_points(px)
        return np.column_stack([xy, np.ones(len(xy))])

    def project(X):
        z = np.where(X[:, 2] > 1e-6, X[:, 2], np.nan)        # behind: no prediction
        return intrinsics.project(X[:, :2] / z[:, None])

    def points(px, rows, R_from, t_from, own_known):
        """Camera-frame points of the pixels (the known point, else the floor, else a
        direction), moved into the other camera (X_other = R_from^T (X - t_from))."""
        d = rays(px)
        X = own_known(rows, d)
        far = ~np.all(np.isfinite(X), axis=1)
        out = (X - t_from) @ R_from
        out[far] = d[far] @ R_from
        return out

    def forward(px, rows):
        def own(rows_, d):
            X = known[rows_].copy()
            miss = ~np.all(np.isfinite(X), axis=1)
            X[miss] = floor_points_cam(d[miss], T_base_cam, floor_z)
            return X
        return project(points(px, rows, R, t, own))

    # camera 1 in camera 2: X2 = R^T (X1 - t), so X1 = R X2 + t
    R_b, t_b = R.T, -R.T @ t

    def backward(px, rows):
        def own(rows_, d):
            # the known point's depth in the new view, along the new pixel's ray
            X1 = known[rows_]
            X2 = (X1 - t) @ R
            z = np.linalg.norm(X2, axis=1) / np.linalg.norm(d, axis=1)
            X = d * z[:, None]
            miss = ~np.all(np.isfinite(X), axis=1)
            X[miss] = floor_points_cam(d[miss], T_base_cam, floor_z)
            return X
        return project(points(px, rows, R_b, t_b, own))

    return forward, backward
