"""Overlapping cameras: match a quarter's tracks into the other camera's image of the same
stamp and triangulate them from the known baseline, metric from a single frame.

ROS-free. The quarter (quarter_estimator) calls StereoPair.match with its tracks' pixels and
places the points as landmarks once the frame's fused pose is known. The search is OpenCV's
pyramidal Lucas-Kanade from the quarter's crop into the other image, starting where a point
at the prior depth would land through the rig's extrinsics; a match must come back to where
it started (forward-backward), lie on its epipolar line of the rig geometry and triangulate
in front of both cameras within the depth limits.

overlapping_pairs() finds the pairs of a rig whose fields of view overlap from the
extrinsics and the intrinsics, for rigs whose file does not name them.
"""
from dataclasses import dataclass
from typing import Dict, Tuple

import cv2
import numpy as np

from camera_pose_nodes.camera_model import CameraIntrinsics
from camera_pose_nodes.landmark_map import triangulate_views, triangulation_covariance


def skew(t):
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def relative_pose(T_base_a: np.ndarray, T_base_b: np.ndarray):
    """(R, t) with x_b = R x_a + t: camera A's frame into camera B's."""
    T = np.linalg.inv(T_base_b) @ T_base_a
    return T[:3, :3].copy(), T[:3, 3].copy()


@dataclass
class StereoConfig:
    window: int = 21             # Lucas-Kanade window (px, odd)
    pyramid_levels: int = 4      # levels above full resolution: disparities of ~100 px
    iterations: int = 30
    epsilon_px: float = 0.01
    fb_px: float = 1.0           # forward-backward error that rejects a match
    epipolar_px: float = 1.5     # distance to the epipolar line that rejects a match
    pixel_sigma: float = 0.5     # matching noise (px, 1 sigma): the disparity noise
    min_depth: float = 0.1       # m
    max_depth: float = 200.0     # m


