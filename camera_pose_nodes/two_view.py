"""Two-view initialisation of a quarter that has no metric source (ROS-free).

Without a wheel, a floor or a stereo pair nothing moves the fused poses at the start, so no
track gets the parallax to be triangulated and the graph would wait forever. A quarter then
measures its camera's motion itself from its tracks: the essential matrix between a common
earlier view and the current one (OpenCV findEssentialMat, RANSAC; recoverPose) gives the
rotation and the direction of travel, never its length. The length is the gauge shared by
every camera: `nominal_speed` times the time between the two views (docs/estimator.md, start
without a scale source); the general arbiter later measures the true scale (scale_state) and
rescales the whole map.
"""
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np


@dataclass
class TwoViewResult:
    R: np.ndarray          # camera rotation: x2 = R x1 + t (points from view 1 to view 2 frame)
    t: np.ndarray          # unit translation of the same convention
    inliers: np.ndarray    # (N,) bool
    parallax_deg: float    # median rotation-compensated ray angle of the inliers


def rotation_compensated_parallax(xy1: np.ndarray, xy2: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Angle (deg) between each view-2 ray and its view-1 ray rotated into view 2."""
    b1 = np.column_stack([xy1, np.ones(len(xy1))]) @ R.T
    b2 = np.column_stack([xy2, np.ones(len(xy2))])
    c = np.sum(b1 * b2, axis=1) / (np.linalg.norm(b1, axis=1) * np.linalg.norm(b2, axis=1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def two_view(xy1: np.ndarray, xy2: np.ndarray, threshold: float, min_points: int,
             min_parallax_deg: float) -> Optional[TwoViewResult]:
    """Relative camera motion from normalized, undistorted correspondences (N, 2) of two
    views. threshold: RANSAC inlier distance in normalized units (pixel sigma / focal).
    None when there are too few points or inliers, or too little parallax: with no
    translation seen, the essential matrix's direction is noise."""
    xy1 = np.asarray(xy1, np.float64).reshape(-1, 2)
    xy2 = np.asarray(xy2, np.float64).reshape(-1, 2)
    if len(xy1) < max(int(min_points), 5):
        return None
    # A cheap gate first: rotation alone moves points too, but without any flow there is
    # nothing to measure (and RANSAC on identical points is degenerate).
    if np.median(np.linalg.norm(xy2 - xy1, axis=1)) < np.radians(0.1 * min_parallax_deg):
        return None
    E, mask = cv2.findEssentialMat(xy1, xy2, focal=1.0, pp=(0.0, 0.0), method=cv2.RANSAC,
                                   prob=0.999, threshold=float(threshold))
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    n, R, t, mask2 = cv2.recoverPose(E, xy1, xy2, focal=1.0, pp=(0.0, 0.0), mask=mask.copy())
    inl = mask2.ravel() > 0
    if int(n) < min_points or inl.sum() < min_points:
        return None
    par = float(np.median(rotation_compensated_parallax(xy1[inl], xy2[inl], R)))
    if par < min_parallax_deg:
        return None
    t = t.ravel() / max(np.linalg.norm(t), 1e-12)
    return TwoViewResult(R, t, inl, par)


def body_pose_from_two_view(T_odom_base_1: np.ndarray, T_base_cam: np.ndarray,
                            result: TwoViewResult, length: float) -> np.ndarray:
    """Body pose at view 2 (base_link in odom), the camera centre having moved `length`
    (the gauge) along the measured direction from its place at view 1."""
    T_oc1 = T_odom_base_1 @ T_base_cam
    # x2 = R x1 + t: camera 2 in camera 1 is (R^T, -R^T t)
    T_c1c2 = np.eye(4)
    T_c1c2[:3, :3] = result.R.T
    T_c1c2[:3, 3] = -result.R.T @ result.t * float(length)
    T_oc2 = T_oc1 @ T_c1c2
    return T_oc2 @ np.linalg.inv(T_base_cam)
