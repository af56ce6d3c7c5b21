"""Node-to-worker allocation (paper section 3), generalised to N cameras and M workers.

Pure function of measured costs (ms per frame). Cases:
  M <= N        whole cameras, sorted by cost descending; each worker gets floor(N/M) of
                them, dealt in that order each to the least loaded worker that has fewer
                than floor(N/M) (count-capped longest-first), then the N - floor(N/M) M
                remaining ones go one by one to the least loaded worker.
  N < M <= 4N   each camera gets floor(M/N) workers; its quarters, sorted by cost, are dealt
                floor(4/N_i) per worker (count-capped longest-first, as above) and the
                remainder go to the least loaded of that
                camera's workers; each of the M - floor(M/N) N spare workers takes the most
                expensive quarter from the most loaded worker holding two or more quarters.
  M > 4N        every quarter on its own worker; the spare workers are added one by one to
                the quarter with the longest predicted time, splitting its extraction and
                tracking into chunks, up to NP_l = ceil(NF / MinF) chunks.
Arbiters: camera arbiter k goes on the least loaded worker hosting camera k's quarters; the
general arbiter (sequential, paper T_5) on the least loaded worker overall.
Node names: '<cam>/q<l>' (l = 1..4), '<cam>/q<l>/chunk<i>' (helpers, i = 2..NP),
'<cam>/arbiter', 'general_arbiter'.
"""
import math
from dataclasses import dataclass, field
from typing import Dict, List, Mapping, Optional, Sequence

QUARTERS = 4
DEFAULT_SPLITTABLE_FRACTION = 0.8     # share of a quarter's cost that is extract + track
DEFAULT_ARBITER_MS = 0.2
DEFAULT_GENERAL_ARBITER_MS = 0.5


@dataclass
class Allocation:
    workers: Dict[int, List[str]]                       # worker -> node names
    chunks: Dict[str, int]                              # '<cam>/q<l>' -> NP (1 = not split)
    load_ms: Dict[int, float]                           # predicted load per worker
    case: str                                           # 'cameras' | 'quarters' | 'chunks'
    cameras: List[str] = field(default_factory=list)
    n_workers: int = 0

    @property
    def makespan_ms(self) -> float:
        return max(self.load_ms.values()) if self.load_ms else 0.0

    @property
    def imbalance(self) -> float:
        """max load / mean load - 1 (0 = perfectly balanced)."""
        mean = sum(self.load_ms.values()) / max(len(self.load_ms), 1)
        return self.makespan_ms / mean - 1.0 if mean > 0 else 0.0

    def worker_of(self, node: str) -> Optional[int]:
        for w, nodes in self.workers.items():
            if node in nodes:
                return w
        return None


def quarter_name(cam: str, l: int) -> str:
    return f'{cam}/q{l + 1}'


def _splittable(quarter_costs, splittable, cam, l):
    if splittable is not None and cam in splittable:
        return min(float(splittable[cam][l]), float(quarter_costs[cam][l]))
    return DEFAULT_SPLITTABLE_FRACTION * float(quarter_costs[cam][l])


def chunk_limit(nf: Optional[Mapping[str, Sequence[int]]], min_f, cam: str, l: int) -> Optional[int]:
    """NP_l = ceil(NF / MinF) (paper eq. cases 1-2), None when feature counts are unknown."""
    if nf is None or cam not in nf:
        return None
    mf = min_f[cam][l] if isinstance(min_f, Mapping) else min_f
    return max(1, math.ceil(int(nf[cam][l]) / max(int(mf), 1)))


def node_costs(quarter_costs: Mapping[str, Sequence[float]], chunks: Mapping[str, int],
               splittable: Optional[Mapping[str, Sequence[float]]] = None,
               arbiter_costs: Optional[Mapping[str, float]] = None,
               general_arbiter_ms: float = DEFAULT_GENERAL_ARBITER_MS) -> Dict[str, float]:
    """Cost of every node name given quarter costs and chunking (primary keeps the
    non-splittable part plus its chunk)."""
    out = {}
    for cam, qc in quarter_costs.items():
        for l in range(QUARTERS):
            q = quarter_name(cam, l)
            npl = chunks.get(q, 1)
            sp = _splittable(quarter_costs, splittable, cam, l)
            out[q] = float(qc[l]) - sp + sp / npl
            for i in range(2, npl + 1):
                out[f'{q}/chunk{i}'] = sp / npl
        out[f'{cam}/arbiter'] = float((arbiter_costs or {}).get(cam, DEFAULT_ARBITER_MS))
    out['general_arbiter'] = float(general_arbiter_ms)
    return out


