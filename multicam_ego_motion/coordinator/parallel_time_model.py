"""Equations (1)-(4) of the paper, fed with measured stage times, for any number of workers M.

Per frame (eq. (1) sums these over the sequence; we predict the per-frame time):
  (2) T_q    = T_pose + T_acquire + T_struct + (T_extract + T_track) / NP_q + T_comm [NP_q > 1]
  (3) T_cam  = max_q T_q + T_arbiter k + T_comm
  (4) T_par  = max_k T_cam + T_comm + T_GA
with the allocation (allocation.allocate) deciding NP_q and which quarters share a worker:
quarters on one worker run one after the other, so a quarter finishes when its worker's
quarter work is done; arbiters sharing a worker also run one after the other. With M = 1
there is no communication and T_par equals the sequential time T_s.
"""
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Sequence

from multicam_ego_motion.coordinator.allocation import QUARTERS, Allocation, allocate, node_costs, quarter_name

STAGES = ('acquire', 'extract', 'track', 'pose', 'structure')
SPLITTABLE = ('extract', 'track')

# Paper Fig. 6(d): improvement (T_s - T_par) / T_s in % for M processors (4 cameras).
PAPER_IMPROVEMENT_PCT = {2: 48.7, 4: 71.6, 6: 74.8, 8: 80.7, 10: 80.9, 14: 84.86, 16: 85.0, 24: 87.5, 48: 90.5}


@dataclass
class TimePrediction:
    n_workers: int
    T_seq_ms: float
    T_par_ms: float
    T_cam_ms: Dict[str, float]
    allocation: Allocation

    @property
    def speedup(self) -> float:
        return self.T_seq_ms / self.T_par_ms if self.T_par_ms > 0 else float('inf')

    @property
    def efficiency(self) -> float:
        return self.speedup / self.n_workers

    @property
    def improvement_pct(self) -> float:
        return 100.0 * (self.T_seq_ms - self.T_par_ms) / self.T_seq_ms if self.T_seq_ms > 0 else 0.0


def _quarter_total(st: Mapping[str, float]) -> float:
    return float(sum(st.get(s, 0.0) for s in STAGES))


def sequential_time(stage_ms: Mapping[str, Sequence[Mapping[str, float]]],
                    arbiter_ms: Mapping[str, float], general_arbiter_ms: float) -> float:
    return (sum(_quarter_total(q) for qs in stage_ms.values() for q in qs)
            + sum(arbiter_ms.get(c, 0.0) for c in stage_ms) + general_arbiter_ms)


def predict(stage_ms: Mapping[str, Sequence[Mapping[str, float]]], n_workers: int,
            arbiter_ms: Optional[Mapping[str, float]] = None, general_arbiter_ms: float = 0.0,
            comm_ms: float = 0.0, nf: Optional[Mapping[str, Sequence[int]]] = None,
            min_f=None) -> TimePrediction:
    """T_par for M = n_workers. stage_ms: camera -> 4 dicts of stage times (ms);
    arbiter_ms: camera -> camera-arbiter time; comm_ms: one message between workers."""
    cams = list(stage_ms)
    arbiter_ms = {c: float((arbiter_ms or {}).get(c, 0.0)) for c in cams}
    qc = {c: [_quarter_total(stage_ms[c][l]) for l in range(QUARTERS)] for c in cams}
    sp = {c: [float(sum(stage_ms[c][l].get(s, 0.0) for s in SPLITTABLE)) for l in range(QUARTERS)] for c in cams}
    alloc = allocate(qc, n_workers, nf=nf, min_f=min_f, splittable=sp, arbiter_costs=arbiter_ms,
                     general_arbiter_ms=general_arbiter_ms)
    cost = node_costs(qc, alloc.chunks, sp, arbiter_ms, general_arbiter_ms)
    comm = comm_ms if n_workers > 1 else 0.0
    # quarter work per worker (primaries and chunks; arbiters come after)
    qload = {w: sum(cost[n] for n in nodes if '/q' in n) for w, nodes in alloc.workers.items()}
    T_cam = {}
    for c in cams:
        finish = 0.0
        for l in range(QUARTERS):
            q = quarter_name(c, l)
            hosts = [w for w, nodes in alloc.workers.items() if q in nodes or any(n.startswith(q + '/chunk') for n in nodes)]
            t = max(qload[w] for w in hosts) + (comm if alloc.chunks[q] > 1 else 0.0)    # eq. (2)
            finish = max(finish, t)
        w_arb = alloc.worker_of(f'{c}/arbiter')
        arbs = [n for n in alloc.workers[w_arb] if n.endswith('/arbiter')]
        before = sum(arbiter_ms[n.split('/')[0]] for n in arbs[:arbs.index(f'{c}/arbiter') + 1])
        T_cam[c] = max(finish, qload[w_arb]) + before + comm                            # eq. (3)
    T_par = max(T_cam.values()) + comm + general_arbiter_ms                              # eq. (4)
    return TimePrediction(n_workers, sequential_time(stage_ms, arbiter_ms, general_arbiter_ms),
                          T_par, T_cam, alloc)


def table(stage_ms, worker_counts: Sequence[int] = tuple(sorted(PAPER_IMPROVEMENT_PCT)), **kw) -> List[dict]:
    """Rows for a report: M, predicted T_par, speedup, efficiency, improvement % and the
    paper's Fig. 6(d) improvement % for that M (None where the paper has no figure)."""
    rows = []
    for M in worker_counts:
        p = predict(stage_ms, M, **kw)
        rows.append({'M': M, 'T_par_ms': p.T_par_ms, 'speedup': p.speedup, 'efficiency': p.efficiency,
                     'improvement_pct': p.improvement_pct, 'paper_improvement_pct': PAPER_IMPROVEMENT_PCT.get(M),
                     'imbalance': p.allocation.imbalance})
    return rows
