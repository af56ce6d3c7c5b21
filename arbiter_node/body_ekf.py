"""The general arbiter's own EKF over body pose and twist (filterpy ExtendedKalmanFilter).

Error state x (12): p (odom, m), dtheta (odom, rad; multiplicative about a nominal rotation
R_nom, folded into R_nom and zeroed after every predict and update, so it stays small),
v (base_link, m/s; Nav2 wants twist in base_link), w (base_link, rad/s).
Pose convention is multicam_ego_motion.geometry.se3: p = p_hat + dp, R = exp([dtheta]x) R_hat.

Process model: constant body twist, p' = p + R J(w dt) v dt (the arc; J = SO(3) left
Jacobian), R' = R exp(w dt), with white linear and angular acceleration noise in the body
frame. Linearised (first order; dp/dw, of order v dt^2, left out so that F @ x stays the
nominal step):
  dp'  = dp - [R J v dt]x dtheta + R J dt dv
  dth' = dtheta + R dt dw
Because dtheta is zero at predict time, F @ x is the exact constant-twist step: its dtheta
block becomes R w dt, and exp(R w dt) R = R exp(w dt) is folded into R_nom.
Why the arc: a step along the heading at its start (Euler, arc_integration=False) cuts every
turn short: at 8 Hz in a 1.3 rad/s turn, 13 mm sideways per 17 cm step, and landmarks
triangulated from those poses carry it (loop ATE 1.07 -> 0.74 %, rotation drift 0.178 ->
0.104 deg/m with the arc).

With a gyro (`gyro_bias=True`) the state has 3 more: b_g, the gyro's bias in base_link
(rad/s), a random walk; a gyro measures w + b_g (update_gyro), the cameras tell the two apart.
With the gyro comes the accelerometer: 3 more, b_a, its bias in base_link (m/s^2), a random
walk. At rest or in steady motion it reads gravity's reaction, g R^T e_z + b_a
(update_gravity): roll and pitch, not yaw. A tilt and a bias read alike until the body turns
about the vertical (the bias turns with the body, the tilt does not): then the two part.
Without one the state stays the 12 above, and so do the results, to the last bit.

Everything the filter holds is guarded: covariances are symmetrised and their eigenvalues
clamped, non-finite inputs are refused, a failed step restores the previous state.
"""
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from arbiter_node.covariance import condition_covariance, mahalanobis2
from multicam_ego_motion.geometry import se3

MAX_VARIANCE = 1e8          # ~10 km / 1e4 rad std: beyond this the state means nothing anyway


@dataclass
class BodyEkfParams:
    accel_noise: float = 0.25            # (m/s^2)^2 / Hz: white linear acceleration, body frame
    angular_accel_noise: float = 0.25    # (rad/s^2)^2 / Hz
    initial_twist_std: float = 1.0       # m/s and rad/s, for (re)initialisation
    max_dt: float = 1.0                  # s: a longer gap is integrated in steps of this size
                                         # (at most 100 steps)
    arc_integration: bool = True         # position along the arc of the twist (False: the chord)
    gyro_bias_std: float = 0.01          # rad/s: the gyro bias's prior (gyro_bias=True)
    gyro_bias_walk: float = 1e-4         # rad/s/sqrt(s): its random walk
    accel_bias_std: float = 0.1          # m/s^2: the accelerometer bias's prior (gyro_bias=True)
    accel_bias_walk: float = 1e-3        # m/s^2/sqrt(s): its random walk


BIAS = slice(12, 15)        # the gyro bias's place in the state (gyro_bias=True)
ACCEL_BIAS = slice(15, 18)  # the accelerometer bias's
STANDARD_GRAVITY = 9.80665  # m/s^2: what an accelerometer at rest reads, up


