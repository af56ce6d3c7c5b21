"""The rig's IMU as the estimators take it (ROS-free): its samples between frames
(imu_buffer) and whether they may be used (imu_health). Below both the quarters, which steer
their search by the gyro, and the general arbiter, which fuses it."""
