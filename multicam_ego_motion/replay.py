"""`ego-motion replay BAG --out DIR`: start the whole graph, play the bag through it, record
what it publishes, and score the odometry against the bag's ground truth.

Writes DIR/output (rosbag2 MCAP: /odom, /tf, quarter and camera estimates, /diagnostics;
with --debug-images also each camera's /<cam>/tracks), DIR/odometry.tum, and when the bag has
ground truth DIR/report.md with plots.
"""
import os
import signal
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional

from multicam_ego_motion import interrupt
from multicam_ego_motion.bag.player import STALL_S
from multicam_ego_motion.errors import UserError


def configure_parser(p):
    p.add_argument('bag', help='rosbag2 MCAP bag (folder) to replay')
    p.add_argument('--out', required=True, help='output folder')
    p.add_argument('--rig', help='rig YAML (default: BAG/rig.yaml, else built from /tf_static)')
    p.add_argument('--params', help="ROS params file (default: the package's config/params.yaml)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument('--lockstep', action='store_true', default=True,
                      help='next frame only when the graph has published /odom for the last (default)')
    mode.add_argument('--rate', type=float, help='real-time factor, like ros2 bag play --rate')
    p.add_argument('--workers', type=int, default=os.cpu_count(), help='worker processes (M)')
    p.add_argument('--ground-truth-topic', default='/ground_truth/odom')
    p.add_argument('--ack-timeout', type=float, default=120.0, help='lockstep: longest wait per frame [s]')
    p.add_argument('--no-wheel', action='store_true', help='do not fuse /wheel/odom')
    imu = p.add_mutually_exclusive_group()
    imu.add_argument('--imu', action='store_true', help='fuse the rig\'s IMU (/imu/data; the general arbiter\'s use_imu)')
    imu.add_argument('--no-imu', action='store_true', help='do not fuse it (whatever the params file says)')
    p.add_argument('--start-offset', type=float, default=0.0, help='skip this much of the bag [s]')
    p.add_argument('--duration', type=float, help='play only this much of the bag [s]')
    p.add_argument('--no-rebalance', action='store_true', help='keep the start allocation')
    p.add_argument('--lockstep-depth', type=int, default=None, metavar='N',
                   help=f'lockstep: frames in flight (default {LOCKSTEP_DEPTH}: the graph pipelines; '
                        'free-running cameras: one more than the cameras; the odometry is the same '
                        'for any N that does not stall)')
    p.add_argument('--stall-ahead', type=float, default=STALL_S, metavar='S',
                   help=f'lockstep: a frame not acknowledged after S seconds lets the next one out, '
                        f'which brings a sample DDS lost at discovery (default {STALL_S:g}; 0: never)')
    p.add_argument('--migrate-every', type=int, default=0, metavar='K',
                   help='debug (lockstep): move one quarter node to the next worker every K frames')
    p.add_argument('--kill-worker-at', type=int, default=None, metavar='N',
                   help='debug (lockstep): SIGKILL the last worker once N frames were acknowledged, '
                        'as a crash would (a crash-recovery drill at a chosen frame)')
    p.add_argument('--sync-window', type=float, default=None, metavar='S',
                   help='optional, free-running cameras: images within S seconds are one frame, '
                        'fused at its latest stamp (the general arbiter\'s sync_window_s, and the '
                        'lockstep player\'s frames; default: the params file\'s value, 0: each '
                        'camera fused at its own stamp)')
    add_remote_arguments(p)
    p.add_argument('--debug-images', action='store_true',
                   help='draw the tracker (the nodes\' debug_images parameter) and record each '
                        'camera\'s /<cam>/tracks: features, flow, landmark/epipolar status')


def add_remote_arguments(p):
    """Remote workers (coordinator.py): the TCP address to listen on and how many of the M
    workers join from other hosts; the key from a file or $EGO_MOTION_CONTROL_KEY."""
    p.add_argument('--listen', metavar='HOST:PORT',
                   help='accept workers from other hosts on this TCP address (`worker --coordinator HOST:PORT`)')
    p.add_argument('--remote-workers', type=int, default=0, metavar='R',
                   help='of the --workers, R join over --listen (the coordinator waits for them)')
    p.add_argument('--key-file', help='the control channel\'s shared key (default: $EGO_MOTION_CONTROL_KEY); '
                                      'needed with --listen')