class BodyEKF:
    def __init__(self, params: Optional[BodyEkfParams] = None, gyro_bias: bool = False):
        self.params = params or BodyEkfParams()
        self.dim = 18 if gyro_bias else 12
        self.kf = ExtendedKalmanFilter(dim_x=self.dim, dim_z=6)
        self.kf.x = np.zeros((self.dim, 1))
        self.kf.P = np.zeros((self.dim, self.dim))
        if gyro_bias:
            self.kf.P[BIAS, BIAS] = np.eye(3) * self.params.gyro_bias_std ** 2
            self.kf.P[ACCEL_BIAS, ACCEL_BIAS] = np.eye(3) * self.params.accel_bias_std ** 2
        self.R_nom = np.eye(3)
        self._clear_clones()
        self.reinitialize(np.eye(4), np.eye(6) * 1e-9)

    @property
    def has_gyro_bias(self) -> bool:
        return self.dim == 18

    # ------------------------------------------------------------------ state access
    def reinitialize(self, T: np.ndarray, cov: np.ndarray, twist: Optional[np.ndarray] = None,
                     twist_cov: Optional[np.ndarray] = None):
        """Restart at pose T (base_link in odom) with 6x6 covariance; twist defaults to zero
        with `initial_twist_std`."""
        if not np.all(np.isfinite(T)):
            raise ValueError('reinitialize: non-finite pose')
        U, _, Vt = np.linalg.svd(T[:3, :3])          # re-orthonormalise whatever we were given
        self.R_nom = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        x = np.zeros((self.dim, 1))
        x[:3, 0] = T[:3, 3]
        if twist is not None and np.all(np.isfinite(twist)):
            x[6:12, 0] = twist
        P = np.zeros((self.dim, self.dim))
        P[:6, :6] = condition_covariance(cov, max_eig=MAX_VARIANCE)
        tc = twist_cov if twist_cov is not None else np.eye(6) * self.params.initial_twist_std ** 2
        P[6:12, 6:12] = condition_covariance(tc, max_eig=MAX_VARIANCE)
        if self.has_gyro_bias:
            # the IMU's biases are the sensor's, not the pose's: kept through a restart
            x[12:, 0] = self.kf.x[12:, 0]
            P[12:, 12:] = self.kf.P[12:, 12:]
        self.kf.x = x
        self.kf.P = P
        self._clear_clones()        # a restart cuts the correlation they lived on

    @property
    def T(self) -> np.ndarray:
        return se3.make_T(self.R_nom, self.kf.x[:3, 0].copy())

    @property
    def pose_covariance(self) -> np.ndarray:
        return condition_covariance(self.kf.P[:6, :6], max_eig=MAX_VARIANCE)

    @property
    def twist(self) -> np.ndarray:
        """(vx, vy, vz, wx, wy, wz) in base_link."""
        return self.kf.x[6:12, 0].copy()

    @property
    def twist_covariance(self) -> np.ndarray:
        return condition_covariance(self.kf.P[6:12, 6:12], max_eig=MAX_VARIANCE)

    @property
    def gyro_bias(self) -> Optional[np.ndarray]:
        """The gyro's bias estimate in base_link (rad/s); None without a gyro."""
        return self.kf.x[BIAS, 0].copy() if self.has_gyro_bias else None

    @property
    def accel_bias(self) -> Optional[np.ndarray]:
        """The accelerometer's bias estimate in base_link (m/s^2); None without an IMU."""
        return self.kf.x[ACCEL_BIAS, 0].copy() if self.has_gyro_bias else None

    @property
    def gyro_bias_covariance(self) -> Optional[np.ndarray]:
        return self.kf.P[BIAS, BIAS].copy() if self.has_gyro_bias else None

    # ------------------------------------------------------------------ pose clones
    # Stochastic cloning: poses kept under keys, with their joint covariance (Pcc, 6m x 6m)
    # and their cross-covariance with the state's error (Pcx, 6m x dim). Every later
    # measurement corrects them through it (a fixed-lag smoother of those poses), and a
    # measurement between two of them (a camera's rotation between its frames) corrects the
    # state.
    def _clear_clones(self):
        self.clone_keys = []
        self.clone_R = np.zeros((0, 3, 3))
        self.clone_p = np.zeros((0, 3))
        self.Pcc = np.zeros((0, 0))
        self.Pcx = np.zeros((0, self.dim))

    def clone_pose(self, key) -> None:
        """Keep the current pose under `key` (replacing one of that key)."""
        self.drop_clone(key)
        m6 = 6 * len(self.clone_keys)
        Pcc = np.empty((m6 + 6, m6 + 6))
        Pcc[:m6, :m6] = self.Pcc
        Pcc[:m6, m6:] = self.Pcx[:, :6]
        Pcc[m6:, :m6] = self.Pcx[:, :6].T
        Pcc[m6:, m6:] = self.kf.P[:6, :6]
        self.Pcc = Pcc
        self.Pcx = np.vstack([self.Pcx, self.kf.P[:6, :]])
        self.clone_keys.append(key)
        self.clone_R = np.concatenate([self.clone_R, self.R_nom[None]])
        self.clone_p = np.concatenate([self.clone_p, self.kf.x[None, :3, 0]])

    def drop_clone(self, key) -> None:
        if key not in self.clone_keys:
            return
        i = self.clone_keys.index(key)
        keep = np.r_[0:6 * i, 6 * i + 6:6 * len(self.clone_keys)]
        self.Pcc = self.Pcc[np.ix_(keep, keep)]
        self.Pcx = self.Pcx[keep]
        self.clone_R = np.delete(self.clone_R, i, axis=0)
        self.clone_p = np.delete(self.clone_p, i, axis=0)
        del self.clone_keys[i]

    def cloned_pose(self, key) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(T, 6x6 covariance) of the pose cloned under `key`, as corrected since; None if none."""
        T = self.clone_T(key)
        if T is None:
            return None
        i = 6 * self.clone_keys.index(key)
        return T, condition_covariance(self.Pcc[i:i + 6, i:i + 6], max_eig=MAX_VARIANCE)

    def clone_T(self, key) -> Optional[np.ndarray]:
        """The pose cloned under `key`, as corrected since; None if none."""
        if key not in self.clone_keys:
            return None
        i = self.clone_keys.index(key)
        return se3.make_T(self.clone_R[i], self.clone_p[i])

    def _correct_clones(self, d) -> None:
        d = d.reshape(-1, 6)
        self.clone_p = self.clone_p + d[:, :3]
        # exp of every clone's correction at once (Rodrigues; the corrections are small,
        # well inside its series' range below 1e-4 rad as well)
        w = d[:, 3:]
        th2 = np.einsum('ij,ij->i', w, w)
        th = np.sqrt(th2)
        small = th < 1e-4
        safe = np.where(small, 1.0, th)
        a = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
        b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
        K = np.zeros((len(w), 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
        E = np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)
        self.clone_R = E @ self.clone_R

    def _clones_updated(self, P_before, H, S, y):
        # The clones' gain Pcx H^T S^-1 is the optimal one whatever the state's gain did
        # (Joseph form), so their cross-covariance follows Pcx (I - K H)^T = Pcx - Kc H P.
        HPc = H @ self.Pcx.T
        Kc = np.linalg.solve(S, HPc).T
        self._correct_clones(Kc @ y)
        Pcc = self.Pcc - Kc @ HPc
        self.Pcc = 0.5 * (Pcc + Pcc.T)
        self.Pcx = self.Pcx - Kc @ (H @ P_before)

    def update_relative_rotation(self, key_a, key_b, R_ab: np.ndarray, cov: np.ndarray,
                                 gate_chi2: float = float('inf')) -> Tuple[bool, float]:
        """The body's rotation from clone a to clone b, R_ab in base_link at a (3x3 covariance
        there): R_b = R_a R_ab. Corrects both clones and, through them, the state."""
        if key_a not in self.clone_keys or key_b not in self.clone_keys:
            return False, float('inf')
        R_ab, cov = np.asarray(R_ab, float), np.asarray(cov, float)
        if not (np.all(np.isfinite(R_ab)) and np.all(np.isfinite(cov))):
            return False, float('inf')
        ia, ib = self.clone_keys.index(key_a), self.clone_keys.index(key_b)
        Ra, Rb = self.clone_R[ia], self.clone_R[ib]
        # R_b = exp(e_b) Rb_hat, R_a = exp(e_a) Ra_hat: log(Ra_hat R_ab Rb_hat^T) = e_b - e_a
        y = se3.R_to_rotvec(Ra @ R_ab @ Rb.T)
        Rm = condition_covariance(Ra @ cov @ Ra.T, max_eig=MAX_VARIANCE)
        n = self.dim
        ra, rb = slice(6 * ia + 3, 6 * ia + 6), slice(6 * ib + 3, 6 * ib + 6)
        # H picks the two clones' rotations: H P is a difference of their rows
        HPx = self.Pcx[rb] - self.Pcx[ra]                  # (3, n): with the state
        HPc = self.Pcc[rb] - self.Pcc[ra]                  # (3, 6m): with the clones
        S = HPc[:, rb] - HPc[:, ra] + Rm
        d2 = mahalanobis2(y, S)
        if not np.isfinite(d2) or d2 > gate_chi2:
            return False, d2
        snap = self._snapshot()
        try:
            Kx = np.linalg.solve(S, HPx).T                 # (n, 3)
            Kc = np.linalg.solve(S, HPc).T                 # (6m, 3)
        except np.linalg.LinAlgError:
            return False, d2
        self.kf.x = self.kf.x + (Kx @ y).reshape(-1, 1)
        self.kf.P = self.kf.P - Kx @ HPx
        if not self._finish(snap):
            return False, d2
        self._correct_clones(Kc @ y)
        self.Pcx = self.Pcx - Kc @ HPx
        Pcc = self.Pcc - Kc @ HPc
        self.Pcc = 0.5 * (Pcc + Pcc.T)
        return True, d2

    # ------------------------------------------------------------------ internals
    def _snapshot(self):
        return self.R_nom.copy(), self.kf.x.copy(), self.kf.P.copy()

    def _restore(self, snap):
        self.R_nom, self.kf.x, self.kf.P = snap[0], snap[1], snap[2]

    def _fold_rotation(self):
        """Move dtheta into the nominal rotation (re-centre the error state)."""
        dth = self.kf.x[3:6, 0]
        self.R_nom = se3.rotvec_to_R(dth) @ self.R_nom
        U, _, Vt = np.linalg.svd(self.R_nom)        # keep it orthonormal over long runs
        self.R_nom = U @ Vt
        self.kf.x[3:6, 0] = 0.0

    def _healthy(self) -> bool:
        return (np.all(np.isfinite(self.kf.x)) and np.all(np.isfinite(self.kf.P))
                and np.all(np.isfinite(self.R_nom)))

    def _finish(self, snap) -> bool:
        self._fold_rotation()
        self.kf.P = condition_covariance(self.kf.P, max_eig=MAX_VARIANCE)
        if not self._healthy():
            self._restore(snap)
            return False
        return True

    # ------------------------------------------------------------------ filter steps
    def predict(self, dt: float, gyro: Optional[Tuple[np.ndarray, np.ndarray]] = None):
        """Constant body-velocity prediction over dt seconds (dt <= 0 or non-finite: no-op).
        gyro: (the gyro's mean rate over these dt seconds in base_link, its 3x3 covariance;
        imu_buffer): the rotation follows the gyro less its bias instead of w (gyro_bias=True)."""
        if not np.isfinite(dt) or dt <= 0:
            return
        if gyro is not None and not self.has_gyro_bias:
            raise ValueError('predict with a gyro: this filter has no gyro bias state (gyro_bias=False)')
        # long gaps in at most 100 steps: bounded cost whatever the gap
        n = int(min(100, np.ceil(dt / self.params.max_dt)))
        for _ in range(n):
            self._predict_step(dt / n, gyro)

    def _predict_step(self, dt: float, gyro=None):
        snap = self._snapshot()
        R = self.R_nom
        v = self.kf.x[6:9, 0]
        RJ = R @ se3.so3_left_jacobian(self.kf.x[9:12, 0] * dt) if self.params.arc_integration else R
        F = np.eye(self.dim)
        F[0:3, 3:6] = -se3.skew(RJ @ v * dt)
        F[0:3, 6:9] = RJ * dt
        qa, qw = self.params.accel_noise, self.params.angular_accel_noise
        Q = np.zeros((self.dim, self.dim))
        if self.has_gyro_bias:
            Q[BIAS, BIAS] = np.eye(3) * self.params.gyro_bias_walk ** 2 * dt
            Q[ACCEL_BIAS, ACCEL_BIAS] = np.eye(3) * self.params.accel_bias_walk ** 2 * dt
        for i, q in ((0, qa), (3, qw)):          # (p, v) and (theta, w): white-acceleration blocks
            Q[i:i + 3, i:i + 3] = np.eye(3) * q * dt ** 3 / 3
            Q[i:i + 3, i + 6:i + 9] = R * q * dt ** 2 / 2   # odom position vs body velocity
            Q[i + 6:i + 9, i:i + 3] = R.T * q * dt ** 2 / 2
            Q[i + 6:i + 9, i + 6:i + 9] = np.eye(3) * q * dt
        u = None
        if gyro is None:
            F[3:6, 9:12] = R * dt
        else:
            # dtheta = R (rate - b_g) dt: the gyro is an input (B u), the bias a state; the
            # angle's noise is the rate's, the angular acceleration only moves w
            rate, cov = np.asarray(gyro[0], float).reshape(3), np.asarray(gyro[1], float)
            F[3:6, BIAS] = -R * dt
            u = np.zeros((self.dim, 1))
            u[3:6, 0] = R @ rate * dt
            Q[3:6, 3:6] = R @ cov @ R.T * dt * dt
            Q[3:6, 9:12] = Q[9:12, 3:6] = 0.0
        self.kf.F, self.kf.Q = F, Q
        if u is None:
            self.kf.predict()
        else:
            self.kf.B = np.eye(self.dim)       # (filterpy: x = F x + B u)
            self.kf.predict(u=u)
        if self._finish(snap) and self.clone_keys:
            self.Pcx = self.Pcx @ F.T

    def pose_innovation(self, T_meas: np.ndarray, cov: np.ndarray) -> Tuple[np.ndarray, float]:
        """Innovation (se3 error of T_meas about the estimate) and its squared Mahalanobis distance."""
        y = se3.pose_error(T_meas, self.T)
        return y, mahalanobis2(y, self.kf.P[:6, :6] + cov)

    def update_pose(self, T_meas: np.ndarray, cov: np.ndarray, gate_chi2: float = float('inf'),
                    learn_bias: bool = True) -> Tuple[bool, float]:
        """6-dof pose measurement (base_link in odom, se3-convention covariance).
        Returns (accepted, squared Mahalanobis distance of the innovation). learn_bias=False:
        the gyro bias is a consider state for this update (Schmidt-Kalman: its gain is zero,
        the covariances stay consistent), for measurements not yet trusted to tell it."""
        if not (np.all(np.isfinite(T_meas)) and np.all(np.isfinite(cov))):
            return False, float('inf')
        cov = condition_covariance(cov, max_eig=MAX_VARIANCE)
        y, d2 = self.pose_innovation(T_meas, cov)
        if not np.isfinite(d2) or d2 > gate_chi2:
            return False, d2
        H = np.hstack([np.eye(6), np.zeros((6, self.dim - 6))])
        if self.has_gyro_bias and not learn_bias:
            return self._schmidt_update(y.reshape(6, 1), H, cov, BIAS), d2
        # z = H x + y makes filterpy's residual z - H x equal the se3 innovation
        z = H @ self.kf.x + y.reshape(6, 1)
        return self._update(z, H, cov), d2

    def update_twist(self, twist: Sequence[float], cov: np.ndarray,
                     axes: Sequence[int] = (0, 1, 2, 3, 4, 5), gate_chi2: float = float('inf')) -> Tuple[bool, float]:
        """Body-twist measurement (e.g. wheel odometry): twist and cov are 6 / 6x6 in
        (vx, vy, vz, wx, wy, wz) base_link order; only `axes` are used."""
        axes = list(axes)
        z6 = np.asarray(twist, dtype=float)
        sub = np.asarray(cov, dtype=float)[np.ix_(axes, axes)]
        if not (np.all(np.isfinite(z6[axes])) and np.all(np.isfinite(sub))) or not axes:
            return False, float('inf')
        sub = condition_covariance(sub, max_eig=MAX_VARIANCE)
        H = np.zeros((len(axes), self.dim))
        for r, a in enumerate(axes):
            H[r, 6 + a] = 1.0
        z = z6[axes].reshape(-1, 1)
        y = (z - H @ self.kf.x)[:, 0]
        d2 = mahalanobis2(y, H @ self.kf.P @ H.T + sub)
        if d2 > gate_chi2:
            return False, d2
        return self._update(z, H, sub), d2

    def _gyro_measurement(self, what: str, value, cov):
        """(z (3, 1), conditioned cov) of a 3-vector measurement, None when not finite."""
        if not self.has_gyro_bias:
            raise ValueError(f'{what}: this filter has no gyro bias state (gyro_bias=False)')
        z = np.asarray(value, float).reshape(3, 1)
        cov = np.asarray(cov, float)
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(cov))):
            return None
        return z, condition_covariance(cov, max_eig=MAX_VARIANCE)

    def _update_gated(self, z, H, cov, gate_chi2: float) -> Tuple[bool, float]:
        y = (z - H @ self.kf.x)[:, 0]
        d2 = mahalanobis2(y, H @ self.kf.P @ H.T + cov)
        if d2 > gate_chi2:
            return False, d2
        return self._update(z, H, cov), d2

    def update_gyro(self, rate: Sequence[float], cov: np.ndarray,
                    gate_chi2: float = float('inf')) -> Tuple[bool, float]:
        """A gyro's mean rate over the last step, in base_link (rad/s, 3x3 covariance): it
        measures w + b_g. Needs gyro_bias=True."""
        m = self._gyro_measurement('update_gyro', rate, cov)
        if m is None:
            return False, float('inf')
        H = np.zeros((3, self.dim))
        H[:, 9:12] = np.eye(3)
        H[:, BIAS] = np.eye(3)
        return self._update_gated(m[0], H, m[1], gate_chi2)

    def update_gyro_bias(self, bias: Sequence[float], cov: np.ndarray,
                         gate_chi2: float = float('inf')) -> Tuple[bool, float]:
        """A direct measurement of the gyro bias (rad/s, 3x3 covariance): the gyro's mean rate
        over a step less the rate the cameras' tracks turned by over it. Needs gyro_bias=True."""
        m = self._gyro_measurement('update_gyro_bias', bias, cov)
        if m is None:
            return False, float('inf')
        H = np.zeros((3, self.dim))
        H[:, BIAS] = np.eye(3)
        return self._update_gated(m[0], H, m[1], gate_chi2)

    def update_gravity(self, specific_force: Sequence[float], cov: np.ndarray,
                       gate_chi2: float = float('inf')) -> Tuple[bool, float]:
        """The specific force an accelerometer reads in base_link (m/s^2, at base_link's
        origin, the body's own acceleration taken out; cov 3x3): g R^T e_z + b_a. With
        R = exp([dtheta]x) R_nom, R^T e_z is to first order R_nom^T (e_z + [e_z]x dtheta):
        roll and pitch, not yaw (about e_z). Needs gyro_bias=True."""
        m = self._gyro_measurement('update_gravity', specific_force, cov)
        if m is None:
            return False, float('inf')
        up = np.array([0.0, 0.0, 1.0])
        H = np.zeros((3, self.dim))
        H[:, 3:6] = STANDARD_GRAVITY * self.R_nom.T @ se3.skew(up)
        H[:, ACCEL_BIAS] = np.eye(3)
        h = STANDARD_GRAVITY * self.R_nom.T @ up + self.kf.x[ACCEL_BIAS, 0]
        # (z = H x + y makes filterpy's residual z - H x the innovation y)
        return self._update_gated(H @ self.kf.x + (m[0][:, 0] - h).reshape(3, 1), H, m[1], gate_chi2)

    def _schmidt_update(self, y, H, Rm, frozen: slice) -> bool:
        """Kalman update with the `frozen` states' gain set to zero (Joseph form, which
        holds for any gain): they keep their estimate, and their covariance with the others
        follows what the update did to those."""
        snap = self._snapshot()
        P = self.kf.P
        S = H @ P @ H.T + Rm
        try:
            K = np.linalg.solve(S, H @ P).T
        except np.linalg.LinAlgError:
            return False
        K[frozen, :] = 0.0
        self.kf.x = self.kf.x + K @ y
        A = np.eye(self.dim) - K @ H
        self.kf.P = A @ P @ A.T + K @ Rm @ K.T
        ok = self._finish(snap)
        if ok and self.clone_keys:
            self._clones_updated(P, H, S, y)
        return ok

    def _update(self, z, H, Rm) -> bool:
        snap = self._snapshot()
        P = self.kf.P
        try:
            self.kf.update(z, lambda x: H, lambda x: H @ x, R=Rm)
        except np.linalg.LinAlgError:
            self._restore(snap)
            return False
        ok = self._finish(snap)
        if ok and self.clone_keys:
            self._clones_updated(P, H, self.kf.S, self.kf.y)
        return ok
