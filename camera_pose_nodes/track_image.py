"""Debug images of the tracker (`debug_images`): a camera's picture with the tracked features,
their recent flow and what each one measures, as /<cam>/tracks (sensor_msgs/Image, bgr8).

Who draws it: a camera's four quarters may run in different worker processes, and only the
quarter knows its tracks. So each quarter draws its own tile, the part of the image it owns,
from the crop it has just tracked (quarter_tile), and publishes it as /<cam>/q<l>/tracks; the
camera arbiter, which already gathers the camera's four quarter estimates by stamp, gathers
the four tiles the same way and puts them side by side (compose_quarters) once it has all
four of a frame, or at its sync timeout (a missing quarter's part is left dark and says so).
Rather than overlays drawn by the arbiter onto the camera's image, because then:
- the arbiter needs no image: it would have to subscribe to the full image of its camera,
  from a worker that may host none of that camera's quarters (one more image reader the
  coordinator's placement and the player's link checks do not know of), and hold images by
  stamp for up to its sync timeout (10 s in lockstep replay) until the overlays come;
- the picture is exactly what the tracker worked on (the crop's pixels, gray as the tracker
  sees them: the image converted to mono, image_conversion) at the moment of the estimate;
- a track never crosses its quarter (one that leaves it is dropped, quarter_region), so a
  tile holds all of its tracks' flow, and a quarter's tile alone is a useful view too;
- with the arbiter on the same worker, the tile goes to it by a call, like the estimates.
The tiles together are the size of one bgr8 image per camera and frame; with the parameter
off (the default) nothing is drawn, published or subscribed.

Colors (BGR), per QuarterEstimator.track_overlay's status: green, a triangulated landmark;
blue, a landmark on the floor (metric depth); yellow, no landmark yet but measured by its
epipolar line; red, new (measures nothing yet). Each feature's line is its path over the last
few frames (the flow), ending at the dot where it is now. ROS-free, tested without ROS.
"""
from typing import Dict, Optional, Sequence, Tuple

import cv2
import numpy as np

from camera_pose_nodes.quarter_estimator import (TRACK_EPIPOLAR, TRACK_FLOOR, TRACK_LANDMARK,
                                                 TRACK_NEW)
from camera_pose_nodes.quarter_region import QuarterRegion

COLORS = {                       # BGR
    TRACK_NEW: (0, 0, 255),          # red
    TRACK_EPIPOLAR: (0, 255, 255),   # yellow
    TRACK_LANDMARK: (0, 255, 0),     # green
    TRACK_FLOOR: (255, 128, 0),      # blue
}
STATUS_NAMES = {TRACK_NEW: 'new', TRACK_EPIPOLAR: 'epipolar', TRACK_LANDMARK: 'landmark',
                TRACK_FLOOR: 'floor landmark'}
TRAIL = 5                        # views per feature's flow line (track_overlay's `trail`)
RADIUS = 2                       # px of a feature's dot
_SHIFT = 2                       # OpenCV fixed-point bits: positions to a quarter pixel
_MISSING_GRAY = 40               # a quarter whose tile did not come


def _fixed(px: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(px, float) * (1 << _SHIFT)).astype(np.int32)


def draw_tracks(img: np.ndarray, trails: np.ndarray, status: np.ndarray,
                offset=(0, 0), radius: int = RADIUS) -> np.ndarray:
    """Draw features into `img` (bgr8, changed in place and returned) whose pixel (0, 0) is
    full-image pixel `offset`: trails (N, K, 2) full-image pixels, the current one last, NaN
    where a track has fewer views; status (N,) TRACK_*. Every line first, then every dot, so
    that no line covers a feature."""
    status = np.asarray(status)
    if not len(status):
        return img
    trails = np.asarray(trails, float).reshape(len(status), -1, 2) - np.asarray(offset, float)
    for path, s in zip(trails, status.tolist()):
        path = path[np.all(np.isfinite(path), axis=1)]
        if len(path) >= 2:
            cv2.polylines(img, [_fixed(path).reshape(-1, 1, 2)], False, COLORS[s], 1,
                          cv2.LINE_8, _SHIFT)
    for path, s in zip(trails, status.tolist()):
        now = path[-1]
        if np.all(np.isfinite(now)):
            cv2.circle(img, tuple(_fixed(now).tolist()), radius << _SHIFT, COLORS[s], -1,
                       cv2.LINE_8, _SHIFT)
    return img


def draw_caption(img: np.ndarray, lines: Sequence[str]) -> np.ndarray:
    """Text in the top-left corner, white on a dark outline (readable on any image)."""
    for i, text in enumerate(lines):
        x, y = 3, 11 + 11 * i
        # the outline: the same thin text shifted around (a thicker one is wider too)
        for dx, dy in ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)):
            cv2.putText(img, text, (x + dx, y + dy), cv2.FONT_HERSHEY_PLAIN, 0.8, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_PLAIN, 0.8, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def quarter_tile(crop: np.ndarray, region: QuarterRegion, trails: np.ndarray,
                 status: np.ndarray, caption: Sequence[str] = ()) -> np.ndarray:
    """The quarter's tile: its owned rectangle of `crop` (the tracker's gray crop, owned part
    plus margin) as bgr8, with its tracks and `caption` drawn."""
    owned = crop[region.y0 - region.cy0:region.y1 - region.cy0,
                 region.x0 - region.cx0:region.x1 - region.cx0]
    tile = cv2.cvtColor(np.ascontiguousarray(owned), cv2.COLOR_GRAY2BGR)
    draw_tracks(tile, trails, status, offset=(region.x0, region.y0))
    return draw_caption(tile, caption)


def quarter_layout(sizes: Dict[int, Tuple[int, int]]) -> Optional[Tuple[Tuple[int, int], Tuple[int, int]]]:
    """((left, right) column widths, (top, bottom) row heights) of the camera image from the
    tile sizes {quarter: (width, height)} seen so far (1 top-left .. 4 bottom-right); a side
    no tile has shown yet takes the other's. None before any tile."""
    def pick(a, b, i):
        for q in (a, b):
            if q in sizes:
                return sizes[q][i]
        return None
    left, right = pick(1, 3, 0), pick(2, 4, 0)
    top, bottom = pick(1, 2, 1), pick(3, 4, 1)
    if left is None and right is None:
        return None
    left, right = left or right, right or left
    top, bottom = top or bottom, bottom or top
    return (left, right), (top, bottom)


def compose_quarters(tiles: Dict[int, np.ndarray], sizes: Dict[int, Tuple[int, int]]) -> Optional[np.ndarray]:
    """The camera image (bgr8) from the quarters' tiles {quarter: (h, w, 3) uint8}; `sizes`:
    every tile size seen so far (quarter_layout). A quarter without a tile is left dark,
    labelled. None when no layout is known yet."""
    layout = quarter_layout(sizes)
    if layout is None:
        return None
    (left, right), (top, bottom) = layout
    img = np.full((top + bottom, left + right, 3), _MISSING_GRAY, np.uint8)
    for q in (1, 2, 3, 4):
        col, row = (q - 1) % 2, (q - 1) // 2
        x0, y0 = (0, left)[col], (0, top)[row]
        w, h = (left, right)[col], (top, bottom)[row]
        tile = tiles.get(q)
        if tile is not None and tile.shape[:2] == (h, w):
            img[y0:y0 + h, x0:x0 + w] = tile
        else:
            draw_caption(img[y0:y0 + h, x0:x0 + w], [f'q{q}: no tile' if tile is None
                                                     else f'q{q}: tile {tile.shape[1]}x{tile.shape[0]}?'])
    return img
