"""Accuracy regression tests: generated scenario bags (fixed seeds) go through the whole graph
(`ego-motion replay`, lockstep, real nodes over DDS on 2 workers) and the odometry it
recorded (odometry.tum) is scored against the bag's /ground_truth/odom with the evaluator.
A change that makes the figures worse than the thresholds below fails.

Bags: 20 s at 8 Hz, 320 x 240, fx = 200 (the committed default bag's settings, so that what
`make run` shows is what is tested), seed 7. The whole file replays four bags, a few minutes
on two cores.
"""
from pathlib import Path

import pytest

from conftest import run_cli
from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories
from multicam_ego_motion.evaluation.trajectory_io import load_trajectory

SEED, DURATION_S, RATE_HZ, WIDTH, HEIGHT, FX = 7, 20, 8, 320, 240, 200
FRAMES = DURATION_S * RATE_HZ + 1

# scenario -> metric -> upper bound: the target, or tighter where the graph is well
# inside it (the measured figure plus a margin for platform differences in floating point:
# lockstep replay repeats itself to ~0.01 % on one machine). Seed-8 runs of the same
# scenarios (not tested) measured loop 0.60 % drift and +0.88 % scale, corridor 0.33 %,
# spin 0.43 %, lighting 0.56 %.
THRESHOLDS = {
    'loop': {
        'ate_pct': 0.6,                       # target 1.0 (measured 0.27)
        'final_drift_pct': 0.7,               # target 1.0 (measured 0.30)
        'rotation_drift_deg_per_m': 0.1,      # target (measured 0.052)
        'abs_scale_error_pct': 0.6,           # target 1.0 (measured 0.02)
    },
    'corridor': {'final_drift_pct': 1.5},     # target 2.0 (measured 0.31)
    'spin_then_drive': {'final_drift_pct': 1.5},   # target 2.0 (measured 0.55)
    'lighting': {'final_drift_pct': 1.0,      # target 2.0 (measured 0.15)
                 'ate_sim3_rmse_m': 0.25},    # no divergence: the shape holds
}


def _replay(scenario: str, root: Path) -> dict:
    bag = root / f'{scenario}_bag'
    r = run_cli('generate', '--scenario', scenario, '--out', bag, '--seed', SEED,
                '--duration', DURATION_S, '--rate', RATE_HZ, '--width', WIDTH, '--height', HEIGHT,
                '--fx', FX, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    out = root / f'{scenario}_replay'
    r = run_cli('replay', bag, '--out', out, '--workers', 2, timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    est = load_trajectory(out / 'odometry.tum')
    ref = load_trajectory(f'{bag}:/ground_truth/odom')
    m = evaluate_trajectories(ref, est)
    m['frames'] = len(est)
    m['abs_scale_error_pct'] = abs(m['scale_error_pct'])
    return m


@pytest.fixture(scope='module')
def metrics(tmp_path_factory):
    root = tmp_path_factory.mktemp('accuracy')
    return {s: _replay(s, root) for s in THRESHOLDS}


@pytest.mark.parametrize('scenario', sorted(THRESHOLDS))
def test_scenario_accuracy(metrics, scenario):
    m = metrics[scenario]
    assert m['frames'] == FRAMES, f'{scenario}: odometry for {m["frames"]} of {FRAMES} frames'
    summary = ', '.join(f'{k} {m[k]:.3f}' for k in THRESHOLDS[scenario])
    for key, bound in THRESHOLDS[scenario].items():
        assert m[key] <= bound, f'{scenario}: {key} {m[key]:.3f} > {bound} ({summary})'


def test_loop_without_wheel_odometry(tmp_path):
    """The wheel prior is optional: the committed loop bag without /wheel/odom. Nothing moves
    the fused poses at the start then, so the quarters put what they see of the floor on it
    from their first view (ground_plane) and track from the next frame; scale comes from
    the floor alone. Measured (seed 7): ATE 0.40 %, drift 0.34 %, 0.076 deg/m, scale -0.95 %."""
    import fault_injection as fi
    bag = fi.rewrite_bag(tmp_path / 'bag', DURATION_S + 1, fi.drop_topic('/wheel/odom'))
    out = tmp_path / 'replay'
    r = run_cli('replay', bag, '--out', out, '--workers', 2, '--lockstep', timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    m = evaluate_trajectories(load_trajectory(f'{bag}:/ground_truth/odom'),
                              load_trajectory(out / 'odometry.tum'))
    summary = (f"ATE {m['ate_pct']:.3f} %, drift {m['final_drift_pct']:.3f} %, "
               f"{m['rotation_drift_deg_per_m']:.4f} deg/m, scale {m['scale_error_pct']:+.2f} %")
    assert m['poses'] == FRAMES, summary
    assert m['ate_pct'] <= 1.0 and m['final_drift_pct'] <= 1.0, summary
    assert m['rotation_drift_deg_per_m'] <= 0.15 and abs(m['scale_error_pct']) <= 1.5, summary
