"""Wheel-odometry readings the general arbiter uses as a twist prior, ROS-free.

One buffer for the node and for the sequential pipeline, so both pick the same reading for a
frame (the sequential pipeline must reproduce the graph's /odom bit for bit).
"""
from typing import List, Optional, Tuple

import numpy as np

# Wheel odometry runs at the frame rate or faster: a reading older than this means the wheels
# went silent, and the fusion must not keep using it.
MAX_AGE_NS = 500_000_000
KEEP = 200                 # readings kept: a few seconds at any usual wheel rate


def twist_from_odometry(msg) -> Tuple[np.ndarray, np.ndarray]:
    """(twist 6, covariance 6x6) in base_link from a nav_msgs/Odometry."""
    tw = msg.twist.twist
    twist = np.array([tw.linear.x, tw.linear.y, tw.linear.z, tw.angular.x, tw.angular.y, tw.angular.z])
    return twist, np.array(msg.twist.covariance, dtype=float).reshape(6, 6)


class WheelBuffer:
    def __init__(self, max_age_ns: int = MAX_AGE_NS):
        self.max_age_ns = max_age_ns
        self.readings: List[Tuple[int, np.ndarray, np.ndarray]] = []   # newest last

    def add(self, stamp_ns: int, twist: np.ndarray, cov: np.ndarray) -> bool:
        """Keeps a finite reading; returns False (and drops it) otherwise."""
        if not (np.all(np.isfinite(twist)) and np.all(np.isfinite(cov))):
            return False
        self.readings.append((int(stamp_ns), np.asarray(twist, float), np.asarray(cov, float)))
        del self.readings[:-KEEP]
        return True

    # The general arbiter's state is pickled after every frame (its snapshot, worker.py): the
    # readings as 2 x 200 small arrays took ~1.5 ms of its worker's CPU a frame, and 79 kB.
    # Stacked into two arrays (same values) they pickle in ~0.1 ms.
    def __getstate__(self):
        return {'max_age_ns': self.max_age_ns,
                'stamps': [s for s, _, _ in self.readings],
                'twists': np.array([t for _, t, _ in self.readings], dtype=float).reshape(-1, 6),
                'covariances': np.array([c for _, _, c in self.readings], dtype=float).reshape(-1, 6, 6)}

    def __setstate__(self, state):
        self.max_age_ns = state['max_age_ns']
        self.readings = list(zip(state['stamps'], state['twists'], state['covariances']))

    def settled(self, stamp_ns: int) -> bool:
        """Whether at(stamp_ns) is final: a reading at or after the stamp arrived, or the
        wheel went silent before it. (None yet: unknown, not final.)"""
        if not self.readings:
            return False
        newest = self.readings[-1][0]
        return newest >= stamp_ns or stamp_ns - newest >= self.max_age_ns

    def stamp_at(self, stamp_ns: int) -> Optional[int]:
        """The stamp of the reading at(stamp_ns) gives (None when it gives none)."""
        for s, _, _ in reversed(self.readings):
            if s <= stamp_ns:
                return s if stamp_ns - s < self.max_age_ns else None
        return None

    def at(self, stamp_ns: int) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """The newest reading not after stamp_ns, if it is fresh; else None."""
        for s, twist, cov in reversed(self.readings):
            if s <= stamp_ns:
                return (twist, cov) if stamp_ns - s < self.max_age_ns else None
        return None
