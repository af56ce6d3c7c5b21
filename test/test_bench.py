"""`ego-motion bench`: the figures and the targets table computed from given numbers (no run,
no timing asserted), and the options that leave out its long parts."""
import math

import pytest

from multicam_ego_motion.bench import targets as bench_targets
from multicam_ego_motion.bench.measures import RateFigures, rate_figures, relative_difference, track_cost
from conftest import run_cli


def quarter(cam, q, features, track_ms, **more):
    return f'ego_motion/{cam}/q{q}', {'features': str(features), 'track_ms': f'{track_ms:.3f}',
                                      'state': 'tracking', **more}


def test_track_cost_sums_over_quarters_and_frames():
    statuses = [quarter('front', 1, 100, 1.0), quarter('front', 2, 50, 2.0),     # frame 1
                quarter('front', 1, 150, 3.0), quarter('rear', 4, 0, 0.5),        # frame 2
                # not quarters: arbiters report other stage times, never counted
                ('ego_motion/front/arbiter', {'arbiter_ms': '9.0', 'features': '999'}),
                ('ego_motion/general_arbiter', {'arbiter_ms': '9.0'}),
                # a quarter without a tracking report (before its CameraInfo) is skipped
                ('ego_motion/left/q3', {'state': 'waiting'})]
    c = track_cost(statuses)
    assert (c.track_ms, c.points, c.reports) == (pytest.approx(6.5), 300, 4)
    assert c.us_per_point == pytest.approx(6.5e3 / 300)
    assert c.points_per_report == pytest.approx(75)
    assert math.isnan(track_cost([('ego_motion/front/arbiter', {})]).us_per_point)


def test_rate_figures_latency_drops_and_real_time_factor():
    # 4 frames at 10 Hz (bag_s counts one period past the last: 0.4 s); the third got no /odom
    published = {100: 10.0, 200: 10.1, 300: 10.2, 400: 10.3}
    received = {100: 10.05, 200: 10.12, 400: 10.38, 999: 11.0}
    f = rate_figures(published, received, bag_s=0.4, n_frames=4)
    assert f.frames == 4 and f.dropped == 1
    assert sorted(f.latencies_ms) == pytest.approx([20.0, 50.0, 80.0])
    assert f.p50 == pytest.approx(50.0)
    # first publish 10.0 -> last /odom 10.38, plus one period 0.1
    assert f.rtf == pytest.approx(0.4 / 0.48)
    nothing = rate_figures(published, {}, bag_s=0.4, n_frames=4)
    assert nothing.dropped == 4 and math.isnan(nothing.rtf) and math.isnan(nothing.p99)


def test_relative_difference_live_vs_offline():
    assert relative_difference(1.1, 1.0) == pytest.approx(0.1)
    assert relative_difference(0.9, 1.0) == pytest.approx(0.1)
    assert math.isnan(relative_difference(1.0, 0.0))
    assert math.isnan(relative_difference(float('nan'), 1.0))


def figures(rtf, dropped, p99, frames=100):
    return RateFigures(frames, rtf, [p99] * (frames - dropped))


def targets(**kw):
    args = dict(seq_ms=150.0, seq_cpu_ms=148.0, m1_ms=160.0, m2_ms=94.0, graph_cpu_m2_ms=165.0,
                replay_cpu_m2_ms=8.5, speedup_bound=1.74, default_rate=figures(1.0, 0, 45.0))
    args.update(kw)
    return {t.name.split(':')[0].split(' <=')[0].split(' >=')[0]: t for t in bench_targets.bench_targets(**args)}


