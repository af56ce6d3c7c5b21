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
    r = FloorRuns(seq_cpu_ms=[4.0, 3.5], graph_cpu_ms=[(7.0, 1.5), (6.5, 1.5)], frames=10)
    assert r.floor_ms == 8.0 - 3.5              # the cheapest run of each
    assert math.isclose(r.allowed_speedup(36.0), 2 * 36.0 / 40.5)
    text = '\n'.join(r.lines(36.0))
    assert '| the floor: graph over sequential [ms] | 4.5 |' in text
    assert '| 6.5 + 1.5 |' in text
    # 1.8 leaves a 36 ms pipeline 4 ms of transport, and needs 40.5 ms over a 4.5 ms floor
    assert 'Ts (2 / 1.8 - 1) [ms] | 4.0 |' in text
    assert '[ms] | 40 |' in text


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
    r = transport_floor(BAG, tmp_path / 'floor', default_params(), duration=1.5, runs=1)
    assert r.frames >= 10
    assert len(r.seq_cpu_ms) == 1 and r.seq_cpu_ms[0] > 0
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
        transport_floor(tmp_path / 'no_such_bag', tmp_path / 'floor', default_params(), runs=1)
    assert 'transport floor run failed' in str(e.value) and 'no_such_bag' in str(e.value)
