"""Extract and track: Shi-Tomasi corners + pyramidal Lucas-Kanade inside one quarter.

Works on the quarter's crop (owned rectangle + margin); points are stored in full-image
pixels. The paper's third level of parallelism (Fig. 3, NP = ceil(NF / MinF)) is here:
tracking is split into chunks of about `min_features` points and extraction into grid
cells, run on a thread pool (OpenCV releases the GIL). Both are per-point / per-cell
independent computations concatenated in a fixed order, so chunked and sequential runs
give identical results.
"""
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np
import cv2

from camera_pose_nodes.quarter_region import QuarterRegion


@dataclass
class KLTConfig:
    min_features: int = 40        # extract only when fewer tracks than this
    max_features: int = 80        # extraction tops the quarter up to this
    window: int = 21              # LK window (px, odd)
    pyramid_levels: int = 3       # LK pyramid levels above the base image
    iterations: int = 30          # LK iterations per level, at most
    epsilon_px: float = 0.01      # LK stops when a step is shorter
    fb_threshold_px: float = 0.5  # forward-backward disagreement that rejects a track
    quality_level: float = 0.01   # Shi-Tomasi quality relative to the cell's best corner
    min_distance_px: float = 8.0  # minimum spacing between features
    block_size: int = 5           # Shi-Tomasi gradient averaging block
    grid_rows: int = 2            # extraction cells per quarter (spreads features)
    grid_cols: int = 2
    max_history: int = 60         # observations kept per track (the oldest is always kept)
    parallel_chunks: bool = False # run chunks/cells on a thread pool
    floor_warp_min_flow_px: float = 0.0  # lost floor tracks moving farther: search on the warped image (0: never)


MIN_PREDICTED_PX = 2.0   # a predicted motion shorter than this is left to the search


class Flow(NamedTuple):
    """Where the tracks `ids` went in a new crop: positions (full-image px) and kept flags;
    `recovered`: which of them the road-warped search found (_recover_on_floor), or None."""
    ids: np.ndarray
    new: np.ndarray
    ok: np.ndarray
    recovered: Optional[np.ndarray] = None


def margin_for(cfg: KLTConfig) -> int:
    """Crop margin so the LK window sees across the owned border at every pyramid level."""
    return cfg.window // 2 + 2 * cfg.pyramid_levels + 2


