"""The coordinator: launches the graph on M worker processes and keeps it running.

* Placement: allocation.allocate() (paper section 3) on the measured quarter costs; before
  anything is measured every quarter costs the same.
* Control channel (control.py): one authenticated connection per worker (a Unix socket for
  the workers it starts; TCP for remote workers when `listen` is given); attach / detach
  nodes; state snapshots of every stateful node go to a folder on this host
  (snapshot_store.py: written there directly by the local workers).
* Remote workers (`listen`, `remote_workers`): R of the M worker slots are filled by
  `worker --coordinator HOST:PORT` processes on other hosts, which join over TCP with the
  shared key; the coordinator sends them the rig, the params and the namespace's remappings,
  then places nodes on them like on its own workers (their costs come over /diagnostics).
  A remote worker whose connection drops, or whose heartbeats stop (its host died), is
  restored like a crashed local worker: its nodes go to the hot spare (or a new local
  worker) with their last snapshots.
* Rebalancing: costs from the quarters' /diagnostics (cost_monitor.py), allocation.
  should_rebalance() with threshold and hysteresis; a move = detach on the source worker
  (which waits until the node is between frames and returns its state), attach on the
  destination with that state. Only quarter nodes and camera arbiters move; the general
  arbiter stays where it started (moving it would re-route /odom under the player's feet
  for no gain: it costs about 1 % of a frame).
* Crash recovery: a worker whose channel closes is restarted under the same index and its
  nodes are attached again with their last snapshots; `on_restored` callbacks then tell the
  frame source (the lockstep player) to publish the current frame again.
* Diagnostics: with a ROS node given (`attach_ros`), it reads /diagnostics and publishes its
  own entry 'ego_motion/coordinator' (allocation, imbalance, migrations, restarts).

Signals: at the first SIGINT, SIGTERM or SIGHUP (interrupt.py) the coordinator stops
restarting workers (`quiesce`): the same signal may have reached them (a terminal's process
group, systemd's cgroup), and the command's cleanup calls `stop()` next. Workers ignore
SIGINT and SIGHUP (they are stopped by their coordinator, in order) and end on SIGTERM.

Worker processes are spawned only from the thread that created the coordinator and from
its watchdog thread, both alive as long as the coordinator: PR_SET_PDEATHSIG fires when the
spawning *thread* ends.
"""
import itertools
from collections import deque
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional

from multicam_ego_motion import interrupt
from multicam_ego_motion.coordinator import control
from multicam_ego_motion.coordinator.allocation import (Allocation, allocate, evaluate_loads, frame_gain,
                                                        frames_needed, should_rebalance)
from multicam_ego_motion.coordinator.cost_monitor import CostMonitor
from multicam_ego_motion.coordinator.graph_spec import (graph_nodes, normalize_namespace, remappings, ros_args,
                                                        topic_parameter_values, under)
from multicam_ego_motion.coordinator.snapshot_store import SnapshotStore
from multicam_ego_motion.errors import UserError

START_TIMEOUT_S = 60.0
REPLY_TIMEOUT_S = 30.0
# Lockstep moves: how long a node may take to finish its frame; a node still mid-frame stays
# and its move is tried again at the next between-frames moment (at most POSTPONED_TRIES).
# With free-running cameras a node's frame can wait for the image or wheel reading the player
# holds back until the move is done: the next moment, after another frame, may find it idle.
LOCKSTEP_IDLE_WAIT_S = 0.1
POSTPONED_TRIES = 50
REMOTE_JOIN_TIMEOUT_S = 120.0
WORKER_MODULE = 'multicam_ego_motion.coordinator.worker'


class WorkerDied(UserError):
    """A request to a worker that died (or whose connection broke) before it replied: the
    crash watcher restores it, so a caller in the middle of a move lets it."""


@dataclass
class WorkerHandle:
    index: int
    proc: subprocess.Popen = None
    log: object = None
    conn: object = None
    pid: int = None
    ready: threading.Event = field(default_factory=threading.Event)
    alive: bool = False
    send_lock: threading.Lock = field(default_factory=threading.Lock)
    remote: bool = False          # a slot filled by a worker that joins over TCP
    host: str = ''                # where a remote worker runs (its connection's peer)
    joining: bool = False         # a remote worker was given this slot and is starting


