"""The recorder: after SIGINT, SIGTERM or SIGHUP the bag is complete and holds every message
received; the command says what it kept in one line and exits with 128 + the signal."""
import signal
import time

import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosbags.highlevel import AnyReader
from std_msgs.msg import String

from conftest import SpinningNode, start_cli

N = 50


def _wait(predicate, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=['SIGINT', 'SIGTERM', 'SIGHUP'])
def test_signal_leaves_a_complete_bag(sig, tmp_path, rclpy_context):
    talker = SpinningNode('talker')
    reliable = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    chatter = talker.node.create_publisher(String, '/chatter', reliable)
    # a best-effort sensor-style publisher: the recorder must subscribe best effort to match
    poses = talker.node.create_publisher(PoseStamped, '/pose', qos_profile_sensor_data)
    out = tmp_path / 'recorded'
    rec = start_cli('record', '--topics', '/chatter', '/pose', '/not_yet', '--out', out)
    try:
        assert _wait(lambda: chatter.get_subscription_count() >= 1
                     and poses.get_subscription_count() >= 1, 20), 'recorder never subscribed'
        for i in range(N):
            chatter.publish(String(data=f'hello {i}'))
            pose = PoseStamped()
            pose.pose.position.x = float(i)
            poses.publish(pose)
            time.sleep(0.005)  # best effort: do not outrun a 2-core machine
        time.sleep(1.0)        # reliable delivery of the tail
        rec.send_signal(sig)
        _, err = rec.communicate(timeout=20)
    finally:
        if rec.poll() is None:
            rec.kill()
        talker.close()
    assert rec.returncode == 128 + sig, err
    with AnyReader([out]) as reader:
        got = {}
        for conn, _, raw in reader.messages():
            got.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    assert [m.data for m in got['/chatter']] == [f'hello {i}' for i in range(N)]
    received_poses = len(got.get('/pose', []))
    assert received_poses >= N * 0.8  # best effort may drop a few, not most
    assert [m.pose.position.x for m in got['/pose']] == sorted(m.pose.position.x for m in got['/pose'])
    summary = [l for l in err.splitlines() if l.startswith('ego-motion: ')]
    assert len(summary) == 1 and 'Traceback' not in err, err
    assert summary[0].startswith(f'ego-motion: record interrupted by {signal.Signals(sig).name} after '), err
    assert f'kept {out}: recorded {N + received_poses} messages' in summary[0]
    assert '/chatter 50' in summary[0] and 'closed with its summary and metadata.yaml' in summary[0]


def test_a_listener_sees_every_recorded_message(tmp_path, rclpy_context):
    """`BagRecorder.listen`: a reader in the recorder's process (the replay's /odom latency
    clock) gets each recorded message from the recorder's own take, the same ones as the bag."""
    from rclpy.serialization import deserialize_message

    from multicam_ego_motion.bag.recorder import BagRecorder
    from multicam_ego_motion.errors import UserError
    talker, host = SpinningNode('talker'), SpinningNode('recording')
    reliable = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    chatter = talker.node.create_publisher(String, '/chatter', reliable)
    rec = BagRecorder(tmp_path / 'recorded', topics=['/chatter'])
    with pytest.raises(UserError, match='/other is not recorded'):
        rec.listen('/other', print)
    heard = []
    rec.listen('/chatter', lambda data: heard.append(deserialize_message(data, String).data))
    try:
        rec.attach(host.node)
        assert rec.wait_for_topics(20), 'recorder never subscribed'
        for i in range(N):
            chatter.publish(String(data=f'hello {i}'))
        assert _wait(lambda: len(heard) >= N, 20), heard
    finally:
        talker.close()
        host.executor.shutdown(timeout_sec=1.0)     # no spinning over what close() destroys
        counts = rec.close()
        host.node.destroy_node()
    assert heard == [f'hello {i}' for i in range(N)]
    assert counts == {'/chatter': N}
