import dataclasses
import pickle

import numpy as np
import pytest

from arbiter_node.general_fusion import PARAMETERS, GeneralFusion, default_params
from arbiter_node.rig_scale import camera_direction, relative_motion
from camera_pose_nodes.pose_estimate import PoseEstimate, uninformative
from multicam_ego_motion.geometry import se3
from multicam_ego_motion.geometry.rig import paper_rig

RIG = paper_rig()
COV = np.diag([0.02, 0.02, 0.02, 0.01, 0.01, 0.01]) ** 2
DT_NS = 50_000_000


def truth(t, v=0.5, w=0.3):
    yaw = w * t
    return se3.make_T(se3.rotvec_to_R([0, 0, yaw]), [v / w * np.sin(yaw), v / w * (1 - np.cos(yaw)), 0.0])


def cams(rng, T, stamp, bad=None, names=None):
    out = {}
    for n in names or RIG.names:
        d = rng.normal(0, np.sqrt(np.diag(COV)))
        if n == bad:
            d = d + np.r_[1.0, 0, 0, 0, 0, 0]
        out[n] = PoseEstimate(stamp, se3.perturb(T, d), COV.copy(), source=n, state='tracking')
    return out


def test_parameters_table_is_declarable():
    for name, (default, desc, lo, hi) in PARAMETERS.items():
        assert desc and isinstance(desc, str)
        if lo is not None:
            assert lo <= default <= hi, name
    with pytest.raises(ValueError):
        GeneralFusion(RIG, {'no_such_param': 1})


def test_tracks_truth_rejects_bad_camera_and_reports_body_twist():
    rng = np.random.default_rng(0)
    g = GeneralFusion(RIG)
    first = g.process(0, {n: uninformative(0, np.eye(4), n, 'initializing') for n in RIG.names})
    assert first.state == 'initializing' and not first.cameras_used
    np.testing.assert_allclose(first.T_odom_base, np.eye(4))
    assert sorted(first.cameras_missing) == sorted(RIG.names)
    for k in range(1, 201):
        f = g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS, bad='left' if k % 10 == 0 else None))
        assert f.state == 'tracking'
        if k % 10 == 0:
            assert 'left' in f.cameras_rejected and 'median' in f.cameras_rejected['left']
            assert sorted(f.cameras_used) == ['back', 'front', 'right']
    err = se3.pose_error(f.T_odom_base, truth(10.0))
    assert np.linalg.norm(err[:3]) < 0.03 and np.linalg.norm(err[3:]) < 0.015
    np.testing.assert_allclose(f.twist, [0.5, 0, 0, 0, 0, 0.3], atol=0.15)
    assert se3.is_valid_covariance(f.pose_covariance) and se3.is_valid_covariance(f.twist_covariance)
    assert not f.scale_observed and f.scale_source == 'landmarks'


def test_dead_reckoning_then_lost_and_wheel_prior():
    rng = np.random.default_rng(1)
    g = GeneralFusion(RIG, {'lost_timeout_s': 1.0})
    for k in range(1, 41):
        g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS))
    none = {n: uninformative(0, np.eye(4), n, 'lost') for n in RIG.names}
    states = [g.process((40 + k) * DT_NS, none).state for k in range(1, 41)]
    assert states[:20] == ['dead_reckoning'] * 20 and states[-1] == 'lost'
    # the wheel prior keeps it dead-reckoning, metric, and moving at the wheel speed
    wheel = (np.r_[0.5, 0, 0, 0, 0, 0.3], np.diag([0.01, 0.01, 1, 1, 1, 0.01]) ** 2)
    x0 = g.process(81 * DT_NS, none, wheel_twist=wheel)
    for k in range(82, 102):
        f = g.process(k * DT_NS, none, wheel_twist=wheel)
    assert f.state == 'dead_reckoning' and f.scale_observed and f.scale_source == 'wheel'
    assert f.twist[0] == pytest.approx(0.5, abs=0.02) and f.twist[5] == pytest.approx(0.3, abs=0.02)
    assert np.linalg.norm(f.T_odom_base[:3, 3] - x0.T_odom_base[:3, 3]) == pytest.approx(0.5, abs=0.1)
    assert np.all(np.isfinite(f.T_odom_base)) and se3.is_valid_covariance(f.pose_covariance)


def test_missing_cameras_and_two_camera_prior_vote():
    rng = np.random.default_rng(2)
    g = GeneralFusion(RIG)
    for k in range(1, 21):
        f = g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS, names=['front', 'back']))
    assert f.cameras_missing == ['left', 'right'] and sorted(f.cameras_used) == ['back', 'front']
    # two cameras that disagree: the prediction votes, the wrong one is rejected
    T = truth(21 * 0.05)
    est = cams(rng, T, 21 * DT_NS, names=['front', 'back'], bad='back')
    f = g.process(21 * DT_NS, est)
    assert f.cameras_used == ['front'] and 'back' in f.cameras_rejected


