"""What flows up the graph: one body-pose estimate per quarter, camera and frame.

A quarter node produces it, the camera arbiter fuses quarters' into the camera's, the
general arbiter fuses cameras' into odometry. Pose is base_link in odom (4x4); covariance is
6x6 in the multicam_ego_motion.geometry.se3 convention (x, y, z, rot x, rot y, rot z, odom frame).
"""
from dataclasses import dataclass, field
from typing import Dict

import numpy as np

# A quarter or camera that has no measurement still reports, with this variance, so that
# arbiters can synchronise on "every source reported" and simply weigh it out.
UNINFORMATIVE_VARIANCE = 1.0e6

STATES = ('initializing', 'tracking', 'lost')


@dataclass
class PoseEstimate:
    stamp_ns: int
    T_odom_base: np.ndarray                      # 4x4
    covariance: np.ndarray                       # 6x6
    source: str = ''                             # e.g. 'front/q2', 'front', 'fused'
    state: str = 'initializing'                  # one of STATES
    n_features: int = 0                          # tracked features
    n_landmarks: int = 0                         # tracked features with a 3D landmark
    n_floor: int = 0                             # of those, landmarks on the floor (metric scale)
    n_inliers: int = 0                           # measurements accepted by gating
    stage_ms: Dict[str, float] = field(default_factory=dict)  # acquire/extract/track/pose/structure

    @property
    def informative(self) -> bool:
        return self.state == 'tracking' and float(np.max(np.diag(self.covariance))) < UNINFORMATIVE_VARIANCE


def uninformative(stamp_ns: int, T_prior: np.ndarray, source: str, state: str, **kw) -> PoseEstimate:
    return PoseEstimate(stamp_ns, T_prior.copy(), np.eye(6) * UNINFORMATIVE_VARIANCE,
                        source=source, state=state, **kw)
