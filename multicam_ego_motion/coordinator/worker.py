"""A worker process (a "processor" of the paper): hosts graph nodes in one executor and obeys
the coordinator over its control channel.

Started by the coordinator: `python -m multicam_ego_motion.coordinator.worker --index I
--control ADDRESS --state-dir DIR [--params-file F] [--namespace NS --ros-args -r FROM:=TO ...]`, the
channel's auth key in $EGO_MOTION_CONTROL_KEY (a namespaced graph: graph_spec.py). It
connects back, says hello, then serves the commands of control.py: attach a node (with the
state it carries on), detach a node (returning its state), stop. After its frames a stateful
node (quarter, general arbiter) leaves its state as a snapshot in the coordinator's folder
(snapshot_store.py; a remote worker sends it over the channel), which is what a restarted
worker is restored from.

On another host: `worker --coordinator HOST:PORT [--key-file F]` (`ros2 run
multicam_ego_motion worker`, `ego-motion worker`) joins a coordinator that listens there
(control.py: the shared key from the file or $EGO_MOTION_CONTROL_KEY, HMAC both ways). The
coordinator gives it a slot, the rig and params files' contents and the namespace's
remappings; images and estimates go over DDS as on one host (the hosts' DDS must discover
each other: same ROS_DOMAIN_ID, a discovery range or initial peers that reach). A worker that
loses its coordinator (connection closed, or no heartbeat for control.HEARTBEAT_TIMEOUT_S)
stops its nodes and exits with status 3: a supervisor (systemd, a launch file's respawn)
starts it again and it joins the next coordinator.

Dies with its parent: PR_SET_PDEATHSIG, and the end of the control channel (a coordinator
that is gone closes it) both end the process, so no worker outlives its coordinator.
Signals: SIGTERM ends it (also PR_SET_PDEATHSIG's); SIGINT and SIGHUP, which a terminal sends
to the whole process group, are ignored: the coordinator, which gets them too, stops its
workers in order (interrupt.py).
"""
import argparse
import ctypes
import math
import os
import pickle
import queue
import signal
import socket
import sys
import tempfile
import threading
import time

import rclpy
import rclpy.signals
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter

from multicam_ego_motion.coordinator import control
from multicam_ego_motion.coordinator.cost_monitor import cost_values
from multicam_ego_motion.coordinator.idle_gc import IdleCollector
from multicam_ego_motion.coordinator.snapshot_store import SnapshotStore
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.ros_plumbing.lean_executor import LeanExecutor
from multicam_ego_motion.ros_plumbing.lean_node import strip_event_handlers

PR_SET_PDEATHSIG = 1
LINK_TIMEOUT_S = 2.0       # longest wait for a moved node's topics to be matched
START_LINK_TIMEOUT_S = 10.0  # longest wait for the whole graph's links at start-up
DETACH_IDLE_TIMEOUT_S = 2.0
QUARTER_SNAPSHOT_EVERY = 5   # frames between state snapshots of a quarter node
NODE_POLL_S = 0.1            # the nodes' own POLL_PERIOD_S
DIAG_STRAGGLER_S = 0.25      # a frame's /diagnostics batch still incomplete after this goes out
# The hosted nodes' costs go to the coordinator a few frames at a time: each message is a
# wake-up of its process on the same cores, and the allocation needs trends, not each frame.
COSTS_EVERY = 8               # frames per COSTS message
COSTS_MAX_AGE_S = 0.5         # ... or sooner, once the oldest waited this long
EXIT_GRACE_S = 5.0            # longest orderly stop once the coordinator is gone or SIGTERM came


def exit_within(grace_s: float, code: int):
    """The process ends at most grace_s from now (with `code`), whatever its orderly stop is
    waiting for: a worker must not outlive its coordinator. A daemon thread, so an orderly
    stop that finishes first is not held up; and, a second later, the kernel's SIGALRM, whose
    default action ends the process even when native code holds the interpreter's lock and
    spins (rclpy's destroy_node racing its own signal handler's shutdown did, for minutes)."""
    timer = threading.Timer(grace_s, os._exit, (code,))
    timer.daemon = True
    timer.start()
    signal.alarm(int(math.ceil(grace_s)) + 1)


# A signal stops the worker: rclpy's own handler shuts the context down from its thread while
# the nodes would be destroyed from this one (a race that can spin forever in destroy_node).
# The nodes then end with the process instead.
stopped_by_signal = threading.Event()


