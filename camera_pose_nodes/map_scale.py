"""A quarter's part in a map without a scale source (ROS-free): its two-view initialisation
and the general arbiter's map rescale.

The rescale: once a scale source measures the map's scale (arbiter_node/scale_state), the
general arbiter publishes a MapScaleCommand on /ego_motion/map_scale (latched): multiply
every position of the map by `factor` about `centre` (odom), from the fused pose of frame
`from_ns` on. Every node applies it at that frame (the general arbiter after fusing it, the
quarters before taking its fused pose), like the frame schedule: so a lockstep replay stays
deterministic and the sequential pipeline equals the graph bit for bit. A map multiplied
about a point reprojects exactly as before (the same rays), so nothing else changes.
"""
import math
import struct
from dataclasses import dataclass

import numpy as np

from camera_pose_nodes.two_view import body_pose_from_two_view, two_view

# The two-view estimate's uncertainty, relative to its gauge length: along the travel the
# length is the gauge itself (its uncertainty is the scale state's, not the pose's);
# across, the direction's RANSAC error in a quarter's narrow view.
_ALONG_STD = 0.05
_ACROSS_STD = 0.05
_ROTATION_STD = 0.003          # rad


def _bits(x: float) -> int:
    return struct.unpack('<q', struct.pack('<d', float(x)))[0]


def _float(b: int) -> float:
    return struct.unpack('<d', struct.pack('<q', int(b)))[0]


@dataclass(frozen=True)
class MapScaleCommand:
    from_ns: int               # applies with the first fused pose at or after this stamp
    epoch: int                 # 1, 2, ...: rescales in order, each once
    factor: float
    centre: tuple              # (x, y, z) in odom

    def to_list(self):
        """An Int64MultiArray's data: the floats as their IEEE bits (exact)."""
        return [int(self.from_ns), int(self.epoch), _bits(self.factor)] + [_bits(c) for c in self.centre]

    @classmethod
    def from_list(cls, values) -> 'MapScaleCommand':
        v = [int(x) for x in values]
        if len(v) != 6 or v[1] < 1:
            raise ValueError(f'a map-scale command is [from_ns, epoch >= 1, factor, cx, cy, cz], got {v}')
        k = _float(v[2])
        c = tuple(_float(b) for b in v[3:])
        if not (math.isfinite(k) and k > 0 and all(math.isfinite(x) for x in c)):
            raise ValueError(f'map-scale command with factor {k} and centre {c}')
        return cls(v[0], v[1], k, c)


def scale_positions(P: np.ndarray, k: float, centre) -> np.ndarray:
    """Points (..., 3) multiplied by k about centre."""
    c = np.asarray(centre, float)
    return c + k * (np.asarray(P, float) - c)


def rescale_filter(kf, k: float, centre):
    """A filter laid out as position (0:3), orientation, linear velocity (6:9), angular
    velocity (the quarter's PoseEKF and the general arbiter's BodyEKF both are; the latter's
    gyro bias after them is unitless in metres): position about centre, velocity and their
    covariance rows/columns by k."""
    x = kf.x
    x[0:3, 0] = scale_positions(x[0:3, 0], k, centre)
    x[6:9, 0] = k * x[6:9, 0]
    s = np.ones(len(x))
    s[0:3] = k
    s[6:9] = k
    kf.P = kf.P * s[:, None] * s[None, :]


def rescale_pose_ekf(ekf, k: float, centre):
    """PoseEKF (once it has started): see rescale_filter."""
    if ekf.stamp_ns is not None:
        rescale_filter(ekf.kf, k, centre)


def rescale_quarter(q, cmd: MapScaleCommand):
    """The quarter's map by cmd.factor about cmd.centre: landmarks (and their covariances),
    fused poses, the EKF's position and velocity."""
    k, c = cmd.factor, cmd.centre
    lm = q.landmarks
    if len(lm):
        lm.X = scale_positions(lm.X, k, c)
        lm.C = lm.C * (k * k)
    for s, T in q.fused_poses.items():
        T = T.copy()
        T[:3, 3] = scale_positions(T[:3, 3], k, c)
        q.fused_poses[s] = T
    q._fused_cache = None
    rescale_pose_ekf(q.ekf, k, c)
    q.scale_epoch = cmd.epoch


def two_view_init(q, stamp_ns: int) -> int:
    """Two-view initialisation of quarter q at stamp_ns (QuarterEstimator._two_view_due):
    sets its EKF's pose from the essential matrix against the oldest fused view that enough
    of its current tracks share. Returns the inlier count, 0 when not (yet) possible."""
    tr, p = q.tracker, q.params
    rows = np.flatnonzero(tr.last_stamps() == stamp_ns)
    if len(rows) < p.two_view_min_points:
        return 0
    fs, fT, _, _ = q._fused_arrays()
    if q._two_view_ref not in q.fused_poses:
        q._two_view_ref = None        # its tracks are gone: start over from a shared view
    ht = tr.hist_t[rows]
    earlier = np.arange(tr.cfg.max_history)[None, :] < (tr.hist_n[rows] - 1)[:, None]
    for slot, s in enumerate(fs.tolist()):
        if s >= stamp_ns:
            break
        if q._two_view_ref is not None and s != q._two_view_ref:
            continue
        at = (ht == s) & earlier
        has = at.any(axis=1)
        if has.sum() < p.two_view_min_points:
            continue
        r, col = rows[has], np.argmax(at[has], axis=1)
        xy1 = q.intrinsics.undistort_points(tr.hist_uv[r, col].astype(float))
        xy2 = q.intrinsics.undistort_points(tr.pts[r].astype(float))
        f = 0.5 * (q.intrinsics.fx + q.intrinsics.fy)
        res = two_view(xy1, xy2, 2.0 * p.pixel_sigma / f, p.two_view_min_points, p.two_view_parallax_deg)
        if res is None:
            return 0     # the oldest shared view has the most parallax: a later one has less
        L = p.two_view_nominal_speed * (stamp_ns - s) * 1e-9
        T1 = fT[slot]
        T2 = body_pose_from_two_view(T1, q.T_base_cam, res, L)
        d = T2[:3, 3] - T1[:3, 3]
        d = d / max(np.linalg.norm(d), 1e-12)
        D = np.outer(d, d)
        cov = np.zeros((6, 6))
        cov[:3, :3] = L * L * (_ALONG_STD ** 2 * D + _ACROSS_STD ** 2 * (np.eye(3) - D))
        cov[3:, 3:] = np.eye(3) * _ROTATION_STD ** 2
        q.ekf.set_pose(T2, cov)
        q._two_view_ref = s
        return int(res.inliers.sum())
    return 0