def _loads(workers, costs):
    return {w: sum(costs[n] for n in nodes) for w, nodes in workers.items()}


def _deal(items, cost, ws, load, cap):
    """Longest-first: each item (already sorted) to the least loaded of `ws` holding fewer
    than `cap` of these items. Returns {worker: [items]}."""
    got = {w: [] for w in ws}
    for it in items:
        w = min((w for w in ws if len(got[w]) < cap), key=lambda w: (load[w], w))
        got[w].append(it)
        load[w] += cost(it)
    return got


def allocate(quarter_costs: Mapping[str, Sequence[float]], n_workers: int,
             nf: Optional[Mapping[str, Sequence[int]]] = None, min_f=None,
             splittable: Optional[Mapping[str, Sequence[float]]] = None,
             arbiter_costs: Optional[Mapping[str, float]] = None,
             general_arbiter_ms: float = DEFAULT_GENERAL_ARBITER_MS) -> Allocation:
    """See module doc. quarter_costs: camera -> 4 per-quarter costs (ms); nf / min_f: feature
    counts and the paper's MinF (int or camera -> 4 ints); splittable: camera -> 4 ms of
    extract + track (default 80 % of the cost)."""
    M = int(n_workers)
    if M < 1:
        raise ValueError('need at least one worker')
    cams = list(quarter_costs)
    N = len(cams)
    if N < 1:
        raise ValueError('need at least one camera')
    for c in cams:
        if len(quarter_costs[c]) != QUARTERS:
            raise ValueError(f'camera {c}: expected {QUARTERS} quarter costs')
    if nf is not None and min_f is None:
        raise ValueError('nf given without min_f')
    workers: Dict[int, List[str]] = {w: [] for w in range(M)}
    chunks = {quarter_name(c, l): 1 for c in cams for l in range(QUARTERS)}
    cam_cost = {c: float(sum(quarter_costs[c])) for c in cams}
    by_cost = sorted(cams, key=lambda c: (-cam_cost[c], cams.index(c)))   # stable: ties keep rig order

    def costs():
        return node_costs(quarter_costs, chunks, splittable, arbiter_costs, general_arbiter_ms)

    def least_loaded(cands, load):
        return min(cands, key=lambda w: (load[w], w))

    if M <= N:
        case = 'cameras'
        per = N // M
        load = {w: 0.0 for w in workers}
        for w, got in _deal(by_cost[:per * M], cam_cost.get, list(workers), load, per).items():
            for cam in got:
                workers[w] += [quarter_name(cam, l) for l in range(QUARTERS)]
        for cam in by_cost[per * M:]:
            w = least_loaded(workers, load)
            workers[w] += [quarter_name(cam, l) for l in range(QUARTERS)]
            load[w] += cam_cost[cam]
    elif M <= QUARTERS * N:
        case = 'quarters'
        per = M // N
        cam_workers = {cam: list(range(i * per, (i + 1) * per)) for i, cam in enumerate(by_cost)}
        load = {w: 0.0 for w in workers}
        for cam in by_cost:
            ws = cam_workers[cam]
            order = sorted(range(QUARTERS), key=lambda l: (-quarter_costs[cam][l], l))
            each = QUARTERS // len(ws)
            for w, got in _deal(order[:each * len(ws)], lambda l: quarter_costs[cam][l], ws, load, each).items():
                workers[w] += [quarter_name(cam, l) for l in got]
            for l in order[each * len(ws):]:
                w = least_loaded(ws, load)
                workers[w].append(quarter_name(cam, l))
                load[w] += quarter_costs[cam][l]
        c = costs()
        for spare in range(per * N, M):
            donors = [w for w in range(per * N) if len(workers[w]) >= 2]
            if not donors:
                break
            w = max(donors, key=lambda w: (load[w], -w))
            q = max(workers[w], key=lambda n: (c[n], -workers[w].index(n)))   # ties: first dealt
            workers[w].remove(q)
            workers[spare].append(q)
            load[w] -= c[q]
            load[spare] += c[q]
    else:
        case = 'chunks'
        quarters = [quarter_name(cam, l) for cam in by_cost
                    for l in sorted(range(QUARTERS), key=lambda l: (-quarter_costs[cam][l], l))]
        for w, q in enumerate(quarters):
            workers[w].append(q)
        limits = {quarter_name(cam, l): chunk_limit(nf, min_f, cam, l) for cam in cams for l in range(QUARTERS)}
        for spare in range(len(quarters), M):
            c = costs()
            cands = [q for q in quarters if limits[q] is None or chunks[q] < limits[q]]
            if not cands:
                break
            q = max(cands, key=lambda q: (c[q], -quarters.index(q)))
            chunks[q] += 1
            workers[spare].append(f'{q}/chunk{chunks[q]}')

    # arbiters: next to their camera's quarters, then the general arbiter anywhere
    c = costs()
    load = _loads(workers, c)
    for cam in by_cost:
        hosts = [w for w, nodes in workers.items() if any(n.startswith(cam + '/q') for n in nodes)]
        w = least_loaded(hosts, load)
        workers[w].append(f'{cam}/arbiter')
        load[w] += c[f'{cam}/arbiter']
    w = least_loaded(workers, load)
    workers[w].append('general_arbiter')
    load[w] += c['general_arbiter']
    return Allocation(workers, chunks, load, case, cams, M)


