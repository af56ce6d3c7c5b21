"""The base's geometry, free of ROS: SE(3) (se3), the rig of cameras on the body (rig) and
camera intrinsics for the scenario renderer (camera_intrinsics). Everything else builds on it."""
