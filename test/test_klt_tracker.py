"""KLT extraction and tracking inside one quarter, on synthetic textures."""
import numpy as np
import pytest

from camera_pose_nodes.klt_tracker import KLTConfig, KLTTracker, margin_for
from camera_pose_nodes.quarter_region import QuarterRegion

W, H = 640, 480


def texture(seed=0, dx=0.0, dy=0.0, w=W, h=H):
    """Sum of random plane waves sampled at (x - dx, y - dy): an exact sub-pixel shift
    (warping a raster would quantise the shift to OpenCV's 1/32 px interpolation table)."""
    rng = np.random.default_rng(seed)
    n = 60
    lam = rng.uniform(6, 40, n)
    th = rng.uniform(0, np.pi, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    kx, ky = 2 * np.pi * np.cos(th) / lam, 2 * np.pi * np.sin(th) / lam
    x = np.arange(w, dtype=np.float64) - dx
    y = np.arange(h, dtype=np.float64) - dy
    # separable: cos(kx x + ky y + ph) = Re(e^{i kx x} e^{i ky y} e^{i ph})
    ex = np.exp(1j * np.outer(kx, x))                   # (n, w)
    ey = np.exp(1j * (np.outer(ky, y) + ph[:, None]))   # (n, h)
    img = np.real(ey.T @ ex)
    img = 0.5 + img / (2.5 * np.sqrt(n))             # fixed scaling: same for every shift
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


def shifted(seed, dx, dy):
    return texture(seed, dx, dy)


def same_history(a, b) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ('ids', 'hist_t', 'hist_uv', 'hist_n'))


def make(cfg=None, quarter=1):
    cfg = cfg or KLTConfig()
    reg = QuarterRegion.of(quarter, W, H, margin_for(cfg))
    return KLTTracker(reg, cfg), reg


def test_subpixel_shift_is_tracked_to_a_tenth_of_a_pixel():
    tr, reg = make()
    tr.track(0, reg.crop(shifted(0, 0, 0)))
    tr.extract(0)
    assert len(tr.ids) >= tr.cfg.min_features
    start = dict(zip(tr.ids.tolist(), tr.pts.copy()))
    n0 = len(start)
    for k, (dx, dy) in enumerate([(0.3, -0.2), (1.05, 0.55), (2.7, 1.3), (4.45, 2.15)], start=1):
        tr.track(k, reg.crop(shifted(0, dx, dy)))
        p0 = np.array([start[i] for i in tr.ids.tolist()])
        err = np.linalg.norm(tr.pts - p0 - [dx, dy], axis=1)
        assert err.max() < 0.1, err.max()
    print(f'\nKLT: {len(tr.ids)}/{n0} tracks kept, max error {err.max():.3f} px, '
          f'median {np.median(err):.3f} px')
    assert len(tr.ids) > 0.8 * n0
    assert all(len(tr.history_of(i)) == 5 for i in tr.ids.tolist())


def test_forward_backward_check_rejects_a_changed_patch():
    tr, reg = make()
    tr.track(0, reg.crop(shifted(0, 0, 0)))
    tr.extract(0)
    nxt = shifted(0, 0.5, 0.5)
    # replace a 100x100 block by unrelated texture (an occluder)
    nxt[40:140, 40:140] = shifted(9, 0, 0)[40:140, 40:140]
    inside = ((tr.pts[:, 0] > 52) & (tr.pts[:, 0] < 128) & (tr.pts[:, 1] > 52) & (tr.pts[:, 1] < 128))
    assert inside.sum() >= 2
    gone = set(tr.ids[inside].tolist())
    outside = set(tr.ids[~inside].tolist())
    tr.track(1, reg.crop(nxt))
    kept = set(tr.ids.tolist())
    assert not (gone & kept)
    assert len(outside & kept) > 0.8 * len(outside)


def test_extraction_only_below_min_features_and_away_from_tracks():
    tr, reg = make(KLTConfig(min_features=30, max_features=60))
    tr.track(0, reg.crop(shifted(0, 0, 0)))
    assert tr.needs_features()
    n = tr.extract(0)
    assert 30 <= n <= 60
    tr.track(1, reg.crop(shifted(0, 0.5, 0)))
    assert not tr.needs_features()
    tr.drop(tr.ids[:len(tr.ids) - 10])                  # occlusion of most features
    assert tr.needs_features()
    keep = tr.pts.copy()
    assert tr.extract(1) > 0
    new = tr.pts[10:]
    d = np.linalg.norm(new[:, None] - keep[None], axis=2)
    assert d.min() >= tr.cfg.min_distance_px - 1e-3
    assert np.all(reg.owns(tr.pts))
    assert len(np.unique(tr.ids)) == len(tr.ids)


