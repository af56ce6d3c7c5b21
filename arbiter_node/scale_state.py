"""The map's scale as part of the general arbiter's state (ROS-free).

Which source fixes the scale: stereo (the rig names stereo_pairs), the floor (the rig's
floor_z: the quarters put floor landmarks at metric depth), the wheel (its twist prior), else
the rig's rotation (rig_scale: in a turn, the cameras' translation directions and their metric
lever arms give the body's metric translation) and, before the first turn, none: the map is
then in the quarters' two-view gauge (camera_pose_nodes/two_view) and its scale unknown.

Only without stereo, floor and wheel does this state act: it keeps the log of the factor that
takes the map to metres, x = log k, with its variance P (P = 1: unknown). Observations of k,
in turns only (the lever arms carry the scale):
- from the quarters' tracks (`scale_from_tracks`, once bearings come in): every pair of fused
  frames over which the body turned `scale_pair_rotation_rad`, the rig's motion fitted to all
  cameras' tracks between them (rig_motion_fit) against the fused translation; independent
  of the map;
- without tracks, every window of frames over which the body turned
  `scale_window_rotation_rad` (rig_scale.solve_rig_translation on the cameras' own motions
  against the fused translation over the window; those motions follow the map, so it sees
  only part of the map's scale error). Once P is small enough the map is rescaled (the "snap"): a
MapScaleCommand multiplies every position by k, from the next frame, in the general arbiter
and in every quarter (camera_pose_nodes/map_scale), and x returns to 0 with P kept. Later
turns keep tightening P and snap again when the factor has moved `scale_snap_min_change` (and one std); the map's own
scale drift (`scale_drift_per_sqrt_s`) keeps P from shrinking to nothing, so later turns
still correct it.

/odom's position covariance carries the scale's uncertainty: P p p^T added for the position
p (about the rescale centre), so it is as large as the distance travelled along the travel
while the scale is unknown.
"""
import math
from collections import deque
from typing import Dict, List, Optional

import numpy as np

from arbiter_node.rig_motion_fit import CameraTracks, fit_rig_motion
from arbiter_node.rig_scale import relative_motion, scale_correction, solve_rig_translation
from arbiter_node.road_pitch import PathNormal, TravelPitch
from camera_pose_nodes.road_plane import camera_over_road, camera_step, fit_road, road_region, road_scale
from camera_pose_nodes.map_scale import MapScaleCommand, rescale_filter, scale_positions
from multicam_ego_motion.geometry import se3

SOURCES = ('none', 'rig rotation', 'road', 'floor', 'wheel', 'stereo')
BEARING_STAMPS_KEPT = 12      # per camera: a pair spans at most scale_pair_max_frames + 1
# per camera in a pickled state (the general arbiter's snapshot after every update, for a
# restore after a crash): the last two frames' tracks carry the next rotation fit and the wait
# for tracks; all twelve cost 2.3 ms a pickle (~300 kB of small arrays, four free-running
# cameras at 15 Hz: 60 snapshots a second, 15 % of the arbiter's worker's time). Older pairs come back
# within a few frames after a restore.
SNAPSHOT_BEARING_STAMPS = 2


def metric_source(rig, wheel_seen: bool) -> Optional[str]:
    """The scale source other than the rig's rotation, or None."""
    return rig.metric_source or ('wheel' if wheel_seen else None)


def rescale_body_ekf(ekf, k: float, centre):
    """BodyEKF: position about centre, linear velocity (base_link) and their covariance by k."""
    rescale_filter(ekf.kf, k, centre)


