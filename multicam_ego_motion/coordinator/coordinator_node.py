"""`ros2 run multicam_ego_motion coordinator --rig RIG.yaml [--params PARAMS.yaml] [--workers M]`:
the product on a robot. Starts the whole graph on M worker processes (default: CPU count),
keeps it running (worker restart with state restore), rebalances on measured costs (checked
once a second: camera drivers give no between-frames moment) and publishes its own
/diagnostics entry. Ends on Ctrl-C / SIGTERM, taking every worker with it.
"""
import argparse
import os
import signal
import sys
from pathlib import Path

from multicam_ego_motion.errors import UserError

DEFAULT_PARAMS = Path(__file__).resolve().parents[2] / 'config' / 'params.yaml'


def main(argv=None):
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.utilities import remove_ros_args

    from multicam_ego_motion.coordinator.coordinator import Coordinator
    from multicam_ego_motion.rig import load_rig

    argv = remove_ros_args(sys.argv if argv is None else ['coordinator', *argv])[1:]
    ap = argparse.ArgumentParser(prog='coordinator', description=__doc__.splitlines()[0])
    ap.add_argument('--rig', required=True, help='rig YAML (cameras, topics, extrinsics)')
    ap.add_argument('--params', default=str(DEFAULT_PARAMS) if DEFAULT_PARAMS.exists() else None,
                    help='ROS params file for the nodes')
    ap.add_argument('--workers', type=int, default=os.cpu_count(), help='worker processes (M)')
    ap.add_argument('--no-rebalance', action='store_true')
    ap.add_argument('--log-dir', help='worker logs (default: a temporary folder)')
    args = ap.parse_args(argv)
    for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
        os.environ.setdefault(var, '1')
    try:
        rig = load_rig(args.rig)
        if args.params and not Path(args.params).exists():
            raise UserError(f'params file not found: {args.params}')
        coordinator = Coordinator(rig, Path(args.rig).resolve(),
                                  Path(args.params).resolve() if args.params else None,
                                  workers=args.workers, log_dir=args.log_dir,
                                  rebalance=not args.no_rebalance)
    except UserError as e:
        print(f'coordinator: error: {e}', file=sys.stderr)
        return 2
    rclpy.init()
    node = rclpy.create_node('ego_motion_coordinator')
    coordinator.logger = lambda text: node.get_logger().info(text)
    signal.signal(signal.SIGTERM, lambda *a: (_ for _ in ()).throw(KeyboardInterrupt()))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    code = 0
    try:
        coordinator.start()
        coordinator.attach_ros(node, rate_mode_period_s=1.0)
        node.create_timer(1.0, coordinator.check_alive)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except UserError as e:
        print(f'coordinator: error: {e}', file=sys.stderr)
        code = 2
    finally:
        coordinator.stop()
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