JUMP = se3.make_T(np.eye(3), [2.0, 0, 0])


def teleport(g, rng, last_frame, names=None, covariance_scale=1.0):
    """The rig's cameras track the truth for 20 frames, then report it 2 m off (JUMP) up to
    last_frame, their covariances times covariance_scale; the fused estimates of the jump."""
    for k in range(1, 21):
        g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS, names=names))
    out = []
    for k in range(21, last_frame + 1):
        jumped = {n: dataclasses.replace(e, covariance=e.covariance * covariance_scale)
                  for n, e in cams(rng, JUMP @ truth(k * 0.05), k * DT_NS, names=names).items()}
        out.append(g.process(k * DT_NS, jumped))
    return out


def test_teleported_cameras_gated_then_reinitialised():
    g = GeneralFusion(RIG, {'max_consecutive_rejections': 3, 'median_use_prior': False})
    fused = teleport(g, np.random.default_rng(3), 24)
    states = [(f.state, len(f.cameras_used)) for f in fused]
    assert states[:2] == [('dead_reckoning', 0), ('dead_reckoning', 0)]
    assert states[2] == ('tracking', 4)             # third rejection: re-initialised on the cameras
    assert np.linalg.norm(se3.pose_error(fused[-1].T_odom_base, JUMP @ truth(24 * 0.05))[:3]) < 0.05


def test_a_camera_the_prediction_out_votes_frame_after_frame_restarts_the_filter():
    """A lone camera, looser than a prediction that fell behind (a car that sped up while the
    filter dead-reckoned): with the prediction voting in the median (median_use_prior), the
    median sits on the prediction and rejects the camera there, before the EKF's gate is
    asked. Such frames count as the gate's refusals do: after max_consecutive_rejections the
    filter restarts on the camera, where it used to shut it out for good."""
    rig = dataclasses.replace(RIG, cameras=list(RIG.cameras[:1]))
    g = GeneralFusion(rig, {'max_consecutive_rejections': 3})
    # the camera looser than the prediction: its vote outweighs the camera's
    fused = teleport(g, np.random.default_rng(5), 29, names=rig.names, covariance_scale=25.0)
    for f in fused[:2]:
        assert all('from the median' in r for r in f.cameras_rejected.values()), f.cameras_rejected
    states = [(f.state, len(f.cameras_used)) for f in fused]
    assert [s[1] for s in states[:2]] == [0, 0]
    assert states[2:] == [('tracking', 1)] * 7     # third refusal: restarted on the camera
    assert np.linalg.norm(se3.pose_error(fused[-1].T_odom_base, JUMP @ truth(29 * 0.05))[:3]) < 0.05


def test_rig_scale_hook_reports_scale_observed():
    g = GeneralFusion(RIG)
    rng = np.random.default_rng(4)
    T1, T2 = truth(0.0, w=0.4), truth(0.5, w=0.4)            # 0.2 rad, 0.25 m between frames
    g.process(0, cams(rng, T1, 0))
    dirs = {c.name: camera_direction(T1, T2, c.translation) for c in RIG.cameras}
    f = g.process(500_000_000, cams(rng, T2, 500_000_000), camera_directions=dirs)
    assert f.scale_observed and f.scale_source == 'rig'
    # the rig's metric t matches the true body translation; the EKF's own step (pulled by
    # its zero-velocity start) is what the ratio compares it with
    t_true = relative_motion(T1, T2)[1]
    assert np.linalg.norm(g.last_scale.t - t_true) < 0.03
    t_ekf = relative_motion(T1, f.T_odom_base)[1]
    assert f.scale_ratio == pytest.approx(float(t_ekf @ g.last_scale.t) / float(t_ekf @ t_ekf), rel=0.1)
    g.reset()
    assert g.process(0, {}).state == 'initializing'


def test_camera_floor_keeps_overconfident_but_agreeing_cameras():
    # Four cameras 1-2 cm / 0.1 deg apart, each claiming 1 mm / 0.01 deg: what quarters report
    # after a turn (their landmarks' covariances leave out the fused poses' error). Without the floor the median
    # rejects every one of them (the fusion would dead-reckon); with it all are used.
    tight = np.diag([1e-3] * 3 + [1.7e-4] * 3) ** 2
    offsets = {'front': [0.01, 0, 0, 0, 0, 0.0017], 'left': [-0.01, 0.01, 0, 0, 0, 0],
               'back': [0, -0.015, 0, 0, 0, -0.0017], 'right': [0.015, 0.005, 0, 0, 0, 0.001]}
    ests = {n: PoseEstimate(DT_NS, se3.perturb(np.eye(4), d), tight, source=n, state='tracking')
            for n, d in offsets.items()}
    bare = GeneralFusion(RIG, {'camera_floor_std_m': 0.0, 'camera_floor_std_rad': 0.0})
    floored = GeneralFusion(RIG)
    assert bare.process(DT_NS, ests).cameras_used == []
    f = floored.process(DT_NS, ests)
    assert sorted(f.cameras_used) == sorted(RIG.names)
    # and a camera 20 cm off is still rejected
    ests['left'] = PoseEstimate(DT_NS, se3.perturb(np.eye(4), [0.2, 0, 0, 0, 0, 0]), tight,
                                source='left', state='tracking')
    f = GeneralFusion(RIG).process(DT_NS, ests)
    assert 'left' in f.cameras_rejected and 'left' not in f.cameras_used


