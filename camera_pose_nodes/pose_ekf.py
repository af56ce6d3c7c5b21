"""Pose: the per-quarter EKF on body pose and twist (filterpy), measured by reprojections.

Error state x (12): p (body position, odom), dtheta (orientation error, odom frame, applied
as R = exp([dtheta]x) R_nom about a nominal rotation kept outside the state), v (linear
velocity, odom), w (angular velocity, body frame). dtheta is folded into R_nom after every
predict/update ("re-centred"), so it is zero between steps and the pose covariance block
P[:6, :6] is directly in the multicam_ego_motion.geometry.se3 convention.

Measurement: normalized, undistorted image coordinates of tracked features whose landmark X
(odom) is known, h = pi(R_cam^T (X - p_cam)) with T_odom_cam = T_odom_base T_base_cam. The
number of measurements changes every frame, so H and R are built per update.

Each step runs either here (numpy/filterpy: the reference) or in the native kernel
(camera_pose_nodes.kernel selects it), on the same state: kf.x, kf.P, R_nom, stamp_ns.
"""
from typing import Optional

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from camera_pose_nodes import kernel
from camera_pose_nodes.camera_model import projection_jacobian
from multicam_ego_motion.geometry.se3 import make_T, R_to_rotvec, rotvec_to_R

DIM = 12
P_, TH, V_, W_ = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
_MIN_EIG = 1e-12
# Steps of the epipolar Jacobian's finite differences (constant: built once, not per update).
_EPS = 1e-6
_EPS_STEPS = tuple(np.eye(3) * _EPS)
_EPS_ROTATIONS = tuple(rotvec_to_R(d) for d in _EPS_STEPS)


