"""Accuracy regression tests: the project's suite, test/suites/accuracy.yaml, run through
`ego-motion check` once. It generates its scenario bags (fixed seed), replays each through
the whole graph (lockstep, real nodes over DDS on 2 workers) and scores the odometry it
recorded against the bag's /ground_truth/odom; a change that makes a figure worse than the
suite's limit fails here, one test per bag.

The limits live in the suite file (with what they were set from); this file checks that
every bag was replayed whole and met them. Five bags: about two minutes on two cores.
"""
import json
from pathlib import Path

import pytest

from conftest import run_cli
from multicam_ego_motion.check.suite import load_suite

SUITE = Path(__file__).resolve().parent / 'suites' / 'accuracy.yaml'
FRAMES = 20 * 8 + 1          # 20 s at 8 Hz, both ends
BAGS = ('loop', 'corridor', 'spin_then_drive', 'lighting', 'loop_no_wheel')


@pytest.fixture(scope='module')
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp('accuracy')
    out = root / 'check'
    r = run_cli('check', SUITE, '--out', out, '--bags-cache', root / 'bags', timeout=850)
    # 1: a regression, which the per-bag tests below name; anything else is a broken run
    assert r.returncode in (0, 1), r.stdout + r.stderr
    return json.loads((out / 'results.json').read_text())


def test_suite_holds_the_accuracy_bags():
    suite = load_suite(SUITE)
    assert tuple(b.name for b in suite.bags) == BAGS
    assert all(b.workers == 2 and b.limits['odometry_share'] == 1.0 for b in suite.bags)
    assert [b.name for b in suite.bags if b.no_wheel] == ['loop_no_wheel']


@pytest.mark.parametrize('name', BAGS)
def test_scenario_accuracy(results, name):
    bag = results['bags'][name]
    assert bag['error'] is None, f'{name}: replay failed: {bag["error"]}'
    f = bag['figures']
    assert f['frames'] == FRAMES, f'{name}: {f["frames"]} of {FRAMES} frames played'
    assert f['frames_with_odometry'] == f['odometry_poses'] == FRAMES, \
        f'{name}: odometry for {f["frames_with_odometry"]} of {FRAMES} frames'
    summary = ', '.join(f'{c["figure"]} ' + ('n/a' if c['value'] is None else f'{c["value"]:.4f}')
                        + f' ({c["condition"]})' for c in bag['checks'])
    failed = [c['figure'] for c in bag['checks'] if not c['passed']]
    assert not failed, f'{name}: {", ".join(failed)} out of bounds ({summary})'
