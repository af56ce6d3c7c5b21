"""Trajectories in and out: TUM files, and pose topics of a rosbag2 bag.

A trajectory source is written `PATH` (a .tum/.txt TUM file), `BAG:/topic`, or `BAG` with the
topic given separately. Bag topics may be nav_msgs/Odometry, PoseWithCovarianceStamped,
PoseStamped (one pose per message, stamped by header.stamp) or nav_msgs/Path (the poses of
the last message). TUM: one line per pose, `stamp tx ty tz qx qy qz qw`, '#' comments.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from multicam_ego_motion.errors import UserError

TUM_SUFFIXES = ('.tum', '.txt')


@dataclass
class Trajectory:
    stamps: np.ndarray      # (N,) seconds, increasing
    positions: np.ndarray   # (N, 3)
    quats_xyzw: np.ndarray  # (N, 4)

    def __len__(self):
        return len(self.stamps)

    def poses(self) -> np.ndarray:
        """(N, 4, 4) homogeneous poses."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = Rotation.from_quat(self.quats_xyzw).as_matrix()
        T[:, :3, 3] = self.positions
        return T

    @classmethod
    def from_poses(cls, stamps, poses) -> 'Trajectory':
        poses = np.asarray(poses, dtype=float)
        return cls(np.asarray(stamps, dtype=float), poses[:, :3, 3].copy(),
                   Rotation.from_matrix(poses[:, :3, :3]).as_quat())

    def subset(self, index) -> 'Trajectory':
        return Trajectory(self.stamps[index], self.positions[index], self.quats_xyzw[index])


def _sorted_unique(stamps, positions, quats, source) -> Trajectory:
    if len(stamps) == 0:
        raise UserError(f'{source}: no poses')
    order = np.argsort(stamps, kind='stable')
    stamps, positions, quats = (np.asarray(a, dtype=float)[order] for a in (stamps, positions, quats))
    # a repeated stamp keeps its last pose (a republished estimate supersedes the earlier one)
    keep = np.append(np.diff(stamps) > 0, True)
    norms = np.linalg.norm(quats, axis=1, keepdims=True)
    if np.any(norms < 1e-9) or not np.all(np.isfinite(positions)):
        raise UserError(f'{source}: holds a zero quaternion or a non-finite position')
    return Trajectory(stamps[keep], positions[keep], (quats / norms)[keep])


def load_tum(path) -> Trajectory:
    path = Path(path)
    if not path.is_file():
        raise UserError(f'trajectory file not found: {path}')
    try:
        data = np.loadtxt(path, comments='#', ndmin=2)
    except ValueError as e:
        raise UserError(f'{path} is not a TUM trajectory ({e})') from None
    if data.size == 0 or data.shape[1] != 8:
        raise UserError(f'{path} is not a TUM trajectory (expected 8 columns per line: '
                        'stamp tx ty tz qx qy qz qw)')
    return _sorted_unique(data[:, 0], data[:, 1:4], data[:, 4:8], path)


def save_tum(trajectory: Trajectory, path):
    data = np.column_stack([trajectory.stamps, trajectory.positions, trajectory.quats_xyzw])
    np.savetxt(path, data, fmt='%.9f', header='stamp tx ty tz qx qy qz qw')


def _pose_fields(pose):
    p, q = pose.position, pose.orientation
    return [p.x, p.y, p.z], [q.x, q.y, q.z, q.w]


def _stamp_s(header):
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def read_bag_topic(bag, topic: str) -> Trajectory:
    from multicam_ego_motion.bag.rosbag2_reader import Rosbag2Reader
    reader = Rosbag2Reader(bag)
    reader.require([topic])
    typename = reader.topics[topic]
    stamps, positions, quats = [], [], []

    def add(header, pose):
        p, q = _pose_fields(pose)
        stamps.append(_stamp_s(header))
        positions.append(p)
        quats.append(q)

    if typename == 'nav_msgs/msg/Path':
        last = None
        for _, msg, _ in reader.decoded([topic]):
            last = msg
        for ps in (last.poses if last is not None else []):
            add(ps.header, ps.pose)
    elif typename in ('nav_msgs/msg/Odometry', 'geometry_msgs/msg/PoseWithCovarianceStamped'):
        for _, msg, _ in reader.decoded([topic]):
            add(msg.header, msg.pose.pose)
    elif typename == 'geometry_msgs/msg/PoseStamped':
        for _, msg, _ in reader.decoded([topic]):
            add(msg.header, msg.pose)
    else:
        raise UserError(f'bag {bag}: topic {topic} has type {typename}, not a trajectory '
                        '(Odometry, PoseWithCovarianceStamped, PoseStamped or Path)')
    return _sorted_unique(np.array(stamps), np.reshape(positions, (-1, 3)),
                          np.reshape(quats, (-1, 4)), f'bag {bag} topic {topic}')


def split_source(spec: str, topic=None):
    """(path, topic or None) of a source written `PATH`, `BAG:/topic` or `BAG` + topic."""
    if topic is None and ':/' in spec:
        spec, _, rest = spec.partition(':/')
        topic = '/' + rest
    return Path(spec), topic


def load_trajectory(spec, topic=None) -> Trajectory:
    path, topic = split_source(str(spec), topic)
    if path.suffix in TUM_SUFFIXES:
        if topic:
            raise UserError(f'{path} is a TUM file: it has no topic {topic}')
        return load_tum(path)
    if topic is None:
        raise UserError(f'{path}: name the trajectory topic (BAG:/topic or --*-topic)')
    return read_bag_topic(path, topic)
