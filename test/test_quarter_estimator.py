"""QuarterEstimator end to end on rendered pixels, with the arbiters simulated."""
import pickle

import numpy as np
import cv2
import pytest

from camera_pose_nodes.camera_model import CameraIntrinsics
from camera_pose_nodes.quarter_estimator import PARAMETERS, QuarterEstimator, QuarterParams
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import paper_rig

W, H, F = 640, 480, 400.0
RATE = 30.0
TEXEL = 0.01                                # metres per texture pixel
WALL_X = 4.0                                # a textured wall at x = 4 m in odom


def wall_texture(seed=0):
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (900, 1200)).astype(np.float32), (0, 0), 1.5)
    t = cv2.normalize(t, None, 0, 255, cv2.NORM_MINMAX)
    return t.astype(np.uint8)


def render_plane(tex, K, T_odom_cam, X0, e1, e2, texel, size):
    """Pinhole image (size w, h) of a textured plane: texel (s, t) is the point X0 + s texel
    e1 + t texel e2, so the texture->image map is the homography K [R^T texel e1, R^T texel e2,
    R^T (X0 - c)]."""
    Rt, c = T_odom_cam[:3, :3].T, T_odom_cam[:3, 3]
    Hm = K @ np.column_stack([Rt @ np.asarray(e1) * texel, Rt @ np.asarray(e2) * texel, Rt @ (np.asarray(X0) - c)])
    return cv2.warpPerspective(tex, Hm, size, flags=cv2.INTER_LINEAR)


def render(tex, K, T_odom_cam):
    """Pinhole image of the wall at x = WALL_X."""
    return render_plane(tex, K, T_odom_cam, [WALL_X, 6.0, 4.5], [0, -1.0, 0], [0, 0, -1.0], TEXEL, (W, H))


def true_pose(t):
    return se3.make_T(se3.rotvec_to_R([0, 0, 0.1 * t]), [0.2 * t, 0.5 * t, 0.0])


def rendered_front(pose, rate, n, seed=0):
    """The paper rig's front camera, its intrinsics, n (stamp, body pose) at `rate` Hz on
    `pose(t)`, and the wall as that camera sees it from each."""
    cam = paper_rig().camera('front')
    intr = CameraIntrinsics.pinhole(F, F, W / 2, H / 2, W, H)
    tex = wall_texture(seed)
    frames = [(int(1e9 * k / rate), pose(k / rate)) for k in range(n)]
    images = [render(tex, intr.K, T @ cam.T_base_cam) for _, T in frames]
    return cam, intr, frames, images


@pytest.fixture(scope='module')
def scene():
    return rendered_front(true_pose, RATE, 60)


PARAMS = QuarterParams(parallax_deg=1.5)
N_TRUE = 12                                 # frames with the true fused pose fed back


def step(est, k, stamp, img, T_true, small=np.eye(6) * 1e-8):
    e = est.process_image(stamp, img)
    if k < N_TRUE:
        est.apply_fused_pose(stamp, T_true, small)
    elif e.state == 'tracking':             # simulated arbiters: the quarter's own estimate
        est.apply_fused_pose(stamp, e.T_odom_base, e.covariance)
    return e


def test_tracks_rendered_sequence_and_hands_over_bit_identically(scene):
    cam, intr, frames, images = scene
    est = QuarterEstimator(cam, 1, intr, PARAMS)
    out, snap, stages = [], None, []
    for k, ((stamp, T), img) in enumerate(zip(frames, images)):
        if k == 30:
            snap = pickle.dumps(est.get_state())
        e = step(est, k, stamp, img, T)
        out.append(e)
        stages.append(e.stage_ms)
        assert e.source == 'front/q1'
        assert set(e.stage_ms) == {'acquire', 'extract', 'track', 'pose', 'structure'}
        assert np.all(np.isfinite(e.T_odom_base)) and np.all(np.isfinite(e.covariance))
    assert out[0].state == 'initializing' and out[0].covariance[0, 0] >= 1e6
    tracked = [k for k, e in enumerate(out) if e.state == 'tracking']
    assert tracked and tracked[0] < N_TRUE and all(k in tracked for k in range(N_TRUE, 60))
    err = np.array([se3.pose_error(out[k].T_odom_base, frames[k][1]) for k in range(N_TRUE, 60)])
    pos, rot = np.linalg.norm(err[:, :3], axis=1), np.degrees(np.linalg.norm(err[:, 3:], axis=1))
    ms = {s: np.mean([st[s] for st in stages[1:]]) for s in stages[0]}
    print(f'\nquarter: pos err max {1e3 * pos.max():.1f} mm (end {1e3 * pos[-1]:.1f}), rot err max '
          f'{rot.max():.3f} deg; features {out[-1].n_features}, landmarks {out[-1].n_landmarks}, '
          f'inliers {out[-1].n_inliers}; stage ms ' + ', '.join(f'{s} {v:.2f}' for s, v in ms.items()))
    assert pos.max() < 0.05 and rot.max() < 0.5
    for e in out[N_TRUE:]:
        assert np.linalg.eigvalsh(e.covariance).min() > 0

    # hand-over: a fresh estimator (another process) continues from the pickled state
    other = QuarterEstimator(cam, 1, intr, PARAMS)
    other.set_state(pickle.loads(snap))
    for k in range(30, 60):
        stamp, T = frames[k]
        e = step(other, k, stamp, images[k], T)
        ref = out[k]
        assert np.array_equal(e.T_odom_base, ref.T_odom_base)
        assert np.array_equal(e.covariance, ref.covariance)
        assert (e.state, e.n_features, e.n_landmarks, e.n_inliers) == \
            (ref.state, ref.n_features, ref.n_landmarks, ref.n_inliers)