def remote_options(args) -> dict:
    from multicam_ego_motion.coordinator import control
    if not getattr(args, 'listen', None):
        if getattr(args, 'remote_workers', 0):
            raise UserError('--remote-workers needs --listen HOST:PORT')
        return {}
    return {'listen': args.listen, 'remote_workers': args.remote_workers,
            'key': control.load_key(args.key_file)}


def resolve_rig(bag_reader, rig_arg):
    from multicam_ego_motion.bag.rig_from_tf import rig_from_bag
    from multicam_ego_motion.geometry.rig import load_rig
    if rig_arg:
        rig, path = load_rig(rig_arg), Path(rig_arg)
    elif (Path(bag_reader.path) / 'rig.yaml').exists():
        path = Path(bag_reader.path) / 'rig.yaml'
        rig = load_rig(path)
    else:
        rig, path = rig_from_bag(bag_reader), None
    found = with_detected_stereo_pairs(bag_reader, with_bag_imu(bag_reader, with_bag_transports(bag_reader, rig)))
    if found is rig or path is None:
        return found, path
    # the nodes read the rig file: a rig completed from the bag goes to a new file
    out = Path(tempfile.mkdtemp(prefix='ego_motion_rig_')) / 'rig.yaml'
    found.save(out)
    return found, out


def with_bag_imu(bag_reader, rig):
    """The bag's IMU (bag/imu_mount.py) when the rig names none."""
    from multicam_ego_motion.bag.imu_mount import with_bag_imu as find
    rig, said = find(bag_reader, rig)
    if said:
        print(f'rig: {said}', flush=True)
    return rig


def with_bag_transports(bag_reader, rig):
    """Each camera's images as the bag has them, raw or compressed (bag/image_transport.py)."""
    from multicam_ego_motion.bag.image_transport import with_bag_transports as choose
    rig, said = choose(bag_reader, rig)
    for line in said:
        print(f'rig: {line}', flush=True)
    return rig


def with_detected_stereo_pairs(bag_reader, rig):
    """A rig that names no stereo_pairs gets those found from its extrinsics and the bag's
    first CameraInfo of each camera (stereo_match.overlapping_pairs)."""
    from dataclasses import replace

    from camera_pose_nodes.camera_model import intrinsics_from_msg
    from camera_pose_nodes.stereo_match import overlapping_pairs
    if not rig.detect_stereo or rig.stereo_pairs or len(rig.cameras) < 2:
        return rig
    topics = {c.camera_info_topic: c.name for c in rig.cameras if c.camera_info_topic in bag_reader.topics}
    intrinsics = {}
    for topic, msg, _ in bag_reader.decoded(list(topics)):
        name = topics[topic]
        if name not in intrinsics:
            try:
                intrinsics[name] = intrinsics_from_msg(msg, name)
            except (UserError, ValueError):
                continue      # the quarter reports a bad CameraInfo
        if len(intrinsics) == len(topics):
            break
    pairs = overlapping_pairs(rig, intrinsics)
    if not pairs:
        return rig
    print(f'rig: overlapping cameras found: stereo pairs {", ".join("/".join(p) for p in pairs)} '
          '(name stereo_pairs in the rig file to choose)', flush=True)
    return replace(rig, stereo_pairs=pairs)


def check_camera_topic_types(reader, rig):
    """A camera topic of another type would never match the nodes' subscriptions and the
    lockstep player would wait for them in vain: reject the bag before the graph starts."""
    for cam in rig.cameras:
        for topic, expected in ((cam.input_topic, cam.input_type),
                                (cam.camera_info_topic, 'sensor_msgs/msg/CameraInfo')):
            found = reader.topics.get(topic)
            if found is not None and found != expected:
                raise UserError(f'bag {reader.path}: {topic} holds {found or "messages of no known type"}, '
                                f'expected {expected} (camera {cam.name})')


# Lockstep waits this long for a camera (or quarter) that has not reported a frame before
# calling it absent: normal frames take ~0.2 s, so this only fires for a stream that really
# stopped, even on an oversubscribed machine (5 s did fire there).
LOCKSTEP_SYNC_TIMEOUT_S = 10.0
# Frames in flight in lockstep: the next frame's images reach the quarters while the last
# frame's fused pose is computed, and they track it meanwhile (player.PlayOptions).
LOCKSTEP_DEPTH = 2


