"""The coordinator's cost monitor (ROS-free): smoothed per-quarter costs from /diagnostics
values, a quarter's first frame left out, and 'measured' only once every quarter has had
WARMUP_FRAMES frames after it."""
import pytest

from multicam_ego_motion.coordinator.cost_monitor import STAGE_KEYS, WARMUP_FRAMES, CostMonitor

CAMERAS = ['front', 'left']


def stages(total_ms):
    return {k: str(total_ms / len(STAGE_KEYS)) for k in STAGE_KEYS}


def frame(monitor, costs):
    """One frame: every quarter of each camera in `costs` at that cost, then the general
    arbiter's entry, which closes it."""
    for cam, ms in costs.items():
        for q in range(1, 5):
            monitor.observe(f'ego_motion/{cam}/q{q}', stages(ms))
    return monitor.observe('ego_motion/general_arbiter', {'arbiter_ms': '1.0'})


def test_first_frame_left_out_and_measured_after_the_warmup():
    m = CostMonitor(CAMERAS)
    assert frame(m, {'front': 0.03, 'left': 0.03})          # first frames: map start, ~free
    for _ in range(WARMUP_FRAMES):
        assert not m.measured
        frame(m, {'front': 2.0, 'left': 2.0})
    assert m.measured
    assert m.quarter_costs() == {'front': [pytest.approx(2.0)] * 4, 'left': [pytest.approx(2.0)] * 4}


def test_a_camera_whose_costs_lag_keeps_the_monitor_unmeasured():
    # One worker's batch came in (front), the other's not yet (left: its first frame only):
    # the loads would read 4 x 2 ms against 4 x 0.03 ms and ask for a rebalance.
    m = CostMonitor(CAMERAS)
    frame(m, {'front': 0.03, 'left': 0.03})
    for _ in range(3 * WARMUP_FRAMES):
        frame(m, {'front': 2.0})
    assert not m.measured
    assert m.quarter_costs()['left'] == [pytest.approx(2.0)] * 4    # unmeasured: the mean, as at start
    for _ in range(WARMUP_FRAMES):
        frame(m, {'left': 1.0})
    assert m.measured and m.quarter_costs()['left'][0] < 1.1


def test_smoothing_follows_a_step_without_jumping():
    m = CostMonitor(CAMERAS, alpha=0.3)
    for _ in range(WARMUP_FRAMES + 1):
        frame(m, {'front': 2.0, 'left': 2.0})
    frame(m, {'front': 12.0, 'left': 2.0})                   # one frame's burst
    assert m.quarter_costs()['front'][0] == pytest.approx(5.0)
    for _ in range(30):
        frame(m, {'front': 12.0, 'left': 2.0})
    assert m.quarter_costs()['front'][0] == pytest.approx(12.0, rel=1e-3)
    assert m.frames == WARMUP_FRAMES + 32


def test_entries_without_timings_or_foreign_names_are_ignored():
    m = CostMonitor(CAMERAS)
    assert not m.observe('ego_motion/front/q1', {'error': 'no CameraInfo'})
    assert not m.observe('other/front/q1', stages(5.0))
    assert not m.observe('ego_motion/front/q1', {k: 'nan?' for k in STAGE_KEYS})
    assert m.seen['front'] == [0, 0, 0, 0]
