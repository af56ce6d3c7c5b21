"""A worker's sends to its coordinator (worker.py): a failed send ends the worker as a lost
coordinator does. No rclpy: Worker.send is called on a stand-in."""
import socket
import threading
import types

import pytest

from multicam_ego_motion.coordinator import control
from multicam_ego_motion.coordinator.worker import Worker


def test_a_send_that_times_out_ends_the_worker_as_a_lost_heartbeat():
    """A remote worker whose link went silent: its send of costs blocks until the socket's
    heartbeat timeout. It must end as when the heartbeats stop (nodes stopped, exit 3 with
    the reason), not with a traceback; a closed connection says so."""
    class Conn:
        def __init__(self, error):
            self.error = error

        def send(self, msg):
            raise self.error

    w = types.SimpleNamespace(send_lock=threading.Lock(), conn=Conn(socket.timeout('timed out')), lost=None)
    with pytest.raises(SystemExit):
        Worker.send(w, (control.COSTS, []))
    assert w.lost == f'no heartbeat for {control.HEARTBEAT_TIMEOUT_S:.0f} s'
    w = types.SimpleNamespace(send_lock=threading.Lock(), conn=Conn(BrokenPipeError(32, 'Broken pipe')), lost=None)
    with pytest.raises(SystemExit):
        Worker.send(w, (control.COSTS, []))
    assert 'Broken pipe' in w.lost
    # the reader's reason, when it came first, stands
    w = types.SimpleNamespace(send_lock=threading.Lock(), conn=Conn(socket.timeout()), lost='connection closed')
    with pytest.raises(SystemExit):
        Worker.send(w, (control.COSTS, []))
    assert w.lost == 'connection closed'


def test_a_worker_whose_orderly_stop_hangs_still_ends():
    """The coordinator gone (its channel closed) while the worker's main thread is stuck (a
    node's teardown, DDS on a loaded machine): the process ends anyway, with status 3, within
    EXIT_GRACE_S, so no worker outlives its coordinator."""
    import subprocess
    import sys
    code = '''
import queue, threading, time, types
from multicam_ego_motion.coordinator.worker import Worker
class Conn:
    is_tcp = False
    def recv(self, timeout=None):
        raise EOFError()
w = types.SimpleNamespace(conn=Conn(), inbox=queue.Queue(), wake=types.SimpleNamespace(trigger=lambda: None), lost=None)
threading.Thread(target=Worker.read_commands, args=(w,), daemon=True).start()
time.sleep(600)     # the main thread never gets to stop the nodes
'''
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3, proc.stderr
