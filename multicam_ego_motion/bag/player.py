"""`ego-motion play`: publish a rosbag2 (MCAP) bag into a running graph.

Two modes:

* rate (default, `--rate R`): a frame recorded t seconds after the start of the played
  window is published t / R seconds of wall time after playback starts, like
  `ros2 bag play --rate R`. Used to measure real-time behaviour, latency and drops.
* lockstep (`--lockstep`): frames are published as fast as the graph finishes them. After
  each *trigger frame* (a frame holding a message on a lockstep topic; default: every
  `*/image_raw` and `*/image_raw/compressed` topic) the player waits for the graph's acknowledgement on `--ack-topic`:
  a message whose header.stamp is at or after the frame's stamp (the newest header stamp
  among the frame's trigger messages), or, for an ack type without a header, any message
  received after the frame was published. No acknowledgement within `--ack-timeout` is an
  error that names the frame. A frame not acknowledged after `--stall-ahead` seconds (2) lets
  the next frame out, up to two more: a graph that lost an image (or whose image sits in the
  transport until the next sample is written) goes on. Deterministic and drop-free; used by
  tests and `replay`.

A *frame* is a run of consecutive messages with the same log time: a rig driver (and the
scenario generator) stamps and logs the images of one exposure together, so the cameras of
one frame are always published together, before any acknowledgement is awaited. Free-running
cameras (`--sync-window S`, lockstep; the general arbiter's `sync_window_s`): a frame is the
run of messages within S of its first, holding each trigger topic at most once, so every
camera's image of one frame is out before the player waits for the frame's /odom (stamped
at its latest image).

Messages are published as the serialized bytes stored in the bag (rclpy's
`Publisher.publish` accepts bytes), never decoded. Publishers are RELIABLE (they match
reliable and best-effort subscribers), `/tf_static` is TRANSIENT_LOCAL. With `--clock`
(default) a rosgraph_msgs/Clock carrying the frame's log time is published before each frame,
so nodes with use_sim_time follow the bag. Before the first frame the player listens to the
graph for `--discovery` seconds (default 1; a fresh process knows no subscriber before
discovery ran) and then waits until every subscriber the graph has on a played topic is
matched to its publisher, so nothing is published into the void (lockstep additionally requires a publisher on the ack topic and
a subscriber on every trigger topic).

Python API (used in-process by `replay`)::

    player = BagPlayer('bags/default', PlayOptions(lockstep=True, ack_topic='/odom'))
    result = player.play(node_or_context)   # -> PlaybackResult

`BagPlayer(...)` opens and checks the bag and options (UserError on bad input) without
touching ROS. `play()` accepts:
  * None: a node is created in rclpy's default context (rclpy.init() must have run);
  * an rclpy Context: a node is created in that context and destroyed afterwards;
  * an rclpy Node: its publishers/subscription are created on it and destroyed afterwards.
    If the node is not in an executor, `play` spins it itself while it waits; if it is
    (e.g. a MultiThreadedExecutor spinning in another thread), `play` only waits and relies
    on that executor to deliver the acknowledgements.
It returns when the last frame was published (and, in lockstep, acknowledged), and raises
UserError on an acknowledgement timeout or a missing graph. `position()` says how far it got
(for the line an interrupted command prints).

Ending: SIGINT, SIGTERM or SIGHUP (interrupt.py) stop `ego-motion play` between two messages:
its publishers are destroyed, one line says how far it got, exit code 128 + the signal.
"""
import argparse
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from typing import Callable, Dict, Iterable, Iterator, List, Optional

from multicam_ego_motion.bag.rosbag2_reader import BagMessage, Rosbag2Reader
from multicam_ego_motion.errors import UserError

# camera images, raw or image_transport's compressed
DEFAULT_LOCKSTEP_PATTERNS = ('*/image_raw', '*/image_raw/compressed')
NS_PER_S = 1_000_000_000
MATCH_SETTLE_S = 0.2
REPUBLISH_PERIOD_S = 0.5
# Lockstep: a frame not acknowledged after this long lets the next frame out (up to
# STALL_AHEAD_FRAMES more in flight). A reliable sample can sit in the transport until the
# next sample on its topic is written (seen after a worker was killed: one camera's image
# stuck for the general arbiter's whole 10 s sync timeout, never repaired by DDS); a live
# camera writes that next sample a frame later, a lockstep player never did. Each node still
# takes the frames in order, so the output is the same as without.
STALL_S = 2.0
STALL_AHEAD_FRAMES = 2


