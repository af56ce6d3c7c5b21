"""sensor_msgs/Imu, as its subscription's CDR bytes -> the gyro's and the accelerometer's sample
as the fusion core takes it (multicam_ego_motion/imu/imu_buffer). Read field by field (cdr_stream): 200
samples a second."""
from dataclasses import dataclass
import struct
from typing import Optional, Tuple

import numpy as np

from multicam_ego_motion.ros_plumbing.cdr_stream import CdrReader

IMU_TYPE = 'sensor_msgs/msg/Imu'


@dataclass(frozen=True)
class ImuSample:
    stamp_ns: int
    frame_id: str
    gyro: Tuple[float, float, float]      # angular velocity (rad/s) in the message's frame
    # its 3x3 covariance as the driver gave it (REP-145: all zeros = unknown, -1 first = not
    # measured; the buffer then takes its default variance)
    gyro_covariance: np.ndarray
    accel: Tuple[float, float, float] = (0.0, 0.0, 0.0)   # linear acceleration (specific force, m/s^2)
    accel_covariance: np.ndarray = None   # as gyro_covariance (-1 first: the driver has no accelerometer)


def _read(data) -> Tuple[int, str, tuple]:
    """(stamp ns, frame_id, the message's 37 doubles); ValueError naming the problem."""
    try:
        r = CdrReader(data)
        stamp_ns, frame_id = r.stamp_and_frame()
        # orientation (4), its covariance (9), angular_velocity (3), its covariance (9),
        # linear_acceleration (3), its covariance (9): read whole, so a short message is refused
        return stamp_ns, frame_id, r.unpack('37d', 8)
    except Exception as e:  # struct.error, IndexError, UnicodeDecodeError, ValueError
        raise ValueError(f'{len(data)} bytes that do not read as {IMU_TYPE} ({type(e).__name__}: {e})') from None


def imu_sample_from_cdr(data) -> ImuSample:
    """The gyro's and accelerometer's sample of one serialized sensor_msgs/Imu; ValueError
    naming the problem."""
    stamp_ns, frame_id, v = _read(data)
    return ImuSample(stamp_ns, frame_id, v[13:16], np.array(v[16:25]).reshape(3, 3),
                     v[25:28], np.array(v[28:37]).reshape(3, 3))


_STAMP = {0: struct.Struct('>iI'), 1: struct.Struct('<iI')}     # by the encapsulation's byte order


def imu_stamp_from_cdr(data) -> Optional[int]:
    """The stamp (ns) of a serialized sensor_msgs/Imu, read without the rest (its header's
    first field): for a reader that already has that sample, from another subscriber of the
    process. None when the bytes are too short or not CDR."""
    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        return None
    sec, nanosec = _STAMP[data[1]].unpack_from(data, 4)
    return sec * 1_000_000_000 + nanosec


def imu_gyro_from_cdr(data) -> Tuple[int, str, Tuple[float, float, float]]:
    """(stamp ns, frame_id, angular velocity in rad/s) of a serialized sensor_msgs/Imu: the
    gyro alone, as the quarters steer by it; ValueError naming the problem."""
    stamp_ns, frame_id, v = _read(data)
    return stamp_ns, frame_id, v[13:16]