class ScaleState:
    def __init__(self, rig, params: dict):
        self.rig = rig
        self.p = params
        self.x = 0.0                                   # log of map -> metric factor
        self.P = float(params['scale_unknown_relative_std']) ** 2
        self.observed = False                          # rig rotation has observed it
        self.epoch = 0
        self.command: Optional[MapScaleCommand] = None  # the latest, for the quarters
        self.pending: Optional[MapScaleCommand] = None  # not yet applied here
        self.history = deque()                         # (stamp, T fused, {camera: centre in odom}, {camera: its stamp})
        self.window_start = None                       # stamp: windows do not overlap
        self.last_ratio: Optional[float] = None
        self.snapped_about = np.zeros(3)               # centre of the position covariance term
        # the last rescale's centre, its pose rescaled by it, P then and its stamp (snap_centre)
        self.last_snap = None
        # camera -> {stamp: {quarter: (ids, xy, sigma)}}: the quarters' tracks (add_bearings)
        self.bearings: Dict[str, Dict[int, dict]] = {}
        self.tracks_for_scale = False   # tracks came for the scale (add_bearings)
        self.pair_end = None                           # stamp: track pairs do not overlap
        self.last_fit = None                           # rig_motion_fit.RigMotionFit, diagnostics
        self.n_observations = 0                        # scale observations fused (diagnostics)
        self.n_road_fits = 0                           # of them from the road (diagnostics)
        self.road_step = None                          # (metric body step, dt) of the last road observation
        self.measured_step = None                      # (stamp a, stamp b, R, t): the rig's motion from its tracks
        self.known_step_observed = False               # a road_scale_known_step observation was fused
        self.measured_pitches = deque(maxlen=int(params['road_scale_measured_window']))
        self.travel_pitch = TravelPitch() if rig.road_scale and params['road_pitch_from_travel'] else None
        window = int(params['road_pitch_window_steps'])
        self.path_normal = PathNormal(window) if self.travel_pitch is not None and window > 0 else None
        if rig.road_scale:
            # the road's points are metric from the first frame, to about the camera's pitch
            self.P = float(params['road_scale_prior_std']) ** 2

    def add_bearings(self, camera: str, quarter: int, stamp_ns: int, ids, xy, sigma, for_scale: bool = True):
        """One quarter's tracks at one of its frames (normalised points, their std). A second
        message for the same frame adds to the first: the features the quarter extracted on
        that frame after it sent its tracks (QuarterEstimator.new_bearings). for_scale: the
        scale is observed on the tracks (else they are kept for the rotations of free-running
        cameras alone)."""
        if camera not in self.rig.names:
            return
        self.tracks_for_scale = self.tracks_for_scale or for_scale
        per = self.bearings.setdefault(camera, {})
        at = per.setdefault(int(stamp_ns), {})
        entry = (np.asarray(ids), np.asarray(xy, float), np.asarray(sigma, float))
        if int(quarter) in at:
            known = at[int(quarter)]
            new = ~np.isin(entry[0], known[0])      # (ids are unique per quarter and frame)
            entry = tuple(np.concatenate([a, b[new]]) for a, b in zip(known, entry))
        at[int(quarter)] = entry
        while len(per) > BEARING_STAMPS_KEPT:
            del per[min(per)]

    def __getstate__(self):
        state = dict(vars(self))
        state['bearings'] = {cam: {s: per[s] for s in sorted(per)[-SNAPSHOT_BEARING_STAMPS:]}
                             for cam, per in self.bearings.items()}
        return state

    def tracks_complete(self, camera: str, stamp_ns: int) -> bool:
        """Whether camera's tracks at stamp_ns came from every quarter that sent its tracks at
        the camera's frame before (true before it sent any)."""
        per = self.bearings.get(camera)
        if not per:
            return True
        before = [s for s in per if s < stamp_ns]
        if not before:
            return True
        return set(per[max(before)]) <= set(per.get(stamp_ns, ()))

    @property
    def relative_std(self) -> float:
        return math.sqrt(self.P)

    # ------------------------------------------------------------------ per frame
    def apply_pending(self, stamp_ns: int, ekf, fusion) -> bool:
        """The rescale decided last frame, at this frame (after its cameras were fused)."""
        c = self.pending
        if c is None or stamp_ns < c.from_ns:
            return False
        self.pending = None
        rescale_body_ekf(ekf, c.factor, c.centre)
        fusion.last_T = fusion.last_T.copy()
        fusion.last_T[:3, 3] = scale_positions(fusion.last_T[:3, 3], c.factor, c.centre)
        for _, T, centres, _ in self.history:
            T[:3, 3] = scale_positions(T[:3, 3], c.factor, c.centre)
            for n in centres:
                centres[n] = scale_positions(centres[n], c.factor, c.centre)
        return True

    def observe(self, stamp_ns: int, T_now: np.ndarray, cameras: Dict[str, np.ndarray],
                camera_stamps: Optional[Dict[str, int]] = None):
        """Record this frame (fused pose; informative cameras' body poses; each camera's own
        stamp) and observe the scale: from the tracks when the quarters send them, else over a
        window of frames once the body turned enough since its start."""
        p = self.p
        if self.observed and self.history:
            # the map's own scale drifts (monocular): the estimate must follow it
            self.P += self.drift_per_sqrt_s ** 2 * max(0.0, (stamp_ns - self.history[-1][0]) * 1e-9)
        centres = {}
        for cam in self.rig.cameras:
            T = cameras.get(cam.name)
            if T is not None:
                centres[cam.name] = (T @ cam.T_base_cam)[:3, 3].copy()
        stamps = {n: int(s) for n, s in (camera_stamps or {}).items()}
        if self.history and self.travel_pitch is not None and stamp_ns > self.history[-1][0]:
            self.travel_pitch.add_step(np.linalg.solve(self.history[-1][1], T_now)[:3, 3])
            if self.path_normal is not None:
                self.path_normal.add_step(stamp_ns, T_now[:3, 3] - self.history[-1][1][:3, 3])
        self.history.append((int(stamp_ns), T_now.copy(), centres, stamps))
        max_ns = p['scale_window_max_s'] * 1e9
        while len(self.history) > p['scale_pair_max_frames'] + 2 and stamp_ns - self.history[0][0] > max_ns:
            self.history.popleft()
        if self.rig.road_scale:
            self._observe_road()
            return
        if p['scale_from_tracks'] and self.tracks_for_scale:
            self._observe_tracks()
            return
        R_now = T_now[:3, :3]
        for s, T, c0, _ in reversed(list(self.history)[:-1]):
            if self.window_start is not None and s < self.window_start:
                break
            angle = float(np.linalg.norm(se3.R_to_rotvec(T[:3, :3].T @ R_now)))
            if angle < p['scale_window_rotation_rad']:
                continue
            self.window_start = int(stamp_ns)
            R, t_map = relative_motion(T, T_now)
            dirs, names = [], []
            for cam in self.rig.cameras:
                if cam.name in c0 and cam.name in centres:
                    dirs.append(T[:3, :3].T @ (centres[cam.name] - c0[cam.name]))
                else:
                    dirs.append(None)
            r = solve_rig_translation(R, dirs, [c.translation for c in self.rig.cameras],
                                      direction_sigma_rad=p['scale_direction_sigma_rad'],
                                      min_rotation_rad=p['scale_min_rotation_rad'],
                                      max_relative_std=p['scale_max_relative_std'],
                                      names=self.rig.names)
            k = scale_correction(t_map, r)
            if k is not None:
                self._update(k, r.relative_std)
            return

    def _update(self, k: float, relative_std: float):
        """Kalman update of log k by one observation of the factor k."""
        z, Rz = math.log(k), max(relative_std, 1e-3) ** 2
        if self.observed and (z - self.x) ** 2 > 9.0 * (self.P + Rz):
            return         # one observation against all before: a bad one (gated)
        g = self.P / (self.P + Rz)
        self.x += g * (z - self.x)
        self.P *= (1.0 - g)
        self.observed = True
        self.last_ratio = k
        self.n_observations += 1

    def tracks_between(self, stamps_a: Dict[str, int], stamps_b: Dict[str, int], frame_a: int,
                       frame_b: int, by_camera: bool = False) -> List[CameraTracks]:
        """Every camera's tracks seen at both frames (each camera at its own stamp in the
        frame, else the frame's), quarter by quarter matched by track id. by_camera: one
        entry per rig camera, None for those without."""
        cams = []
        for cam in self.rig.cameras:
            per = self.bearings.get(cam.name, {})
            qa = per.get(stamps_a.get(cam.name, frame_a))
            qb = per.get(stamps_b.get(cam.name, frame_b))
            if not qa or not qb:
                if by_camera:
                    cams.append(None)
                continue
            quarters = sorted(set(qa) & set(qb))
            if quarters:
                # one match for the camera: each quarter's ids (unique within it) made unique
                # across quarters (16 small matches a frame cost more than the fits on them)
                ia, pa, sa = self._stacked(qa, quarters)
                ib, pb, sb = self._stacked(qb, quarters)
                _, ja, jb = np.intersect1d(ia, ib, assume_unique=True, return_indices=True)
                cams.append(CameraTracks(cam.rotation, cam.translation, pa[ja], pb[jb],
                                         np.maximum(sa[ja], sb[jb])))
            elif by_camera:
                cams.append(None)
        return cams

    @staticmethod
    def _stacked(per_quarter, quarters):
        """(ids made unique across quarters, points, stds) of the quarters' tracks at a frame."""
        ids = [np.asarray(per_quarter[q][0], np.int64) + (int(q) << 40) for q in quarters]
        return (np.concatenate(ids), np.concatenate([per_quarter[q][1] for q in quarters]),
                np.concatenate([per_quarter[q][2] for q in quarters]))

    def _observe_tracks(self):
        """The rig's metric motion from the tracks between two earlier fused frames a and b
        (b the previous frame: this one's tracks may still be on their way to a general
        arbiter node), a the latest before b that the body turned scale_pair_rotation_rad
        from, at most scale_pair_max_frames before it; pairs do not overlap."""
        p = self.p
        hist = list(self.history)
        if len(hist) < 3:
            return
        b = hist[-2]
        if self.pair_end is not None and b[0] <= self.pair_end:
            return
        a = None
        for h in reversed(hist[max(0, len(hist) - 2 - p['scale_pair_max_frames']):-2]):
            if self.pair_end is not None and h[0] < self.pair_end:
                break
            angle = float(np.linalg.norm(se3.R_to_rotvec(h[1][:3, :3].T @ b[1][:3, :3])))
            if angle >= p['scale_pair_rotation_rad']:
                a = h
                break
        if a is None:
            return
        self.pair_end = b[0]
        cams = self.tracks_between(a[3], b[3], a[0], b[0])
        R, t_map = relative_motion(a[1], b[1])
        fit = fit_rig_motion(R, t_map, cams)
        self.last_fit = fit
        if not fit.ok:
            return
        if fit.relative_std > p['scale_max_relative_std']:
            return
        nn = float(t_map @ t_map)
        k = float(t_map @ fit.t) / nn if nn > 1e-12 else 0.0
        if k > 0 and np.isfinite(k):
            # One std for every pair, not the fit's prediction: weighted by that, the scale
            # read 2-3 % low (the prediction is smaller where |t| came out short).
            self._update(k, p['scale_pair_std'])

    def road_up(self, at_ns: Optional[int] = None) -> np.ndarray:
        """The road's normal (up) in the body frame at the recorded frame at_ns: square to the
        path driven up to then (road_pitch.PathNormal, road_pitch_window_steps) once the
        direction of travel is known, else square to the direction of travel (road_pitch) when
        road_pitch_from_travel, else the body's z."""
        if self.travel_pitch is None:
            return np.array([0.0, 0.0, 1.0])
        if self.path_normal is not None and at_ns is not None and self.travel_pitch.pitch_rad is not None:
            T = next((T for s, T, _, _ in reversed(self.history) if s <= at_ns), None)
            up = self.path_normal.up_body(at_ns, T[:3, :3]) if T is not None else None
            if up is not None:
                return up
        return self.travel_pitch.up_body()

    def _observe_road(self):
        """Over a road: each camera's fused step between the two previous frames made metric
        by its tracks in the lane ahead (road_plane.road_scale, on the road whose normal the
        direction of travel gives; before that is known, the road homography's own step,
        road_plane.fit_road): one observation of the scale per camera and frame pair, and
        the body's metric step of the pair (the cameras' median) for road_speed."""
        p = self.p
        hist = list(self.history)
        if len(hist) < 3:
            return
        a, b = hist[-3], hist[-2]
        if self.pair_end is not None and b[0] <= self.pair_end:
            return
        self.pair_end = b[0]
        self.road_step = None
        ks = []
        up = self.road_up(a[0])
        # the known step's factor once the road's normal is known (the homography's before)
        known_step = p['road_scale_known_step'] and (self.travel_pitch is None
                                                     or self.travel_pitch.pitch_rad is not None)
        T_b_body = b[1]
        m = self.measured_step
        if known_step and p['road_scale_measured_step'] and m is not None and (m[0], m[1]) == (a[0], b[0]):
            # the rig's motion measured on the tracks: its rotation and direction, the fused
            # step's length; the road's normal square to that direction (the body's lateral
            # axis in the road)
            d = m[3] / np.linalg.norm(m[3])
            T_b_body = a[1] @ se3.make_T(m[2], d * np.linalg.norm(np.linalg.solve(a[1], b[1])[:3, 3]))
            self.measured_pitches.append(math.atan2(d[2], math.hypot(d[0], d[1])))
            pitch = float(np.median(self.measured_pitches))
            up = np.array([-math.sin(pitch), 0.0, math.cos(pitch)])
        for cam, tracks in zip(self.rig.cameras, self.tracks_between(a[3], b[3], a[0], b[0], by_camera=True)):
            if tracks is None:
                continue
            down_c, height = camera_over_road(up, cam.rotation, cam.translation, self.rig.floor_z)
            below = road_region(tracks.xa, down_c, cam.rotation, height)
            T_a, T_b = a[1] @ cam.T_base_cam, T_b_body @ cam.T_base_cam
            if known_step:
                T_ab = np.linalg.solve(T_b, T_a)                        # camera a -> camera b
                if np.linalg.norm(T_ab[:3, 3]) < p['road_scale_min_step_m']:
                    continue               # points above the road move as it does
                rs = road_scale(tracks.xa[below], tracks.xb[below], T_ab[:3, :3], T_ab[:3, 3], down_c, height)
                if rs is not None:
                    ks.append(rs.factor)
                    self.n_road_fits += 1
                    self.known_step_observed = True
                    self._update(rs.factor, math.hypot(p['road_scale_spread_factor'] * rs.relative_std,
                                                       p['road_scale_std_floor']))
                continue
            fit = fit_road(tracks.xa[below], tracks.xb[below], down_c, height,
                           p['road_scale_threshold'] * float(np.median(tracks.sigma)), p['road_scale_min_step_m'])
            if fit is None:
                continue
            t_map = T_a[:3, :3].T @ (T_b[:3, 3] - T_a[:3, 3])            # in camera a
            t_metric = camera_step(fit)
            nn = float(t_map @ t_map)
            k = float(t_map @ t_metric) / nn if nn > 1e-12 else 0.0
            if k > 0 and np.isfinite(k):
                ks.append(k)
                self.n_road_fits += 1
                self._update(k, p['road_scale_std'])
        if ks:
            # the body's metric step a -> b (body a's frame), its duration
            self.road_step = (float(np.median(ks)) * np.linalg.solve(a[1], b[1])[:3, 3], (b[0] - a[0]) * 1e-9)

    def fit_summary(self) -> str:
        """The last rig-motion fit to the quarters' tracks, for /diagnostics: what it used,
        or why it was not usable; '' before any."""
        f = self.last_fit
        if f is None:
            return ''
        if not f.ok:
            return f'not used: {f.reason}'
        return f'{f.n_inliers} of {f.n_points} tracks, {f.rms:.2f} sigma rms, |t| std {f.relative_std:.3f}'

    def decide(self, stamp_ns: int, T_now: np.ndarray) -> Optional[MapScaleCommand]:
        """A rescale command, from the next frame on, when the scale is known well enough
        (and, after the first, when it moved enough)."""
        p = self.p
        if not self.observed or self.pending is not None or self.relative_std > p['scale_snap_relative_std']:
            return None
        if self.epoch > 0 and abs(self.x) < max(p['scale_snap_min_change'], self.relative_std):
            return None
        if (self.rig.road_scale and self.epoch == 0 and p['road_scale_first_snap_known_step']
                and p['road_scale_known_step'] and not self.known_step_observed
                and abs(self.x) < p['road_scale_std']):
            # The first rescale is about the origin (the whole path so far): from the road
            # homography's steps alone (before the road's normal is known) it followed one or
            # two observations that scatter 15-50 % (kitti_seq1 road: 1.046 where the map was
            # 20 % long), and the later ones, about the recent path, never set the start right.
            # Unless those steps moved the scale from the start's by more than one of their
            # std (road_scale_std): the start is then off beyond their scatter (kitti_seq1
            # halves started 43 % long; held, 11 frames went out at that scale until the first
            # known step, 1 s in, then the pose jumped 4.9 m back).
            return None
        about = p['road_scale_snap_about'] if self.rig.road_scale else p['scale_snap_about']
        centre = self.snap_centre(stamp_ns, T_now, about)
        k = math.exp(self.x)
        self.epoch += 1
        self.command = MapScaleCommand(int(stamp_ns) + 1, self.epoch, k, tuple(float(v) for v in centre))
        self.pending = self.command
        self.x = 0.0
        pose_after = centre + k * (T_now[:3, 3] - centre)
        self.last_snap = (centre, pose_after, self.P, int(stamp_ns))
        self.snapped_about = pose_after if about == 'blend' else centre
        return self.command

    def snap_centre(self, stamp_ns: int, T_now: np.ndarray, about: str) -> np.ndarray:
        """The point a rescale keeps fixed. `blend`: x holds the error the map carried from
        before the last rescale (variance P then) and the drift it grew since (the drift's
        variance over the time since); the first belongs to the path the last rescale scaled
        (about its centre), the second to the path since (about the pose then), so the centre is
        their mean weighted by the two variances. About the origin every rescale scaled the
        whole path again: on KITTI 07, where the road rescales every second or two, each one
        jumped the pose back by 1 % of the distance from the start and the run ended 7 % short."""
        if about == 'origin' or (about == 'blend' and self.last_snap is None):
            return np.zeros(3)
        if about == 'current':
            return T_now[:3, 3].astype(float).copy()
        centre, pose_after, P_then, stamp_then = self.last_snap
        grown = self.drift_per_sqrt_s ** 2 * max(0.0, (stamp_ns - stamp_then) * 1e-9)
        w = P_then / max(P_then + grown, 1e-300)
        return w * centre + (1.0 - w) * pose_after

    @property
    def drift_per_sqrt_s(self) -> float:
        """The map's scale drift per sqrt(s): faster over a road, which observes it every frame."""
        return self.p['road_scale_drift_per_sqrt_s'] if self.rig.road_scale else self.p['scale_drift_per_sqrt_s']

    def odom_covariance(self, T: np.ndarray, pose_cov: np.ndarray) -> np.ndarray:
        d = T[:3, 3] - self.snapped_about
        C = pose_cov.copy()
        C[:3, :3] += self.P * np.outer(d, d)
        return C
