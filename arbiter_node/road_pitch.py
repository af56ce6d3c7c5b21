"""The road's normal in the body frame, from the direction the car travels (ROS-free).

Why: a camera's pitch to the road is rarely known to a degree (KITTI's, taken as level, is
about 1 deg down), and the road's scale is that sensitive to it: a road point 10 deg below the
horizon is 5-10 % nearer or farther per degree (road_plane.road_scale). A car moves along the
road it stands on, so the road's plane holds the direction of travel: the slope of the body's
steps in its own x-z plane, taken over many steps (a median: bumps, braking and hills average
out), is the body's pitch to the road. Measured on KITTI 07 and kitti_seq1: 1.0 and 1.2 deg by
the ground truth, 0.9 and 1.0 by the fused steps.

But the body does not keep one pitch to the road: its springs pitch it by a degree or two when
it brakes or accelerates (KITTI 07: 0.2-0.9 deg down on straights, 1.4-2.2 braking into a
turn), a tenth of the scale per degree. The rotation the cameras measure sees that pitch, and
the road's slope changes slowly: so the road's normal is square to the path the body drove over
its last steps, in the odometry frame, and into the body's frame by its rotation then
(PathNormal). Measured over five feature thresholds (sequential pipeline, mean ATE / final
drift %): KITTI 07 1.83 / 2.38 -> 1.35 / 2.00 (20 steps),
kitti_seq1 with the road as its scale 2.59 / 4.52 -> 2.23 / 2.75 (docs/estimator.md).
"""
import bisect
import math
from collections import deque
from typing import Optional

import numpy as np


WINDOW_STEPS = 300          # the median's window: hills come and go, the mounting stays
MIN_STEPS = 10              # before this many steps: the body's own axes
MIN_STEP_M = 0.1            # shorter steps' directions are noise
MAX_PITCH_RAD = math.radians(5.0)   # a larger slope is not a car on its road


class TravelPitch:
    """Median slope of the body's steps (forward or reverse alike) over the last `window`
    steps longer than `min_step_m`; none before `min_steps` of them."""

    def __init__(self, window: int = WINDOW_STEPS, min_steps: int = MIN_STEPS,
                 min_step_m: float = MIN_STEP_M, max_pitch_rad: float = MAX_PITCH_RAD):
        self.slopes = deque(maxlen=int(window))
        self.min_steps = int(min_steps)
        self.min_step_m = float(min_step_m)
        self.max_pitch_rad = float(max_pitch_rad)

    def add_step(self, t_body: np.ndarray):
        """One step of the body (its translation in the earlier body frame)."""
        along = abs(float(t_body[0]))
        if along < self.min_step_m or along < 3.0 * abs(float(t_body[1])):
            return                   # standing, or mostly sideways (a skid, a bad step)
        self.slopes.append(math.atan2(float(t_body[2]) * math.copysign(1.0, float(t_body[0])), along))

    @property
    def pitch_rad(self) -> Optional[float]:
        if len(self.slopes) < self.min_steps:
            return None
        p = float(np.median(self.slopes))
        return p if abs(p) <= self.max_pitch_rad else None   # beyond it: not a car on a road

    def up_body(self) -> np.ndarray:
        """The road's normal (up) in the body frame: the body's z tilted by the pitch about
        its y axis so that it is square to the direction of travel."""
        p = self.pitch_rad or 0.0
        return np.array([-math.sin(p), 0.0, math.cos(p)])


WINDOW_PATH_STEPS = 20      # about 2 s at 10 Hz: the steps' directions' noise averages out
MIN_PATH_M = 1.0            # a shorter path's direction is noise


class PathNormal:
    """The road's normal square to the path the body drove over its last `window` steps (in
    the odometry frame), given in the body's frame at a time by the body's rotation then. The
    body's lateral axis is taken to lie in the road (its roll is the road's bank)."""

    def __init__(self, window: int = WINDOW_PATH_STEPS, min_path_m: float = MIN_PATH_M):
        self.window = int(window)
        self.min_path_m = float(min_path_m)
        # (stamp at its end, step in odom); a few more than the window: the frame pairs
        # asked about end one or two steps back
        self.steps = deque(maxlen=self.window + 8)

    def add_step(self, stamp_ns: int, step_odom: np.ndarray):
        """The body's step ending at stamp_ns, in the odometry frame. (Steps before a rescale of
        the map keep their length: a few percent between steps does not turn their sum.)"""
        self.steps.append((int(stamp_ns), np.asarray(step_odom, float).copy()))

    def up_body(self, at_ns: int, R_odom_body: np.ndarray) -> Optional[np.ndarray]:
        """The road's normal (up) in the body frame at at_ns (the body's rotation then): square
        to the `window` steps up to at_ns and the one after it; None with fewer steps or a
        path shorter than min_path_m."""
        steps = list(self.steps)
        n_before = bisect.bisect_right([s for s, _ in steps], int(at_ns))
        if n_before < self.window + 1:
            return None
        path = np.sum([v for _, v in steps[n_before - self.window:n_before + 1]], axis=0)
        if np.linalg.norm(path) < self.min_path_m:
            return None
        n = np.cross(path, R_odom_body[:, 1])
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            return None
        n /= norm
        if n @ R_odom_body[:, 2] < 0.0:
            n = -n
        return R_odom_body.T @ n
