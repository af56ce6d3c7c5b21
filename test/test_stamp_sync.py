from arbiter_node.stamp_sync import StampSynchronizer


def test_releases_when_all_sources_reported():
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0)
    assert s.add('a', 10, 'A', now=0.0) == []
    groups = s.add('b', 10, 'B', now=0.1)
    assert len(groups) == 1 and groups[0].items == {'a': 'A', 'b': 'B'} and not groups[0].timed_out


def test_absent_source_costs_one_timeout_then_is_not_waited_for():
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0)
    assert s.add('a', 10, 'A', now=0.0) == []
    assert s.poll(now=0.5) == []
    g = s.poll(now=1.01)
    assert [x.stamp_ns for x in g] == [10] and g[0].missing == ['b'] and g[0].timed_out
    g = s.add('a', 20, 'A2', now=1.1)          # b is absent now: released at once
    assert [x.stamp_ns for x in g] == [20] and g[0].missing == ['b']
    assert s.add('b', 30, 'B3', now=1.2) == []  # b is back: waited for again
    g = s.add('a', 30, 'A3', now=1.3)
    assert g[0].items == {'a': 'A3', 'b': 'B3'}


def test_late_stamp_is_dropped_and_order_kept():
    s = StampSynchronizer(['a'], timeout_s=1.0)
    s.add('a', 20, 'x', now=0.0)
    assert s.add('a', 10, 'y', now=0.1) == []
    assert s.dropped_late == 1


def test_newer_complete_group_releases_older_incomplete_one():
    s = StampSynchronizer(['a', 'b'], timeout_s=10.0)
    s.add('a', 10, 'A', now=0.0)
    s.add('a', 20, 'A', now=0.1)
    g = s.add('b', 20, 'B', now=0.2)
    assert [x.stamp_ns for x in g] == [10, 20]
    assert g[0].missing == ['b']


def test_late_estimate_of_an_absent_source_makes_it_awaited_again():
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0)
    s.add('a', 10, 'A', now=0.0)
    s.poll(now=2.0)                            # b missed frame 10: absent
    assert s.add('a', 20, 'A', now=2.1)[0].missing == ['b']
    assert s.add('b', 20, 'B', now=2.2) == []  # late for 20, but alive again
    assert s.add('a', 30, 'A', now=2.3) == []  # so frame 30 waits for b
    assert s.add('b', 30, 'B', now=2.4)[0].items == {'a': 'A', 'b': 'B'}


# --- free-running cameras: a window instead of identical stamps -------------------------
MS = 1_000_000


def test_window_groups_stamps_a_few_ms_apart_in_any_order():
    s = StampSynchronizer(['a', 'b', 'c'], timeout_s=10.0, window_ns=30 * MS)
    assert s.add('c', 24 * MS, 'C', now=0.0) == []       # arrival order is not stamp order
    assert s.add('a', 0, 'A', now=0.1) == []
    g = s.add('b', 8 * MS, 'B', now=0.2)
    assert len(g) == 1 and g[0].items == {'a': 'A', 'b': 'B', 'c': 'C'} and not g[0].timed_out
    assert g[0].stamp_ns == 24 * MS and g[0].first_ns == 0    # fused at the latest stamp
    assert g[0].stamps == {'a': 0, 'b': 8 * MS, 'c': 24 * MS}
    # the next frame (66.7 ms later) is a group of its own, even with the window open
    assert s.add('a', 67 * MS, 'A2', now=0.3) == []
    assert s.add('b', 75 * MS, 'B2', now=0.4) == []
    assert s.add('c', 91 * MS, 'C2', now=0.5)[0].stamps == {'a': 67 * MS, 'b': 75 * MS, 'c': 91 * MS}


def test_window_zero_keeps_identical_stamps_apart():
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0)
    s.add('a', 10, 'A', now=0.0)
    g = s.add('b', 11, 'B', now=0.1)        # 1 ns apart: two frames, and b is past frame 10
    assert [x.stamp_ns for x in g] == [10] and g[0].missing == ['b'] and 'b' not in s.absent
    g = s.poll(now=1.2)
    assert [x.stamp_ns for x in g] == [11] and g[0].missing == ['a'] and g[0].timed_out


def test_one_source_twice_in_the_window_starts_the_next_group():
    s = StampSynchronizer(['a', 'b'], timeout_s=10.0, window_ns=50 * MS)
    s.add('a', 0, 'A1', now=0.0)
    s.add('a', 33 * MS, 'A2', now=0.1)                    # within the window, but a's next frame
    g = s.add('b', 40 * MS, 'B2', now=0.2)
    assert [x.stamps for x in g] == [{'a': 0}, {'a': 33 * MS, 'b': 40 * MS}]


def test_slower_camera_is_not_waited_for_between_its_frames():
    # a at 30 Hz, b at 15 Hz: after b's period is known, the groups without a frame of b are
    # released as soon as a reported, and b is neither missing nor absent there.
    s = StampSynchronizer(['a', 'b'], timeout_s=10.0, window_ns=5 * MS)
    p = 33_333_333
    released = []
    now = 0.0
    for k in range(8):
        now += 0.1
        released += s.add('a', k * p, f'a{k}', now)
        if k % 2 == 0:
            released += s.add('b', k * p, f'b{k}', now)
        if k == 1:   # b's period is unknown yet: its first gap costs one timeout
            assert released[-1].stamp_ns == 0
            now += 10.0
            released += s.poll(now)
            assert released[-1].timed_out and released[-1].missing == ['b']
            assert 'b' not in s.absent                    # maybe slower, not dead
    assert [g.stamp_ns for g in released] == [k * p for k in range(8)]
    assert [sorted(g.items) for g in released[2:]] == [['a', 'b'], ['a']] * 3
    assert not any(g.timed_out or g.missing for g in released[2:])


