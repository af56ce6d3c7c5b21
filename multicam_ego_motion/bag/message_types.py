"""Map ROS 2 type names ('sensor_msgs/msg/Image') to rclpy classes and ros2msg definitions."""
import importlib
from functools import lru_cache

from multicam_ego_motion.errors import UserError


@lru_cache(maxsize=None)
def message_class(typename: str):
    """The rclpy message class for a type name such as 'nav_msgs/msg/Odometry'."""
    parts = typename.split('/')
    if len(parts) != 3 or parts[1] != 'msg':
        raise UserError(f'not a ROS 2 message type name: {typename!r}')
    pkg, _, name = parts
    try:
        return getattr(importlib.import_module(f'{pkg}.msg'), name)
    except (ImportError, AttributeError):
        raise UserError(f'unknown message type {typename!r} (is package {pkg} installed?)') from None


def typename_of(msg_or_class) -> str:
    cls = msg_or_class if isinstance(msg_or_class, type) else type(msg_or_class)
    pkg = cls.__module__.split('.')[0]
    return f'{pkg}/msg/{cls.__name__}'


@lru_cache(maxsize=None)
def message_definition(typename: str) -> str:
    """Concatenated ros2msg text (the schema rosbag2 stores in MCAP) for a type."""
    # rosbags carries the upstream definitions of every Jazzy message, tf2_msgs included.
    from multicam_ego_motion.ros_plumbing.wire_types import STORE as store
    if typename not in store.types:
        raise UserError(f'no message definition known for {typename!r}')
    text, _ = store.generate_msgdef(typename, ros_version=2)
    return text