def graph_overrides(lockstep: bool, use_wheel: bool, debug_images: bool = False,
                    sync_window_s=None, use_imu: Optional[bool] = None):
    # Lockstep replay waits for everything (deterministic); rate mode must keep going.
    wait = 60.0 if lockstep else 0.3
    general = {'sync_timeout_s': LOCKSTEP_SYNC_TIMEOUT_S if lockstep else 0.2,
               'wheel_wait_s': 2.0 if lockstep else 0.05,
               'imu_wait_s': 2.0 if lockstep else 0.05,
               'tracks_wait_s': 2.0 if lockstep else 0.05,
               'imu_qos': 'reliable' if lockstep else 'sensor_data',
               'use_wheel_odometry': use_wheel,
               # rate mode: the lag behind the frames (frame skipping, max_lag_s) is read on
               # the bag's /clock; lockstep processes every frame
               'use_sim_time': not lockstep}
    if lockstep:
        general['max_lag_s'] = 0.0
        general['odom_rate_hz'] = 0.0     # the player waits for each fused stamp's /odom
    if sync_window_s is not None:     # (left out when not given: the params file's value stands)
        general['sync_window_s'] = float(sync_window_s)
    # (image_transport: the rig replay hands the nodes has each camera's transport as the
    # bag holds it, which a params file's image_transport must not override)
    quarter = {'image_qos': 'reliable' if lockstep else 'sensor_data',
               'feedback_timeout_s': wait, 'image_transport': '',
               # (the quarters steer by the gyro while the general arbiter uses it: gyro_steer)
               'imu_wait_s': general['imu_wait_s'], 'imu_qos': general['imu_qos']}
    if use_imu is not None:           # (likewise)
        general['use_imu'] = quarter['use_imu'] = bool(use_imu)
    overrides = {'quarter': quarter,
                 'camera_arbiter': {'sync_timeout_s': LOCKSTEP_SYNC_TIMEOUT_S if lockstep else 0.2},
                 'general_arbiter': general}
    if debug_images:          # (left out when off: the params file's value stands)
        overrides['quarter']['debug_images'] = True
        overrides['camera_arbiter']['debug_images'] = True
    return overrides


def free_running_depth(reader, rig) -> int:
    """Lockstep frames in flight for the bag's cameras: LOCKSTEP_DEPTH when their stamps
    coincide; with free-running cameras (each image a frame of its own, fused at its own
    stamp) one more than the cameras, so that the images the general arbiter must see before
    it fuses an estimate (the other cameras' next ones, the wheel's next tick) are out before
    the player waits for that estimate's /odom. Cameras at different rates need more at the
    start, while the arbiter waits for a camera until its second image (its period) comes:
    every instant up to that image (capture_spread.start_depth). Says so in one line."""
    from multicam_ego_motion.bag.capture_spread import bag_capture_spread
    spread = bag_capture_spread(reader, [c.input_topic for c in rig.cameras])
    depth = LOCKSTEP_DEPTH
    if spread.spread_ns:
        print(f'replay: {spread.describe()}: free-running, each camera fused at its own stamp',
              flush=True)
        depth = max(depth, len(rig.cameras) + 1)
    if spread.start_frames > depth:
        print(f'replay: cameras at different rates or phases: {spread.start_frames} frames in flight, '
              'so that each camera\'s second image is out while the fusion waits to learn its period',
              flush=True)
        depth = spread.start_frames
    return depth


def recorded_topics(rig, debug_images: bool = False):
    topics = ['/odom', '/tf', '/ego_motion/fused_pose', '/ego_motion/path', '/ego_motion/frame_schedule',
              '/ego_motion/map_scale',
              '/diagnostics']
    for c in rig.cameras:
        topics.append(f'/{c.name}/pose')
        topics += [f'/{c.name}/q{q}/pose' for q in range(1, 5)]
        if debug_images:
            topics.append(f'/{c.name}/tracks')
    return topics


def wait_for_graph(node, rig, bag_reader, coordinator, timeout_s=60.0):
    """Every worker hosting quarters of a present camera subscribed to its images, every
    quarter to its CameraInfo (one missed with the first frames left a camera out of them:
    seen with two frames in flight), and the general arbiter up."""
    deadline = time.monotonic() + timeout_s
    present = [c for c in rig.cameras if c.input_topic in bag_reader.topics]
    quarters = {c.name: sum(1 for s in coordinator.specs.values()
                            if s.kind == 'quarter' and s.parameters.get('camera') == c.name)
                for c in present}
    while time.monotonic() < deadline:
        coordinator.check_alive()
        ok = all(node.count_subscribers(c.input_topic) >= coordinator.image_readers(c.name)
                 and node.count_subscribers(c.camera_info_topic) >= quarters[c.name]
                 for c in present)
        ok = ok and node.count_publishers('/odom') >= 1
        if ok:
            return
        time.sleep(0.2)
    raise UserError(f'the graph did not come up within {timeout_s:.0f} s (see {coordinator.log_dir})')


