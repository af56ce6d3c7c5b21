"""General arbiter core (paper T_5 / T_GA), ROS-free: cameras -> odometry.

Per frame: median filter across cameras (camera_median) -> covariance-weighted fusion of the
inliers (quarter_fusion.information_fusion, correlation-inflated) -> BodyEKF update (gated).
No informative camera: predict only, with the wheel-odometry twist prior when given.
Free-running cameras: each estimate comes at its own stamp (a group of one camera, gated by
the EKF alone) and each wheel reading is applied once, at its own stamp. With an opt-in sync
window a frame's estimates may carry different stamps; each is moved to the frame's common
time (the latest stamp) with the EKF's constant-twist motion model before the median
(time_shift), and the fused pose is given back to each camera at its own stamp (pose_at).
Scale: the rig-scale observer (rig_scale) is fed when per-camera translation directions are
available and `scale_observed` reports it; until it is wired to correct anything, metric
scale comes from the wheel prior (when configured) and from the landmarks.
"""
from collections import deque
from dataclasses import dataclass, field, fields, replace
from typing import Dict, List, Mapping, Optional, Tuple

import numpy as np

from arbiter_node.body_ekf import STANDARD_GRAVITY, BodyEKF, BodyEkfParams
from arbiter_node.camera_median import median_filter
from arbiter_node.covariance import condition_covariance
from arbiter_node.quarter_fusion import CHI2_6DOF_999, information_fusion
from arbiter_node.time_shift import shift_pose
from arbiter_node.rig_motion_fit import fit_rig_motion, refine_rig_motion
from arbiter_node.rig_scale import RigScaleResult, relative_motion, scale_correction, solve_rig_translation
from arbiter_node.road_motion import body_twist, camera_motion, rig_motion
from arbiter_node.scale_state import ScaleState, metric_source
from camera_pose_nodes.map_scale import scale_positions
from camera_pose_nodes.pose_estimate import PoseEstimate
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.geometry.rig import Rig
from multicam_ego_motion.imu.imu_buffer import ImuBuffer
from multicam_ego_motion.imu.imu_health import ImuHealth, ImuHealthLimits

FUSED_STATES = ('initializing', 'tracking', 'lost', 'dead_reckoning')

