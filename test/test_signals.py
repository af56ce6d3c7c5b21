"""Every signal ends cleanly (interrupt.py), and a bag whose writer was killed is recoverable.

* SIGINT, SIGTERM and SIGHUP at a random moment of a replay: exit code 128 + signal, one
  line saying what was interrupted and what was kept, no process left, and the output bag
  closed: read back by two independent readers (mcap's own and rosbags), which agree with
  each other, with metadata.yaml and with the count the line states. Nothing recorded before
  the signal is missing: the bag holds at least the /odom messages metadata.yaml counted
  (the recorder's flush, every second) just before the signal was sent, and its /odom
  stamps are the bag's first frames, in order, none twice, none skipped.
* SIGKILL at a random moment: the bag is unfinished (our readers say so and name
  `ego-motion reindex`); `ego-motion reindex` rebuilds it with the same guarantees and
  keeps the original.
* play and the coordinator node end the same way; the reader tells an unfinished bag from a
  corrupt one; reindex on files built to be unfinished (no ROS graph needed).

The moment of the signal is random (seeded; the seed is in every assertion message, set
EGO_MOTION_SIGNAL_SEED to replay one); no assertion is about time.
"""
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from std_msgs.msg import String

import process_table
from conftest import REPO, read_bag, run_cli, start_cli
from multicam_ego_motion import interrupt
from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader, scan_mcap
from multicam_ego_motion.bag.rosbag2_writer import Rosbag2Writer
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.ros_plumbing.pose_messages import stamp_to_ns
from replay_run import recorded_counts, replay_env, start_replay, wait_for_odom

DEFAULT_BAG = REPO / 'bags' / 'default'   # 20 s: long enough that no signal comes after its end
SEED = int(os.environ.get('EGO_MOTION_SIGNAL_SEED', random.SystemRandom().randrange(10 ** 6)))


def one_line(stderr, prefix='ego-motion: '):
    """The single summary line (the replay's ROS INFO log lines come before it)."""
    lines = [l for l in stderr.splitlines() if l.startswith(prefix)]
    assert len(lines) == 1 and 'Traceback' not in stderr, stderr[-3000:]
    return lines[0]


# ---- the shared handler ----------------------------------------------------------------

@pytest.mark.parametrize('sig', interrupt.SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_a_signal_raises_once_and_waits_for_a_deferred_block(sig):
    with interrupt.handling():
        with pytest.raises(interrupt.Interrupted) as caught:
            os.kill(os.getpid(), sig)
            time.sleep(5)              # the handler raises at the next bytecode
        assert caught.value.exit_code == 128 + sig and interrupt.received() == sig
        os.kill(os.getpid(), sig)      # a second signal while closing: ignored
        time.sleep(0.01)
    with interrupt.handling():
        closed = []
        with pytest.raises(interrupt.Interrupted):
            with interrupt.deferred():
                os.kill(os.getpid(), sig)
                time.sleep(0.01)
                assert interrupt.requested()
                closed.append(True)    # the block ran to its end
        assert closed == [True]
    assert signal.getsignal(sig) is not interrupt._handler   # restored


def test_an_ignored_signal_stays_ignored():
    old = signal.signal(signal.SIGHUP, signal.SIG_IGN)   # nohup
    try:
        with interrupt.handling():
            assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, old)


# ---- unfinished vs corrupt, and reindex (no ROS graph) ----------------------------------

N_MESSAGES, FLUSHED = 300, 200


@pytest.fixture
def killed_bag(tmp_path):
    """A bag as a SIGKILL leaves it: the first FLUSHED messages flushed, the writer never
    closed (the file copied before close); and the complete bag it would have become."""
    w = Rosbag2Writer(tmp_path / 'complete', chunk_size=4000)
    for i in range(N_MESSAGES):
        w.write('/chatter', String(data=f'hello {i} ' * 5), 1_000_000 + i)
        if i + 1 == FLUSHED:
            w.flush()
            shutil.copytree(tmp_path / 'complete', tmp_path / 'killed')
    w.close()
    return tmp_path / 'killed', tmp_path / 'complete'