class StereoPair:
    """Camera A (the quarter's) and camera B (its partner): geometry and matching."""

    def __init__(self, T_base_a: np.ndarray, T_base_b: np.ndarray, intr_a: CameraIntrinsics,
                 intr_b: CameraIntrinsics, cfg: StereoConfig):
        self.R, self.t = relative_pose(T_base_a, T_base_b)
        self.baseline = float(np.linalg.norm(self.t))
        if self.baseline < 1e-6:
            raise ValueError('stereo pair cameras share their centre: no baseline')
        self.E = skew(self.t) @ self.R                # x_b^T E x_a = 0
        self.c_b = -self.R.T @ self.t                 # B's centre in A's frame
        self.intr_a, self.intr_b = intr_a, intr_b
        self.cfg = cfg
        self.focal_b = 0.5 * (intr_b.fx + intr_b.fy)
        self.sigma_n = cfg.pixel_sigma / (0.5 * (intr_a.fx + intr_a.fy))
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.iterations, cfg.epsilon_px)

    def predict(self, xy_a: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixels in B of A's normalized points at `depth` (along A's optical axis); NaN when
        behind B."""
        X_a = np.column_stack([xy_a * depth[:, None], depth])
        X_b = X_a @ self.R.T + self.t
        z = np.where(X_b[:, 2] > 1e-6, X_b[:, 2], np.nan)
        return self.intr_b.project(X_b[:, :2] / z[:, None])

    def _lk(self, img0, img1, p0, guess):
        c = self.cfg
        p1, st, _ = cv2.calcOpticalFlowPyrLK(
            img0, img1, p0.reshape(-1, 1, 2), guess.reshape(-1, 1, 2).copy(),
            winSize=(c.window, c.window), maxLevel=c.pyramid_levels, criteria=self._criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        return p1.reshape(-1, 2), st.reshape(-1).astype(bool)

    def match(self, crop_a: np.ndarray, offset_a, gray_b: np.ndarray, px_a: np.ndarray,
              prior_depth: np.ndarray):
        """Match A's pixels `px_a` (N, 2, full-image coordinates, all inside the crop
        `crop_a` whose pixel (0, 0) is `offset_a`) into B's image and triangulate them.
        prior_depth (N,) or scalar: where each search starts (m along A's axis).
        Returns (ok (N,), px_b (N, 2), X_a (N, 3) points in A's camera frame,
        C_a (N, 3, 3) their covariances); rows not ok hold NaN."""
        N = len(px_a)
        ok = np.zeros(N, bool)
        px_b = np.full((N, 2), np.nan)
        X = np.full((N, 3), np.nan)
        C = np.full((N, 3, 3), np.nan)
        if N == 0:
            return ok, px_b, X, C
        c = self.cfg
        px_a = np.asarray(px_a, np.float64)
        xy_a = self.intr_a.undistort_points(px_a)
        guess = self.predict(xy_a, np.broadcast_to(np.asarray(prior_depth, float), (N,)).copy())
        hb, wb = gray_b.shape
        valid = np.all(np.isfinite(guess), axis=1)
        guess = np.where(valid[:, None], guess, px_a)
        # Lucas-Kanade takes two images of one size: A's crop and the part of B where the
        # crop's points land (shifted by their median predicted disparity), so that both
        # hold real texture at every pyramid level (a crop pasted on a blank canvas put its
        # edge into the coarse levels' windows, and matches failed near it)
        ox, oy = int(offset_a[0]), int(offset_a[1])
        ch, cw = crop_a.shape
        shift = np.round(np.median(guess[valid] - px_a[valid], axis=0)) if valid.any() else np.zeros(2)
        bx, by = ox + int(shift[0]), oy + int(shift[1])
        sub_b = _window(gray_b, bx, by, cw, ch)
        p0 = (px_a - [ox, oy]).astype(np.float32)
        g = (guess - [bx, by]).astype(np.float32)
        p1_sub, st1 = self._lk(crop_a, sub_b, p0, g)
        p1 = p1_sub + np.float32([bx, by])
        good = valid & st1 & np.all(np.isfinite(p1), axis=1)
        good &= (p1[:, 0] >= 0) & (p1[:, 0] <= wb - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= hb - 1)
        # The checks that need only the forward match come first (the epipolar line, the
        # triangulated depth: a third of KITTI's matches lie beyond the range), so the
        # backward search, as costly as the forward one, runs only on matches that would be
        # kept. Each point is searched on its own: the result is the same as checking all.
        idx = np.flatnonzero(good)
        if not len(idx):
            return ok, px_b, X, C
        xa = xy_a[idx]
        xb = self.intr_b.undistort_points(p1[idx].astype(np.float64))
        ha = np.column_stack([xa, np.ones(len(idx))])
        hb_ = np.column_stack([xb, np.ones(len(idx))])
        lines = ha @ self.E.T                                   # epipolar lines in B
        dist = np.abs(np.sum(lines * hb_, axis=1)) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12)
        keep = dist * self.focal_b < c.epipolar_px
        idx, xa, xb = idx[keep], xa[keep], xb[keep]
        if not len(idx):
            return ok, px_b, X, C
        n = len(idx)
        R_oc = np.stack([np.broadcast_to(np.eye(3), (n, 3, 3)),
                         np.broadcast_to(self.R.T, (n, 3, 3))], axis=1)
        c_o = np.stack([np.zeros((n, 3)), np.broadcast_to(self.c_b, (n, 3))], axis=1)
        xy = np.stack([xa, xb], axis=1)
        Xa = triangulate_views(R_oc, c_o, xy)
        Xb = Xa @ self.R.T + self.t
        fine = np.all(np.isfinite(Xa), axis=1)
        fine &= (Xa[:, 2] > c.min_depth) & (Xa[:, 2] < c.max_depth) & (Xb[:, 2] > c.min_depth)
        if not fine.any():
            return ok, px_b, X, C
        idx, Xa, Xb, R_oc = idx[fine], Xa[fine], Xb[fine], R_oc[fine]
        back, st2 = self._lk(sub_b, crop_a, p1_sub[idx], p0[idx])
        fb = st2 & (np.linalg.norm(back - p0[idx], axis=1) < c.fb_px)
        if not fb.any():
            return ok, px_b, X, C
        idx, Xa, Xb, R_oc = idx[fb], Xa[fb], Xb[fb], R_oc[fb]
        Xc = np.stack([Xa, Xb], axis=1)
        Cov = triangulation_covariance(Xc, R_oc, np.ones((len(idx), 2)), self.sigma_n)
        ok[idx] = True
        px_b[idx] = p1[idx]
        X[idx] = Xa
        C[idx] = Cov
        return ok, px_b, X, C


def _window(img: np.ndarray, x0: int, y0: int, w: int, h: int) -> np.ndarray:
    """img[y0:y0+h, x0:x0+w], the border replicated where it reaches outside."""
    H, W = img.shape
    pad = max(0, -x0, -y0, x0 + w - W, y0 + h - H)
    if pad:
        img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
        x0, y0 = x0 + pad, y0 + pad
    return np.ascontiguousarray(img[y0:y0 + h, x0:x0 + w])


def overlap_fraction(T_base_a, T_base_b, intr_a: CameraIntrinsics, intr_b: CameraIntrinsics,
                     grid: int = 9, depths_in_baselines=(5.0, 10.0, 20.0, 50.0)) -> float:
    """The share of A's image (a grid of rays, each at several depths, in multiples of the
    baseline: where a pair's matches can be triangulated) that lands inside B's image."""
    R, t = relative_pose(T_base_a, T_base_b)
    b = float(np.linalg.norm(t))
    if b < 1e-6:
        return 0.0
    u, v = np.meshgrid(np.linspace(0, intr_a.width - 1, grid), np.linspace(0, intr_a.height - 1, grid))
    xy = intr_a.undistort_points(np.column_stack([u.ravel(), v.ravel()]))
    hits = []
    for d in depths_in_baselines:
        X_b = np.column_stack([xy * d * b, np.full(len(xy), d * b)]) @ R.T + t
        front = X_b[:, 2] > 1e-6
        px = np.full((len(xy), 2), -1.0)
        if front.any():
            px[front] = intr_b.project(X_b[front, :2] / X_b[front, 2:3])
        hits.append(front & (px[:, 0] >= 0) & (px[:, 0] <= intr_b.width - 1)
                    & (px[:, 1] >= 0) & (px[:, 1] <= intr_b.height - 1))
    return float(np.mean(hits))


def overlapping_pairs(rig, intrinsics: Dict[str, CameraIntrinsics],
                      min_overlap: float = 0.5) -> Tuple[Tuple[str, str], ...]:
    """Pairs of the rig's cameras (rig order) that each see at least `min_overlap` of the
    other's image at plausible depths. Cameras without intrinsics are left out."""
    names = [c.name for c in rig.cameras if c.name in intrinsics]
    mounts = {c.name: c for c in rig.cameras}
    pairs = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            Ta, Tb = mounts[a].T_base_cam, mounts[b].T_base_cam
            if (overlap_fraction(Ta, Tb, intrinsics[a], intrinsics[b]) >= min_overlap
                    and overlap_fraction(Tb, Ta, intrinsics[b], intrinsics[a]) >= min_overlap):
                pairs.append((a, b))
    return tuple(pairs)
