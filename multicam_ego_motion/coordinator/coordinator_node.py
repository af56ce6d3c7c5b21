"""`ros2 run multicam_ego_motion coordinator --rig RIG.yaml [--params PARAMS.yaml] [--workers M]`:
the product on a robot. Starts the whole graph on M worker processes (default: CPU count),
keeps it running (worker restart with state restore), rebalances on measured costs (checked
once a second: camera drivers give no between-frames moment) and publishes its own
/diagnostics entry. Ends on SIGINT (Ctrl-C), SIGTERM (systemd, a launch system) or SIGHUP
(interrupt.py): it stops every worker, says so in one line and exits with 128 + the signal.
"""
import argparse
import os
import sys
import time
from pathlib import Path

from multicam_ego_motion import interrupt
from multicam_ego_motion.errors import UserError

DEFAULT_PARAMS = Path(__file__).resolve().parents[2] / 'config' / 'params.yaml'


def main(argv=None):
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
    with interrupt.handling():
        try:
            code = _run(coordinator)
        except interrupt.Interrupted:
            code = None
        if interrupt.received() is not None:
            print(interrupt.line('coordinator'), file=sys.stderr, flush=True)
            return 128 + interrupt.received()
        return code


def _run(coordinator) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    t0 = time.monotonic()
    interrupt.note(progress=lambda: f'after {time.monotonic() - t0:.0f} s',
                   kept=f'nothing written (worker logs in {coordinator.log_dir})')
    code = 0
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('ego_motion_coordinator')
    coordinator.logger = lambda text: node.get_logger().info(text)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        coordinator.start()           # a signal here raises interrupt.Interrupted
        coordinator.attach_ros(node, rate_mode_period_s=1.0)
        node.create_timer(1.0, coordinator.check_alive)
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
            n = len(coordinator.worker_pids())
            coordinator.stop()
            interrupt.note(kept=f'stopped its {n} worker processes; nothing written '
                                f'(worker logs in {coordinator.log_dir})')
            node.destroy_node()
            rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
