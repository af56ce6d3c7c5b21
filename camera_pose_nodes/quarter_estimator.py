"""The quarter node's core (paper T_kl): acquire, extract, track, pose, structure.

ROS-free: the node converts messages (image_conversion), builds the intrinsics
(camera_model) and calls process_image() per frame and apply_fused_pose() when the general
arbiter's fused pose of that frame comes back. get_state()/set_state() hand the quarter
over to another process (the coordinator's rebalancing) with bit-identical continuation.

Pose: tracks with a landmark are measured by reprojection; tracks without one (too young to
be triangulated, e.g. in fast turns) by their epipolar line to an earlier fused view, which
fixes rotation but not distance (see docs/estimator.md).
"""
import math
import time
from dataclasses import field, fields, make_dataclass, replace
from functools import lru_cache
from typing import Dict, Optional

import cv2
import numpy as np

from camera_pose_nodes.camera_model import CameraIntrinsics
from camera_pose_nodes.ground_plane import FLOOR_TILT_SIGMA_RAD, floor_plane, floor_points, snap_to_floor
from camera_pose_nodes.klt_tracker import KLTConfig, KLTTracker, margin_for
from camera_pose_nodes.landmark_map import LandmarkMap, bearings_odom, angle_deg
from camera_pose_nodes.pose_ekf import PoseEKF
from camera_pose_nodes.pose_estimate import PoseEstimate, UNINFORMATIVE_VARIANCE, uninformative
from camera_pose_nodes.quarter_region import QuarterRegion
from camera_pose_nodes.stereo_match import StereoConfig, StereoPair, relative_pose
from camera_pose_nodes import flow_prediction, map_scale, road_plane
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import CameraMount
from multicam_ego_motion.geometry.se3 import R_to_rotvec, rotvec_to_R

# Fused poses come back at the stamps a quarter tracked, within a feedback timeout or so.
OWN_STAMPS_KEPT = 32
ROAD_NORMALS_KEPT = 64       # road normals waiting for a fused pose (one a frame)

STATE_VERSION = 12    # 12: road normal; 11: new bearings; 10: motion with translation; 2: landmark covariances; 3: floor flags; 4: extract_ms; 5: arrays; 6: motion; 7: stereo partner; 8: map scale; 9: own stamps
STAGES = ('acquire', 'extract', 'track', 'pose', 'structure')
_ROTATION_ONLY_POSITION_VARIANCE = 1.0e2   # m^2: 'position not measured', still < UNINFORMATIVE
_TRIANGULATION_VIEWS = 5     # views per DLT: oldest, newest and evenly spaced between
_PREDICT_MAX_RATE_STD = 0.5  # rad/s: a less certain angular rate does not steer the tracker
_PREDICT_MAX_DT_S = 1.0      # nor does one from longer ago
_PREDICT_MIN_SPEED_STD = 0.5          # m/s: a velocity this certain steers the tracker ...
_PREDICT_MAX_SPEED_REL_STD = 0.5      # ... or one known to half its speed


@lru_cache(maxsize=None)
def _view_tables(max_views: int):
    """For a track with m fused views (row m, up to max_views): which of them go into the DLT
    (oldest, newest and evenly spaced between), and 1 for each listed first, 0 for a repeat
    (short tracks repeat views). Tables, so that all tracks are looked up at once."""
    idx = np.zeros((max_views + 1, _TRIANGULATION_VIEWS), np.int64)
    distinct = np.zeros((max_views + 1, _TRIANGULATION_VIEWS))
    for m in range(1, max_views + 1):
        js = np.linspace(0, m - 1, _TRIANGULATION_VIEWS).round().astype(int)
        idx[m] = js
        distinct[m] = [1.0 if v == 0 or js[v] != js[v - 1] else 0.0 for v in range(len(js))]
    return idx, distinct


def feature_scale(image_size, scale_max: float) -> float:
    """How many times min_features and max_features a quarter of this image keeps: the square
    root of its area against a 160x120 quarter's, between 1 and scale_max. Why: the counts
    were set on 320x240 images; a real camera's quarter (KITTI: 613x185) spread 80 corners
    over six times the area, its road got a handful, and at car speed the few road points
    that survived a frame could not say which of them lay on the road (road_plane). Twice
    the features: ATE + final drift over 14 KITTI cases and variants 733 -> 428 %."""
    w, h = image_size
    return float(np.clip(math.sqrt((w / 2) * (h / 2) / (160.0 * 120.0)), 1.0, scale_max))


def road_normal_of(up_base, source: str) -> np.ndarray:
    """A road normal given in base_link as a unit vector; UserError naming it when it is not a
    road's (not finite, not unit, or more than 60 degrees from base_link's z)."""
    up = np.asarray(up_base, float).reshape(3)
    n = float(np.linalg.norm(up))
    if not (np.all(np.isfinite(up)) and abs(n - 1.0) < 1e-3 and up[2] > 0.5):
        raise UserError(f'{source}: road normal {up.tolist()} is not a unit vector within 60 deg of base_link z')
    return up / n


