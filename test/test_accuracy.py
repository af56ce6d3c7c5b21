"""Accuracy regression tests: the project's suite, test/suites/accuracy.yaml, run through
`ego-motion check` once. It generates its scenario bags (fixed seed), replays each through
the whole graph (lockstep, real nodes over DDS on 2 workers) and scores the odometry it
recorded against the bag's /ground_truth/odom; a change that makes a figure worse than the
suite's limit fails here, one test per bag.

The limits live in the suite file (with what they were set from); this file checks that
every bag was replayed whole and met them. Five bags: about two minutes on two cores.
"""
from pathlib import Path

import pytest

from conftest import assert_suite_bag, check_suite
from multicam_ego_motion.check.suite import load_suite

SUITE = Path(__file__).resolve().parent / 'suites' / 'accuracy.yaml'
FRAMES = 20 * 8 + 1          # 20 s at 8 Hz, both ends
BAGS = ('loop', 'corridor', 'spin_then_drive', 'lighting', 'loop_no_wheel')


@pytest.fixture(scope='module')
def results(tmp_path_factory):
    return check_suite(SUITE, tmp_path_factory.mktemp('accuracy'), timeout=850)


def test_suite_holds_the_accuracy_bags():
    suite = load_suite(SUITE)
    assert tuple(b.name for b in suite.bags) == BAGS
    assert all(b.workers == 2 and b.limits['odometry_share'] == 1.0 for b in suite.bags)
    assert [b.name for b in suite.bags if b.no_wheel] == ['loop_no_wheel']


@pytest.mark.parametrize('name', BAGS)
def test_scenario_accuracy(results, name):
    assert_suite_bag(results, name, FRAMES)
