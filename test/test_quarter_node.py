"""The quarter node's shell logic that needs no running graph (the nodes are real; messages
are handed to their callbacks)."""
import numpy as np
import pytest

from camera_pose_nodes.pose_estimate import PoseEstimate
from camera_pose_nodes.quarter_node import decode_fused
from conftest import REPO
from multicam_ego_motion.ros_plumbing.pose_messages import estimate_to_msg, stamp_to_ns
from multicam_ego_motion.geometry.se3 import make_T, rotvec_to_R


def fused_msg(stamp_ns, x):
    T = make_T(rotvec_to_R([0.0, 0.0, 0.3]), [x, 0.5, 0.0])
    return estimate_to_msg(PoseEstimate(stamp_ns, T, np.eye(6) * 1e-4, source='fused'))


def test_a_worker_decodes_the_shared_fused_pose_once_and_nobody_can_change_it():
    a = fused_msg(1_000_000_000, 1.0)
    first = decode_fused(a)
    assert decode_fused(a) is first          # the next quarter fed the same message object
    assert first.stamp_ns == 1_000_000_000 and first.T_odom_base[0, 3] == pytest.approx(1.0)
    # shared by all the worker's quarters: an in-place change would leak into the others
    with pytest.raises(ValueError):
        first.T_odom_base[0, 3] = 2.0
    with pytest.raises(ValueError):
        first.covariance[0, 0] = 1.0
    b = fused_msg(1_125_000_000, 1.5)           # the next frame's message
    second = decode_fused(b)
    assert second is not first and second.stamp_ns == 1_125_000_000
    assert second.T_odom_base[0, 3] == pytest.approx(1.5)


def _front_frames(n):
    """CameraInfo and the first n images of the default bag's front camera (real messages)."""
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    info, images = None, []
    for topic, msg, _ in Rosbag2Reader(REPO / 'bags' / 'default').decoded(
            ['/front/camera_info', '/front/image_raw']):
        if topic == '/front/camera_info':
            info = info or msg
        else:
            images.append(msg)
        if info is not None and len(images) >= n:
            return info, images


def _quarter():
    from rclpy.parameter import Parameter
    from camera_pose_nodes.quarter_node import QuarterNode
    node = QuarterNode(shared_inputs=True, parameter_overrides=[
        Parameter('camera', value='front'), Parameter('quarter', value=3),
        Parameter('rig_file', value=str(REPO / 'bags' / 'default' / 'rig.yaml'))])
    processed, diag = [], []
    node.estimate_sink = lambda msg: processed.append(stamp_to_ns(msg.header.stamp))
    node.diag_sink = lambda stamp, status: diag.append({kv.key: kv.value for kv in status.values})
    return node, processed, diag


def test_a_quarter_follows_the_frame_schedule(rclpy_context):
    """Without a schedule every frame is processed in order; with the general arbiter's
    schedule (every 2nd frame from a fused one) the others are skipped, also those already
    waiting, and counted in /diagnostics."""
    from std_msgs.msg import Int64MultiArray
    info, images = _front_frames(8)
    stamps = [stamp_to_ns(m.header.stamp) for m in images]
    period = stamps[1] - stamps[0]
    node, processed, diag = _quarter()
    try:
        node.on_info(info)
        node.on_image(images[0])                       # the first frame needs no feedback
        for m in images[1:4]:
            node.on_image(m)                           # the graph is busy: frames queue
        assert processed == stamps[:1] and len(node.pending) == 3
        node.on_fused(fused_msg(stamps[0], 0.0))
        assert processed == stamps[:2] and len(node.pending) == 2     # every frame, in order
        assert diag[-1]['images_skipped'] == '0'
        # behind: from frame 1 (fused), every 2nd frame: 3, 5, 7 (2 waits and is skipped)
        node.on_schedule(Int64MultiArray(data=[stamps[1], period, 2]))
        assert [stamp_to_ns(m.header.stamp) for _, m in node.pending] == [stamps[3]]
        for m in images[4:8]:
            node.on_image(m)
        node.on_fused(fused_msg(stamps[1], 0.1))
        node.on_fused(fused_msg(stamps[3], 0.2))
        node.on_fused(fused_msg(stamps[5], 0.3))
        assert processed == [stamps[0], stamps[1], stamps[3], stamps[5], stamps[7]]
        assert sum(int(d['images_skipped']) for d in diag) == 3     # frames 2, 4, 6
        # a malformed schedule is refused with an error, the one in force stays
        node.on_schedule(Int64MultiArray(data=[stamps[7], 0, 2]))
        assert node.schedule.takes(stamps[7] + 2 * period) and not node.schedule.takes(stamps[7] + period)
    finally:
        node.estimator.close()
        node.destroy_node()