@dataclass
class PlayOptions:
    lockstep: bool = False
    rate: float = 1.0
    ack_topic: str = '/odom'
    ack_timeout_s: float = 30.0
    # lockstep: trigger frames published but not yet acknowledged, at most. 1: each waits
    # for the last; 2: the next frame is already delivered while the graph finishes the last
    # (the graph pipelines: its quarters compute the next optical flow meanwhile). Each node
    # still takes the frames in order, so the output is the same. Needs a stamped ack type.
    lockstep_depth: int = 1
    # lockstep: a frame not acknowledged after this long lets the next one out (STALL_S; 0: never)
    stall_ahead_s: float = STALL_S
    lockstep_topics: Optional[List[str]] = None   # bag topic names; None: every */image_raw(/compressed)
    sync_window_s: float = 0.0    # lockstep: a frame spans this much log time (free-running cameras)
    remap: Dict[str, str] = field(default_factory=dict)  # bag topic -> published topic
    start_offset_s: float = 0.0
    duration_s: Optional[float] = None
    topics: Optional[List[str]] = None            # bag topics to play; None: all
    clock: bool = True
    progress: Optional[bool] = None               # None: only when stderr is a terminal
    discovery_s: float = 1.0          # listen to the graph this long before the first frame
    discovery_timeout_s: float = 5.0  # then wait at most this long for subscribers to match
    # lockstep: called with the frame index after an acknowledged trigger frame, just before
    # the next frame is published (the coordinator moves nodes there); never after the last
    # frame, where a move would only change what the run's final diagnostics say
    between_frames: Optional[Callable[[int], None]] = None
    # Called about twice a second while the player waits (for the graph or an ack); raising
    # (a UserError) aborts playback: `replay` uses it to notice a dead worker at once
    # instead of after the ack timeout.
    health_check: Optional[Callable[[], None]] = None
    # lockstep: instead of subscribing to the ack topic, register the ack handler (it takes
    # the serialized message) with a reader this process already has on that topic, e.g.
    # BagRecorder.listen: one take per ack instead of two
    ack_source: Optional[Callable[[Callable[[bytes], None]], None]] = None


@dataclass
class Frame:
    index: int
    log_time_ns: int
    messages: List[BagMessage]
    stamp_ns: Optional[int]  # stamp the ack must reach; None: not a trigger frame

    @property
    def is_trigger(self) -> bool:
        return self.stamp_ns is not None


@dataclass
class PlaybackResult:
    frames: int = 0
    messages: int = 0
    per_topic: Dict[str, int] = field(default_factory=dict)  # published topic -> count
    wall_time_s: float = 0.0
    published_at: Dict[int, float] = field(default_factory=dict)  # trigger stamp -> monotonic s
    republished: int = 0              # frames published again after a graph restart
    published_ahead: int = 0          # lockstep: frames let out while an older one stalled (STALL_S)


def parse_remaps(items: Iterable[str]) -> Dict[str, str]:
    remap = {}
    for item in items or ():
        src, sep, dst = item.partition(':=')
        if not sep or not src or not dst:
            raise UserError(f'bad remap {item!r}: expected FROM:=TO')
        remap[src] = dst
    return remap


