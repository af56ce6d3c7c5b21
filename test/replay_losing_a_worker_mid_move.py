"""`ego-motion replay ...` whose first node move loses a worker at its worst moment, for
test_faults_processes: KILL_DURING_MOVE=source kills the worker the node leaves just before
it is asked to let go of it; =destination kills the worker it goes to after it was let go
(detached, its state in the coordinator's hands) and before it is attached there."""
import os
import signal
import sys

from multicam_ego_motion import cli
from multicam_ego_motion.coordinator import control
from multicam_ego_motion.coordinator.coordinator import Coordinator

VICTIM = os.environ['KILL_DURING_MOVE']
assert VICTIM in ('source', 'destination'), VICTIM
killed = []


def kill_once(handle):
    if not killed:
        killed.append(handle.proc.pid)
        os.kill(handle.proc.pid, signal.SIGKILL)
        print(f'test: killed worker {handle.index} (pid {handle.proc.pid}), the move\'s {VICTIM}',
              flush=True)


request, attach = Coordinator._request, Coordinator._attach


def _request(self, h, kind, *args, **kw):
    if kind == control.DETACH and VICTIM == 'source':
        kill_once(h)
    return request(self, h, kind, *args, **kw)


def _attach(self, h, key, state, wait_links=False):
    if VICTIM == 'destination':
        kill_once(h)
    return attach(self, h, key, state, wait_links)


Coordinator._request, Coordinator._attach = _request, _attach
sys.exit(cli.main(sys.argv[1:]))