# name -> (default, description, min, max): what a node declares as ROS parameters.
PARAMETERS = {
    'median_mahalanobis_gate': (CHI2_6DOF_999, 'chi-square (6 dof) gate of a camera against the cross-camera median', 1.0, 1e6),
    'median_max_translation_m': (0.5, 'absolute gate: a camera farther than this from the median is rejected (m)', 0.01, 100.0),
    'median_max_rotation_rad': (0.2, 'absolute gate: a camera rotated more than this from the median is rejected (rad)', 0.001, 3.15),
    'median_use_prior': (True, 'let the EKF prediction vote in the median (see median_prior_max_cameras)', None, None),
    'median_prior_max_cameras': (8, 'the EKF prediction votes while at most this many cameras are informative: 2 = only where the cameras cannot out-vote one another; 8 = always (breaks 2-2 ties)', 0, 64),
    'median_weighted': (True, 'weight each vote in the median by its precision (1 / RMS std): loose cameras cannot move it', None, None),
    'lone_camera_covariance_scale': (2.0, "free-running cameras: a camera fused alone at its stamp has its covariance times this (no other camera's vote vets it; loop seeds 7-10 at random phases, final drift summed: 1.55 % at 1, 1.19 % at 2, 1.15 % at 3, 1.22 % at 4; synchronised 1.08 %)", 1.0, 100.0),
    'lone_camera_robust_chi2': (4.0, "free-running cameras: a camera fused alone whose innovation's squared Mahalanobis distance d2 (6 dof) exceeds this has its covariance times sqrt(d2 / this), a Huber weight: a lone fix far from the prediction pulls it by a bounded amount, as no other camera's vote out-votes it (loop seeds 7-11 at random phases, ATE / final drift summed, mean of three feature thresholds: 1.46 / 1.66 % without, 1.38 / 1.55 at 4; synchronised 1.20 / 1.36); 1e6: off", 1.0, 1e6),
    'lone_camera_track_rotation': (True, "free-running cameras: each camera's rotation between its last two frames, fitted to its tracks (rig_motion_fit), measures the body's rotation between the fused poses at those stamps (clones of them in the body EKF): the turn's rate from image measurements alone, where a lone fix and the prediction alone let the rate lag in fast turns", None, None),
    'lone_track_rotation_cov_scale': (8.0, "lone_camera_track_rotation: the fit's rotation covariance times this", 0.01, 1e6),
    'camera_correlation': (0.0, 'assumed error correlation between cameras (shared fed-back landmarks); inflates the fused covariance by 1+(n-1)rho', 0.0, 1.0),
    'camera_floor_std_m': (0.005, 'added to every camera estimate: position std of the landmark-map error the quarters leave out (m)', 0.0, 10.0),
    'camera_floor_std_rad': (0.002, 'added to every camera estimate: rotation std of the landmark-map error (rad)', 0.0, 1.0),
    'ekf_gate_chi2': (CHI2_6DOF_999, 'chi-square (6 dof) gate of the fused camera pose against the EKF prediction', 1.0, 1e6),
    'max_consecutive_rejections': (5, 'after this many frames in a row whose cameras were refused (their fused pose gated out by the EKF, or every camera out-voted by the prediction in the median), re-initialise the EKF on the cameras', 1, 1000),
    'accel_noise': (0.25, 'EKF process noise: white linear acceleration, body frame ((m/s^2)^2/Hz)', 1e-6, 100.0),
    'angular_accel_noise': (0.25, 'EKF process noise: white angular acceleration, body frame ((rad/s^2)^2/Hz)', 1e-6, 100.0),
    'initial_pose_std': (1e-4, 'pose std at start: odom starts at the robot (REP-105), so tiny (m, rad)', 1e-6, 10.0),
    'initial_twist_std': (1.0, 'twist std at (re)initialisation (m/s, rad/s)', 1e-3, 100.0),
    'max_dt': (1.0, 'prediction step cap (s); longer gaps are integrated in steps', 0.01, 10.0),
    'lost_timeout_s': (2.0, 'without camera updates or wheel prior for this long, the state is lost', 0.1, 600.0),
    'arc_integration': (True, 'EKF prediction moves along the arc of the twist (constant body twist), not along the heading at the start of the step', None, None),
    'wheel_planar_only': (True, 'use only vx, vy, wz of the wheel twist (a wheeled base measures nothing else)', None, None),
    'use_imu': (False, 'fuse the gyro of the rig\'s IMU (rig file `imu`, or its frame in /tf_static) when one publishes: the rotation between frames follows it, less its bias, which the EKF estimates. Off by default: it holds spins without wheel (heading 17 -> 1.2 deg) but the accuracy matrix with the wheel is not yet better with it (mean final drift 0.342 against 0.324 %: docs/fusion.md)', None, None),
    'imu_gyro_variance': (1e-5, 'a gyro sample\'s variance per axis ((rad/s)^2) when its message has no covariance', 1e-12, 1.0),
    'gyro_bias_std': (0.01, 'the gyro bias\'s prior std (rad/s; MEMS: a few tenths of a degree per second)', 1e-6, 1.0),
    'gyro_bias_walk': (1e-4, 'the gyro bias\'s random walk (rad/s/sqrt(s))', 1e-9, 1.0),
    'imu_gyro_saturation': (34.9, 'IMU health (imu_health): a gyro component at or beyond this is saturated (rad/s; 34.9 = 2000 deg/s, a MEMS gyro\'s widest range: set the driver\'s)', 0.01, 1000.0),
    'imu_saturation_repeats': (20, 'IMU health: one gyro component reading the same non-zero value this many samples in a row while another moves is saturated (a range that clips)', 2, 1000000),
    'imu_stuck_samples': (20, 'IMU health: the gyro repeating one sample exactly (all three axes) this many times in a row is stuck (a MEMS gyro\'s noise never repeats)', 2, 1000000),
    'imu_silent_s': (0.2, 'IMU health: no sample for longer than this at a frame\'s stamp, or none since the first frame, is a silent IMU (s)', 0.01, 600.0),
    'imu_refused_fraction': (0.05, 'IMU health: more than this fraction of the last imu_refused_window samples refused (out of order, repeated or not finite) is a fault; fewer is jitter', 0.0, 1.0),
    'imu_refused_window': (100, 'IMU health: ... of this many samples', 1, 1000000),
    'imu_gyro_bias_max': (0.05, 'IMU health: the filter\'s gyro-bias estimate beyond this (rad/s, its norm) is a drifting bias (a MEMS gyro\'s turn-on bias is a few tenths of a degree per second, 0.01 rad/s); it holds until a reset, the bias frozen', 1e-4, 10.0),
    'imu_gyro_disagreement': (0.03, 'IMU health: the cameras\' fixes turning away from the gyro\'s prediction by more than this on average (rad/s, over imu_disagreement_window_s) is a drifting bias (the innovation test)', 1e-4, 10.0),
    'imu_disagreement_per_rotation': (0.05, 'IMU health: ... plus this much per radian the body turned (the cameras\' own rotation error grows with the rotation: 4 % in the 10 s loop\'s turns)', 0.0, 1.0),
    'imu_disagreement_window_s': (1.0, 'IMU health: ... over this long (s)', 0.1, 600.0),
    'imu_recover_s': (2.0, 'IMU health: after a problem, the gyro is used again once none was seen for this long (s)', 0.0, 3600.0),
    'imu_gravity': (True, "with the gyro: the accelerometer's mean specific force over each frame step, moved to base_link's origin and less the body's own acceleration as the filter has it, measures which way is up (roll and pitch; BodyEKF.update_gravity, with the accelerometer's bias a state) while the body does not accelerate hard; not on a level floor (planar_motion), whose landmarks hold the tilt already (there the accuracy matrix read 0.374 % mean final drift with it, 0.344 without)", None, None),
    'imu_accel_variance': (1e-3, "an accelerometer sample's variance per axis ((m/s^2)^2) when its message has no covariance", 1e-12, 100.0),
    'imu_gravity_std_rad': (0.003, "imu_gravity: the up direction's std beyond the accelerometer's white noise and its bias (a state) (rad; times g in m/s^2): the accelerations the filter does not see (spin_then_drive without wheel or floor, seeds 7-9, ATE / final drift summed: 4.89 / 8.50 % without imu_gravity, 5.44 / 7.07 at 0.01, 4.25 / 7.15 at 0.003)", 1e-6, 1.0),
    'imu_gravity_max_accel': (0.5, "imu_gravity: a step whose body acceleration (the filter's) or whose reading's magnitude off gravity is more than this does not measure up (m/s^2)", 0.0, 100.0),
    'imu_gravity_gate_chi2': (11.34, "imu_gravity: chi-square (3 dof, 99 %) gate of the up direction against the filter's", 1.0, 1e6),
    'gyro_bias_tracks_settle_s': (0.0, 'gyro_bias_from_tracks: the tracks tell the gyro bias from this long after the first fix (their fit of the rig\'s rotation needs no map, only the tracks of two frames: from the start, the bias is known before the first turn)', 0.0, 600.0),
    'gyro_bias_settle_s': (3.0, 'the cameras\' fixes tell the gyro bias (without gyro_bias_from_tracks) and test the gyro (imu_health) only from this long after the first fix (while the maps form the fixes are off by tenths of a degree between frames, which the filter took for a 4 mrad/s bias)', 0.0, 600.0),
    'gyro_bias_from_tracks': (True, "with the gyro: every frame, the rig's rotation between the two previous frames fitted to all cameras' tracks at once (rig_motion_fit.refine_rig_motion, from the gyro's rotation) measures the gyro bias directly, as the gyro's mean rate less that rotation's, and the fused poses no longer tell it (a spin's fixes, off by tenths of a degree, pulled it the wrong way: docs/fusion.md)", None, None),
    'gyro_bias_tracks_min_travel': (1.0, "gyro_bias_from_tracks: only while the body's speed is at least this times its turn rate times the longest camera lever arm (m/s per m/s): in a spin in place every camera moves sideways, along its epipolar lines, where a yaw error does not show", 0.0, 100.0),
    'gyro_bias_tracks_inflation': (2.0, "gyro_bias_from_tracks: the fit's rotation covariance times this (a margin: on the generator's scenes the fits' rotations are within 0.05 mrad/s of the truth after a spin, where they predict 0.3)", 1.0, 1e4),
    'gyro_bias_tracks_gate_chi2': (11.34, "gyro_bias_from_tracks: chi-square (3 dof, 99 %) gate of that bias measurement against the filter's bias", 1.0, 1e6),
    'gyro_bias_tracks_settled_std': (5e-4, "gyro_bias_from_tracks: once the filter's gyro bias std (its largest axis, rad/s) is below this, the bias is measured every gyro_bias_tracks_settled_every frames only (it walks slowly: on the generator's scenes its std settles at 0.2-0.26 mrad/s within 2 s of the first fit); 0: every frame", 0.0, 1.0),
    'gyro_bias_tracks_settled_every': (2, 'gyro_bias_from_tracks: with the bias settled (gyro_bias_tracks_settled_std), one frame in this many measures it', 1, 100),
    'planar_motion': (True, 'the base moves on the rig\'s level floor (rig floor_z, not with floor_level false; robot_localization calls it two_d_mode): every frame measures its vz, wx, wy as 0', None, None),
    'planar_twist_std': (1e-3, 'std of that planar-motion measurement of vz (m/s), wx and wy (rad/s)', 1e-6, 10.0),
    'wheel_gate_chi2': (1e3, 'chi-square gate of the wheel twist against the EKF twist (slip detection)', 1.0, 1e9),
    'scale_direction_sigma_rad': (0.01, 'angular std of a camera translation direction fed to the rig-scale observer (rad)', 1e-5, 0.5),
    'scale_min_rotation_rad': (0.02, 'rig-scale observer: below this body rotation scale is unobservable (rad)', 1e-4, 1.0),
    'scale_max_relative_std': (0.1, 'rig-scale observer: trust t only when its predicted relative error is below this', 1e-3, 1.0),
    'start_speed_std': (20.0, 'rig with a metric source of its own (stereo pair or floor) and no wheel yet: linear velocity std at the first camera fix (m/s); such a rig measures metric motion from the first frames and may start at speed (a car), where the at-rest start gated out every later frame', 1e-3, 1000.0),
    'start_min_cameras': (2, 'without stereo, floor or wheel: the first fix needs this many cameras that agree (two-view initialisation)', 1, 64),
    'start_from_tracks': (True, 'without stereo, floor or wheel: on frames without a camera fix, the rig\'s motion between the two previous frames fitted to the quarters\' tracks (rig_motion_fit) is a twist measurement whenever it is metric (a turn or a spin in place: the lever arms), so /odom turns with a rig that spins before it drives', None, None),
    'start_max_translation_std_m': (0.02, '... when the fitted translation\'s std is below this (m)', 1e-4, 1.0),
    'rig_rotation_scale': (True, 'without stereo, floor or wheel: measure the map scale from the rig\'s rotation (rig_scale over windows of frames) and rescale the map (scale_state)', None, None),
    'scale_unknown_relative_std': (1.0, 'without stereo, floor or wheel: the map scale\'s relative std before the rig has turned (scale_state; /odom\'s position covariance carries it)', 1e-3, 100.0),
    'scale_from_tracks': (True, 'without stereo, floor or wheel: measure the map scale from the quarters\' tracks (their bearings) between two frames of a turn, all cameras at once (rig_motion_fit), independent of the map; without tracks, from the cameras\' own motions over windows of frames', None, None),
    'scale_pair_rotation_rad': (0.05, 'scale_state: a scale observation from the tracks spans at least this much body rotation (the lever arms\' signal)', 0.005, 1.0),
    'scale_pair_max_frames': (4, 'scale_state: ... over at most this many frames (tracks must last)', 1, 10),
    'scale_pair_std': (0.1, 'scale_state: relative std of one scale observation from the tracks, the same for all (what per-pair observations scatter by; the fit\'s predicted std only rejects weak pairs, above scale_max_relative_std)', 1e-3, 10.0),
    'scale_window_rotation_rad': (1.0, 'scale_state: a rig-rotation scale observation spans this much body rotation (windows do not overlap)', 0.02, 3.0),
    'scale_window_max_s': (4.0, 'scale_state: ... within at most this long', 0.1, 60.0),
    'scale_snap_relative_std': (0.1, 'scale_state: the map is rescaled once the scale\'s relative std is below this', 1e-4, 1.0),
    'scale_snap_min_change': (0.01, 'scale_state: after the first rescale, rescale again when the scale moved this much (relative)', 0.0, 1.0),
    'scale_drift_per_sqrt_s': (0.01, 'scale_state: relative scale drift of a map without a scale source per sqrt(s) (the scale estimate\'s random walk)', 0.0, 1.0),
    'road_scale': (True, "over a road (the rig's floor_level false, no stereo pair): measure the map scale from each camera's road points between frames (road_plane: their depth on the road against their depth triangulated with the fused step; the road homography's step until road_pitch knows the road's normal), rescale the map (scale_state) and measure the body's speed with it (road_speed)", None, None),
    'road_twist': (True, "over a road (road_scale): each camera's motion between the two previous frames from all its tracks, rotation and direction from the essential matrix, length from the road's homography (road_motion), measures the body's twist before the cameras' poses are fused (without the road's length: the rotation only); independent of the quarters' maps, which break at car speed", None, None),
    'road_twist_direction_std_rad': (0.03, 'road_twist: std of the measured direction of travel (rad)', 1e-4, 1.0),
    'road_twist_length_std': (0.3, 'road_twist: relative std of the step length from the road (one camera, two frames)', 1e-3, 10.0),
    'road_twist_min_disagreement_deg': (0.75, "road_twist: used only where it differs from the filter's rotation by at least this per frame (deg): where the quarters' maps broke (at 5 Hz they turned 2-8 deg where a car turned 0.3); where the maps hold they measure the rotation as well and the length with it", 0.0, 45.0),
    'road_twist_min_points': (30, 'road_twist: essential-matrix inliers a camera needs', 8, 10000),
    'road_twist_min_parallax_deg': (0.3, 'road_twist: median rotation-compensated parallax a camera needs (deg; below it the direction is noise)', 0.0, 45.0),
    'road_scale_prior_std': (0.1, 'road_scale: the map scale\'s relative std at the start (the road points of one frame are metric to about the camera\'s pitch to the road)', 1e-3, 10.0),
    'road_scale_std': (0.15, 'road_scale: relative std of one observation (one camera, two frames) from the road homography (before road_pitch knows the road\'s normal)', 1e-3, 10.0),
    'road_scale_spread_factor': (1.5, 'road_scale_known_step: one observation\'s relative std is this times the spread of its tracks\' ratios (road_plane.RoadScale.relative_std), in quadrature with road_scale_std_floor; on KITTI their errors against the truth scatter 0.9-1.8 times that spread and the floor in quadrature (robust), heavy-tailed', 0.1, 100.0),
    'road_scale_std_floor': (0.03, 'road_scale_known_step: the least relative std of one observation (the road\'s normal and the camera\'s height are known to about that)', 1e-3, 1.0),
    'road_scale_drift_per_sqrt_s': (0.02, 'scale_state over a road: the map\'s scale drift per sqrt(s) (scale_drift_per_sqrt_s elsewhere); on KITTI a monocular map grows 5-15 % in 10 s, which the road observes every frame', 0.0, 1.0),
    'road_scale_snap_about': ('blend', 'scale_state over a road: rescale about `blend` (a point between the last rescale\'s centre and the pose at the last rescale, weighted by the scale\'s variance then against the drift since: the part of the error the map carried from before, the part it grew since), `origin` or `current` (as scale_snap_about)', None, None),
    'road_scale_threshold': (2.5, 'road_scale: RANSAC threshold of the road homography, in point stds', 0.5, 20.0),
    'road_pitch_from_travel': (True, "road_scale, road_twist: the road's normal square to the body's direction of travel (the median slope of the fused steps: road_pitch), not the body's z axis; a camera's pitch to the road is rarely known to a degree (KITTI's: about 1), and 1 deg moves the road's scale by 5-10 %", None, None),
    'road_pitch_window_steps': (20, "road_scale, road_twist: the road's normal square to the path the body drove over its last this many steps (odometry frame), in the body's frame by its rotation then: the body pitches 1-2 deg to the road when it brakes, which the rotation sees and the median slope of the steps in the body's own frame (road_pitch_from_travel) does not; 0: that median alone", 0, 300),
    'road_scale_measured_step': (True, "road_scale_known_step: the step's rotation and direction from the rig's motion measured on all cameras' tracks (road_twist's rig_motion), and the road's normal square to the median direction of the last road_scale_measured_window such steps, instead of the fused poses and the fused path's normal: an observation moves by about 2 cot(a) per radian of the camera's pitch to the road (2 % per 0.1 deg for a point 10 deg below the horizon), and a fused path that drifted in a turn tilts both together (KITTI 07's image halves read 3 % low)", None, None),
    'road_scale_measured_window': (5, "road_scale_measured_step: the road's normal from the median pitch of this many measured steps (one step's direction scatters)", 1, 100),
    'road_scale_known_step': (True, "road_scale: the fused step between the frames made metric by the road's depth of its road tracks against their depth triangulated with that step (road_plane.road_scale: one unknown, once road_pitch_from_travel knows the road's normal), not the road homography's own step (eight unknowns: 2-3 times the scatter)", None, None),
    'road_scale_first_snap_known_step': (True, "road_scale_known_step: the first rescale (about the odom origin: the whole path so far) waits for the first observation from the known step (once the road's normal is known), unless the road homography's steps moved the scale by more than road_scale_std already; from those steps alone it followed one or two observations that scatter 15-50 %", None, None),
    'road_speed': (True, "road_scale: the metric step of the last road observation (the cameras' median) measures the body's forward speed every frame, as a wheel would; the rescales of the map alone left KITTI 07's scale 20 % long after a turn", None, None),
    'road_speed_std': (0.05, 'road_speed: relative std of that speed', 1e-3, 10.0),
    'road_scale_min_step_m': (0.1, 'road_scale: shorter camera steps observe nothing (points above the road move as it does)', 1e-3, 10.0),
    'scale_snap_about': ('origin', 'scale_state: rescale the map about the odom origin (`origin`: past and future odometry at one scale, a jump now), the current pose (`current`: no jump, a kink) or `blend` (road_scale_snap_about)', None, None),
}