def stop_on_signal(code: int):
    """From a signal handler: the nodes are left to the process's end, which comes within
    EXIT_GRACE_S with `code` (exit_within), and the main thread unwinds now."""
    stopped_by_signal.set()
    exit_within(EXIT_GRACE_S, code)
    raise SystemExit(0)


def _die_with_parent():
    try:
        ctypes.CDLL('libc.so.6', use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def node_class(kind: str):
    if kind == 'quarter':
        from camera_pose_nodes.quarter_node import QuarterNode
        return QuarterNode
    if kind == 'camera_arbiter':
        from arbiter_node.camera_arbiter_node import CameraArbiterNode
        return CameraArbiterNode
    if kind == 'general_arbiter':
        from arbiter_node.general_arbiter_node import GeneralArbiterNode
        return GeneralArbiterNode
    raise UserError(f'unknown node kind {kind!r}')


def create_node(spec: dict, params_file: str = None, **kwargs):
    """The node of a spec, lean: each rclpy node brings seven services of its own (six
    parameter services and get_type_description), and with 21 nodes those were most of the
    entities an executor's wait set holds. Parameters
    still come from the params file and the overrides; they are only not served."""
    cli_args = ['--ros-args', '--params-file', params_file] if params_file else None
    overrides = [Parameter(k, value=v) for k, v in spec['parameters'].items()]
    overrides.append(Parameter('start_type_description_service', value=False))
    return node_class(spec['kind'])(namespace=spec['namespace'], parameter_overrides=overrides,
                                    cli_args=cli_args, start_parameter_services=False, **kwargs)


# Inputs from outside the graph (the player, a driver): not awaited by LINKS at start-up,
# where nothing publishes them yet. Wheel odometry is optional anyway.
EXTERNAL_INPUTS = ('/image_raw', '/image_raw/compressed', '/camera_info', '/wheel/odom')


def linked(node, shared=(), graph_only=False) -> bool:
    """Every input (its own subscriptions and the `shared` ones that feed it) has a publisher
    and every estimate output a subscriber: a moved node must not miss the next frame because
    discovery was still under way. graph_only: only the inputs from other graph nodes."""
    skip = EXTERNAL_INPUTS if graph_only else ('/wheel/odom',)
    subs_ok = all(s.get_publisher_count() > 0 for s in list(node.subscriptions) + list(shared)
                  if not s.topic_name.endswith(skip))
    local = getattr(node, 'estimate_sink', None) is not None     # its arbiter is co-hosted
    pubs_ok = all(p.get_subscription_count() > 0 for p in node.publishers
                  if (p.topic_name.endswith('/pose') and not local)
                  or p.topic_name.endswith('/ego_motion/fused_pose'))
    return subs_ok and pubs_ok


class Worker:
    def __init__(self, index: int, conn, params_file, namespace: str = '/', paths=None, state_dir=None):
        """state_dir: the coordinator's snapshot folder on this host (snapshot_store.py), or
        None (a remote worker): snapshots then go over the control channel."""
        self.index = index
        self.snapshots = SnapshotStore(state_dir) if state_dir else None
        self.paths = paths or {}        # coordinator's file path -> this host's copy (remote)
        self.lost = None                # why the coordinator was lost, if it was
        self.conn = conn
        self.params_file = params_file
        self.send_lock = threading.Lock()
        self.inbox = queue.Queue()
        self.deferred = []              # (predicate, action, deadline): waits off the executor
        self.hosted = {}                # key -> node
        self.kinds = {}                 # key -> node kind
        self.frames_done = {}           # key -> frames finished (snapshot cadence)
        self.node = rclpy.create_node(
            f'ego_motion_worker_{index}' if index >= 0 else f'ego_motion_worker_spare_{os.getpid()}',
            namespace=namespace or '/', start_parameter_services=False,
            parameter_overrides=[Parameter('start_type_description_service', value=False)])
        # LeanExecutor: rclpy's executor rebuilt the wait set in Python before every wait
        # and woke once more after every callback (lean_executor.py).
        self.executor = LeanExecutor()
        self.executor.add_node(self.node)
        # The reader thread only queues; nodes are created and destroyed in the executor.
        self.wake = self.node.create_guard_condition(self.serve)
        self.ticker = self.node.create_timer(0.005, self.poll_deferred)
        self.ticker.cancel()            # runs only while something is deferred
        # One timer polls every hosted node's timeouts (each node's own timer is removed):
        # 21 timers at 10 Hz were ~200 executor wake-ups a second, each a wait-set rebuild.
        self.poller = self.node.create_timer(NODE_POLL_S, self.poll_nodes)
        # The hosted nodes' /diagnostics statuses (quarters, arbiters), batched per frame
        # stamp: one message per worker and frame instead of one per node (a publish to the
        # other processes' subscribers, the recorder's and the coordinator's, cost ~0.3-2 ms
        # of CPU here, and each is a wake-up of the replay process).
        from diagnostic_msgs.msg import DiagnosticArray

        from multicam_ego_motion.ros_plumbing.qos import RELIABLE
        self.diag_pub = self.node.create_publisher(DiagnosticArray, '/diagnostics', RELIABLE)
        self.diag_batches = {}          # (sec, nanosec) -> (stamp, [DiagnosticStatus], opened at)
        self.diag_expected = None       # status names of a complete batch (hosted nodes')
        self.costs_out = []             # [(stamp key, [(name, values)], when)] not sent yet
        strip_event_handlers(self.node)
        # Shared inputs: one subscription per topic for all hosted quarters (a camera's image,
        # the fused pose) calling each one's callback. Per quarter, they were 2 takes and 2
        # executor callbacks per frame, and 2 more readers for every publisher to write to.
        self.feeds = {}                 # topic -> (subscription, {key: callback})
        # Work that waits until no callback is ready (spin): the quarters' new features once
        # their estimates are out, and their next-frame optical flow while the fused pose is
        # under way. Before other callbacks it would delay the estimates the arbiters wait
        # for, i.e. the fused pose itself.
        self.idle_work = []             # nodes whose work_ahead() is due, in arrival order
        self.gc = IdleCollector()       # last: everything imported and set up is frozen

    def offer_idle_work(self, node):
        # Once per node: a quarter offers after each image and each fused pose, and a worker
        # that is never idle (overloaded) would otherwise queue every offer.
        if not any(n is node for n in self.idle_work):
            self.idle_work.append(node)

    def feed(self, key, node):
        for topic, (msg_type, qos, callback) in node.inputs.items():
            if topic not in self.feeds:
                def dispatch(msg, topic=topic):
                    for cb in list(self.feeds[topic][1].values()):
                        cb(msg)
                sub = self.node.create_subscription(msg_type, topic, dispatch, qos,
                                                    raw=topic in getattr(node, 'raw_inputs', ()))
                strip_event_handlers(self.node)
                self.feeds[topic] = (sub, {})
            self.feeds[topic][1][key] = callback

    def unfeed(self, key):
        for topic in list(self.feeds):
            sub, callbacks = self.feeds[topic]
            callbacks.pop(key, None)
            if not callbacks:
                self.node.destroy_subscription(sub)
                del self.feeds[topic]

    def wire_local(self):
        """Quarter estimates (and debug_images tiles) go to a camera arbiter of the same
        worker by a call, and camera estimates to a general arbiter of the same worker (they
        are still published when anyone else listens: the recorder, a viewer); an arbiter
        subscribes only to its sources hosted elsewhere. Redone whenever a node comes or goes."""
        arbiters = {n.camera: n for k, n in self.hosted.items() if self.kinds[k] == 'camera_arbiter'}
        local = {}
        for k, n in self.hosted.items():
            if self.kinds[k] != 'quarter':
                continue
            arb = arbiters.get(n.camera.name)
            source = f'q{n.quarter}'
            n.estimate_sink = None if arb is None else (lambda msg, a=arb, s=source: a.on_quarter(s, msg))
            # debug_images: the tracks tile the same way, when both draw them
            n.tracks_sink = (None if arb is None or not arb.debug_images or n.pub_tracks is None
                             else (lambda msg, a=arb, s=source: a.on_tracks(s, msg)))
            local.setdefault(n.camera.name, set()).add(source)
        for cam, arb in arbiters.items():
            arb.take_local(local.get(cam, set()))
            strip_event_handlers(arb)
        # Camera estimates go to a general arbiter of the same worker the same way.
        general = next((n for k, n in self.hosted.items() if self.kinds[k] == 'general_arbiter'), None)
        for cam, arb in arbiters.items():
            arb.estimate_sink = None if general is None else (lambda msg, g=general, c=cam: g.on_camera(c, msg))
        if general is not None:
            general.take_local(set(arbiters))
            strip_event_handlers(general)

    def shared_subscriptions(self, node):
        return [self.feeds[t][0] for t in getattr(node, 'inputs', {}) if t in self.feeds]

    def poll_nodes(self):
        for node in list(self.hosted.values()):
            node.poll()
        # Stragglers only: with two frames in flight the next frame's batch is usually still
        # filling, and flushing it split one message a frame into two.
        now = time.monotonic()
        for k in sorted(self.diag_batches):
            if now - self.diag_batches[k][2] > DIAG_STRAGGLER_S:
                self.flush_diagnostics(k)
        self.send_costs_if_due()

    def collect_diagnostic(self, stamp, status):
        key = (stamp.sec, stamp.nanosec)
        batch = self.diag_batches.setdefault(key, (stamp, [], time.monotonic()))[1]
        batch.append(status)
        # complete when every hosted node that reports has: its status name is its key's
        if self.diag_expected is None:
            self.diag_expected = {f'ego_motion/{k}' for k, n in self.hosted.items()
                                  if getattr(n, 'diag_sink', None)}
        if len(batch) >= len(self.diag_expected) and self.diag_expected <= {s.name for s in batch}:
            self.flush_diagnostics(key)

    def flush_diagnostics(self, key=None):
        """Publish the batch of `key` (all batches when None: the poll timer's stragglers)."""
        from multicam_ego_motion.ros_plumbing import diagnostics
        for k in ([key] if key is not None else sorted(self.diag_batches)):
            stamp, statuses, _ = self.diag_batches.pop(k)
            self.diag_pub.publish(diagnostics.array(stamp, statuses))
            # The allocation's input, without the coordinator decoding the whole batch.
            self.costs_out.append((k, [(s.name, cost_values(s)) for s in statuses], time.monotonic()))
        self.send_costs_if_due()

    def send_costs_if_due(self):
        if self.costs_out and (len(self.costs_out) >= COSTS_EVERY
                               or time.monotonic() - self.costs_out[0][2] > COSTS_MAX_AGE_S):
            frames, self.costs_out = self.costs_out, []
            self.send((control.COSTS, [(k, entries) for k, entries, _ in frames]))

    def send(self, msg):
        with self.send_lock:
            try:
                self.conn.send(msg)
            except OSError as e:
                # The coordinator is gone as surely as when its heartbeats stop: a link that
                # went silent fills the send buffer and the send times out with the socket's
                # heartbeat timeout (socket.timeout is an OSError), often before the reader
                # notices. End the same way: nodes stopped, exit 3 (not a traceback).
                if self.lost is None:
                    self.lost = (f'no heartbeat for {control.HEARTBEAT_TIMEOUT_S:.0f} s'
                                 if isinstance(e, socket.timeout) else str(e) or 'connection closed')
                raise SystemExit(0) from e

    def read_commands(self):
        # Over TCP the coordinator pings every second: silence means its host is gone.
        timeout = control.HEARTBEAT_TIMEOUT_S if self.conn.is_tcp else None
        try:
            while True:
                msg = self.conn.recv(timeout=timeout)
                if msg[0] == control.STOP:
                    break           # the coordinator closes the channel next: not a loss
                if msg[0] != control.PING:
                    self.inbox.put(msg)
                    self.wake.trigger()
        except socket.timeout:
            self.lost = f'no heartbeat for {timeout:.0f} s'
        except (EOFError, OSError, control.AuthError) as e:
            self.lost = str(e) or 'connection closed'
        self.inbox.put((control.STOP,))     # coordinator gone: end with it
        self.wake.trigger()
        exit_within(EXIT_GRACE_S, 3 if self.lost else 0)

    def serve(self):
        while True:
            try:
                cmd = self.inbox.get_nowait()
            except queue.Empty:
                return
            if cmd[0] == control.STOP:
                raise SystemExit(0)
            if cmd[0] == control.ATTACH:
                self.attach(*cmd[1:])
            elif cmd[0] == control.DETACH:
                self.detach(*cmd[1:])
            elif cmd[0] == control.LINKS:
                self.links(*cmd[1:])

    def defer(self, predicate, action, timeout_s):
        self.deferred.append((predicate, action, time.monotonic() + timeout_s))
        self.ticker.reset()
        self.poll_deferred()

    def poll_deferred(self):
        now = time.monotonic()
        for item in list(self.deferred):
            predicate, action, deadline = item
            ok = predicate()
            if ok or now > deadline:
                self.deferred.remove(item)
                action(ok)
        if not self.deferred:
            self.ticker.cancel()

    def snapshot(self, key, node):
        # A quarter's state is ~70 kB: pickling it every frame cost more than the gap saves
        # (a quarter restored from a few frames back just tracks across it); the general
        # arbiter (12 kB, and the odometry's continuity) is saved every frame.
        count = self.frames_done.get(key, 0)
        self.frames_done[key] = count + 1
        if key != 'general_arbiter' and count % QUARTER_SNAPSHOT_EVERY:
            return
        data = pickle.dumps(node.get_state(), protocol=pickle.HIGHEST_PROTOCOL)
        if self.snapshots is not None:
            try:
                self.snapshots.put(key, data)
            except (OSError, ValueError) as e:    # a restore then starts from an older one
                self.node.get_logger().error(f'{key}: state snapshot not saved: {e}',
                                             throttle_duration_sec=10.0)
        else:
            self.send((control.SNAPSHOT, key, data))

    def attach(self, req, spec, state_bytes, wait_links=False):
        key = spec['key']
        if self.paths:          # files named by the coordinator's paths: this host's copies
            spec = dict(spec, parameters={k: self.paths.get(v, v) if isinstance(v, str) else v
                                          for k, v in spec['parameters'].items()})
        try:
            node = create_node(spec, self.params_file,
                               **({'shared_inputs': True} if spec['kind'] == 'quarter' else {}))
            if state_bytes is not None and hasattr(node, 'set_state'):
                state = pickle.loads(state_bytes)
                if state is not None:
                    node.set_state(state)
        except Exception as e:      # reported to the coordinator, which fails the run
            self.send((control.REPLY, req, {'ok': False, 'error': f'{key}: {type(e).__name__}: {e}'}))
            return
        if hasattr(node, 'get_state'):
            node.on_frame_done = lambda n, key=key: self.snapshot(key, n)
        node.destroy_timer(node.poll_timer)       # poll_nodes() polls it
        if hasattr(node, 'diag_sink'):
            node.diag_sink = self.collect_diagnostic
        if hasattr(node, 'work_ahead_sink'):
            node.work_ahead_sink = self.offer_idle_work
        strip_event_handlers(node)
        self.hosted[key] = node
        self.diag_expected = None
        self.kinds[key] = spec['kind']
        if getattr(node, 'inputs', None):
            self.feed(key, node)
        self.wire_local()
        self.executor.add_node(node)
        # Which process hosts what: read by people after a crash, and by the fault tests.
        print(f'worker {self.index} (pid {os.getpid()}) hosts {", ".join(self.hosted)}', flush=True)

        if not wait_links:          # start-up and restore: nothing to match yet / frame re-sent
            self.send((control.REPLY, req, {'ok': True}))
            return

        def done(in_time):
            time.sleep(0.05)        # the other side of each match (writer vs reader) catches up
            self.send((control.REPLY, req, {'ok': True, 'linked': in_time}))
        self.defer(lambda: linked(node, self.shared_subscriptions(node)), done, LINK_TIMEOUT_S)

    def links(self, req):
        """Reply once every hosted node's links to the rest of the graph are matched (both
        ends: a writer that matched a reader before the reader matched it loses samples).
        At start-up: a camera estimate of the first frame published before the general
        arbiter's reader had matched was lost, and the frame waited for the sync timeout."""
        nodes = list(self.hosted.values())

        def done(in_time):
            self.send((control.REPLY, req, {'ok': True, 'linked': in_time}))
        self.defer(lambda: all(linked(n, self.shared_subscriptions(n), graph_only=True) for n in nodes),
                   done, START_LINK_TIMEOUT_S)

    def detach(self, req, key, idle_wait_s=None):
        """Detach a node once it is between frames, and reply with its state. idle_wait_s:
        a node still mid-frame after that long stays (the reply says busy); None: it is taken
        as it is after DETACH_IDLE_TIMEOUT_S."""
        node = self.hosted.get(key)
        if node is None:
            self.send((control.REPLY, req, {'ok': False, 'error': f'{key} is not hosted here'}))
            return

        def done(idle):
            if not idle and idle_wait_s is not None:
                self.send((control.REPLY, req, {'ok': True, 'busy': True}))
                return
            self.flush_diagnostics()
            state = node.get_state() if hasattr(node, 'get_state') else None
            self.unfeed(key)
            self.idle_work[:] = [n for n in self.idle_work if n is not node]
            self.executor.remove_node(node)
            node.destroy_node()
            del self.hosted[key]
            self.diag_expected = None
            del self.kinds[key]
            self.wire_local()
            self.send((control.REPLY, req, {'ok': True, 'idle': idle,
                                            'state': pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)}))
        # Between frames only: the state must include the last frame's fused pose.
        self.defer(getattr(node, 'idle', lambda: True), done,
                   DETACH_IDLE_TIMEOUT_S if idle_wait_s is None else idle_wait_s)

    def _spin(self):
        """The executor's loop, plus idle work: one item whenever a look at the wait set
        finds nothing ready, then garbage collection (idle_gc)."""
        ex = self.executor
        looked = False          # the last non-blocking wait found callbacks
        while True:
            ready = ex.wait_ready(0.0 if self.idle_work or self.gc.due() else None)
            if not ready:
                # Only a wait that found nothing right after one that found something is
                # not idle yet: what those callbacks produced may be ready now.
                if looked:
                    looked = False
                elif self.idle_work:
                    self.idle_work.pop(0).work_ahead()
                else:
                    self.gc.collect_idle()
                continue
            looked = True
            self.gc.collect_if_overdue()
            for call in ready:
                call()

    def spin(self):
        threading.Thread(target=self.read_commands, daemon=True).start()
        self.send((control.HELLO, self.index, os.getpid(), socket.gethostname()))
        if self.conn.is_tcp:
            control.keep_alive(self.conn, threading.Event())
        try:
            self._spin()
        finally:
            if not stopped_by_signal.is_set():
                for node in self.hosted.values():
                    node.destroy_node()
                self.node.destroy_node()