def test_initializing_until_landmarks_and_reset(scene):
    cam, intr, frames, images = scene
    est = QuarterEstimator(cam, 2, intr, PARAMS)
    e = est.process_image(frames[0][0], images[0])
    # nothing tracked yet; the first features are extracted once the estimate is out
    assert e.state == 'initializing' and not e.informative and e.n_features == 0
    assert est.extraction_due()
    est.apply_fused_pose(frames[0][0], frames[0][1], np.eye(6) * 1e-6)
    assert not est.extraction_due() and len(est.tracker.ids) > 0
    e = est.process_image(frames[1][0], images[1])
    assert e.state == 'initializing' and e.n_features > 0
    # the prediction is the fused pose of the previous frame propagated (zero velocity yet)
    assert np.allclose(e.T_odom_base, frames[0][1], atol=1e-9)
    est.reset()
    assert len(est.tracker.ids) == 0 and len(est.landmarks) == 0 and not est.fused_poses


def test_rejects_bad_input(scene):
    cam, intr, frames, images = scene
    est = QuarterEstimator(cam, 1, intr, PARAMS)
    with pytest.raises(UserError, match='expected 640x480'):
        est.process_image(0, images[0][:100])
    with pytest.raises(UserError, match='gray uint8'):
        est.process_image(0, images[0].astype(np.float32))
    with pytest.raises(UserError, match='quarter must be 1..4'):
        QuarterEstimator(cam, 5, intr, PARAMS)
    with pytest.raises(UserError, match='min_features'):
        QuarterParams(min_features=0).validate()
    with pytest.raises(UserError, match='different parameters'):
        QuarterEstimator(cam, 1, intr, QuarterParams()).set_state(est.get_state())


def test_parameter_table_matches_dataclass():
    p = QuarterParams()
    for name, (default, desc, lo, hi) in PARAMETERS.items():
        assert getattr(p, name) == default and desc
        assert lo is None or lo <= default <= hi
    assert set(PARAMETERS) == set(vars(p))


def test_features_extracted_early_or_when_needed_give_the_same_estimates(scene):
    """A worker extracts a frame's new features in its idle time after the estimate went out
    (they take no part in it); without that they are extracted when first needed (the fused
    pose's structure, the next frame). Same estimates, same tracks; the extraction's CPU time
    is reported with the next estimate."""
    cam, intr, frames, images = scene
    early = QuarterEstimator(cam, 3, intr, PARAMS)
    late = QuarterEstimator(cam, 3, intr, PARAMS)
    extracted = 0
    for k, ((stamp, T), img) in enumerate(zip(frames, images)):
        ref = step(late, k, stamp, img, T)
        e = early.process_image(stamp, img)
        due = early.extraction_due()
        if due:
            extracted += 1
            n = len(early.tracker.ids)
            early.extract_pending()
            assert len(early.tracker.ids) > n and not early.extraction_due()
        if k < N_TRUE:
            early.apply_fused_pose(stamp, T, np.eye(6) * 1e-8)
        elif e.state == 'tracking':
            early.apply_fused_pose(stamp, e.T_odom_base, e.covariance)
        assert np.array_equal(e.T_odom_base, ref.T_odom_base)
        assert np.array_equal(e.covariance, ref.covariance)
        assert (e.state, e.n_features, e.n_landmarks, e.n_inliers) == \
            (ref.state, ref.n_features, ref.n_landmarks, ref.n_inliers)
        if not late.extraction_due():       # (no fused pose came to make it extract)
            assert np.array_equal(early.tracker.ids, late.tracker.ids)
        if k and extracted_before:
            assert e.stage_ms['extract'] > 0.0
        extracted_before = due
    assert extracted >= 2


