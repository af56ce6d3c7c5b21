"""The bench's transport floor: the graph with quarters that do no work (bench/transport_floor.py)."""
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from multicam_ego_motion.bench.measures import read_statuses, is_quarter
from multicam_ego_motion.bench.transport_floor import ENV, FloorRuns, transport_floor
from multicam_ego_motion.evaluation.trajectory_io import read_bag_topic
from multicam_ego_motion.ros_plumbing.package_share import default_params

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'default'


def test_floor_figures_from_given_numbers():
    # sequential runs before, between and after the two graph runs (the host got slower)
    r = FloorRuns(seq_cpu_ms=[3.0, 4.0, 4.0], graph_cpu_ms=[(7.0, 1.5), (7.5, 1.5)], frames=10)
    assert r.floors_ms == [8.5 - 3.5, 9.0 - 4.0]  # each against the runs around it
    assert r.floor_ms == 5.0                       # the lowest bounds
    assert math.isclose(r.allowed_speedup(40.0), 2 * 40.0 / 45.0)
    text = '\n'.join(r.lines(40.0))
    assert '| the floor: graph over sequential [ms] | 5.0 |' in text
    assert '| sequential pipeline, CPU per frame [ms] | 3.5 |' in text
    assert '| 7.0 + 1.5 |' in text
    # 1.8 leaves a 40 ms pipeline 4.4 ms of transport, and needs 45 ms over a 5 ms floor
    assert 'Ts (2 / 1.8 - 1) [ms] | 4.4 |' in text
    assert '[ms] | 45 |' in text
    assert 'floors 5.0 / 5.0 ms' in text


def test_null_estimator_answers_every_image_without_tracking():
    # In a child process: install() changes the estimator class of the process it runs in.
    code = (
        'import json, numpy as np\n'
        'from multicam_ego_motion.bench.transport_floor import installed_from_environment\n'
        'assert installed_from_environment()\n'
        'from multicam_ego_motion.sequential_pipeline import run_sequential\n'
        'from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader\n'
        'from multicam_ego_motion.replay import resolve_rig\n'
        'from multicam_ego_motion.params_file import fusion_params_from, quarter_params_from\n'
        'from multicam_ego_motion.ros_plumbing.package_share import default_params\n'
        f'bag = {str(BAG)!r}\n'
        'rig, _ = resolve_rig(Rosbag2Reader(bag), None)\n'
        'p = default_params()\n'
        'r = run_sequential(bag, rig, quarter_params_from(p), fusion_params_from(p), max_frames=6)\n'
        'q = [e for es in r.quarters.values() for e in es]\n'
        'print(json.dumps({"frames": len(r.fused), "estimates": len(q), "features": sum(e.n_features for e in q),\n'
        '                  "identity": all(np.array_equal(e.T_odom_base, np.eye(4)) for e in q)}))\n')
    p = subprocess.run([sys.executable, '-c', code], env=dict(os.environ, **{ENV: '1'}),
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    d = json.loads(p.stdout.strip().splitlines()[-1])
    assert d['frames'] == 6
    assert d['estimates'] == 6 * 16
    assert d['features'] == 0 and d['identity']


def test_floor_run_puts_idle_quarters_in_every_worker(tmp_path):
    r = transport_floor(BAG, tmp_path / 'floor', BAG / 'rig.yaml', default_params(), duration=1.5, runs=1)
    assert r.frames >= 10
    assert len(r.seq_cpu_ms) == 2 and min(r.seq_cpu_ms) > 0      # before and after the graph run
    (workers, replay), = r.graph_cpu_ms
    assert workers > 0 and replay > 0
    out = tmp_path / 'floor' / 'graph0' / 'output'
    assert len(read_bag_topic(out, '/odom')) == r.frames         # every frame fused, in lockstep
    quarters = [v for name, v in read_statuses(out) if is_quarter(name) and 'features' in v]
    # every quarter of both workers answered, and none of them tracked a feature
    assert len(quarters) == 16 * r.frames
    assert all(v['features'] == '0' and v['state'] == 'tracking' for v in quarters)


def test_a_failed_floor_run_raises_with_the_child_output(tmp_path):
    with pytest.raises(RuntimeError) as e:
        transport_floor(tmp_path / 'no_such_bag', tmp_path / 'floor', BAG / 'rig.yaml', default_params(), runs=1)
    assert 'transport floor run failed' in str(e.value) and 'no_such_bag' in str(e.value)