def test_targets_from_given_numbers():
    t = targets(camera_rate=figures(0.86, 33, 250.0, frames=301),
                slow_camera_rates={15.0: (figures(1.0, 0, 80.0), 0.93), 10.0: (figures(1.0, 0, 60.0), 0.71)},
                live_offline={10.0: (0.02, 0.01), 15.0: (0.05, 0.02), 30.0: (0.05, 0.30)})
    assert len(t) == 13
    seq = t['sequential pipeline CPU per frame']
    assert (seq.measured, seq.met) == ('148.0 ms', False)
    over = next(v for k, v in t.items() if k.startswith('graph overhead'))
    assert over.measured.startswith('25.5 ms') and over.met is False     # 165 + 8.5 - 148
    sp = t['speedup at M = 2']
    assert sp.measured == '1.60 (the CPU time allows 1.74)' and sp.met is False
    sp = targets(floor_bound=1.77)['speedup at M = 2']
    assert sp.measured == "1.60 (the CPU time allows 1.74; the transport's floor alone 1.77)"
    m1 = t['graph at M = 1']
    assert m1.measured == '1.07 x' and m1.met is True
    m1 = targets(m1_seq_ms=120.0)['graph at M = 1']     # against the sequential runs around it
    assert m1.measured == '1.33 x' and m1.met is False
    assert t['default bag, rate mode, M = 2'].met is True
    cam = next(v for k, v in t.items() if k.startswith('camera rate'))
    assert cam.measured == 'RTF 0.86, 33 of 301 dropped, p99 250 ms' and cam.met is False
    live = [v for k, v in t.items() if k.startswith('live')]
    assert [v.met for v in live] == [True, True, False]
    assert live[2].measured == 'ATE 5.0 %, final drift 30.0 % apart'
    # 15 and 10 Hz: every frame, and at most one core at the reference speed
    slow = [v for k, v in t.items() if k.startswith('camera rate (4 x 640x480 at 1')]
    assert [v.met for v in slow] == [True, True]
    cores = [v for k, v in t.items() if k.startswith('cores needed')]
    assert [(v.measured, v.met) for v in cores] == [('0.93', True), ('0.71', True)]
    over = targets(slow_camera_rates={15.0: (figures(1.0, 0, 80.0), 1.32)})
    assert next(v for k, v in over.items() if k.startswith('cores needed, 4 x 640x480 at 15')).met is False


def test_targets_met_at_their_bounds_and_not_run_when_skipped():
    t = targets(seq_cpu_ms=45.0, graph_cpu_m2_ms=50.0, replay_cpu_m2_ms=5.0, seq_ms=180.0, m1_ms=225.0,
                m2_ms=100.0, default_rate=figures(0.98, 0, 50.0),
                skipped_camera_rate='--skip-camera-rate', skipped_live_offline='--skip-live-vs-offline')
    measured = [v for v in t.values() if v.met is not None]
    assert len(measured) == 5 and all(v.met for v in measured)
    skipped = [v for v in t.values() if v.met is None]
    assert [v.measured for v in skipped] == ['skipped (--skip-camera-rate)'] * 5 + ['skipped (--skip-live-vs-offline)'] * 3
    # a drop, or a p99 one ms over, misses
    assert not bench_targets.rate_target('x', figures(1.0, 1, 10.0), 50.0).met
    assert not bench_targets.rate_target('x', figures(1.0, 0, 51.0), 50.0).met


def test_targets_table_one_row_each():
    lines = bench_targets.table([bench_targets.Target('a <= 1', '0.5', True),
                                 bench_targets.Target('b >= 2', '1.0', False),
                                 bench_targets.Target('c', 'skipped (--x)', None)])
    assert lines[:2] == ['| target | measured | |', '|---|---|---|']
    assert lines[2:] == ['| a <= 1 | 0.5 | met |', '| b >= 2 | 1.0 | **missed** |', '| c | skipped (--x) | not run |']


def test_bench_help_lists_the_skip_options():
    r = run_cli('bench', '--help')
    assert r.returncode == 0, r.stderr
    for opt in ('--skip-transport-floor', '--skip-camera-rate', '--skip-live-vs-offline', '--skip-imu',
                '--camera-rate-bags'):
        assert opt in r.stdout


def test_crash_row_reports_the_restore_and_what_was_published_again():
    from multicam_ego_motion.bench.worker_crash import CrashFigures
    lines = CrashFigures(frames=161, odom=161, restore_s=[0.71], republished=1, wall_ms_per_frame=40.0,
                         longest_gap_s=1.234, partial=2, hosted_general=True, published_ahead=3).lines()
    text = '\n'.join(lines)
    assert '| killed after frame | 53 of 161 |' in text and '| time to restore its nodes on the spare [s] | 0.71 |' in text
    assert '| frames with /odom | 161 of 161 |' in text and '| frames published again | 1 |' in text
    assert '| longest wait between two /odom [s] | 1.23 |' in text
    assert '| of those, fused without some camera | 2 |' in text
    assert '| it hosted the general arbiter | yes |' in text
    assert '| frames let out while an older one stalled (2 s without /odom) | 3 |' in text
    assert 'none (not restored)' in '\n'.join(CrashFigures(10, 3, [], 0, 1.0).lines())


def test_machine_speed_reference_work():
    """The bench's machine line: fixed reference work whose figures are real measurements
    (the flow it times finds the known shift of its synthetic quarter)."""
    import cv2
    import numpy as np
    from multicam_ego_motion.bench import machine_speed
    a, b = machine_speed._quarter_pair()
    assert a.shape == b.shape == (120, 160)
    p0 = cv2.goodFeaturesToTrack(a, 80, 0.01, 5)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(21, 21), maxLevel=3)
    ok = st.ravel() == 1
    assert len(p0) >= 60 and ok.mean() > 0.9
    assert np.allclose(np.median((p1 - p0).reshape(-1, 2)[ok], axis=0), [2.3, -1.6], atol=0.05)
    s = machine_speed.measure()
    assert s.cpus >= 1 and s.cpu
    assert 0.0 < s.lk_us_per_point < 1e4 and 0.0 < s.python_ms < 1e5
    line = s.line()
    assert f'{s.lk_us_per_point:.1f} us per point' in line and f'{s.python_ms:.1f} ms' in line