def test_prefetched_flow_gives_the_same_estimates(scene):
    """Pipelining: the next image's optical flow computed before the fused pose of the last
    frame is applied (which drops tracks whose landmark stopped fitting) gives bit-identical
    estimates, and the flow's CPU time still counts as the track stage."""
    cam, intr, frames, images = scene
    plain = QuarterEstimator(cam, 1, intr, PARAMS)
    piped = QuarterEstimator(cam, 1, intr, PARAMS)
    fused = None            # the pipelined quarter's fused pose still to apply
    used = 0
    for k, ((stamp, T), img) in enumerate(zip(frames, images)):
        ref = step(plain, k, stamp, img, T)
        if fused is not None:
            piped.prefetch(stamp, img)          # the image came before the fused pose
            assert piped.prefetched(stamp)
            piped.apply_fused_pose(*fused)
            used += piped.prefetched(stamp)
        e = piped.process_image(stamp, None if piped.prefetched(stamp) else img)
        assert not piped.prefetched(stamp)
        fused = None
        if k < N_TRUE:
            fused = (stamp, T, np.eye(6) * 1e-8)
        elif e.state == 'tracking':
            fused = (stamp, e.T_odom_base, e.covariance)
        assert np.array_equal(e.T_odom_base, ref.T_odom_base)
        assert np.array_equal(e.covariance, ref.covariance)
        assert (e.state, e.n_features, e.n_landmarks, e.n_inliers) == \
            (ref.state, ref.n_features, ref.n_landmarks, ref.n_inliers)
        if k:
            assert e.stage_ms['track'] > 0.0
    assert used == len(frames) - 1
    # a prefetch of another stamp is not used
    piped.prefetch(frames[-1][0] + 1, images[-1])
    assert not piped.prefetched(frames[-1][0] + 2)
    with pytest.raises(ValueError, match='none prefetched'):
        piped.process_image(frames[-1][0] + 2, None)


def swing_pose(t):
    """Yawing back and forth at up to 1.5 rad/s: features move up to 20 px a frame at 30 Hz."""
    return se3.make_T(se3.rotvec_to_R([0, 0, 0.3 * np.sin(2 * np.pi * 0.8 * t)]), [0.3 * t, 0.0, 0.0])


@pytest.fixture(scope='module')
def swing():
    return rendered_front(swing_pose, RATE, 40, seed=1)


def test_tracking_steered_by_the_rotation_is_accurate_and_the_same_prefetched(swing):
    """predict_flow: in a fast swing the search starts where the quarter's angular rate puts
    each feature. The prediction is used, the poses stay as accurate as without it, and a
    flow computed before the fused pose came (prefetch) gives bit-identical estimates."""
    cam, intr, frames, images = swing
    runs = {}
    for predict in (True, False):
        p = QuarterParams(parallax_deg=1.5, predict_flow=predict)
        plain, piped = QuarterEstimator(cam, 1, intr, p), QuarterEstimator(cam, 1, intr, p)
        errs, steered = [], 0
        for k, ((stamp, T), img) in enumerate(zip(frames, images)):
            if k:
                steered += plain._flow_predictor(stamp) is not None
                piped.prefetch(stamp, img)
                piped.apply_fused_pose(frames[k - 1][0], frames[k - 1][1], np.eye(6) * 1e-8)
            e = plain.process_image(stamp, img)
            plain.apply_fused_pose(stamp, T, np.eye(6) * 1e-8)
            f = piped.process_image(stamp, None if piped.prefetched(stamp) else img)
            assert np.array_equal(e.T_odom_base, f.T_odom_base) and e.n_features == f.n_features
            if e.state == 'tracking':
                errs.append(np.linalg.norm(se3.pose_error(e.T_odom_base, T)[3:]))
        runs[predict] = (steered, errs)
    steered, errs = runs[True]
    assert steered >= len(frames) // 2, steered           # the swing is predicted
    assert runs[False][0] == 0
    assert len(errs) >= len(runs[False][1]) - 2           # tracking as often as without
    assert np.median(errs) < 2 * np.median(runs[False][1]) + 1e-3


