"""Debug images of the tracker (camera_pose_nodes.track_image, QuarterEstimator.track_overlay),
without ROS: features drawn where they are, in their status's color, with their flow line; a
quarter's tile; the camera image put together from the tiles."""
import pickle

import numpy as np
import pytest

from camera_pose_nodes.quarter_estimator import (TRACK_EPIPOLAR, TRACK_FLOOR, TRACK_LANDMARK,
                                                 TRACK_NEW, QuarterEstimator, QuarterParams)
from camera_pose_nodes.quarter_region import QuarterRegion
from camera_pose_nodes.track_image import (COLORS, RADIUS, compose_quarters, draw_tracks,
                                           quarter_layout, quarter_tile)
from test_quarter_estimator import PARAMS, scene, step  # noqa: F401  (scene: a fixture)

NAN = np.nan
GRAY = 100


def plain(w=160, h=120):
    return np.full((h, w, 3), GRAY, np.uint8)


def color_at(img, u, v):
    return tuple(int(c) for c in img[int(round(v)), int(round(u))])


def test_every_status_has_its_own_color_away_from_the_gray_of_an_image():
    colors = [COLORS[s] for s in (TRACK_NEW, TRACK_EPIPOLAR, TRACK_LANDMARK, TRACK_FLOOR)]
    assert len(set(colors)) == 4
    assert all(max(c) - min(c) >= 128 for c in colors)      # saturated: never a gray


def test_features_are_drawn_where_they_are_in_their_status_color_with_their_flow():
    img = plain()
    # current positions last; a track with fewer views is NaN before its first
    trails = np.array([
        [[NAN, NAN], [NAN, NAN], [NAN, NAN], [20.0, 20.0]],        # new: a dot only
        [[NAN, NAN], [NAN, NAN], [40.0, 60.0], [60.0, 60.0]],      # epipolar, moved 20 px right
        [[100.0, 20.0], [100.0, 30.0], [100.0, 40.0], [100.0, 50.0]],   # landmark, going down
        [[140.0, 100.0], [140.0, 100.0], [139.5, 100.0], [139.25, 100.25]],  # floor, sub-pixel
    ])
    status = np.array([TRACK_NEW, TRACK_EPIPOLAR, TRACK_LANDMARK, TRACK_FLOOR], np.uint8)
    before = img.copy()
    assert draw_tracks(img, trails, status) is img
    for (u, v), s in zip(trails[:, -1], status):
        assert color_at(img, u, v) == COLORS[s]
        # the dot covers its radius around the feature
        assert color_at(img, u + RADIUS, v) == COLORS[s] and color_at(img, u, v - RADIUS) == COLORS[s]
    # flow lines: along the path, in the track's color
    for u in (45, 50, 55):
        assert color_at(img, u, 60) == COLORS[TRACK_EPIPOLAR]
    for v in (22, 30, 38, 44):
        assert color_at(img, 100, v) == COLORS[TRACK_LANDMARK]
    # nothing before a track's first view: no line to the left of the new feature's dot
    assert color_at(img, 20 - RADIUS - 2, 20) == (GRAY,) * 3
    assert color_at(img, 40 - 2, 60) == (GRAY,) * 3      # the epipolar track's path starts at 40
    # only the features and their lines changed
    changed = np.any(img != before, axis=2)
    near = np.zeros_like(changed)
    for path in trails:
        for u, v in path[np.all(np.isfinite(path), axis=1)]:
            near[max(0, int(v) - RADIUS - 1):int(v) + RADIUS + 2, max(0, int(u) - RADIUS - 1):int(u) + RADIUS + 2] = True
    near[20:51, 99:102] = True              # the landmark's line
    near[59:62, 40:61] = True               # the epipolar one's
    assert changed.any() and not (changed & ~near).any()


def test_an_offset_image_draws_full_image_pixels_at_their_place_in_it():
    img = plain(50, 40)
    draw_tracks(img, np.array([[[210.0, 130.0]]]), np.array([TRACK_LANDMARK]), offset=(200, 100))
    assert color_at(img, 10, 30) == COLORS[TRACK_LANDMARK]
    # no tracks (a quarter that lost them all): nothing drawn
    before = img.copy()
    draw_tracks(img, np.zeros((0, 5, 2), np.float32), np.zeros(0, np.uint8))
    assert np.array_equal(img, before)
    # features outside (other quarters' pixels) are clipped, not an error
    draw_tracks(img, np.array([[[10.0, 10.0]], [[NAN, NAN]]]), np.array([TRACK_NEW, TRACK_NEW]),
                offset=(200, 100))