def test_a_fused_pose_that_comes_before_its_image_is_applied_after_it(rclpy_context):
    """The general arbiter fused frame 2 without this camera (its image came late): the fused
    pose of frame 2 comes first. It is applied once image 2 is processed, so frame 3 goes on
    at once instead of waiting for a fused pose that already came (the camera then dropped
    out of the fusion for good). A fused pose at another camera's capture time (free-running
    cameras) is never applied."""
    info, images = _front_frames(5)
    stamps = [stamp_to_ns(m.header.stamp) for m in images]
    node, processed, diag = _quarter()
    try:
        node.on_info(info)
        node.on_image(images[0])
        node.on_fused(fused_msg(stamps[0], 0.0))
        node.on_image(images[1])
        node.on_fused(fused_msg(stamps[1], 0.1))
        assert processed == stamps[:2]
        node.on_fused(fused_msg(stamps[2], 0.2))            # ahead of image 2
        node.on_fused(fused_msg(stamps[3] + 4_000_000, 0.3))  # another camera's capture time
        assert stamps[2] not in node.estimator.fused_poses
        node.on_image(images[2])
        assert processed == stamps[:3] and stamps[2] in node.estimator.fused_poses
        assert node.last_fused_ns == stamps[2]
        node.on_image(images[3])                            # no wait for feedback
        assert processed == stamps[:4] and not node.pending
        node.on_fused(fused_msg(stamps[3], 0.3))
        node.on_image(images[4])
        assert processed == stamps[:5]
        assert stamps[3] + 4_000_000 not in node.estimator.fused_poses and not node.fused_ahead
    finally:
        node.estimator.close()
        node.destroy_node()


def test_four_quarters_of_a_worker_decode_each_compressed_image_once(rclpy_context, tmp_path):
    """A camera whose transport is `compressed`: its four quarters in one process (a
    worker's shared feed hands each the same message) decode each JPEG once, and each
    estimates its frame from it; a corrupt JPEG is decoded once and reported by each
    quarter, naming the topic, and the next image goes on."""
    import cv2
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import CompressedImage

    from camera_pose_nodes.decoded_images import SHARED
    from camera_pose_nodes.image_conversion import image_msg_to_gray
    from camera_pose_nodes.quarter_node import QuarterNode
    from multicam_ego_motion.geometry.rig import load_rig
    rig = load_rig(REPO / 'bags' / 'default' / 'rig.yaml')
    rig.cameras[0].transport = 'compressed'
    rig.save(tmp_path / 'rig.yaml')
    info, images = _front_frames(3)

    def jpeg(m, data=None):
        ok, enc = cv2.imencode('.jpg', image_msg_to_gray(m), [cv2.IMWRITE_JPEG_QUALITY, 90])
        return CompressedImage(header=m.header, format='mono8; jpeg compressed mono8',
                               data=enc.tobytes() if data is None else data)
    compressed = [jpeg(images[0]), jpeg(images[1], b'\xff\xd8\xff corrupt'), jpeg(images[2])]
    stamps = [stamp_to_ns(m.header.stamp) for m in images]
    nodes, processed, errors = [], [], []
    for q in range(1, 5):
        node = QuarterNode(shared_inputs=True, parameter_overrides=[
            Parameter('camera', value='front'), Parameter('quarter', value=q),
            Parameter('rig_file', value=str(tmp_path / 'rig.yaml'))])
        assert '/front/image_raw/compressed' in node.inputs
        node.estimate_sink = lambda msg: processed.append(stamp_to_ns(msg.header.stamp))
        node.diag_sink = lambda stamp, status: errors.append(status.message) if status.level == b'\x02' else None
        node.on_info(info)
        nodes.append(node)
    try:
        before = SHARED.decodes
        for k, msg in enumerate(compressed):
            for node in nodes:
                node.on_image(msg)
            if k < 2:
                for node in nodes:
                    node.on_fused(fused_msg(stamps[k], 0.1 * k))
        assert SHARED.decodes - before == 3                 # one per image, not per quarter
        assert processed == [stamps[0]] * 4 + [stamps[2]] * 4
        assert len(errors) == 4 and all('/front/image_raw/compressed' in e and 'could not be decoded' in e
                                        for e in errors), errors
    finally:
        for node in nodes:
            node.estimator.close()
            node.destroy_node()


