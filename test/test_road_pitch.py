"""The road's normal from the direction of travel (arbiter_node/road_pitch): the median slope
of the body's steps, forward or reverse, once there are enough of them."""
import math

import numpy as np
import pytest

from arbiter_node.road_pitch import TravelPitch


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
