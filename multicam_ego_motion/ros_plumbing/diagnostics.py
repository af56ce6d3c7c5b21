"""Build diagnostic_msgs entries for the graph's /diagnostics (features, stage times, states)."""
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

LEVEL = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN,
         'error': DiagnosticStatus.ERROR, 'stale': DiagnosticStatus.STALE}


def status(name: str, level: str, message: str, values: dict, hardware_id: str = '') -> DiagnosticStatus:
    s = DiagnosticStatus()
    s.level = LEVEL[level]
    s.name = name
    s.message = message
    s.hardware_id = hardware_id
    s.values = [KeyValue(key=str(k), value=(f'{v:.3f}' if isinstance(v, float) else str(v)))
                for k, v in values.items()]
    return s


def array(stamp, statuses) -> DiagnosticArray:
    msg = DiagnosticArray()
    msg.header.stamp = stamp
    msg.status = list(statuses)
    return msg


def emit(stamp, status: DiagnosticStatus, sink, publisher):
    """A node's status for one frame: into its worker's per-frame batch when the worker gave
    it a `sink` (coordinator/worker.py), else published on its own."""
    if sink is not None:
        sink(stamp, status)
    else:
        publisher.publish(array(stamp, [status]))