def group_frames(messages: Iterable[BagMessage], trigger_topics, window_ns: int = 0) -> Iterator[Frame]:
    """Group log-time-ordered messages into frames: runs with equal log time, or with
    window_ns > 0, runs within window_ns of their first message that hold each trigger topic
    at most once (free-running cameras)."""
    from multicam_ego_motion.bag.header_stamp import has_header, header_stamp_ns
    trigger_topics = set(trigger_topics)
    batch: List[BagMessage] = []
    triggers_seen = set()
    index = 0

    def finish():
        stamps = [header_stamp_ns(m.data) if has_header(m.typename) else m.log_time_ns
                  for m in batch if m.topic in trigger_topics]
        return Frame(index, batch[0].log_time_ns, batch, max(stamps) if stamps else None)

    def starts_new(msg):
        if window_ns <= 0:
            return msg.log_time_ns != batch[0].log_time_ns
        return (msg.log_time_ns - batch[0].log_time_ns > window_ns
                or (msg.topic in trigger_topics and msg.topic in triggers_seen))

    for msg in messages:
        if batch and starts_new(msg):
            yield finish()
            index += 1
            batch = []
            triggers_seen = set()
        batch.append(msg)
        if msg.topic in trigger_topics:
            triggers_seen.add(msg.topic)
    if batch:
        yield finish()