def test_source_reporting_once_then_silent_becomes_absent_on_its_second_miss():
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0, window_ns=5 * MS)
    s.add('a', 0, 'A', now=0.0)
    s.add('b', 0, 'B', now=0.0)
    s.add('a', 100 * MS, 'A', now=0.1)
    assert s.poll(now=1.2)[0].missing == ['b'] and 'b' not in s.absent
    s.add('a', 200 * MS, 'A', now=1.3)
    assert s.poll(now=2.4)[0].missing == ['b'] and 'b' in s.absent
    assert s.add('a', 300 * MS, 'A', now=2.5)[0].missing == ['b']     # not waited for now


def test_bad_window_is_refused():
    import pytest
    with pytest.raises(ValueError, match='window'):
        StampSynchronizer(['a'], 1.0, window_ns=-1)


def test_group_a_source_has_moved_past_is_not_waited_for():
    # Two frames in flight: b (15 Hz, period not known yet) reports its next frame while a's
    # frame without b is open. b's stamps only grow, so that frame is released at once.
    p = 33_333_333
    s = StampSynchronizer(['a', 'b'], timeout_s=10.0, window_ns=5 * MS)
    s.add('a', 0, 'a0', now=0.0)
    assert len(s.add('b', 0, 'b0', now=0.0)) == 1
    assert s.add('a', p, 'a1', now=0.1) == []             # b might still come for frame 1
    g = s.add('b', 2 * p, 'b2', now=0.2)
    assert [x.stamp_ns for x in g] == [p] and not g[0].timed_out and 'b' not in s.absent
    g = s.add('a', 2 * p, 'a2', now=0.3)
    assert g[0].items == {'a': 'a2', 'b': 'b2'} and not g[0].timed_out


def test_a_camera_capturing_just_after_a_group_is_not_named_missing():
    # 15 Hz (66.7 ms): b captures 7 ms after a, within the eighth of its period in which it is
    # due in a's group; its image belongs to its own stamp, so a's group does not miss it.
    P, d = 66_700_000, 7_000_000
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0)
    out = []
    for k in range(4):
        out += s.add('a', k * P, 'A', now=0.1 * k)
        out += s.add('b', k * P + d, 'B', now=0.1 * k + 0.01)
    assert [g.stamp_ns for g in out] == [t for k in range(4) for t in (k * P, k * P + d)]
    # (until b has two stamps its period is unknown: the first group still names it)
    assert not any(g.timed_out for g in out)
    assert [g.missing for g in out[2:]] == [[]] * 6, [(g.stamp_ns, g.missing) for g in out]


def test_a_dropped_frame_of_a_synchronised_camera_is_named_missing():
    P = 100
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0)
    out = []
    for k in range(3):
        out += s.add('a', k * P, 'A', now=0.1 * k)
        out += s.add('b', k * P, 'B', now=0.1 * k)
    out += s.add('a', 3 * P, 'A', now=0.3)              # b drops frame 3
    out += s.add('b', 4 * P, 'B', now=0.4)
    out += s.add('a', 4 * P, 'A', now=0.4)
    assert [(g.stamp_ns, g.missing) for g in out] == [(0, []), (P, []), (2 * P, []), (3 * P, ['b']), (4 * P, [])]


def test_a_frame_the_schedule_skips_is_not_waited_for():
    """Free-running cameras behind a frame schedule: a camera whose next frame the schedule
    skips is due at the one after, so the other camera's estimates before that are released
    at once, not after the timeout."""
    P = 100
    skipped = {('b', 3 * P + 40)}
    s = StampSynchronizer(['a', 'b'], timeout_s=1.0, takes=lambda src, t: (src, t) not in skipped)
    unscheduled = StampSynchronizer(['a', 'b'], timeout_s=1.0)
    for sync in (s, unscheduled):
        for k in range(3):                       # a at 0, 100, 200; b 40 ms after each
            sync.add('a', k * P, 'A', now=0.01 * k)
            sync.add('b', k * P + 40, 'B', now=0.01 * k)
        assert [x.stamp_ns for x in sync.add('a', 3 * P, 'A', now=0.1)] == [3 * P]
    # b's 340 is skipped: its next frame is 440, after a's 400
    g = s.add('a', 4 * P, 'A', now=0.11)
    assert [x.stamp_ns for x in g] == [4 * P] and not g[0].timed_out and g[0].missing == []
    assert [x.stamp_ns for x in s.add('b', 4 * P + 40, 'B', now=0.12)] == [4 * P + 40]
    # without the schedule a's 400 waits for b's 340 until the timeout
    assert unscheduled.add('a', 4 * P, 'A', now=0.11) == []
    g = unscheduled.poll(now=1.2)
    assert [x.stamp_ns for x in g] == [4 * P] and g[0].timed_out and g[0].missing == ['b']