def peak_rss_kb(pids) -> int:
    """Sum of the peak resident sets (VmHWM) of live processes."""
    total = 0
    for pid in pids:
        try:
            for line in Path(f'/proc/{pid}/status').read_text().splitlines():
                if line.startswith('VmHWM:'):
                    total += int(line.split()[1])
        except (OSError, ValueError):
            pass
    return total


def cpu_seconds(pids) -> float:
    """User + system CPU time [s] of live processes (this one included if in pids)."""
    tick = os.sysconf('SC_CLK_TCK')
    total = 0.0
    for pid in pids:
        try:
            fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
        except (OSError, ValueError, IndexError):
            pass
    return total


@dataclass
class GraphRun:
    counts: dict
    playback: object
    wall_s: float
    total_s: float
    odom_received: Dict[int, float] = field(default_factory=dict)   # stamp -> monotonic s
    peak_rss_kb: int = 0
    coordinator: object = None
    # CPU time [s] used while playing: the workers (the graph) and this process (player,
    # recorder, coordinator). On a shared machine, wall time measures the neighbours too.
    cpu_workers_s: float = 0.0
    cpu_replay_s: float = 0.0

    @property
    def frames_wall_s(self) -> float:
        """First frame published -> last /odom received: the frames' wall time, without the
        player's start-up before them (discovery and matching, 0.5 s or more: about 3 ms a
        frame of a 161-frame lockstep run)."""
        published = getattr(self.playback, 'published_at', None) or {}
        if not published or not self.odom_received:
            return self.wall_s
        return max(self.odom_received.values()) - min(published.values())


def make_link_waiter(rig, player, timeout_s=2.0):
    """For a moved quarter: wait until the player sees the image subscriptions the graph
    has once it is detached, then once attached (`readers`, from the coordinator: one per
    worker hosting that camera's quarters); a frame published before its new worker's
    subscription matched would be lost for it."""
    def wait(spec, phase, readers):
        if spec['kind'] != 'quarter':
            return
        topic = rig.camera(spec['parameters']['camera']).input_topic
        ok = ((lambda: player.subscription_count(topic) <= readers) if phase == 'detached'
              else (lambda: player.subscription_count(topic) >= readers))
        deadline = time.monotonic() + timeout_s
        while not ok() and time.monotonic() < deadline:
            time.sleep(0.002)
    return wait


def _killing(coordinator, at_frame):
    """The coordinator's between-frames hook, which also kills its last worker once."""
    done = []

    def between(frame_index):
        if not done and frame_index >= at_frame:
            done.append(coordinator.workers[-1].proc.pid)
            os.kill(done[0], signal.SIGKILL)
            print(f'replay: killed worker {len(coordinator.workers) - 1} (pid {done[0]}) after frame '
                  f'{frame_index}', flush=True)
        coordinator.between_frames(frame_index)
    return between


