"""The bag player: lockstep delivery, remap, time window, rate timing, bad input."""
import re
import time

import pytest
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from conftest import SpinningNode, run_cli
from multicam_ego_motion.bag.player import BagPlayer, PlayOptions, parse_remaps
from multicam_ego_motion.bag.rosbag2_writer import Rosbag2Writer
from multicam_ego_motion.errors import UserError

T0 = 1_700_000_000 * 10**9
PERIOD = 100_000_000          # 10 frames per second
N_FRAMES = 11                 # 0.0 .. 1.0 s
CAMERAS = ('/cam_front', '/cam_back')


def _stamped(cls, t_ns):
    msg = cls()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 10**9)
    return msg


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """Per frame: two 4x4 images + one camera_info (same log time); a chatter message in between."""
    path = tmp_path_factory.mktemp('bags') / 'synthetic'
    with Rosbag2Writer(path) as w:
        for k in range(N_FRAMES):
            t = T0 + k * PERIOD
            for cam in CAMERAS:
                img = _stamped(Image, t)
                img.height = img.width = 4
                img.encoding, img.step, img.data = 'mono8', 4, bytes([k] * 16)
                w.write(f'{cam}/image_raw', img, t)
            w.write('/cam_front/camera_info', _stamped(CameraInfo, t), t)
            w.write('/chatter', String(data=f'msg {k}'), t + PERIOD // 2)
    return path


def _key(topic, msg):
    """What identifies a message of the synthetic bag."""
    if isinstance(msg, String):
        return msg.data
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def _expected(bag, player_options=None):
    player = BagPlayer(bag, player_options or PlayOptions())
    out = {}
    for frame in player.frames():
        for m in frame.messages:
            out.setdefault(m.topic, []).append(_key(m.topic, m.decode()))
    return out


class Recipient(SpinningNode):
    """Subscribes to every played topic; in lockstep, acks a frame once all cameras arrived."""

    TYPES = {'/chatter': String, '/talk': String, '/cam_front/camera_info': CameraInfo,
             **{f'{c}/image_raw': Image for c in CAMERAS}}

    def __init__(self, topics, ack=False):
        super().__init__('recipient')
        from nav_msgs.msg import Odometry
        self.received = {t: [] for t in topics}
        self.images_per_stamp = {}
        self.ack_pub = self.node.create_publisher(Odometry, '/odom', 10) if ack else None
        qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        for t in topics:
            self.node.create_subscription(self.TYPES[t], t, lambda m, t=t: self.on_msg(t, m), qos)

    def on_msg(self, topic, msg):
        from nav_msgs.msg import Odometry
        with self.lock:
            self.received[topic].append(_key(topic, msg))
            if self.ack_pub is None or not topic.endswith('/image_raw'):
                return
            stamp = _key(topic, msg)
            self.images_per_stamp[stamp] = self.images_per_stamp.get(stamp, 0) + 1
            if self.images_per_stamp[stamp] == len(CAMERAS):
                odom = Odometry()
                odom.header.stamp = msg.header.stamp
                self.ack_pub.publish(odom)


def test_frames_group_messages_by_log_time(bag):
    frames = list(BagPlayer(bag, PlayOptions(lockstep=True)).frames())
    assert len(frames) == 2 * N_FRAMES  # camera frames and chatter frames alternate
    cam = frames[0]
    assert sorted(m.topic for m in cam.messages) == [
        '/cam_back/image_raw', '/cam_front/camera_info', '/cam_front/image_raw']
    assert cam.stamp_ns == T0 and cam.is_trigger
    assert not frames[1].is_trigger and frames[1].messages[0].topic == '/chatter'


def test_start_offset_and_duration_select_the_window(bag):
    # [0.25 s, 0.75 s): camera frames 3..7 at 0.3..0.7 s, chatter 2..6 at 0.25..0.65 s
    player = BagPlayer(bag, PlayOptions(start_offset_s=0.25, duration_s=0.5))
    got = {}
    for frame in player.frames():
        for m in frame.messages:
            got.setdefault(m.topic, []).append(_key(m.topic, m.decode()))
    assert got['/cam_front/image_raw'] == [T0 + k * PERIOD for k in range(3, 8)]
    assert got['/chatter'] == [f'msg {k}' for k in range(2, 7)]


def test_lockstep_delivers_every_message_once_in_order(bag, rclpy_context):
    expected = _expected(bag)
    recipient = Recipient(list(expected), ack=True)
    try:
        proc = run_cli('play', bag, '--lockstep', '--ack-timeout', '10', timeout=60)
        assert proc.returncode == 0, proc.stderr
        time.sleep(0.3)  # let the last non-trigger messages arrive
        with recipient.lock:
            assert recipient.received == expected
        assert f'played {sum(map(len, expected.values()))} messages in {2 * N_FRAMES} frames' \
            in proc.stderr
    finally:
        recipient.close()


class LaggingRecipient(Recipient):
    """Acknowledges frame k only once frame k + 1 arrived (the first and the last at once),
    as a graph that is busy with a frame when the next one comes; records a third frame
    arriving while two are unacknowledged."""

    def __init__(self, topics):
        super().__init__(topics, ack=False)
        from nav_msgs.msg import Odometry
        self.ack_pub = self.node.create_publisher(Odometry, '/odom', 10)
        self.complete, self.acked, self.too_many = [], set(), []

    def reset(self):
        """Forget the frames of a playback (not what was received), for the next one."""
        with self.lock:
            self.images_per_stamp.clear()
            self.complete, self.acked = [], set()

    def on_msg(self, topic, msg):
        from nav_msgs.msg import Odometry
        with self.lock:
            self.received[topic].append(_key(topic, msg))
            if not topic.endswith('/image_raw'):
                return
            stamp = _key(topic, msg)
            self.images_per_stamp[stamp] = self.images_per_stamp.get(stamp, 0) + 1
            if self.images_per_stamp[stamp] < len(CAMERAS):
                return
            if len([s for s in self.complete if s not in self.acked]) >= 2:
                self.too_many.append(stamp)
            self.complete.append(stamp)
            due = [s for s in self.complete[:-1] if s not in self.acked]
            if stamp in (T0, T0 + (N_FRAMES - 1) * PERIOD):
                due.append(stamp)
            for s in due:
                odom = Odometry()
                odom.header.stamp.sec, odom.header.stamp.nanosec = divmod(s, 10**9)
                self.ack_pub.publish(odom)
                self.acked.add(s)


def _play_lagging(bag, recipient, *args):
    """Play the bag in lockstep into a LaggingRecipient: every message once and in order.
    Returns the player's stderr."""
    recipient.reset()
    proc = run_cli('play', bag, '--lockstep', *args, timeout=120)
    assert proc.returncode == 0, proc.stderr
    time.sleep(0.3)
    with recipient.lock:
        assert recipient.received == _expected(bag)
        assert recipient.complete == [T0 + k * PERIOD for k in range(N_FRAMES)]
    return proc.stderr


def _depth_one_without_stall_ahead_waits_for_ever(bag, recipient):
    recipient.reset()
    proc = run_cli('play', bag, '--lockstep', '--ack-timeout', '2', '--stall-ahead', '0', timeout=60)
    assert proc.returncode != 0 and 'frame 2 ' in proc.stderr \
        and 'was not acknowledged' in proc.stderr, proc.stderr


def test_lockstep_depth_two_sends_the_next_frame_before_the_ack(bag, rclpy_context):
    """--lockstep-depth 2: a graph that answers frame k only after frame k + 1 arrived is
    served (depth 1 would wait for it forever), never more than two frames ahead, every
    message once and in order."""
    recipient = LaggingRecipient(list(_expected(bag)))
    try:
        _play_lagging(bag, recipient, '--lockstep-depth', '2', '--ack-timeout', '10')
        with recipient.lock:
            assert recipient.too_many == []
        _depth_one_without_stall_ahead_waits_for_ever(bag, recipient)
    finally:
        recipient.close()


def test_lockstep_lets_the_next_frame_out_when_a_frame_stalls(bag, rclpy_context):
    """A frame whose sample sits in the transport until the next one on its topic is written
    (the recipient sees frame k only with frame k + 1) is not waited for until the ack timeout:
    after --stall-ahead the next frame goes out, which brings it. Every message once and in
    order."""
    recipient = LaggingRecipient(list(_expected(bag)))
    try:
        err = _play_lagging(bag, recipient, '--ack-timeout', '20', '--stall-ahead', '0.3')
        # frames 1 .. N - 2 each waited for the next one (frame 0 and the last are acked at once)
        assert f'({N_FRAMES - 2} let out while an older frame stalled)' in err, err
        _depth_one_without_stall_ahead_waits_for_ever(bag, recipient)
    finally:
        recipient.close()


def test_lockstep_without_acknowledgement_names_the_frame(bag, rclpy_context):
    from nav_msgs.msg import Odometry
    silent = SpinningNode('silent_graph')  # publishes /odom but never acknowledges
    silent.node.create_publisher(Odometry, '/odom', 10)
    silent.node.create_subscription(Image, '/cam_front/image_raw', lambda m: None, 10)
    try:
        proc = run_cli('play', bag, '--lockstep', '--ack-timeout', '1',
                       '--topics', '/cam_front/image_raw', timeout=60)
    finally:
        silent.close()
    assert proc.returncode == 2
    assert 'Traceback' not in proc.stderr
    assert re.search(r'frame 0 \(stamp 1700000000\.000000000 s, /cam_front/image_raw\) was not '
                     r'acknowledged on /odom within 1 s', proc.stderr), proc.stderr


def test_rate_mode_timing_and_remap(bag, rclpy_context):
    recipient = Recipient(['/talk', '/chatter'])
    try:
        # Rate mode publishes whether or not anyone listens (like ros2 bag play): give a
        # loaded machine time to discover the recipient first.
        proc = run_cli('play', bag, '--rate', '2', '--remap', '/chatter:=/talk',
                       '--topics', '/chatter', '--discovery', '8', timeout=60)
        assert proc.returncode == 0, proc.stderr
        time.sleep(0.3)
        with recipient.lock:
            assert recipient.received['/talk'] == [f'msg {k}' for k in range(N_FRAMES)]
            assert recipient.received['/chatter'] == []
    finally:
        recipient.close()
    # chatter spans 1.0 s of bag time, 0.5 s at rate 2: the player paces (never faster than
    # that); how much slower a loaded host makes it is not a test bound
    wall = float(re.search(r'in ([0-9.]+) s', proc.stderr).group(1))
    assert wall >= 0.45, proc.stderr


def test_parse_remaps_rejects_malformed_rules():
    assert parse_remaps(['/a:=/b']) == {'/a': '/b'}
    with pytest.raises(UserError):
        parse_remaps(['/a=/b'])


@pytest.mark.parametrize('case', ['missing bag', 'corrupt bag', 'missing topic', 'negative stall'])
def test_bad_input_is_one_line_error(case, bag, tmp_path):
    if case == 'missing bag':
        args, expect = [tmp_path / 'nope'], 'bag not found'
    elif case == 'corrupt bag':
        corrupt = tmp_path / 'corrupt.mcap'
        corrupt.write_bytes(b'\x89MCAP0\r\n' + b'garbage' * 100)
        args, expect = [corrupt], 'is corrupt'
    elif case == 'missing topic':
        args, expect = [bag, '--topics', '/nope'], 'has no topic /nope'
    else:
        args, expect = [bag, '--lockstep', '--stall-ahead', '-1'], '--stall-ahead must be >= 0 seconds'
    proc = run_cli('play', *args, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and expect in lines[0] and lines[0].startswith('ego-motion: error:'), \
        proc.stderr



def test_subscription_counts_after_play_are_zero_not_an_error(bag, rclpy_context):
    # The end of play destroys the publishers while the coordinator's background rebalance
    # may still wait on a moved quarter's image subscription (make_link_waiter): that read
    # raised InvalidHandle in the coordinator's thread, at the end of a rate-mode replay.
    player = BagPlayer(bag, PlayOptions(rate=20.0, discovery_s=0.0, discovery_timeout_s=0.0,
                                        topics=['/chatter'], clock=False))
    result = player.play(rclpy_context)
    assert result.messages == N_FRAMES
    assert player.subscription_count('/chatter') == 0
