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
