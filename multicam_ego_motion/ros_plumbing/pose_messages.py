"""Conversions between the cores' numpy types and ROS messages (stamps, poses, covariances)."""
import math

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped

from camera_pose_nodes.pose_estimate import UNINFORMATIVE_VARIANCE, PoseEstimate
from multicam_ego_motion.geometry.se3 import R_to_quat_xyzw, make_T, quat_xyzw_to_R


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def pose_to_T(pose) -> np.ndarray:
    q = pose.orientation
    p = pose.position
    return make_T(quat_xyzw_to_R([q.x, q.y, q.z, q.w]), [p.x, p.y, p.z])


def fill_pose(pose, T: np.ndarray):
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    q = R_to_quat_xyzw(T[:3, :3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def covariance_field(C) -> np.ndarray:
    """A 6x6 covariance as the value of a message's covariance field: a float64 array (a
    copy), which rclpy's setter takes as is; a list of floats it checks element by element
    in Python (~40 us a field). Same values, same bytes on the wire."""
    return np.array(C, dtype=np.float64).reshape(36)


def estimate_to_msg(est: PoseEstimate, frame_id: str = 'odom') -> PoseWithCovarianceStamped:
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = ns_to_stamp(est.stamp_ns)
    msg.header.frame_id = frame_id
    fill_pose(msg.pose.pose, est.T_odom_base)
    msg.pose.covariance = covariance_field(est.covariance)
    return msg


def msg_to_estimate(msg: PoseWithCovarianceStamped, source: str = '') -> PoseEstimate:
    """An estimate whose covariance is the uninformative one comes from a source that is
    initializing or lost (the message has no state field)."""
    values = [float(v) for v in msg.pose.covariance]
    cov = np.array(values).reshape(6, 6)
    # plain floats: numpy's reductions on 36 numbers took half of this function's ~35 us
    informative = (all(map(math.isfinite, values))
                   and max(values[::7]) < 0.5 * UNINFORMATIVE_VARIANCE)     # [::7]: the diagonal
    return PoseEstimate(stamp_to_ns(msg.header.stamp), pose_to_T(msg.pose.pose), cov,
                        source=source, state='tracking' if informative else 'initializing')


def transform_msg(T: np.ndarray, parent: str, child: str, stamp_ns: int) -> TransformStamped:
    t = TransformStamped()
    t.header.stamp = ns_to_stamp(stamp_ns)
    t.header.frame_id = parent
    t.child_frame_id = child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (
        float(v) for v in T[:3, 3])
    q = R_to_quat_xyzw(T[:3, :3])
    r = t.transform.rotation
    r.x, r.y, r.z, r.w = (float(v) for v in q)
    return t