def default_params() -> Dict[str, object]:
    return {k: v[0] for k, v in PARAMETERS.items()}


@dataclass
class FusedEstimate:
    stamp_ns: int
    T_odom_base: np.ndarray
    pose_covariance: np.ndarray            # 6x6, se3 convention (odom)
    twist: np.ndarray                      # (vx, vy, vz, wx, wy, wz) in base_link
    twist_covariance: np.ndarray           # 6x6
    state: str                             # one of FUSED_STATES
    scale_observed: bool = False
    scale_source: str = 'landmarks'        # 'rig' | 'wheel' | 'landmarks' | 'none'
    scale_ratio: Optional[float] = None    # rig-observed / estimated translation (diagnostic)
    scale_fixed_by: str = 'none'           # scale_state.SOURCES
    scale_relative_std: float = 0.0        # the map scale's relative std (scale_state)
    odom_covariance: Optional[np.ndarray] = None   # /odom's: pose_covariance + the scale's share
    cameras_used: List[str] = field(default_factory=list)
    cameras_rejected: Dict[str, str] = field(default_factory=dict)
    cameras_missing: List[str] = field(default_factory=list)     # in the rig, no estimate or uninformative
    ekf_d2: Optional[float] = None         # Mahalanobis^2 of the fused camera pose vs prediction
    # the twist (and covariance) early cameras were moved to stamp_ns with (free-running cameras)
    shift_twist: Optional[np.ndarray] = None
    shift_twist_covariance: Optional[np.ndarray] = None