class PoseEKF:
    def __init__(self, accel_sigma=2.0, alpha_sigma=2.0, init_pose_sigma=1.0e3,
                 init_twist_sigma=10.0):
        self.accel_sigma = float(accel_sigma)     # white acceleration, m/s^2 per sqrt(Hz)
        self.alpha_sigma = float(alpha_sigma)     # white angular acceleration, rad/s^2
        self.init_pose_sigma = float(init_pose_sigma)
        self.init_twist_sigma = float(init_twist_sigma)
        self.kf = ExtendedKalmanFilter(dim_x=DIM, dim_z=2)
        self._native = kernel.use_native()
        self.reset()

    # ----- state -------------------------------------------------------------------------
    def reset(self, T_odom_base=None):
        T = np.eye(4) if T_odom_base is None else np.asarray(T_odom_base, float)
        self.kf.x = np.zeros((DIM, 1))
        self.kf.x[P_, 0] = T[:3, 3]
        self.R_nom = T[:3, :3].copy()
        self.kf.P = np.diag([self.init_pose_sigma ** 2] * 6 + [self.init_twist_sigma ** 2] * 6)
        self.stamp_ns = None

    def get_state(self) -> dict:
        return {'x': self.kf.x.copy(), 'P': self.kf.P.copy(), 'R_nom': self.R_nom.copy(),
                'stamp_ns': self.stamp_ns}

    def set_state(self, s: dict):
        self.kf.x = np.array(s['x'], float).reshape(DIM, 1)
        self.kf.P = np.array(s['P'], float)
        self.R_nom = np.array(s['R_nom'], float)
        self.stamp_ns = s['stamp_ns']

    @property
    def T_odom_base(self) -> np.ndarray:
        return make_T(self.R_nom, self.kf.x[P_, 0])

    @property
    def pose_covariance(self) -> np.ndarray:
        return self.kf.P[:6, :6].copy()

    @property
    def twist(self):
        """(v in odom, w in base_link, 6x6 covariance of [v, w])."""
        return self.kf.x[V_, 0].copy(), self.kf.x[W_, 0].copy(), self.kf.P[6:, 6:].copy()

    def healthy(self) -> bool:
        return bool(np.isfinite(self.kf.x).all() and np.isfinite(self.kf.P).all())

    # ----- internals ---------------------------------------------------------------------
    def _native_state(self):
        """(x, P, R_nom) as the native kernel's functions take them and give them back."""
        return self.kf.x, self.kf.P, self.R_nom

    def _set_native_state(self, x, P, R_nom):
        self.kf.x = x.reshape(DIM, 1)
        self.kf.P = P
        self.R_nom = R_nom

    def _recentre(self):
        dth = self.kf.x[TH, 0]
        if np.any(dth != 0.0):
            self.R_nom = rotvec_to_R(dth) @ self.R_nom
            # Re-orthonormalise so that rounding never accumulates into a non-rotation.
            u, _, vt = np.linalg.svd(self.R_nom)
            self.R_nom = u @ vt
            self.kf.x[TH, 0] = 0.0

    def _condition(self):
        """Keep P symmetric positive definite (rounding in long runs can break both)."""
        P = 0.5 * (self.kf.P + self.kf.P.T)
        w, U = np.linalg.eigh(P)
        if w.min() < _MIN_EIG:
            P = (U * np.maximum(w, _MIN_EIG)) @ U.T
            P = 0.5 * (P + P.T)
        self.kf.P = P

    # ----- predict -----------------------------------------------------------------------
    def predict(self, stamp_ns: int, body_rate: Optional[np.ndarray] = None):
        """Constant-velocity prediction to `stamp_ns` (no-op for the first or a repeated stamp).
        body_rate: the body's mean angular rate over the step as a gyro measured it (base_link,
        rad/s): the predicted rotation is the last one turned by it instead of by the filter's
        own rate, the covariance as the model has it (the update is linearized there; the
        cameras still measure the rotation)."""
        if self.stamp_ns is None:
            self.stamp_ns = int(stamp_ns)
            return
        dt = (int(stamp_ns) - self.stamp_ns) * 1e-9
        if dt <= 0.0:
            return   # out-of-order/duplicate stamp: never run the model backwards
        self.stamp_ns = int(stamp_ns)
        R_before = self.R_nom.copy()
        if self._native:
            self._set_native_state(*kernel.native.ekf_predict(
                *self._native_state(), dt, self.accel_sigma, self.alpha_sigma))
        else:
            self._predict_numpy(dt)
        if body_rate is not None and np.all(np.isfinite(body_rate)):
            self.R_nom = R_before @ rotvec_to_R(np.asarray(body_rate, float) * dt)
            self.kf.x[TH, 0] = 0.0

    def _predict_numpy(self, dt: float):
        F = np.eye(DIM)
        F[P_, V_] = np.eye(3) * dt
        # dtheta (odom) integrates the body rate rotated into odom: R_nom w dt. Since
        # exp([R w]x) R = R exp([w]x), F x followed by re-centring is the exact rotation update.
        F[TH, W_] = self.R_nom * dt
        qa, qw = self.accel_sigma ** 2, self.alpha_sigma ** 2
        Q = np.zeros((DIM, DIM))
        Q[P_, P_] = np.eye(3) * qa * dt ** 3 / 3
        Q[P_, V_] = Q[V_, P_] = np.eye(3) * qa * dt ** 2 / 2
        Q[V_, V_] = np.eye(3) * qa * dt
        Q[TH, TH] = np.eye(3) * qw * dt ** 3 / 3
        Q[TH, W_] = self.R_nom * qw * dt ** 2 / 2
        Q[W_, TH] = Q[TH, W_].T
        Q[W_, W_] = np.eye(3) * qw * dt
        self.kf.F, self.kf.Q = F, Q
        self.kf.predict()
        self._recentre()
        self._condition()

    # ----- measurement model -------------------------------------------------------------
    def project(self, X: np.ndarray, T_base_cam: np.ndarray):
        """Predicted normalized coordinates (N x 2), camera-frame depth (N), and the
        Jacobians (N x 2 x 12) of the landmarks X (N x 3, odom) at the current estimate."""
        R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
        p = self.kf.x[P_, 0]
        A = (self.R_nom @ R_bc).T                       # odom -> camera rotation
        d = X - p                                       # landmark relative to body, odom
        Xc = d @ A.T - R_bc.T @ t_bc
        z = Xc[:, 2]
        uv, _, Jpi = projection_jacobian(Xc)
        n = len(X)
        # Xc = A (I - [dtheta]x)(X - p) - ...: dXc/dp = -A, dXc/ddtheta = A [X - p]x
        dth = np.einsum('ij,njk->nik', A, _skew_batch(d))
        H = np.zeros((n, 2, DIM))
        H[:, :, P_] = -Jpi @ A
        H[:, :, TH] = Jpi @ dth
        return uv, z, H

    # ----- update ------------------------------------------------------------------------
    def update(self, X: np.ndarray, z_obs: np.ndarray, sigma_uv, T_base_cam: np.ndarray,
               gate_chi2: float = 9.21, min_depth: float = 0.05,
               X_cov: np.ndarray = None) -> np.ndarray:
        """Fuse observed normalized coordinates z_obs (N x 2) of landmarks X (N x 3).
        sigma_uv: (su, sv) measurement std in normalized units. Returns the inlier mask.
        X_cov (N x 3 x 3, optional): the landmarks' own covariances, projected into each
        feature's noise (J_X C_X J_X^T), so a landmark known poorly along its ray weighs little.
        Each feature is gated on its own 2-dof Mahalanobis distance against the prior, so a
        gross outlier cannot drag the others; the accepted ones are fused in one update."""
        X = np.asarray(X, float).reshape(-1, 3)
        z_obs = np.asarray(z_obs, float).reshape(-1, 2)
        inl = np.zeros(len(X), bool)
        if len(X) == 0:
            return inl
        if self._native:
            su, sv = np.broadcast_to(np.asarray(sigma_uv, float), (2,))
            X_cov = None if X_cov is None else np.asarray(X_cov, float).reshape(-1, 3, 3)
            *state, inl, _ = kernel.native.ekf_update_reprojection(
                *self._native_state(), X, z_obs, su, sv, T_base_cam, gate_chi2, min_depth, X_cov)
            self._set_native_state(*state)
            return inl
        uv, depth, H = self.project(X, T_base_cam)
        r = z_obs - uv
        Rm = np.diag(np.square(np.asarray(sigma_uv, float)))
        if X_cov is not None:
            Jx = -H[:, :, P_]                          # d(uv)/dX = -d(uv)/dp
            Rm = Rm + Jx @ np.asarray(X_cov, float).reshape(-1, 3, 3) @ Jx.transpose(0, 2, 1)
        S = H @ self.kf.P @ H.transpose(0, 2, 1) + Rm
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        valid = (depth > min_depth) & np.all(np.isfinite(r), axis=1) & (det > 0)
        det = np.where(valid, det, 1.0)
        # 2x2 inverse in closed form, vectorised over features
        d2 = (S[:, 1, 1] * r[:, 0] ** 2 - (S[:, 0, 1] + S[:, 1, 0]) * r[:, 0] * r[:, 1]
              + S[:, 0, 0] * r[:, 1] ** 2) / det
        inl = valid & (d2 < gate_chi2)
        if not inl.any():
            return inl
        Hs = H[inl].reshape(-1, DIM)
        zs = z_obs[inl].reshape(-1, 1)
        hs = uv[inl].reshape(-1, 1)
        if Rm.ndim == 2:
            Rs = np.kron(np.eye(int(inl.sum())), Rm)
        else:                                          # per-feature 2x2 blocks on the diagonal
            n = int(inl.sum())
            Rs = np.zeros((n, 2, n, 2))
            Rs[np.arange(n), :, np.arange(n), :] = Rm[inl]
            Rs = Rs.reshape(2 * n, 2 * n)
        if not self._guarded_update(zs, Hs, hs, Rs):
            return np.zeros(len(X), bool)
        return inl

    def _guarded_update(self, z, H, h, R) -> bool:
        """One filterpy update with fixed H and h(x); False (prediction kept) if it produced NaN."""
        x_before, P_before = self.kf.x.copy(), self.kf.P.copy()
        self.kf.update(z, HJacobian=lambda _x: H, Hx=lambda _x: h, R=R)
        if not self.healthy():
            # A degenerate geometry produced NaN: keep the prediction rather than poison P.
            self.kf.x, self.kf.P = x_before, P_before
            return False
        self._recentre()
        self._condition()
        return True

    # ----- epipolar update (tracks without a landmark) -------------------------------------
    def epipolar_residual(self, R_ob, p, c1, r1, xy2, T_base_cam):
        """Signed distance (normalized image units) of the observations xy2 (N x 2) from the
        epipolar lines of the rays r1 (N x 3, odom) seen from camera centres c1 (N x 3, odom),
        with the body at (R_ob, p). Also returns |n_xy| / |n| (near 0 at the epipole)."""
        R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
        A = (R_ob @ R_bc).T                              # odom -> camera
        n = _epipolar_normal(c1, p + R_ob @ t_bc, A, r1 @ A.T)
        nxy = np.hypot(n[0], n[1])
        e = _line_distance(n, nxy, xy2)
        return e, nxy / np.maximum(np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), 1e-12)

    def update_epipolar(self, c1, r1, xy2, sigma, T_base_cam, gate_chi2=6.63,
                        min_baseline=0.02) -> np.ndarray:
        """Two-view constraint of tracks that have no landmark yet: the current observation
        must lie on the epipolar line of an earlier view taken at a fused pose (camera centre
        c1, ray r1 in odom). It needs no depth, so a quarter whose features are too young to
        be triangulated (fast turns) still measures its rotation and direction of travel.
        sigma: std of the line distance (normalized units). Returns the inlier mask."""
        c1 = np.asarray(c1, float).reshape(-1, 3)
        r1 = np.asarray(r1, float).reshape(-1, 3)
        xy2 = np.asarray(xy2, float).reshape(-1, 2)
        inl = np.zeros(len(c1), bool)
        if len(c1) == 0:
            return inl
        if self._native:
            *state, inl, _ = kernel.native.ekf_update_epipolar(
                *self._native_state(), c1, r1, xy2, sigma, T_base_cam, gate_chi2, min_baseline)
            self._set_native_state(*state)
            return inl
        p = self.kf.x[P_, 0].copy()
        c2 = p + self.R_nom @ T_base_cam[:3, 3]
        # a short baseline leaves the epipolar line undefined (pure rotation, standing still)
        ok = np.linalg.norm(c1 - c2, axis=1) >= min_baseline
        if not ok.any():
            return inl
        e, sharp = self.epipolar_residual(self.R_nom, p, c1, r1, xy2, T_base_cam)
        ok &= np.isfinite(e) & (sharp > 0.1)
        H = np.zeros((len(c1), DIM))
        # Numerical Jacobian: 6 vectorised evaluations. A position step leaves the camera's
        # rotation, hence the ray in the camera frame, unchanged: computed once.
        R_bc, t_bc = T_base_cam[:3, :3], T_base_cam[:3, 3]
        A = (self.R_nom @ R_bc).T
        r1_cam = r1 @ A.T
        lever = self.R_nom @ t_bc
        for k in range(3):
            n = _epipolar_normal(c1, (p + _EPS_STEPS[k]) + lever, A, r1_cam)
            H[:, k] = (_line_distance(n, np.hypot(n[0], n[1]), xy2) - e) / _EPS
            R_ob = _EPS_ROTATIONS[k] @ self.R_nom
            A_k = (R_ob @ R_bc).T
            n = _epipolar_normal(c1, p + R_ob @ t_bc, A_k, r1 @ A_k.T)
            H[:, 3 + k] = (_line_distance(n, np.hypot(n[0], n[1]), xy2) - e) / _EPS
        S = np.einsum('ni,ij,nj->n', H, self.kf.P, H) + sigma ** 2
        inl = ok & np.all(np.isfinite(H), axis=1) & (e ** 2 < gate_chi2 * S)
        if not inl.any():
            return inl
        Hs = H[inl]
        if not self._guarded_update(np.zeros((int(inl.sum()), 1)), Hs, e[inl].reshape(-1, 1),
                                    np.eye(int(inl.sum())) * sigma ** 2):
            return np.zeros(len(c1), bool)
        return inl

    # ----- realign to the fused estimate --------------------------------------------------
    def relinearize(self, T_odom_base: np.ndarray, dt: float):
        """Move the prior's mean to T_odom_base (a robust pose from the same frame's
        landmarks), its covariance kept, and the velocity by the same displacement over dt:
        the update is then linearized where the measurements are, as an iterated EKF's
        first step. Matters when the prior is far off: a car at full speed from the first
        frame moved 1.2 m while the filter predicted rest, and one linearized update from
        there overshot by 10 to 20 %."""
        T = np.asarray(T_odom_base, float)
        d = T[:3, 3] - self.kf.x[P_, 0]
        if dt > 0.0:
            self.kf.x[V_, 0] = self.kf.x[V_, 0] + d / dt
        self.kf.x[P_, 0] = T[:3, 3]
        self.kf.x[TH, 0] = 0.0
        u, _, vt = np.linalg.svd(T[:3, :3])
        self.R_nom = u @ vt

    def set_pose(self, T_odom_base: np.ndarray, cov6: np.ndarray):
        """Replace the pose by the arbiters' fused pose N(T, cov6).

        The fused pose already contains this quarter's own measurement, so fusing it as an
        independent measurement would count that twice and make the filter overconfident.
        Instead the pose marginal is *replaced* and the twist is moved along with it through
        the prior's pose-twist correlation (Gaussian conditioning on the new pose, a.k.a.
        Jeffrey's rule): twist' = twist + G (pose_f - pose), G = P_tp P_pp^-1,
        P_tt' = P_tt - G P_pt + G C G^T, P_tp' = G C. During initialisation this is also
        what estimates the velocity from the sequence of fused poses."""
        T_odom_base = np.asarray(T_odom_base, float)
        if self._native:
            self._set_native_state(*kernel.native.ekf_set_pose(*self._native_state(), T_odom_base, cov6))
            return
        C = 0.5 * (np.asarray(cov6, float) + np.asarray(cov6, float).T)
        P = self.kf.P
        delta = np.concatenate([T_odom_base[:3, 3] - self.kf.x[P_, 0],
                                R_to_rotvec(T_odom_base[:3, :3] @ self.R_nom.T)])
        Ppp, Ptp = P[:6, :6], P[6:, :6]
        try:
            G = np.linalg.solve(Ppp + np.eye(6) * _MIN_EIG, Ptp.T).T
        except np.linalg.LinAlgError:
            G = np.zeros((6, 6))
        if not np.all(np.isfinite(G)):
            G = np.zeros((6, 6))
        Pn = np.empty_like(P)
        Pn[:6, :6] = C
        Pn[6:, :6] = G @ C
        Pn[:6, 6:] = Pn[6:, :6].T
        Pn[6:, 6:] = P[6:, 6:] - G @ Ptp.T + G @ C @ G.T
        self.kf.x[6:, 0] = self.kf.x[6:, 0] + G @ delta
        self.kf.x[P_, 0] = T_odom_base[:3, 3]
        self.kf.x[TH, 0] = 0.0
        self.R_nom = T_odom_base[:3, :3].copy()
        self.kf.P = Pn
        self._condition()


def _epipolar_normal(c1, c2, A, r1_cam):
    """Epipolar plane normals in the camera frame, (c1 - c2) x r1, as 3 component arrays
    (the cross product written out: np.cross's generic axis handling cost more than the
    arithmetic, and the products and differences are the same)."""
    a = (c1 - c2) @ A.T
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = r1_cam[:, 0], r1_cam[:, 1], r1_cam[:, 2]
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


def _line_distance(n, nxy, xy2):
    return (n[0] * xy2[:, 0] + n[1] * xy2[:, 1] + n[2]) / np.maximum(nxy, 1e-12)


def _skew_batch(v: np.ndarray) -> np.ndarray:
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out