def test_image_transport_parameter_wins_over_the_rig_file(rclpy_context):
    """A rig file that says nothing of transports (raw) and a robot that publishes only
    image_transport's compressed stream: the quarter's `image_transport: compressed` makes
    it subscribe `<image topic>/compressed`, and a JPEG published there over DDS comes out as
    its pose estimate. Empty keeps the rig's transport; any other value is refused, naming
    the parameter and the choices."""
    import time

    import cv2
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import CompressedImage

    from camera_pose_nodes.image_conversion import image_msg_to_gray
    from camera_pose_nodes.quarter_node import QuarterNode
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from multicam_ego_motion.errors import UserError
    from multicam_ego_motion.ros_plumbing.qos import RELIABLE

    def quarter(transport, **kw):
        return QuarterNode(parameter_overrides=[
            Parameter('camera', value='front'), Parameter('quarter', value=3),
            Parameter('rig_file', value=str(REPO / 'bags' / 'default' / 'rig.yaml')),
            Parameter('image_transport', value=transport)], **kw)

    raw = quarter('')
    assert '/front/image_raw' in raw.inputs and '/front/image_raw/compressed' not in raw.inputs
    raw.destroy_node()
    with pytest.raises(UserError, match=r"image_transport must be one of raw, compressed.*'theora'"):
        quarter('theora')

    info, images = _front_frames(1)
    ok, enc = cv2.imencode('.jpg', image_msg_to_gray(images[0]), [cv2.IMWRITE_JPEG_QUALITY, 90])
    jpeg = CompressedImage(header=images[0].header, format='mono8; jpeg compressed mono8',
                           data=enc.tobytes())
    node = quarter('compressed', namespace='/front/q3')
    assert '/front/image_raw/compressed' in node.inputs and '/front/image_raw' not in node.inputs
    from rclpy.node import Node
    robot = Node('robot_camera')
    pub_info = robot.create_publisher(type(info), '/front/camera_info', RELIABLE)
    pub_jpeg = robot.create_publisher(CompressedImage, '/front/image_raw/compressed', RELIABLE)
    poses = []
    robot.create_subscription(PoseWithCovarianceStamped, '/front/q3/pose',
                              lambda m: poses.append(stamp_to_ns(m.header.stamp)), RELIABLE)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(robot)
    try:
        deadline = time.monotonic() + 20.0
        while not poses and time.monotonic() < deadline:
            if node.intrinsics is None:
                pub_info.publish(info)
            else:
                pub_jpeg.publish(jpeg)
            executor.spin_once(timeout_sec=0.1)
        assert poses and poses[0] == stamp_to_ns(images[0].header.stamp)
    finally:
        executor.shutdown()
        if node.estimator is not None:
            node.estimator.close()
        node.destroy_node()
        robot.destroy_node()