def _movable_start(t0: np.ndarray) -> np.ndarray:
    """A rig-motion fit's start translation: t0, or a small one the fit can move from where
    t0 is (nearly) zero."""
    return t0 if np.linalg.norm(t0) >= 1e-3 else np.array([1e-2, 0.0, 0.0])


class GeneralFusion:
    def __init__(self, rig: Rig, params: Optional[Mapping[str, object]] = None):
        self.rig = rig
        self.params = default_params()
        for k, v in (params or {}).items():
            if k not in PARAMETERS:
                raise ValueError(f'unknown general-fusion parameter {k!r}')
            self.params[k] = v
        self.reset()

    def reset(self):
        p = self.params
        self.ekf = BodyEKF(BodyEkfParams(accel_noise=p['accel_noise'], angular_accel_noise=p['angular_accel_noise'],
                                         initial_twist_std=p['initial_twist_std'], max_dt=p['max_dt'],
                                         arc_integration=p['arc_integration'],
                                         gyro_bias_std=p['gyro_bias_std'], gyro_bias_walk=p['gyro_bias_walk']),
                           gyro_bias=self.wants_imu())
        self.ekf.reinitialize(np.eye(4), np.eye(6) * p['initial_pose_std'] ** 2)
        self.imu = (ImuBuffer(self.rig.imu.rotation, p['imu_gyro_variance'],
                              translation=self.rig.imu.translation, accel_variance=p['imu_accel_variance'])
                    if self.wants_imu() else None)
        # (each limit is the parameter imu_<its name>)
        self.imu_health = (ImuHealth(self.rig.imu.frame_id, ImuHealthLimits(
            **{f.name: p[f'imu_{f.name}'] for f in fields(ImuHealthLimits)}))
            if self.imu is not None else None)
        self.gyro_used = False         # this frame step follows the gyro (imu_health says it may)
        self.lone_rotations = 0        # lone cameras' track rotations used (diagnostics)
        self.bias_fixes = 0            # gyro bias measurements from the tracks used (diagnostics)
        self._bias_frames_skipped = 0  # frames since the last bias fit, while the bias is settled
        self.gravity_fixes = 0         # frame steps whose accelerometer measured up (diagnostics)
        self._twist_before: Optional[Tuple[int, np.ndarray]] = None   # (stamp, v) at the last step
        self.last_stamp_ns: Optional[int] = None
        self.wheel_used_ns: Optional[int] = None       # the stamp of the last wheel reading applied
        self.last_support_ns: Optional[int] = None     # last camera update or wheel prior
        self.has_tracked = False       # a camera fix, or (start_from_tracks) a twist from the tracks
        self.camera_fixed = False      # a camera fix
        self.first_fix_ns: Optional[int] = None    # the first camera fix's stamp
        self.frames = deque(maxlen=2)  # (stamp, {camera: its stamp}) of the last frames
        self.rejections = 0
        self.wheel_seen = False
        self.last_T: np.ndarray = np.eye(4)
        self.last_scale: Optional[RigScaleResult] = None
        self.wheel_seen = False
        self.scale = ScaleState(self.rig, self.params)

    # -------------------------------------------------------------- IMU
    def wants_imu(self) -> bool:
        """Whether the rig's IMU's gyro is fused (imu_buffer, body_ekf gyro_bias)."""
        return bool(self.params['use_imu'] and getattr(self.rig, 'imu', None) is not None)

    def add_imu(self, stamp_ns: int, gyro, gyro_covariance=None, frame_id: Optional[str] = None,
                accel=None, accel_covariance=None) -> Optional[str]:
        """One IMU sample (gyro in the frame it names, rad/s; frame_id None: the rig's IMU
        frame; the accelerometer's specific force, m/s^2, None without one); returns why it
        was refused. Every sample tells the IMU's health."""
        if self.imu is None:
            return None
        frame_id = self.rig.imu.frame_id if frame_id is None else frame_id
        if frame_id != self.rig.imu.frame_id:
            refused = (f'sample in frame {frame_id!r}, the rig\'s IMU is {self.rig.imu.frame_id!r}: '
                       'sample not used')
        else:
            refused = self.imu.add(stamp_ns, gyro, gyro_covariance, accel, accel_covariance)
        self.imu_health.sample(stamp_ns, frame_id, gyro, refused)
        return refused

    def gyro_steer_bias(self) -> Optional[np.ndarray]:
        """For the quarters (gyro_steer): the gyro bias (base_link, rad/s) as of the last
        step, while the gyro carries the steps; None when it does not (no IMU, or a bad one)."""
        if self.imu is None or not self.gyro_used or self.ekf.gyro_bias is None:
            return None
        return np.array(self.ekf.gyro_bias, float)

    def imu_settled(self, stamp_ns: int) -> bool:
        """The IMU's samples cover the time up to stamp_ns, or it is silent, or it is heard
        there with samples that were refused (always, without an IMU)."""
        if self.imu is None or self.imu.settled(stamp_ns) or self.imu_health.silent:
            return True
        heard = self.imu_health.last_heard_ns
        return heard is not None and heard >= stamp_ns

    def _refused(self) -> bool:
        """Counts a frame whose cameras the filter refused; True once max_consecutive_rejections
        came in a row: the filter, not the cameras, is most likely wrong by now."""
        self.rejections += 1
        return self.rejections >= self.params['max_consecutive_rejections']

    def _cameras_settled(self, stamp_ns: int, key: str = 'gyro_bias_settle_s') -> bool:
        """Whether the cameras' fixes (or, key gyro_bias_tracks_settle_s, their tracks) may tell
        the gyro bias."""
        return (self.first_fix_ns is not None
                and (stamp_ns - self.first_fix_ns) * 1e-9 >= self.params[key])

    def _predict(self, t0_ns: int, t1_ns: int):
        """The EKF from t0 to t1, its rotation following the gyro where its samples cover
        the step (else the constant twist's)."""
        gyro = self.imu.mean_rate(t0_ns, t1_ns) if self.gyro_used else None
        # (on a level floor the floor's landmarks and planar_motion hold the tilt, and the
        # accelerometer added only its bias: the accuracy matrix's mean final drift
        # 0.344 -> 0.374 % with it there)
        gravity = self.imu is not None and self.params['imu_gravity'] and not self._planar_motion()
        v_before = self.ekf.twist[:3] if gravity else None
        self.ekf.predict((t1_ns - t0_ns) * 1e-9, gyro)
        if gyro is not None:
            self.ekf.update_gyro(*gyro)
            if gravity:
                self._gravity(t0_ns, t1_ns, v_before)
        if gravity and t1_ns > t0_ns:
            self._twist_before = (t0_ns, v_before)

    def _planar_motion(self) -> bool:
        """planar_motion applies: the rig's floor is level."""
        return bool(self.params['planar_motion'] and self.rig.floor_z is not None
                    and getattr(self.rig, 'floor_level', True))

    def _gravity(self, t0_ns: int, t1_ns: int, v_before: np.ndarray) -> bool:
        """imu_gravity: the accelerometer's mean over the step, less the body's acceleration
        (w x v of the filter's twist, and the change of its velocity since the step before:
        the body's own acceleration a step late), is gravity's reaction: up."""
        m = self.imu.mean_specific_force(t0_ns, t1_ns)
        if m is None:
            return False
        f, var = m
        p = self.params
        tw = self.ekf.twist
        a_body = np.cross(tw[3:], tw[:3])
        if self._twist_before is not None and self._twist_before[0] < t0_ns:
            a_body = a_body + (v_before - self._twist_before[1]) / ((t0_ns - self._twist_before[0]) * 1e-9)
        up = f - a_body
        g = float(np.linalg.norm(up))
        if np.linalg.norm(a_body) > p['imu_gravity_max_accel'] or abs(g - STANDARD_GRAVITY) > p['imu_gravity_max_accel']:
            return False
        var = var + (STANDARD_GRAVITY * p['imu_gravity_std_rad']) ** 2
        used, _ = self.ekf.update_gravity(up, np.eye(3) * var, p['imu_gravity_gate_chi2'])
        self.gravity_fixes += int(used)
        return used

    # -------------------------------------------------------------- scale hook
    def observe_scale(self, T_prev: np.ndarray, T_now: np.ndarray,
                      camera_directions: Mapping[str, np.ndarray]) -> RigScaleResult:
        """Rig-scale observer: per-camera translation directions over [prev, now] (base_link
        at prev, up to scale), body rotation from the fused poses."""
        R, _ = relative_motion(T_prev, T_now)
        names = self.rig.names
        dirs = [camera_directions.get(n) for n in names]
        centres = [c.translation for c in self.rig.cameras]
        self.last_scale = solve_rig_translation(
            R, dirs, centres, direction_sigma_rad=self.params['scale_direction_sigma_rad'],
            min_rotation_rad=self.params['scale_min_rotation_rad'],
            max_relative_std=self.params['scale_max_relative_std'], names=names)
        return self.last_scale

    def _wheel_update(self, wheel_twist) -> bool:
        axes = (0, 1, 5) if self.params['wheel_planar_only'] else tuple(range(6))
        # (with a gyro, the wheel's speed only: its yaw rate carries the slip's bias, 4-8
        # mrad/s in the generator's, which the filter then took for the gyro's: corridor
        # heading 4.8 deg off after 20 s, final drift 5.3 %)
        axes = self._twist_axes(axes)
        used, _ = self.ekf.update_twist(wheel_twist[0], wheel_twist[1], axes, self.params['wheel_gate_chi2'])
        return used

    def _with_floor(self, estimates: Mapping[str, PoseEstimate]) -> Dict[str, PoseEstimate]:
        # A landmark's covariance holds its image-noise share only, not the error of the
        # fused poses it was triangulated from, so a camera's covariance omits that: without
        # this floor, cameras that agree to a few cm look thousands of sigmas apart after a turn.
        fm, fr = self.params['camera_floor_std_m'], self.params['camera_floor_std_rad']
        if fm == 0.0 and fr == 0.0:
            return dict(estimates)
        floor = np.diag([fm * fm] * 3 + [fr * fr] * 3)
        return {n: (replace(e, covariance=e.covariance + floor) if e.informative else e)
                for n, e in estimates.items()}

    def _to_common_time(self, stamp_ns: int, estimates: Mapping[str, PoseEstimate],
                        twist: np.ndarray, twist_cov: np.ndarray) -> Dict[str, PoseEstimate]:
        # A camera captured earlier than the frame's common time: its pose moved forward along
        # the EKF's twist (predicted to stamp_ns), its covariance grown by the twist's.
        out = {}
        for n, e in estimates.items():
            if e.stamp_ns != stamp_ns and e.informative:
                T, C = shift_pose(e.T_odom_base, e.covariance, (stamp_ns - e.stamp_ns) * 1e-9, twist,
                                  twist_cov, self.params['accel_noise'], self.params['angular_accel_noise'])
                e = replace(e, stamp_ns=stamp_ns, T_odom_base=T, covariance=C)
            out[n] = e
        return out

    def pose_at(self, fused: 'FusedEstimate', stamp_ns: int) -> Tuple[np.ndarray, np.ndarray]:
        """The fused pose and covariance moved to `stamp_ns` (a camera's own capture time in
        the frame); at the fused stamp itself, exactly the fused pose.

        Moved back with the twist the cameras were moved forward with, not the updated one: a
        camera that agrees with the fusion then gets its own pose back, whatever the twist's
        error. With the updated twist, the difference (the twist's correction times the
        offset) went into every camera's landmarks, frame after frame: under acceleration the
        odometry fell behind by centimetres a second."""
        twist = fused.shift_twist if fused.shift_twist is not None else fused.twist
        twist_cov = fused.shift_twist_covariance if fused.shift_twist is not None else fused.twist_covariance
        return shift_pose(fused.T_odom_base, fused.pose_covariance, (stamp_ns - fused.stamp_ns) * 1e-9,
                          twist, twist_cov, self.params['accel_noise'], self.params['angular_accel_noise'])

    # -------------------------------------------------------------- per frame
    def process(self, stamp_ns: int, camera_estimates: Mapping[str, PoseEstimate],
                wheel_twist: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                camera_directions: Optional[Mapping[str, np.ndarray]] = None,
                wheel_stamp_ns: Optional[int] = None) -> FusedEstimate:
        """One frame at stamp_ns (its common time; a camera estimate stamped earlier is moved
        to it). wheel_twist = (twist 6, covariance 6x6) in base_link, or None.
        camera_directions: optional per-camera translation directions since the last frame.
        wheel_stamp_ns: the wheel reading's stamp; one between the last frame and this one
        (free-running cameras: the wheel ticks with the frame's first capture) is applied
        at its own time, before the cameras."""
        p = self.params
        wheel_used = False
        camera_stamps = {n: e.stamp_ns for n, e in camera_estimates.items()}
        if self.imu_health is not None:
            # (the previous frame pair's bias, while gyro_used still says whether the gyro
            # carried that pair)
            self._gyro_bias_from_tracks(stamp_ns)
            # A bad IMU (imu_health): this step without the gyro, as without an IMU; the
            # bias estimate is passed even while frozen, so a drifted one keeps it out.
            self.gyro_used = self.imu_health.check(stamp_ns, self.ekf.gyro_bias)
        if wheel_stamp_ns is not None:
            if self.wheel_used_ns is not None and wheel_stamp_ns <= self.wheel_used_ns:
                # Each reading once: cameras at their own stamps come several times per wheel
                # tick, and the same reading applied at each was 4-fold confident and stale.
                wheel_twist = None
            elif wheel_twist is not None:
                self.wheel_used_ns = wheel_stamp_ns
        wheel_first = (wheel_twist is not None and wheel_stamp_ns is not None
                       and self.last_stamp_ns is not None
                       and self.last_stamp_ns < wheel_stamp_ns < stamp_ns)
        if wheel_first:
            # Why: applied at the frame's latest stamp, a wheel speed 24 ms old under 1.5 m/s^2
            # slowed every prediction, and the fused poses fed back carried it into the maps.
            self._predict(self.last_stamp_ns, wheel_stamp_ns)
            wheel_used = self._wheel_update(wheel_twist)
            self._predict(wheel_stamp_ns, stamp_ns)
        elif self.last_stamp_ns is not None:
            self._predict(self.last_stamp_ns, stamp_ns)   # dt <= 0 is a no-op
        step_s = 0.0 if self.last_stamp_ns is None else (stamp_ns - self.last_stamp_ns) * 1e-9
        self.last_stamp_ns = stamp_ns if self.last_stamp_ns is None else max(stamp_ns, self.last_stamp_ns)
        T_prev = self.last_T

        road_twists = self._road_twist() if self.has_tracked else 0
        # A camera alone at its stamp (free-running cameras, each fused at its own capture
        # time): a median of it and the prediction cannot out-vote either, and gating it on its
        # own covariance rejected it whenever the prediction erred (in turns); the EKF's gate
        # weighs both.
        alone = self._alone(camera_estimates)
        if alone and self.has_tracked and p['lone_camera_track_rotation']:
            # (before the fix: the rotation corrects the prediction the fix is gated against)
            self._lone_track_rotation(next(iter(camera_estimates)), stamp_ns)
        prior = (self.ekf.T, self.ekf.pose_covariance) if (p['median_use_prior'] and self.has_tracked
                                                           and not alone) else None
        shift_twist = (self.ekf.twist, self.ekf.twist_covariance)
        camera_estimates = self._with_floor(self._to_common_time(stamp_ns, camera_estimates, *shift_twist))

        def median(prior):
            return median_filter(dict(camera_estimates), p['median_mahalanobis_gate'], p['median_max_translation_m'],
                                 p['median_max_rotation_rad'], prior, p['median_prior_max_cameras'],
                                 p['median_weighted'])

        med = median(prior)
        restart = False
        if prior is not None and med.T_median is not None and not med.inliers and self._refused():
            # Every camera out-voted by the prediction (one or two cameras, where the prediction
            # ties them) is a fix the filter refused, as one its gate refuses: counted alike,
            # the filter is re-initialised on the cameras alone. Without it, a prediction that
            # dead-reckoned a car through an acceleration fell farther behind each frame and
            # shut its one camera out for good (KITTI 07 at 5 Hz: 17 frames, drift 12 %).
            med = median(None)
            restart = bool(med.inliers)
        out_rejected = dict(med.rejected)
        missing = sorted(set(self.rig.names) - set(camera_estimates)) + sorted(med.uninformative)
        used: List[str] = []
        d2 = None
        camera_update = False
        # Without a scale source the first fix comes from the quarters' two-view geometry,
        # whose direction of travel one quarter alone can get wrong (a narrow view confuses
        # sideways travel with a turn): the rig starts once enough cameras agree.
        start_ok = (self.camera_fixed or len(med.inliers) >= p['start_min_cameras']
                    or metric_source(self.rig, self.wheel_seen or wheel_twist is not None) is not None)
        if med.inliers and start_ok:
            names = sorted(med.inliers)
            ests = [med.inliers[n] for n in names]
            T_f, cov_f = information_fusion([e.T_odom_base for e in ests], [e.covariance for e in ests], med.T_median)
            cov_f = condition_covariance(cov_f * (1.0 + (len(ests) - 1) * p['camera_correlation'])
                                         * (p['lone_camera_covariance_scale'] if alone else 1.0))
            if restart:
                self.ekf.reinitialize(T_f, cov_f, twist=self.ekf.twist)
                camera_update, d2 = True, 0.0
            elif not self.has_tracked:
                # first fix: the cameras define the pose (odom origin was the start)
                twist_cov = None
                if getattr(self.rig, 'metric_source', None) is not None and not self.wheel_seen and wheel_twist is None:
                    twist_cov = np.diag([p['start_speed_std'] ** 2] * 3
                                        + [p['initial_twist_std'] ** 2] * 3)
                self.ekf.reinitialize(T_f, cov_f, twist_cov=twist_cov)
                camera_update, d2 = True, 0.0
            else:
                # the cameras tell the gyro's bias once settled and while the gyro is used
                # (out, its bias is frozen: it no longer moves the pose); with
                # gyro_bias_from_tracks the tracks do, not the fixes (a spin's fixes, off by
                # tenths of a degree, pulled the bias the wrong way)
                settled = self.gyro_used and self._cameras_settled(stamp_ns)
                tell_bias = settled and not self._bias_from_tracks()
                innovation = (self.ekf.pose_innovation(T_f, cov_f)
                              if alone or (settled and step_s > 0) else None)
                # the innovation test of imu_health: where the fix turns against the gyro
                residual = (self.ekf.T[:3, :3].T @ innovation[0][3:]
                            if settled and step_s > 0 else None)
                if alone and innovation[1] > p['lone_camera_robust_chi2']:
                    cov_f = cov_f * np.sqrt(innovation[1] / p['lone_camera_robust_chi2'])
                camera_update, d2 = self.ekf.update_pose(T_f, cov_f, p['ekf_gate_chi2'],
                                                         learn_bias=tell_bias)
                if camera_update and residual is not None:
                    # (fixes the gate refuses are the cameras' outliers, not the gyro's)
                    self.imu_health.camera_residual(stamp_ns, residual, step_s,
                                                    np.linalg.norm(self.ekf.twist[3:]) * step_s)
                if not camera_update and self._refused():
                    self.ekf.reinitialize(T_f, cov_f, twist=self.ekf.twist)
                    camera_update = True
            if camera_update:
                used = names
                self.rejections = 0
                self.has_tracked = self.camera_fixed = True
                if self.first_fix_ns is None:
                    self.first_fix_ns = int(stamp_ns)
            else:
                for n in names:
                    out_rejected[n] = f'fused pose gated out by the EKF (mahalanobis {d2:.1f})'

        # (only where the cameras gave nothing: with their fix as well, the loop's scale read
        # 6 % short; the tracks' twist and the cameras' poses come from the same images)
        tracks_update = (not camera_update and wheel_twist is None
                         and p['start_from_tracks'] and self._bearings_for_scale() and not self.wheel_seen
                         and self._twist_from_tracks())
        if tracks_update:
            self.has_tracked = True
        # The wheel twist after the camera update (applying it at mid-step, trapezoidally,
        # was tried: it lags less in turns but spin_then_drive's scale went to -12 %).
        if wheel_twist is not None and not wheel_first:
            wheel_used = self._wheel_update(wheel_twist)
        self.wheel_seen = self.wheel_seen or wheel_twist is not None
        if self._planar_motion():
            # Why: the cameras measure the body's climb and tilt as freely as its travel, and
            # with floor landmarks (ground_plane) a pitch error tilts the floor they are put on;
            # the two fed each other, 0.2 m of height drift over 9 m in spin_then_drive.
            sd = p['planar_twist_std']
            self.ekf.update_twist(np.zeros(6), np.eye(6) * sd * sd, axes=(2, 3, 4))

        if camera_update or wheel_used or tracks_update or road_twists:
            self.last_support_ns = stamp_ns
        if camera_update or tracks_update or road_twists:
            state = 'tracking'
        elif not self.has_tracked:
            state = 'initializing'
        elif (self.last_support_ns is not None
              and (stamp_ns - self.last_support_ns) * 1e-9 <= p['lost_timeout_s']):
            state = 'dead_reckoning'
        else:
            state = 'lost'

        fixed_by, scale_std, odom_cov = self._scale_step(stamp_ns, wheel_used, camera_update,
                                                         {n: med.inliers[n].T_odom_base for n in used},
                                                         camera_stamps)
        # road_speed: the road's metric step of the last frame pair as a forward speed, as a
        # wheel's (one frame late: at 10 Hz a car's speed changes by 1-2 % in that time)
        if self.params['road_speed'] and fixed_by == 'road' and self.scale.road_step is not None:
            step, dt = self.scale.road_step
            self.scale.road_step = None
            if dt > 0 and abs(step[0]) > self.params['road_scale_min_step_m']:
                v = step / dt
                sd = self.params['road_speed_std'] * abs(v[0])
                self.ekf.update_twist(np.r_[v, np.zeros(3)], np.eye(6) * sd * sd, axes=(0,),
                                      gate_chi2=self.params['ekf_gate_chi2'])
        T_now = self.ekf.T
        scale_ratio = None
        scale_source = 'wheel' if wheel_used else ('landmarks' if self.has_tracked else 'none')
        rig_observed = False
        if camera_directions:
            r = self.observe_scale(T_prev, T_now, camera_directions)
            rig_observed = r.observed
            if r.observed:
                scale_source = 'rig'
                scale_ratio = scale_correction(relative_motion(T_prev, T_now)[1], r)
        self.last_T = T_now
        self.frames.append((int(stamp_ns), camera_stamps))
        if alone and p['lone_camera_track_rotation']:
            # (the first fix or a restart: the filter began here, with no clones)
            self._keep_lone_clone(next(iter(camera_estimates)), stamp_ns)
        return FusedEstimate(
            stamp_ns=stamp_ns, T_odom_base=T_now, pose_covariance=self.ekf.pose_covariance,
            twist=self.ekf.twist, twist_covariance=self.ekf.twist_covariance, state=state,
            scale_observed=bool(rig_observed or wheel_used), scale_source=scale_source,
            scale_ratio=scale_ratio, cameras_used=used, cameras_rejected=out_rejected,
            cameras_missing=missing, ekf_d2=d2, shift_twist=shift_twist[0],
            shift_twist_covariance=shift_twist[1], scale_fixed_by=fixed_by,
            scale_relative_std=scale_std,
            odom_covariance=self.ekf.pose_covariance if odom_cov is None else odom_cov)

    def _scale_step(self, stamp_ns, wheel_used, camera_update, camera_poses, camera_stamps):
        """scale_state's part of a frame: (source, relative std, /odom covariance or None).
        Nothing here touches the estimate while stereo, floor or wheel fix the scale."""
        self.wheel_seen = self.wheel_seen or wheel_used
        other = metric_source(self.rig, self.wheel_seen)
        road = self.rig.road_scale and self.params['road_scale'] and not self.wheel_seen
        if other is not None and not road:
            return other, 0.0, None
        sc = self.scale
        c = sc.pending
        if sc.apply_pending(stamp_ns, self.ekf, self):
            # this frame's cameras were measured before the quarters rescaled
            for n, T in camera_poses.items():
                T = T.copy()
                T[:3, 3] = scale_positions(T[:3, 3], c.factor, c.centre)
                camera_poses[n] = T
        if camera_update and (self.params['rig_rotation_scale'] or road):
            sc.observe(stamp_ns, self.ekf.T, camera_poses, camera_stamps)
            sc.decide(stamp_ns, self.ekf.T)
        fixed_by = ('road' if road else 'rig rotation') if sc.observed else ('floor' if road else 'none')
        return fixed_by, sc.relative_std, sc.odom_covariance(self.ekf.T, self.ekf.pose_covariance)

    def _twist_from_tracks(self) -> bool:
        """On a frame without a camera fix: the rig's motion between the two previous frames
        from the quarters' tracks (this frame's may still be on their way), as a twist
        measurement when it is metric: rotated scale_pair_rotation_rad, its translation known
        to start_max_translation_std_m. A rig spinning in place has no two-view start (no
        parallax), but its cameras' centres move on the lever arms, and that is metric."""
        if len(self.frames) < 2:
            return False
        p = self.params
        (s0, c0), (s1, c1) = self.frames
        dt = (s1 - s0) * 1e-9
        if dt <= 0.0:
            return False
        cams = self.scale.tracks_between(c0, c1, s0, s1)
        twist = self.ekf.twist
        fit = fit_rig_motion(se3.rotvec_to_R(twist[3:] * dt), self._fit_start(dt), cams)
        self.scale.last_fit = fit
        if not fit.ok:
            return False
        rotvec = se3.R_to_rotvec(fit.R)
        C = fit.covariance
        if (np.linalg.norm(rotvec) < p['scale_pair_rotation_rad']
                or np.sqrt(np.trace(C[3:, 3:])) > p['start_max_translation_std_m']):
            return False
        vw = [3, 4, 5, 0, 1, 2]     # the fit's (rotation, t) -> the twist's (v, w)
        cov = C[np.ix_(vw, vw)]
        # x4: single fits scatter about twice their predicted std (docs/fusion.md, scale)
        used, _ = self.ekf.update_twist(np.r_[fit.t, rotvec] / dt, 4.0 * cov / dt ** 2,
                                        axes=self._twist_axes((0, 1, 2, 3, 4, 5)))
        return used

    def _lone_track_rotation(self, name: str, stamp_ns: int) -> bool:
        """lone_camera_track_rotation: camera `name`'s rotation from its previous frame to this
        one (stamp_ns) fitted to its tracks, between the pose clones at those stamps: this
        stamp's clone is the prediction, so the rotation corrects the turn's rate at once."""
        self._keep_lone_clone(name, stamp_ns)
        held = self._clone_stamps(name)
        if len(held) < 2:
            return False
        s0, s1 = held[-2], held[-1]
        cams = self.scale.tracks_between({name: s0}, {name: s1}, s0, s1)
        if not cams:
            return False
        Ta, Tb = self.ekf.clone_T((name, s0)), self.ekf.clone_T((name, s1))
        fit = refine_rig_motion(Ta[:3, :3].T @ Tb[:3, :3],
                                _movable_start(Ta[:3, :3].T @ (Tb[:3, 3] - Ta[:3, 3])), cams)
        if not fit.ok:
            return False
        used, _ = self.ekf.update_relative_rotation((name, s0), (name, s1), fit.R,
                                                    self.params['lone_track_rotation_cov_scale'] * fit.covariance[:3, :3],
                                                    gate_chi2=self.params['ekf_gate_chi2'])
        self.lone_rotations += int(used)
        return used

    def _keep_lone_clone(self, name: str, stamp_ns: int) -> None:
        """A clone of the pose at camera `name`'s stamp, and of its previous one."""
        if (name, int(stamp_ns)) not in self.ekf.clone_keys:
            self.ekf.clone_pose((name, int(stamp_ns)))
        for older in self._clone_stamps(name)[:-2]:
            self.ekf.drop_clone((name, older))

    def tracks_settled(self, stamp_ns: int, cameras) -> bool:
        """Whether a frame of `cameras` can be fused as far as the tracks go: a camera fused
        alone (lone_camera_track_rotation) waits for its quarters' tracks of that stamp (as
        many quarters as sent them at its previous frame); a lockstep replay then fuses what
        the sequential pipeline does, whichever message the executor took first."""
        if not (self._alone(cameras) and self.params['lone_camera_track_rotation'] and self.has_tracked):
            return True
        return self.scale.tracks_complete(next(iter(cameras)), int(stamp_ns))

    def _alone(self, cameras) -> bool:
        """Whether `cameras` (one frame's) is one camera of a rig of several: a free-running
        camera fused at its own stamp (process() and the wait for its tracks decide alike)."""
        return len(cameras) == 1 and len(self.rig.names) > 1

    def _clone_stamps(self, name: str) -> List[int]:
        """The stamps of camera `name`'s pose clones in the body EKF, oldest first."""
        return [s for n, s in self.ekf.clone_keys if n == name]

    def _fit_start(self, dt: float) -> np.ndarray:
        """The filter's translation over dt, a start for the rig-motion fits."""
        return _movable_start(self.ekf.twist[:3] * dt)

    def _twist_axes(self, axes):
        """The axes of a twist measurement (the wheel's, or the tracks' of the previous frame
        pair) to use: while the gyro is used, not its rotation (the tracks', a frame late, read
        the gyro's rate minus the step's change as a bias of 0.09 rad/s at the start of a spin)."""
        return tuple(a for a in axes if a < 3) if self.gyro_used else tuple(axes)

    def _road_twist(self) -> int:
        """road_twist: every camera's motion between the two previous frames (this frame's
        tracks may still be on their way) as a twist measurement. Returns how many were used."""
        p = self.params
        if not (p['road_twist'] and self.rig.road_scale and self._bearings_for_scale()) or len(self.frames) < 2:
            return 0
        (s0, c0), (s1, c1) = self.frames
        dt = (s1 - s0) * 1e-9
        if dt <= 0.0:
            return 0
        tracks, motions = [], []
        up = self.scale.road_up(s0)
        for cam, tr in zip(self.rig.cameras, self.scale.tracks_between(c0, c1, s0, s1, by_camera=True)):
            if tr is None:
                continue
            sigma = float(np.median(tr.sigma))
            m = camera_motion(tr, up, self.rig.floor_z, 2.0 * sigma,
                              p['road_twist_min_points'], p['road_twist_min_parallax_deg'],
                              p['road_scale_threshold'] * sigma, p['road_scale_min_step_m'])
            tracks.append(tr)
            if m is not None:
                motions.append((tr, m))
        prior = se3.make_T(se3.rotvec_to_R(self.ekf.twist[3:] * dt), self.ekf.twist[:3] * dt)
        motion = rig_motion(tracks, motions, prior, p['road_twist_min_points'])
        if motion is None:
            return 0
        self.scale.measured_step = (s0, s1, motion.R, motion.t)
        twist, cov = body_twist(motion, dt, p['road_twist_direction_std_rad'], p['road_twist_length_std'])
        if np.linalg.norm(twist[3:] - self.ekf.twist[3:]) * dt < np.radians(p['road_twist_min_disagreement_deg']):
            return 0
        # without the road's length, the rotation only: a direction with a length from the
        # filter's own speed held a car that started at rest at rest
        axes = self._twist_axes((0, 1, 2, 3, 4, 5) if motion.length_known else (3, 4, 5))
        if not axes:
            return 0
        ok, _ = self.ekf.update_twist(twist, cov, axes=axes, gate_chi2=p['ekf_gate_chi2'])
        return int(ok)

    def _bearings_for_scale(self) -> bool:
        """Whether the scale is measured from the quarters' tracks: without stereo and floor
        (and wheel, once one is seen), or over a road."""
        if self.rig.road_scale:
            return bool(self.params['road_scale'])
        return bool(self.params['rig_rotation_scale'] and self.params['scale_from_tracks']
                    and metric_source(self.rig, False) is None)

    def _lone_rotations(self) -> bool:
        """lone_camera_track_rotation on a rig of several cameras: whether they are free-running
        shows only in their stamps, and their tracks are wanted from the first frame on."""
        return len(self.rig.names) > 1 and bool(self.params['lone_camera_track_rotation'])

    def _bias_from_tracks(self) -> bool:
        return self.wants_imu() and bool(self.params['gyro_bias_from_tracks'])

    def wants_bearings(self) -> bool:
        """Whether the quarters' tracks can tell this fusion anything: the scale (above),
        with a gyro its bias (gyro_bias_from_tracks), on a rig of several cameras the rotation
        of each one fused alone at its stamp (lone_camera_track_rotation)."""
        return self._bearings_for_scale() or self._bias_from_tracks() or self._lone_rotations()

    def add_bearings(self, camera: str, quarter: int, stamp_ns: int, ids, xy, sigma):
        """A quarter's tracks at one of its frames (normalised points and their std), for the
        scale from the rig's motion, the gyro's bias and free-running cameras' rotations;
        taken from the frame after it on."""
        for_scale = (self._bearings_for_scale() and not self.wheel_seen) or self._bias_from_tracks()
        if for_scale or self._lone_rotations():
            self.scale.add_bearings(camera, quarter, stamp_ns, ids, xy, sigma, for_scale=for_scale)

    def _gyro_bias_from_tracks(self, stamp_ns: int) -> bool:
        """gyro_bias_from_tracks: the rig's rotation between the two previous frames from all
        cameras' tracks (this frame's may still be on their way) against the gyro's mean rate
        over the same frames: a measurement of the bias alone, from image measurements alone.
        Why not the bias from the fused poses: their errors in a spin (tenths of a degree
        between frames while the quarters' maps break) went into it (spin_then_drive seed 8:
        +1.5 mrad/s where the truth is -3.7). Once the cameras have settled
        (gyro_bias_settle_s)."""
        p = self.params
        if (not (self.gyro_used and self._bias_from_tracks()
                 and self._cameras_settled(stamp_ns, 'gyro_bias_tracks_settle_s'))
                or len(self.frames) < 2):
            return False
        if self._bias_settled() and self._bias_frames_skipped + 1 < p['gyro_bias_tracks_settled_every']:
            self._bias_frames_skipped += 1
            return False
        self._bias_frames_skipped = 0
        (s0, c0), (s1, c1) = self.frames
        dt = (s1 - s0) * 1e-9
        gyro = self.imu.mean_rate(s0, s1) if dt > 0.0 else None
        if gyro is None:
            return False
        cams = self.scale.tracks_between(c0, c1, s0, s1)
        if not cams:
            return False
        rate, rate_cov = gyro
        # Only while the body travels more than its cameras swing on their lever arms: in a
        # spin in place every camera moves sideways, along its epipolar lines, where a yaw
        # error does not show (spin_then_drive: fits 0.5-8 % off the rate, all one way)
        lever = max(float(np.linalg.norm(c.centre)) for c in cams)
        speed = float(np.linalg.norm(self.ekf.twist[:3]))
        if speed < p['gyro_bias_tracks_min_travel'] * float(np.linalg.norm(rate - self.ekf.gyro_bias)) * lever:
            return False
        # from the gyro's own rotation, not less the filter's bias: a measurement of the bias
        # that does not start from the estimate it corrects
        fit = refine_rig_motion(se3.rotvec_to_R(rate * dt), self._fit_start(dt), cams)
        if not fit.ok:
            return False
        bias = rate - se3.R_to_rotvec(fit.R) / dt
        cov = p['gyro_bias_tracks_inflation'] * fit.covariance[:3, :3] / dt ** 2 + rate_cov
        used, _ = self.ekf.update_gyro_bias(bias, cov, p['gyro_bias_tracks_gate_chi2'])
        self.bias_fixes += int(used)
        return used

    def _bias_settled(self) -> bool:
        """The filter's gyro bias is known to gyro_bias_tracks_settled_std (every axis)."""
        C = self.ekf.gyro_bias_covariance
        limit = self.params['gyro_bias_tracks_settled_std']
        return C is not None and limit > 0.0 and float(np.max(np.diag(C))) < limit * limit

    @property
    def map_scale_command(self):
        """The latest map rescale (camera_pose_nodes/map_scale), None before any."""
        return self.scale.command

    def road_normal(self, stamp_ns: int) -> Optional[np.ndarray]:
        """The road's normal (up, base_link) at frame stamp_ns for the quarters' road points
        (QuarterEstimator.add_road_normal): the road scale's own (road_pitch), once the direction
        of travel is known; None before, and off a road (the body's z then)."""
        travel = self.scale.travel_pitch           # (None off a road)
        if travel is None or travel.pitch_rad is None:
            return None
        return self.scale.road_up(stamp_ns)