def test_params_file_sets_every_fusion_parameter_with_its_type():
    # config/params.yaml is what the graph loads; a missing entry would silently fall back to
    # the code's default, a wrong type (0 for 0.0) would make the node refuse to start.
    from pathlib import Path

    from multicam_ego_motion.params_file import fusion_params_from
    params = fusion_params_from(Path(__file__).resolve().parents[1] / 'config' / 'params.yaml')
    defaults = default_params()
    assert set(params) == set(defaults)
    for k, v in defaults.items():
        assert type(params[k]) is type(v), (k, params[k], v)


def test_planar_motion_holds_height_and_tilt_against_cameras_that_climb():
    """Cameras that measure every step 2 mm too high and 0.5 mrad pitched, from the last
    fused pose (as the quarters do: their filters restart from it each frame): without
    planar_motion the fused body climbs and tilts with them frame after frame; with it,
    it stays near the floor and level."""
    step_error = se3.make_T(se3.rotvec_to_R([0.0, -5e-4, 0.0]), [0.0, 0.0, 0.002])

    def run(planar, rig=RIG):
        rng = np.random.default_rng(4)
        # (without a floor the rig-rotation scale would rescale these made-up cameras)
        g = GeneralFusion(rig, {'planar_motion': planar, 'rig_rotation_scale': rig.floor_z is not None})
        last = np.eye(4)
        for k in range(1, 101):
            T = last @ se3.inv_T(truth((k - 1) * 0.05)) @ truth(k * 0.05) @ step_error
            last = g.process(k * DT_NS, cams(rng, T, k * DT_NS)).T_odom_base
        pitch = abs(float(se3.R_to_rotvec(truth(5.0)[:3, :3].T @ last[:3, :3])[1]))
        return abs(float(last[2, 3])), pitch

    z_free, pitch_free = run(False)
    z_planar, pitch_planar = run(True)
    assert z_free > 0.08 and pitch_free > 0.02          # measured 0.12 m, 0.037 rad
    assert z_planar < 0.4 * z_free and pitch_planar < 0.2 * pitch_free   # 0.03 m, 0.004 rad
    # a rig that knows no floor (floor_z None) cannot assume the body moves on one (it also
    # starts at rest, a rig with a floor at any speed: start_speed_std)
    no_floor = dataclasses.replace(RIG, floor_z=None)
    assert run(True, no_floor) == run(False, no_floor)


def test_each_wheel_reading_is_applied_once():
    # Free-running cameras fuse several times per wheel tick: the reading must not be reused
    # (stale, and as confident again each time).
    wheel = (np.r_[1.0, 0, 0, 0, 0, 0], np.eye(6) * 1e-4)
    rng = np.random.default_rng(3)
    fused = {}
    for reuse in (False, True):
        g = GeneralFusion(RIG)
        g.process(0, cams(rng, truth(0.0), 0), wheel_twist=wheel, wheel_stamp_ns=0)
        stamp = DT_NS // 3
        f = g.process(stamp, {'left': cams(rng, truth(stamp * 1e-9), stamp)['left']},
                      wheel_twist=wheel, wheel_stamp_ns=stamp if reuse else 0)
        fused[reuse] = f
    assert fused[False].scale_source != 'wheel' and fused[True].scale_source == 'wheel'


def test_a_camera_alone_at_its_stamp_is_gated_by_the_ekf_not_the_median():
    # The prediction a little more confident than the camera (after the covariance floor,
    # 5 mm) and 2.8 cm from it: a two-vote median sat on the prediction and rejected the
    # camera on its own covariance (31 > 22.5); the EKF's gate weighs both (17 < 22.5).
    g = GeneralFusion(RIG)
    rng = np.random.default_rng(4)
    for k in range(5):
        g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS))
    stamp = 4 * DT_NS
    g.ekf.kf.P[:6, :6] = np.diag([0.0045] * 3 + [0.0018] * 3) ** 2
    T = se3.perturb(g.ekf.T, [0.028, 0, 0, 0, 0, 0])
    f = g.process(stamp, {'back': PoseEstimate(stamp, T, np.eye(6) * 1e-12, source='back', state='tracking')})
    assert f.cameras_used == ['back'], f.cameras_rejected


