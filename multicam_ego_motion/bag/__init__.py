"""rosbag2 (MCAP storage) reading and writing, and the bag player and recorder."""
