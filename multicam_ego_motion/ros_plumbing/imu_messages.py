"""sensor_msgs/Imu, as its subscription's CDR bytes (wire_types) -> the gyro's sample as the
fusion core takes it (arbiter_node/imu_buffer)."""
from dataclasses import dataclass
from typing import Tuple

import numpy as np

from multicam_ego_motion.ros_plumbing.pose_messages import stamp_to_ns
from multicam_ego_motion.ros_plumbing.wire_types import from_cdr

IMU_TYPE = 'sensor_msgs/msg/Imu'


@dataclass(frozen=True)
class GyroSample:
    stamp_ns: int
    frame_id: str
    gyro: Tuple[float, float, float]      # angular velocity (rad/s) in the message's frame
    # its 3x3 covariance as the driver gave it (REP-145: all zeros = unknown, -1 first = not
    # measured; the buffer then takes its default variance)
    gyro_covariance: np.ndarray


def gyro_sample_from_cdr(data) -> GyroSample:
    """The gyro's sample of one serialized sensor_msgs/Imu; ValueError naming the problem."""
    msg = from_cdr(data, IMU_TYPE)
    w = msg.angular_velocity
    return GyroSample(stamp_to_ns(msg.header.stamp), msg.header.frame_id, (w.x, w.y, w.z),
                      msg.angular_velocity_covariance.reshape(3, 3))
