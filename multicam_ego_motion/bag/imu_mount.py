"""Where a bag's IMU sits, when the rig file does not say: the frame of its first
sensor_msgs/Imu and that frame's transform from base_link in /tf_static (REP-145), as a
robot's URDF publishes it. `replay` and `check` complete the rig with it, as they take the
image transport the bag has."""
from dataclasses import replace
from typing import Optional, Tuple

import numpy as np

from multicam_ego_motion.bag.rig_from_tf import mount, static_transforms
from multicam_ego_motion.geometry.rig import IMU_TOPIC, ImuMount, Rig


def imu_from_bag(reader, base_frame: str = 'base_link',
                 topic: str = IMU_TOPIC) -> Tuple[Optional[ImuMount], Optional[str]]:
    """(the mount, None), or (None, why not) when the bag has IMU samples that cannot be
    placed, or (None, None) when it has none."""
    if topic not in reader.topics:
        return None, None
    frame = None
    for _, msg, _ in reader.decoded([topic]):
        frame = msg.header.frame_id
        break
    if frame is None:
        return None, None
    if frame in ('', base_frame):
        return ImuMount(base_frame, np.zeros(3), np.eye(3), topic), None
    t = static_transforms(reader).get(frame)
    if t is not None and t.header.frame_id == base_frame:
        return ImuMount(frame, *mount(t), topic), None
    return None, (f'{topic} is in frame {frame!r}, which /tf_static does not place in {base_frame}: '
                  'the IMU is not used (give it as `imu` in the rig file)')


def with_bag_imu(reader, rig: Rig) -> Tuple[Rig, Optional[str]]:
    """The rig with the bag's IMU when the rig names none; and what to tell the user."""
    if rig.imu is not None:
        return rig, None
    mount, why = imu_from_bag(reader, rig.base_frame)
    if mount is None:
        return rig, why
    return replace(rig, imu=mount), (f'IMU on {mount.topic} in {mount.frame_id} (from the bag\'s '
                                     f'/tf_static)')
