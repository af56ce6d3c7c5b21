"""The graph across hosts: three network namespaces on this machine (bench/netns.py: veth
pairs to a bridge, 10.77.0.x, nothing outside, DDS over UDPv4 only with initial peers), the
coordinator and player in host 0, one remote worker in each of hosts 1 and 2 (`ego-motion
worker --coordinator 10.77.0.1:PORT`, the key in a file). The default bag's lockstep /odom
through that graph is the one-host run's, byte for byte; a worker without the key is refused
on both sides; killing every process of a worker's host mid-run is recovered (its nodes are
restored on the coordinator host's spare) and every frame gets its /odom.

Skipped, with the reason, where namespaces cannot be made (not root, no `ip`)."""
import os
import re
import subprocess
import sys
import threading
import time

import pytest

from conftest import REPO, run_cli
from multicam_ego_motion.bench import netns

DEFAULT_BAG = REPO / 'bags' / 'default'
DURATION_S = 3.0          # lockstep comparison (24 frames)
KILL_DURATION_S = 15.0    # the crash run (120 frames): the failure comes after frame KILL_AT, mid-run even when the counter matches the graph late
KILL_AT = 12
PORT = 7451
COORDINATOR = f'{netns.SUBNET}.1:{PORT}'

REASON = netns.unavailable()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f'multi-host test: {REASON}')

CLI = [sys.executable, '-m', 'multicam_ego_motion.cli']
ODOM_COUNTER = '''
import sys, rclpy
from nav_msgs.msg import Odometry
from multicam_ego_motion.ros_plumbing.qos import RELIABLE
rclpy.init()
node = rclpy.create_node('odom_counter')
n = [0]
def seen(msg):
    n[0] += 1
    print(n[0], flush=True)
node.create_subscription(Odometry, '/odom', seen, RELIABLE)
rclpy.spin(node)
'''


@pytest.fixture(scope='module')
def hosts(tmp_path_factory):
    from multicam_ego_motion.ros_plumbing.ros_domain import free_domain
    h = netns.Hosts(3, free_domain(os.getpid() + 17))
    h.__enter__()
    yield h
    h.close()                 # namespaces and their processes go, also when a test failed


@pytest.fixture(scope='module')
def env(tmp_path_factory):
    key_file = tmp_path_factory.mktemp('key') / 'control.key'
    key_file.write_text('multi-host-test-key-' + os.urandom(16).hex())
    key_file.chmod(0o600)
    e = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    e.pop('EGO_MOTION_CONTROL_KEY', None)
    return e, key_file


