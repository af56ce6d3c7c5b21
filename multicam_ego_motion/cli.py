"""`ego-motion`: the one command a user runs. Subcommands live in their own modules.

Each subcommand module exposes `configure_parser(parser)` and `run(args) -> int`. Bad input
raises UserError, printed here as one line with a non-zero exit and no traceback. SIGINT,
SIGTERM and SIGHUP end any subcommand cleanly (interrupt.py): its `finally` clauses close
what it wrote, then one line says what was interrupted and what was kept, exit 128 + signal.
"""
import argparse
import importlib
import os
import sys

from multicam_ego_motion import interrupt
from multicam_ego_motion.errors import UserError

SUBCOMMANDS = {
    'generate': ('multicam_ego_motion.scenarios.generator', 'render a scenario bag'),
    'import-kitti': ('multicam_ego_motion.kitti_import', 'turn a KITTI sequence into a bag'),
    'play': ('multicam_ego_motion.bag.player', 'publish a bag into a running graph'),
    'record': ('multicam_ego_motion.bag.recorder', 'record topics into a bag'),
    'evaluate': ('multicam_ego_motion.evaluation.evaluate', 'score an estimate against ground truth'),
    'replay': ('multicam_ego_motion.replay', 'run the whole graph on a bag and score it'),
    'bench': ('multicam_ego_motion.bench.timing', 'measure sequential vs parallel timing'),
    'ablation': ('multicam_ego_motion.ablation', 'fused vs single cameras vs single quarters on a bag'),
    'matrix': ('multicam_ego_motion.bench.accuracy_matrix', 'accuracy matrix: seeds x scenarios through the sequential pipeline'),
    'profile': ('multicam_ego_motion.bench.profile_table', 'where the CPU goes: stage x kind of work, per frame'),
    'check': ('multicam_ego_motion.check.command', 'regression suite: replay its bags, judge the figures, JUnit XML'),
    'worker': ('multicam_ego_motion.coordinator.remote_worker', "join a coordinator's worker pool from this host (TCP)"),
    'reindex': ('multicam_ego_motion.bag.reindex', 'rebuild an unfinished bag (writer killed) from its complete chunks'),
}


def _single_threaded_blas():
    # numpy's BLAS threads fight the worker processes for the cores: on 2 cores the EKF's
    # small matrix products ran 10-20x slower with them. Must be set before numpy loads.
    for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
        os.environ.setdefault(var, '1')


def _isolate_ros_network():
    # A replay must never talk to a robot on the same network unless the user says so.
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


def build_parser():
    parser = argparse.ArgumentParser(prog='ego-motion', description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest='command', required=True)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text)
        p.set_defaults(_module=module)
        try:
            importlib.import_module(module).configure_parser(p)
        except ModuleNotFoundError as e:
            # Not built yet: the module itself or its parent package is absent.
            if e.name is None or not (module == e.name or module.startswith(e.name + '.')):
                raise
            p.set_defaults(_missing=True)
    return parser


def main(argv=None) -> int:
    _single_threaded_blas()
    _isolate_ros_network()
    args = build_parser().parse_args(argv)
    if getattr(args, '_missing', False):
        print(f'ego-motion: error: {args.command} is not available in this build', file=sys.stderr)
        return 2
    with interrupt.handling():
        try:
            code = int(importlib.import_module(args._module).run(args) or 0)
        except interrupt.Interrupted as e:
            print(interrupt.line('ego-motion', args.command, e.signum), file=sys.stderr, flush=True)
            return e.exit_code
        except UserError as e:
            print(f'ego-motion: error: {e}', file=sys.stderr)
            return 2
        except KeyboardInterrupt:     # a SIGINT ignored at start, raised by someone else
            return 130
        # A signal during a closing that then ended another way: still say so.
        if interrupt.received() is not None:
            print(interrupt.line('ego-motion', args.command), file=sys.stderr, flush=True)
            return 128 + interrupt.received()
        return code


if __name__ == '__main__':
    sys.exit(main())