def test_a_road_quarter_keeps_tracks_in_the_lane_and_sends_them_from_their_first_frame():
    """A camera 1.65 m over a road, looking ahead; its lane is plain asphalt (an eighth of
    the contrast around it). The bottom-left quarter's grid cells fill up with the strong
    corners beside the lane; with road_lane_features it also keeps that many tracks in the
    lane (road_region), ranked against the lane's own best corner. The features extracted
    after a frame's tracks were sent come out of new_bearings() with that frame's stamp, so
    the general arbiter can pair that frame with the next (and on a rig without a road,
    where nothing needs them, none do)."""
    from camera_pose_nodes.road_plane import road_region
    from multicam_ego_motion.geometry.rig import CameraMount, optical_rotation

    w, h = 1240, 376                                                # KITTI's image
    cam = CameraMount('front', '/front/image_raw', '/front/camera_info', 'front_optical',
                      np.array([0.0, 0.0, 1.65]), optical_rotation(0.0))
    intr = CameraIntrinsics.pinhole(720.0, 720.0, w / 2, h / 2, w, h)
    vv, uu = np.mgrid[0:h, 0:w]
    px = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    lane = road_region(intr.undistort_points(px), cam.rotation.T @ [0, 0, -1.0], cam.rotation,
                       1.65).reshape(h, w)
    strong = cv2.resize(wall_texture(4), (w, 900))[:h].astype(np.float32)
    img = np.where(lane, 128.0 + (strong - 128.0) / 8.0, strong).round().astype(np.uint8)

    def first_frame(lane_features, road=True):
        est = QuarterEstimator(cam, 3, intr, QuarterParams(road_lane_features=lane_features),
                               (w, h), 0.0, road)
        est.process_image(0, img)
        est.apply_fused_pose(0, np.eye(4), np.eye(6) * 1e-8)        # extracts
        pts = est.tracker.pts
        in_lane = lane[pts[:, 1].round().astype(int), pts[:, 0].round().astype(int)]
        return est, int(in_lane.sum())

    plain, n_plain = first_frame(0)
    kept, n_kept = first_frame(20)
    print(f'\nlane tracks: {n_plain} by the grid cells alone, {n_kept} with road_lane_features 20 '
          f'({len(kept.tracker.ids)} in the quarter)')
    assert n_plain <= 3 and n_kept >= 20
    stamp, ids, xy, sigma = kept.new_bearings()
    assert stamp == 0 and np.array_equal(ids, kept.tracker.ids) and len(xy) == len(sigma) == len(ids)
    assert np.allclose(xy, intr.undistort_points(kept.tracker.pts))
    assert kept.new_bearings() is None                              # taken once
    e = kept.process_image(int(1e8), img)                           # the same view again
    ids_b, _, _ = kept.bearings()
    assert e is not None and np.isin(ids, ids_b).mean() > 0.9        # pairs (0, 1) for all of them
    off_road, _ = first_frame(20, road=False)
    assert off_road.new_bearings() is None and off_road._lane_shortfall() == 0