class BagPlayer:
    """A bag checked against the options, ready to be played (see the module docstring)."""

    def __init__(self, bag, options: Optional[PlayOptions] = None):
        self.options = opts = options or PlayOptions()
        if opts.rate <= 0:
            raise UserError(f'--rate must be positive (got {opts.rate})')
        if not 0.0 <= opts.sync_window_s <= 1.0:
            raise UserError(f'--sync-window must be within 0 and 1 s (got {opts.sync_window_s})')
        if opts.lockstep_depth < 1:
            raise UserError(f'--lockstep-depth must be at least 1 (got {opts.lockstep_depth})')
        if not opts.stall_ahead_s >= 0:
            raise UserError(f'--stall-ahead must be >= 0 seconds (got {opts.stall_ahead_s})')
        if opts.start_offset_s < 0 or (opts.duration_s is not None and opts.duration_s <= 0):
            raise UserError('--start-offset must be >= 0 and --duration > 0')
        self.reader = Rosbag2Reader(bag)
        if opts.topics:
            self.reader.require(opts.topics)
        self.topics = list(opts.topics) if opts.topics else sorted(self.reader.topics)
        unknown_remaps = [t for t in opts.remap if t not in self.topics]
        if unknown_remaps:
            raise UserError(f'--remap names topics that are not played: {", ".join(unknown_remaps)}')
        self.published_name = {t: opts.remap.get(t, t) for t in self.topics}
        self.trigger_topics = self._trigger_topics()
        if opts.lockstep and opts.ack_topic in self.published_name.values():
            raise UserError(f'the ack topic {opts.ack_topic} is also played from the bag: '
                            'the player would acknowledge itself (use --topics or --remap)')
        if self.reader.start_ns is None:
            raise UserError(f'bag {self.reader.path} holds no messages')
        self.start_ns = self.reader.start_ns + round(opts.start_offset_s * NS_PER_S)
        if self.start_ns > self.reader.end_ns:
            length = (self.reader.end_ns - self.reader.start_ns) / NS_PER_S
            raise UserError(f'--start-offset {opts.start_offset_s} s is past the end of the '
                            f'bag ({length:.3f} s long)')
        self.end_ns = (self.start_ns + round(opts.duration_s * NS_PER_S)
                       if opts.duration_s is not None else None)  # exclusive
        self._cond = threading.Condition()
        self._ack_count = 0
        self._ack_stamp_ns = None
        self._ack_stamped = False
        self._republish = threading.Event()
        self._ack_deadline = {}       # lockstep: frame index -> when its ack timeout ends
        self._publishers = {}
        self.result: Optional[PlaybackResult] = None   # while and after playing
        self._played_s = 0.0
        self._window_s = None

    def position(self) -> str:
        """How far playback got, in words: 'at 5.2 s of the bag's 20.0 s (42 frames published)'."""
        if self.result is None:
            return 'before the first frame'
        span = f' of the bag\'s {self._window_s:.1f} s' if self._window_s is not None else ''
        return (f'at {self._played_s:.1f} s{span} ({self.result.frames} frames, '
                f'{self.result.messages} messages published)')

    def request_republish(self):
        """Lockstep: publish the frame being waited for again (thread-safe), and keep doing so
        every REPUBLISH_PERIOD_S until it is acknowledged. A restarted worker's nodes lost the
        frame; the nodes that have it ignore a copy (same stamp)."""
        self._republish.set()

    def subscription_count(self, topic: str) -> int:
        """Subscribers matched to the player's publisher of a (published) topic; 0 once the
        player has destroyed it (the end of play, while a rebalance in the coordinator's
        background thread may still wait on a moved quarter's link)."""
        from rclpy.exceptions import InvalidHandle
        pub = self._publishers.get(topic)
        try:
            return pub.get_subscription_count() if pub is not None else 0
        except InvalidHandle:
            return 0

    def _trigger_topics(self):
        opts = self.options
        if not opts.lockstep:
            return []
        if opts.lockstep_topics:
            missing = [t for t in opts.lockstep_topics if t not in self.topics]
            if missing:
                raise UserError(f'lockstep topic(s) not played: {", ".join(missing)}')
            return list(opts.lockstep_topics)
        found = [t for t in self.topics if any(fnmatchcase(t, p) for p in DEFAULT_LOCKSTEP_PATTERNS)]
        if not found:
            raise UserError(f'lockstep: no {" or ".join(DEFAULT_LOCKSTEP_PATTERNS)} topic among the played '
                            'topics; name the trigger topics with --lockstep-topics')
        return found

    def frames(self) -> Iterator[Frame]:
        """The frames of the selected window and topics, in order (no ROS needed)."""
        msgs = self.reader.messages(self.topics, start_ns=self.start_ns, end_ns=self.end_ns)
        # Rate mode plays by the bag's clock: each message at its own log time.
        opts = self.options
        window_ns = round(opts.sync_window_s * NS_PER_S) if opts.lockstep else 0
        return group_frames(msgs, self.trigger_topics, window_ns)

    # ---- the rclpy shell ----------------------------------------------------------------

    def play(self, node_or_context=None) -> PlaybackResult:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        own_node = not isinstance(node_or_context, Node)
        node = (Node('ego_motion_player', context=node_or_context) if own_node
                else node_or_context)
        executor = None
        if node.executor is None:
            executor = SingleThreadedExecutor(context=node.context)
            executor.add_node(node)
        self._executor = executor
        self._t_created = time.monotonic()
        entities = []
        try:
            return self._play_on(node, entities)
        finally:
            if executor is not None:
                executor.remove_node(node)
                executor.shutdown(timeout_sec=0)
            for kind, entity in entities:
                (node.destroy_publisher if kind == 'pub' else node.destroy_subscription)(entity)
            if own_node:
                node.destroy_node()

    def _play_on(self, node, entities) -> PlaybackResult:
        from rclpy.serialization import serialize_message
        from rosgraph_msgs.msg import Clock

        from multicam_ego_motion.bag.message_types import message_class
        from multicam_ego_motion.bag.topic_qos import publishing_qos
        opts, log = self.options, node.get_logger()
        publishers = {}
        for topic in self.topics:
            name = self.published_name[topic]
            pub = node.create_publisher(message_class(self.reader.topics[topic]), name,
                                        publishing_qos(name))
            entities.append(('pub', pub))
            publishers[topic] = pub
            self._publishers[name] = pub
        clock_pub = None
        if opts.clock:
            clock_pub = node.create_publisher(Clock, '/clock', publishing_qos('/clock', depth=10))
            entities.append(('pub', clock_pub))
        if opts.lockstep:
            ack_sub = self._subscribe_ack(node)
            if ack_sub is not None:
                entities.append(('sub', ack_sub))
        self._wait_for_subscribers(node, publishers)

        result = PlaybackResult(per_topic={self.published_name[t]: 0 for t in self.topics})
        t0_wall = time.monotonic()
        end_ns = self.end_ns if self.end_ns is not None else self.reader.end_ns + 1
        window_s = (min(end_ns, self.reader.end_ns + 1) - self.start_ns) / NS_PER_S
        self.result, self._window_s = result, window_s
        bar = _progress_bar(window_s, opts.progress)
        done_s = 0.0
        clock = Clock()
        acked_trigger = None          # index of the last acknowledged trigger frame
        depth = opts.lockstep_depth if self._ack_stamped else 1
        in_flight = deque()           # trigger frames published, not yet acknowledged
        trigger_set = set(self.trigger_topics)
        first_seen = set()            # trigger topics published before the first ack
        any_acked = False
        ahead = 0                     # frames let out beyond the depth while the oldest stalls
        self._ack_deadline.clear()
        read_error = []

        def frames():
            # A bag that turns out damaged mid-way ends playback, but only after the frames
            # already published were acknowledged: their output must not be lost.
            try:
                yield from self.frames()
            except UserError as e:
                read_error.append(e)
        try:
            for frame in frames():
                if acked_trigger is not None and opts.between_frames is not None:
                    opts.between_frames(acked_trigger)
                acked_trigger = None
                if not opts.lockstep:
                    due = t0_wall + (frame.log_time_ns - self.start_ns) / NS_PER_S / opts.rate
                    self._wait(lambda: False, due - time.monotonic())
                with self._cond:
                    acks_before = self._ack_count
                if clock_pub is not None:
                    clock.clock.sec, clock.clock.nanosec = divmod(frame.log_time_ns, NS_PER_S)
                    clock_pub.publish(serialize_message(clock))
                for msg in frame.messages:
                    publishers[msg.topic].publish(bytes(msg.data))
                    result.per_topic[self.published_name[msg.topic]] += 1
                if frame.is_trigger or not opts.lockstep:
                    result.published_at.setdefault(frame.stamp_ns if frame.is_trigger else frame.log_time_ns,
                                                   time.monotonic())
                result.messages += len(frame.messages)
                result.frames += 1
                if opts.lockstep and frame.is_trigger:
                    in_flight.append(frame)
                    first_seen.update(m.topic for m in frame.messages if m.topic in trigger_set)
                    # The first frame alone: the graph's first answer shows it is listening.
                    # Free-running cameras: up to the first image of every camera (within the
                    # depth), as the general arbiter fuses the first estimate once every camera
                    # has reported one at or after it.
                    first_limit = 1 if first_seen >= trigger_set else depth
                    while len(in_flight) >= (depth + ahead if any_acked else first_limit):
                        stall_s = (opts.stall_ahead_s if opts.stall_ahead_s > 0 and any_acked
                                   and ahead < STALL_AHEAD_FRAMES else None)
                        n = self._await_ack(in_flight, acks_before, publishers, stall_s)
                        if n is None:           # stalled: let the next frame out
                            ahead += 1
                            result.published_ahead += 1
                            break
                        result.republished += n
                        acked_trigger = in_flight.popleft().index
                        any_acked, ahead = True, 0
                now_s = (frame.log_time_ns - self.start_ns) / NS_PER_S
                bar.update(now_s - done_s)
                done_s = self._played_s = now_s
            while in_flight:
                result.republished += self._await_ack(in_flight, acks_before, publishers)
                in_flight.popleft()
            if read_error:
                raise read_error[0]
        finally:
            bar.close()
        result.wall_time_s = time.monotonic() - t0_wall
        log.info(f'played {result.messages} messages in {result.frames} frames '
                 f'in {result.wall_time_s:.2f} s'
                 + (f' ({result.published_ahead} let out while an older frame stalled)'
                    if result.published_ahead else ''))
        return result

    def _subscribe_ack(self, node):
        from multicam_ego_motion.bag.header_stamp import has_header, header_stamp_ns
        from multicam_ego_motion.bag.message_types import message_class
        from multicam_ego_motion.bag.topic_qos import subscribing_qos
        ack = self.options.ack_topic
        # Discovery, not the graph's frame time, bounds how long finding the publisher takes.
        if not self._wait(lambda: node.get_publishers_info_by_topic(ack),
                          max(self.options.ack_timeout_s, self.options.discovery_timeout_s)):
            raise UserError(f'lockstep: nothing publishes the ack topic {ack} within '
                            f'{max(self.options.ack_timeout_s, self.options.discovery_timeout_s):g} s (is the graph running?)')
        infos = node.get_publishers_info_by_topic(ack)
        typename = infos[0].topic_type
        stamped = self._ack_stamped = has_header(typename)

        def on_ack(data):
            with self._cond:
                self._ack_count += 1
                if stamped:
                    stamp = header_stamp_ns(data)
                    if self._ack_stamp_ns is None or stamp > self._ack_stamp_ns:
                        self._ack_stamp_ns = stamp
                self._cond.notify_all()

        if self.options.ack_source is not None:
            self.options.ack_source(on_ack)
            return None
        return node.create_subscription(message_class(typename), ack, on_ack,
                                        subscribing_qos(i.qos_profile for i in infos), raw=True)

    def _wait_for_subscribers(self, node, publishers):
        """Wait until every known subscriber of a played topic is matched to our publisher."""
        opts = self.options
        if opts.lockstep:
            triggers = [publishers[t] for t in self.trigger_topics]
            if not self._wait(lambda: all(p.get_subscription_count() for p in triggers),
                              opts.ack_timeout_s):
                raise UserError('lockstep: nothing subscribes to '
                                f'{", ".join(self.published_name[t] for t in self.trigger_topics)}'
                                f' within {opts.ack_timeout_s:g} s')

        def all_matched():
            return all(pub.get_subscription_count() >= node.count_subscribers(pub.topic_name)
                       for pub in publishers.values())
        # A fresh participant knows no subscriber yet: listen first, then wait for the matches.
        self._wait(lambda: False, opts.discovery_s - (time.monotonic() - self._t_created))
        if not self._wait(all_matched, opts.discovery_timeout_s):
            node.get_logger().warning('not every subscriber matched before playback started')
        # Our writer matching a reader does not mean that reader has matched us yet; a sample
        # sent before it has is dropped by it (rate mode lost its first message that way).
        self._wait(lambda: False, MATCH_SETTLE_S)

    def _await_ack(self, in_flight, acks_before: int, publishers=None, stall_s=None) -> Optional[int]:
        """Wait for the acknowledgement of the oldest frame in flight; returns how often the
        frames in flight were published again, or None when `stall_s` passed without it
        (the frame's ack timeout keeps running from its first wait)."""
        opts = self.options
        frame = in_flight[0]
        deadlines = self._ack_deadline

        def acknowledged():
            if self._ack_stamped:
                return self._ack_stamp_ns is not None and self._ack_stamp_ns >= frame.stamp_ns
            return self._ack_count > acks_before  # ack type without a header

        def acknowledged_or_restart():
            return acknowledged() or self._republish.is_set()

        deadline = deadlines.setdefault(frame.index, time.monotonic() + opts.ack_timeout_s)
        republished = 0
        if stall_s is not None and not self._wait(acknowledged_or_restart, min(stall_s, deadline - time.monotonic())) \
                and time.monotonic() < deadline:
            return None
        while self._wait(acknowledged_or_restart, deadline - time.monotonic()):
            if acknowledged():
                deadlines.pop(frame.index, None)
                return republished
            if republished == 0:
                # The restored graph gets the whole timeout from its restore on.
                deadline = time.monotonic() + opts.ack_timeout_s
            elif time.monotonic() > deadline:
                break       # (the flag stays set: without this the loop never ended)
            # A worker was restarted: again, until the frame is acknowledged (a copy sent
            # before the restored nodes were matched is lost for them).
            for f in in_flight:
                for msg in f.messages:
                    publishers[msg.topic].publish(bytes(msg.data))
            republished += 1
            if self._wait(acknowledged, REPUBLISH_PERIOD_S):
                self._republish.clear()
                deadlines.pop(frame.index, None)
                return republished
        topics = sorted({m.topic for m in frame.messages if m.topic in self.trigger_topics})
        raise UserError(
            f'lockstep: frame {frame.index} (stamp {frame.stamp_ns / NS_PER_S:.9f} s, '
            f'{", ".join(topics)}) was not acknowledged on {opts.ack_topic} within '
            f'{opts.ack_timeout_s:g} s')

    def _wait(self, predicate, timeout_s: float) -> bool:
        """Spin (own executor) or sleep (someone else spins) until predicate() or timeout."""
        deadline = time.monotonic() + max(timeout_s, 0.0)
        next_check = time.monotonic() + 0.5
        while True:
            with self._cond:
                if predicate():
                    return True
            now = time.monotonic()
            if self.options.health_check is not None and now >= next_check:
                self.options.health_check()
                next_check = now + 0.5
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            if self._executor is not None:
                self._executor.spin_once(timeout_sec=min(remaining, 0.05))
            else:
                with self._cond:
                    self._cond.wait(min(remaining, 0.05))


