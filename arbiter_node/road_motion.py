"""A camera's metric motion between two frames from its tracks over a road (ROS-free).

Why: at car speed (a metre or more and several degrees between frames) the quarters' maps
break: tracks live a few frames, landmarks wait for parallax from fused poses that are not
moving yet, and a quarter measured on bearings alone turned its camera by 2-8 deg where the
car turned 0.3. All of one camera's tracks between two frames, independent of any map, hold
its motion: the essential matrix (two_view: OpenCV's five-point RANSAC) gives the rotation
(KITTI 07 at 5 Hz: 0.13 deg median error per frame, one quarter alone 0.3-0.6 with tails of
several degrees) and the direction of travel; the road ahead (road_plane: the plane's
homography, metric from the camera's height) gives the length. The general arbiter measures
the body's twist with it (general_fusion, `road_twist`).
"""
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from arbiter_node.rig_motion_fit import CameraTracks, fit_rig_motion
from camera_pose_nodes.road_plane import camera_over_road, camera_step, fit_road, road_region
from camera_pose_nodes.two_view import two_view
from multicam_ego_motion.geometry import se3


@dataclass
class CameraMotion:
    R: np.ndarray              # camera a -> b: X_b = R X_a + t
    direction: np.ndarray      # (3,) unit: camera b's centre from camera a's, in camera a
    length_m: Optional[float]  # metric length of that step from the road; None: not seen
    inliers: np.ndarray        # (N,) bool: the tracks the essential matrix holds


def camera_motion(tracks: CameraTracks, up_body: Optional[np.ndarray], floor_z: Optional[float],
                  threshold: float, min_points: int, min_parallax_deg: float, road_threshold: float,
                  min_step_m: float) -> Optional[CameraMotion]:
    """Motion of one camera between frames a and b from its tracks in both; the road through
    the body's (0, 0, floor_z) with normal up_body (body frame; floor_z None: no road). None
    when the tracks do not fix it."""
    tv = two_view(tracks.xa, tracks.xb, threshold, min_points, min_parallax_deg)
    if tv is None:
        return None
    direction = -tv.R.T @ tv.t
    length = None
    if floor_z is not None:
        down_c, height_m = camera_over_road(up_body, tracks.R_base_cam, tracks.centre, floor_z)
        road = road_region(tracks.xa, down_c, tracks.R_base_cam, height_m) & tv.inliers
        fit = fit_road(tracks.xa[road], tracks.xb[road], down_c, height_m, road_threshold, min_step_m)
        if fit is not None:
            along = float(camera_step(fit) @ direction)
            length = along if along > 0.0 else None
    return CameraMotion(tv.R, direction, length, tv.inliers)


@dataclass
class RigMotion:
    R: np.ndarray              # body a -> b: body b's axes in body a
    t: np.ndarray              # body b's origin in body a (m when length_known)
    rotation_cov: np.ndarray   # 3x3 (rad^2)
    length_known: bool


def _in_body(m: CameraMotion, tracks: CameraTracks, length: float) -> np.ndarray:
    """Body b in body a (4x4) when the camera moved as `m` says, `length` along its direction."""
    T_cam = se3.make_T(m.R.T, m.direction * length)          # camera b in camera a
    T_bc = se3.make_T(tracks.R_base_cam, tracks.centre)
    return T_bc @ T_cam @ np.linalg.inv(T_bc)


def rig_motion(tracks: Sequence[CameraTracks], motions: Sequence[Tuple[CameraTracks, CameraMotion]],
               prior: np.ndarray, min_points: int) -> Optional[RigMotion]:
    """The body's motion from its cameras' tracks and the motions of those whose essential
    matrix held (with their tracks): the rig's motion
    fitted to all their tracks at once (rig_motion_fit: robust, the rotation's covariance
    from the fit, x4: single fits scatter about twice their predicted std), started from each
    camera's motion and from `prior` (body b in body a, the filter's), the start whose fit
    holds the most tracks kept. Why not one camera's essential matrix: a narrow view confuses
    a turn with sideways travel (KITTI 07's image halves: 0.2 deg median error, up to 10 deg;
    the fit to both halves 0.03-0.08 deg). The length: the median of the cameras' road steps,
    else the prior's and length_known False."""
    if not motions:
        return None
    lengths = [m.length_m for _, m in motions if m.length_m is not None]
    length = float(np.median(lengths)) if lengths else max(float(np.linalg.norm(prior[:3, 3])), 0.05)
    starts = [_in_body(m, tr, length) for tr, m in motions] + [prior]
    best = None
    for T0 in starts:
        if np.linalg.norm(T0[:3, 3]) < 1e-6:
            continue
        fit = fit_rig_motion(T0[:3, :3], T0[:3, 3], list(tracks), min_points=min_points, min_cameras=1)
        if fit.ok and (best is None or fit.n_inliers > best.n_inliers):
            best = fit
    if best is None:
        return None
    t = _metric_translation(best.R, best.t, motions)
    if t is None:
        n = float(np.linalg.norm(best.t))
        if n < 1e-9:
            return None
        t = best.t / n * length
    return RigMotion(best.R, t, 4.0 * best.covariance[:3, :3], bool(lengths))


def _metric_translation(R: np.ndarray, t: np.ndarray, motions) -> Optional[np.ndarray]:
    """The body's translation that moves each camera with a road step by that step's length
    (the median over those cameras), from a fitted motion (R, t) whose length is free. Why not
    t scaled to the length: in a turn a camera off the body's axis of rotation moves by
    t + (R - I) c, so t's direction depends on its length (with one camera the fit holds the
    same on the whole line t(s) = s u - (R - I) c, and which point it returns depends on its
    start: a 1.6 m step turning 6 deg, camera 0.5 m ahead of the body, read 3.5 deg sideways)."""
    out = []
    for tr, m in motions:
        if m.length_m is None:
            continue
        lever = (R - np.eye(3)) @ tr.centre
        u = t + lever                           # the camera's step as the fit has it
        n = float(np.linalg.norm(u))
        if n > 1e-9:
            out.append(u * (m.length_m / n) - lever)
    return np.median(out, axis=0) if out else None


def body_twist(motion: RigMotion, dt: float, direction_std: float, length_std: float
               ) -> Tuple[np.ndarray, np.ndarray]:
    """The body twist (vx, vy, vz, wx, wy, wz in base_link) of that motion over `dt`, and its
    covariance: the direction of travel to `direction_std` (rad), the length to `length_std`
    (relative) when the road measured it, else not at all."""
    L = float(np.linalg.norm(motion.t))
    d = motion.t / L if L > 1e-9 else np.array([1.0, 0.0, 0.0])
    twist = np.r_[motion.t, se3.R_to_rotvec(motion.R)] / dt
    along_var = (length_std * L) ** 2 if motion.length_known else 1e6
    cov = np.zeros((6, 6))
    cov[:3, :3] = along_var * np.outer(d, d) + (max(L, 0.05) * direction_std) ** 2 * (np.eye(3) - np.outer(d, d))
    cov[3:, 3:] = motion.rotation_cov
    return twist, cov / dt ** 2
