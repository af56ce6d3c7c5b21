"""Frame skipping when the graph is behind the cameras: the general arbiter's governor and
the schedule every quarter follows (ROS-free)."""
import pytest

from camera_pose_nodes.frame_schedule import FrameGovernor, FrameSchedule, ScheduleBook

P = 33_333_333          # 30 Hz
T0 = 1_704_067_200_000_000_000


def test_a_schedule_takes_every_stride_th_frame_from_its_start_by_stamp_alone():
    s = FrameSchedule(T0, P, 3)
    taken = [k for k in range(10) if s.takes(T0 + k * P + (k % 2) * 1000)]   # stamps jitter
    assert taken == [0, 3, 6, 9]
    assert FrameSchedule(T0, P, 1).takes(T0 + 5 * P)
    assert FrameSchedule.from_list(s.to_list()) == s
    with pytest.raises(ValueError):
        FrameSchedule.from_list([T0, 0, 2])
    with pytest.raises(ValueError):
        FrameSchedule.from_list([T0, P, 3, 4])         # keeps more than it has


def test_a_schedule_keeps_a_fraction_of_the_frames_evenly_spread():
    s = FrameSchedule(T0, P, 7, 5)                    # 5 of every 7
    taken = [k for k in range(1, 29) if s.takes(T0 + k * P)]
    assert len(taken) == 20
    gaps = {b - a for a, b in zip(taken, taken[1:])}
    assert gaps == {1, 2}                              # never two skipped in a row
    assert FrameSchedule.from_list(s.to_list()) == s and float(s.fraction) == pytest.approx(5 / 7)
    assert FrameSchedule.from_list([T0, P, 3]) == FrameSchedule(T0, P, 3, 1)   # [from, period, stride]


def test_a_book_applies_each_schedule_from_its_start_and_survives_a_hand_over():
    book = ScheduleBook()
    assert all(book.takes(T0 + k * P) for k in range(5))
    book.add(FrameSchedule(T0 + 2 * P, P, 2))
    book.add(FrameSchedule(T0 + 8 * P, P, 1))
    assert [k for k in range(12) if book.takes(T0 + k * P)] == [0, 1, 2, 4, 6, 8, 9, 10, 11]
    moved = ScheduleBook()
    moved.set_state(book.get_state())
    assert [moved.takes(T0 + k * P) for k in range(12)] == [book.takes(T0 + k * P) for k in range(12)]


def simulate(governor, cost_frames, n=120):
    """A graph that needs `cost_frames` frame periods per processed frame (lag in /clock):
    returns the strides in force and the lags seen."""
    book, clock, strides, lags = ScheduleBook(), T0, [], []
    k = 0
    while k < n:
        stamp = T0 + k * P
        if not book.takes(stamp):
            k += 1
            continue
        clock = max(clock, stamp) + cost_frames * P      # done this long after it came
        s = governor.update(stamp, clock)
        if s is not None:
            book.add(s)
        strides.append(governor.stride)
        lags.append((clock - stamp) / 1e9)
        k += 1
    return strides, lags


def test_the_governor_keeps_a_slow_graph_within_its_lag_and_returns_to_every_frame():
    gov = FrameGovernor(max_lag_s=0.1)
    strides, lags = simulate(gov, cost_frames=1.6)       # 1.6 periods per frame: falls behind
    assert set(strides[-20:]) == {2} and max(lags[-20:]) <= 0.1
    slow = FrameGovernor(max_lag_s=0.1)
    strides, lags = simulate(slow, cost_frames=3.5, n=300)   # the lag is this graph's latency
    assert set(strides[-5:]) == {4} and max(lags[-5:]) <= 3.5 * P / 1e9 + 1e-9
    fast = FrameGovernor(max_lag_s=0.1)
    strides, _ = simulate(fast, cost_frames=0.5)
    assert set(strides) == {1}                             # keeps up: every frame
    assert len(fast.lags) <= 2 * fast.hold_frames        # snapshotted every frame: bounded
    # catching up after a slow spell lowers the stride again
    gov.max_lag_s = 0.1
    strides, _ = simulate(gov, cost_frames=0.5, n=200)
    assert strides[-1] == 1


