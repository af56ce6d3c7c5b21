"""The Fast DDS profile of the graph's own processes (replay, bench, the workers they start).

Fast DDS's default shared-memory segment is 0.5 MB: less than one frame of four 640x480
images (4 x 307 kB), let alone two in flight. A reliable writer that finds it full leaves
the samples to be repaired on heartbeats: four cameras at 640x480 ran 655 ms per frame on
200 ms of CPU (M = 1), 171-186 ms with config/fastdds.xml's 4 MB segment. A profile the
user set (FASTRTPS_DEFAULT_PROFILES_FILE) or another RMW is left alone.
"""
import os
from pathlib import Path

PROFILE_VAR = 'FASTRTPS_DEFAULT_PROFILES_FILE'     # Fast DDS 2.x (ros_fastrtps 2.14)
FAST_DDS_RMWS = ('rmw_fastrtps_cpp', 'rmw_fastrtps_dynamic_cpp')


def profile() -> Path:
    """The package's config/fastdds.xml (package_share.py: checkout or install space)."""
    from multicam_ego_motion.ros_plumbing import package_share
    return package_share.config_file('fastdds.xml')


def use_graph_profile(env=None) -> bool:
    """Point `env` (default os.environ) at config/fastdds.xml; before rclpy.init and before
    worker processes are started (they inherit it). Returns whether it was set. A package
    whose config/fastdds.xml is missing is an error (UserError), not a silent default."""
    env = os.environ if env is None else env
    if PROFILE_VAR in env or env.get('RMW_IMPLEMENTATION', FAST_DDS_RMWS[0]) not in FAST_DDS_RMWS:
        return False
    env[PROFILE_VAR] = str(profile())
    return True
