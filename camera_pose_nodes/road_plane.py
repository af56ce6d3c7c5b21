"""Road points between two frames: the tracks that move as the plane under the camera does.

Why: a car moves a metre and more between frames, so a road point is seen in few frames and
the fused poses, which give triangulation its scale, do not move at all until something
metric measures them (no wheel, no stereo). The road itself is metric: the camera's height
above it is known (the rig's floor_z), so a road point is fixed by its ray from one view.
Which tracks are on the road is what this module decides, from the tracks' motion between
the previous frame and this one: points on one plane move by one homography,
H = R + t n^T / h (camera 0 -> 1, n the plane's normal in camera 0, h its distance), points
above it (cars, kerbs, walls) do not. OpenCV's RANSAC homography finds them, its
decomposition gives the plane's normal and the step t / h: a solution whose normal agrees
with the floor the rig knows, and whose step is long enough for height differences to show,
makes its inliers road points. The quarter places them on the floor from the previous frame's
fused pose (ground_plane.floor_points), and its EKF measures this frame against them: a
metric step from one pair of frames, whatever moved the fused poses before.
"""
import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from camera_pose_nodes.two_view import two_view

MIN_POINTS = 8                    # a homography from fewer is not worth trusting
NORMAL_AGREEMENT_COS = np.cos(np.radians(12.0))   # decomposed normal against the rig's floor
ROAD_MIN_DEPRESSION_RAD = np.radians(3.0)   # tracks nearer the horizon meet the road too far
ROAD_AHEAD_M = 20.0          # the road region: where the floor is nearer than this ...
ROAD_HALF_WIDTH_M = 3.0      # ... and within this of the camera sideways (the lane)
# road_scale: each track weighed by (1 / its depth)^DEPTH_WEIGHT_POWER, after those whose
# ratio is more than e^GROSS_LOG_RATIO off the plain median are dropped (see there)
DEPTH_WEIGHT_POWER = 3.0
GROSS_LOG_RATIO = 1.0


def camera_over_road(up_body: np.ndarray, R_base_cam: np.ndarray, centre: np.ndarray, floor_z: float):
    """(down_c, height_m): the road's normal pointing down in a camera's frame and the
    camera's height above the road, for the road through the body's (0, 0, floor_z) with
    normal up_body (body frame; the camera's axes R_base_cam and centre in the body)."""
    down_c = R_base_cam.T @ -up_body
    return down_c, float(up_body @ (centre - np.array([0.0, 0.0, floor_z])))


def road_region(xy: np.ndarray, down_c: np.ndarray, R_base_cam: np.ndarray, height: float) -> np.ndarray:
    """Which normalised points (N, 2) look at the road ahead: their ray meets the rig's floor
    within ROAD_AHEAD_M and ROAD_HALF_WIDTH_M sideways. Why a region: the lower half of a
    street image holds parked cars and house fronts, planes of their own, and a homography
    fit to all of it found those (KITTI 07: steps half their length); the lane ahead is road."""
    rays = np.column_stack([xy, np.ones(len(xy))])
    s = rays @ down_c / np.linalg.norm(rays, axis=1)
    ok = s >= np.sin(ROAD_MIN_DEPRESSION_RAD)
    lam = np.where(ok, height / np.where(ok, rays @ down_c, 1.0), 0.0)
    X_body = (rays * lam[:, None]) @ R_base_cam.T          # from the camera, in base_link axes
    return ok & (X_body[:, 0] <= ROAD_AHEAD_M) & (np.abs(X_body[:, 1]) <= ROAD_HALF_WIDTH_M)


@dataclass
class RoadFit:
    inliers: np.ndarray        # (N,) bool: the tracks that move as the road does
    R: np.ndarray              # (3, 3) camera 0 -> 1 rotation: X1 = R X0 + t
    step_m: np.ndarray         # (3,) t (m), the translation in camera 1's frame
    normal: np.ndarray         # (3,) the plane's normal in camera 0 (towards the road)


def fit_road(xy0: np.ndarray, xy1: np.ndarray, down_c: np.ndarray, height_m: float,
             threshold: float, min_step_m: float, min_points: int = MIN_POINTS) -> Optional[RoadFit]:
    """xy0, xy1 (N, 2): normalised undistorted points of the same tracks in frames 0 and 1;
    down_c (3,): the floor's normal in camera 0 pointing down (towards the floor); height_m:
    the camera's height above it; threshold: RANSAC reprojection error (normalised units);
    min_step_m: shorter steps are not used (their plane parallax is within the noise).
    Returns None when no plane fit agrees with the floor."""
    if len(xy0) < min_points:
        return None
    H, mask = cv2.findHomography(xy0.astype(np.float64), xy1.astype(np.float64), cv2.RANSAC,
                                 ransacReprojThreshold=float(threshold), maxIters=500,
                                 confidence=0.995)
    if H is None or mask is None:
        return None
    inliers = mask.ravel().astype(bool)
    if inliers.sum() < min_points:
        return None
    n_sol, Rs, ts, ns = cv2.decomposeHomographyMat(H, np.eye(3))
    best, best_cos = None, NORMAL_AGREEMENT_COS
    for R, t, n in zip(Rs, ts, ns):
        c = float(n.ravel() @ down_c)
        if c > best_cos:
            best, best_cos = (R, t.ravel(), n.ravel()), c
    if best is None:
        return None
    R, t, n = best
    step = t * height_m
    if not np.all(np.isfinite(step)) or np.linalg.norm(step) < min_step_m:
        return None
    return RoadFit(inliers, R, step, n)


