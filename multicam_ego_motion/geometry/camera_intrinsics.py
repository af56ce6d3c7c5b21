"""Pinhole intrinsics with plumb_bob distortion: the K, D and P a CameraInfo carries."""
from dataclasses import dataclass
from typing import Tuple

import numpy as np

from multicam_ego_motion.errors import UserError


@dataclass(frozen=True)
class CameraIntrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: Tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)   # plumb_bob k1 k2 p1 p2 k3
    tx: float = 0.0   # P[0,3] = -fx * baseline for the second camera of a rectified pair

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def P(self) -> np.ndarray:
        P = np.zeros((3, 4))
        P[:, :3] = self.K
        P[0, 3] = self.tx
        return P

    @property
    def D(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=float)

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(self.D != 0.0))

    @staticmethod
    def default(width: int = 640, height: int = 480, k1: float = 0.0) -> 'CameraIntrinsics':
        """fx = fy = 400 at 640 px wide (77 x 62 degree field of view), scaled with width."""
        if width < 16 or height < 16:
            raise UserError(f'image size {width}x{height} is too small (at least 16x16)')
        f = 400.0 * width / 640.0
        return CameraIntrinsics(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0,
                                (float(k1), 0.0, 0.0, 0.0, 0.0))