def test_tracks_leaving_the_quarter_are_dropped():
    tr, reg = make(quarter=1)
    tr.track(0, reg.crop(shifted(0, 0, 0)))
    tr.extract(0)
    tr.track(1, reg.crop(shifted(0, 6.0, 0)))
    assert np.all(reg.owns(tr.pts))
    assert tr.pts[:, 0].max() < reg.x1


def test_chunked_parallel_equals_sequential():
    seq, reg = make(KLTConfig(min_features=12, max_features=70))
    par, _ = make(KLTConfig(min_features=12, max_features=70, parallel_chunks=True))
    assert par.n_chunks(70) == 6
    shifts = [(0, 0), (0.4, 0.1), (1.2, -0.7), (2.5, -1.0), (6.0, -2.0)]
    for k, (dx, dy) in enumerate(shifts):
        frame = reg.crop(shifted(3, dx, dy))
        for t in (seq, par):
            t.track(k, frame)
            if t.needs_features():
                t.extract(k)
        assert np.array_equal(seq.ids, par.ids)
        assert np.array_equal(seq.pts, par.pts)
    assert same_history(seq, par)
    par.close()


def test_flow_computed_before_a_drop_tracks_the_rest_identically():
    """A quarter computes the next flow before the last fused pose drops tracks (pipelining):
    tracking with that flow after the drop equals tracking after the drop without it."""
    a, reg = make()
    b, _ = make()
    for tr in (a, b):
        tr.track(0, reg.crop(shifted(0, 0, 0)))
        tr.extract(0)
    nxt = reg.crop(shifted(0, 1.3, -0.7))
    flow = b.flow(nxt)
    assert np.array_equal(flow.ids, b.ids) and np.array_equal(b.prev_crop, a.prev_crop)
    gone = a.ids[::3]
    a.drop(gone)
    b.drop(gone)
    a.track(1, nxt)
    b.track(1, nxt, flow)
    assert np.array_equal(a.ids, b.ids) and np.array_equal(a.pts, b.pts)
    assert same_history(a, b) and len(a.ids) > 0
    assert not set(gone.tolist()) & set(b.ids.tolist())
    # a flow that lacks tracks (extracted since) is refused rather than mixed in
    assert b.extract(1) > 0
    with pytest.raises(ValueError, match='other tracks'):
        b.track(2, nxt, flow)


def test_history_keeps_the_oldest_view_and_the_newest_ones():
    """max_history views per track: when full, the second-oldest goes (the oldest has the
    parallax); hand-over carries the history."""
    tr, reg = make(KLTConfig(max_history=4))
    tr.track(0, reg.crop(shifted(0, 0, 0)))
    tr.extract(0)
    for k in range(1, 7):
        tr.track(k, reg.crop(shifted(0, 0.3 * k, 0)))
    i = int(tr.ids[0])
    assert [t for t, _, _ in tr.history_of(i)] == [0, 4, 5, 6]
    assert np.array_equal(tr.last_stamps(), np.full(len(tr.ids), 6))
    assert np.allclose(tr.last_px(), tr.pts)
    moved, _ = make(KLTConfig(max_history=4))
    moved.set_state(tr.get_state())
    assert same_history(tr, moved) and moved.history_of(i) == tr.history_of(i)
    with pytest.raises(ValueError, match='history'):
        make()[0].set_state(tr.get_state())          # another max_history


def road_step(t_forward=0.8, height=1.65, f=300.0):
    """The floor's homography (previous -> new pixels) of a camera looking along the road,
    `height` above it, moving `t_forward` m ahead: near road patches grow and shear."""
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    n = np.array([0.0, 1.0, 0.0])                    # the floor's down in the camera
    Hm = K @ (np.eye(3) - np.outer([0, 0, t_forward], n) / height) @ np.linalg.inv(K)
    return Hm / Hm[2, 2]


