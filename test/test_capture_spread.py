"""The capture spread of a rig's cameras and the grouping window found from it (ROS-free)."""
import pytest

from arbiter_node.capture_spread import WindowLearner, capture_spread

PERIOD = 66_666_667          # 15 Hz
MS = 1_000_000


def rig(offsets_ms, frames=30, period=PERIOD, start=0):
    return {f'/cam{i}/image_raw': [start + k * period + o * MS for k in range(frames)]
            for i, o in enumerate(offsets_ms)}


def test_synchronised_cameras_need_no_window():
    s = capture_spread(rig([0, 0, 0, 0]))
    assert (s.spread_ns, s.window_s, s.groupable) == (0, 0.0, True) and s.period_ns == PERIOD


def test_free_running_cameras_get_a_window_above_their_spread():
    s = capture_spread(rig([0, 8, 16, 24]))
    assert s.spread_ns == 24 * MS and s.window_s == pytest.approx(0.031) and s.groupable
    # the same rig recorded from the middle of a frame (the first images are the late cameras)
    late_start = {t: v[1:] if i < 2 else v for i, (t, v) in enumerate(rig([0, 8, 16, 24]).items())}
    assert capture_spread(late_start).spread_ns == 24 * MS


def test_cameras_at_different_rates_with_common_instants_need_no_window():
    half = PERIOD // 2
    stamps = {**rig([0, 0], frames=60, period=half), '/c/image_raw': [2 * k * half for k in range(30)]}
    s = capture_spread(stamps)
    assert s.spread_ns == 0 and s.window_s == 0.0 and s.period_ns == half


def test_a_spread_near_half_the_period_cannot_be_grouped():
    s = capture_spread(rig([0, 30]))
    assert s.spread_ns == 30 * MS and not s.groupable
    assert 'up to 30.0 ms apart (shortest frame period 66.7 ms)' in s.describe()
    window, said = s.verdict()
    assert window is None and 'no sync window groups them' in said


def test_the_verdict_says_what_to_group_by():
    assert capture_spread(rig([0, 0, 0, 0])).verdict() == (None, None)
    window, said = capture_spread(rig([0, 8, 16, 24])).verdict()
    assert window == pytest.approx(0.031) and said.endswith('free-running, grouped by a sync window of 0.031 s')


def test_too_little_to_tell():
    assert capture_spread({}).window_s == 0.0
    assert capture_spread({'/a': [0]}).window_s == 0.0
    assert capture_spread(rig([0, 8], frames=1)).window_s == 0.0


def test_a_learner_answers_once_when_a_camera_has_enough_frames():
    learner = WindowLearner(frames=5)
    stamps = rig([0, 8, 16, 24], frames=10)
    answers = []
    for k in range(10):
        for topic, ts in stamps.items():
            answers.append(learner.add(topic, ts[k]))
    got = [a for a in answers if a is not None]
    assert len(got) == 1 and got[0].spread_ns == 24 * MS and got[0].window_s == pytest.approx(0.031)
    assert answers.index(got[0]) == 4 * 4          # the first camera's 5th frame
    synced = WindowLearner(frames=3)
    out = [synced.add(t, ts[k]) for k in range(3) for t, ts in rig([0, 0]).items()]
    assert [a.window_s for a in out if a is not None] == [0.0]


def test_frames_a_lockstep_player_keeps_out_until_every_period_is_known():
    """Until a camera's second image the general arbiter waits for it in every group; the
    player must have that image out by then (start_frames: instants from a group to the
    waited-for camera's next image)."""
    assert capture_spread(rig([0, 0, 0, 0])).start_frames == 1
    # 30/20/15/10 Hz with common instants: the 33 ms group waits for the 10 Hz camera's
    # 100 ms image, 4 instants on (33, 50, 67, 100)
    rates = {f'/c{hz}/image_raw': [round(k * 1e9 / hz) for k in range(hz * 2)] for hz in (30, 20, 15, 10)}
    s = capture_spread(rates)
    assert s.spread_ns == 0 and s.start_frames == 4
    # four phases over the period: the 8 ms group waits for the 0 ms camera's second image
    # (8, 16, 24, 66.7: 4), no more than the cameras
    assert capture_spread(rig([0, 8, 16, 24])).start_frames == 4