def _members(a: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """np.isin(a, sorted_set) for a sorted set, by binary search (isin sorts both)."""
    if not len(sorted_set):
        return np.zeros(a.shape, bool)
    i = np.minimum(np.searchsorted(sorted_set, a), len(sorted_set) - 1)
    return sorted_set[i] == a


# A track's status in the debug image (track_overlay, track_image): what it measures.
TRACK_NEW = 0        # no landmark and no earlier view with a fused pose: measures nothing yet
TRACK_EPIPOLAR = 1   # no landmark, an earlier fused view: its epipolar line (rotation only)
TRACK_LANDMARK = 2   # a triangulated landmark: reprojection
TRACK_FLOOR = 3      # a landmark placed on the floor (ground_plane): reprojection, metric depth


# name -> (default, description, min, max). The node declares its ROS parameters from this.
PARAMETERS = {
    'min_features': (40, "extract new features when fewer are tracked (paper's Min)", 4, 1000),
    'max_features': (80, 'extraction tops the quarter up to this many features', 8, 4000),
    'road_feature_scale_max': (2.0, 'min_features and max_features are for a 160x120 quarter (a 320x240 image); on a road (road_landmarks), a larger quarter gets more, by the square root of its area, up to this factor (1: never more)', 1.0, 10.0),
    'klt_window': (21, 'Lucas-Kanade window size in pixels (odd)', 5, 63),
    'pyramid_levels': (3, 'Lucas-Kanade pyramid levels above the full-resolution image', 0, 6),
    'klt_iterations': (30, 'Lucas-Kanade iterations per pyramid level, at most', 1, 100),
    'klt_epsilon_px': (0.01, 'Lucas-Kanade stops iterating when a step moves the point less than this (px)', 1e-4, 1.0),
    'fb_threshold_px': (0.5, 'forward-backward tracking error that rejects a track (px)', 0.05, 10.0),
    'floor_warp_min_flow_px': (15.0, "on a road (road_landmarks), a track on the floor that Lucas-Kanade loses and whose floor homography moves it farther than this is searched again on the previous image warped by that homography (rectified images; 0: never)", 0.0, 1000.0),
    'road_lane_features': (20, "on a road (road_landmarks), keep at least this many tracks in the lane ahead (road_plane.road_region: the level floor within 20 m ahead and 3 m sideways), extracted there whenever fewer, however many the quarter has, with their quality relative to the lane's best corner: plain asphalt beside a car's edges has no corner within quality_level of theirs, and the road's scale needs tracks on the road at every frame pair (0: only as the rest of the quarter)", 0, 1000),
    'quality_level': (0.01, 'Shi-Tomasi corner quality relative to the best in its cell', 1e-4, 0.5),
    'min_distance_px': (8.0, 'minimum distance between features (px)', 1.0, 100.0),
    'block_size': (5, 'Shi-Tomasi gradient averaging block (px)', 3, 15),
    'grid_rows': (2, 'extraction cells per quarter, rows (spreads features)', 1, 8),
    'grid_cols': (2, 'extraction cells per quarter, columns', 1, 8),
    'parallel_chunks': (False, 'split extraction/tracking into ~min_features chunks on threads', None, None),
    'max_history': (60, 'observations kept per track for triangulation (oldest always kept)', 2, 10000),
    'pixel_sigma': (1.0, 'feature measurement noise (px, 1 sigma)', 0.05, 20.0),
    'landmark_covariance': (True, "add each landmark's triangulation covariance to its reprojection noise (landmarks are not exact: see landmark_map)", None, None),
    'gate_chi2': (9.21, 'per-feature Mahalanobis gate (chi-square, 2 dof; 9.21 = 99 %)', 1.0, 100.0),
    'accel_sigma': (2.0, 'process noise: white linear acceleration (m/s^2/sqrt(Hz))', 1e-4, 100.0),
    'alpha_sigma': (2.0, 'process noise: white angular acceleration (rad/s^2/sqrt(Hz))', 1e-4, 100.0),
    'predict_flow': (True, "start each feature's Lucas-Kanade search where the camera's rotation (this quarter's angular rate) moves it, not at zero flow", None, None),
    'gyro_steer': (True, "with the rig's IMU in use (the quarter node's and the general arbiter's use_imu): each frame's search starts, and the filter's predicted rotation is, where the gyro turned the camera since the last frame (gyro_steer), not where the last rate held constant puts it: spinning up at 8 Hz that lagged by degrees a frame and every camera lost its tracks for 3 s", None, None),
    'predict_translation_min_speed': (3.0, "from this speed (m/s) on, each feature's search also starts moved by the camera's translation since the last estimate, at its landmark's depth or where its ray meets the floor (flow_prediction): at car speed near points move 100 px a frame", 0.0, 1000.0),
    'epipolar': (True, 'also measure tracks without a landmark by their epipolar line to an earlier fused view', None, None),
    'epipolar_min_baseline': (0.05, 'shortest camera baseline (m) for an epipolar measurement', 0.001, 10.0),
    'min_inliers': (6, 'inliers needed to report tracking (else lost)', 3, 1000),
    'parallax_deg': (2.0, 'ray angle a track needs before it is triangulated (deg)', 0.1, 45.0),
    'refine_factor': (2.0, 're-triangulate a landmark when its parallax grew by this factor', 1.1, 100.0),
    'max_reproj_px': (2.0, 'landmarks reprojecting worse than this are rejected/dropped (px)', 0.1, 50.0),
    'min_depth': (0.1, 'nearest accepted landmark depth (m)', 0.001, 10.0),
    'max_depth': (200.0, 'farthest accepted landmark depth (m)', 1.0, 1e5),
    'ground_plane': (True, 'put landmarks that lie on the floor onto it: their depth is then metric from the camera height (see ground_plane; needs the rig\'s floor_z)', None, None),
    'road_landmarks': (True, "on a road (the rig's floor_level false, no stereo pair), every frame, tracks that moved since the previous frame as the floor does (a plane homography whose normal and height agree with the rig's floor: road_plane) are placed on the floor from the previous fused pose: metric steps at car speed without a wheel or stereo (needs ground_plane)", None, None),
    'road_tilt_std_deg': (1.0, "on a road (road_landmarks), the body's tilt to the road (1 sigma, deg) in the depth of every point put on it (ground_plane.floor_points: relative std tilt / sin(depression)); a car pitches 1-2 deg to its road when it brakes and a camera's mount to the road is known to about a degree, so the near road carries the scale and the far road (17 % at 15 m under a camera 1.65 m up) little: with ground_plane's indoor 0.2 deg the far points held the map 5-10 % long against the general arbiter's road scale (docs/estimator.md)", 0.01, 10.0),
    'road_normal': (True, "on a road (road_landmarks), its points are put on the road the general arbiter's road scale stands on (its normal from the direction of travel, road_pitch; add_road_normal), not on the plane square to the body's z axis: a camera is a degree or so pitched to its road (KITTI's: about 1 deg down), which put the road's far points 5-20 % too far, every step read that much long and the road scale cut the maps back 2 % every few frames (docs/estimator.md)", None, None),
    'road_first_step': (True, "on a road (road_landmarks), the first frame pair since the floor was seeded: the EKF's update is linearized at the step the quarter's tracks measure (rotation and direction from the essential matrix, when their median parallax reaches two_view_parallax_deg; the length from the lane's tracks on the road: road_plane.road_step), not at rest: a car moves a metre between those frames, and kitti_seq1's lower quarters read its first 1.2 m step as 1.3 to 2.2 m (docs/estimator.md)", None, None),
    'road_min_step': (0.1, 'shortest camera step (m) between two frames at which road_landmarks looks for the floor (shorter: points above it move alike)', 0.001, 10.0),
    'ground_tolerance': (0.3, 'a floor landmark\'s depth is never farther than this fraction from its ray\'s floor intersection', 0.001, 1.0),
    'two_view_init': (True, 'without landmarks, floor or any motion of the fused poses, initialise from two-view geometry on the tracks (essential matrix): rotation and direction of travel, the length from two_view_nominal_speed (see two_view)', None, None),
    'two_view_min_points': (12, 'RANSAC inliers a two-view initialisation needs', 5, 1000),
    'two_view_parallax_deg': (1.0, 'median rotation-compensated ray angle a two-view initialisation needs (deg)', 0.05, 45.0),
    'two_view_nominal_speed': (1.0, 'the gauge of a map without a scale source: the camera moved this fast between the two views (m/s); the general arbiter rescales once a source measures the scale', 1e-3, 100.0),
    'ground_map_scale_std': (0.03, 'relative scale uncertainty of the fused poses, allowed for when judging a landmark on the floor', 0.0, 1.0),
    'stereo': (True, "with a camera whose view overlaps this one (rig stereo_pairs): match the tracks without a landmark into its image of the same stamp and triangulate them from the baseline, metric from one frame (stereo_match); no partner: no effect", None, None),
    'stereo_pyramid_levels': (4, 'Lucas-Kanade pyramid levels of the search into the partner image (disparities up to ~10 x 2^levels px)', 0, 6),
    'stereo_fb_px': (1.0, 'forward-backward error that rejects a stereo match (px)', 0.05, 10.0),
    'stereo_epipolar_px': (1.5, "a stereo match farther than this from its epipolar line (the rig's extrinsics) is rejected (px)", 0.05, 20.0),
    'stereo_pixel_sigma': (1.0, "stereo matching noise (px, 1 sigma): the disparity noise in the stereo landmarks' covariance", 0.05, 10.0),
    'stereo_max_range': (160.0, 'farthest stereo landmark, in baselines: its disparity is f/range px (KITTI, f 707 px: 4.4 px at 160, against stereo_pixel_sigma 1 px; the landmark\'s covariance carries its depth noise, and at car speed far points are the ones that stay in view for several frames)', 2.0, 10000.0),
    'stereo_prior_depth': (20.0, "where the search into the partner image starts, in baselines, while the quarter has no landmarks of its own (then: their median depth)", 1.0, 10000.0),
}


class _QuarterParamsChecks:
    """Checks of QuarterParams (the fields come from PARAMETERS, the one table)."""

    def validate(self) -> 'QuarterParams':
        for f in fields(self):
            v = getattr(self, f.name)
            _, _, lo, hi = PARAMETERS[f.name]
            if lo is None:
                continue
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) \
                    or not lo <= v <= hi:
                raise UserError(f'parameter {f.name} = {v!r} is outside [{lo}, {hi}]')
        if self.max_features < self.min_features:
            raise UserError(f'max_features ({self.max_features}) must be >= min_features '
                            f'({self.min_features})')
        if self.klt_window % 2 == 0:
            raise UserError(f'klt_window must be odd, got {self.klt_window}')
        return self

    def as_dict(self) -> dict:
        # Every field is a scalar: a flat copy is dataclasses.asdict's result without its
        # recursive deep copy (~0.2 ms, at every state snapshot).
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> 'QuarterParams':
        unknown = set(d) - set(PARAMETERS)
        if unknown:
            raise UserError(f'unknown quarter parameter(s): {", ".join(sorted(unknown))}')
        return cls(**d).validate()


# The quarter's parameters as a dataclass generated from PARAMETERS: one table says each
# parameter's name, default, description and range, for the node, the params file and the
# ROS-free callers alike.
QuarterParams = make_dataclass(
    'QuarterParams', [(name, type(default), field(default=default))
                      for name, (default, _, _, _) in PARAMETERS.items()],
    bases=(_QuarterParamsChecks,))
QuarterParams.__module__ = __name__


