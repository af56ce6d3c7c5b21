"""Intrinsics from CameraInfo fields: pixel <-> normalized image coordinates.

The filter and triangulation work on undistorted normalized coordinates (x/z, y/z in the
optical frame), so lens distortion is handled once, here.
"""
from dataclasses import dataclass

import numpy as np
import cv2

from multicam_ego_motion.errors import UserError

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)

# ROS distortion_model names -> number of coefficients OpenCV takes.
_MODELS = {'plumb_bob': (4, 5), 'rational_polynomial': (8, 14), 'equidistant': (4, 4),
           'none': (0, 0), '': (0, 0)}


def projection_jacobian(Xc: np.ndarray):
    """Normalized projection (x/z, y/z) of camera-frame points Xc (..., 3): returns
    (xy (..., 2), z with |z| >= 1e-9 (...), Jacobian d(xy)/d(Xc) (..., 2, 3)). The filter's
    measurement model and the landmarks' covariance both differentiate it."""
    z = Xc[..., 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    xy = Xc[..., :2] / zs[..., None]
    J = np.zeros(Xc.shape[:-1] + (2, 3))
    J[..., 0, 0] = J[..., 1, 1] = 1.0 / zs
    J[..., :, 2] = -xy / zs[..., None]
    return xy, zs, J


@dataclass
class CameraIntrinsics:
    K: np.ndarray                 # 3x3
    D: np.ndarray                 # distortion coefficients (may be empty)
    distortion_model: str         # ROS name
    width: int
    height: int

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @classmethod
    def from_camera_info(cls, k, d, distortion_model: str, width: int, height: int,
                         camera: str = 'camera') -> 'CameraIntrinsics':
        """From CameraInfo.k (9 row-major), .d, .distortion_model, .width, .height."""
        K = np.asarray(k, dtype=float).reshape(-1)
        if K.size != 9:
            raise UserError(f'{camera}: CameraInfo.k must have 9 numbers, got {K.size}')
        K = K.reshape(3, 3)
        D = np.asarray(d if d is not None else [], dtype=float).reshape(-1)
        model = (distortion_model or '').lower()
        if model not in _MODELS:
            raise UserError(f'{camera}: distortion model {distortion_model!r} not supported '
                            f'(supported: plumb_bob, rational_polynomial, equidistant, none)')
        if not np.all(np.isfinite(K)) or not np.all(np.isfinite(D)):
            raise UserError(f'{camera}: CameraInfo has NaN/inf in k or d')
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise UserError(f'{camera}: CameraInfo focal length must be > 0 '
                            f'(fx={K[0, 0]}, fy={K[1, 1]}); is the camera calibrated?')
        if int(width) <= 0 or int(height) <= 0:
            raise UserError(f'{camera}: CameraInfo size {width}x{height} is empty')
        lo, hi = _MODELS[model]
        if np.any(D != 0) and not lo <= D.size <= hi:
            raise UserError(f'{camera}: {model} expects {lo}..{hi} coefficients, got {D.size}')
        if not np.any(D != 0):
            model, D = 'none', np.zeros(0)
        return cls(K, D, model, int(width), int(height))

    @classmethod
    def pinhole(cls, fx, fy, cx, cy, width, height) -> 'CameraIntrinsics':
        return cls.from_camera_info([fx, 0, cx, 0, fy, cy, 0, 0, 1], [], 'none', width, height)

    def undistort_points(self, px: np.ndarray) -> np.ndarray:
        """Nx2 pixels -> Nx2 normalized undistorted coordinates."""
        px = np.asarray(px, dtype=np.float64).reshape(-1, 1, 2)
        if px.shape[0] == 0:
            return np.zeros((0, 2))
        if self.distortion_model == 'none':
            K = self.K
            return np.column_stack(((px[:, 0, 0] - K[0, 2]) / K[0, 0],
                                    (px[:, 0, 1] - K[1, 2]) / K[1, 1]))
        if self.distortion_model == 'equidistant':
            return cv2.fisheye.undistortPoints(px, self.K, self.D).reshape(-1, 2)
        # The default 5 iterations leave ~0.03 px at strongly distorted corners; iterate to
        # convergence so distortion never becomes a measurement bias.
        return cv2.undistortPoints(px, self.K, self.D, None, None, None, _UNDISTORT_CRITERIA
                                   ).reshape(-1, 2)

    def project(self, normalized: np.ndarray) -> np.ndarray:
        """Nx2 normalized coordinates -> Nx2 pixels (distortion applied)."""
        xy = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
        if xy.shape[0] == 0:
            return np.zeros((0, 2))
        if self.distortion_model == 'none':
            return xy * [self.K[0, 0], self.K[1, 1]] + [self.K[0, 2], self.K[1, 2]]
        pts = np.column_stack((xy, np.ones(len(xy)))).reshape(-1, 1, 3)
        if self.distortion_model == 'equidistant':
            out, _ = cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.D)
        else:
            out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.D)
        return out.reshape(-1, 2)


def intrinsics_from_msg(msg, camera: str = 'camera') -> CameraIntrinsics:
    """From a sensor_msgs/CameraInfo (duck-typed: no ROS import here)."""
    return CameraIntrinsics.from_camera_info(msg.k, msg.d, msg.distortion_model, msg.width,
                                             msg.height, camera=camera)
