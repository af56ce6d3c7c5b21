"""road_motion: a camera's motion between two frames from its tracks over a road, without a
map: rotation and direction from the essential matrix, the length from the road ahead."""
import numpy as np
import pytest

from arbiter_node.rig_motion_fit import CameraTracks
from arbiter_node.road_motion import body_twist, camera_motion, rig_motion
from multicam_ego_motion.geometry import se3

# a forward camera 1.65 m above the road (optical z = base x, optical y = down)
R_BC = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
C_B = np.array([0.5, 0.0, 1.65])
SIGMA = 1.0 / 700.0
UP = np.array([0.0, 0.0, 1.0])    # the road's normal in the body frame (level)


def scene(rng):
    road = np.column_stack([rng.uniform(4, 18, 120), rng.uniform(-2.8, 2.8, 120), np.zeros(120)])
    walls = np.column_stack([rng.uniform(6, 40, 150), rng.choice([-7.0, 7.0], 150), rng.uniform(0.2, 5, 150)])
    return np.vstack([road, walls])


def observe(X_odom, T_odom_base):
    T_oc = T_odom_base @ se3.make_T(R_BC, C_B)
    Xc = (X_odom - T_oc[:3, 3]) @ T_oc[:3, :3]
    return Xc[:, :2] / Xc[:, 2:3], Xc[:, 2]


def tracks(step_m, yaw_deg, noise_px, seed=0):
    rng = np.random.default_rng(seed)
    X = scene(rng)
    Tb = se3.make_T(se3.rotvec_to_R([0.0, 0.0, np.radians(yaw_deg)]), [step_m, 0.0, 0.0])
    xa, za = observe(X, np.eye(4))
    xb, zb = observe(X, Tb)
    seen = (za > 1) & (zb > 1) & (np.abs(xa).max(axis=1) < 0.9) & (np.abs(xb).max(axis=1) < 0.9)
    xa, xb = xa[seen], xb[seen]
    xa = xa + rng.normal(0, noise_px * SIGMA, xa.shape)
    xb = xb + rng.normal(0, noise_px * SIGMA, xb.shape)
    return CameraTracks(R_BC, C_B, xa, xb, np.full(len(xa), SIGMA)), Tb


@pytest.mark.parametrize('step_m, yaw_deg', [(1.2, 2.0), (1.6, 6.0), (0.6, 0.3), (0.6, 6.0)])
def test_motion_from_tracks_is_metric_over_a_road(step_m, yaw_deg):
    tr, Tb = tracks(step_m, yaw_deg, noise_px=0.5)
    m = camera_motion(tr, UP, 0.0, 2.0 * SIGMA, 30, 0.3, 2.5 * SIGMA, 0.1)
    assert m is not None and m.length_m is not None
    T_cam = np.linalg.inv(se3.make_T(R_BC, C_B)) @ Tb @ se3.make_T(R_BC, C_B)   # camera b in a
    err = np.degrees(np.linalg.norm(se3.R_to_rotvec(m.R @ T_cam[:3, :3])))
    assert err < 0.4          # (0.5 px noise, straight ahead: 0.14-0.22 deg)
    true_dir = T_cam[:3, 3] / np.linalg.norm(T_cam[:3, 3])
    assert np.degrees(np.arccos(np.clip(m.direction @ true_dir, -1, 1))) < 2.0
    assert m.length_m == pytest.approx(np.linalg.norm(T_cam[:3, 3]), rel=0.05)
    # the body twist that moves the body by Tb in dt
    dt = 0.1
    rm = rig_motion([tr], [(tr, m)], np.eye(4), 30)
    assert rm.length_known
    twist, cov = body_twist(rm, dt, 0.03, 0.3)
    assert twist[:3] * dt == pytest.approx(Tb[:3, 3], abs=0.03)    # (measured 0.001-0.014)
    assert np.degrees(twist[5] * dt) == pytest.approx(yaw_deg, abs=0.4)
    # the length is known to 30 %: along the travel, its std is 30 % of the step
    along = rm.t / np.linalg.norm(rm.t)
    assert np.sqrt(along @ cov[:3, :3] @ along) * dt == pytest.approx(0.3 * np.linalg.norm(rm.t), rel=1e-6)
    # the rotation's std from the fit: a fraction of a degree
    assert 1e-4 < np.sqrt(np.max(np.diag(rm.rotation_cov))) < np.radians(0.5)