def test_odom_rate():
    from arbiter_node.general_arbiter_node import odom_due
    assert odom_due(None, 5, 10.0) and odom_due(0, 1, 0.0)
    assert not odom_due(0, 99_999_999, 10.0) and odom_due(0, 100_000_000, 10.0)


def test_a_camera_alone_at_its_stamp_weighs_less_than_one_of_a_frame():
    """lone_camera_covariance_scale: a camera fused alone (free-running cameras) pulls the
    fused pose from the prediction less than its own covariance says; cameras fused together
    are not touched."""
    import copy

    def pull(scale, lone):
        g = GeneralFusion(RIG, {'lone_camera_covariance_scale': scale})
        rng = np.random.default_rng(4)
        for k in range(5):
            g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS))
        stamp = 5 * DT_NS
        predicted = copy.deepcopy(g).process(stamp, {}).T_odom_base
        T = se3.perturb(predicted, [0.01, 0, 0, 0, 0, 0])
        est = {n: PoseEstimate(stamp, T, np.eye(6) * 1e-4, source=n, state='tracking')
               for n in (['back'] if lone else RIG.names)}
        f = g.process(stamp, est)
        assert f.cameras_used
        return float(np.linalg.norm(f.T_odom_base[:3, 3] - predicted[:3, 3]))
    lone1, lone2 = pull(1.0, True), pull(2.0, True)
    assert 0.0 < lone2 < 0.8 * lone1
    assert pull(1.0, False) == pull(2.0, False)


def test_a_camera_alone_waits_for_its_quarters_tracks_of_its_stamp():
    """tracks_settled: a camera fused alone (free-running cameras) is fused once every quarter
    that sent its tracks at the camera's previous frame has sent them at this one, so its
    rotation from that frame to this one is fitted with this frame's tracks (the general
    arbiter waits up to tracks_wait_s). A frame of several cameras, a filter not started yet,
    or lone_camera_track_rotation off do not wait."""
    g = GeneralFusion(RIG)
    assert g.tracks_settled(0, ['back'])                     # nothing fused yet
    rng = np.random.default_rng(4)
    for k in range(3):
        g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS))
    a, b = 3 * DT_NS, 4 * DT_NS
    xy, sigma = np.zeros((2, 2)), np.full(2, 1e-3)
    assert g.tracks_settled(a, ['back'])                     # the camera never sent tracks
    for q in (1, 2, 4):                                      # (quarter 3 sees nothing)
        g.add_bearings('back', q, a, [1, 2], xy, sigma)
    for q in (1, 2):
        g.add_bearings('back', q, b, [1, 2], xy, sigma)
        assert not g.tracks_settled(b, ['back'])
    assert g.tracks_settled(b, ['back', 'front'])            # a frame of two: no wait
    g.add_bearings('back', 4, b, [1], xy[:1], sigma[:1])
    assert g.tracks_settled(b, ['back'])
    off = GeneralFusion(RIG, {'lone_camera_track_rotation': False})
    for k in range(3):
        off.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS))
    off.add_bearings('back', 1, a, [1, 2], xy, sigma)
    assert off.tracks_settled(b, ['back'])


def test_a_pickled_fusion_keeps_the_last_two_frames_of_tracks():
    """The general arbiter's snapshot (after every update) holds each camera's tracks of its
    last two frames, what the next rotation fit and the wait for tracks read, not all twelve a
    scale pair may span; the restored fusion waits and fits as the original does."""
    g = GeneralFusion(RIG)
    rng = np.random.default_rng(5)
    for k in range(3):
        g.process(k * DT_NS, cams(rng, truth(k * 0.05), k * DT_NS))
    xy, sigma = np.zeros((2, 2)), np.full(2, 1e-3)
    stamps = [k * DT_NS for k in range(3, 9)]
    for s in stamps:
        for q in (1, 2, 3):
            g.add_bearings('back', q, s, [1, 2], xy, sigma)
    assert sorted(g.scale.bearings['back']) == stamps                  # the fusion keeps them all
    restored = pickle.loads(pickle.dumps(g))
    assert sorted(restored.scale.bearings['back']) == stamps[-2:]
    assert sorted(g.scale.bearings['back']) == stamps                  # (pickling took nothing away)
    nxt = 9 * DT_NS
    restored.add_bearings('back', 1, nxt, [1, 2], xy, sigma)
    assert not restored.tracks_settled(nxt, ['back'])                  # quarters 2 and 3 still to come
    for q in (2, 3):
        restored.add_bearings('back', q, nxt, [1, 2], xy, sigma)
    assert restored.tracks_settled(nxt, ['back'])