class KLTTracker:
    def __init__(self, region: QuarterRegion, cfg: KLTConfig):
        self.region = region
        self.cfg = cfg
        self._pool = None
        self.reset()

    # ----- state -------------------------------------------------------------------------
    def reset(self):
        self.next_id = 0
        self.ids = np.zeros(0, dtype=np.int64)
        self.pts = np.zeros((0, 2), dtype=np.float32)     # full-image pixels
        # Each track's observations as rows of fixed-size arrays (no Python object per
        # track): stamps, pixels, and how many of the max_history slots are used. The
        # oldest view is always kept (it has the parallax); the rest slide.
        H = self.cfg.max_history
        self.hist_t = np.zeros((0, H), dtype=np.int64)
        self.hist_uv = np.zeros((0, H, 2), dtype=np.float32)
        self.hist_n = np.zeros(0, dtype=np.int64)
        self.prev_crop = None      # previous frame's crop: what the next frame is tracked from
        self._cur_crop = None
        self.last_recovered = 0    # tracks the last track() kept from the road-warped search

    def get_state(self) -> dict:
        return {'next_id': self.next_id, 'ids': self.ids.copy(), 'pts': self.pts.copy(),
                'hist_t': self.hist_t.copy(), 'hist_uv': self.hist_uv.copy(),
                'hist_n': self.hist_n.copy(),
                'prev_crop': None if self.prev_crop is None else self.prev_crop.copy()}

    def set_state(self, s: dict):
        self.next_id = int(s['next_id'])
        self.ids = np.asarray(s['ids'], dtype=np.int64).copy()
        self.pts = np.asarray(s['pts'], dtype=np.float32).copy()
        self.hist_t = np.asarray(s['hist_t'], dtype=np.int64).copy()
        self.hist_uv = np.asarray(s['hist_uv'], dtype=np.float32).copy()
        self.hist_n = np.asarray(s['hist_n'], dtype=np.int64).copy()
        if self.hist_t.shape != (len(self.ids), self.cfg.max_history):
            raise ValueError(f'tracker state has history {self.hist_t.shape}, expected '
                             f'({len(self.ids)}, {self.cfg.max_history})')
        self.prev_crop = None if s['prev_crop'] is None else np.array(s['prev_crop'], np.uint8)
        self._cur_crop = self.prev_crop

    # ----- history -----------------------------------------------------------------------
    def last_stamps(self) -> np.ndarray:
        """Stamp of each track's newest observation."""
        return self.hist_t[np.arange(len(self.ids)), self.hist_n - 1]

    def last_px(self) -> np.ndarray:
        """Pixel of each track's newest observation (float64)."""
        return self.hist_uv[np.arange(len(self.ids)), self.hist_n - 1].astype(np.float64)

    def views_used(self) -> np.ndarray:
        """(N, max_history) mask of the history slots in use."""
        return np.arange(self.cfg.max_history)[None, :] < self.hist_n[:, None]

    def history_of(self, track_id: int):
        """[(stamp, u, v), ...] of one track, oldest first."""
        r = int(np.searchsorted(self.ids, track_id))
        if r >= len(self.ids) or self.ids[r] != track_id:
            raise KeyError(track_id)
        n = int(self.hist_n[r])
        return [(int(t), float(u), float(v)) for t, (u, v) in
                zip(self.hist_t[r, :n].tolist(), self.hist_uv[r, :n].tolist())]

    def _keep(self, keep: np.ndarray):
        self.ids, self.pts = self.ids[keep], self.pts[keep]
        self.hist_t, self.hist_uv, self.hist_n = self.hist_t[keep], self.hist_uv[keep], self.hist_n[keep]

    def _append_views(self, stamp_ns: int):
        """Append the current positions as every track's newest view."""
        H = self.cfg.max_history
        full = self.hist_n == H
        if full.any():                     # drop the second-oldest: the oldest has the parallax
            self.hist_t[full, 1:H - 1] = self.hist_t[full, 2:]
            self.hist_uv[full, 1:H - 1] = self.hist_uv[full, 2:]
        rows = np.arange(len(self.ids))
        col = np.minimum(self.hist_n, H - 1)
        self.hist_t[rows, col] = stamp_ns
        self.hist_uv[rows, col] = self.pts
        self.hist_n = np.minimum(self.hist_n + 1, H)

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # ----- helpers -----------------------------------------------------------------------
    def _map(self, fn, items):
        if self.cfg.parallel_chunks and len(items) > 1:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=max(2, len(items)),
                                                thread_name_prefix='klt')
            return list(self._pool.map(fn, items))
        return [fn(it) for it in items]

    def n_chunks(self, n_points: int) -> int:
        """NP = ceil(NF / MinF), the paper's split of a quarter's features."""
        return max(1, math.ceil(n_points / max(1, self.cfg.min_features)))

    # ----- track -------------------------------------------------------------------------
    def flow(self, crop: np.ndarray, predict=None, floor_warp=None) -> Optional[Flow]:
        """Lucas-Kanade flow of the current tracks from the previous crop into `crop`, without
        changing the tracker: a quarter computes it while it still waits for the previous
        frame's fused pose (pipelining), and track() applies it to the tracks that are left.
        `predict`: a pair of functions (forward, backward) mapping full-image pixels (N, 2)
        of the tracks `rows` (indices into this tracker's tracks) to where they should be in
        the new / previous image (flow_prediction): the search starts there instead of at
        zero flow. `floor_warp` (flow_prediction.FloorWarp): tracks known to lie on the floor
        that this search loses are searched again on the previous crop warped by the floor's
        homography (_recover_on_floor)."""
        if self.prev_crop is None or not len(self.ids):
            return None
        # OpenCV 5's Python binding no longer accepts prebuilt pyramids here, so each call
        # builds its own; the pyramid is a pure function of the image, hence chunking and
        # state hand-over still give identical results.
        off = self.region.offset
        p0 = (self.pts - off).reshape(-1, 1, 2).astype(np.float32)
        w = self.cfg.window
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.cfg.iterations, self.cfg.epsilon_px)
        prev, lv = self.prev_crop, self.cfg.pyramid_levels

        fwd, bwd = predict if predict is not None else (None, None)

        def search(img0, img1, pts, fn, rows):
            """LK of `pts` from img0 into img1, starting where `fn` predicts them (motions it
            predicts under MIN_PREDICTED_PX, and non-finite ones, start at zero flow)."""
            if fn is None:
                return cv2.calcOpticalFlowPyrLK(img0, img1, pts, None, winSize=(w, w),
                                                maxLevel=lv, criteria=crit)
            p = pts.reshape(-1, 2)
            g = fn(p + off, rows) - off
            zero = ~np.all(np.isfinite(g), axis=1) | (np.abs(g - p).max(axis=1) < MIN_PREDICTED_PX)
            g[zero] = p[zero]
            return cv2.calcOpticalFlowPyrLK(img0, img1, pts, g.reshape(-1, 1, 2).astype(np.float32),
                                            winSize=(w, w), maxLevel=lv, criteria=crit,
                                            flags=cv2.OPTFLOW_USE_INITIAL_FLOW)

        def lk(chunk):
            a = p0[chunk]
            b, st1, _ = search(prev, crop, a, fwd, chunk)
            new = b.reshape(-1, 2) + off
            # Only tracks that can still be kept are checked backwards (a quarter of them
            # were lost or left the quarter; each point is tracked on its own, so leaving
            # the others out changes nothing).
            ok = (st1.ravel() == 1) & np.all(np.isfinite(new), axis=1)
            ok &= self.region.owns(new)       # left the quarter: the neighbour takes over
            if ok.any():
                # Backwards from the new position's own prediction, never from the start
                # point: a search that starts at the answer would pass a wrong track.
                back, st2, _ = search(crop, prev, b[ok], bwd, chunk[ok])
                fb = np.linalg.norm((back - a[ok]).reshape(-1, 2), axis=1)
                ok[ok] = (st2.ravel() == 1) & (fb < self.cfg.fb_threshold_px)
            return new, ok

        # Chunks only pay on threads: run alone, each call rebuilt both pyramids (the
        # points are tracked independently, so one call gives the same result).
        n = self.n_chunks(len(p0)) if self.cfg.parallel_chunks else 1
        chunks = np.array_split(np.arange(len(p0)), n)
        res = self._map(lk, chunks)
        new, ok = np.concatenate([r[0] for r in res]), np.concatenate([r[1] for r in res])
        recovered = None
        if floor_warp is not None and self.cfg.floor_warp_min_flow_px > 0:
            recovered = self._recover_on_floor(crop, floor_warp, new, ok)
        return Flow(self.ids.copy(), new, ok, recovered)

    def _recover_on_floor(self, crop: np.ndarray, warp, new: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Lucas-Kanade again for the lost tracks known to lie on the floor whose homography
        moves them more than floor_warp_min_flow_px: from the previous crop warped by the
        floor's homography, where such a patch keeps its shape (a near road patch grows and
        shears by 15-35 % between frames at 5-10 Hz, and a translation-only search then
        fails from any start; on KITTI 07 at 5 Hz the warp keeps 2.5x the lower image's
        tracks), forward-backward on the warped pair. Only known floor points and only as a
        fallback: other points below the horizon (kerbs, cars, walls) warped as floor were
        kept at wrong places and collapsed a road-scaled map. Updates `new` and `ok`; returns
        which tracks it found."""
        off = self.region.offset
        found_mask = np.zeros(len(ok), bool)
        cand = ~ok & warp.on_floor
        if not cand.any():
            return found_mask
        p = self.pts[cand].astype(np.float64)
        q = cv2.perspectiveTransform(p.reshape(-1, 1, 2), warp.H).reshape(-1, 2)
        far = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q - p, axis=1) > self.cfg.floor_warp_min_flow_px)
        if not far.any():
            return found_mask
        rows = np.flatnonzero(cand)[far]
        to_crop = np.array([[1.0, 0.0, -off[0]], [0.0, 1.0, -off[1]], [0.0, 0.0, 1.0]])
        Hc = to_crop @ warp.H @ np.linalg.inv(to_crop)
        warped = cv2.warpPerspective(self.prev_crop, Hc, (crop.shape[1], crop.shape[0]), flags=cv2.INTER_LINEAR)
        s0 = (q[far] - off).reshape(-1, 1, 2).astype(np.float32)
        w, lv = self.cfg.window, self.cfg.pyramid_levels
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.cfg.iterations, self.cfg.epsilon_px)
        b, st1, _ = cv2.calcOpticalFlowPyrLK(warped, crop, s0, None, winSize=(w, w), maxLevel=lv, criteria=crit)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(crop, warped, b, None, winSize=(w, w), maxLevel=lv, criteria=crit)
        fb = np.linalg.norm((back - s0).reshape(-1, 2), axis=1)
        found = b.reshape(-1, 2) + off
        good = ((st1.ravel() == 1) & (st2.ravel() == 1) & (fb < self.cfg.fb_threshold_px)
                & np.all(np.isfinite(found), axis=1) & self.region.owns(found))
        new[rows[good]] = found[good]
        ok[rows[good]] = True
        found_mask[rows[good]] = True
        return found_mask

    def track(self, stamp_ns: int, crop: np.ndarray, flow: Optional[Flow] = None,
              predict=None, floor_warp=None) -> int:
        """Track existing features from the previous crop into `crop`; returns tracks kept.
        `flow`: this crop's flow() computed earlier; tracks dropped since are skipped (each
        point is tracked on its own, so the result is the same as tracking now).
        `predict`, `floor_warp`: as for flow()."""
        if flow is None:
            flow = self.flow(crop, predict, floor_warp)
        if flow is not None and len(self.ids):
            # The tracks left now are a subsequence of those the flow was computed for (ids
            # only grow, so both are sorted).
            rows = np.searchsorted(flow.ids, self.ids)
            if np.any(rows >= len(flow.ids)) or not np.array_equal(flow.ids[rows], self.ids):
                raise ValueError('the flow was computed for other tracks')
            new, ok = flow.new[rows], flow.ok[rows]
            # (a flow computed early also found tracks dropped since: not counted)
            self.last_recovered = 0 if flow.recovered is None else int(flow.recovered[rows].sum())
            self._keep(ok)
            self.pts = new[ok].astype(np.float32)
            self._append_views(stamp_ns)
        if crop.base is not None or not crop.flags.c_contiguous:
            crop = crop.copy()      # kept as the next frame's reference: must not change under us
        self.prev_crop = self._cur_crop = crop
        return len(self.ids)

    # ----- extract -----------------------------------------------------------------------
    def needs_features(self) -> bool:
        return len(self.ids) < self.cfg.min_features

    def extract(self, stamp_ns: int) -> int:
        """Top the quarter up with Shi-Tomasi corners, one grid cell at a time, away from
        existing tracks. Returns the number of new features."""
        crop = self._cur_crop
        if crop is None:
            return 0
        cfg, reg = self.cfg, self.region
        n_cells = cfg.grid_rows * cfg.grid_cols
        cap = math.ceil(cfg.max_features / n_cells)
        xs = np.linspace(reg.x0, reg.x1, cfg.grid_cols + 1).round().astype(int)
        ys = np.linspace(reg.y0, reg.y1, cfg.grid_rows + 1).round().astype(int)
        half = int(math.ceil(cfg.min_distance_px / 2))
        pad = cfg.block_size
        existing = self.pts

        cells = []
        for r in range(cfg.grid_rows):
            for c in range(cfg.grid_cols):
                # Interior cell borders are shrunk by half the min distance so that corners
                # of neighbouring cells keep the spacing a single call would enforce.
                x0 = xs[c] + (half if c > 0 else 0)
                x1 = xs[c + 1] - (half if c < cfg.grid_cols - 1 else 0)
                y0 = ys[r] + (half if r > 0 else 0)
                y1 = ys[r + 1] - (half if r < cfg.grid_rows - 1 else 0)
                inside = ((existing[:, 0] >= xs[c]) & (existing[:, 0] < xs[c + 1])
                          & (existing[:, 1] >= ys[r]) & (existing[:, 1] < ys[r + 1]))
                want = cap - int(inside.sum())
                if want > 0 and x1 - x0 > 2 and y1 - y0 > 2:
                    cells.append((x0, y0, x1, y1, want))

        def corners(cell):
            x0, y0, x1, y1, want = cell
            # Read a padded window so the gradient block sees real pixels at the cell edge.
            wx0, wy0 = max(reg.cx0, x0 - pad), max(reg.cy0, y0 - pad)
            wx1, wy1 = min(reg.cx1, x1 + pad), min(reg.cy1, y1 + pad)
            mask = np.zeros((wy1 - wy0, wx1 - wx0), np.uint8)
            mask[y0 - wy0:y1 - wy0, x0 - wx0:x1 - wx0] = 255
            return self._corners_in((wx0, wy0, wx1, wy1), mask, want, existing)

        found = self._map(corners, cells)
        new = np.concatenate(found).astype(np.float32) if found else np.zeros((0, 2), np.float32)
        return self._add(stamp_ns, new)

    def extract_in(self, stamp_ns: int, mask: np.ndarray, box, want: int) -> int:
        """Up to `want` Shi-Tomasi corners where `mask` (crop pixels, uint8) is set, away from
        existing tracks, their quality relative to the best corner there, not the cell's: a
        region of plain asphalt next to a car's edges gets its own corners. `box`: the
        mask's bounding box (x0, y0, x1, y1) in crop pixels. Returns how many."""
        crop = self._cur_crop
        if crop is None or want <= 0:
            return 0
        reg = self.region
        x0, y0, x1, y1 = box
        pad = self.cfg.block_size
        wx0, wy0 = max(0, x0 - pad), max(0, y0 - pad)
        wx1, wy1 = min(crop.shape[1], x1 + pad), min(crop.shape[0], y1 + pad)
        window = (reg.cx0 + wx0, reg.cy0 + wy0, reg.cx0 + wx1, reg.cy0 + wy1)
        return self._add(stamp_ns, self._corners_in(window, mask[wy0:wy1, wx0:wx1].copy(), int(want), self.pts)
                         .astype(np.float32))

    def _corners_in(self, window, mask: np.ndarray, want: int, existing: np.ndarray) -> np.ndarray:
        """Up to `want` Shi-Tomasi corners of the current crop within `window` (x0, y0, x1, y1,
        full-image pixels) where `mask` (the window's size, uint8) is set and no `existing`
        track (full-image pixels) is nearer than min_distance_px: full-image pixels (M, 2)."""
        cfg, reg = self.cfg, self.region
        wx0, wy0, wx1, wy1 = window
        sub = self._cur_crop[wy0 - reg.cy0:wy1 - reg.cy0, wx0 - reg.cx0:wx1 - reg.cx0]
        # Only features whose exclusion disc reaches this window change the mask.
        r = int(cfg.min_distance_px)
        near = existing[(existing[:, 0] > wx0 - r - 1) & (existing[:, 0] < wx1 + r + 1)
                        & (existing[:, 1] > wy0 - r - 1) & (existing[:, 1] < wy1 + r + 1)]
        # (as Python floats: iterating the float32 rows cost more than drawing; the
        # differences are exact in both, pixels being multiples of 2^-15 below 512)
        for u, v in near.tolist():
            cv2.circle(mask, (int(round(u - wx0)), int(round(v - wy0))), r, 0, -1)
        p = cv2.goodFeaturesToTrack(sub, maxCorners=want, qualityLevel=cfg.quality_level,
                                    minDistance=cfg.min_distance_px, mask=mask,
                                    blockSize=cfg.block_size)
        if p is None:
            return np.zeros((0, 2), np.float32)
        return p.reshape(-1, 2) + np.array([wx0, wy0], np.float32)

    def _add(self, stamp_ns: int, new: np.ndarray) -> int:
        """New tracks at full-image pixels `new`, first seen at stamp_ns."""
        if len(new):
            new_ids = np.arange(self.next_id, self.next_id + len(new), dtype=np.int64)
            self.next_id += len(new)
            H = self.cfg.max_history
            t = np.zeros((len(new), H), np.int64)
            t[:, 0] = stamp_ns
            uv = np.zeros((len(new), H, 2), np.float32)
            uv[:, 0] = new
            self.ids = np.concatenate([self.ids, new_ids])
            self.pts = np.concatenate([self.pts, new])
            self.hist_t = np.concatenate([self.hist_t, t])
            self.hist_uv = np.concatenate([self.hist_uv, uv])
            self.hist_n = np.concatenate([self.hist_n, np.ones(len(new), np.int64)])
        return len(new)

    def drop(self, ids):
        """Forget tracks (e.g. whose landmark proved inconsistent)."""
        ids = np.asarray(list(ids), dtype=np.int64)
        if not len(ids):
            return
        self._keep(~np.isin(self.ids, ids))