@dataclass
class CoordinatorStats:
    migrations: int = 0
    restarts: int = 0
    rebalances: int = 0
    restore_s: List[float] = field(default_factory=list)   # worker death -> nodes attached
    log: List[str] = field(default_factory=list)


class Coordinator:
    def __init__(self, rig, rig_file, params_file=None, workers: int = None, overrides=None,
                 log_dir=None, env=None, rebalance: bool = True, threshold: float = 0.10,
                 hysteresis_frames: int = 10, quorum: float = 0.8, migrate_every: int = 0,
                 spare: bool = True,
                 logger=print, namespace: str = '', listen: str = None, remote_workers: int = 0,
                 key: bytes = None, join_timeout_s: float = REMOTE_JOIN_TIMEOUT_S):
        self.rig = rig
        self.rig_file = str(rig_file)
        # The graph's namespace (graph_spec.py): its nodes, and its topics through remappings
        # that every worker process gets as global ROS arguments.
        self.namespace = normalize_namespace(namespace)
        self.specs = {n.key: n for n in graph_nodes(rig, str(rig_file), overrides=overrides,
                                                    namespace=self.namespace)}
        self.remappings = (remappings(rig, self.namespace, topic_parameter_values(params_file, overrides))
                           if self.namespace else [])
        self.n_workers = max(1, int(workers or os.cpu_count() or 1))
        self.params_file = str(params_file) if params_file else None
        # the quarters' `stereo` parameter: whether a stereo partner's quarters take this
        # camera's image too (image_readers)
        self.stereo_on = bool((overrides or {}).get('quarter', {}).get('stereo', True))
        if params_file and 'stereo' not in (overrides or {}).get('quarter', {}):
            from multicam_ego_motion.params_file import quarter_params_from
            self.stereo_on = bool(quarter_params_from(params_file).get('stereo', True))
        self.log_dir = Path(log_dir or tempfile.mkdtemp(prefix='ego_motion_workers_'))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        # One BLAS thread per worker: the workers are the parallelism (see cli.py).
        self.env = dict(env if env is not None else os.environ)
        for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
            self.env.setdefault(var, '1')
        self.rebalance_enabled = rebalance and self.n_workers > 1
        self.threshold = threshold
        self.hysteresis_frames = hysteresis_frames
        self.quorum = quorum
        self.migrate_every = int(migrate_every) if self.n_workers > 1 else 0
        self.logger = logger
        self.costs = CostMonitor(rig.names)
        self.stats = CoordinatorStats()
        self.snapshots = SnapshotStore()           # node key -> its newest state (snapshot_store.py)
        self.placement: Dict[str, int] = {}        # node key -> worker index
        self.allocation: Optional[Allocation] = None
        self.on_restored: List[Callable[[int], None]] = []
        self.link_waiter: Optional[Callable[[dict, str], None]] = None   # see migrate()
        self.workers = [WorkerHandle(i) for i in range(self.n_workers)]
        # Remote slots are the last R: a join fills the first free one.
        self.listen_address = listen
        self.remote_workers = int(remote_workers or 0)
        if self.remote_workers and not listen:
            raise UserError('remote workers need an address to listen on (--listen HOST:PORT)')
        if not 0 <= self.remote_workers <= self.n_workers:
            raise UserError(f'{self.remote_workers} remote workers: at most the {self.n_workers} workers in all')
        if listen and not key:
            raise UserError('listening for remote workers needs the control key '
                            f'(--key-file FILE or ${control.KEY_ENV})')
        for h in self.workers[self.n_workers - self.remote_workers:]:
            h.remote = True
        self.key = key
        self.join_timeout_s = join_timeout_s
        self._tcp = None
        # A hot spare (started, imports done, no nodes) takes over a dead worker: a cold
        # start of Python + rclpy + the node modules takes seconds on a loaded machine.
        self.spare = spare
        self._spare: Optional[WorkerHandle] = None
        self._replies: Dict[int, dict] = {}
        self._reply_cond = threading.Condition()
        self._req = itertools.count(1)
        self._ops = threading.RLock()              # one placement change at a time
        self._dead = []
        self._dead_cond = threading.Condition()
        self._stopping = False
        self._quiet = False          # quiesce(): a signal came, stop() follows
        self._last_rebalance_frame = -10 ** 9
        self._last_forced_frame = 0
        self._postponed: List[tuple] = []          # lockstep moves whose node was mid-frame
        self._postponed_tries = 0
        # Per closed frame, against the placement of the time: was a move worth it? Kept as
        # frames close (the executor thread) so that the lockstep between-frames hook only
        # looks at flags (the full decision costs ~3 ms of Python per frame).
        self._placement_version = 0
        self._gains = deque(maxlen=hysteresis_frames)
        self._forced = 0
        self._listener = None
        self._ros_node = None
        self._diag_pub = None
        self._costs_lock = threading.Lock()

    # ---- start / stop ---------------------------------------------------------------------
    def start(self):
        interrupt.on_signal(self.quiesce)
        self._listener, key_env = control.listen(tempfile.gettempdir(), self.key)
        self.env.update(key_env)
        threading.Thread(target=self._accept_loop, args=(self._listener,), daemon=True,
                         name='coordinator-accept').start()
        if self.listen_address:
            self._tcp = control.listen_tcp(self.listen_address, self.key)
            self.say(f'listening for remote workers on {self.listen_address}')
            threading.Thread(target=self._accept_loop, args=(self._tcp,), daemon=True,
                             name='coordinator-accept-tcp').start()
            threading.Thread(target=self._heartbeats, daemon=True, name='coordinator-heartbeat').start()
        self.allocation = allocate(self.costs.quarter_costs(), self.n_workers)
        for w, keys in self.allocation.workers.items():
            for k in keys:
                self.placement[k] = w
        self.say(f'allocation ({self.allocation.case}): ' + '; '.join(
            f'worker {w}: {", ".join(keys)}' for w, keys in self.allocation.workers.items()))
        for h in self.workers:
            if not h.remote:
                self._spawn(h)
        if self.spare:
            # Its imports (about 1 s of CPU) run alongside the workers' and end before the
            # first frame: started last, they took a core from the first seconds of a run
            # (about 4 ms a frame of a 20 s lockstep replay on two cores).
            self._spare = WorkerHandle(-1)
            self._spawn(self._spare)
        if self.remote_workers:
            self.say(f'waiting for {self.remote_workers} remote worker(s): `worker --coordinator '
                     f'{self.listen_address}` with the same key on the other host(s)')
        for h in self.workers:
            self._wait_ready(h)
            self._attach_all(h)
        self._await_links(self.workers)
        if self._spare is not None:
            self._wait_ready(self._spare)
        self._watchdog = threading.Thread(target=self._watch, daemon=True, name='coordinator-watchdog')
        self._watchdog.start()
        return self

    def quiesce(self):
        """No more worker restarts or spares from now on (a signal came: `stop()` follows).
        Only sets a flag: it runs inside the signal handler."""
        self._quiet = True

    def stop(self, timeout=10.0):
        interrupt.remove_hook(self.quiesce)
        self._stopping = True
        with self._dead_cond:
            self._dead_cond.notify_all()
        handles = self.workers + ([self._spare] if self._spare is not None else [])
        for h in handles:
            self._send(h, (control.STOP,))
        deadline = time.monotonic() + timeout
        for h in handles:
            if h.proc is None:
                if h.conn is not None:
                    # A remote worker: it reads STOP, stops its nodes and closes its end; our
                    # close after that cannot reset the connection before STOP was read.
                    end = min(deadline, time.monotonic() + 2.0)
                    while h.alive and time.monotonic() < end:
                        time.sleep(0.02)
                    h.conn.close()
                continue
            try:
                h.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                h.proc.kill()
                h.proc.wait()
            if h.log:
                h.log.close()
        for listener in (self._listener, self._tcp):
            if listener is not None:
                listener.close()
        self.snapshots.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def say(self, text):
        self.stats.log.append(text)
        if self.logger:
            self.logger(f'coordinator: {text}')

    def check_alive(self):
        """Raise if a worker failed in a way a restart cannot fix (e.g. a bad parameter)."""
        if getattr(self, '_fatal', None):
            raise UserError(self._fatal)

    def worker_pids(self) -> List[int]:
        handles = self.workers + ([self._spare] if self._spare is not None else [])
        return [h.proc.pid for h in handles if h.proc is not None and h.proc.poll() is None]

    def remote_pids(self) -> List[int]:
        """Process ids the remote workers gave (on their own hosts)."""
        return [h.pid for h in self.workers if h.remote and h.alive and h.pid]

    def nodes_of(self, worker: int) -> List[str]:
        return [k for k, w in self.placement.items() if w == worker]

    def image_readers(self, camera: str, placement=None) -> int:
        """How many subscriptions a camera's image topic has from the graph: one per worker
        hosting any of its quarters or of its stereo partners' quarters (they take its image
        too; a worker takes each input once for all, worker.py)."""
        placement = self.placement if placement is None else placement
        takers = {camera}
        if self.stereo_on:
            takers |= {c for c in self.rig.names if self.rig.stereo_partners(c)[:1] == [camera]}
        return len({w for k, w in placement.items() if self.specs[k].kind == 'quarter'
                    and self.specs[k].parameters.get('camera') in takers})

    # ---- processes and channel -----------------------------------------------------------
    def _spawn(self, h: WorkerHandle):
        h.ready.clear()
        h.alive = False
        h.remote, h.host = False, ''      # a remote slot restored here is a local worker now
        if h.log:
            h.log.close()
        h.log = open(self.log_dir / (f'worker_{h.index}.log' if h.index >= 0 else 'worker_spare.log'), 'a')
        cmd = [sys.executable, '-m', WORKER_MODULE, '--index', str(h.index),
               '--control', self._listener.address, '--state-dir', str(self.snapshots.folder)]
        if self.params_file:
            cmd += ['--params-file', self.params_file]
        if self.namespace:
            cmd += ['--namespace', self.namespace]
        cmd += ros_args(self.remappings)
        h.proc = subprocess.Popen(cmd, stdout=h.log, stderr=subprocess.STDOUT, env=self.env)

    def _wait_ready(self, h: WorkerHandle):
        if h.remote:
            deadline = time.monotonic() + self.join_timeout_s
            while not h.ready.wait(0.1):
                if time.monotonic() > deadline:
                    raise UserError(f'worker {h.index}: no remote worker joined within '
                                    f'{self.join_timeout_s:.0f} s (start `worker --coordinator '
                                    f'{self.listen_address}` with the same key on the other host)')
            return
        deadline = time.monotonic() + START_TIMEOUT_S
        while not h.ready.wait(0.1):
            if h.proc.poll() is not None or time.monotonic() > deadline:
                raise UserError(f'worker {h.index} did not start (exit code {h.proc.poll()}): '
                                f'{self._log_tail(h)}')

    def _log_tail(self, h):
        lines = (self.log_dir / (f'worker_{h.index}.log' if h.index >= 0 else 'worker_spare.log')).read_text().strip().splitlines()
        return lines[-1] if lines else 'no output'

    def _accept_loop(self, listener):
        while not self._stopping:
            try:
                conn = listener.accept()
            except control.AuthError as e:
                self.say(str(e))
                continue
            except OSError:
                if self._stopping:
                    return
                continue
            # The handshake is done; a joining worker's start-up must not hold other joins.
            threading.Thread(target=self._admit, args=(conn,), daemon=True,
                             name='coordinator-admit').start()

    def _admit(self, conn):
        try:
            # a local worker says hello once rclpy and its node are up (seconds on a busy
            # host); a remote one at once (its second hello comes when it is up: _join)
            hello = conn.recv(timeout=control.HANDSHAKE_TIMEOUT_S if conn.is_tcp else START_TIMEOUT_S)
            if hello[0] != control.HELLO:
                raise EOFError(f'expected hello, got {hello[0]!r}')
            if hello[1] == control.REMOTE:
                self._join(conn, hello)
                return
        except (EOFError, OSError, control.AuthError) as e:
            self.say(f'control connection from {conn.peer} dropped before it said hello: {e}')
            conn.close()
            return
        if not -1 <= hello[1] < len(self.workers) or conn.is_tcp:
            conn.close()
            return
        h = self.workers[hello[1]] if hello[1] >= 0 else self._spare
        if h is None:
            conn.close()
            return
        self._bind(h, conn, hello[2])

    def _bind(self, h, conn, pid):
        h.conn, h.pid, h.alive = conn, pid, True
        threading.Thread(target=self._read_loop, args=(h, conn), daemon=True,
                         name=f'coordinator-worker-{h.index}').start()
        h.ready.set()

    def _join(self, conn, hello):
        """A remote worker: the first free remote slot, the graph's configuration, then its
        second hello once it is up (rclpy, node modules)."""
        host = f'{hello[3]} ({conn.peer})' if len(hello) > 3 else conn.peer
        with self._ops:
            h = next((w for w in self.workers if w.remote and not w.alive and not w.joining
                      and not w.ready.is_set()), None)
            if h is None or self._stopping or self._quiet:
                self.say(f'remote worker {host} turned away: every remote slot is taken')
                try:
                    conn.send((control.STOP,))
                finally:
                    conn.close()
                return
            h.joining = True
        try:
            conn.send((control.WELCOME, h.index, self._remote_config()))
            ready = conn.recv(timeout=START_TIMEOUT_S)
            if ready[0] != control.HELLO:
                raise EOFError(f'expected hello, got {ready[0]!r}')
        except (EOFError, OSError, control.AuthError) as e:
            self.say(f'remote worker {host} dropped while starting: {e}')
            conn.close()
            h.joining = False
            return
        h.host, h.joining = host, False
        self.say(f'remote worker {host} joined as worker {h.index} (pid {ready[2]} there)')
        self._bind(h, conn, ready[2])

    def _remote_config(self) -> dict:
        """What a worker on another host needs: the files the node specs name (rig,
        params: paths here, contents there), the namespace and its remappings."""
        files = {self.rig_file: Path(self.rig_file).read_text()}
        if self.params_file:
            files[self.params_file] = Path(self.params_file).read_text()
        return {'files': files, 'params_file': self.params_file, 'namespace': self.namespace or '/',
                'ros_args': ros_args(self.remappings)}

    def _heartbeats(self):
        # A remote host that dies sends no FIN: its worker is declared dead when its pings
        # stop (read loop timeout); these pings tell remote workers the same about us.
        while not self._stopping:
            for h in list(self.workers):
                if h.remote and h.alive:
                    self._send(h, (control.PING,))
            time.sleep(control.HEARTBEAT_S)

    def _read_loop(self, h: WorkerHandle, conn):
        timeout = control.HEARTBEAT_TIMEOUT_S if conn.is_tcp else None
        why = 'its connection closed'
        try:
            while True:
                msg = conn.recv(timeout=timeout)
                if msg[0] == control.SNAPSHOT:
                    self.snapshots.put(msg[1], msg[2])      # a remote worker's
                elif msg[0] == control.COSTS:
                    self._on_costs(msg[1])
                elif msg[0] == control.REPLY:
                    with self._reply_cond:
                        self._replies[msg[1]] = msg[2]
                        self._reply_cond.notify_all()
        except socket.timeout:
            why = f'no heartbeat for {timeout:.0f} s'
            conn.close()
        except (EOFError, OSError, control.AuthError) as e:
            if isinstance(e, control.AuthError):
                why = str(e)
        if h.conn is conn:            # not an old connection of a worker already replaced
            if h.remote and not self._stopping:
                self.say(f'remote worker {h.index} on {h.host} lost: {why}')
            h.alive = False
            with self._dead_cond:
                self._dead.append((h.index, time.monotonic()))
                self._dead_cond.notify_all()
            with self._reply_cond:
                self._reply_cond.notify_all()

    def _send(self, h, msg):
        if h.conn is None or not h.alive:
            return False
        try:
            with h.send_lock:
                h.conn.send(msg)
            return True
        except (OSError, ValueError):
            return False

    def _request(self, h, kind, *args, timeout=REPLY_TIMEOUT_S) -> dict:
        return self._collect(h, kind, [self._post(h, kind, *args)], timeout)[0]

    def _post(self, h, kind, *args) -> int:
        req = next(self._req)
        if not self._send(h, (kind, req, *args)):
            raise WorkerDied(f'worker {h.index} is not reachable')
        return req

    def _collect(self, h, kind, reqs, timeout=REPLY_TIMEOUT_S) -> List[dict]:
        return [self._reply(h, kind, req, time.monotonic() + timeout) for req in reqs]

    def _reply(self, h, kind, req, deadline) -> dict:
        with self._reply_cond:
            while req not in self._replies:
                if not h.alive:
                    raise WorkerDied(f'worker {h.index}: no reply to {kind} (died)')
                if time.monotonic() > deadline:
                    raise UserError(f'worker {h.index}: no reply to {kind} (timeout)')
                self._reply_cond.wait(0.1)
            reply = self._replies.pop(req)
        if not reply.get('ok'):
            raise UserError(f'worker {h.index}: {reply.get("error")}')
        return reply

    def _attach(self, h, key, state, wait_links=False):
        return self._request(h, control.ATTACH, self.specs[key].to_dict(), state, wait_links)

    def _attach_all(self, h):
        # All requests first: the worker creates the nodes back to back.
        reqs = [self._post(h, control.ATTACH, self.specs[k].to_dict(), self.snapshots.get(k), False)
                for k in self.nodes_of(h.index)]
        self._collect(h, control.ATTACH, reqs)

    def _await_links(self, handles):
        """Every worker's nodes matched to the rest of the graph (worker.links)."""
        reqs = [(h, self._post(h, control.LINKS)) for h in handles]
        late = [h.index for h, req in reqs
                if not self._collect(h, control.LINKS, [req], timeout=REPLY_TIMEOUT_S)[0].get('linked')]
        if late:
            self.say(f'worker(s) {", ".join(map(str, late))}: not every link of their nodes '
                     'matched in time; the first frames may wait for sync timeouts')

    # ---- crash recovery ---------------------------------------------------------------------
    def _watch(self):
        while True:
            with self._dead_cond:
                while not self._dead and not self._stopping:
                    self._dead_cond.wait(0.5)
                if self._stopping:
                    return
                index, t_dead = self._dead.pop(0)
            if self._quiet:
                # A signal came (maybe to the worker too): stop() follows, nothing restarts.
                # This thread stays until then: the workers it spawned die with it.
                continue
            if index < 0:                       # the spare itself died: start another
                self.say('the spare worker died; starting another')
                self._spare = WorkerHandle(-1)
                self._spawn(self._spare)
                continue
            h = self.workers[index]
            if h.proc is not None:
                h.proc.wait()
                self.say(f'worker {index} died (exit code {h.proc.returncode}); restarting it '
                         f'with {", ".join(self.nodes_of(index))}')
            else:
                h.ready.clear()
                self.say(f'remote worker {index} is gone; restoring '
                         f'{", ".join(self.nodes_of(index))} on a local worker')
            try:
                with self._ops:
                    spare, self._spare = self._spare, None
                    if spare is not None and spare.alive:
                        spare.index = index          # the spare becomes worker `index`
                        self.workers[index] = h = spare
                    else:
                        self._spawn(h)
                        self._wait_ready(h)
                    self._attach_all(h)
            except UserError as e:
                self._fatal = f'worker {index} could not be restored: {e}'
                self.say(self._fatal)
                continue
            dt = time.monotonic() - t_dead
            self.stats.restarts += 1
            self.stats.restore_s.append(dt)
            self.say(f'worker {index} restored in {dt:.2f} s')
            for cb in self.on_restored:
                cb(index)
            if self.spare and self._spare is None and not (self._stopping or self._quiet):
                self._spare = WorkerHandle(-1)
                self._spawn(self._spare)

    # ---- migration and rebalancing ---------------------------------------------------------
    def migrate(self, key: str, dst: int, between_frames: bool = False) -> bool:
        """Move a node to worker `dst` with its state; no frame is skipped when called
        between frames (lockstep). `link_waiter(spec, phase, readers)` (phase 'detached',
        'attached'; readers: the image subscriptions of the node's camera after that phase),
        when set, waits until the frame source sees the change. between_frames (lockstep): a
        node that has not finished its frame within LOCKSTEP_IDLE_WAIT_S stays (False): with
        free-running cameras its frame can wait for one the player holds back until this
        returns. Otherwise (rate mode) it is taken as it is after DETACH_IDLE_TIMEOUT_S."""
        with self._ops:
            src = self.placement[key]
            if src == dst:
                return True
            spec = self.specs[key].to_dict()
            camera = spec['parameters'].get('camera')
            without = {k: w for k, w in self.placement.items() if k != key}
            # image readers once detached from src, then once attached to dst
            readers = (self.image_readers(camera, without),
                       self.image_readers(camera, dict(without, **{key: dst})))
            t = [time.monotonic()]
            try:
                reply = self._request(self.workers[src], control.DETACH, key,
                                      LOCKSTEP_IDLE_WAIT_S if between_frames else None)
            except WorkerDied as e:
                # The node stays placed on src: the crash watcher (waiting for this lock)
                # restores it there with src's other nodes, from its last snapshot.
                self.say(f'move of {key} abandoned: {e}; its worker is being restored')
                return True
            if reply.get('busy'):
                return False
            t.append(time.monotonic())
            if self.link_waiter:
                self.link_waiter(spec, 'detached', readers[0])
            t.append(time.monotonic())
            if reply['state'] is not None:
                self.snapshots.put(key, reply['state'])
            try:
                self._attach(self.workers[dst], key, reply['state'], wait_links=True)
            except WorkerDied as e:
                # Detached from src already: placed on dst, it is restored there with the
                # state it was detached with.
                self.placement[key] = dst
                self._placement_version += 1
                self.say(f'move of {key} to worker {dst} cut short: {e}; it is restored there')
                return True
            t.append(time.monotonic())
            if self.link_waiter:
                self.link_waiter(spec, 'attached', readers[1])
            t.append(time.monotonic())
            self.placement[key] = dst
            self._placement_version += 1
            self.stats.migrations += 1
            self.say(f'moved {key}: worker {src} -> {dst} in {1e3 * (t[-1] - t[0]):.0f} ms (detach, unlink, '
                     'attach, link: ' + ', '.join(f'{1e3 * (b - a):.0f}' for a, b in zip(t, t[1:])) + ' ms)'
                     + ('' if reply.get('idle', True) else '; taken mid-frame: not between frames in time'))
            return True

    def current_allocation(self) -> Allocation:
        workers = {w: [k for k, v in self.placement.items() if v == w] for w in range(self.n_workers)}
        a = Allocation(workers, {k: 1 for k in self.specs if self.specs[k].kind == 'quarter'}, {},
                       self.allocation.case, list(self.rig.names), self.n_workers)
        a.load_ms = evaluate_loads(a, self.costs.quarter_costs(), **self._cost_kw())
        return a

    def _cost_kw(self):
        kw = {'arbiter_costs': dict(self.costs.arbiter_ms)}
        if self.costs.general_arbiter_ms is not None:
            kw['general_arbiter_ms'] = self.costs.general_arbiter_ms
        return kw

    def between_frames(self, frame_index: int):
        """Called by the frame source between two frames (lockstep): the safe moment to move
        nodes. Forced migrations (a debug/test option) move one quarter every K frames."""
        if self._postponed:
            self._postponed_tries += 1
            if self._postponed_tries > POSTPONED_TRIES:
                self.say(f'{len(self._postponed)} move(s) dropped: the node was mid-frame at '
                         f'{POSTPONED_TRIES} between-frames moments in a row: '
                         + ', '.join(f'{k} -> worker {w}' for k, w in self._postponed))
                self._postponed = []
            else:
                left = self._run_moves(self._postponed)
                if len(left) < len(self._postponed):
                    self._postpone(left)     # a move went: the count is of tries in a row
                else:
                    self._postponed = left
            return
        if self.migrate_every and frame_index - self._last_forced_frame >= self.migrate_every:
            self._last_forced_frame = frame_index
            quarters = [k for k in self.specs if self.specs[k].kind == 'quarter']
            key = quarters[self._forced % len(quarters)]
            self._forced += 1
            self._postpone(self._run_moves([(key, (self.placement[key] + 1) % self.n_workers)]))
            return
        self.maybe_rebalance(between_frames=True)

    def _run_moves(self, moves, between_frames: bool = True) -> list:
        """The moves in order; from the first whose node is mid-frame on, those left."""
        for i, (key, w) in enumerate(moves):
            if not self.migrate(key, w, between_frames):
                return moves[i:]
        return []

    def _postpone(self, moves):
        self._postponed, self._postponed_tries = moves, 0

    def maybe_rebalance(self, between_frames: bool = False):
        if not self.rebalance_enabled or not self.costs.measured or self._postponed:
            return
        frame = self.costs.frames
        if frame - self._last_rebalance_frame < 2 * self.hysteresis_frames:
            return                  # let the costs settle after a move
        flags = list(self._gains)
        if len(flags) < self.hysteresis_frames or any(v != self._placement_version for v, _ in flags) \
                or sum(ok for _, ok in flags) < frames_needed(self.hysteresis_frames, self.quorum):
            return
        current = self.current_allocation()
        d = should_rebalance(list(self.costs.history), current, threshold=self.threshold,
                             hysteresis_frames=self.hysteresis_frames, quorum=self.quorum, **self._cost_kw())
        if not d.rebalance:
            return
        moves = [(k, w) for w, keys in d.proposal.workers.items() for k in keys
                 if k in self.placement and k != 'general_arbiter' and self.placement[k] != w]
        if not moves:
            return
        self._last_rebalance_frame = frame
        self.stats.rebalances += 1
        loads = lambda a: '/'.join(f'{a.load_ms.get(w, 0.0):.1f}' for w in range(self.n_workers))
        self.say(f'rebalance at frame {frame}: {d.reason}; worker loads {loads(current)} -> '
                 f'{loads(d.proposal)} ms, imbalance {current.imbalance:.2f} -> '
                 f'{d.proposal.imbalance:.2f}; {len(moves)} move(s): '
                 + ', '.join(f'{k} -> worker {w}' for k, w in moves))
        self._postpone(self._run_moves(moves, between_frames))
        self.allocation = d.proposal

    # ---- ROS side: the coordinator's own diagnostics -------------------------------------
    def attach_ros(self, node, rate_mode_period_s: Optional[float] = None):
        """Publish the coordinator's /diagnostics entry on `node` for every frame whose costs
        came in from the workers (a few frames at a time: worker.COSTS_EVERY). With
        `rate_mode_period_s`, rebalancing runs on a timer (no lockstep hook)."""
        from diagnostic_msgs.msg import DiagnosticArray

        from multicam_ego_motion.ros_plumbing.qos import RELIABLE
        self._ros_node = node
        topic = under(self.namespace, '/diagnostics')
        self._diag_pub = node.create_publisher(DiagnosticArray, topic, RELIABLE)
        if rate_mode_period_s:      # steady clock: a node on sim time may wait for /clock forever
            from rclpy.clock import Clock, ClockType
            node.create_timer(rate_mode_period_s, self._rebalance_in_background,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._bg_busy = threading.Lock()

    def _rebalance_in_background(self):
        # Moves block on worker replies: never in the executor thread that delivers them.
        if self._bg_busy.acquire(blocking=False):
            def run():
                try:
                    self.maybe_rebalance()
                except UserError as e:
                    self.say(f'rebalancing failed: {e}')
                finally:
                    self._bg_busy.release()
            threading.Thread(target=run, daemon=True).start()

    def _on_costs(self, frames):
        # Workers' reader threads: one at a time into the cost monitor (a worker sends a few
        # frames at once; the coordinator's /diagnostics entry still goes out for each).
        with self._costs_lock:
            for stamp, entries in frames:
                closed = False
                for name, values in entries:
                    closed |= self.costs.observe(name, values)
                if closed:
                    self._note_gain()
                    if self._diag_pub is not None:
                        from builtin_interfaces.msg import Time
                        self._publish_diag(Time(sec=stamp[0], nanosec=stamp[1]))

    def _note_gain(self):
        if not self.rebalance_enabled or not self.costs.measured:
            return
        version = self._placement_version
        ok, _, _ = frame_gain(self.costs.quarter_costs(), self.current_allocation(), self.threshold,
                              **self._cost_kw())
        self._gains.append((version, ok))

    def _publish_diag(self, stamp):
        from multicam_ego_motion.ros_plumbing import diagnostics
        a = self.current_allocation()
        values = {'workers': self.n_workers, 'imbalance': float(a.imbalance),
                  'makespan_ms': float(a.makespan_ms), 'migrations': self.stats.migrations,
                  'rebalances': self.stats.rebalances, 'restarts': self.stats.restarts}
        for w, keys in a.workers.items():
            values[f'worker_{w}'] = ','.join(keys)
            values[f'worker_{w}_load_ms'] = float(a.load_ms.get(w, 0.0))
        level = 'ok' if all(h.alive for h in self.workers) else 'warn'
        self._diag_pub.publish(diagnostics.array(stamp, [diagnostics.status(
            'ego_motion/coordinator', level, f'{self.n_workers} workers, imbalance {a.imbalance:.2f}', values)]))