def test_unfinished_and_corrupt_bags_get_different_one_line_errors(killed_bag, tmp_path):
    killed, complete = killed_bag
    assert scan_mcap(next(killed.glob('*.mcap'))).state == 'unfinished'
    with pytest.raises(UserError) as e:
        Rosbag2Reader(killed)
    assert 'is unfinished' in str(e.value) and f'`ego-motion reindex {killed}`' in str(e.value)
    assert '\n' not in str(e.value)
    # cut in the middle of a finished file: unfinished too (it is what a kill mid-write leaves)
    cut = tmp_path / 'cut.mcap'
    data = next(complete.glob('*.mcap')).read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    with pytest.raises(UserError, match='is unfinished'):
        Rosbag2Reader(cut)
    # corrupt: garbage after the magic, a damaged byte in a finished file's summary
    garbage = tmp_path / 'garbage.mcap'
    garbage.write_bytes(b'\x89MCAP0\r\n' + b'garbage' * 100)
    damaged = tmp_path / 'damaged.mcap'
    raw = bytearray(data)
    raw[-37] ^= 0xFF                     # the footer's opcode
    damaged.write_bytes(bytes(raw))
    for bad in (garbage, damaged):
        with pytest.raises(UserError) as e:
            Rosbag2Reader(bad)
        assert 'is corrupt' in str(e.value) and 'is unfinished' not in str(e.value), str(e.value)
    # the command line: evaluate and play name the bag and the remedy, one line, exit 2
    for args in (['evaluate', '--reference', f'{killed}:/chatter', '--estimate', f'{killed}:/chatter',
                  '--out', tmp_path / 'ev'],
                 ['play', killed]):
        proc = run_cli(*args, timeout=60)
        assert proc.returncode == 2, proc.stderr
        assert one_line(proc.stderr).startswith('ego-motion: error: bag ')
        assert 'unfinished' in proc.stderr and 'ego-motion reindex' in proc.stderr


