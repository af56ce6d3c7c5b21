"""Measured node costs for the allocation: per-quarter stage times from the nodes'
/diagnostics statuses, exponentially smoothed (one frame's burst of extraction must not look
like a trend).

A quarter's first frame is left out (it only starts the map: ~0.03 ms against ~1.5 ms later,
on the loop at 320 x 240), and the costs count as measured once every quarter has
WARMUP_FRAMES more: workers send their costs a few frames at a time, so one worker's quarters
can read their first frame's cost while another's are current, and a rebalance on that
(free-running cameras, measured loads 10.7 / 0.8 ms) moved ten nodes for nothing.

ROS-free: fed with (status name, values) pairs. Workers send them with each frame's
/diagnostics batch over the control channel (`cost_values`): the coordinator decoding every
/diagnostics message (about 200 key-value objects a frame) cost about 1 ms per frame.
"""
from collections import deque
from typing import Dict, List

from multicam_ego_motion.coordinator.allocation import QUARTERS

STAGE_KEYS = ('acquire_ms', 'extract_ms', 'track_ms', 'pose_ms', 'structure_ms')
PREFIX = 'ego_motion/'
COST_KEYS = frozenset(STAGE_KEYS + ('features', 'arbiter_ms'))
WARMUP_FRAMES = 8


def cost_values(status) -> Dict[str, str]:
    """The values `observe` reads, from a diagnostic_msgs DiagnosticStatus (duck-typed)."""
    return {kv.key: kv.value for kv in status.values if kv.key in COST_KEYS}


class CostMonitor:
    def __init__(self, cameras: List[str], alpha: float = 0.3, history: int = 200):
        self.cameras = list(cameras)
        self.alpha = float(alpha)
        self.quarter_ms: Dict[str, List[float]] = {c: [None] * QUARTERS for c in self.cameras}
        self.features: Dict[str, List[int]] = {c: [0] * QUARTERS for c in self.cameras}
        self.seen: Dict[str, List[int]] = {c: [0] * QUARTERS for c in self.cameras}  # frames
        self.arbiter_ms: Dict[str, float] = {}
        self.general_arbiter_ms = None
        self.history = deque(maxlen=history)       # per frame: camera -> 4 smoothed costs
        self.nf_history = deque(maxlen=history)
        self.frames = 0

    def _smooth(self, old, new):
        return new if old is None else old + self.alpha * (new - old)

    def observe(self, name: str, values: Dict[str, str]) -> bool:
        """One /diagnostics status; True when it closed a frame (the general arbiter's)."""
        if not name.startswith(PREFIX):
            return False
        parts = name[len(PREFIX):].split('/')
        try:
            if len(parts) == 2 and parts[0] in self.quarter_ms and parts[1].startswith('q'):
                if not all(k in values for k in STAGE_KEYS):
                    return False          # an error entry without timings
                l = int(parts[1][1:]) - 1
                cost = sum(float(values[k]) for k in STAGE_KEYS)
                self.seen[parts[0]][l] += 1
                if self.seen[parts[0]][l] > 1:
                    self.quarter_ms[parts[0]][l] = self._smooth(self.quarter_ms[parts[0]][l], cost)
                self.features[parts[0]][l] = int(values.get('features', 0))
            elif len(parts) == 2 and parts[1] == 'arbiter' and 'arbiter_ms' in values:
                self.arbiter_ms[parts[0]] = self._smooth(self.arbiter_ms.get(parts[0]), float(values['arbiter_ms']))
            elif parts == ['general_arbiter'] and 'arbiter_ms' in values:
                self.general_arbiter_ms = self._smooth(self.general_arbiter_ms, float(values['arbiter_ms']))
                self.frames += 1
                self.history.append(self.quarter_costs())
                self.nf_history.append({c: list(v) for c, v in self.features.items()})
                return True
        except (ValueError, IndexError):
            pass
        return False

    @property
    def measured(self) -> bool:
        return all(n > WARMUP_FRAMES for qs in self.seen.values() for n in qs)

    def quarter_costs(self) -> Dict[str, List[float]]:
        """camera -> 4 costs (ms); before a quarter was measured, the mean of the measured
        ones (1 ms when none is): equal costs, as the allocation assumes at start."""
        known = [v for qs in self.quarter_ms.values() for v in qs if v is not None]
        default = sum(known) / len(known) if known else 1.0
        return {c: [default if v is None else v for v in qs] for c, qs in self.quarter_ms.items()}