def test_a_quarter_tile_is_its_owned_part_of_the_crop_with_its_tracks_and_caption():
    W, H = 321, 241                         # odd: the right and bottom quarters are wider
    full = (np.arange(W)[None, :] % 200 + np.arange(H)[:, None] % 50).astype(np.uint8)
    reg = QuarterRegion.of(4, W, H, 15)
    crop = reg.crop(full)
    pt = np.array([[[NAN, NAN], [200.0, 180.0], [210.0, 190.0]]])
    tile = quarter_tile(crop, reg, pt, np.array([TRACK_FLOOR]), caption=['q4 tracking'])
    assert tile.shape == (H - H // 2, W - W // 2, 3) and tile.dtype == np.uint8
    assert color_at(tile, 210 - reg.x0, 190 - reg.y0) == COLORS[TRACK_FLOOR]
    assert color_at(tile, 205 - reg.x0, 185 - reg.y0) == COLORS[TRACK_FLOOR]     # its flow
    # elsewhere the gray pixels of the image it owns (the caption in the top-left corner)
    owned = full[reg.y0:reg.y1, reg.x0:reg.x1]
    same = np.all(tile == owned[:, :, None], axis=2)
    assert same[20:, :].mean() > 0.99 and not same[:12, :60].all()


def test_the_camera_image_is_put_together_from_the_quarters_tiles():
    W, H = 321, 241
    sizes, tiles = {}, {}
    for q in (1, 2, 3, 4):
        r = QuarterRegion.of(q, W, H, 0)
        tiles[q] = np.full((r.y1 - r.y0, r.x1 - r.x0, 3), 50 * q, np.uint8)
        sizes[q] = (r.x1 - r.x0, r.y1 - r.y0)
    img = compose_quarters(tiles, sizes)
    assert img.shape == (H, W, 3)
    for q in (1, 2, 3, 4):
        r = QuarterRegion.of(q, W, H, 0)
        assert np.all(img[r.y0:r.y1, r.x0:r.x1] == 50 * q)
    # a quarter whose tile did not come is dark and says so; the others are in place
    img = compose_quarters({1: tiles[1], 2: tiles[2], 4: tiles[4]}, sizes)
    r3 = QuarterRegion.of(3, W, H, 0)
    part = img[r3.y0:r3.y1, r3.x0:r3.x1]
    assert img.shape == (H, W, 3) and np.all(img[:H // 2, :W // 2] == 50)
    assert np.median(part) == 40 and part.max() == 255           # text on dark gray
    # the size of a quarter no tile has shown yet comes from its neighbours
    assert quarter_layout({1: sizes[1]}) == ((160, 160), (120, 120))
    assert quarter_layout({2: sizes[2], 3: sizes[3]}) == ((160, 161), (120, 121))
    assert compose_quarters({}, {}) is None


def test_track_overlay_reads_the_tracks_and_changes_nothing(scene):
    cam, intr, frames, images = scene
    est = QuarterEstimator(cam, 1, intr, PARAMS)
    prev, seen = {}, set()
    for k, ((stamp, T), img) in enumerate(zip(frames[:20], images[:20])):
        step(est, k, stamp, img, T)
        before = pickle.dumps(est.get_state())
        trails, status = est.track_overlay(4)
        assert pickle.dumps(est.get_state()) == before          # read-only
        tr = est.tracker
        assert trails.shape == (len(tr.ids), 4, 2) and status.shape == (len(tr.ids),)
        assert np.array_equal(trails[:, -1], tr.pts)
        # the line ends where each track was the frame before
        for i, tid in enumerate(tr.ids.tolist()):
            if tid in prev:
                assert np.array_equal(trails[i, -2], prev[tid])
            n = int(tr.hist_n[i])
            assert np.isnan(trails[i, :max(0, 4 - n)]).all() and np.isfinite(trails[i, 4 - min(n, 4):]).all()
        prev = dict(zip(tr.ids.tolist(), tr.pts.copy()))
        has, _ = est.landmarks.rows(tr.ids)
        assert np.array_equal(has, np.isin(status, (TRACK_LANDMARK, TRACK_FLOOR)))
        assert not np.any(status == TRACK_FLOOR)                 # no floor in this scene
        seen |= set(status.tolist())
        if k == 1:      # the first frame's tracks: one earlier view, fused: epipolar lines
            assert len(status) and np.all(status == TRACK_EPIPOLAR)
    assert {TRACK_LANDMARK, TRACK_EPIPOLAR} <= seen
    # with the epipolar update off, tracks without a landmark measure nothing: new
    est = QuarterEstimator(cam, 1, intr, QuarterParams(parallax_deg=1.5, epipolar=False))
    for k in range(2):
        step(est, k, frames[k][0], images[k], frames[k][1])
    status = est.track_overlay(4)[1]
    assert len(status) and np.all(status == TRACK_NEW)


def test_track_overlay_lines_leave_out_the_oldest_view_kept_in_a_full_history(scene):
    # A full history keeps its oldest view (parallax) in slot 0 and slides the rest: a line
    # through it would jump back to where the track began.
    cam, intr, frames, images = scene
    est = QuarterEstimator(cam, 1, intr, QuarterParams(parallax_deg=1.5, max_history=3))
    prev = {}
    for k, ((stamp, T), img) in enumerate(zip(frames[:6], images[:6])):
        step(est, k, stamp, img, T)
        trails, _ = est.track_overlay(4)
        tr = est.tracker
        for i, tid in enumerate(tr.ids.tolist()):
            finite = np.isfinite(trails[i]).all(axis=1)
            assert finite.sum() == min(int(tr.hist_n[i]), 2)
            if tid in prev:
                assert np.array_equal(trails[i, -2], prev[tid])
        prev = dict(zip(tr.ids.tolist(), tr.pts.copy()))
    assert (est.tracker.hist_n == 3).any()
