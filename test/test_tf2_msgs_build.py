"""The locally built tf2_msgs (resource/tf2_msgs) is the upstream Jazzy type, usable over DDS.

The hash is what peers compare: a ROS 2 Jazzy node subscribing /tf matches our publisher only if
our TFMessage has the upstream RIHS01 hash, so it is checked both in the generated type
description and as the DDS graph reports it for a live publisher.
"""
import json
import os
import sys
import threading
import time

import pytest

# Upstream tf2_msgs/msg/TFMessage in ROS 2 Jazzy, as `ros2 topic info -v /tf` prints it on a
# Jazzy install (and as rosbag2 Jazzy records it in metadata.yaml type_description_hash).
UPSTREAM_TFMESSAGE_HASH = 'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'
TYPE_NAME = 'tf2_msgs/msg/TFMessage'


def _description_hash():
    # The wheels install ament prefixes into the venv itself and set no AMENT_PREFIX_PATH, so
    # look in sys.prefix as well as in any prefix the environment names.
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    for prefix in prefixes:
        path = os.path.join(prefix, 'share', 'tf2_msgs', 'msg', 'TFMessage.json')
        if os.path.isfile(path):
            break
    else:
        pytest.fail(f'no share/tf2_msgs/msg/TFMessage.json under {prefixes}')
    with open(path) as f:
        hashes = json.load(f)['type_hashes']
    return {h['type_name']: h['hash_string'] for h in hashes}[TYPE_NAME]


def test_generated_type_description_has_upstream_hash():
    assert _description_hash() == UPSTREAM_TFMESSAGE_HASH


def _transform(i):
    from geometry_msgs.msg import TransformStamped

    t = TransformStamped()
    t.header.stamp.sec = 1700000000 + i
    t.header.stamp.nanosec = 123456789
    t.header.frame_id = 'odom'
    t.child_frame_id = f'cam_{i}'
    t.transform.translation.x = 1.5 * i
    t.transform.translation.y = -2.25
    t.transform.translation.z = 0.125
    t.transform.rotation.x = 0.0
    t.transform.rotation.y = 0.0
    t.transform.rotation.z = 0.7071067811865476
    t.transform.rotation.w = 0.7071067811865476
    return t


def test_tfmessage_round_trips_over_dds(monkeypatch):
    # Own domain and localhost-only discovery, set before rclpy.init reads them, so parallel or
    # concurrent runs on this machine never see each other.
    domain = 1 + os.getpid() % 100
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from tf2_msgs.msg import TFMessage

    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    try:
        talker = rclpy.create_node('tf2_msgs_build_talker', context=ctx)
        listener = rclpy.create_node('tf2_msgs_build_listener', context=ctx)
        topic = '/tf2_msgs_build_check'
        received = []
        got = threading.Event()

        def on_msg(msg):
            received.append(msg)
            got.set()

        # Reliable + transient local: the message is delivered even if discovery finishes after
        # the publish, so the test does not depend on timing.
        qos = rclpy.qos.QoSProfile(
            depth=1,
            reliability=rclpy.qos.ReliabilityPolicy.RELIABLE,
            durability=rclpy.qos.DurabilityPolicy.TRANSIENT_LOCAL)
        pub = talker.create_publisher(TFMessage, topic, qos)
        listener.create_subscription(TFMessage, topic, on_msg, qos)

        sent = TFMessage(transforms=[_transform(i) for i in range(3)])
        pub.publish(sent)

        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(talker)
        executor.add_node(listener)
        deadline = time.monotonic() + 20.0
        while not got.is_set() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert got.is_set(), 'no TFMessage came back over DDS within 20 s'

        # Real DDS hands the subscriber a deserialized copy, so equality checks the whole
        # serialization path of the generated type support.
        msg = received[0]
        assert msg is not sent
        assert msg == sent
        assert [t.child_frame_id for t in msg.transforms] == ['cam_0', 'cam_1', 'cam_2']
        assert msg.transforms[2].transform.translation.x == pytest.approx(3.0)

        # What the graph announces is what a remote Jazzy node compares against.
        infos = listener.get_publishers_info_by_topic(topic)
        assert len(infos) == 1
        assert infos[0].topic_type == TYPE_NAME
        assert str(infos[0].topic_type_hash) == UPSTREAM_TFMESSAGE_HASH
        executor.shutdown()
        talker.destroy_node()
        listener.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