def test_each_graph_run_is_compared_with_the_sequential_runs_around_it():
    from multicam_ego_motion.bench.timing import DefaultBagRuns
    # the host slowed down between the runs: the sequential pipeline took 30 ms, then 36, then 36
    d = DefaultBagRuns(seq_runs=[(30.0, 30.0), (36.0, 36.0), (36.0, 36.0)],
                       lockstep_runs={1: [(33.0, 10, 33.0, 2.0), (39.6, 10, 39.6, 2.0)],
                                      2: [(18.0, 10, 34.0, 2.0), (20.5, 10, 40.0, 2.0)]},
                       brackets={1: [0, 1], 2: [0, 1]}, rate_run=None, cores=2)
    # M = 2: 33 / 18 = 1.83 in the first minutes, 36 / 20.5 = 1.76 later: the first counts,
    # against the sequential runs around it (not the fastest of all: 30 / 18 = 1.67)
    assert d.best[2] == (18.0, 10, 34.0, 2.0)
    assert d.Ts == 33.0 and d.Ts_cpu == 33.0
    assert math.isclose(d.ceiling, 33.0 / (36.0 / 2))
    # M = 1: 33 / 33 = 1.0 against 36 / 39.6 = 0.91: the first, with its own sequential runs
    assert d.best[1][0] == 33.0 and d.sequential_around(1) == (33.0, 33.0)


def test_decode_cost_row_per_input_kind():
    """The bench's decode table: one row per input kind, each input one the graph reads as
    the scene's gray image (what is timed is the real conversion, not a failure)."""
    import cv2
    import numpy as np
    from camera_pose_nodes.image_conversion import image_msg_to_gray
    from multicam_ego_motion.bench import decode_cost
    gray = cv2.cvtColor(decode_cost.scene(), cv2.COLOR_BGR2GRAY).astype(float)
    kinds = decode_cost.inputs()
    for name, msg in kinds:
        g = image_msg_to_gray(msg, (640, 480)).astype(float)
        assert np.abs(g - gray)[4:-4, 4:-4].mean() < 3.0, name
    rows = decode_cost.measure(repeats=1)
    assert [r[0] for r in rows] == [k for k, _ in kinds]
    text = '\n'.join(decode_cost.lines(rows))
    for name, size, ms in rows:
        assert f'| {name} | {size} | {ms:.2f} |' in text


def test_cores_needed_per_camera_rate_here_and_at_the_reference_speed():
    from pathlib import Path

    from multicam_ego_motion.bench.camera_rate import CameraRate, RateRun
    run = lambda graph_ms, player_ms: RateRun(figures(1.0, 0, 50.0), Path('.'), Path('.'), 'reused', 150,
                                              10.0, graph_ms, player_ms, 800.0)
    # 4 cameras: (20 + 2) ms per image -> 88 ms per frame
    c = CameraRate([], {30.0: run(12.0, 1.0), 15.0: run(20.0, 2.0), 10.0: run(25.0, 2.5)}, 4)
    assert c.cores(15.0) == pytest.approx(88.0 * 15 / 1000)
    assert c.cores(10.0) == pytest.approx(110.0 * 10 / 1000)
    assert c.figures is c.runs[30.0].figures and c.cpu_per_image_ms == 12.0
    # on a machine at 12 us per LK point the reference (6 us) machine needs half
    line = c.cores_line(12.0)
    assert '15 Hz 1.32' in line and 'at 6 us per Lucas-Kanade point: 30 Hz 0.78, 15 Hz 0.66, 10 Hz 0.55' in line


def test_imu_cost_row_compares_the_interleaved_rounds():
    from multicam_ego_motion.bench.imu_cost import TARGET_PCT, ImuCost
    c = ImuCost(without_ms=[40.0, 38.0], with_ms=[41.0, 40.0])
    assert abs(c.extra_pct - 100.0 * (40.5 - 39.0) / 39.0) < 1e-9 and c.met
    assert c.lines()[-1] == '| 2 rounds, interleaved | 40.0, 38.0 | 41.0, 40.0 | +3.8 % |'
    assert not ImuCost([40.0], [40.0 * (1 + TARGET_PCT / 100) + 0.1]).met