class QuarterEstimator:
    def __init__(self, camera: CameraMount, quarter: int, intrinsics: CameraIntrinsics,
                 params: Optional[QuarterParams] = None, image_size=None,
                 floor_z: Optional[float] = None, road: bool = False):
        """floor_z: the rig's floor in base_link (Rig.floor_z); None disables floor landmarks.
        road: the floor is a road, flat only locally, and the rig has no stereo pair
        (Rig.road_scale): road_landmarks runs there. Why not on a level indoor floor: at
        walking speed the steps between two frames (0.1 to 0.2 m) cannot tell the floor from
        points a few cm above it, and triangulation with the floor check (snap_to_floor) has
        the time to: the accuracy matrix's mean final drift went from 0.32 to 0.43 % with
        road_landmarks there."""
        self.camera = camera
        self.floor_z = floor_z
        self.quarter = int(quarter)
        self.intrinsics = intrinsics
        self.params = (params or QuarterParams()).validate()
        self.uses_floor = self.params.ground_plane and floor_z is not None
        self.uses_road = self.uses_floor and road and self.params.road_landmarks
        # the body's tilt to its floor, in the depth of a point put on it (ground_plane)
        self.floor_tilt_rad = (math.radians(self.params.road_tilt_std_deg) if self.uses_road
                               else FLOOR_TILT_SIGMA_RAD)
        w, h = image_size if image_size is not None else (intrinsics.width, intrinsics.height)
        self.image_size = (int(w), int(h))
        p = self.params
        scale = feature_scale(self.image_size, p.road_feature_scale_max) if self.uses_road else 1.0
        self.klt_cfg = KLTConfig(
            min_features=int(round(p.min_features * scale)), max_features=int(round(p.max_features * scale)),
            window=p.klt_window,
            pyramid_levels=p.pyramid_levels, iterations=p.klt_iterations,
            epsilon_px=p.klt_epsilon_px, fb_threshold_px=p.fb_threshold_px,
            quality_level=p.quality_level, min_distance_px=p.min_distance_px,
            block_size=p.block_size, grid_rows=p.grid_rows, grid_cols=p.grid_cols,
            max_history=p.max_history, parallel_chunks=p.parallel_chunks,
            floor_warp_min_flow_px=p.floor_warp_min_flow_px)
        self.region = QuarterRegion.of(self.quarter, *self.image_size, margin_for(self.klt_cfg))
        self.source = f'{camera.name}/q{self.quarter}'
        self.T_base_cam = camera.T_base_cam
        self.tracker = KLTTracker(self.region, self.klt_cfg)
        self.ekf = PoseEKF(p.accel_sigma, p.alpha_sigma)
        self.landmarks = LandmarkMap(p.parallax_deg, p.max_reproj_px, p.min_depth, p.max_depth,
                                     p.refine_factor, focal_px=0.5 * (intrinsics.fx + intrinsics.fy),
                                     pixel_sigma=p.pixel_sigma)
        self.sigma_uv = (p.pixel_sigma / intrinsics.fx, p.pixel_sigma / intrinsics.fy)
        self.stereo = None          # StereoPair with the partner camera (set_partner)
        self.partner = None         # (CameraMount, CameraIntrinsics) of that camera
        self.reset()

    def set_partner(self, partner: CameraMount, intrinsics: CameraIntrinsics):
        """The camera whose view overlaps this one (a stereo pair, Rig.stereo_pairs) and its
        intrinsics: from then on apply_fused_pose takes its image of the same stamp."""
        if not self.params.stereo:
            return
        self.partner = (partner, intrinsics)
        p = self.params
        baseline = float(np.linalg.norm(relative_pose(self.T_base_cam, partner.T_base_cam)[1]))
        cfg = StereoConfig(window=p.klt_window, pyramid_levels=p.stereo_pyramid_levels,
                           iterations=p.klt_iterations, epsilon_px=p.klt_epsilon_px,
                           fb_px=p.stereo_fb_px, epipolar_px=p.stereo_epipolar_px,
                           pixel_sigma=p.stereo_pixel_sigma, min_depth=p.min_depth,
                           max_depth=min(p.max_depth, p.stereo_max_range * baseline))
        self.stereo = StereoPair(self.T_base_cam, partner.T_base_cam, self.intrinsics, intrinsics, cfg)
        self.partner_size = (intrinsics.width, intrinsics.height)

    @property
    def wants_partner_image(self) -> bool:
        return self.stereo is not None

    def reset(self):
        self.tracker.reset()
        self.ekf.reset()
        self.landmarks.reset()
        self.fused_poses: Dict[int, np.ndarray] = {}
        self._fused_cache = None
        self.structure_ms = 0.0
        self.extract_ms = 0.0
        self._prefetched = None    # (stamp, tracked-from crop, crop, flow, stage ms) of the next frame
        # (stamp, body angular rate) of the last estimate: steers the next frame's tracking.
        # Kept as it was then, so a flow computed early (prefetch) or late is the same.
        self._motion = None
        # The rig's gyro (gyro_steer.GyroSteer), set by the host with an IMU: the search's
        # start and the filter's predicted rotation follow it over each frame step.
        self.gyro = None
        self._extract_due = None   # stamp whose new features are still to be extracted
        self._cells_due = False    # ... in the grid's cells (too few tracks in the quarter)
        self._lane_want = 0        # ... this many in the lane ahead (road_lane_features)
        self._lane_cache = None    # (mask, box) of the lane ahead in this quarter (_lane)
        self._new_bearings = None  # (stamp, ids, xy, sigma) of features extracted, not yet taken
        self.own_stamps = []       # the last OWN_STAMPS_KEPT stamps this quarter tracked
        self.scale_epoch = 0         # map rescales applied (map_scale)
        self._two_view_ref = None    # stamp of the view a two-view initialisation started from
        self._scale_pending = []     # map-scale commands waiting for their frame
        self._road_pending = []      # (stamp, road normal in base_link) not yet in use
        self.road_up = None          # the road's normal in use (base_link); None: the body's z

    def add_road_normal(self, stamp_ns: int, up_base) -> None:
        """The general arbiter's road normal at its frame stamp_ns (base_link, unit; road_normal):
        used from the next frame's fused pose on (apply_fused_pose takes the newest one older
        than its own stamp), so a lockstep replay does not depend on which message came first."""
        up = road_normal_of(up_base, self.source)
        if self.uses_road and self.params.road_normal:
            self._road_pending.append((int(stamp_ns), up))
            self._road_pending.sort(key=lambda sv: sv[0])
            del self._road_pending[:-ROAD_NORMALS_KEPT]

    def takes_feedback(self, stamp_ns: int) -> bool:
        """Whether a fused pose at `stamp_ns` is this quarter's: one of its own frames (or
        any, before the first). Free-running cameras: the general arbiter feeds the fused pose
        back at every camera's stamp; another camera's carries nothing to triangulate here."""
        return not self.own_stamps or int(stamp_ns) in self.own_stamps

    def close(self):
        self.tracker.close()

    # ----- per frame ---------------------------------------------------------------------
    def _crop(self, gray) -> np.ndarray:
        gray = np.asarray(gray)
        if gray.dtype != np.uint8 or gray.ndim != 2:
            raise UserError(f'{self.source}: expected a gray uint8 image, got {gray.dtype} '
                            f'with shape {gray.shape}')
        if (gray.shape[1], gray.shape[0]) != self.image_size:
            raise UserError(f'{self.source}: image is {gray.shape[1]}x{gray.shape[0]}, '
                            f'expected {self.image_size[0]}x{self.image_size[1]} (CameraInfo)')
        return np.ascontiguousarray(self.region.crop(gray))

    def prefetch(self, stamp_ns: int, gray: np.ndarray):
        """Crop the next frame and compute its optical flow now, while the fused pose of the
        last frame is still on its way (the flow does not depend on it): process_image of
        this stamp then starts from there. Results are the same as without (klt_tracker)."""
        self.extract_pending()     # the flow must cover the last frame's new features
        t0 = time.thread_time()
        crop = self._crop(gray)
        t1 = time.thread_time()
        flow = self.tracker.flow(crop, self._flow_predictor(stamp_ns), self._floor_warp(stamp_ns))
        self._prefetched = (int(stamp_ns), self.tracker.prev_crop, crop, flow,
                            {'acquire': (t1 - t0) * 1e3, 'track': (time.thread_time() - t1) * 1e3})

    def prefetched(self, stamp_ns: int) -> bool:
        """Whether process_image(stamp_ns, None) can start from a prefetch()."""
        pre = self._prefetched
        return pre is not None and pre[0] == stamp_ns and pre[1] is self.tracker.prev_crop

    def process_image(self, stamp_ns: int, gray: Optional[np.ndarray]) -> PoseEstimate:
        """`gray` may be None when prefetched(stamp_ns)."""
        self.extract_pending()
        # Stage times are CPU time of this thread, not wall time: they are the costs the
        # coordinator balances, and on a shared machine wall time mostly measured the
        # preemption by other processes (one camera's quarters read 20 to 380 ms per frame
        # for the same work). OpenCV runs single-threaded in the workers (worker.py), so its
        # work is on this thread; with `parallel_chunks` the helper threads are not counted.
        pre = self._prefetched if self.prefetched(stamp_ns) else None
        self._prefetched = None
        ms: Dict[str, float] = {'acquire': 0.0, 'track': 0.0}
        flow = None
        if pre is not None:
            _, _, crop, flow, ms = pre
        t0 = time.thread_time()
        if pre is None:
            if gray is None:
                raise ValueError(f'{self.source}: no image and none prefetched for {stamp_ns}')
            crop = self._crop(gray)
        t1 = time.thread_time()
        ms['acquire'] += (t1 - t0) * 1e3

        # (the rotation steers the search only when the flow is computed now)
        if flow is None:
            flow = self.tracker.flow(crop, self._flow_predictor(stamp_ns), self._floor_warp(stamp_ns))
        self.tracker.track(stamp_ns, crop, flow)
        self.own_stamps = self.own_stamps[-(OWN_STAMPS_KEPT - 1):] + [int(stamp_ns)]
        t2 = time.thread_time()
        ms['track'] += (t2 - t1) * 1e3

        # New features are extracted later (extract_pending): they have no landmark and no
        # earlier view, so they take no part in this frame's estimate, and a worker extracts
        # them once the estimate is out, in its idle time (latency).
        self._cells_due = self.tracker.needs_features()
        self._lane_want = self._lane_shortfall()
        if self._cells_due or self._lane_want:
            self._extract_due = int(stamp_ns)
        ms['extract'] = self.extract_ms     # ran after the previous estimate
        self.extract_ms = 0.0
        t3 = time.thread_time()

        stamp_before = self.ekf.stamp_ns
        # (the gyro's rotation over the step, where it is in use: the update is linearized
        # there, not at the last rate held constant)
        self.ekf.predict(stamp_ns, None if self.gyro is None or stamp_before is None
                         else self.gyro.rate(stamp_before, stamp_ns))
        if self.uses_road:
            if self.params.road_first_step and len(self.fused_poses) == 1:
                self._relinearize_first_road_step(stamp_ns)
            self._road_landmarks(stamp_ns)
        has, X = self.landmarks.lookup(self.tracker.ids)
        n_inliers = 0
        if len(X):
            xy = self.intrinsics.undistort_points(self.tracker.pts[has])
            if self.stereo is not None and stamp_before is not None:
                self._relinearize(X, xy, (stamp_ns - stamp_before) * 1e-9)
            X_cov = (self.landmarks.covariances_of(self.tracker.ids[has])
                     if self.params.landmark_covariance else None)
            inl = self.ekf.update(X, xy, self.sigma_uv, self.T_base_cam, self.params.gate_chi2,
                                  self.params.min_depth, X_cov)
            n_inliers = int(inl.sum())
        n_epipolar = self._epipolar_update(stamp_ns, ~has) if self.params.epipolar else 0
        n_two_view = 0
        if n_inliers < self.params.min_inliers and self._two_view_due():
            n_two_view = map_scale.two_view_init(self, stamp_ns)
        if not self.ekf.healthy():
            # Cannot happen by construction (guards in the EKF); if it does, restart the
            # filter from the last fused pose rather than publish NaN.
            last = self.fused_poses[max(self.fused_poses)] if self.fused_poses else None
            self.ekf.reset(last)
            self.ekf.predict(stamp_ns)
        t4 = time.thread_time()
        ms['pose'] = (t4 - t3) * 1e3
        ms['structure'] = self.structure_ms    # ran when the previous fused pose came back

        cov = self.ekf.pose_covariance
        if n_inliers >= self.params.min_inliers:
            state = 'tracking'
        elif n_two_view:
            state = 'tracking'     # pose and covariance from the two views (map_scale)
            n_inliers, n_epipolar = n_two_view, 0
        elif n_epipolar >= self.params.min_inliers:
            # Epipolar lines fix rotation and the direction of travel, never the distance: the
            # position is the prediction, so report it as unknown and only the rotation counts.
            state = 'tracking'
            cov[:3, :] = 0.0
            cov[:, :3] = 0.0
            cov[:3, :3] = np.eye(3) * _ROTATION_ONLY_POSITION_VARIANCE
        elif len(self.landmarks) == 0:
            state = 'initializing'
        else:
            state = 'lost'
        self._remember_motion(stamp_ns, state)
        kw = dict(n_features=len(self.tracker.ids), n_landmarks=int(has.sum()),
                  n_floor=self.landmarks.floor_count(self.tracker.ids[has]),
                  n_inliers=n_inliers + n_epipolar, stage_ms=ms)
        if state != 'tracking':
            return uninformative(stamp_ns, self.ekf.T_odom_base, self.source, state, **kw)
        return PoseEstimate(stamp_ns, self.ekf.T_odom_base, cov,
                            source=self.source, state=state, **kw)

    def bearings(self):
        """The tracks of the frame just processed (call right after process_image, before
        new features are extracted): ids, normalised undistorted points and their std in
        those units. The general arbiter fits the rig's metric motion to them in turns
        (arbiter_node/rig_motion_fit) when nothing else gives the scale."""
        xy = self.intrinsics.undistort_points(self.tracker.pts)
        return self.tracker.ids.copy(), xy, np.full(len(xy), self._bearing_sigma())

    def _bearing_sigma(self) -> float:
        return self.params.pixel_sigma / (0.5 * (self.intrinsics.fx + self.intrinsics.fy))

    def _relinearize(self, X, xy, dt):
        """Stereo rigs (metric landmarks from the first frame, often a car at speed): a
        robust pose from this frame's landmarks (OpenCV PnP, RANSAC, from the prediction)
        becomes the point the EKF update is linearized at (PoseEKF.relinearize)."""
        if len(X) < max(6, self.params.min_inliers):
            return
        T_oc = self.ekf.T_odom_base @ self.T_base_cam
        R_co = T_oc[:3, :3].T
        rvec, _ = cv2.Rodrigues(R_co)
        tvec = -R_co @ T_oc[:3, 3]
        f = 0.5 * (self.intrinsics.fx + self.intrinsics.fy)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            X.astype(np.float64), xy.astype(np.float64), np.eye(3), None,
            rvec.copy(), tvec.reshape(3, 1).copy(), useExtrinsicGuess=True, iterationsCount=100,
            reprojectionError=3.0 * self.params.pixel_sigma / f, confidence=0.99,
            flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or inl is None or len(inl) < max(6, self.params.min_inliers, len(X) // 2):
            return
        R_co, _ = cv2.Rodrigues(rvec)
        T_oc_new = np.eye(4)
        T_oc_new[:3, :3] = R_co.T
        T_oc_new[:3, 3] = -R_co.T @ tvec.reshape(3)
        T_ob = T_oc_new @ np.linalg.inv(self.T_base_cam)
        if np.all(np.isfinite(T_ob)):
            self.ekf.relinearize(T_ob, dt)

    def _two_view_due(self) -> bool:
        """No scale source has moved this quarter's map yet: no landmarks, no floor, no stereo
        partner, fused poses that put this camera where the first one did (no wheel moved
        them, no spin measured from the tracks); or this quarter
        started from two views and has no landmarks yet: it goes on measuring against the
        same view, so the map keeps one gauge (nominal speed) until landmarks hold it."""
        if not (self.params.two_view_init and not self.uses_floor and self.partner is None
                and self.fused_poses and len(self.landmarks) == 0):
            return False
        if self._two_view_ref in self.fused_poses:
            return True        # keeps the gauge until this quarter has landmarks
        _, fT, _, _ = self._fused_arrays()
        # this camera's centre, not the body's: a rig spinning in place (its motion measured
        # from the tracks, general_fusion) moves its cameras on their lever arms, a baseline
        # to triangulate from, where a two-view start would invent a nominal-speed translation
        p = fT[:, :3, :3] @ self.T_base_cam[:3, 3] + fT[:, :3, 3]
        if float(np.max(np.linalg.norm(p - p[0], axis=1))) >= self.params.epipolar_min_baseline:
            return False
        # nor when they turn: the fusion measures the motion already (a spin, from the tracks),
        # and two views of a turn that have parallax only from the lever arm are no start
        turn = np.einsum('ij,nij->n', fT[0, :3, :3], fT[:, :3, :3])      # trace(R0^T R)
        return float(np.min(turn)) > 1.0 + 2.0 * np.cos(np.radians(self.params.two_view_parallax_deg))

    def rescale_command(self, command):
        """The general arbiter's map-scale command (map_scale.MapScaleCommand): applied with
        the first fused pose at or after its stamp, so every node rescales at the same frame."""
        if command.epoch > self.scale_epoch and all(c.epoch != command.epoch for c in self._scale_pending):
            self._scale_pending = sorted(self._scale_pending + [command], key=lambda c: c.epoch)

    def _remember_motion(self, stamp_ns, state):
        v, w, cov = self.ekf.twist
        rate_std = math.sqrt(max(float(np.max(np.diag(cov)[3:])), 0.0))
        ok = state == 'tracking' and np.all(np.isfinite(w)) and rate_std < _PREDICT_MAX_RATE_STD
        self._motion = None
        if ok and self.params.predict_flow:
            self._motion = flow_prediction.MotionPrior(int(stamp_ns), w.copy())
            speed_std = math.sqrt(max(float(np.max(np.diag(cov)[:3])), 0.0))
            if np.all(np.isfinite(v)) \
                    and speed_std < max(_PREDICT_MIN_SPEED_STD, _PREDICT_MAX_SPEED_REL_STD * float(np.linalg.norm(v))):
                self._with_translation(self.ekf.T_odom_base[:3, :3].T @ v)
        if (self._motion is None and self.params.predict_flow and len(self.fused_poses) >= 2
                and self.uses_road):
            # A road quarter that is not tracking (its road points ran out at speed): the
            # fusion's motion over the last two fused poses, translation included; with
            # nothing to steer it, the next frame's road points (100 px of flow) were lost too.
            s0, s1 = sorted(self.fused_poses)[-2:]
            dt = (s1 - s0) * 1e-9
            if 0.0 < dt <= _PREDICT_MAX_DT_S:
                T0, T1 = self.fused_poses[s0], self.fused_poses[s1]
                self._motion = flow_prediction.MotionPrior(int(stamp_ns), R_to_rotvec(T0[:3, :3].T @ T1[:3, :3]) / dt)
                self._with_translation(T1[:3, :3].T @ (T1[:3, 3] - T0[:3, 3]) / dt)
        if (self._motion is None and self.params.predict_flow and len(self.fused_poses) >= 2
                and not self.uses_floor and self.partner is None):
            # Not tracking (no map yet, or lost), nothing metric in this quarter (no floor, no
            # stereo): the fusion's rate, from the last two fused poses. Why: spinning in place
            # at 1.9 rad/s every quarter lost its tracks (46 px a frame, searched from zero
            # flow) while the rig's fit still measured the spin. With the floor it made
            # spin_then_drive worse (final drift 0.54 -> 2.2 %): there the quarters start from
            # floor landmarks at once.
            s0, s1 = sorted(self.fused_poses)[-2:]
            dt = (s1 - s0) * 1e-9
            if 0.0 < dt <= _PREDICT_MAX_DT_S:
                w = R_to_rotvec(self.fused_poses[s0][:3, :3].T @ self.fused_poses[s1][:3, :3]) / dt
                if np.linalg.norm(w) > 1e-6:
                    self._motion = flow_prediction.MotionPrior(int(stamp_ns), w)

    def _with_translation(self, v_body):
        """The motion prior moves points too, at predict_translation_min_speed and faster:
        the body's velocity and the camera-frame points of the landmarks as this estimate has
        them. Slower, the pyramid's search covers what translation moves a point (and on the
        accuracy matrix's indoor runs steering by it changed nothing but the noise: the worst
        run's final drift 0.54 -> 0.62 %)."""
        if float(np.linalg.norm(v_body)) < self.params.predict_translation_min_speed:
            return
        T = self.ekf.T_odom_base @ self.T_base_cam
        has, X = self.landmarks.lookup(self.tracker.ids)
        self._motion.v_body = np.asarray(v_body, float)
        self._motion.ids = self.tracker.ids[has].copy()
        self._motion.Xc = (X - T[:3, 3]) @ T[:3, :3]

    def _steering(self, stamp_ns) -> Optional[flow_prediction.MotionPrior]:
        """The motion that steers the search for `stamp_ns`: the last estimate's prior, or
        None when there is none or it may not steer that frame (not before it, or too long
        before). With the gyro in use, the prior's rotation is the gyro's over the step (the
        prior's own rate held constant lags by degrees a frame when a turn speeds up), and a
        quarter without a prior (lost, no map yet) gets the gyro's rotation from its last
        frame alone."""
        m = self._motion
        if self.gyro is not None and self.params.predict_flow:
            t0 = m.stamp_ns if m is not None else self.ekf.stamp_ns
            if t0 is not None and 0.0 < (int(stamp_ns) - t0) * 1e-9 <= _PREDICT_MAX_DT_S:
                w = self.gyro.rate(t0, int(stamp_ns))
                if w is not None:
                    m = (flow_prediction.MotionPrior(int(t0), w) if m is None
                         else replace(m, w_body=w))
        if m is None or not 0.0 < (int(stamp_ns) - m.stamp_ns) * 1e-9 <= _PREDICT_MAX_DT_S:
            return None
        return m

    def _floor_warp(self, stamp_ns) -> Optional[flow_prediction.FloorWarp]:
        """On a road, the floor's homography from the last estimate's motion to `stamp_ns`
        (KLTTracker._recover_on_floor), or None."""
        if not self.uses_road or self.klt_cfg.floor_warp_min_flow_px <= 0:
            return None
        motion = self._steering(stamp_ns)
        if motion is None:
            return None
        return flow_prediction.floor_warp(motion, stamp_ns, self.T_base_cam, self.intrinsics,
                                          self.tracker.ids, self.floor_z)

    def _flow_predictor(self, stamp_ns):
        """(forward, backward) pixel maps of the camera's motion from the last estimate to
        `stamp_ns`, or None. Why: in a turn the features move tens of pixels a frame and
        Lucas-Kanade, starting from zero flow, iterated to its limit on every pyramid level
        (tracking took twice its straight-line CPU in the loop's turns, at 30 Hz the graph fell
        behind there); from the rotation's prediction it converges in a few steps. The
        translation moves near points only: it is left to the search below
        predict_translation_min_speed (flow_prediction above it)."""
        motion = self._steering(stamp_ns)
        if motion is None:
            return None
        if motion.v_body is not None:
            return flow_prediction.predictor(motion, stamp_ns, self.T_base_cam, self.intrinsics,
                                             self.tracker.ids, self.floor_z if self.uses_floor else None)
        dt = (int(stamp_ns) - motion.stamp_ns) * 1e-9
        R_bc = self.T_base_cam[:3, :3]
        # directions in camera 1 -> camera 2: R_bc^T exp(-[w] dt) R_bc (w in the body frame)
        R21 = R_bc.T @ rotvec_to_R(-motion.w_body * dt) @ R_bc
        intr = self.intrinsics

        def rotate(R):
            def apply(px, _rows):
                d = np.column_stack([intr.undistort_points(px), np.ones(len(px))]) @ R.T
                z = np.where(d[:, 2] > 1e-6, d[:, 2], np.nan)       # behind: no prediction
                return intr.project(d[:, :2] / z[:, None])
            return apply
        return rotate(R21), rotate(R21.T)

    def extraction_due(self) -> bool:
        return self._extract_due is not None

    def extract_pending(self):
        """Extract the new features of the last frame, if due. Runs by itself before anything
        that depends on them (the fused pose's structure, the next frame, the state); a host
        may run it earlier, when idle. Either way the results are the same."""
        if self._extract_due is None:
            return
        t0 = time.thread_time()
        n0 = len(self.tracker.ids)
        if self._cells_due:
            self.tracker.extract(self._extract_due)
        if self._lane_want:
            mask, box = self._lane()
            self.tracker.extract_in(self._extract_due, mask, box, self._lane_want)
        n = len(self.tracker.ids) - n0
        if n and self.uses_road:
            # their first view, for the general arbiter's frame pairs (new_bearings)
            xy = self.intrinsics.undistort_points(self.tracker.pts[-n:])
            nb = (self._extract_due, self.tracker.ids[-n:].copy(), xy, np.full(n, self._bearing_sigma()))
            if self._new_bearings is not None and self._new_bearings[0] == nb[0]:
                nb = (nb[0],) + tuple(np.concatenate([a, b]) for a, b in zip(self._new_bearings[1:], nb[1:]))
            self._new_bearings = nb
        self._extract_due = None
        self._cells_due, self._lane_want = False, 0
        self.extract_ms += (time.thread_time() - t0) * 1e3

    def new_bearings(self):
        """On a road, the features extracted since the last call, at the frame they were
        extracted on: (stamp, ids, normalised points, stds), or None. bearings() goes out
        before its frame's new features exist, so without these a track born on frame a
        counts for the general arbiter's road scale from the pair (b, c) on, not (a, b): at
        car speed the lane's tracks rarely live three frames (KITTI 07 at 5 Hz: 0-7 of them
        in the lane a frame pair, below road_scale's minimum, on half the drive)."""
        nb, self._new_bearings = self._new_bearings, None
        return nb

    def _lane_shortfall(self) -> int:
        """How many tracks the lane ahead lacks (road_lane_features), on a road."""
        want = self.params.road_lane_features
        if not (self.uses_road and want > 0) or self._lane()[1] is None:
            return 0
        return max(0, want - int(self._in_lane(self.tracker.pts).sum()))

    def _lane(self):
        """(mask, box): where this quarter's own rectangle looks at the lane ahead (crop
        pixels, uint8) and its bounding box (x0, y0, x1, y1), box None where it does not.
        From the rig: the camera's mount over the level floor (a cache: it never changes)."""
        if self._lane_cache is None:
            reg = self.region
            h, w = reg.cy1 - reg.cy0, reg.cx1 - reg.cx0
            vv, uu = np.mgrid[reg.cy0:reg.cy1, reg.cx0:reg.cx1]
            own = (uu >= reg.x0) & (uu < reg.x1) & (vv >= reg.y0) & (vv < reg.y1)
            inside = own & self._in_lane(np.column_stack([uu.ravel(), vv.ravel()])).reshape(h, w)
            ys, xs = np.nonzero(inside)
            box = None if not len(xs) else (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
            self._lane_cache = (inside.astype(np.uint8) * 255, box)
        return self._lane_cache

    def _in_lane(self, px: np.ndarray) -> np.ndarray:
        """Which full-image pixels look at the lane ahead (road_region, the level floor)."""
        if not len(px):
            return np.zeros(0, bool)
        R = self.T_base_cam[:3, :3]
        down_c, height = road_plane.camera_over_road(np.array([0.0, 0.0, 1.0]), R, self.T_base_cam[:3, 3],
                                                     self.floor_z)
        return road_plane.road_region(self.intrinsics.undistort_points(px), down_c, R, height)

    def _fused_arrays(self):
        """(sorted stamps (K,), body poses (K, 4, 4), camera rotations (K, 3, 3), camera
        centres (K, 3)) of the fused poses, rebuilt when they changed."""
        if self._fused_cache is None:
            st = np.array(sorted(self.fused_poses), np.int64)
            T = np.array([self.fused_poses[k] for k in st.tolist()]).reshape(-1, 4, 4)
            R_oc, c_o = self._camera_pose(T)
            self._fused_cache = (st, T, R_oc, c_o)
        return self._fused_cache

    def _earlier_fused_views(self, rows=None) -> np.ndarray:
        """(len(rows), max_history) mask of the history slots of tracks `rows` (all when None)
        before their newest view that have a fused pose: where an epipolar line can start."""
        tr = self.tracker
        ht, n = (tr.hist_t, tr.hist_n) if rows is None else (tr.hist_t[rows], tr.hist_n[rows])
        earlier = np.arange(tr.cfg.max_history)[None, :] < (n - 1)[:, None]
        return earlier & _members(ht, self._fused_arrays()[0])

    def _epipolar_update(self, stamp_ns, without_landmark) -> int:
        """Epipolar measurements of the tracks without a landmark (see PoseEKF.update_epipolar),
        each against its oldest view that has a fused pose. Returns the inlier count."""
        tr = self.tracker
        if not self.fused_poses:
            return 0
        rows = np.flatnonzero(without_landmark & (tr.last_stamps() == stamp_ns))
        if not len(rows):
            return 0
        fs, fT, _, _ = self._fused_arrays()
        # the oldest view with a fused pose (not the current one): the longest baseline, the
        # best-defined line
        infused = self._earlier_fused_views(rows)
        found = infused.any(axis=1)
        rows, col = rows[found], np.argmax(infused[found], axis=1)
        slot = np.searchsorted(fs, tr.hist_t[rows, col])
        # The body itself must have moved: spinning in place only swings the camera on its
        # lever arm, a baseline too short for its direction to be known from the poses.
        body_p = self.ekf.T_odom_base[:3, 3]
        moved = np.linalg.norm(fT[:, :3, 3] - body_p, axis=1) >= self.params.epipolar_min_baseline
        ok = moved[slot]
        rows, col, slot = rows[ok], col[ok], slot[ok]
        if not len(rows):
            return 0
        first_T = fT[slot]
        first_px = tr.hist_uv[rows, col].astype(float)
        R_oc, c_o = self._camera_pose(first_T)
        xy1 = self.intrinsics.undistort_points(first_px)
        rays = bearings_odom(R_oc, xy1)
        xy2 = self.intrinsics.undistort_points(tr.pts[rows].astype(float))
        # both ends are noisy: the line distance has about sqrt(2) pixel sigmas
        sigma = math.sqrt(2.0) * self.params.pixel_sigma / (0.5 * (self.intrinsics.fx + self.intrinsics.fy))
        inl = self.ekf.update_epipolar(c_o, rays, xy2, sigma, self.T_base_cam,
                                       gate_chi2=self.params.gate_chi2 * 6.63 / 9.21,
                                       min_baseline=self.params.epipolar_min_baseline)
        return int(inl.sum())

    def twist(self):
        """(v in odom, w in base_link, 6x6 covariance of [v, w]) of the last estimate."""
        return self.ekf.twist

    def track_overlay(self, trail: int = 5):
        """What a debug image shows of the current tracks (read-only: nothing the estimate
        depends on changes). Returns (trails (N, trail, 2) float32 full-image pixels, the
        track's last `trail` views oldest first and the current one last, NaN where it has
        fewer; status (N,) uint8 TRACK_*). Called after process_image: the landmarks then
        are those its estimate used. TRACK_EPIPOLAR marks the tracks the epipolar update
        takes up; it measures them once the body moved epipolar_min_baseline from that view."""
        tr = self.tracker
        N, H, K = len(tr.ids), tr.cfg.max_history, max(1, int(trail))
        n = tr.hist_n
        # slots 0..n-1 are consecutive views; once full, slot 0 is the oldest kept and
        # slots 1..H-1 the consecutive latest
        k = np.minimum(np.where(n < H, n, H - 1), K)
        cols = n[:, None] - K + np.arange(K)[None, :]
        trails = tr.hist_uv[np.arange(N)[:, None], np.clip(cols, 0, H - 1)].astype(np.float32)
        trails[np.arange(K)[None, :] < (K - k)[:, None]] = np.nan
        status = np.full(N, TRACK_NEW, np.uint8)
        if self.params.epipolar and self.fused_poses:
            status[self._earlier_fused_views().any(axis=1)] = TRACK_EPIPOLAR
        has, r = self.landmarks.rows(tr.ids)
        status[has] = np.where(self.landmarks.on_floor[r], TRACK_FLOOR, TRACK_LANDMARK)
        return trails, status

    # ----- feedback from the general arbiter -----------------------------------------------
    def apply_fused_pose(self, stamp_ns: int, T_odom_base: np.ndarray, cov6: np.ndarray,
                         partner_gray: Optional[np.ndarray] = None) -> float:
        """Realign to the fused pose of frame `stamp_ns`, then triangulate and prune
        landmarks with it. Returns the structure stage time (ms), also reported with the
        next frame's estimate. An uninformative fused pose carries nothing and is ignored.
        partner_gray: the stereo partner's image of the same stamp (set_partner), whose
        matches give the tracks without a landmark a metric one."""
        self.extract_pending()     # the new features are part of the structure (floor seeding)
        t0 = time.thread_time()
        T = np.asarray(T_odom_base, float)
        C = np.asarray(cov6, float)
        if T.shape != (4, 4) or C.shape != (6, 6):
            raise UserError(f'{self.source}: fused pose must be 4x4 and covariance 6x6')
        if not (np.all(np.isfinite(T)) and np.all(np.isfinite(C))) \
                or np.max(np.diag(C)) >= UNINFORMATIVE_VARIANCE:
            return 0.0
        stamp_ns = int(stamp_ns)
        while self._scale_pending and stamp_ns >= self._scale_pending[0].from_ns:
            map_scale.rescale_quarter(self, self._scale_pending.pop(0))
        first = not self.fused_poses
        while self._road_pending and self._road_pending[0][0] < stamp_ns:
            self.road_up = self._road_pending.pop(0)[1]
        if self.ekf.stamp_ns is None:
            self.ekf.reset(T)
            self.ekf.stamp_ns = stamp_ns
            self.ekf.set_pose(T, C)
        elif stamp_ns == self.ekf.stamp_ns:
            self.ekf.set_pose(T, C)
        # (older stamps: a late message, still good for triangulation)
        self.fused_poses[stamp_ns] = T.copy()
        self._fused_cache = None
        self._prune_landmarks(stamp_ns, T)
        self._triangulate()
        if self.stereo is not None and partner_gray is not None:
            self._stereo_landmarks(stamp_ns, T, partner_gray)
        if first and self.uses_floor:
            self._seed_floor(stamp_ns, T)
        self._forget_unused_poses()
        self.structure_ms = (time.thread_time() - t0) * 1e3
        return self.structure_ms

    def _camera_pose(self, T_odom_base):
        T = T_odom_base @ self.T_base_cam
        return T[..., :3, :3], T[..., :3, 3]

    def _prune_landmarks(self, stamp_ns, T):
        tr = self.tracker
        seen = tr.last_stamps() == stamp_ns
        if not seen.any():
            return
        ids = tr.ids[seen]
        R_oc, c_o = self._camera_pose(T)
        bad = self.landmarks.check(ids, R_oc, c_o, self.intrinsics.undistort_points(tr.last_px()[seen]))
        # A landmark that stopped fitting usually means the track drifted: restart both.
        tr.drop(ids[bad])

    def _triangulate(self):
        tr, lm = self.tracker, self.landmarks
        if not len(tr.ids):
            return
        fs, fT, R_all, c_all = self._fused_arrays()
        # the views of each track that have a fused pose, in order: their columns first
        infused = tr.views_used() & _members(tr.hist_t, fs)
        m = infused.sum(axis=1)
        rows = np.flatnonzero(m >= 2)
        if not len(rows):
            return
        m = m[rows]
        order = np.argsort(~infused[rows], axis=1, kind='stable')
        # Ray angle between the oldest and newest views (rotation-compensated in odom). Only
        # those two views are needed to decide; the tracks that pass get all their views
        # below (every step is per point and view, so the values are the same either way).
        r = np.arange(len(rows))
        ends = np.column_stack([order[:, 0], order[r, m - 1]])
        R_oc, c_o, xy = self._views(rows, ends, fs, R_all, c_all)
        rays = bearings_odom(R_oc, xy)
        par = angle_deg(rays[:, 0], rays[:, -1])
        want = lm.want(tr.ids[rows], par)
        if not want.any():
            return
        idx, distinct = _view_tables(tr.cfg.max_history)
        rows, order, m = rows[want], order[want], m[want]
        cols = np.take_along_axis(order, idx[m], axis=1)
        ids = tr.ids[rows]
        R_oc, c_o, xy = self._views(rows, cols, fs, R_all, c_all)
        ok = lm.triangulate(ids, R_oc, c_o, xy, view_weights=distinct[m])
        if self.uses_floor and ok.any():
            last = np.searchsorted(fs, tr.hist_t[rows[ok], cols[ok, -1]])
            self._snap_to_floor(ids[ok], R_oc[ok, -1], c_o[ok, -1], xy[ok, -1], fT[last])

    def _seed_floor(self, stamp_ns, T):
        """With its first fused pose (the start, or after a reset) a quarter puts the features
        it sees below the horizon on the floor from this one view: no parallax needed, so it
        tracks from the next frame even though nothing moves the fused poses yet without wheel
        odometry (nothing else starts the loop then). Points not on the floor are corrected
        when their parallax allows a triangulation (which re-judges them) or dropped by the
        checks. Only at the start: seeding whenever a map ran thin (fast turns) made
        spin_then_drive's drift 0.7 -> 1.5 % (seed 7) and 0.6 -> 3.5 % (seed 8)."""
        tr = self.tracker
        has, _ = self.landmarks.rows(tr.ids)
        rows = np.flatnonzero(~has & (tr.last_stamps() == stamp_ns))
        if not len(rows):
            return
        ids = tr.ids[rows]
        R_oc, c_o = self._camera_pose(T)
        xy = self.intrinsics.undistort_points(tr.last_px()[rows])
        n, d = floor_plane(T, self.floor_z, self.road_up)
        N = len(rows)
        valid, X, _, C = floor_points(bearings_odom(np.broadcast_to(R_oc, (N, 3, 3)), xy),
                                      np.broadcast_to(c_o, (N, 3)), np.broadcast_to(n, (N, 3)),
                                      np.full(N, d), self.landmarks.sigma_n, self.floor_tilt_rad)
        self.landmarks.place(ids[valid], X[valid], C[valid])

    def _tracks_since(self, s0, stamp_ns):
        """The tracks seen in this frame and, one sighting before, at frame s0: their rows in
        the tracker and their points at s0 (normalised, undistorted)."""
        tr = self.tracker
        rows = np.flatnonzero((tr.hist_n >= 2) & (tr.last_stamps() == stamp_ns))
        prev = tr.hist_n[rows] - 2
        ok = tr.hist_t[rows, prev] == s0
        rows, prev = rows[ok], prev[ok]
        return rows, self.intrinsics.undistort_points(tr.hist_uv[rows, prev].astype(float))

    def _relinearize_first_road_step(self, stamp_ns):
        """road_first_step: the first frame pair since the floor was seeded (one fused pose)
        has no motion to predict from, so the EKF would linearize its update at rest while a
        car moved a metre; it is linearized at the step this quarter's tracks measure
        (road_plane.road_step) instead, as the stereo rigs' is at a PnP pose."""
        s0 = next(iter(self.fused_poses))
        rows, xy0 = self._tracks_since(s0, stamp_ns)
        if len(rows) < self.params.two_view_min_points:
            return
        xy1 = self.intrinsics.undistort_points(self.tracker.pts[rows].astype(float))
        T0 = self.fused_poses[s0]
        R_oc, c_o = self._camera_pose(T0)
        n, d = floor_plane(T0, self.floor_z, self.road_up)
        step = road_plane.road_step(xy0, xy1, R_oc.T @ -n, float(n @ c_o - d), self.T_base_cam[:3, :3],
                                    2.5 * self.landmarks.sigma_n, self.params.two_view_min_points,
                                    self.params.two_view_parallax_deg)
        if step is None:
            return
        T_c0c1 = np.eye(4)
        T_c0c1[:3, :3] = step.R.T
        T_c0c1[:3, 3] = step.centre_m
        T1 = T0 @ self.T_base_cam @ T_c0c1 @ np.linalg.inv(self.T_base_cam)
        self.ekf.relinearize(T1, (stamp_ns - s0) * 1e-9)

    def _road_landmarks(self, stamp_ns) -> int:
        """Tracks seen in the previous frame and in this one that move as the floor does
        (road_plane.fit_road) and have no landmark yet: placed on the floor from the previous
        frame's fused pose, so this frame's update measures a metric step against them."""
        tr = self.tracker
        if len(self.own_stamps) < 2 or self.own_stamps[-2] not in self.fused_poses:
            return 0
        s0 = self.own_stamps[-2]
        rows, xy0 = self._tracks_since(s0, stamp_ns)
        if len(rows) < road_plane.MIN_POINTS:
            return 0
        T0 = self.fused_poses[s0]
        R_oc, c_o = self._camera_pose(T0)
        n, d = floor_plane(T0, self.floor_z, self.road_up)
        N = len(rows)
        valid, X, _, C = floor_points(bearings_odom(np.broadcast_to(R_oc, (N, 3, 3)), xy0),
                                      np.broadcast_to(c_o, (N, 3)), np.broadcast_to(n, (N, 3)),
                                      np.full(N, d), self.landmarks.sigma_n, self.floor_tilt_rad)
        if valid.sum() < road_plane.MIN_POINTS:
            return 0
        xy1 = self.intrinsics.undistort_points(tr.pts[rows[valid]].astype(float))
        fit = road_plane.fit_road(xy0[valid], xy1, R_oc.T @ -n, float(n @ c_o - d),
                                  2.5 * self.landmarks.sigma_n, self.params.road_min_step)
        if fit is None:
            return 0
        sel = np.flatnonzero(valid)[fit.inliers]
        has, _ = self.landmarks.rows(tr.ids[rows[sel]])
        sel = sel[~has]
        self.landmarks.place(tr.ids[rows[sel]], X[sel], C[sel])
        return len(sel)

    def _stereo_landmarks(self, stamp_ns, T, gray_b):
        """Tracks seen in this frame without a landmark: matched into the partner's image
        of the same stamp and triangulated from the rig's baseline, placed in odom with the
        fused pose. Every frame: the map of a camera that sees only far or fast-moving
        points (a car's) never waits for parallax. A placed landmark is re-triangulated over
        time like any other once its parallax allows (LandmarkMap.want)."""
        gray_b = np.asarray(gray_b)
        if gray_b.dtype != np.uint8 or gray_b.ndim != 2 \
                or (gray_b.shape[1], gray_b.shape[0]) != self.partner_size:
            raise UserError(f'{self.source}: stereo partner image is {gray_b.dtype} {gray_b.shape}, '
                            f'expected gray uint8 {self.partner_size[0]}x{self.partner_size[1]} (CameraInfo)')
        tr = self.tracker
        has, _ = self.landmarks.rows(tr.ids)
        seen = tr.last_stamps() == stamp_ns
        rows = np.flatnonzero(~has & seen)
        if not len(rows) or tr.prev_crop is None:
            return
        R_oc, c_o = self._camera_pose(T)
        # the search starts at the depth of the quarter's own landmarks when it has some
        prior = self.params.stereo_prior_depth * self.stereo.baseline
        with_lm = has & seen
        if with_lm.sum() >= 5:
            _, X = self.landmarks.lookup(tr.ids[with_lm])
            z = ((X - c_o) @ R_oc)[:, 2]
            z = z[z > 0]
            if len(z) >= 5:
                prior = float(np.median(z))
        ok, _, X_a, C_a = self.stereo.match(tr.prev_crop, self.region.offset, gray_b,
                                            tr.last_px()[rows], prior)
        if not ok.any():
            return
        X_o = X_a[ok] @ R_oc.T + c_o
        C_o = R_oc @ C_a[ok] @ R_oc.T
        self.landmarks.place(tr.ids[rows[ok]], X_o, C_o, on_floor=False)

    def _snap_to_floor(self, ids, R_oc, c_o, xy, T):
        """Floor landmarks onto the floor, judged from each one's newest view (body poses T)."""
        _, X = self.landmarks.lookup(ids)
        p = self.params
        on, X_f, C_f = snap_to_floor(X, self.landmarks.covariances_of(ids), R_oc, c_o, xy, T,
                                     self.floor_z, p.ground_tolerance, p.ground_map_scale_std,
                                     self.landmarks.sigma_n, self.floor_tilt_rad, self.road_up)
        self.landmarks.place(ids[on], X_f, C_f)

    def _views(self, rows, cols, fs, R_all, c_all):
        """(R_oc, c_o, xy) of the history slots `cols` (N, V) of tracks `rows` (N)."""
        N, V = cols.shape
        rr = np.broadcast_to(rows[:, None], cols.shape)
        px = self.tracker.hist_uv[rr, cols].astype(float)                  # (N, V, 2)
        xy = self.intrinsics.undistort_points(px.reshape(-1, 2)).reshape(N, V, 2)
        slot = np.searchsorted(fs, self.tracker.hist_t[rr, cols])
        return R_all[slot], c_all[slot], xy

    def _forget_unused_poses(self):
        self.landmarks.keep_only(self.tracker.ids)
        fs, _, _, _ = self._fused_arrays()
        seen = self.tracker.hist_t[self.tracker.views_used()]
        slot = np.minimum(np.searchsorted(fs, seen), len(fs) - 1)
        used = np.zeros(len(fs), bool)
        used[slot[fs[slot] == seen]] = True
        used[-1] = True                        # the latest stays (the next frame's prediction)
        if not used.all():
            for s in fs[~used].tolist():
                del self.fused_poses[s]
            self._fused_cache = None

    # ----- hand-over ---------------------------------------------------------------------
    def get_state(self) -> dict:
        """Everything needed to continue in another process with identical results
        (picklable: numpy arrays, dicts, lists, numbers)."""
        self.extract_pending()     # (the same tracks as if it had run already)
        return {'version': STATE_VERSION, 'source': self.source,
                'params': self.params.as_dict(), 'image_size': self.image_size,
                'ekf': self.ekf.get_state(), 'tracker': self.tracker.get_state(),
                'landmarks': self.landmarks.get_state(),
                'fused_poses': {k: v.copy() for k, v in self.fused_poses.items()},
                'structure_ms': self.structure_ms, 'extract_ms': self.extract_ms,
                'motion': None if self._motion is None else self._motion.to_list(),
                'partner': self.partner, 'own_stamps': list(self.own_stamps),
                'scale_epoch': self.scale_epoch, 'two_view_ref': self._two_view_ref,
                'scale_pending': [c.to_list() for c in self._scale_pending],
                'new_bearings': self._new_bearings,
                'road_up': None if self.road_up is None else self.road_up.tolist(),
                'road_pending': [(t, v.tolist()) for t, v in self._road_pending]}

    def set_state(self, s: dict):
        if s.get('version') != STATE_VERSION:
            raise UserError(f'{self.source}: state version {s.get("version")} is not '
                            f'{STATE_VERSION}')
        if s.get('source') != self.source or tuple(s.get('image_size', ())) != self.image_size:
            raise UserError(f'{self.source}: state belongs to {s.get("source")} '
                            f'{s.get("image_size")}, not this quarter {self.image_size}')
        if s.get('params') != self.params.as_dict():
            raise UserError(f'{self.source}: state was made with different parameters')
        self.ekf.set_state(s['ekf'])
        self.tracker.set_state(s['tracker'])
        self.landmarks.set_state(s['landmarks'])
        self.fused_poses = {int(k): np.array(v, float) for k, v in s['fused_poses'].items()}
        self._fused_cache = None
        self.own_stamps = [int(v) for v in s['own_stamps']]
        self.structure_ms = float(s['structure_ms'])
        self.extract_ms = float(s['extract_ms'])
        m = s['motion']
        self._motion = None if m is None else flow_prediction.MotionPrior.from_list(m)
        self.stereo, self.partner = None, None
        if s['partner'] is not None:
            self.set_partner(*s['partner'])
        self._prefetched = None
        self._extract_due = None
        self._cells_due, self._lane_want = False, 0
        self.scale_epoch = int(s['scale_epoch'])
        self._two_view_ref = s['two_view_ref']
        self._scale_pending = [map_scale.MapScaleCommand.from_list(c) for c in s['scale_pending']]
        self._new_bearings = s['new_bearings']
        self.road_up = None if s['road_up'] is None else np.array(s['road_up'], float)
        self._road_pending = [(int(t), np.array(v, float)) for t, v in s['road_pending']]
