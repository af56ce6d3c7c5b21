"""`ego-motion bench`: the figures computed from given numbers (no run, no timing asserted),
and the options that leave out its long parts."""
import math

import pytest

from multicam_ego_motion.bench_measures import rate_figures, relative_difference, track_cost
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


def test_bench_help_lists_the_skip_options():
    r = run_cli('bench', '--help')
    assert r.returncode == 0, r.stderr
    for opt in ('--skip-camera-rate', '--skip-live-vs-offline', '--camera-rate-bags'):
        assert opt in r.stdout
