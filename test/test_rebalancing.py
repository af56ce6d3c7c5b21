"""Rebalancing on measured costs: on the bare_wall scenario the left
camera's features thin out as it passes the bare wall, its quarters' measured cost (CPU ms
from their /diagnostics) falls to about half, and the coordinator, which started with
whole cameras per worker ({front, back} / {left, right}), moves a quarter to the worker
that went idle. Nothing is forced (no --migrate-every): the move comes from the costs.
The odometry keeps every frame, finite; the number of moves stays small (no thrashing)."""
import numpy as np
import pytest

from multicam_ego_motion.scenarios.generator import generate
from replay_run import replay

RATE = 8
# Textured until ~6.7 s, then the bare stretch (left camera) to 14.7 s. With the arbiters' few
# ms the two workers start nearly balanced, so the imbalance builds from the bare wall on and
# the 10-frame hysteresis ends ~3.5-5 s in. The best move gains 11-25 %, against a 10 %
# threshold, measured on a loaded machine frame by frame: one CI run of 8 s never had 8 of 10
# frames over it, so the run goes to 14 s.
START_S, DURATION_S = 4.0, 10.0
FRAMES = int(DURATION_S * RATE)
STAGES = ('acquire_ms', 'extract_ms', 'track_ms', 'pose_ms', 'structure_ms')


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    base = tmp_path_factory.mktemp('rebalance')
    bag = base / 'bare_wall'
    # The scenario's path needs its full 30 s (the bare stretch is 6.7-14.7 s along it).
    generate('bare_wall', bag, seed=7, duration=30.0, rate=RATE, width=320, height=240,
             progress=False)
    r = replay(bag, base / 'out', '--start-offset', START_S, '--duration', DURATION_S, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    return r


def camera_costs(run):
    """{t: {camera: sum of its quarters' stage times [ms]}} from the recorded /diagnostics."""
    out = {}
    for d in run.diagnostics('ego_motion/'):
        parts = d.name.split('/')
        if len(parts) == 3 and parts[2].startswith('q') and all(k in d.values for k in STAGES):
            cams = out.setdefault(round(d.t, 3), {})
            cams[parts[1]] = cams.get(parts[1], 0.0) + sum(float(d.values[k]) for k in STAGES)
    return out


def ratio_left(costs, t0, t1):
    """The left camera's cost over the mean of the other three, frames in [t0, t1)."""
    frames = [c for t, c in costs.items() if t0 <= t < t1 and len(c) == 4]
    assert frames
    return np.mean([c['left'] / np.mean([c[k] for k in ('front', 'back', 'right')]) for c in frames])


def test_coordinator_moves_nodes_when_the_left_camera_goes_bare(run):
    out = run.stdout.splitlines()
    rebalances = [l for l in out if l.startswith('coordinator: rebalance at frame')]
    moves = [l for l in out if l.startswith('coordinator: moved ')]
    assert rebalances, run.stdout
    # no thrashing: with two workers a node that moves twice went back (each rebalance waits
    # 2 x 10 frames after the one before, so 80 frames allow 4)
    moved = [m.split('moved ')[1].split(':')[0] for m in moves]
    assert 1 <= len(moves) <= 4 and len(rebalances) <= 3 and len(set(moved)) == len(moved), run.stdout
    # start: whole cameras, left with right; nodes move to that worker once it got cheaper
    # (a move the other way may come first: the textured start measured the workers 46-50 vs
    # 57-70 ms once on this VM, a legitimate rebalance before the wall)
    start = next(l for l in out if l.startswith('coordinator: allocation'))
    left_worker = int(start.split('left/q1')[0].rsplit('worker ', 1)[1].split(':')[0])
    into_left = [k for k, m in enumerate(moves)
                 if m.split(': worker ')[1].split(' in ')[0].endswith(f'-> {left_worker}')]
    assert into_left, moves

    coord = run.diagnostics('ego_motion/coordinator')
    assert coord and {'imbalance', 'migrations', 'rebalances', f'worker_{left_worker}'} <= set(coord[0].values)
    assert int(coord[-1].values['migrations']) == len(moves)
    assert int(coord[-1].values['rebalances']) == len(rebalances)
    t_move = min(d.t for d in coord if int(d.values['migrations']) > into_left[0])
    assert t_move > START_S + 1.5
    # what the coordinator answered: the worker it moved into measured the lighter one (its own
    # loads in the rebalance line; the second before the move is no measure of the wall: the
    # 10-frame hysteresis can end ~0.3 s into it, read 0.92 of the textured ratio once on CI)
    into_line = next(l for l in rebalances if f'-> worker {left_worker}' in l)
    loads = [float(x) for x in into_line.split('worker loads ')[1].split(' -> ')[0].split('/')]
    targets = {int(m.rsplit('worker ', 1)[1]) for m in into_line.split('move(s): ')[1].split(', ')}
    if targets == {left_worker}:        # (a fresh allocation may move nodes both ways)
        assert loads[left_worker] == min(loads), into_line
    # and the left camera's measured cost fell (bare wall)
    costs = camera_costs(run)
    textured = ratio_left(costs, START_S + 0.5, START_S + 1.5)
    # (about half by the end: 0.48-0.50 of the textured ratio measured; CPU times of a loaded
    # machine move it, 0.61 once on CI, so the bound is 0.7, far below the textured 1.0)
    assert ratio_left(costs, START_S + DURATION_S - 1.0, START_S + DURATION_S) < 0.7 * textured
    # and each rebalance was for a better balance on the costs it measured. (The imbalance
    # measured after a move is CPU time on a shared machine: CI runs read it 0.19 after vs 0.18
    # before, and 0.14 vs 0.11 over 0.25-1 s after, while the moved node's first frames on its
    # new worker cost more; a timing, not asserted.)
    for line in rebalances:
        before, after = line.split('imbalance ')[1].split(';')[0].split(' -> ')
        assert float(after) < float(before), line


def test_odometry_stays_valid_through_the_moves(run):
    stamps, T, _, _ = run.odometry()
    assert len(stamps) == FRAMES and len(set(stamps.tolist())) == FRAMES
    assert run.odom_problems() == []
    assert np.all(np.isfinite(T))
    assert run.leftover_processes() == []