def test_the_body_translation_is_the_one_that_moves_the_camera_its_road_step():
    """A camera 0.5 m ahead of the body's axis, the body turning 6 deg: the fit holds the same
    on every t(s) = s u - (R - I) c (one camera: its step's length is free), and the body's
    metric translation is the point of that line that moves the camera by its road step,
    whichever point the fit returned (t scaled to the length instead: up to 10 deg sideways)."""
    from types import SimpleNamespace

    from arbiter_node.road_motion import _metric_translation
    _, Tb = tracks(1.6, 6.0, noise_px=0.5)
    R, lever = Tb[:3, :3], (Tb[:3, :3] - np.eye(3)) @ C_B
    u = Tb[:3, 3] + lever                              # the camera's true step, in the body frame
    cam = (SimpleNamespace(centre=C_B), SimpleNamespace(length_m=float(np.linalg.norm(u))))
    for s in (0.3, 1.0, 2.5):
        t_fit = s * u - lever
        assert _metric_translation(R, t_fit, [cam]) == pytest.approx(Tb[:3, 3], abs=1e-9)
        naive = t_fit / np.linalg.norm(t_fit) * np.linalg.norm(u)
        if s != 1.0:
            assert np.linalg.norm(naive - Tb[:3, 3]) > 0.01
    # a camera without a road step takes no part; none at all: no answer
    blind = (SimpleNamespace(centre=np.zeros(3)), SimpleNamespace(length_m=None))
    assert _metric_translation(R, 2.0 * u - lever, [cam, blind]) == pytest.approx(Tb[:3, 3], abs=1e-9)
    assert _metric_translation(R, u, [blind]) is None


def test_without_the_road_the_length_is_left_open():
    tr, _ = tracks(1.2, 2.0, noise_px=0.5)
    m = camera_motion(tr, None, None, 2.0 * SIGMA, 30, 0.3, 2.5 * SIGMA, 0.1)
    assert m is not None and m.length_m is None
    prior = se3.make_T(np.eye(3), [0.5, 0.0, 0.0])       # the filter's step: 0.5 m
    rm = rig_motion([tr], [(tr, m)], prior, 30)
    assert not rm.length_known and np.linalg.norm(rm.t) == pytest.approx(0.5)
    twist, cov = body_twist(rm, 0.1, 0.03, 0.3)
    along = rm.t / 0.5
    assert np.sqrt(along @ cov[:3, :3] @ along) * 0.1 > 100.0      # not measured
    assert along == pytest.approx([1.0, 0.0, 0.0], abs=0.03)     # the direction is


def test_no_motion_or_too_few_tracks_give_nothing():
    tr, _ = tracks(0.0, 0.0, noise_px=0.0)
    assert camera_motion(tr, UP, 0.0, 2.0 * SIGMA, 30, 0.3, 2.5 * SIGMA, 0.1) is None
    tr, _ = tracks(1.2, 2.0, noise_px=0.5)
    few = CameraTracks(R_BC, C_B, tr.xa[:20], tr.xb[:20], tr.sigma[:20])
    assert camera_motion(few, UP, 0.0, 2.0 * SIGMA, 30, 0.3, 2.5 * SIGMA, 0.1) is None


def test_two_cameras_fix_what_one_narrow_view_confuses():
    """Two narrow cameras looking 60 deg apart: each one's essential matrix alone mixes a turn
    with sideways travel; the rig fit to both holds the rotation."""
    rng = np.random.default_rng(3)
    Tb = se3.make_T(se3.rotvec_to_R([0.0, 0.0, np.radians(3.0)]), [1.2, 0.05, 0.0])
    X = np.column_stack([rng.uniform(5, 40, 800), rng.uniform(-25, 25, 800), rng.uniform(-1.5, 4, 800)])
    cams = []
    for yaw in (np.radians(30), np.radians(-30)):
        R = se3.rotvec_to_R([0.0, 0.0, yaw]) @ R_BC
        T_bc = se3.make_T(R, C_B)
        obs = []
        for T in (np.eye(4), Tb):
            T_oc = T @ T_bc
            Xc = (X - T_oc[:3, 3]) @ T_oc[:3, :3]
            obs.append((Xc[:, :2] / Xc[:, 2:3], Xc[:, 2]))
        (xa, za), (xb, zb) = obs
        # a narrow view: 30 deg across
        seen = (za > 1) & (zb > 1) & (np.abs(xa).max(axis=1) < 0.27) & (np.abs(xb).max(axis=1) < 0.27)
        xa = xa[seen] + rng.normal(0, SIGMA, (seen.sum(), 2))
        xb = xb[seen] + rng.normal(0, SIGMA, (seen.sum(), 2))
        cams.append(CameraTracks(R, C_B, xa, xb, np.full(len(xa), SIGMA)))
    ms = [(c, camera_motion(c, None, None, 2.0 * SIGMA, 30, 0.3, 2.5 * SIGMA, 0.1)) for c in cams]
    assert all(m is not None for _, m in ms)
    def camera_error_deg(c, m):
        T_bc = se3.make_T(c.R_base_cam, c.centre)
        T_cam = np.linalg.inv(T_bc) @ Tb @ T_bc           # camera b in camera a
        return np.degrees(np.linalg.norm(se3.R_to_rotvec(m.R @ T_cam[:3, :3])))
    single = [camera_error_deg(c, m) for c, m in ms]
    assert max(single) > 0.5          # (1.0 and 7.8 deg with this seed)
    rm = rig_motion(cams, ms, np.eye(4), 30)
    joint = np.degrees(np.linalg.norm(se3.R_to_rotvec(rm.R.T @ Tb[:3, :3])))
    assert joint < 0.1
