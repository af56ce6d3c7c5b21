"""Moving quarter nodes between workers mid-run (state hand-over) changes nothing: in
lockstep a run with forced migrations skips no frame and publishes the same odometry as a
run without. Also the prerequisite: two plain lockstep runs are identical, and pipelining
(two frames in flight, the default) gives the same odometry as one frame at a time."""
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from test_crash_recovery import no_worker_left, odometry

REPO = Path(__file__).resolve().parents[1]
DEFAULT_BAG = REPO / 'bags' / 'default'
DURATION_S = 3                      # 24 frames at 8 Hz
FRAMES = DURATION_S * 8


def replay(out, *extra):
    r = run_cli('replay', DEFAULT_BAG, '--out', out, '--workers', 2, '--duration', DURATION_S,
                '--no-rebalance', *extra, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


@pytest.fixture(scope='module')
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp('migration')
    plain = [replay(base / f'plain{i}') for i in range(2)]
    moved = replay(base / 'moved', '--migrate-every', 3)
    replay(base / 'depth1', '--lockstep-depth', 1)
    return base, plain, moved


def assert_identical_odometry(a, b):
    s1, p1 = odometry(a)
    s2, p2 = odometry(b)
    assert len(s1) == FRAMES and s1 == s2
    assert np.array_equal(p1, p2)


def test_two_lockstep_runs_are_identical(runs):
    base, _, _ = runs
    assert_identical_odometry(base / 'plain0', base / 'plain1')


def test_pipelining_changes_nothing(runs):
    base, _, _ = runs
    assert_identical_odometry(base / 'plain0', base / 'depth1')


def test_forced_migrations_skip_no_frame_and_change_nothing(runs):
    base, _, moved_out = runs
    assert 'moved front/q1: worker' in moved_out
    n_moves = moved_out.count('coordinator: moved ')
    assert n_moves >= (FRAMES - 1) // 3 - 1
    s1, p1 = odometry(base / 'plain0')
    s2, p2 = odometry(base / 'moved')
    assert s1 == s2                              # every frame, none skipped
    assert np.max(np.abs(p1 - p2)) < 1e-9


def test_no_worker_left_after_runs(runs):
    assert no_worker_left()