def evaluate_loads(allocation: Allocation, quarter_costs: Mapping[str, Sequence[float]],
                   splittable=None, arbiter_costs=None,
                   general_arbiter_ms: float = DEFAULT_GENERAL_ARBITER_MS) -> Dict[int, float]:
    """Per-worker load of an existing allocation under new costs."""
    c = node_costs(quarter_costs, allocation.chunks, splittable, arbiter_costs, general_arbiter_ms)
    return {w: sum(c.get(n, 0.0) for n in nodes) for w, nodes in allocation.workers.items()}


def relabel(proposal: Allocation, current: Allocation) -> Allocation:
    """The same allocation with its workers renumbered to keep as many nodes where they are
    as possible (worker numbers are arbitrary; every renumbering is a move of many nodes):
    greedy on the largest overlap, which is exact for two workers."""
    overlap = sorted(((len(set(nodes) & set(current.workers.get(w, []))), -p, -w, p, w)
                      for p, nodes in proposal.workers.items() for w in current.workers), reverse=True)
    mapping, used = {}, set()
    for _, _, _, p, w in overlap:
        if p not in mapping and w not in used:
            mapping[p] = w
            used.add(w)
    return Allocation({mapping[p]: list(n) for p, n in proposal.workers.items()}, dict(proposal.chunks),
                      {mapping[p]: v for p, v in proposal.load_ms.items()}, proposal.case,
                      list(proposal.cameras), proposal.n_workers)


def refine(current: Allocation, quarter_costs: Mapping[str, Sequence[float]], max_moves: int = 4,
           min_step: float = 0.03, **cost_kw) -> Allocation:
    """Local search from the current placement: move single quarter nodes from the most
    loaded worker to the least loaded one while that lowers the pair's larger load by at
    least `min_step` of it (each time the quarter that evens them best), at most
    `max_moves` moves: a move that gains a few percent is not worth a hand-over. It refines the
    paper's whole-camera rule (M <= N), which cannot balance e.g. one cheap camera among
    three expensive ones on two workers, and it moves few nodes (each move is a state
    hand-over). Arbiters and chunk helpers stay where they are."""
    c = node_costs(quarter_costs, current.chunks, **cost_kw)
    workers = {w: list(n) for w, n in current.workers.items()}
    load = {w: sum(c.get(n, 0.0) for n in nodes) for w, nodes in workers.items()}
    for _ in range(max_moves):
        if len(workers) < 2:
            break
        hi = max(workers, key=lambda w: (load[w], -w))
        lo = min(workers, key=lambda w: (load[w], w))
        movable = [n for n in workers[hi] if n.count('/') == 1 and '/q' in n]
        if not movable:
            break
        q = min(movable, key=lambda n: (max(load[hi] - c[n], load[lo] + c[n]), movable.index(n)))
        if max(load[hi] - c[q], load[lo] + c[q]) > load[hi] * (1.0 - min_step):
            break
        workers[hi].remove(q)
        workers[lo].append(q)
        load[hi] -= c[q]
        load[lo] += c[q]
    return Allocation(workers, dict(current.chunks), load, current.case, list(current.cameras),
                      current.n_workers)


def moves_between(current: Allocation, proposal: Allocation) -> List[str]:
    return [n for w, nodes in proposal.workers.items() for n in nodes if current.worker_of(n) != w]


