"""Structure: metric 3D landmarks (odom) per track id, triangulated from fused poses.

Scale comes only from the poses handed in (the general arbiter's fused body poses and the
rig extrinsics); nothing here chooses a scale. A track becomes a landmark once the rays of
its oldest and newest views (with a known fused pose) subtend `parallax_deg`; it is
re-triangulated with more views when its parallax has grown by `refine_factor`, and dropped
when it reprojects badly or falls behind the camera.

Each landmark keeps the covariance its views' geometry gives it (triangulation_covariance).
Why: treating landmarks as exact let a young landmark, triangulated from two consecutive
fused poses, carry their relative error into the next camera pose *extrapolated* (the
camera reports e_k + (e_k - e_(k-1))), so a yaw-rate error of the fused poses sustained
itself through the map: the loop's heading crept ~0.05 deg per frame on straight stretches
with all cameras agreeing. With the covariance in the measurement noise, such landmarks
weigh little along their ray and the long-baseline ones hold the pose.
"""
import numpy as np

from camera_pose_nodes import kernel
from camera_pose_nodes.camera_model import projection_jacobian


def triangulate_views(R_oc: np.ndarray, c_o: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Linear multi-view DLT, vectorised over points.

    R_oc (N, V, 3, 3) camera->odom rotations, c_o (N, V, 3) camera centres in odom,
    xy (N, V, 2) normalized image coordinates. Returns X (N, 3) in odom. The coordinates are
    taken relative to each point's first camera centre for conditioning."""
    ref = c_o[:, :1, :]
    Rt = np.swapaxes(R_oc, -1, -2)                                   # odom -> camera
    t = -np.einsum('nvij,nvj->nvi', Rt, c_o - ref)                   # X_c = Rt X + t
    P = np.concatenate([Rt, t[..., None]], axis=-1)                  # (N, V, 3, 4)
    rows_u = xy[..., 0, None] * P[..., 2, :] - P[..., 0, :]
    rows_v = xy[..., 1, None] * P[..., 2, :] - P[..., 1, :]
    A = np.concatenate([rows_u, rows_v], axis=1)                     # (N, 2V, 4)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]
    w = np.where(np.abs(Xh[:, 3]) < 1e-12, 1e-12, Xh[:, 3])
    return Xh[:, :3] / w[:, None] + ref[:, 0, :]


def triangulation_covariance(Xc: np.ndarray, R_oc: np.ndarray, view_weights: np.ndarray,
                             sigma_n: float) -> np.ndarray:
    """Covariance (N, 3, 3) of triangulated points from their views' image noise:
    (sum_v w_v J_v^T J_v / sigma_n^2)^-1 with J_v the Jacobian of the normalized projection
    in view v. Xc (N, V, 3): each point in each view's camera frame, R_oc^T (X - c).
    Poses are taken as exact, so this is the geometry's share only: a point seen over a
    short baseline is known along its ray far worse than across it.
    view_weights (N, V): 1 per distinct view, 0 for a repeated one (short tracks repeat
    views in the DLT's fixed-size list)."""
    _, _, Jpi = projection_jacobian(Xc)
    J = np.einsum('nvij,nvkj->nvik', Jpi, R_oc)                       # d(xy)/dX = Jpi R_oc^T
    info = np.einsum('nv,nvji,nvjk->nik', view_weights, J, J) / (sigma_n * sigma_n)
    # a tiny ridge keeps a degenerate (rotation-only) point invertible; checks drop it anyway
    return np.linalg.inv(info + np.eye(3) * 1e-12)


def bearings_odom(R_oc: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Unit rays in odom for normalized coordinates xy (..., 2) seen with rotations R_oc."""
    f = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    r = np.einsum('...ij,...j->...i', R_oc, f)
    return r / np.linalg.norm(r, axis=-1, keepdims=True)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    # a zero-length ray (degenerate triangulation at a camera centre) counts as no parallax
    c = np.where(n > 1e-300, np.sum(a * b, axis=-1) / np.maximum(n, 1e-300), 1.0)
    c = np.clip(c, -1.0, 1.0)
    return np.degrees(np.arccos(c))


class LandmarkMap:
    """Landmarks by track id, as arrays sorted by id (no Python object per landmark): the
    quarter looks up, checks and updates all of its tracks' landmarks at once."""

    def __init__(self, parallax_deg=2.0, max_reproj_px=2.0, min_depth=0.1, max_depth=200.0,
                 refine_factor=2.0, focal_px=500.0, pixel_sigma=1.0):
        self.parallax_deg = float(parallax_deg)
        self.max_reproj_px = float(max_reproj_px)
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        self.refine_factor = float(refine_factor)
        self.focal_px = float(focal_px)      # converts normalized errors to pixels
        self.sigma_n = float(pixel_sigma) / self.focal_px
        self._native = kernel.use_native()    # triangulate in the native kernel (kernel.py)
        self.reset()

    _FIELDS = ('ids', 'X', 'C', 'parallax', 'on_floor')

    def reset(self):
        self.ids = np.zeros(0, np.int64)           # sorted
        self.X = np.zeros((0, 3))                  # points in odom
        self.C = np.zeros((0, 3, 3))               # their covariances
        # parallax (deg) of the last triangulation; NaN: never triangulated (placed on the floor)
        self.parallax = np.zeros(0)
        self.on_floor = np.zeros(0, bool)          # placed on the floor (ground_plane)

    def get_state(self) -> dict:
        return {k: getattr(self, k).copy() for k in self._FIELDS}

    def set_state(self, s: dict):
        self.ids = np.asarray(s['ids'], np.int64).copy()
        self.X = np.asarray(s['X'], float).reshape(-1, 3).copy()
        self.C = np.asarray(s['C'], float).reshape(-1, 3, 3).copy()
        self.parallax = np.asarray(s['parallax'], float).copy()
        self.on_floor = np.asarray(s['on_floor'], bool).copy()
        if not (len(self.ids) == len(self.X) == len(self.C) == len(self.parallax) == len(self.on_floor)):
            raise ValueError('landmark state arrays differ in length')

    def __len__(self):
        return len(self.ids)

    def __contains__(self, track_id) -> bool:
        return bool(self.rows(np.array([track_id]))[0][0])

    def rows(self, ids: np.ndarray):
        """(mask of ids with a landmark, their rows in the arrays)."""
        ids = np.asarray(ids, dtype=np.int64)
        r = np.searchsorted(self.ids, ids)
        has = r < len(self.ids)
        has[has] = self.ids[r[has]] == ids[has]
        return has, r[has]

    def lookup(self, ids: np.ndarray):
        """(mask of ids with a landmark, their points M x 3)."""
        has, r = self.rows(ids)
        return has, self.X[r]

    def point(self, track_id: int) -> np.ndarray:
        has, r = self.rows([track_id])
        if not has[0]:
            raise KeyError(track_id)
        return self.X[r[0]]

    def covariances_of(self, ids: np.ndarray) -> np.ndarray:
        """(M, 3, 3) covariances of landmarks `ids` (all must have one)."""
        has, r = self.rows(ids)
        if not has.all():
            raise KeyError(f'no landmark for track(s) {np.asarray(ids)[~has].tolist()}')
        return self.C[r]

    def floor_count(self, ids: np.ndarray) -> int:
        """How many of `ids` have a landmark placed on the floor."""
        _, r = self.rows(ids)
        return int(self.on_floor[r].sum())

    def want(self, track_ids, parallax_deg):
        """Is a (re-)triangulation of these tracks worth doing at these parallaxes? (scalar
        or arrays)"""
        ids = np.atleast_1d(np.asarray(track_ids, np.int64))
        par = np.broadcast_to(np.asarray(parallax_deg, float), ids.shape)
        old = np.full(len(ids), np.nan)
        has, r = self.rows(ids)
        old[has] = self.parallax[r]
        w = (par >= self.parallax_deg) & (np.isnan(old) | (par >= self.refine_factor * old))
        return bool(w[0]) if np.ndim(track_ids) == 0 else w

    def _upsert(self, ids, X, C, parallax, on_floor: bool):
        """Set landmarks `ids` (unique); parallax None keeps an existing landmark's record."""
        ids = np.asarray(ids, np.int64)
        if not len(ids):
            return
        has, r = self.rows(ids)
        self.X[r] = X[has]
        self.C[r] = C[has]
        self.on_floor[r] = on_floor
        if parallax is not None:
            self.parallax[r] = parallax[has]
        new = ~has
        if new.any():
            par_new = np.full(int(new.sum()), np.nan) if parallax is None else parallax[new]
            ids_all = np.concatenate([self.ids, ids[new]])
            order = np.argsort(ids_all, kind='stable')
            self.ids = ids_all[order]
            self.X = np.concatenate([self.X, X[new]])[order]
            self.C = np.concatenate([self.C, C[new]])[order]
            self.parallax = np.concatenate([self.parallax, par_new])[order]
            self.on_floor = np.concatenate([self.on_floor, np.full(int(new.sum()), on_floor)])[order]

    def _keep(self, keep: np.ndarray):
        for k in self._FIELDS:
            setattr(self, k, getattr(self, k)[keep])

    def triangulate(self, ids: np.ndarray, R_oc: np.ndarray, c_o: np.ndarray,
                    xy: np.ndarray, view_weights=None) -> np.ndarray:
        """Triangulate tracks `ids` from V views each (arrays as in triangulate_views, the
        first and last view being the widest pair) and keep those passing the checks:
        parallax at the point, positive depth in range, reprojection in every view.
        Returns the mask of accepted ids."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return np.zeros(0, bool)
        w = np.ones(np.shape(xy)[:2]) if view_weights is None else np.asarray(view_weights, float)
        if self._native:
            X, C, par, ok = kernel.native.triangulate_checked(
                R_oc, c_o, xy, w, self.sigma_n, self.min_depth, self.max_depth,
                self.parallax_deg, self.focal_px, self.max_reproj_px)
            if ok.any():
                self._upsert(ids[ok], X[ok], C[ok], par[ok], on_floor=False)
            return ok
        X = triangulate_views(R_oc, c_o, xy)
        rel = X[:, None, :] - c_o                                    # (N, V, 3)
        Xc = np.einsum('nvji,nvj->nvi', R_oc, rel)                   # R_oc^T (X - c)
        depth = Xc[..., 2]
        ok = np.all(np.isfinite(X), axis=1)
        ok &= np.all(depth > self.min_depth, axis=1) & np.all(depth < self.max_depth, axis=1)
        par = angle_deg(rel[:, 0], rel[:, -1])
        ok &= par >= self.parallax_deg
        zs = np.where(depth > 1e-9, depth, 1e-9)
        err = np.linalg.norm(Xc[..., :2] / zs[..., None] - xy, axis=-1) * self.focal_px
        ok &= np.all(err < self.max_reproj_px, axis=1)
        if not ok.any():
            return ok
        C = triangulation_covariance(Xc[ok], R_oc[ok], w[ok], self.sigma_n)
        self._upsert(ids[ok], X[ok], C, par[ok], on_floor=False)
        return ok

    def check(self, ids: np.ndarray, R_oc: np.ndarray, c_o: np.ndarray,
              xy: np.ndarray) -> np.ndarray:
        """Drop landmarks of `ids` that reproject worse than max_reproj_px or lie behind the
        camera (R_oc 3x3, c_o 3: one camera pose; xy N x 2 observations). Returns the mask
        of dropped ids."""
        ids = np.asarray(ids, dtype=np.int64)
        has, r = self.rows(ids)
        bad = np.zeros(len(ids), bool)
        if not has.any():
            return bad
        Xc = (self.X[r] - c_o) @ R_oc
        depth = Xc[:, 2]
        zs = np.where(depth > 1e-9, depth, 1e-9)
        err = np.linalg.norm(Xc[:, :2] / zs[:, None] - xy[has], axis=1) * self.focal_px
        bad_h = (depth <= self.min_depth) | (err > self.max_reproj_px) | ~np.isfinite(err)
        bad[np.flatnonzero(has)[bad_h]] = True
        keep = np.ones(len(self.ids), bool)
        keep[r[bad_h]] = False
        self._keep(keep)
        return bad

    def place(self, ids: np.ndarray, X: np.ndarray, C: np.ndarray, on_floor: bool = True):
        """Set landmarks `ids` from outside the triangulation: X (M, 3) with covariances
        C (M, 3, 3), on the floor (ground_plane) or from a stereo pair (stereo_match);
        their parallax record stays."""
        self._upsert(ids, np.asarray(X, float).reshape(-1, 3), np.asarray(C, float).reshape(-1, 3, 3),
                     None, on_floor=on_floor)

    def forget(self, track_id: int):
        self._keep(self.ids != int(track_id))

    def keep_only(self, live_ids):
        """Landmarks of tracks that no longer exist are of no use to a tracking-only map."""
        _, r = self.rows(live_ids)
        keep = np.zeros(len(self.ids), bool)
        keep[r] = True
        self._keep(keep)
