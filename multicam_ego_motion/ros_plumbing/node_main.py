"""The `ros2 run` entry point shared by every node: init, build, spin, and a one-line error
(no traceback) when the node rejects its parameters or rig."""
import sys

import rclpy
from rclpy.executors import ExternalShutdownException

from multicam_ego_motion.errors import UserError


def spin_node(node_class, name: str, args=None) -> int:
    rclpy.init(args=args)
    try:
        node = node_class()
    except UserError as e:
        print(f'{name}: error: {e}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