def best_proposal(current: Allocation, quarter_costs, nf=None, min_f=None, tolerance: float = 0.05,
                  **cost_kw) -> Allocation:
    """The better of a fresh allocation (renumbered to the current workers) and a local
    refinement of the current one; within `tolerance` of each other, the one with fewer
    moves (measured on bare_wall: a whole-camera swap of 10 nodes won over one quarter move
    by 0.7 %, and the costs it was computed from had moved on by the time it was done)."""
    fresh = relabel(allocate(quarter_costs, current.n_workers, nf=nf, min_f=min_f if nf else None,
                             **cost_kw), current)
    local = refine(current, quarter_costs, **cost_kw)
    cands = sorted([fresh, local], key=lambda a: a.makespan_ms)
    if cands[1].makespan_ms <= cands[0].makespan_ms * (1.0 + tolerance) and \
            len(moves_between(current, cands[1])) < len(moves_between(current, cands[0])):
        return cands[1]
    return cands[0]


@dataclass
class RebalanceDecision:
    rebalance: bool
    reason: str
    current_makespan_ms: float = 0.0
    best_makespan_ms: float = 0.0
    frames_over: int = 0
    proposal: Optional[Allocation] = None


def frame_gain(quarter_costs, current: Allocation, threshold: float = 0.10, min_gain_ms: float = 1.0,
               nf=None, min_f=None, **cost_kw):
    """(worth moving, current makespan, best proposal's makespan) for one frame's costs."""
    cur = max(evaluate_loads(current, quarter_costs, **cost_kw).values())
    best = best_proposal(current, quarter_costs, nf=nf, min_f=min_f, **cost_kw).makespan_ms
    return best > 0 and cur > best * (1.0 + threshold) and cur - best > min_gain_ms, cur, best


def frames_needed(hysteresis_frames: int, quorum: float) -> int:
    """How many of the hysteresis window's frames must show the gain."""
    return max(1, min(hysteresis_frames, math.ceil(quorum * hysteresis_frames - 1e-9)))


def should_rebalance(costs_history: Sequence[Mapping[str, Sequence[float]]], current: Allocation,
                     threshold: float = 0.10, hysteresis_frames: int = 10,
                     nf_history: Optional[Sequence[Mapping[str, Sequence[int]]]] = None, min_f=None,
                     min_gain_ms: float = 1.0, quorum: float = 0.8, **cost_kw) -> RebalanceDecision:
    """Move nodes only when, in at least `quorum` of the last `hysteresis_frames` frames and
    on their mean costs, the current allocation's makespan exceeds the best proposal's
    (best_proposal: a fresh allocation or a few quarter moves) by more than `threshold`
    (relative) and `min_gain_ms`. The hysteresis stops a single slow frame (a burst of
    feature extraction) from causing a migration, which itself costs a state hand-over; the
    quorum stops a single fast one (a scheduler hiccup on a loaded machine) from holding a
    real imbalance in place for another window."""
    if len(costs_history) < hysteresis_frames:
        return RebalanceDecision(False, f'{len(costs_history)} frames of history < {hysteresis_frames}')
    over = 0
    cur = best = 0.0
    for i, qc in enumerate(costs_history[-hysteresis_frames:]):
        nf = nf_history[-hysteresis_frames:][i] if nf_history else None
        gain, cur, best = frame_gain(qc, current, threshold, min_gain_ms, nf=nf, min_f=min_f, **cost_kw)
        over += gain
    if over < frames_needed(hysteresis_frames, quorum):
        return RebalanceDecision(False, f'gain above {threshold:.0%} in {over}/{hysteresis_frames} frames',
                                 cur, best, over)
    # propose from the mean recent costs, so that the new allocation fits the trend
    mean = {cam: [sum(h[cam][l] for h in costs_history[-hysteresis_frames:]) / hysteresis_frames
                  for l in range(QUARTERS)] for cam in current.cameras}
    gain, cur, best = frame_gain(mean, current, threshold, min_gain_ms, nf=nf_history[-1] if nf_history
                                 else None, min_f=min_f, **cost_kw)
    if not gain:
        return RebalanceDecision(False, f'gain on the mean costs of {hysteresis_frames} frames below '
                                 f'{threshold:.0%}', cur, best, over)
    nf = nf_history[-1] if nf_history else None
    prop = best_proposal(current, mean, nf=nf, min_f=min_f, **cost_kw)
    return RebalanceDecision(True, f'current makespan {cur:.2f} ms > best {best:.2f} ms by more than '
                             f'{threshold:.0%} in {over}/{hysteresis_frames} frames', cur, best, over, prop)