def test_a_road_quarter_leans_on_the_near_road_when_the_camera_is_pitched_to_it():
    """A camera 1.65 m over a textured road at car speed (1.2 m a frame), truly pitched 1 deg
    down (or up) from the mount the rig gives it: every point the quarter puts on the road
    (road_landmarks, its floor landmarks) lands too far (too near), the farther the more,
    and the steps it measures against them come out long (short). road_tilt_std_deg gives
    the far road the depth uncertainty that tilt means, so the near road carries the step:
    with 1 deg the step's error is well below ground_plane's indoor 0.2 deg's, and with the
    mount right the steps stay metric."""
    from multicam_ego_motion.geometry.rig import CameraMount, optical_rotation

    w, h, step = 1240, 376, 1.2                                    # KITTI's image and speed
    intr = CameraIntrinsics.pinhole(720.0, 720.0, w / 2, h / 2, w, h)
    cam = CameraMount('front', '/front/image_raw', '/front/camera_info', 'front_optical',
                      np.array([0.0, 0.0, 1.65]), optical_rotation(0.0))
    rng = np.random.default_rng(5)
    road = cv2.GaussianBlur(rng.uniform(0, 255, (600, 3000)).astype(np.float32), (0, 0), 1.5)
    road = cv2.normalize(road, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)  # 60 x 12 m

    def render_road(T_odom_cam):
        # texel (s, t) is the road point (-2 + 0.02 s, 6 - 0.02 t, 0)
        return render_plane(road, intr.K, T_odom_cam, [-2.0, 6.0, 0.0], [1.0, 0, 0], [0, -1.0, 0], 0.02, (w, h))

    def step_error(pitch_deg, tilt_deg, road_normal=False):
        """Median relative error of the bottom-left quarter's steps, the fused poses true;
        road_normal: given the road's normal as the rig's mount sees it (add_road_normal)."""
        T_bc = cam.T_base_cam.copy()
        R_pitch = se3.rotvec_to_R([0.0, np.radians(pitch_deg), 0.0])
        T_bc[:3, :3] = R_pitch @ T_bc[:3, :3]
        est = QuarterEstimator(cam, 3, intr, QuarterParams(road_tilt_std_deg=tilt_deg), (w, h), 0.0, True)
        ratios = []
        for k in range(14):
            T = se3.make_T(np.eye(3), [k * step, 0.0, 0.0])
            if road_normal:
                est.add_road_normal(int(k * 1e8), R_pitch.T @ [0.0, 0.0, 1.0])
            e = est.process_image(int(k * 1e8), render_road(T @ T_bc))
            if k >= 2 and e is not None and e.state == 'tracking':
                ratios.append((e.T_odom_base[0, 3] - (k - 1) * step) / step)
            est.apply_fused_pose(int(k * 1e8), T, np.eye(6) * 1e-8)
        assert len(ratios) >= 10
        return float(np.median(ratios)) - 1.0

    err = {(p, t): step_error(p, t) for p in (1.0, -1.0, 0.0) for t in (0.2, 1.0)}
    print('\nstep error (camera pitch, road tilt std): '
          + ', '.join(f'{p:+.0f} deg / {t} deg: {e:+.3f}' for (p, t), e in err.items()))
    assert err[(1.0, 0.2)] > 0.06 and err[(-1.0, 0.2)] < -0.03      # the pitch shows
    for p in (1.0, -1.0):
        assert abs(err[(p, 1.0)]) < 0.8 * abs(err[(p, 0.2)]), p
    assert abs(err[(1.0, 1.0)]) < 0.08
    assert abs(err[(0.0, 1.0)]) < 0.02
    # Given the road's normal (the general arbiter's, from the direction of travel), the road
    # points land where they are and the steps are metric whichever way the camera is pitched.
    mended = {p: step_error(p, 1.0, road_normal=True) for p in (1.0, -1.0)}
    print('with the road normal: ' + ', '.join(f'{p:+.0f} deg: {e:+.3f}' for p, e in mended.items()))
    for p, e in mended.items():
        assert abs(e) < 0.02 and abs(e) < 0.5 * abs(err[(p, 1.0)]), p


def test_the_road_normal_holds_from_the_next_fused_pose_and_a_bad_one_is_refused():
    """The general arbiter's road normal at frame k is used from the fused pose after k's on
    (so a lockstep replay does not depend on which of the two messages came first), it travels
    with the quarter's state to another worker, and a vector that is no road's normal is
    refused with its values named. Off a road it changes nothing."""
    from multicam_ego_motion.geometry.rig import CameraMount, optical_rotation

    cam = CameraMount('front', '/front/image_raw', '/front/camera_info', 'front_optical',
                      np.array([0.0, 0.0, 1.65]), optical_rotation(0.0))
    intr = CameraIntrinsics.pinhole(720.0, 720.0, 620.0, 188.0, 1240, 376)
    est = QuarterEstimator(cam, 3, intr, QuarterParams(), (1240, 376), 0.0, True)
    up = se3.rotvec_to_R([0.0, np.radians(-1.0), 0.0]) @ [0.0, 0.0, 1.0]
    img = np.full((376, 1240), 128, np.uint8)
    est.process_image(0, img)
    est.add_road_normal(0, up)
    est.apply_fused_pose(0, np.eye(4), np.eye(6) * 1e-8)
    assert est.road_up is None                          # frame 0's normal: from frame 1 on
    est.process_image(int(1e8), img)
    moved = est.get_state()
    est.apply_fused_pose(int(1e8), np.eye(4), np.eye(6) * 1e-8)
    np.testing.assert_allclose(est.road_up, up)
    other = QuarterEstimator(cam, 3, intr, QuarterParams(), (1240, 376), 0.0, True)
    other.set_state(pickle.loads(pickle.dumps(moved)))
    other.apply_fused_pose(int(1e8), np.eye(4), np.eye(6) * 1e-8)
    np.testing.assert_allclose(other.road_up, up)
    for bad in ([0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [np.nan, 0.0, 1.0]):
        with pytest.raises(UserError, match='road normal'):
            est.add_road_normal(int(2e8), bad)
    indoor = QuarterEstimator(cam, 3, intr, QuarterParams(), (1240, 376), 0.0, False)
    indoor.add_road_normal(0, up)
    indoor.apply_fused_pose(int(1e8), np.eye(4), np.eye(6) * 1e-8)
    assert indoor.road_up is None
