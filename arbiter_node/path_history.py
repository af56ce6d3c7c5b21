"""The travelled path shown on /ego_motion/path, ROS-free: decimated, bounded, throttled.

Publishing a nav_msgs/Path costs ~10 us per pose in rclpy (measured: 1000 poses 7.8 ms,
10000 poses 100 ms), on the general arbiter's thread, which also publishes /odom. A path of
every frame, republished every frame, made that cost grow with the run (8 Hz for 20 min:
~100 ms a frame). Kept: a pose every `min_spacing_m` or `min_turn_rad`, at most
`max_poses` of them, republished at most every `publish_period_s` of stamp time.
"""
from typing import List, Optional, Tuple

import numpy as np

from multicam_ego_motion.geometry import se3


class PathHistory:
    def __init__(self, min_spacing_m: float = 0.05, min_turn_rad: float = 0.1,
                 max_poses: int = 5000, publish_period_s: float = 1.0):
        self.min_spacing_m = float(min_spacing_m)
        self.min_turn_rad = float(min_turn_rad)
        self.max_poses = int(max_poses)
        self.publish_period_ns = int(round(publish_period_s * 1e9))
        self.reset()

    def reset(self):
        # (stamp_ns, T odom<-base, the caller's item: e.g. its message), oldest first
        self.poses: List[Tuple[int, np.ndarray, object]] = []
        self.last_publish_ns: Optional[int] = None

    def add(self, stamp_ns: int, T: np.ndarray, item: object = None) -> bool:
        """Offer the pose of a frame (`item` is kept with it when it is kept). Returns True
        when the path is due to be published (it changed and the last publication is at least
        a period old)."""
        changed = False
        if not self.poses:
            changed = True
        else:
            last = self.poses[-1][1]
            moved = np.linalg.norm(T[:3, 3] - last[:3, 3]) >= self.min_spacing_m
            turned = np.linalg.norm(se3.R_to_rotvec(last[:3, :3].T @ T[:3, :3])) >= self.min_turn_rad
            changed = bool(moved or turned)
        if changed:
            self.poses.append((int(stamp_ns), np.array(T, float), item))
            del self.poses[:-self.max_poses]
        due = changed and (self.last_publish_ns is None
                           or stamp_ns - self.last_publish_ns >= self.publish_period_ns)
        if due:
            self.last_publish_ns = int(stamp_ns)
        return due
