"""A worker killed with SIGKILL mid-run is restarted and its nodes restored (from the
coordinator's last state snapshots; how fast is `make bench`'s crash row); the lockstep run completes with every frame
and its accuracy stays within 10 % of an uninterrupted run. No worker process outlives a
run, killed or not."""
import os
import re
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from conftest import run_cli

REPO = Path(__file__).resolve().parents[1]
DEFAULT_BAG = REPO / 'bags' / 'default'
DURATION_S = 5                      # 40 frames at 8 Hz
FRAMES = DURATION_S * 8
WORKER = 'multicam_ego_motion.coordinator.worker'
# Every process this test module starts carries this tag in its environment: the orphan
# check finds our workers and not those of another session on the machine.
TAG = f'EGO_MOTION_TEST_TAG={uuid.uuid4().hex}'
os.environ['EGO_MOTION_TEST_TAG'] = TAG.split('=', 1)[1]


def odometry(out):
    """(stamps, N x 7 [t, q]) of the recorded /odom."""
    with AnyReader([Path(out) / 'output']) as reader:
        conns = [c for c in reader.connections if c.topic == '/odom']
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs]
    p = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z,
                   m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
                   m.pose.pose.orientation.w] for m in msgs])
    return stamps, p


def worker_processes(tag=TAG):
    """pid -> command line of every live worker process started under this test's tag."""
    found = {}
    for d in os.listdir('/proc'):
        if not d.isdigit():
            continue
        try:
            cmd = Path(f'/proc/{d}/cmdline').read_bytes().replace(b'\0', b' ').decode()
            if WORKER in cmd and tag.encode() in Path(f'/proc/{d}/environ').read_bytes():
                found[int(d)] = cmd
        except OSError:
            continue
    return found


def no_worker_left(tag=TAG, wait_s=3.0):
    deadline = time.monotonic() + wait_s
    while worker_processes(tag) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not worker_processes(tag)


def ate(stdout):
    return float(re.search(r'ATE RMSE after SE\(3\) fit \[m\]\s+([0-9.]+)', stdout).group(1))


@pytest.fixture(scope='module')
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp('crash')
    r = run_cli('replay', DEFAULT_BAG, '--out', base / 'plain', '--workers', 2,
                '--duration', DURATION_S, '--no-rebalance', timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    # The replay kills its last worker (SIGKILL) once a third of the frames were acknowledged
    # (the quarters hold real state then): at a frame, not at a moment, so the kill lands
    # mid-run however fast the host (an outside /odom counter matched the graph late on a
    # quiet machine, and the run was over before the kill).
    r2 = run_cli('replay', DEFAULT_BAG, '--out', base / 'killed', '--workers', 2,
                 '--duration', DURATION_S, '--no-rebalance', '--kill-worker-at', FRAMES // 3,
                 timeout=600)
    output = r2.stdout + r2.stderr
    m = re.search(r'replay: killed worker 1 \(pid (\d+)\) after frame (\d+)', output)
    killed = int(m.group(1)) if m else None
    frame = int(m.group(2)) if m else None
    return base, r.stdout, r2.returncode, output, killed, frame


def test_killed_worker_is_restored_and_the_run_completes(runs):
    base, _, code, output, killed, frame = runs
    assert killed is not None, 'no worker was killed:\n' + output[-3000:]
    assert frame < FRAMES, frame          # mid-run
    assert code == 0, output
    # restored (how fast is a figure for the bench, not a test bound: 3.3 s on a loaded CI host)
    assert re.search(r'worker 1 restored in ([0-9.]+) s', output), output
    stamps, _ = odometry(base / 'killed')
    assert len(stamps) == FRAMES and stamps == sorted(set(stamps))


def test_accuracy_within_ten_percent_of_uninterrupted(runs):
    _, plain_out, _, output, _, _ = runs
    a_plain, a_killed = ate(plain_out), ate(output)
    assert a_killed <= 1.10 * a_plain + 1e-3, (a_plain, a_killed)


def test_no_orphan_workers(runs):
    assert no_worker_left()