def camera_step(fit: RoadFit) -> np.ndarray:
    """Camera 1's centre in camera 0's frame (m)."""
    return -fit.R.T @ fit.step_m


@dataclass
class RoadScale:
    factor: float              # k: the metric step is k times the given one
    relative_std: float        # of k, from the points' scatter
    n_points: int


def road_scale(xy0: np.ndarray, xy1: np.ndarray, R: np.ndarray, t: np.ndarray, down_c: np.ndarray,
               height_m: float, min_points: int = MIN_POINTS) -> Optional[RoadScale]:
    """The factor k that makes a known motion's step metric, from road points: each track
    triangulated with the motion (X1 = R X0 + t, camera 0 -> 1) gives a depth proportional to
    |t|; its ray meets the road (normal down_c in camera 0, height_m below) at a metric depth;
    k is the median of their ratios, each weighted by (1 / its depth)^3, of the tracks within
    a factor e of the plain median. Why weighted: a camera pitch error d moves a road point's
    depth by about d Z / h (Z its depth, h the camera's height), and its flow, which
    triangulation divides by, falls as 1 / Z^2: on KITTI 07 the ratios at 13-25 m often read
    20-40 % (up to 2x) above those at 6-10 m, which agree with the truth (docs/fusion.md). Why
    the gross tracks out first: the weights trust the near lane, where a car ahead at nearly
    the rig's speed (kitti_seq1) has points that barely move and read k ~ 0.01-0.3. A hard cut
    at 14 m did as well on KITTI 07 but starved the narrow views of image halves.
    Why not the homography (fit_road): with the rotation and
    the direction of travel known, one unknown is left, where a homography fits eight to the
    10-30 road tracks a frame at car speed has; its steps scattered 0.84-1.19 of the truth
    (interquartile, KITTI 07), these 0.94-1.06. The road's normal must be the one the car
    drives on (road_pitch): 1 deg of camera pitch moves k by 5-10 %.
    None with fewer than min_points usable tracks, or when none is near the plain median."""
    r0 = np.column_stack([xy0, np.ones(len(xy0))])
    a = r0 @ R.T
    # x1 (d a_z + t_z) = d a_xy + t_xy  ->  d (x1 a_z - a_xy) = t_xy - x1 t_z, per track
    c = xy1 * a[:, 2:3] - a[:, :2]
    e = t[None, :2] - xy1 * t[2]
    cc = (c * c).sum(axis=1)
    depth = (c * e).sum(axis=1) / np.maximum(cc, 1e-12)
    toward_road = r0 @ down_c
    ok = (depth > 0.0) & (toward_road > 1e-3) & (cc > 1e-12)
    if ok.sum() < min_points:
        return None
    log_k = np.log(height_m / toward_road[ok]) - np.log(depth[ok])
    weight = toward_road[ok] ** DEPTH_WEIGHT_POWER      # toward_road = h / Z
    sane = np.abs(log_k - np.median(log_k)) <= GROSS_LOG_RATIO
    if not sane.any():
        # an even count split in two groups further apart than that: the plain median lies
        # between them and no track agrees with it (a car ahead as large as the road seen)
        return None
    log_k, weight = log_k[sane], weight[sane]
    med = _weighted_median(log_k, weight)
    mad = 1.4826 * float(np.median(np.abs(log_k - med)))
    k = math.exp(med)
    if not np.isfinite(k):
        return None
    return RoadScale(k, 1.25 * mad / math.sqrt(len(log_k)), len(log_k))


@dataclass
class RoadStep:
    R: np.ndarray              # (3, 3) camera 0 -> 1 rotation: X1 = R X0 + t
    centre_m: np.ndarray       # (3,) camera 1's centre in camera 0's frame (m)
    scale: RoadScale           # the length's factor and the lane tracks behind it


def road_step(xy0: np.ndarray, xy1: np.ndarray, down_c: np.ndarray, height_m: float,
              R_base_cam: np.ndarray, threshold: float, min_points: int,
              min_parallax_deg: float) -> Optional[RoadStep]:
    """A camera's metric motion between two frames from its tracks alone: the rotation and
    the direction of travel from the essential matrix of all of them (two_view, which needs
    min_points inliers and min_parallax_deg of median parallax), the length from those in
    the lane ahead (road_region) by road_scale. Why: with no motion known (a road rig's first
    frame pair) this is where the quarter's update is linearized (quarter_estimator,
    road_first_step). None when either part is not measured."""
    tv = two_view(xy0, xy1, threshold, min_points, min_parallax_deg)
    if tv is None:
        return None
    lane = tv.inliers & road_region(xy0, down_c, R_base_cam, height_m)
    rs = road_scale(xy0[lane], xy1[lane], tv.R, tv.t, down_c, height_m)
    if rs is None:
        return None
    return RoadStep(tv.R, -tv.R.T @ tv.t * rs.factor, rs)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value at which the weights of the sorted values first reach half their sum."""
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])
