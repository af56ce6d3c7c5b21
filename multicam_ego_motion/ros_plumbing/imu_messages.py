"""sensor_msgs/Imu -> the gyro's sample as the fusion core takes it (arbiter_node/imu_buffer)."""
import numpy as np


def imu_gyro(msg) -> np.ndarray:
    """Angular velocity (rad/s) in the message's frame."""
    w = msg.angular_velocity
    return np.array([w.x, w.y, w.z], float)


def imu_gyro_covariance(msg) -> np.ndarray:
    """Its 3x3 covariance as the driver gave it (REP-145: all zeros = unknown, -1 first =
    not measured; the buffer then takes its default variance)."""
    return np.asarray(msg.angular_velocity_covariance, float).reshape(3, 3)
