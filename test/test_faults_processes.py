"""Fault injection, processes: signals to the replay (the coordinator) and to its workers,
and the DDS isolation every run gets.

Expected: no process outlives its replay; Ctrl-C leaves a complete, readable output bag with
everything recorded so far; a worker that dies fails the replay at once with a message
is restarted by the coordinator with its nodes' last state, and the replay completes with
every frame.
"""
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.stream_reader import StreamReader

import fault_injection as fi
import process_table
from multicam_ego_motion.ros_plumbing import ros_domain
from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
from replay_run import ReplayRun, recorded_counts, replay_env, start_replay, wait_for_odom
from test_faults_bags import assert_one_line_error

SECONDS = 4
WORKER = 'multicam_ego_motion.coordinator.worker'


@pytest.fixture(scope='module')
def short_bag(tmp_path_factory):
    return fi.rewrite_bag(tmp_path_factory.mktemp('proc') / 'bag', SECONDS)


def frame_stamps(bag):
    return sorted({it.log_ns for it in fi.load_items(SECONDS) if it.topic.endswith('/image_raw')})


def workers_of(proc):
    return [p for p in process_table.children(proc.pid) if WORKER in process_table.cmdline(p)]


def hosts(out):
    """{pid: hosted node keys} from the workers' start-up log lines."""
    found = {}
    for log in (out / 'logs').glob('worker_*.log'):
        # The newest line of each pid: a worker logs its hosted set after every attach.
        for pid, keys in re.findall(r'\(pid (\d+)\) hosts (.*)$', log.read_text(), re.M):
            found[int(pid)] = keys.split(', ')
    return found


def finished(proc, bag, out, timeout=60):
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        # Not left running: a hung replay and its workers would load (and fail) later tests.
        os.killpg(proc.pid, signal.SIGKILL)
        stdout, stderr = proc.communicate()
        raise AssertionError(f'replay still running after {timeout} s:\n{stdout}\n{stderr[-4000:]}')
    return ReplayRun(bag, out, proc.returncode, stdout, stderr, 0.0)


def assert_output_has_a_prefix_of_the_frames(run, bag):
    """The output bag is complete (readable, metadata.yaml agrees with the MCAP) and its
    /odom is the first N frames of the bag, none skipped."""
    reader = Rosbag2Reader(run.output)                 # raises if not finished properly
    assert recorded_counts(run.out) == {t: n for t, n in reader.counts.items()}
    stamps = run.odometry()[0]
    assert len(stamps) >= 1
    expected = [(t - frame_stamps(bag)[0]) / 1e9 for t in frame_stamps(bag)[:len(stamps)]]
    assert list(stamps) == pytest.approx(expected)
    assert run.odom_problems() == []


# ---- ROS network isolation ----------------------------------------------------------------

def test_ros_domain_is_picked_unless_the_user_set_one():
    picked = ros_domain.isolate({})
    assert 1 <= int(picked['ROS_DOMAIN_ID']) <= 100
    assert picked['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    user = ros_domain.isolate({'ROS_DOMAIN_ID': '42', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'})
    assert user == {'ROS_DOMAIN_ID': '42', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'}


def test_a_reserved_domain_is_not_picked_by_another_run():
    """The domain a run took is held for its lifetime: another process that starts its
    search right there (the same pid-spread start) takes the next one, although no DDS
    participant is on the held domain yet."""
    held = ros_domain.reserve_domain(seed=1234)
    start = 1234 % len(ros_domain.DOMAINS)
    code = ('from multicam_ego_motion.ros_plumbing import ros_domain as r; '
            f'print(r.free_domain({start}), r.reserve_domain({start}))')
    other = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                           timeout=60, cwd=str(Path(__file__).resolve().parents[1]))
    assert other.returncode == 0, other.stderr
    looked, reserved = map(int, other.stdout.split())
    assert held not in (looked, reserved) and 1 <= reserved <= 100
    # (this process's own search does not hand out its held domain twice either)
    assert ros_domain.reserve_domain(seed=1234) != held


def test_replay_honours_a_user_set_domain(clean_run):
    assert clean_run.returncode == 0, clean_run
    assert f'ROS_DOMAIN_ID={clean_run.user_domain})' in clean_run.stdout


# ---- signals to the replay ----------------------------------------------------------------

def test_sigint_leaves_a_complete_output_bag_and_no_process(short_bag, tmp_path):
    out = tmp_path / 'out'
    # No ROS_DOMAIN_ID: the replay picks one, and its workers run on it, on localhost only.
    proc = start_replay(short_bag, out, env=replay_env(out, ROS_AUTOMATIC_DISCOVERY_RANGE=None))
    domain = re.search(r'ROS_DOMAIN_ID=(\d+)', proc.stdout.readline()).group(1)
    wait_for_odom(proc, out, 5)
    for pid in workers_of(proc):
        env = process_table.environment(pid)
        assert env['ROS_DOMAIN_ID'] == domain
        assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    os.killpg(proc.pid, signal.SIGINT)                # what Ctrl-C in a terminal does
    run = finished(proc, short_bag, out, timeout=30)
    assert run.returncode == 130, run
    assert 'Traceback' not in run.stderr, run
    assert_output_has_a_prefix_of_the_frames(run, short_bag)
    assert run.leftover_processes() == []


