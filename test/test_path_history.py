"""/ego_motion/path: decimated by distance and turn, bounded, republished at most once a period."""
import numpy as np

from arbiter_node.path_history import PathHistory
from multicam_ego_motion.geometry import se3

S = 1_000_000_000


def pose(x, yaw=0.0):
    return se3.make_T(se3.rotvec_to_R([0, 0, yaw]), [x, 0, 0])


def test_keeps_a_pose_per_spacing_or_turn():
    h = PathHistory(min_spacing_m=0.095, min_turn_rad=0.2, max_poses=100, publish_period_s=0.0)
    for k in range(101):                       # 1 m in 1 cm steps
        h.add(k * S // 100, pose(0.01 * k))
    xs = [T[0, 3] for _, T, _ in h.poses]
    assert len(xs) == 11 and np.allclose(np.diff(xs), 0.1)
    h.add(2 * S, pose(1.0, yaw=0.1))           # turned too little: dropped
    h.add(3 * S, pose(1.0, yaw=0.25))          # turned enough in place: kept
    assert len(h.poses) == 12 and h.poses[-1][0] == 3 * S


def test_bounded_and_keeps_the_callers_item():
    h = PathHistory(min_spacing_m=0.0, max_poses=5, publish_period_s=0.0)
    for k in range(20):
        h.add(k * S, pose(float(k)), item=f'msg{k}')
    assert [it for _, _, it in h.poses] == [f'msg{k}' for k in range(15, 20)]


def test_published_at_most_once_a_period_and_only_when_it_changed():
    h = PathHistory(min_spacing_m=0.05, max_poses=1000, publish_period_s=1.0)
    due = [h.add(k * S // 8, pose(0.1 * k)) for k in range(41)]    # 5 s at 8 Hz, moving
    assert [k for k, d in enumerate(due) if d] == [0, 8, 16, 24, 32, 40]
    assert not h.add(10 * S, pose(4.0))         # standing still: nothing new to publish
    h.reset()
    assert h.add(11 * S, pose(0.0)) and len(h.poses) == 1
