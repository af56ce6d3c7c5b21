"""`ros2 run multicam_ego_motion coordinator --rig RIG.yaml [--params PARAMS.yaml] [--workers M]`:
the product on a robot. Starts the whole graph on M worker processes (default: CPU count),
keeps it running (worker restart with state restore), rebalances on measured costs (checked
once a second: camera drivers give no between-frames moment) and publishes its own
/diagnostics entry. Ends on SIGINT (Ctrl-C), SIGTERM (systemd, a launch system) or SIGHUP
(interrupt.py): it stops every worker, says so in one line and exits with 128 + the signal.

ROS arguments (what launch/multicam_ego_motion.launch.py gives it): the coordinator's
namespace (`--ros-args -r __ns:=/robot1`) is the whole graph's, nodes and topics
(coordinator/graph_spec.py); its `use_sim_time` parameter is every graph node's. Without
--params, the package's config/params.yaml (package_share.py: a checkout's or the install
space's share/multicam_ego_motion/config).

Workers on other hosts: `--listen HOST:PORT --remote-workers R --key-file F` (R of the M
workers join with `ros2 run multicam_ego_motion worker --coordinator HOST:PORT`; coordinator.py).
"""
import argparse
import os
import sys
import time
from pathlib import Path

from multicam_ego_motion import interrupt
from multicam_ego_motion.errors import UserError

NODE_NAME = 'ego_motion_coordinator'
KINDS = ('quarter', 'camera_arbiter', 'general_arbiter')
USE_SIM_TIME = ('every node of the graph takes its time from /clock (a bag played with its '
                '/clock, a simulator); the coordinator\'s own timers stay on the steady clock')


def parse_args(argv=None):
    from rclpy.utilities import remove_ros_args
    argv = remove_ros_args(sys.argv if argv is None else ['coordinator', *argv])[1:]
    ap = argparse.ArgumentParser(prog='coordinator', description=__doc__.splitlines()[0])
    ap.add_argument('--rig', required=True, help='rig YAML (cameras, topics, extrinsics)')
    ap.add_argument('--params', help="ROS params file for the nodes (default: the package's config/params.yaml)")
    ap.add_argument('--workers', type=int, default=0,
                    help='worker processes (M; default, or 0: the CPU count)')
    ap.add_argument('--no-rebalance', action='store_true')
    ap.add_argument('--log-dir', help='worker logs (default: a temporary folder)')
    from multicam_ego_motion.replay import add_remote_arguments
    add_remote_arguments(ap)
    return ap.parse_args(argv)


def main(argv=None):
    from multicam_ego_motion.ros_plumbing import package_share
    from multicam_ego_motion.geometry.rig import load_rig

    ros_argv = sys.argv if argv is None else ['coordinator', *argv]
    args = parse_args(argv)
    for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
        os.environ.setdefault(var, '1')
    try:
        rig = load_rig(args.rig)
        params = Path(args.params) if args.params else package_share.default_params()
        if not params.is_file():
            raise UserError(f'params file not found: {params}')
        from multicam_ego_motion.replay import remote_options
        remote = remote_options(args)
        if args.workers < 0:
            raise UserError(f'--workers {args.workers}: give 1 or more, or 0 for the CPU count')
    except UserError as e:
        print(f'coordinator: error: {e}', file=sys.stderr)
        return 2
    with interrupt.handling():
        try:
            code = _run(args, rig, params.resolve(), ros_argv, remote)
        except interrupt.Interrupted:
            code = None
        if interrupt.received() is not None:
            print(interrupt.line('coordinator'), file=sys.stderr, flush=True)
            return 128 + interrupt.received()
        return code


def _node(ros_argv):
    """The coordinator's ROS node: its namespace and use_sim_time are the graph's."""
    import rclpy
    from rcl_interfaces.msg import ParameterDescriptor, ParameterType
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=ros_argv, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(NODE_NAME)
    # declared by rclpy itself (its time source); described here
    node.set_descriptor('use_sim_time', ParameterDescriptor(
        description=USE_SIM_TIME, type=ParameterType.PARAMETER_BOOL))
    return node


def _run(args, rig, params, ros_argv, remote) -> int:
    import rclpy
    from rclpy.clock import Clock, ClockType
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    from multicam_ego_motion.coordinator.coordinator import Coordinator

    t0 = time.monotonic()
    interrupt.note(progress=lambda: f'after {time.monotonic() - t0:.0f} s', kept='nothing written')
    code = 0
    node = _node(ros_argv)
    coordinator = None
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        sim_time = bool(node.get_parameter('use_sim_time').value)
        coordinator = Coordinator(rig, Path(args.rig).resolve(), params, workers=args.workers or None,
                                  log_dir=args.log_dir, rebalance=not args.no_rebalance,
                                  overrides={kind: {'use_sim_time': sim_time} for kind in KINDS},
                                  namespace=node.get_namespace(),
                                  logger=lambda text: node.get_logger().info(text), **remote)
        interrupt.note(kept=f'nothing written (worker logs in {coordinator.log_dir})')
        node.get_logger().info(
            f'rig {args.rig}, params {params}, {coordinator.n_workers} workers, namespace '
            f'{coordinator.namespace or "/"}{", use_sim_time" if sim_time else ""}')
        coordinator.start()           # a signal here raises interrupt.Interrupted
        coordinator.attach_ros(node, rate_mode_period_s=1.0)
        # the watchdog runs on the steady clock: /clock may pause or never come
        node.create_timer(1.0, coordinator.check_alive, clock=Clock(clock_type=ClockType.STEADY_TIME))
        # Running: a signal only ends this loop, never a callback half-way.
        with interrupt.deferred():
            while not interrupt.requested():
                executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    except UserError as e:
        print(f'coordinator: error: {e}', file=sys.stderr)
        code = 2
    finally:
        with interrupt.deferred():    # stopping the workers is not cut short
            if coordinator is not None:
                n = len(coordinator.worker_pids())
                coordinator.stop()
                interrupt.note(kept=f'stopped its {n} worker processes; nothing written '
                                    f'(worker logs in {coordinator.log_dir})')
            node.destroy_node()
            rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
