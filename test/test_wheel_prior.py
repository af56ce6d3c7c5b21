"""The wheel reading the general arbiter (and the sequential pipeline) fuses for a frame."""
import numpy as np

from arbiter_node.wheel_prior import MAX_AGE_NS, WheelBuffer

COV = np.eye(6) * 1e-4


def twist(vx):
    return np.array([vx, 0, 0, 0, 0, 0.1])


def test_newest_reading_not_after_the_frame():
    b = WheelBuffer()
    for i in range(5):
        b.add(i * 100_000_000, twist(float(i)), COV)
    assert b.at(250_000_000)[0][0] == 2.0          # the reading at 0.2 s, not the one at 0.3 s
    assert b.at(300_000_000)[0][0] == 3.0          # a reading stamped with the frame counts
    assert b.at(-1) is None                        # nothing before the first reading


def test_stale_readings_mean_the_wheels_went_silent():
    b = WheelBuffer()
    b.add(0, twist(1.0), COV)
    assert b.at(MAX_AGE_NS - 1) is not None
    assert b.at(MAX_AGE_NS) is None


def test_non_finite_readings_are_dropped():
    b = WheelBuffer()
    assert b.add(0, twist(1.0), COV)
    assert not b.add(100_000_000, twist(float('nan')), COV)
    bad_cov = COV.copy()
    bad_cov[0, 0] = float('inf')
    assert not b.add(100_000_000, twist(2.0), bad_cov)
    assert b.at(150_000_000)[0][0] == 1.0          # the last finite one is used


def test_buffer_is_bounded():
    b = WheelBuffer()
    for i in range(1000):
        b.add(i, twist(1.0), COV)
    assert len(b.readings) <= 200


def test_settled_once_a_reading_at_or_after_the_frame_came_or_the_wheel_went_silent():
    buf = WheelBuffer(max_age_ns=500)
    assert not buf.settled(100)                   # nothing heard yet: not final
    tw, cov = np.zeros(6), np.eye(6)
    buf.add(90, tw, cov)
    assert not buf.settled(100)                   # the frame's own reading may still come
    buf.add(100, tw, cov)
    assert buf.settled(100) and buf.settled(95)
    assert not buf.settled(101)
    assert buf.settled(600)                       # 500 ns without a reading: silent
