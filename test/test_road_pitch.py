"""The road's normal from the direction of travel (arbiter_node/road_pitch): the median slope
of the body's steps, forward or reverse, once there are enough of them; and square to the path
driven over the last steps, in the body's frame by its rotation (PathNormal), which follows the
body's own pitch to the road when it brakes."""
import math

import numpy as np
import pytest

from scipy.spatial.transform import Rotation

from arbiter_node.road_pitch import PathNormal, TravelPitch


def step(length, slope_deg, lateral=0.0):
    s = math.radians(slope_deg)
    return np.array([length * math.cos(s), lateral, length * math.sin(s)])


def test_the_slope_of_the_steps_is_the_pitch_and_the_normal_is_square_to_them():
    rng = np.random.default_rng(0)
    tp = TravelPitch(window=300, min_steps=10, min_step_m=0.1, max_pitch_rad=math.radians(5))
    for i in range(9):
        tp.add_step(step(1.0, 1.2 + rng.normal(0, 0.5)))
    assert tp.pitch_rad is None                        # not enough steps yet: the body's z
    np.testing.assert_allclose(tp.up_body(), [0.0, 0.0, 1.0])
    for i in range(200):
        # bumps and a hill: the median holds; reversing: the same slope
        d = 1.0 if i % 7 else -1.0
        tp.add_step(d * step(1.0, 1.2 + rng.normal(0, 0.5) + (3.0 if i % 13 == 0 else 0.0)))
    assert math.degrees(tp.pitch_rad) == pytest.approx(1.2, abs=0.15)
    assert tp.up_body() @ step(1.0, math.degrees(tp.pitch_rad)) == pytest.approx(0.0, abs=1e-12)
    assert tp.up_body()[2] > 0.99


def test_short_sideways_and_implausible_steps_say_nothing():
    tp = TravelPitch(window=50, min_steps=5, min_step_m=0.1, max_pitch_rad=math.radians(5))
    for _ in range(20):
        tp.add_step(step(0.05, 10.0))                  # standing
        tp.add_step(np.array([0.2, 1.0, 0.1]))         # mostly sideways
    assert tp.pitch_rad is None
    for _ in range(20):
        tp.add_step(step(1.0, 8.0))                    # not a car on its road
    assert tp.pitch_rad is None and tp.up_body()[2] == 1.0


def drive(n, slope_deg, turn_deg_per_step, pitch_to_road_deg, noise_deg=0.0, seed=0):
    """A body driving 1 m steps on a plane sloped slope_deg, turning in it, pitched to it by
    pitch_to_road_deg(i) (nose down): (stamps, its rotations, its steps in the odom frame,
    the road's normal in the odom frame)."""
    rng = np.random.default_rng(seed)
    R_road = Rotation.from_euler('y', -slope_deg, degrees=True)
    stamps, rotations, steps = [], [], []
    for i in range(n):
        heading = Rotation.from_euler('z', turn_deg_per_step * i, degrees=True)
        rotations.append((R_road * heading * Rotation.from_euler('y', pitch_to_road_deg(i), degrees=True)).as_matrix())
        wobble = Rotation.from_rotvec(np.radians(rng.normal(0.0, noise_deg, 3)))
        steps.append((R_road * heading * wobble).apply([1.0, 0.0, 0.0]))
        stamps.append(100_000_000 * (i + 1))
    return stamps, rotations, steps, R_road.apply([0.0, 0.0, 1.0])


def angle_deg(a, b):
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)) / np.linalg.norm(a) / np.linalg.norm(b))))


@pytest.mark.parametrize('turn', [0.0, 3.0])
def test_the_path_normal_follows_the_bodys_own_pitch_to_the_road(turn):
    # on a 2 deg slope, the body pitched 0.5 deg to the road and then 2 deg as it brakes: in the
    # body's frame the road's normal tilts with it; the steps' directions scatter by 0.3 deg
    stamps, rotations, steps, n_odom = drive(60, 2.0, turn, lambda i: 0.5 if i < 40 else 2.0, 0.3)
    pn = PathNormal(window=20, min_path_m=1.0)
    for i, (s, v) in enumerate(zip(stamps, steps)):
        pn.add_step(s, v)
        if i - 2 not in (30, 50):
            continue
        i -= 2                   # as the scale state asks: about the frame pair two frames back
        up = pn.up_body(stamps[i], rotations[i])
        truth = rotations[i].T @ n_odom
        assert angle_deg(up, truth) < 0.15, i
        # a normal that is one constant in the body frame is off by the change of pitch
        assert angle_deg(truth, [0.0, 0.0, 1.0]) == pytest.approx(0.5 if i < 40 else 2.0, abs=1e-6)


def test_the_path_normal_needs_its_window_and_a_path_and_ignores_later_steps():
    stamps, rotations, steps, n_odom = drive(40, 1.0, 0.0, lambda i: 1.0)
    pn = PathNormal(window=20, min_path_m=1.0)
    for s, v in zip(stamps[:20], steps[:20]):
        pn.add_step(s, v)
    assert pn.up_body(stamps[19], rotations[19]) is None            # 20 steps, 21 needed
    for s, v in zip(stamps[20:30], steps[20:30]):
        pn.add_step(s, v)
    up = pn.up_body(stamps[25], rotations[25])
    # steps after the one that follows at_ns do not count: a later climb changes nothing
    pn.add_step(stamps[30], np.array([0.0, 0.0, 5.0]))
    np.testing.assert_array_equal(pn.up_body(stamps[25], rotations[25]), up)
    assert angle_deg(up, rotations[25].T @ n_odom) < 1e-6
    standing = PathNormal(window=20, min_path_m=1.0)
    for s in stamps[:30]:
        standing.add_step(s, np.array([0.01, 0.0, 0.0]))             # 0.2 m in all: no direction
    assert standing.up_body(stamps[25], rotations[25]) is None
