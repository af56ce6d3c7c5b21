"""`ego-motion worker --coordinator HOST:PORT`: join a coordinator's worker pool from this host
(worker.py does the work; this module keeps the command line's import light)."""
from multicam_ego_motion.coordinator.control import KEY_ENV


def configure_parser(ap):
    ap.add_argument('--coordinator', metavar='HOST:PORT', required=True,
                    help='join the coordinator listening there (its --listen) over TCP')
    ap.add_argument('--key-file', help=f'the shared control key (default: ${KEY_ENV}); '
                                       'never give the key itself on the command line')
    ap.add_argument('--connect-timeout', type=float, default=60.0, metavar='S',
                    help='keep trying to reach the coordinator this long (default 60 s)')


def run(args) -> int:
    from multicam_ego_motion.coordinator.worker import run_remote
    return run_remote(args)
