"""Garbage collection moved to a worker's idle time (coordinator/idle_gc.py), without ROS."""
import gc

import pytest

from multicam_ego_motion.coordinator.idle_gc import BUSY_FACTOR, IdleCollector


@pytest.fixture
def collector():
    c = IdleCollector()
    try:
        yield c
    finally:
        c.close()


def allocate(n):
    """n container objects that survive (tracked by the collector)."""
    return [[i] for i in range(n)]


def test_what_exists_at_start_is_frozen_and_nothing_is_collected_automatically(collector):
    assert not gc.isenabled()
    assert gc.get_freeze_count() > 1000            # the imported libraries' objects
    t0 = collector.thresholds[0]
    keep = allocate(3 * t0)                         # Python would have collected ~3 times
    assert gc.get_count()[0] >= 3 * t0
    assert collector.due() and collector.generation_due() == 0
    collector.collect_if_overdue()                  # busy, but not far past due: waits
    assert gc.get_count()[0] >= 3 * t0
    collector.collect_idle()                        # idle: the young generation goes
    assert gc.get_count()[0] < t0 and not collector.due()
    assert gc.get_count()[1] == 1                   # counted like an automatic collection
    del keep


def test_older_generations_are_collected_by_pythons_thresholds(collector):
    t0, t1, _ = collector.thresholds
    gc.collect()
    # (2 t0: lists freed before come back from a free list, which the count does not see)
    for _ in range(t1):                             # t1 young collections make the next one older
        keep = allocate(2 * t0)
        collector.collect_idle()
        del keep
    keep = allocate(2 * t0)
    assert collector.generation_due() == 1
    collector.collect_idle()
    assert gc.get_count()[1] == 0 and gc.get_count()[2] == 1


def test_a_worker_that_never_gets_idle_still_collects(collector):
    t0 = collector.thresholds[0]
    keep = allocate(BUSY_FACTOR * t0 + 10)
    collector.collect_if_overdue()
    assert gc.get_count()[0] < t0
    del keep


def test_close_gives_python_back_its_collector():
    c = IdleCollector()
    c.close()
    assert gc.isenabled() and gc.get_freeze_count() == 0
