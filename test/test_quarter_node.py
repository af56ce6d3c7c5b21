"""The quarter node's shell logic that needs no running graph (the nodes are real; messages
are handed to their callbacks)."""
import numpy as np
import pytest

from camera_pose_nodes.pose_estimate import PoseEstimate
from camera_pose_nodes.quarter_node import decode_fused
from conftest import REPO
from multicam_ego_motion.pose_messages import estimate_to_msg, stamp_to_ns
from multicam_ego_motion.se3 import make_T, rotvec_to_R


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


def _quarter(newest_image_only):
    from rclpy.parameter import Parameter
    from camera_pose_nodes.quarter_node import QuarterNode
    node = QuarterNode(shared_inputs=True, parameter_overrides=[
        Parameter('camera', value='front'), Parameter('quarter', value=3),
        Parameter('rig_file', value=str(REPO / 'bags' / 'default' / 'rig.yaml')),
        Parameter('newest_image_only', value=newest_image_only)])
    processed, diag = [], []
    node.estimate_sink = lambda msg: processed.append(stamp_to_ns(msg.header.stamp))
    node.diag_sink = lambda stamp, status: diag.append({kv.key: kv.value for kv in status.values})
    return node, processed, diag


@pytest.mark.parametrize('newest_image_only', [True, False])
def test_a_quarter_behind_the_camera_takes_the_newest_image(rclpy_context, newest_image_only):
    """Live (newest_image_only): frames that queued while the fused pose of the last one was
    on its way are skipped, and counted; lockstep replay (false) processes every frame."""
    info, images = _front_frames(4)
    node, processed, diag = _quarter(newest_image_only)
    try:
        node.on_info(info)
        stamps = [stamp_to_ns(m.header.stamp) for m in images]
        node.on_image(images[0])                       # the first frame needs no feedback
        for m in images[1:]:
            node.on_image(m)                           # the graph is busy: frames queue
        assert processed == stamps[:1] and len(node.pending) == 3
        node.on_fused(fused_msg(stamps[0], 0.0))
        if newest_image_only:
            assert processed == [stamps[0], stamps[3]] and not node.pending
            assert diag[-1]['images_skipped'] == '2'
        else:
            assert processed == stamps[:2] and len(node.pending) == 2
            assert diag[-1]['images_skipped'] == '0'
    finally:
        node.estimator.close()
        node.destroy_node()
