"""`ego-motion record`: record topics of a running graph into a rosbag2 (MCAP) bag.

One generic subscription per topic: the type comes from the graph
(`get_publishers_info_by_topic`), messages arrive as serialized bytes (`raw=True`) and go
into the bag unchanged (`Rosbag2Writer.write_serialized`) with the receive time of the
node's clock (wall time, or the bag time with `--use-sim-time`). Topics named with
`--topics` that do not exist yet are subscribed as soon as a publisher appears; `--all`
keeps adding every new topic (hidden `_` topics excepted). The subscription QoS matches the
publishers: reliable when every publisher is reliable, best effort as soon as one is
(sensor-data cameras), transient local for latched topics such as /tf_static.

Ending: SIGINT, SIGTERM or SIGHUP (interrupt.py) closes the bag (summary, metadata.yaml) and
it holds every message received until then: closing first takes what is still waiting in
the subscriptions' queues. The command then exits with 128 + the signal, after one line
saying how many messages it kept. Every second the writer also finishes its current chunk,
hands it to the OS and rewrites metadata.yaml, so a hard kill (SIGKILL, OOM) loses at most
the last second: the .mcap then has no summary and footer (our readers call it unfinished),
but its finished chunks are intact and `ego-motion reindex BAG` rebuilds the bag from them.

Python API (used in-process by `replay`)::

    recorder = BagRecorder('out/run/estimate', topics=['/odom', '/ego_motion/path'])
    recorder.attach(node)            # subscriptions + discovery/flush timers on `node`
    recorder.wait_for_topics(10.0)   # optional: until every named topic is subscribed
    ...                              # someone spins `node`
    counts = recorder.close()        # -> {topic: messages written}; bag complete
                                     # (call it once nothing spins `node` any more)

`attach` does not spin: the caller's executor does. Callbacks may run on several threads
(MultiThreadedExecutor); writes are serialized by a lock.
"""
import threading
import time
from typing import Dict, Iterable, Optional

from multicam_ego_motion import interrupt
from multicam_ego_motion.bag.rosbag2_writer import Rosbag2Writer
from multicam_ego_motion.errors import UserError

DISCOVERY_PERIOD_S = 0.2
FLUSH_PERIOD_S = 1.0
DRAIN_LIMIT = 10_000   # messages taken per subscription when closing (the graph may still publish)


def is_hidden(topic: str) -> bool:
    return any(part.startswith('_') for part in topic.split('/'))