def start_workers(hosts, env, key_file, out):
    logs = []
    for i in (1, 2):
        log = open(out / f'remote_worker_{i}.log', 'w')
        logs.append(out / f'remote_worker_{i}.log')
        hosts.run(i, CLI + ['worker', '--coordinator', COORDINATOR, '--key-file', key_file],
                  env=env, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
    return logs


def replay_in_host0(hosts, env, key_file, out, duration):
    return hosts.run(0, CLI + ['replay', DEFAULT_BAG, '--out', out, '--workers', 2,
                               '--remote-workers', 2, '--listen', COORDINATOR, '--key-file', key_file,
                               '--duration', duration, '--no-rebalance'],
                     env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)


def poses(tum_text):
    return [line for line in tum_text.splitlines() if line and not line.startswith('#')]


def summary_value(stdout, label):
    m = re.search(rf'^{re.escape(label)}\s+(\S+)', stdout, re.M)
    assert m, f'{label!r} not in the replay summary:\n{stdout[-3000:]}'
    return m.group(1)


@pytest.fixture(scope='module')
def lockstep_runs(hosts, env, tmp_path_factory):
    e, key_file = env
    base = tmp_path_factory.mktemp('multi_host')
    t0 = time.monotonic()
    one = run_cli('replay', DEFAULT_BAG, '--out', base / 'one_host', '--workers', 2,
                  '--duration', DURATION_S, '--no-rebalance', timeout=600)
    assert one.returncode == 0, one.stderr[-3000:]
    out = base / 'three_hosts'
    out.mkdir()
    # a worker that does not know the key, started first: refused, the others join
    wrong = dict(e, EGO_MOTION_CONTROL_KEY='not-the-key-' + os.urandom(8).hex())
    intruder = hosts.run(1, CLI + ['worker', '--coordinator', COORDINATOR], env=wrong,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    replay = replay_in_host0(hosts, e, key_file, out, DURATION_S)
    intruder_out, _ = intruder.communicate(timeout=120)
    logs = start_workers(hosts, e, key_file, out)
    stdout, _ = replay.communicate(timeout=600)
    return base, one, replay.returncode, stdout, intruder.returncode, intruder_out, logs, time.monotonic() - t0


def test_three_hosts_give_the_one_host_odometry(lockstep_runs):
    base, one, code, stdout, _, _, logs, _ = lockstep_runs
    assert code == 0, stdout[-3000:]
    assert 'joined as worker 0' in stdout and 'joined as worker 1' in stdout, stdout[-3000:]
    one_host = (base / 'one_host' / 'odometry.tum').read_text()
    three_hosts = (base / 'three_hosts' / 'odometry.tum').read_text()
    frames = int(summary_value(stdout, 'frames played'))
    assert frames >= 20 and len(poses(three_hosts)) == frames
    assert three_hosts == one_host
    # the remote workers hosted graph nodes, then stopped when the coordinator did
    for log in logs:
        text = log.read_text()
        assert re.search(r'worker \d \(pid \d+\) hosts \S', text), text[-2000:]
        assert 'stopped by the coordinator' in text, text[-2000:]


def test_worker_without_the_key_is_refused_on_both_sides(lockstep_runs):
    _, _, _, stdout, intruder_code, intruder_out, _, _ = lockstep_runs
    assert intruder_code == 2, intruder_out
    assert 'refused this worker: wrong control key' in intruder_out
    assert re.search(rf'refused a worker from {re.escape(netns.SUBNET)}\.2:\d+: it does not know the control key',
                     stdout), stdout[-3000:]


def run_with_a_failure(hosts, env, tmp_path_factory, name, fail):
    """A lockstep run on the three hosts; `fail()` is called once KILL_AT /odom were seen
    (a counter subscribed in host 0). Returns (replay stdout, return code, what fail()
    returned, the remote workers' log files)."""
    e, key_file = env
    out = tmp_path_factory.mktemp('multi_host') / name
    out.mkdir()
    counter = hosts.run(0, [sys.executable, '-c', ODOM_COUNTER], env=e, stdout=subprocess.PIPE,
                        stderr=subprocess.DEVNULL, text=True, cwd=REPO)
    replay = replay_in_host0(hosts, e, key_file, out, KILL_DURATION_S)
    logs = start_workers(hosts, e, key_file, out)
    done = []

    def watch():
        for line in counter.stdout:
            if int(line) >= KILL_AT:
                done.append(fail())
                return
    threading.Thread(target=watch, daemon=True).start()
    stdout, _ = replay.communicate(timeout=600)
    counter.kill()
    assert done, f'the failure never came (fewer than {KILL_AT} /odom seen):\n{stdout[-3000:]}'
    return out, stdout, replay.returncode, done[0], logs


def assert_recovered(out, stdout, code):
    assert code == 0, stdout[-3000:]
    assert re.search(r'remote worker \d is gone; restoring', stdout), stdout[-3000:]
    assert ', 1 worker restarts' in stdout, stdout[-3000:]
    frames = int(summary_value(stdout, 'frames played'))
    assert frames >= 40
    assert int(summary_value(stdout, '/odom messages')) == frames
    assert len(poses((out / 'odometry.tum').read_text())) == frames
    assert float(summary_value(stdout, 'ATE RMSE, aligned on first pose [% of path]')) < 2.0


def test_killed_remote_host_is_recovered(hosts, env, tmp_path_factory):
    """Every process of host 2 killed: the kernel closes the worker's connection."""
    out, stdout, code, killed, _ = run_with_a_failure(
        hosts, env, tmp_path_factory, 'host_killed', lambda: hosts.kill_host(2))
    assert killed, 'no process was running in host 2'
    assert re.search(r'remote worker \d on .* lost: its connection closed', stdout), stdout[-3000:]
    assert_recovered(out, stdout, code)


def test_unreachable_host_is_recovered(hosts, env, tmp_path_factory):
    """Host 2's link goes down (a host that died or a cable pulled: no FIN, only silence): the
    coordinator misses its heartbeats and restores its nodes; the cut-off worker misses the
    coordinator's, stops its nodes and exits with 3."""
    def cut():
        netns._ip('-n', hosts.names[2], 'link', 'set', 'eth0', 'down')
        return True
    try:
        out, stdout, code, _, logs = run_with_a_failure(hosts, env, tmp_path_factory, 'host_unreachable', cut)
        assert re.search(r'remote worker \d on .* lost: no heartbeat for 5 s', stdout), stdout[-3000:]
        assert_recovered(out, stdout, code)
        deadline = time.monotonic() + 30
        cut_off = logs[1]
        while 'lost the coordinator' not in cut_off.read_text() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert 'no heartbeat for 5 s); stopped its nodes, exiting' in cut_off.read_text(), cut_off.read_text()[-2000:]
    finally:
        netns._ip('-n', hosts.names[2], 'link', 'set', 'eth0', 'up')
