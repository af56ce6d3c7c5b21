"""sensor_msgs/Imu, as its subscription's CDR bytes -> the gyro's sample as the fusion core
takes it (arbiter_node/imu_buffer). Read field by field (cdr_stream): 200 samples a second."""
from dataclasses import dataclass
from typing import Tuple

import numpy as np

from multicam_ego_motion.ros_plumbing.cdr_stream import CdrReader

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
    try:
        r = CdrReader(data)
        stamp_ns, frame_id = r.stamp_and_frame()
        # orientation (4), its covariance (9), angular_velocity (3), its covariance (9),
        # linear_acceleration (3), its covariance (9): read whole, so a short message is refused
        v = r.unpack('37d', 8)
    except Exception as e:  # struct.error, IndexError, UnicodeDecodeError, ValueError
        raise ValueError(f'{len(data)} bytes that do not read as {IMU_TYPE} ({type(e).__name__}: {e})') from None
    return GyroSample(stamp_ns, frame_id, v[13:16], np.array(v[16:25]).reshape(3, 3))