class BagRecorder:
    """Subscribe to topics of the graph and write what arrives into a new bag."""

    def __init__(self, out, topics: Optional[Iterable[str]] = None, all_topics: bool = False):
        self.topics = list(topics or [])
        self.all_topics = all_topics
        if not self.topics and not all_topics:
            raise UserError('record: name the topics with --topics, or use --all')
        self.writer = Rosbag2Writer(out)
        self._lock = threading.Lock()
        # discover() runs from attach() on the caller's thread and from the timer on the
        # executor's: without this, both could subscribe the same topic (every message twice).
        self._discover_lock = threading.Lock()
        self._subscriptions = {}  # topic -> Subscription
        self._node = None
        self._timers = []
        self._closed = False
        self._listeners = {}      # topic -> [fn(serialized message)]

    def listen(self, topic: str, fn):
        """Also hand every recorded message of `topic` (serialized) to fn: a reader in the
        same process then needs no subscription and no take of its own."""
        if topic not in self.topics and not self.all_topics:
            raise UserError(f'record: {topic} is not recorded, so it cannot be listened to')
        self._listeners.setdefault(topic, []).append(fn)

    def attach(self, node):
        self._node = node
        self._timers = [node.create_timer(DISCOVERY_PERIOD_S, self.discover),
                        node.create_timer(FLUSH_PERIOD_S, self.flush)]
        self.discover()

    def discover(self):
        """Subscribe to every wanted topic that now has a publisher."""
        with self._discover_lock:
            self._discover()

    def _discover(self):
        from multicam_ego_motion.bag.message_types import message_class
        from multicam_ego_motion.bag.topic_qos import subscribing_qos
        node = self._node
        if self.all_topics:
            candidates = [t for t, _ in node.get_topic_names_and_types() if not is_hidden(t)]
        else:
            candidates = self.topics
        for topic in candidates:
            if topic in self._subscriptions:
                continue
            infos = node.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            typename = infos[0].topic_type
            try:
                cls = message_class(typename)
            except UserError as e:
                node.get_logger().warning(f'not recording {topic}: {e}')
                self._subscriptions[topic] = None
                continue
            with self._lock:
                self.writer.add_topic(topic, typename)
            self._subscriptions[topic] = node.create_subscription(
                cls, topic, lambda data, t=topic, ty=typename: self._on_message(t, ty, data),
                subscribing_qos(i.qos_profile for i in infos), raw=True)
            node.get_logger().info(f'recording {topic} ({typename})')

    def _on_message(self, topic, typename, data):
        for fn in self._listeners.get(topic, ()):
            fn(data)
        stamp = self._node.get_clock().now().nanoseconds
        with self._lock:
            if not self._closed:
                self.writer.write_serialized(topic, typename, data, stamp)

    def wait_for_topics(self, timeout_s: float) -> bool:
        """True once every topic named in `topics` is subscribed and matched to a publisher.

        Created is not enough: a reliable, volatile subscription misses what is published
        before discovery matches it (discovery needs spinning)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            subs = [self._subscriptions.get(t) for t in self.topics]
            if all(s is not None and s.get_publisher_count() > 0 for s in subs):
                return True
            time.sleep(0.05)
        return False

    def flush(self):
        with self._lock:
            if not self._closed:
                self.writer.flush()

    def counts(self) -> Dict[str, int]:
        with self._lock:
            return self.writer.message_counts()

    def drain(self) -> int:
        """Write what the subscriptions have received but no callback has taken yet (the
        executor was stopped by a signal or the end of a run); returns how many. Only while
        nothing else spins the node."""
        taken = 0
        for topic, sub in list(self._subscriptions.items()):
            if sub is None:
                continue
            for _ in range(DRAIN_LIMIT):
                try:
                    with sub.handle:
                        info = sub.handle.take_message(sub.msg_type, sub.raw)
                except Exception:   # destroyed, or the context is gone: nothing more to take
                    break
                if info is None:
                    break
                sub.callback(info[0])
                taken += 1
        return taken

    def close(self) -> Dict[str, int]:
        """Stop recording and finish the bag (summary, metadata.yaml); returns messages
        written per topic. Messages still queued in the subscriptions are written first."""
        with self._lock:
            if self._closed:
                return self.writer.message_counts()
        if self._node is not None:
            self.drain()
        with self._lock:
            self._closed = True
            self.writer.close()
        if self._node is not None:
            for timer in self._timers:
                self._node.destroy_timer(timer)
            for sub in self._subscriptions.values():
                if sub is not None:
                    self._node.destroy_subscription(sub)
        return self.writer.message_counts()


# ---- command line ---------------------------------------------------------------------

def configure_parser(parser):
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument('--topics', nargs='+', metavar='TOPIC', help='topics to record')
    which.add_argument('--all', action='store_true', help='record every (non-hidden) topic')
    parser.add_argument('--out', '-o', required=True, help='new bag folder')
    parser.add_argument('--use-sim-time', action='store_true',
                        help='log messages with the /clock time instead of wall time')


def run(args) -> int:
    recorder = BagRecorder(args.out, topics=args.topics, all_topics=args.all)
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    # A signal (interrupt.py) only ends the loop below: it never cuts a write in half (the
    # callbacks run in this thread); the bag is closed, then Interrupted is raised and the
    # command line prints what was kept.
    t0 = time.monotonic()
    interrupt.note(progress=lambda: f'after {time.monotonic() - t0:.1f} s of recording')
    with interrupt.deferred():
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        try:
            node = Node('ego_motion_recorder', parameter_overrides=[
                Parameter('use_sim_time', value=args.use_sim_time)])
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            recorder.attach(node)
            try:
                while not interrupt.requested():
                    executor.spin_once(timeout_sec=0.1)
            finally:
                executor.shutdown(timeout_sec=0)
                recorder.close()
                node.destroy_node()
        finally:
            counts = recorder.close()     # once only; also when the node never came up
            rclpy.try_shutdown()
            interrupt.note(kept=f'kept {args.out}: recorded {sum(counts.values())} messages ('
                           + (', '.join(f'{t} {n}' for t, n in sorted(counts.items())) or 'none')
                           + '), closed with its summary and metadata.yaml')
    return 0