def test_lost_floor_tracks_are_found_on_the_road_warped_image():
    """A car's step over the road: lower-image patches grow by ~25 % and move 20-80 px.
    Lucas-Kanade from the floor's own prediction loses most of them; searched again on the
    previous image warped by the floor's homography, the tracks known to lie on the floor
    come back where the homography puts them. Tracks not known on the floor stay lost, and
    with floor_warp_min_flow_px 0 nothing is searched again."""
    import cv2
    from camera_pose_nodes.flow_prediction import FloorWarp

    Hm = road_step()
    img0 = texture(3)
    img1 = cv2.warpPerspective(img0, Hm, (W, H), flags=cv2.INTER_CUBIC)

    def run(cfg, on_floor):
        tr, reg = make(cfg, quarter=3)
        tr.track(0, reg.crop(img0))
        tr.extract(0)
        p0 = tr.pts.astype(np.float64)
        truth = cv2.perspectiveTransform(p0.reshape(-1, 1, 2), Hm).reshape(-1, 2)
        predict = (lambda px, rows: truth[rows], lambda px, rows: p0[rows])
        flow = tr.flow(reg.crop(img1), predict, FloorWarp(Hm, on_floor(len(p0))))
        inside = reg.owns(truth)
        moved = np.linalg.norm(truth - p0, axis=1) > 15
        return flow, truth, inside & moved

    on = KLTConfig(floor_warp_min_flow_px=15.0)
    plain, truth, judged = run(on, lambda n: np.zeros(n, bool))
    warped, truth_w, judged_w = run(on, lambda n: np.ones(n, bool))
    assert np.array_equal(truth, truth_w) and judged.sum() >= 20
    kept_plain, kept_warp = plain.ok[judged].mean(), warped.ok[judged].mean()
    found = judged & warped.ok & ~plain.ok
    err = np.linalg.norm(warped.new - truth, axis=1)[found]
    err_plain = np.linalg.norm(plain.new - truth, axis=1)[judged & plain.ok]
    print(f'\nroad step: {judged.sum()} tracks, plain LK keeps {kept_plain:.0%} (error median '
          f'{np.median(err_plain):.2f} px, max {err_plain.max():.2f}), with the floor warp {kept_warp:.0%}: '
          f'the {found.sum()} found again within {np.median(err):.2f} px median, {err.max():.2f} max')
    assert kept_warp > 0.8 and kept_warp > kept_plain + 0.3
    assert np.median(err) < 0.15 and err.max() < 0.5
    assert not plain.recovered.any() and np.array_equal(warped.recovered, warped.ok & ~plain.ok)
    # the tracks plain LK kept are untouched by the recovery
    both = plain.ok & judged
    assert np.array_equal(warped.new[both], plain.new[both])
    off, _, _ = run(KLTConfig(floor_warp_min_flow_px=0.0), lambda n: np.ones(n, bool))
    assert np.array_equal(off.ok, plain.ok) and np.array_equal(off.new[off.ok], plain.new[plain.ok])


def test_a_plain_region_gets_corners_ranked_against_its_own_best():
    """A quarter whose right part is plain (asphalt beside a car's edges: a twentieth of the
    contrast): extraction by grid cell ranks corners against the cell's best and finds none
    there; extract_in ranks them against the best inside its mask and fills the region,
    away from the tracks there are and inside the mask only."""
    strong = texture(5).astype(np.float32)
    weak = 128.0 + (texture(6).astype(np.float32) - 128.0) / 20.0
    img = np.where(np.arange(W)[None, :] < 160, strong, weak).round().astype(np.uint8)
    cfg = KLTConfig(grid_rows=1, grid_cols=1)
    tr, reg = make(cfg, quarter=1)
    crop = reg.crop(img)
    tr.track(0, crop)
    tr.extract(0)
    n0 = len(tr.ids)
    assert n0 >= 20 and not (tr.pts[:, 0] >= 170).any()
    mask = np.zeros(crop.shape, np.uint8)
    x0, x1, y1 = 170 - reg.cx0, reg.x1 - reg.cx0, reg.y1 - reg.cy0
    mask[:y1, x0:x1] = 255
    n = tr.extract_in(0, mask, (x0, 0, x1, y1), 15)
    new = tr.pts[n0:]
    print(f'\nplain region: {n} corners ranked against its own best, none by the cell\'s ({n0} elsewhere)')
    assert n == 15 and len(tr.ids) == n0 + 15
    assert (new[:, 0] >= 170).all() and (new[:, 0] < reg.x1).all() and (new[:, 1] < reg.y1).all()
    gaps = np.linalg.norm(new[:, None] - tr.pts[None, :n0], axis=2)
    assert gaps.min() >= cfg.min_distance_px
    assert (tr.hist_t[n0:, 0] == 0).all() and (tr.hist_n[n0:] == 1).all()