def _join(args, key):
    """Connect, authenticate, get a slot and the graph's configuration."""
    deadline = time.monotonic() + args.connect_timeout
    while True:
        try:
            conn = control.connect_tcp(args.coordinator, key)
            break
        except control.AuthError:
            raise
        except ConnectionError as e:
            if time.monotonic() > deadline:
                raise UserError(f'{e} (tried for {args.connect_timeout:.0f} s)') from None
            time.sleep(0.5)
    conn.send((control.HELLO, control.REMOTE, os.getpid(), socket.gethostname()))
    msg = conn.recv(timeout=control.HANDSHAKE_TIMEOUT_S)
    if msg[0] != control.WELCOME:
        conn.close()
        raise UserError(f'coordinator at {args.coordinator} has no free worker slot')
    return conn, msg[1], msg[2]


def run_remote(args) -> int:
    if not args.coordinator:
        raise UserError('give --coordinator HOST:PORT (the address the coordinator listens on)')
    key = control.load_key(args.key_file)          # a missing key fails before the imports
    import cv2
    cv2.setNumThreads(1)                            # as a local worker (main() says why)
    for kind in ('quarter', 'camera_arbiter', 'general_arbiter'):
        node_class(kind)
    try:
        conn, index, config = _join(args, key)
    except control.AuthError as e:
        raise UserError(f'{e}') from None
    print(f'worker: joined the coordinator at {args.coordinator} as worker {index}', flush=True)
    folder = tempfile.mkdtemp(prefix='ego_motion_remote_worker_')
    paths = {}
    for i, (path, text) in enumerate(sorted(config['files'].items())):
        local = os.path.join(folder, f'{i}_{os.path.basename(path)}')
        with open(local, 'w') as f:
            f.write(text)
        paths[path] = local
    # Ctrl-C, SIGTERM, SIGHUP: stop the nodes and exit (rclpy's handlers, which call these,
    # wake the executor's blocking wait).
    signals = []

    def on_signal(signum, frame):
        signals.append(signum)
        stop_on_signal(128 + signum)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)
    rclpy.init(args=['worker', *config['ros_args']],
               signal_handler_options=rclpy.signals.SignalHandlerOptions.ALL)
    worker = None
    try:
        worker = Worker(index, conn, paths.get(config['params_file']), config['namespace'], paths)
        worker.spin()
    except (KeyboardInterrupt, SystemExit, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
        import shutil
        shutil.rmtree(folder, ignore_errors=True)
    if worker is not None and worker.lost:
        print(f'worker: lost the coordinator at {args.coordinator} ({worker.lost}); '
              'stopped its nodes, exiting', flush=True)
        return 3
    if signals:
        print(f'worker: stopped by {signal.Signals(signals[0]).name}; its nodes are restored '
              'elsewhere by the coordinator', flush=True)
        return 128 + signals[0]
    print('worker: stopped by the coordinator', flush=True)
    return 0


def main_remote(argv=None):
    """Console entry point `worker` (ros2 run multicam_ego_motion worker)."""
    from rclpy.utilities import remove_ros_args
    from multicam_ego_motion.coordinator import remote_worker
    ap = argparse.ArgumentParser(prog='worker', description='join a coordinator\'s worker pool from this host')
    remote_worker.configure_parser(ap)
    args = ap.parse_args(remove_ros_args(sys.argv if argv is None else ['worker', *argv])[1:])
    try:
        return run_remote(args)
    except UserError as e:
        print(f'worker: error: {e}', file=sys.stderr, flush=True)
        return 2


def main(argv=None):
    for sig in (signal.SIGINT, signal.SIGHUP):   # the coordinator stops us (module docstring)
        signal.signal(sig, signal.SIG_IGN)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--index', type=int, required=True, help='worker index; -1: a hot spare')
    ap.add_argument('--control', required=True, help='address of the coordinator\'s control channel')
    ap.add_argument('--params-file')
    ap.add_argument('--namespace', default='/', help='the graph\'s namespace (its remappings follow --ros-args)')
    ap.add_argument('--state-dir', help='the coordinator\'s snapshot folder on this host (snapshot_store.py)')
    # --ros-args (the namespace's remappings) are rclpy.init's: it reads them from sys.argv
    from rclpy.utilities import remove_ros_args
    args = ap.parse_args(remove_ros_args(sys.argv if argv is None else ['worker', *argv])[1:])
    _die_with_parent()
    # The workers are the parallelism (like OPENBLAS_NUM_THREADS=1 from the coordinator):
    # OpenCV's own pool only oversubscribes the cores, and its work would escape the
    # nodes' stage times (CPU time of the calling thread), which are the costs balanced.
    import cv2
    cv2.setNumThreads(1)
    # EGO_MOTION_NULL_ESTIMATOR=1 (the bench's transport floor): the quarters do no work.
    from multicam_ego_motion.bench import transport_floor
    transport_floor.installed_from_environment()
    # Import the node modules before saying hello: a spare that takes over a dead worker
    # then only creates nodes (restore within 2 s even on a loaded machine).
    for kind in ('quarter', 'camera_arbiter', 'general_arbiter'):
        node_class(kind)
    conn = control.connect(args.control)
    signal.signal(signal.SIGTERM, lambda signum, frame: stop_on_signal(0))
    # rclpy's SIGTERM handler wakes the executor's blocking wait (shuts the context down).
    rclpy.init(signal_handler_options=rclpy.signals.SignalHandlerOptions.SIGTERM)
    # EGO_MOTION_PROFILE_DIR=DIR: each worker writes cProfile stats to
    # DIR/worker_<index>_<pid>.prof when it stops (where the graph's CPU goes beyond the
    # nodes' own stage times). The pid: spares all start with index -1.
    profile_dir = os.environ.get('EGO_MOTION_PROFILE_DIR')
    profiler = None
    if profile_dir:
        import cProfile
        profiler = cProfile.Profile(time.thread_time)   # CPU time: wall time charged other processes' turns to whatever ran
        profiler.enable()
    try:
        Worker(args.index, conn, args.params_file, args.namespace, state_dir=args.state_dir).spin()
    except (KeyboardInterrupt, SystemExit, ExternalShutdownException):
        pass
    finally:
        if profiler is not None:
            profiler.disable()
            os.makedirs(profile_dir, exist_ok=True)
            profiler.dump_stats(os.path.join(profile_dir, f'worker_{args.index}_{os.getpid()}.prof'))
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