def kept_share(governor, cost_frames, n=300):
    book, clock, kept = ScheduleBook(), T0, []
    lags = []
    for k in range(n):
        stamp = T0 + k * P
        if not book.takes(stamp):
            kept.append(False)
            continue
        kept.append(True)
        clock = max(clock, stamp) + cost_frames * P
        s = governor.update(stamp, clock)
        if s is not None:
            book.add(s)
        lags.append((clock - stamp) / 1e9)
    return sum(kept[-100:]) / 100, lags


def test_the_governor_drops_as_few_frames_as_it_must():
    """A graph that needs 1.3 periods a frame keeps up with about 3 frames in 4, where every
    second frame (an integer stride) would drop half."""
    gov = FrameGovernor(max_lag_s=0.1)
    share, lags = kept_share(gov, cost_frames=1.3)
    assert 0.6 <= share <= 1 / 1.3 and max(lags[-30:]) <= 0.1
    assert gov.fraction < 1 and gov.achieved_rate_hz() == pytest.approx(float(gov.fraction) * 30, rel=1e-3)
    assert gov.camera_rate_hz() == pytest.approx(30.0, rel=1e-3)


def test_a_lag_of_zero_or_less_keeps_every_frame():
    """A clock that reads the frame stamps themselves (or runs behind them): nothing to skip,
    and nothing to divide by."""
    for offset in (0, -P // 2):
        gov = FrameGovernor(max_lag_s=0.1)
        gov.stride, gov.keep = 2, 1                       # after a slow spell
        made = [gov.update(T0 + k * P, T0 + k * P + offset) for k in range(30)]
        last = [s for s in made if s is not None][-1]
        assert gov.fraction == 1 and (last.keep, last.stride) == (1, 1)


def test_the_governor_is_off_in_lockstep_and_when_the_clocks_disagree():
    off = FrameGovernor(max_lag_s=0.0)
    assert set(simulate(off, cost_frames=3.0)[0]) == {1}
    wall = FrameGovernor(max_lag_s=0.1)
    assert wall.update(T0, T0 + 3600 * 10**9) is None and wall.update(T0 + P, T0 + 3600 * 10**9) is None
    assert not wall.enabled                # a bag played without /clock: never skip


def test_a_schedule_starts_after_every_frame_a_quarter_may_have_taken():
    """Quarters whose fused poses time out run ahead of them: a new schedule starts after
    the newest estimate the arbiter received, on the old schedule's grid, and no later than
    it must (not after the clock's now, seconds ahead under load)."""
    gov = FrameGovernor(max_lag_s=0.1)
    made = []
    for k in range(40):
        stamp = T0 + k * P
        now = stamp + (4 + k) * P                 # the fused poses fall ever further behind
        newest = stamp + (1 + k // 4) * P         # and the quarters run ahead of them
        s = gov.update(stamp, now, newest)
        if s is not None:
            made.append((stamp, newest, s))
    assert made, 'the governor never raised the stride'
    old_stride = 1
    for stamp, newest, s in made:
        assert s.from_ns > newest
        assert (s.from_ns - stamp) % (old_stride * P) == 0
        assert s.from_ns - newest <= (2 + 1) * old_stride * P
        old_stride = s.stride


def test_a_camera_at_another_rate_counts_its_own_frames():
    """A 15 Hz camera in a 30 Hz rig under 'every second frame': by the rig's period all its
    stamps fall on even frames (kept all, or none); by its own it keeps every second one. A
    camera at the rig's rate whose shortest step is a few us short (jitter) counts by the
    schedule's period, like the other cameras of a synchronised rig."""
    s = FrameSchedule(T0, P, 2)
    slow, jittery = ScheduleBook(), ScheduleBook()
    slow.add(s)
    jittery.add(s)
    for k in range(20):
        slow.saw(T0 + 2 * k * P)
        jittery.saw(T0 + k * P + (k % 2) * 3000)
    assert [slow.takes(T0 + 2 * k * P) for k in range(1, 7)] == [False, True] * 3
    assert all(FrameSchedule(T0, P, 2).takes(T0 + 2 * k * P) for k in range(1, 7))     # the rig's count
    assert [jittery.takes(T0 + k * P) for k in range(1, 7)] == [s.takes(T0 + k * P) for k in range(1, 7)]
    moved = ScheduleBook()
    moved.set_state(slow.get_state())
    assert moved.period_ns == 2 * P and moved.takes(T0 + 4 * P) and not moved.takes(T0 + 6 * P)


def test_the_governor_spreads_the_skipping_over_free_running_cameras():
    """Four cameras at 30 Hz with phases 0, 0.3, 0.55 and 0.8 of the period, fused each at
    its own stamp, through a graph that needs half a period per image (two periods a frame of
    the rig): told the cameras' period, the governor keeps the same share of every camera's
    frames, 0.38 where half would do, with the lag under a quarter of a second. An estimate's
    steady lag is one image and its wait behind the others', not the rig's frame, so the
    fraction climbs a step at a time and the growing rule finds the cost: taken as a frame's
    cost that lag raised the fraction to 7/8 and the growing rule threw it to 1/5 (the lag's
    median 0.25 s, 99th percentile 0.61). (From the steps between fused stamps the governor
    read a period a fifth of the frame's, and kept some cameras' frames and none of others'.)"""
    phases = [0.0, 0.3, 0.55, 0.8]
    gov, book = FrameGovernor(max_lag_s=0.1), ScheduleBook()
    clock, kept = T0, {c: [] for c in range(4)}
    lags = []
    for k in range(1800):
        for c, ph in enumerate(phases):
            stamp = T0 + k * P + int(ph * P)
            take = book.takes(stamp, P)
            kept[c].append(take)
            if not take:
                continue
            clock = max(clock, stamp) + P // 2
            lags.append((clock - stamp) / 1e9)
            s = gov.update(stamp, clock, None, P)
            if s is not None:
                book.add(s)
    shares = [sum(v[300:]) / len(v[300:]) for v in kept.values()]
    assert max(shares) - min(shares) <= 0.05 and 0.35 <= min(shares) and max(shares) <= 0.5, shares
    assert gov.camera_rate_hz() == pytest.approx(30.0, rel=1e-3)
    late = sorted(lags[len(lags) // 5:])
    assert late[int(0.99 * len(late))] <= 0.25, late[int(0.99 * len(late))]   # kept up, calmly


def test_free_running_cameras_take_every_frame_again_soon_after_an_overload_passes():
    """Four free-running cameras at 15 Hz through a graph with room to spare (0.15 of a period
    an image) until 0.5 s of images cost three times that (a node's move, a burst of
    extraction): the lag outgrows max_lag_s and frames are skipped, then the graph has room
    again. Half the skipped frames come back at each step (while no fraction below every frame
    was outgrown), so every frame is taken again 3 s after (1/2, 3/4, 7/8, every frame); one
    fraction at a time (4/7, 3/5, 5/8, ...) it took 11.6 s and 20 % of the 20 s of frames."""
    period = int(1e9 / 15)
    phases = [0.0, 0.3, 0.55, 0.8]
    gov, book = FrameGovernor(max_lag_s=0.25), ScheduleBook()
    clock, kept, skipping = T0, [], []
    for k in range(300):
        cost = 0.45 if 60 <= k < 68 else 0.15
        for ph in phases:
            stamp = T0 + k * period + int(ph * period)
            take = book.takes(stamp, period)
            kept.append(take)
            if take:
                clock = max(clock, stamp) + int(cost * period)
                s = gov.update(stamp, clock, None, period)
                if s is not None:
                    book.add(s)
        skipping.append(gov.fraction < 1)
    assert any(skipping[60:80])                              # the overload was felt
    back = max(k for k, s in enumerate(skipping) if s) + 1
    assert (back - 68) / 15 <= 3.5, (back - 68) / 15
    assert sum(kept) / len(kept) >= 0.9
    assert all(kept[-4 * 100:])                              # the last 100 frames all taken