def run_graph(bag, out: Path, rig, rig_file, params, workers, lockstep=True, rate=1.0,
              use_wheel=True, ack_timeout=120.0, start_offset=0.0, duration=None,
              migrate_every=0, rebalance=True, logger=print, record_topics=None,
              lockstep_depth=LOCKSTEP_DEPTH, debug_images=False, kill_worker_at=None,
              sync_window_s=None, remote=None, remote_cpu=False, use_imu=None,
              stall_ahead_s=STALL_S) -> GraphRun:
    """Coordinator + in-process player and recorder: one run of the graph over a bag.
    kill_worker_at (lockstep; the bench's crash row): SIGKILL the last worker once this many
    frames were acknowledged, as a crash would. remote: Coordinator keywords for remote
    workers (listen, remote_workers, key); remote_cpu: their processes are on this machine
    (network namespaces, the bench's two-host row) and their CPU counts with the workers'."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rclpy.exceptions import InvalidHandle

    from multicam_ego_motion.bag.header_stamp import header_stamp_ns
    from multicam_ego_motion.bag.player import BagPlayer, PlayOptions
    from multicam_ego_motion.bag.recorder import BagRecorder
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.coordinator.coordinator import Coordinator
    from multicam_ego_motion.ros_plumbing.lean_executor import LeanExecutor
    from multicam_ego_motion.ros_plumbing.lean_node import LeanNode

    from multicam_ego_motion.params_file import sync_window_from

    reader = Rosbag2Reader(bag)
    # The player's lockstep frames must be the general arbiter's groups.
    window = sync_window_from(params) if sync_window_s is None else float(sync_window_s)
    coordinator = Coordinator(rig, Path(rig_file).resolve(), Path(params).resolve(), workers=workers,
                              overrides=graph_overrides(lockstep, use_wheel, debug_images, sync_window_s,
                                                        use_imu),
                              log_dir=out / 'logs',
                              rebalance=rebalance, migrate_every=migrate_every, logger=logger,
                              **(remote or {}))
    # No rclpy signal handlers: on Ctrl-C they invalidate the context under the spinning
    # thread. SIGINT, SIGTERM and SIGHUP raise interrupt.Interrupted here (the command line
    # installs interrupt.handling()), which reaches the finally below: it closes in order.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stopping = threading.Event()
    node = executor = spinner = recorder = player = None
    received = {}
    t_start = time.monotonic()
    result = None
    peak = 0
    wall = 0.0
    out_bag = out / 'output'
    interrupt.note(progress=lambda: 'while starting the graph', kept='nothing recorded yet')
    try:
        with interrupt.deferred():   # every resource below exists, or the finally sees None
            # Player, recorder and coordinator share this node (LeanNode: without the QoS
            # event handlers of its ~25 publishers/subscriptions), spun by a LeanExecutor
            # (rclpy's rebuilt its wait set in Python before each of ~8 waits a frame). Its
            # subscriptions are the recorder's only: created on this thread or in its own
            # callbacks, destroyed after the spinning stopped (the player takes its acks from
            # the recorder), so none goes away under a wait.
            node = LeanNode('ego_motion_replay')
            executor = LeanExecutor()
            executor.add_node(node)

            def spin():
                while not stopping.is_set():
                    try:
                        executor.spin_once(timeout_sec=0.1)
                    except InvalidHandle:
                        # An entity invalidated under the wait (rclpy tearing down on an
                        # error): the next wait set is built without it.
                        continue
                    except Exception:
                        # Tearing down (a signal, end of run) can invalidate more under the
                        # wait set; anything raised before that is a real error.
                        if not stopping.is_set():
                            raise

            spinner = threading.Thread(target=spin, daemon=True, name='spin')
            topics = list(record_topics or recorded_topics(rig, debug_images))
            # /odom is always recorded: the latency clock below and the lockstep player's acks
            # listen on the recorder's subscription (one take a frame for all three)
            recorder = BagRecorder(out_bag, topics=topics + ['/odom'] * ('/odom' not in topics))
            recorder.listen('/odom', lambda data: received.setdefault(header_stamp_ns(data), time.monotonic()))
        coordinator.start()
        # Rate mode has no between-frames moment: rebalancing runs on a timer there.
        coordinator.attach_ros(node, rate_mode_period_s=None if lockstep else 1.0)
        spinner.start()
        recorder.attach(node)
        wait_for_graph(node, rig, reader, coordinator)
        recorder.wait_for_topics(10.0)
        player = BagPlayer(bag, PlayOptions(
            lockstep=lockstep, lockstep_depth=lockstep_depth, rate=rate, ack_topic='/odom',
            ack_timeout_s=ack_timeout, discovery_s=0.5, progress=None, sync_window_s=window,
            start_offset_s=start_offset, duration_s=duration, stall_ahead_s=stall_ahead_s,
            ack_source=lambda fn: recorder.listen('/odom', fn),
            between_frames=(coordinator.between_frames if kill_worker_at is None
                            else _killing(coordinator, kill_worker_at)) if lockstep else None,
            health_check=coordinator.check_alive))
        interrupt.note(progress=player.position)
        coordinator.link_waiter = make_link_waiter(rig, player)
        coordinator.on_restored.append(lambda w: player.request_republish())
        workers = coordinator.worker_pids() + (coordinator.remote_pids() if remote_cpu else [])
        cpu0 = cpu_seconds(workers), cpu_seconds([os.getpid()])
        t_play = time.monotonic()
        result = player.play(node)
        wall = time.monotonic() - t_play
        cpu1 = cpu_seconds(workers), cpu_seconds([os.getpid()])
        time.sleep(0.5 if lockstep else 1.0)  # let the last estimates reach the recorder
        coordinator.check_alive()
        peak = peak_rss_kb(coordinator.worker_pids() + [os.getpid()])
        interrupt.note(progress=lambda: 'after the whole bag was played')
    finally:
        # Closing is never cut short: a signal that comes meanwhile (at the end of a run) is
        # held until everything is closed, later ones are ignored. Stop the spinning thread
        # before the recorder destroys its subscriptions: spinning over destroyed entities
        # raises in that thread (InvalidHandle). The recorder takes what is still queued,
        # then closes.
        with interrupt.deferred():
            stopping.set()
            if executor is not None:
                executor.wake()             # out of its wait; shut down once it has stopped
            if spinner is not None and spinner.is_alive():
                spinner.join(timeout=5.0)
            if executor is not None:
                executor.shutdown()         # (destroys the guard conditions a wait would use)
            counts = recorder.close() if recorder is not None else {}
            if recorder is not None:
                interrupt.note(kept=f'kept {out_bag}: {counts.get("/odom", 0)} /odom, '
                                    f'{sum(counts.values())} messages in all, closed with its '
                                    'summary and metadata.yaml')
            coordinator.stop()
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    cpu = (cpu1[0] - cpu0[0], cpu1[1] - cpu0[1]) if result is not None else (0.0, 0.0)
    return GraphRun(counts, result, wall, time.monotonic() - t_start, received, peak, coordinator, *cpu)


def run(args) -> int:
    from multicam_ego_motion.ros_plumbing import dds_transport, package_share, ros_domain
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    from multicam_ego_motion.replay_summary import summarize

    ros_domain.isolate()
    dds_transport.use_graph_profile()
    out = Path(args.out)
    if (out / 'output').exists():
        raise UserError(f'output folder {out} already holds a replay (output/ exists)')
    reader = Rosbag2Reader(args.bag)
    rig, rig_file = resolve_rig(reader, args.rig)
    check_camera_topic_types(reader, rig)
    missing = [c.name for c in rig.cameras if c.input_topic not in reader.topics]
    if len(missing) == len(rig.cameras):
        raise UserError(f'bag {args.bag} has none of the rig\'s image topics')
    out.mkdir(parents=True, exist_ok=True)
    if rig_file is None:
        rig_file = out / 'rig.yaml'
        rig.save(rig_file)
    params = Path(args.params) if args.params else package_share.default_params()
    if not params.exists():
        raise UserError(f'params file not found: {params}')
    lockstep = args.rate is None
    remote = remote_options(args)
    if args.migrate_every and not lockstep:
        raise UserError('--migrate-every needs lockstep replay')
    if args.kill_worker_at is not None and (not lockstep or args.kill_worker_at < 1):
        raise UserError('--kill-worker-at needs lockstep replay and a frame number >= 1')
    print(f'replay: {args.bag} ({", ".join(rig.names)}; '
          f'{"lockstep" if lockstep else f"rate {args.rate}"}; {args.workers} workers; '
          f'ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]})', flush=True)
    print(f'replay: rig {rig_file}; params {params}', flush=True)
    if missing:
        print(f'replay: cameras without topics in the bag (the graph runs on the others): '
              f'{", ".join(missing)}', flush=True)
    depth = args.lockstep_depth
    if depth is None:
        depth = free_running_depth(reader, rig)
    g = run_graph(args.bag, out, rig, rig_file, params, args.workers, lockstep=lockstep,
                  rate=args.rate or 1.0, use_wheel=not args.no_wheel, ack_timeout=args.ack_timeout,
                  start_offset=args.start_offset, duration=args.duration,
                  migrate_every=args.migrate_every, rebalance=not args.no_rebalance,
                  logger=lambda t: print(t, flush=True), lockstep_depth=depth,
                  debug_images=args.debug_images, sync_window_s=args.sync_window, remote=remote,
                  kill_worker_at=args.kill_worker_at, stall_ahead_s=args.stall_ahead,
                  use_imu=True if args.imu else (False if args.no_imu else None))
    st = g.coordinator.stats
    print(f'coordinator: {st.migrations} migrations ({st.rebalances} rebalances), '
          f'{st.restarts} worker restarts'
          + (f' (restored in {", ".join(f"{t:.2f}" for t in st.restore_s)} s)' if st.restore_s else '')
          + (f', frames re-published {g.playback.republished}' if g.playback else '')
          + (f', frames let out while an older one stalled {g.playback.published_ahead}'
             if g.playback and g.playback.published_ahead else ''), flush=True)
    return summarize(args.bag, reader, out, g.counts, g.playback, g.wall_s, g.total_s,
                     args.ground_truth_topic)