def _progress_bar(total_s: float, enabled: Optional[bool]):
    from tqdm import tqdm
    return tqdm(total=round(total_s, 3), unit='bag s', file=sys.stderr, leave=False,
                disable=None if enabled is None else not enabled,
                bar_format='{l_bar}{bar}| {n:.1f}/{total:.1f} bag s [{elapsed}<{remaining}]')


# ---- command line ---------------------------------------------------------------------

def configure_parser(parser: argparse.ArgumentParser):
    parser.add_argument('bag', help='bag folder (metadata.yaml + .mcap) or .mcap file')
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument('--lockstep', action='store_true',
                      help='publish the next frame when the graph acknowledged the last one')
    mode.add_argument('--rate', type=float, default=1.0, help='playback rate (default 1.0)')
    parser.add_argument('--ack-topic', default='/odom',
                        help='lockstep: topic whose header.stamp acknowledges a frame')
    parser.add_argument('--ack-timeout', type=float, default=30.0, metavar='S',
                        help='lockstep: seconds to wait for an acknowledgement (default 30)')
    parser.add_argument('--lockstep-depth', type=int, default=1, metavar='N',
                        help='lockstep: frames published before the oldest is acknowledged '
                             '(default 1; 2 lets a pipelining graph work ahead)')
    parser.add_argument('--stall-ahead', type=float, default=STALL_S, metavar='S',
                        help=f'lockstep: a frame not acknowledged after S seconds lets the next '
                             f'frame out, up to {STALL_AHEAD_FRAMES} more (a sample stuck in the transport '
                             f'comes with the next one; default {STALL_S:g}, 0: never)')
    parser.add_argument('--lockstep-topics', nargs='+', metavar='TOPIC',
                        help=f'lockstep trigger topics (default: every {" and ".join(DEFAULT_LOCKSTEP_PATTERNS)})')
    parser.add_argument('--sync-window', type=float, default=0.0, metavar='S',
                        help='lockstep, free-running cameras: images within S seconds of a '
                             'frame\'s first are one frame (the general arbiter\'s sync_window_s; '
                             'default 0: identical stamps)')
    parser.add_argument('--remap', nargs='+', default=[], metavar='FROM:=TO',
                        help='publish bag topic FROM as TO')
    parser.add_argument('--start-offset', type=float, default=0.0, metavar='S',
                        help='skip the first S seconds of the bag')
    parser.add_argument('--duration', type=float, metavar='S',
                        help='play only S seconds (from the start offset)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC', help='play only these topics')
    parser.add_argument('--discovery', type=float, default=1.0, metavar='S',
                        help='listen to the graph S seconds before the first frame (default 1)')
    parser.add_argument('--clock', action=argparse.BooleanOptionalAction, default=True,
                        help='publish /clock with the bag time (default on)')
    parser.add_argument('--progress', action=argparse.BooleanOptionalAction, default=None,
                        help='progress bar on stderr (default: when stderr is a terminal)')


def options_from_args(args) -> PlayOptions:
    return PlayOptions(lockstep=args.lockstep, rate=args.rate, ack_topic=args.ack_topic,
                       ack_timeout_s=args.ack_timeout, lockstep_topics=args.lockstep_topics,
                       lockstep_depth=args.lockstep_depth, stall_ahead_s=args.stall_ahead,
                       sync_window_s=args.sync_window,
                       remap=parse_remaps(args.remap), start_offset_s=args.start_offset,
                       duration_s=args.duration, topics=args.topics, clock=args.clock,
                       progress=args.progress, discovery_s=args.discovery)


def run(args) -> int:
    player = BagPlayer(args.bag, options_from_args(args))  # bad input fails before ROS starts
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from multicam_ego_motion import interrupt
    # The signals are interrupt.py's (the command line installed it): rclpy's own handlers
    # would shut the context down under the waiting player instead.
    interrupt.note(progress=player.position, kept=f'nothing written (play only publishes {args.bag})')
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        player.play()  # logs the summary line through the ROS logger
    finally:
        with interrupt.deferred():
            rclpy.try_shutdown()
    return 0
