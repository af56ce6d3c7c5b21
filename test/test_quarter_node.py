"""The quarter node's shell logic that needs no running graph."""
import numpy as np
import pytest

from camera_pose_nodes.pose_estimate import PoseEstimate
from camera_pose_nodes.quarter_node import decode_fused
from multicam_ego_motion.pose_messages import estimate_to_msg
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