def test_sigkill_of_the_replay_takes_its_workers_down(short_bag, tmp_path):
    out = tmp_path / 'out'
    proc = start_replay(short_bag, out)
    wait_for_odom(proc, out, 4)
    workers = workers_of(proc)
    assert len(workers) == 3          # two hosting the graph, one warm spare for restarts
    flushed = recorded_counts(out)['/odom']
    proc.kill()
    proc.communicate()
    # PR_SET_PDEATHSIG: the kernel signals each worker when the replay dies.
    assert process_table.wait_gone(workers, 10.0) == []
    assert process_table.marked(str(out)) == []
    # No summary (the recorder could not close the bag), but every chunk it flushed (each
    # second) is intact: what metadata.yaml last counted can be recovered.
    recovered = 0
    try:
        for record in StreamReader(open(fi.mcap_file(out / 'output'), 'rb'), emit_chunks=False).records:
            recovered += getattr(record, 'channel_id', None) is not None and hasattr(record, 'data')
    except Exception:   # the file ends mid-record: that is where the kill hit
        pass
    assert recovered >= sum(recorded_counts(out).values()) >= flushed


# ---- a worker dies ----------------------------------------------------------------------

def kill_worker(bag, out, hosting_general_arbiter):
    proc = start_replay(bag, out)
    wait_for_odom(proc, out, 4)
    placement = hosts(out)
    victim = next(pid for pid, keys in placement.items()
                  if ('general_arbiter' in keys) == hosting_general_arbiter)
    os.kill(victim, signal.SIGKILL)
    t_kill = time.monotonic()
    run = finished(proc, bag, out, timeout=120)
    return run, victim, placement[victim], time.monotonic() - t_kill


@pytest.mark.parametrize('hosting_general_arbiter', [False, True],
                         ids=['camera_worker', 'general_arbiter_host'])
def test_killed_worker_is_restarted_and_the_replay_completes(short_bag, tmp_path, hosting_general_arbiter):
    out = tmp_path / 'out'
    run, _, _, _ = kill_worker(short_bag, out, hosting_general_arbiter)
    assert run.returncode == 0, run
    stamps = run.odometry()[0]
    assert len(stamps) == len(frame_stamps(short_bag))   # no frame lost
    assert run.odom_problems() == []
    # Every frame fused from all four cameras, none after a sync timeout: the nodes that had
    # the re-published frames already sent their estimates again. (Before, a restored general
    # arbiter waited 10 s for the other worker's cameras and fused three frames without them.)
    fused = run.diagnostics('ego_motion/general_arbiter')
    assert len(fused) == len(stamps)
    assert [(d.t, d.message) for d in fused
            if d.values['cameras_missing'] or d.values['sync_timed_out'] != 'False'] == []
    assert run.leftover_processes() == []


def test_a_frame_whose_state_was_saved_keeps_its_diagnostics_through_a_crash(short_bag, tmp_path):
    """The general arbiter's worker dies right after saving its state of the first frame:
    that frame's /odom is out and the restored arbiter goes on from the next one, so the
    frame's /diagnostics must be out too. (A worker sends a frame's statuses in one message
    once all its nodes reported; the quarters and camera arbiters reported after passing
    their estimates on, and where the last estimate completed the frame (the first one here:
    later frames wait for the wheel) the co-hosted chain fused and saved it first: the crash
    lost the frame's statuses.)"""
    out = tmp_path / 'out'
    here = Path(__file__).resolve().parent
    env = replay_env(out, DIE_AFTER_SNAPSHOT='1', DIE_MARKER=str(tmp_path / 'died'))
    env['PYTHONPATH'] = str(here) + os.pathsep + env['PYTHONPATH']
    # One worker: every estimate reaches the general arbiter by direct calls in its process.
    proc = subprocess.Popen([sys.executable, str(here / 'replay_losing_the_arbiter_after_a_snapshot.py'),
                             'replay', str(short_bag), '--out', str(out), '--workers', '1'],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, start_new_session=True)
    run = finished(proc, short_bag, out, timeout=180)
    assert run.returncode == 0, run
    assert (tmp_path / 'died').exists()                  # the injected crash happened
    assert re.search(r'worker \d restored in', run.stdout), run.stdout
    stamps = run.odometry()[0]
    assert len(stamps) == len(frame_stamps(short_bag))   # every frame once
    fused = run.diagnostics('ego_motion/general_arbiter')
    assert sorted(d.t for d in fused) == pytest.approx(list(stamps))
    # Every camera arbiter's status of every frame as well (twice for a frame its restored
    # quarters processed again).
    arbiters = {d.name for d in run.diagnostics('ego_motion/') if d.name.endswith('/arbiter')}
    assert len(arbiters) == 4
    for name in arbiters:
        assert sorted({d.t for d in run.diagnostics(name)}) == pytest.approx(list(stamps)), name


@pytest.mark.parametrize('victim', ['source', 'destination'])
def test_worker_killed_during_a_move_is_restored_with_the_moved_node(short_bag, tmp_path, victim):
    """A crash in the middle of a node move (a rebalance, here a forced move every 3 frames)
    is a crash like any other: the worker is restored, the moved node with it (on the worker
    it was leaving, or the one it was going to), and no frame is lost. (The move failed the
    replay with "no reply to detach (died)" before.)"""
    out = tmp_path / 'out'
    proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name('replay_losing_a_worker_mid_move.py')),
                             'replay', str(short_bag), '--out', str(out), '--workers', '2',
                             '--migrate-every', '3'],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=replay_env(out, KILL_DURING_MOVE=victim), start_new_session=True)
    run = finished(proc, short_bag, out, timeout=180)
    assert run.returncode == 0, run
    assert f'the move\'s {victim}' in run.stdout
    assert re.search(r'worker \d restored in', run.stdout), run.stdout
    # the first forced move (front/q1) did not happen, or happened, and the crash watcher
    # restored front/q1 where the coordinator had it placed
    assert 'move of front/q1' in run.stdout, run.stdout
    stamps = run.odometry()[0]
    assert len(stamps) == len(frame_stamps(short_bag))   # no frame lost
    assert run.odom_problems() == []
    assert run.leftover_processes() == []
