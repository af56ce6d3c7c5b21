"""The targets section of `ego-motion bench`: one row per target, the measured value, met or
missed. Built from the bench's figures (plain numbers), so it can be checked without a run.
"""
import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

SEQ_CPU_MS = 45.0            # sequential pipeline, CPU per frame
OVERHEAD_MS = 10.0           # graph at M = 2: CPU per frame beyond the sequential pipeline's
SPEEDUP_M2 = 1.8
M1_RATIO = 1.25              # graph at M = 1 over sequential, wall per frame
RTF_MIN = 0.98               # "real time": RTF 1.0 within what a shared host's timing allows
DEFAULT_RATE_P99_MS = 50.0   # default bag, rate mode, M = 2
CAMERA_RATE_P99_MS = 100.0   # four 640x480 cameras at 30, 15 and 10 Hz, rate mode, M = 2
SLOW_RATE_CORES = 1.0        # ... at 15 and 10 Hz: cores needed at the reference LK speed
LIVE_OFFLINE_REL = 0.10      # live (rate mode) vs offline (lockstep) ATE and final drift


@dataclass
class Target:
    name: str
    measured: str
    met: Optional[bool]      # None: not measured in this run


def table(targets: List[Target]) -> List[str]:
    lines = ['| target | measured | |', '|---|---|---|']
    for t in targets:
        verdict = 'not run' if t.met is None else ('met' if t.met else '**missed**')
        lines.append(f'| {t.name} | {t.measured} | {verdict} |')
    return lines


def rate_target(name: str, fig, p99_ms: float, skipped: str = '') -> Target:
    """RTF >= RTF_MIN, nothing dropped, p99 within p99_ms; fig: measures.RateFigures."""
    name = f'{name}: RTF >= {RTF_MIN:.2f} (1.0), 0 dropped, latency p99 <= {p99_ms:.0f} ms'
    if fig is None:
        return Target(name, f'skipped ({skipped})' if skipped else 'not measured', None)
    met = fig.rtf >= RTF_MIN and fig.dropped == 0 and fig.p99 <= p99_ms     # NaN: missed
    return Target(name, f'RTF {fig.rtf:.2f}, {fig.dropped} of {fig.frames} dropped, p99 {fig.p99:.0f} ms', met)


def slow_rate_targets(rate_hz: float, run: Optional[Tuple[object, float]], skipped: str = '') -> List[Target]:
    """At 15 and 10 Hz: every frame with room to spare, on at most SLOW_RATE_CORES at the
    reference speed (run: (RateFigures, cores))."""
    name = f'camera rate (4 x 640x480 at {rate_hz:g} Hz), rate mode, M = 2'
    cores_name = (f'cores needed, 4 x 640x480 at {rate_hz:g} Hz (graph + player CPU per frame x rate, '
                  f'at the reference Lucas-Kanade speed) <= {SLOW_RATE_CORES:g}')
    if run is None:
        return [rate_target(name, None, CAMERA_RATE_P99_MS, skipped),
                Target(cores_name, f'skipped ({skipped})' if skipped else 'not measured', None)]
    fig, cores = run
    return [rate_target(name, fig, CAMERA_RATE_P99_MS),
            Target(cores_name, f'{cores:.2f}', cores <= SLOW_RATE_CORES)]


def live_offline_target(rate_hz: float, rel: Optional[Tuple[float, float]], skipped: str = '') -> Target:
    """rel: relative differences (ATE, final drift) of live against offline."""
    name = (f'live (rate mode) vs offline (lockstep), VGA {rate_hz:g} Hz, M = 2: ATE and final drift '
            f'within {LIVE_OFFLINE_REL * 100:.0f} %')
    if rel is None:
        return Target(name, f'skipped ({skipped})' if skipped else 'not measured', None)
    ate, drift = rel
    met = ate <= LIVE_OFFLINE_REL and drift <= LIVE_OFFLINE_REL
    return Target(name, f'ATE {_pct(ate)}, final drift {_pct(drift)} apart', met)


def _pct(x: float) -> str:
    return f'{100 * x:.1f} %' if math.isfinite(x) else 'n/a'


def bench_targets(*, seq_ms: float, seq_cpu_ms: float, m1_ms: float, m2_ms: float,
                  graph_cpu_m2_ms: float, replay_cpu_m2_ms: float, speedup_bound: float,
                  default_rate, floor_bound: Optional[float] = None, m1_seq_ms: Optional[float] = None,
                  camera_rate=None, live_offline: Optional[Dict[float, Tuple[float, float]]] = None,
                  live_offline_rates=(10.0, 15.0, 30.0), skipped_camera_rate: str = '',
                  slow_camera_rates: Optional[Dict[float, Tuple[object, float]]] = None,
                  skipped_live_offline: str = '') -> List[Target]:
    """Every target of the bench. Times per frame in ms: seq_ms / seq_cpu_ms the sequential
    pipeline's wall / CPU, m1_ms / m2_ms the graph's wall in lockstep, graph_cpu_m2_ms and
    replay_cpu_m2_ms the CPU of the workers and of player, recorder and coordinator at M = 2;
    speedup_bound what the CPU time allows at M = 2, floor_bound what the transport's floor alone
    allows (transport_floor.py; None: not run); m1_seq_ms the sequential wall the M = 1 run is
    compared with (default seq_ms); default_rate / camera_rate RateFigures
    (camera_rate None: not run); slow_camera_rates {rate Hz: (RateFigures, cores needed at the
    reference LK speed)} for 15 and 10 Hz; live_offline {rate Hz: (ATE, drift) relative
    differences}."""
    overhead = graph_cpu_m2_ms + replay_cpu_m2_ms - seq_cpu_ms
    speedup = seq_ms / m2_ms
    m1_seq = seq_ms if m1_seq_ms is None else m1_seq_ms
    live_offline = live_offline or {}
    return [
        Target(f'sequential pipeline CPU per frame <= {SEQ_CPU_MS:.0f} ms', f'{seq_cpu_ms:.1f} ms',
               seq_cpu_ms <= SEQ_CPU_MS),
        Target(f'graph overhead at M = 2 (graph + player, recorder, coordinator CPU per frame '
               f'- sequential CPU per frame) <= {OVERHEAD_MS:.0f} ms',
               f'{overhead:.1f} ms ({graph_cpu_m2_ms:.1f} + {replay_cpu_m2_ms:.1f} - {seq_cpu_ms:.1f})',
               overhead <= OVERHEAD_MS),
        Target(f'speedup at M = 2 >= {SPEEDUP_M2}', f'{speedup:.2f} (the CPU time allows {speedup_bound:.2f}'
               + (f'; the transport\'s floor alone {floor_bound:.2f}' if floor_bound is not None else '') + ')',
               speedup >= SPEEDUP_M2),
        Target(f'graph at M = 1 <= {M1_RATIO} x sequential', f'{m1_ms / m1_seq:.2f} x', m1_ms / m1_seq <= M1_RATIO),
        rate_target('default bag, rate mode, M = 2', default_rate, DEFAULT_RATE_P99_MS),
        rate_target('camera rate (4 x 640x480 at 30 Hz), rate mode, M = 2', camera_rate, CAMERA_RATE_P99_MS,
                    skipped_camera_rate),
    ] + [t for r in (15.0, 10.0) for t in slow_rate_targets(r, (slow_camera_rates or {}).get(r),
                                                            skipped_camera_rate)] + [live_offline_target(r, live_offline.get(r), skipped_live_offline) for r in live_offline_rates]