def test_reindex_recovers_the_complete_chunks_and_keeps_the_original(killed_bag):
    killed, _ = killed_bag
    original = next(killed.glob('*.mcap'))
    before = original.read_bytes()
    proc = run_cli('reindex', killed, timeout=60)
    assert proc.returncode == 0, proc.stderr
    n = int(re.search(r'recovered (\d+) messages', proc.stdout).group(1))
    assert n == FLUSHED, proc.stdout             # everything flushed before the "kill"
    kept = original.with_name(original.name + '.unfinished')
    assert kept.read_bytes() == before and f'kept as {kept}' in proc.stdout
    # two independent readers and metadata.yaml agree; the messages are the first n written
    topics, messages = read_bag(killed)
    with open(original, 'rb') as fh:
        by_mcap = [(m.log_time, m.data) for _, _, m in make_reader(fh).iter_messages()]
    assert topics == {'/chatter': ('std_msgs/msg/String', n)} and len(by_mcap) == n
    assert [m.data for _, _, m in messages] == [f'hello {i} ' * 5 for i in range(n)]
    assert [t for t, _ in by_mcap] == [1_000_000 + i for i in range(n)]
    meta = yaml.safe_load((killed / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['message_count'] == n and meta['files'][0]['path'] == original.name
    assert Rosbag2Reader(killed).counts == {'/chatter': n}
    # again: nothing to do, the bag is complete
    again = run_cli('reindex', killed, timeout=60)
    assert again.returncode == 0 and 'is complete' in again.stdout, again


# ---- signals to a replay ----------------------------------------------------------------

@pytest.fixture(scope='module')
def default_frames():
    """Log times (= header stamps) of the default bag's frames."""
    return sorted({m.log_time_ns for m in Rosbag2Reader(DEFAULT_BAG).messages(['/front/image_raw'])})


def odom_read_back(bag_dir, why):
    """(/odom header stamps via rosbags, /odom count via mcap, metadata.yaml's /odom count)."""
    topics, messages = read_bag(bag_dir)
    stamps = [stamp_to_ns(m.header.stamp) for t, _, m in messages if t == '/odom']
    n_mcap = 0
    for f in Path(bag_dir).glob('*.mcap'):
        with open(f, 'rb') as fh:
            n_mcap += sum(1 for _ in make_reader(fh).iter_messages(topics=['/odom']))
    meta = recorded_counts(Path(bag_dir).parent).get('/odom', 0)
    assert topics.get('/odom', (None, 0))[1] == len(stamps), why
    return stamps, n_mcap, meta


CASES = [('SIGINT', 'group'),     # Ctrl-C in a terminal: the whole foreground process group
         ('SIGTERM', 'process'),  # timeout, a CI runner's cancel, `kill PID`
         ('SIGTERM', 'group'),    # systemd (KillMode=control-group): the workers get it too
         ('SIGHUP', 'group'),     # the terminal or SSH session closed
         ('SIGKILL', 'process')]  # nothing can close the bag: ego-motion reindex


@pytest.mark.parametrize('name,target', CASES, ids=[f'{n}-{t}' for n, t in CASES])
def test_signal_at_a_random_moment_of_a_replay(name, target, tmp_path, default_frames):
    sig = signal.Signals[name]
    rng = random.Random(f'{SEED}-{name}-{target}')
    out = tmp_path / 'out'
    proc = start_replay(DEFAULT_BAG, out)
    try:
        assert proc.stdout.readline().startswith('replay: '), proc.communicate()
        # the moment: during start-up (graph not up, maybe no bag yet), or while playing
        during_startup = sig != signal.SIGKILL and rng.random() < 0.3
        delay = rng.uniform(0.0, 3.0)
        if during_startup:
            moment = f'start-up + {delay:.2f} s'
        else:
            wait_for_odom(proc, out, 1)
            moment = f'first /odom flushed + {delay:.2f} s'
        time.sleep(delay)
        flushed = recorded_counts(out).get('/odom', 0)   # on disk before the signal
        assert proc.poll() is None, f'the replay ended before the signal ({moment})'
        (os.killpg if target == 'group' else os.kill)(proc.pid, sig)
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    why = f'{name} to the {target} at {moment}, flushed {flushed} /odom (seed {SEED}): {stderr[-2000:]}'
    left = process_table.wait_gone(process_table.marked(str(out)), 10.0)
    assert left == [], (why, [process_table.cmdline(p) for p in left])
    bag_dir = out / 'output'

    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL, why
        with pytest.raises(UserError, match=r'is unfinished.*`ego-motion reindex '):
            Rosbag2Reader(bag_dir)
        fixed = run_cli('reindex', bag_dir, timeout=120)
        assert fixed.returncode == 0, (why, fixed.stderr)
        assert re.search(r'recovered \d+ messages', fixed.stdout), fixed.stdout
        assert list(bag_dir.glob('*.mcap.unfinished')), why
        stated = None
    else:
        assert proc.returncode == 128 + sig, why
        line = one_line(stderr)
        assert line.startswith(f'ego-motion: replay interrupted by {name}'), why
        if not bag_dir.exists():             # before the recorder was created
            assert during_startup and 'kept' not in line, why
            return
        stated = int(re.search(r'kept \S+: (\d+) /odom', line).group(1))

    stamps, n_mcap, n_meta = odom_read_back(bag_dir, why)
    assert len(stamps) == n_mcap == n_meta, why                 # readers and metadata agree
    if stated is not None:
        assert len(stamps) == stated, why                        # what the line says
    assert len(stamps) >= flushed, why                           # nothing recorded is lost
    assert stamps == default_frames[:len(stamps)], why           # first frames, in order
    assert Rosbag2Reader(bag_dir).counts.get('/odom', 0) == len(stamps), why


# ---- play and the coordinator node ------------------------------------------------------

def test_play_ends_cleanly_on_sigterm(rclpy_context):
    from rosgraph_msgs.msg import Clock

    from conftest import SpinningNode
    listener = SpinningNode('clock_listener')
    clocks = []
    listener.node.create_subscription(Clock, '/clock', clocks.append, 10)
    # Rate mode, slowly (the 20 s bag in 100 s): still playing when the signal comes.
    proc = start_cli('play', DEFAULT_BAG, '--rate', '0.2', '--discovery', '1')
    try:
        deadline = time.monotonic() + 60
        while len(clocks) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(clocks) >= 2 and proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        listener.close()
    assert proc.returncode == 128 + signal.SIGTERM, err
    line = one_line(err)
    assert line.startswith("ego-motion: play interrupted by SIGTERM at "), line
    assert "of the bag's 20.0 s" in line and 'nothing written' in line, line


def test_coordinator_node_stops_its_workers_on_sigterm(tmp_path):
    out = tmp_path / 'coordinator'
    env = replay_env(out)
    env['ROS_DOMAIN_ID'] = os.environ['ROS_DOMAIN_ID']
    proc = subprocess.Popen(
        [sys.executable, '-m', 'multicam_ego_motion.coordinator.coordinator_node',
         '--rig', str(DEFAULT_BAG / 'rig.yaml'), '--workers', '2', '--log-dir', str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            logs = list(out.glob('worker_*.log'))
            if len(logs) >= 2 and all('hosts' in l.read_text() for l in logs if 'spare' not in l.name):
                break
            time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()
        os.killpg(proc.pid, signal.SIGTERM)     # systemd: the workers get it too
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    line = one_line(err, 'coordinator: interrupted')
    assert 'by SIGTERM' in line and 'worker processes' in line, line
    assert process_table.wait_gone(process_table.marked(str(out)), 10.0) == []
