"""A worker process (a "processor" of the paper): hosts a set of graph nodes in one executor.

Started by the coordinator with a JSON spec: `python -m multicam_ego_motion.coordinator.worker
--spec FILE`. It dies with its parent (PR_SET_PDEATHSIG, and a parent-pid check as a second
guard), so a killed coordinator leaves no orphans.
"""
import argparse
import ctypes
import json
import os
import signal
import sys

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.parameter import Parameter

from multicam_ego_motion.errors import UserError

PR_SET_PDEATHSIG = 1


def _die_with_parent():
    try:
        ctypes.CDLL('libc.so.6', use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def node_class(kind: str):
    if kind == 'quarter':
        from camera_pose_nodes.quarter_node import QuarterNode
        return QuarterNode
    if kind == 'camera_arbiter':
        from arbiter_node.camera_arbiter_node import CameraArbiterNode
        return CameraArbiterNode
    if kind == 'general_arbiter':
        from arbiter_node.general_arbiter_node import GeneralArbiterNode
        return GeneralArbiterNode
    raise UserError(f'unknown node kind {kind!r}')


def create_node(spec: dict, params_file: str = None):
    cli_args = ['--ros-args', '--params-file', params_file] if params_file else None
    overrides = [Parameter(k, value=v) for k, v in spec['parameters'].items()]
    return node_class(spec['kind'])(namespace=spec['namespace'], parameter_overrides=overrides,
                                    cli_args=cli_args)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--spec', required=True, help='JSON: {"worker": i, "params_file": ..., "nodes": [...]}')
    args = ap.parse_args(argv)
    _die_with_parent()
    parent = os.getppid()
    with open(args.spec) as f:
        spec = json.load(f)
    rclpy.init()
    executor = SingleThreadedExecutor()
    nodes = []
    try:
        for n in spec['nodes']:
            node = create_node(n, spec.get('params_file'))
            nodes.append(node)
            executor.add_node(node)
    except UserError as e:
        print(f'worker {spec.get("worker")}: error: {e}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    if nodes:
        def check_parent():
            if os.getppid() != parent:
                raise SystemExit(0)
        nodes[0].create_timer(0.5, check_parent)
        nodes[0].get_logger().info(
            f'worker {spec.get("worker")} (pid {os.getpid()}) hosts {", ".join(n["key"] for n in spec["nodes"])}')
    signal.signal(signal.SIGTERM, lambda *a: (_ for _ in ()).throw(SystemExit(0)))
    try:
        executor.spin()
    except (KeyboardInterrupt, SystemExit, ExternalShutdownException):
        pass
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
