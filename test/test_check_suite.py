"""`ego-motion check`: suite validation, judging against limits and a baseline, the reports
(JUnit XML, summary, results.json), exit codes, and one end-to-end run on a short bag.

Everything but the last test runs without the graph: the replay is replaced by figures given
here, so these tests take a second.
"""
import json
import math
import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from conftest import REPO, run_cli
from multicam_ego_motion import cli
from multicam_ego_motion.check import command
from multicam_ego_motion.check.baseline import load_baseline
from multicam_ego_motion.check.figures import baseline_checks, limit_checks
from multicam_ego_motion.check.report import BagResult, junit_xml
from multicam_ego_motion.check.suite import load_suite
from multicam_ego_motion.errors import UserError

DEFAULT_BAG = REPO / 'bags' / 'default'
LOOP = {'scenario': 'loop', 'seed': 7, 'duration': 3, 'rate': 8, 'width': 320, 'height': 240}


def write_suite(folder: Path, doc, name='suite.yaml') -> Path:
    path = folder / name
    path.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc, sort_keys=False))
    return path


# ---- the suite file ----------------------------------------------------------------------

def test_suite_paths_defaults_and_names(tmp_path):
    (tmp_path / 'p.yaml').write_text('{}\n')
    path = write_suite(tmp_path, {
        'defaults': {'workers': 1, 'limits': {'odometry_share': 1.0, 'ate_pct': 2.0}},
        'baseline': 'base.json',
        'bags': [{'bag': str(DEFAULT_BAG), 'params': 'p.yaml', 'limits': {'ate_pct': 0.5}},
                 {'generate': LOOP, 'no_wheel': True, 'workers': 2, 'duration': 2.5,
                  'baseline_tolerance_pct': 10}]})
    suite = load_suite(path)
    a, b = suite.bags
    assert (a.name, a.bag, a.params, a.workers) == ('default', DEFAULT_BAG, tmp_path / 'p.yaml', 1)
    assert a.limits == {'ate_pct': 0.5, 'odometry_share': 1.0}       # own limit wins
    assert (b.name, b.generate.scenario, b.generate.duration, b.no_wheel) == ('loop', 'loop', 3.0, True)
    assert (b.workers, b.duration, b.baseline_tolerance_pct) == (2, 2.5, 10.0)
    assert suite.baseline == tmp_path / 'base.json'


@pytest.mark.parametrize('doc, where, words', [
    ({'bags': [{'bag': 'x', 'limits': {}}], 'extra': 1}, 'extra', 'unknown key'),
    ({'bags': []}, 'bags', 'non-empty list'),
    ({'bags': [{'generate': LOOP, 'limits': {'ate_pct': 1}},
               {'name': 'corridor', 'generate': {**LOOP, 'scenario': 'corridor'}, 'limts': {'ate_pct': 1}}]},
     'bags[1] (corridor): limts', 'unknown key (expected one of: name, bag, generate'),
    ({'bags': [{'name': 'loop', 'generate': LOOP, 'limits': {'ate': 1}}]},
     'bags[0] (loop): limits.ate', 'unknown key (expected one of: ate_pct'),
    ({'bags': [{'name': 'loop', 'generate': LOOP, 'limits': {'ate_pct': 'low'}}]},
     'bags[0] (loop): limits.ate_pct', "expected a number, got 'low'"),
    ({'bags': [{'name': 'loop', 'generate': LOOP, 'limits': {'odometry_share': 1.5}}]},
     'bags[0] (loop): limits.odometry_share', 'must be between 0 and 1'),
    ({'bags': [{'name': 'loop', 'generate': LOOP}]}, 'bags[0] (loop)', 'nothing to check'),
    ({'bags': [{'name': 'loop', 'generate': LOOP, 'bag': 'b', 'limits': {'ate_pct': 1}}]},
     'bags[0] (loop)', 'or import_kitti (a KITTI sequence), not bag and generate'),
    ({'bags': [{'name': 'loop', 'limits': {'ate_pct': 1}}]}, 'bags[0] (loop)', 'not none'),
    ({'bags': [{'name': 'k', 'import_kitti': {'folder': 'no_such_seq'}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (k): import_kitti.folder', 'no_such_seq not found'),
    ({'bags': [{'name': 'k', 'import_kitti': {'every': 2}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (k): import_kitti', 'needs a folder'),
    ({'bags': [{'name': 'k', 'import_kitti': {'folder': '.', 'stereo': False}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (k): import_kitti.stereo', 'unknown key'),
    ({'bags': [{'name': 'k', 'import_kitti': {'folder': '.', 'halves': 'yes'}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (k): import_kitti.halves', 'expected true or false'),
    ({'bags': [{'bag': 'missing_bag', 'limits': {'ate_pct': 1}}]},
     'bags[0] (missing_bag): bag', 'missing_bag not found'),
    ({'bags': [{'name': 'x', 'generate': {**LOOP, 'scenario': 'moon'}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): generate', "unknown scenario 'moon'"),
    ({'bags': [{'name': 'x', 'generate': {**LOOP, 'duration': 9000}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): generate', 'duration must be between 0.5 and 600 s'),
    ({'bags': [{'name': 'x', 'generate': {**LOOP, 'speed': 2}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): generate.speed', 'unknown key'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'workers': 0, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): workers', 'must be between 1 and 64'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'no_wheel': 'yes', 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): no_wheel', 'expected true or false'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'rig': 'nope.yaml', 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): rig', 'nope.yaml not found'),
    ({'bags': [{'name': 'a b', 'generate': LOOP, 'limits': {'ate_pct': 1}}]},
     'bags[0] (a b): name', 'use letters, digits'),
    ({'bags': [{'generate': LOOP, 'limits': {'ate_pct': 1}}, {'generate': LOOP, 'limits': {'ate_pct': 1}}]},
     'bags[1] (loop): name', 'same name as bags[0]'),
    ({'defaults': {'limits': {'ate_pct': -1}}, 'bags': [{'generate': LOOP}]},
     'defaults: limits.ate_pct', 'must be at least 0'),
    ({'defaults': {'name': 'x'}, 'bags': [{'generate': LOOP, 'limits': {'ate_pct': 1}}]},
     'defaults: name', 'unknown key'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'repeat': {'qualty_level': [0.01, 0.02]}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): repeat', "'qualty_level' is not a parameter of the quarter nodes"),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'repeat': {'predict_flow': [True, False]}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): repeat', "'predict_flow' is not a number"),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'repeat': {'quality_level': [0.01]}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): repeat.quality_level', 'expected a list of 2 to 9 values'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'repeat': {'quality_level': [0.01, 0.9]}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): repeat.quality_level', 'must be between 0.0001 and 0.5, got 0.9'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'repeat': {'min_features': [40, 40.5]}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): repeat.min_features', 'expected an integer, got 40.5'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'repeat': {'min_features': [40, 40]}, 'limits': {'ate_pct': 1}}]},
     'bags[0] (x): repeat.min_features', 'the same value twice'),
    ({'bags': [{'name': 'x', 'generate': LOOP, 'repeat': {'min_features': [40, 50], 'quality_level': [0.1, 0.2]},
                'limits': {'ate_pct': 1}}]},
     'bags[0] (x): repeat', 'expected one quarter parameter and its values, got 2 keys'),
])
def test_suite_errors_name_file_entry_and_key(tmp_path, doc, where, words):
    path = write_suite(tmp_path, doc)
    with pytest.raises(UserError) as e:
        load_suite(path)
    assert str(e.value).startswith(f'{path}: {where}: '), str(e.value)
    assert words in str(e.value)


def test_suite_not_yaml_names_the_line(tmp_path):
    path = write_suite(tmp_path, 'bags:\n  - name: loop\n    limits: {ate_pct: 1\n')
    with pytest.raises(UserError, match=rf'^{path}: not valid YAML at line \d+'):
        load_suite(path)


def test_generated_bags_are_cached_under_their_settings(tmp_path):
    from multicam_ego_motion.check.bags import GenerateSpec, ensure_generated, renderer_fingerprint
    spec = GenerateSpec('corridor', seed=3, duration=0.5, rate=4, width=64, height=48)
    bag = ensure_generated(tmp_path, spec)
    assert bag.name == f'corridor_s3_0.5s_4hz_64x48_{renderer_fingerprint()}'
    assert (bag / 'metadata.yaml').exists() and (bag / 'rig.yaml').exists()
    stamp = (bag / 'metadata.yaml').stat().st_mtime_ns
    assert ensure_generated(tmp_path, spec) == bag                       # reused, not rendered again
    assert (bag / 'metadata.yaml').stat().st_mtime_ns == stamp
    assert sorted(p.name for p in tmp_path.iterdir()) == [bag.name]     # no temporary left


# ---- judging -----------------------------------------------------------------------------

FIGS = {'ate_pct': 0.30, 'final_drift_pct': 0.50, 'rotation_drift_deg_per_m': 0.05,
        'abs_scale_error_pct': 0.0004, 'odometry_share': 0.99, 'ate_sim3_rmse_m': 0.1,
        'rpe_trans_pct': None, 'frames': 100}


def by_figure(checks):
    return {c.figure: c for c in checks}


def test_limits_are_upper_bounds_but_odometry_share_a_lower_one():
    c = by_figure(limit_checks('loop', FIGS, {'ate_pct': 0.30, 'final_drift_pct': 0.4,
                                              'odometry_share': 1.0, 'rpe_trans_pct': 5.0}))
    assert c['ate_pct'].passed                      # equal to the limit: allowed
    assert not c['final_drift_pct'].passed
    assert not c['odometry_share'].passed           # 99 of 100 frames, all required
    assert not c['rpe_trans_pct'].passed            # not measured: never passes a limit
    assert by_figure(limit_checks('loop', FIGS, {'odometry_share': 0.95}))['odometry_share'].passed
    assert c['final_drift_pct'].message() == 'loop: final_drift_pct 0.500, limit <= 0.4: FAIL'
    assert c['odometry_share'].condition() == '>= 1'


def test_baseline_allows_the_tolerance_and_one_printed_digit():
    base = {'ate_pct': 0.25, 'final_drift_pct': 0.50, 'rotation_drift_deg_per_m': 0.04,
            'abs_scale_error_pct': 0.0001, 'odometry_share': 1.0, 'ate_sim3_rmse_m': 0.2}
    c = by_figure(baseline_checks('loop', FIGS, base, 10.0, limits={'ate_sim3_rmse_m': 1.0}))
    assert set(c) == {'ate_pct', 'final_drift_pct', 'rotation_drift_deg_per_m',
                      'abs_scale_error_pct', 'odometry_share', 'ate_sim3_rmse_m'}
    assert not c['ate_pct'].passed and math.isclose(c['ate_pct'].bound, 0.275)   # 20 % worse
    assert c['final_drift_pct'].passed                         # unchanged
    assert not c['rotation_drift_deg_per_m'].passed            # 25 % worse
    assert c['abs_scale_error_pct'].passed                     # 4x, but below 0.001: not shown
    assert c['odometry_share'].passed and math.isclose(c['odometry_share'].bound, 0.9)
    assert c['ate_sim3_rmse_m'].passed                         # better
    assert c['ate_pct'].name == 'ate_pct vs baseline'
    assert c['ate_pct'].condition() == '<= 0.275 (baseline 0.250 + 10 %)'
    strict = by_figure(baseline_checks('loop', FIGS, base, 0.0, limits={}))
    assert not strict['odometry_share'].passed                 # 0.99 < 1.0 - 0.001
    assert strict['final_drift_pct'].passed


def test_baseline_without_the_bag_or_a_figure_is_skipped():
    (missing,) = baseline_checks('new_bag', FIGS, None, 5.0, {})
    assert missing.skipped and missing.passed and 'no baseline' in missing.condition()
    c = by_figure(baseline_checks('loop', FIGS, {'ate_pct': 0.3}, 5.0, {}))
    assert c['ate_pct'].passed and not c['ate_pct'].skipped
    assert c['final_drift_pct'].skipped and c['final_drift_pct'].passed


# ---- JUnit XML ---------------------------------------------------------------------------

def test_junit_xml_is_well_formed_and_names_bag_and_figure(tmp_path):
    ok = BagResult('loop', '/bags/loop', tmp_path / 'loop', seconds=20.0, figures=FIGS,
                   checks=limit_checks('loop', FIGS, {'ate_pct': 1.0, 'final_drift_pct': 0.1}))
    ok.checks += baseline_checks('loop', FIGS, None, 5.0, {})
    broken = BagResult('corridor', '/bags/corridor', tmp_path / 'corridor', seconds=3.5,
                       error='the graph published no /odom (see logs) & <more>')
    root = ET.fromstring(junit_xml('accuracy', [ok, broken]))
    assert root.tag == 'testsuites'
    assert (root.get('tests'), root.get('failures'), root.get('errors'), root.get('skipped')) == ('4', '1', '1', '1')
    assert float(root.get('time')) == pytest.approx(23.5)
    suites = {s.get('name'): s for s in root.iter('testsuite')}
    assert set(suites) == {'loop', 'corridor'}
    cases = {c.get('name'): c for c in suites['loop'].iter('testcase')}
    assert set(cases) == {'ate_pct', 'final_drift_pct', 'figures vs baseline'}
    for s in suites.values():
        float(s.get('time'))
        for c in s.iter('testcase'):
            float(c.get('time'))
            assert c.get('classname') == f'accuracy.{s.get("name")}'
    assert cases['ate_pct'].find('failure') is None
    failure = cases['final_drift_pct'].find('failure')
    assert failure.get('message') == 'loop: final_drift_pct 0.500, limit <= 0.1: FAIL'
    assert 'bag loop' in failure.text and 'figure final_drift_pct' in failure.text
    assert cases['figures vs baseline'].find('skipped') is not None
    (replay,) = suites['corridor'].iter('testcase')
    assert replay.get('name') == 'replay'
    assert replay.find('error').get('message').startswith('corridor: replay failed: the graph published no /odom')


# ---- the command, with the replay replaced -----------------------------------------------

@pytest.fixture
def fake_replay(monkeypatch):
    """`ego-motion check` in this process, each bag's replay giving figures[name]."""
    from multicam_ego_motion.ros_plumbing import dds_transport
    figures = {}
    monkeypatch.setattr(dds_transport, 'use_graph_profile', lambda env=None: False)
    monkeypatch.setattr(command, 'prepare',
                        lambda e, suite, cache, label: command.PreparedBag(e, Path(f'/bags/{e.name}'), None, None,
                                                                           REPO / 'config' / 'params.yaml'))

    def replay_and_score(p, out, params=None):
        f = figures[p.entry.name]
        if callable(f):              # figures from the params file the replay was given
            return f(yaml.safe_load(Path(params).read_text())), {}
        if isinstance(f, Exception):
            raise f
        return dict(f), {}
    monkeypatch.setattr(command, 'replay_and_score', replay_and_score)
    return figures


def check(*argv) -> int:
    return cli.main(['check', *map(str, argv)])


def two_bag_suite(tmp_path, **extra):
    return write_suite(tmp_path, {**extra, 'bags': [
        {'name': 'loop', 'generate': LOOP, 'limits': {'ate_pct': 0.5, 'odometry_share': 1.0}},
        {'name': 'lighting', 'generate': {**LOOP, 'scenario': 'lighting'},
         'limits': {'final_drift_pct': 1.0}, 'baseline_tolerance_pct': 10}]})


def test_exit_codes_and_outputs(tmp_path, fake_replay, capsys):
    suite = two_bag_suite(tmp_path)
    out = tmp_path / 'out'
    base = tmp_path / 'base.json'
    fake_replay['loop'] = {'ate_pct': 0.3, 'odometry_share': 1.0, 'frames': 25}
    fake_replay['lighting'] = {'final_drift_pct': 0.5, 'ate_pct': 0.4, 'frames': 25}

    # a bag compares with a baseline, and there is none: bad input
    assert check(suite, '--out', out) == 2
    assert 'lighting compare with a baseline' in capsys.readouterr().err
    assert not out.exists()                         # nothing replayed, nothing written

    assert check(suite, '--out', out, '--baseline', base, '--update-baseline') == 0
    assert load_baseline(base) == {'loop': fake_replay['loop'], 'lighting': fake_replay['lighting']}
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1] == 'check: all 3 checks of 2 bags pass'
    assert f'check: baseline written: {base}' in printed

    # worse than the baseline by more than 10 %, and a limit missed: exit 1, named
    fake_replay['lighting'] = {'final_drift_pct': 0.6, 'ate_pct': 0.4, 'frames': 25}
    fake_replay['loop'] = {'ate_pct': 0.3, 'odometry_share': 0.96, 'frames': 25}
    assert check(suite, '--out', out, '--baseline', base) == 1
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith('check: REGRESSION in 2 of ')
    assert 'loop odometry_share 0.960 (allowed >= 1)' in last
    assert 'lighting final_drift_pct vs baseline 0.600 (allowed <= 0.550 (baseline 0.500 + 10 %))' in last
    results = json.loads((out / 'results.json').read_text())
    assert results['failures'] == ['loop odometry_share', 'lighting final_drift_pct vs baseline']
    assert not results['passed'] and not results['bags']['loop']['passed']
    summary = re.sub(' +', ' ', (out / 'summary.md').read_text())
    assert '| lighting | final_drift_pct vs baseline | 0.600 |' in summary
    root = ET.parse(out / 'junit.xml').getroot()
    assert root.get('failures') == '2'

    # within the tolerance: 0 again (the same output folder is reused)
    fake_replay['lighting'] = {'final_drift_pct': 0.54, 'ate_pct': 0.4, 'frames': 25}
    fake_replay['loop'] = {'ate_pct': 0.3, 'odometry_share': 1.0, 'frames': 25}
    assert check(suite, '--out', out, '--baseline', base) == 0

    # an earlier run's results.json serves as a baseline too
    shutil.copy(out / 'results.json', tmp_path / 'previous.json')
    fake_replay['lighting'] = {'final_drift_pct': 0.6, 'ate_pct': 0.4, 'frames': 25}   # 0.54 -> 0.6
    assert check(suite, '--out', out, '--baseline', tmp_path / 'previous.json') == 1
    assert capsys.readouterr().out.splitlines()[-1].endswith(
        'lighting final_drift_pct vs baseline 0.600 (allowed <= 0.594 (baseline 0.540 + 10 %))')

    # --only, a replay that fails: exit 1 naming the bag; the baseline keeps its figures
    fake_replay['lighting'] = UserError('the graph did not come up within 60 s')
    assert check(suite, '--out', out, '--baseline', base, '--update-baseline', '--only', 'lighting') == 1
    assert capsys.readouterr().out.splitlines()[-1] == \
        'check: REGRESSION in 1 of 1 checks: lighting replay (error)'
    assert load_baseline(base)['lighting'] == {'final_drift_pct': 0.5, 'ate_pct': 0.4, 'frames': 25}
    assert set(load_baseline(base)) == {'loop', 'lighting'}

    assert check(suite, '--out', out, '--only', 'nope') == 2
    assert "--only: nope not in" in capsys.readouterr().err


def test_a_repeated_bag_is_judged_by_the_mean_of_its_replays(tmp_path, fake_replay, capsys):
    # each replay gets the params file with its value (the rest of the file as it was);
    # ATE and drift are averaged, odometry_share and the counts are the worst replay's
    suite = write_suite(tmp_path, {'bags': [{
        'name': 'drive', 'generate': LOOP, 'repeat': {'quality_level': [0.009, 0.01, 0.011]},
        'limits': {'ate_pct': 1.0, 'final_drift_pct': 2.0, 'odometry_share': 1.0}}]})
    assert load_suite(suite).bags[0].repeat.labels() == \
        ['quality_level=0.009', 'quality_level=0.01', 'quality_level=0.011']
    ate = {0.009: 0.7, 0.01: 1.4, 0.011: 0.6}           # one replay over the limit, the mean under it

    def replay(params):
        q = params['/**/quarter_node']['ros__parameters']
        assert q['min_features'] == 40                   # the package's file, one value changed
        v = q['quality_level']
        return {'ate_pct': ate[v], 'final_drift_pct': 1.0 + v * 100, 'odometry_share': 1.0,
                'frames': 160, 'frames_with_odometry': 160, 'odometry_poses': 160}
    fake_replay['drive'] = replay
    out = tmp_path / 'out'
    assert check(suite, '--out', out) == 0
    printed = capsys.readouterr().out
    assert 'check: [1/1] drive: quality_level=0.01: ATE 1.400 %, final drift 2.000 %, /odom for 160 of 160 frames' \
        in printed
    f = json.loads((out / 'results.json').read_text())['bags']['drive']['figures']
    assert f['ate_pct'] == pytest.approx(0.9) and f['final_drift_pct'] == pytest.approx(2.0)
    assert [r['ate_pct'] for r in f['replays']] == [0.7, 1.4, 0.6]
    for v in (0.009, 0.01, 0.011):
        written = yaml.safe_load((out / 'drive' / f'quality_level={v:g}' / 'params.yaml').read_text())
        assert written['/**/quarter_node']['ros__parameters']['quality_level'] == v

    # one replay short of a frame's /odom fails the bag, whatever the others did
    def short(params):
        f = replay(params)
        if params['/**/quarter_node']['ros__parameters']['quality_level'] == 0.011:
            f.update(odometry_share=159 / 160, frames_with_odometry=159, odometry_poses=159)
        return f
    fake_replay['drive'] = short
    assert check(suite, '--out', out) == 1
    assert capsys.readouterr().out.splitlines()[-1].endswith('drive odometry_share 0.994 (allowed >= 1)')
    f = json.loads((out / 'results.json').read_text())['bags']['drive']['figures']
    assert (f['frames_with_odometry'], f['frames']) == (159, 160)

    # the mean over the limit: a regression
    ate[0.009] = 1.2
    fake_replay['drive'] = replay
    assert check(suite, '--out', out) == 1
    assert capsys.readouterr().out.splitlines()[-1].endswith('drive ate_pct 1.067 (allowed <= 1)')


def test_output_folder_of_something_else_is_refused(tmp_path, fake_replay, capsys):
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'notes.txt').write_text('mine')
    assert check(two_bag_suite(tmp_path, baseline='b.json'), '--out', out, '--update-baseline') == 2
    assert 'is not empty' in capsys.readouterr().err
    assert (out / 'notes.txt').read_text() == 'mine'


def test_bad_suite_is_one_line_and_exit_2(tmp_path):
    path = write_suite(tmp_path, {'bags': [{'name': 'loop', 'generate': LOOP, 'limits': {'drift': 1}}]})
    r = run_cli('check', path, '--out', tmp_path / 'out')
    assert r.returncode == 2
    assert r.stderr.strip() == (f'ego-motion: error: {path}: bags[0] (loop): limits.drift: unknown key '
                                '(expected one of: ate_pct, final_drift_pct, rotation_drift_deg_per_m, '
                                'abs_scale_error_pct, odometry_share, ate_rmse_m, ate_se3_rmse_m, '
                                'ate_sim3_rmse_m, ate_sim3_pct, first_odometry_s, final_drift_m, '
                                'rpe_trans_pct, rpe_rot_deg_per_m)')


# ---- end to end --------------------------------------------------------------------------

def test_short_bag_passes_loose_limits_and_fails_an_impossible_one(tmp_path):
    """3 s of the committed default bag, twice through the graph: loose limits pass, a final
    drift of 0 cannot; the baseline written holds what was measured."""
    from multicam_ego_motion.evaluation.evaluate import evaluate_trajectories
    from multicam_ego_motion.evaluation.trajectory_io import load_trajectory
    suite = write_suite(tmp_path, {
        'baseline': 'baseline.json',
        'defaults': {'duration': 3, 'workers': 2},
        'bags': [{'name': 'short', 'bag': str(DEFAULT_BAG),
                  'limits': {'ate_pct': 50, 'final_drift_pct': 50, 'odometry_share': 1.0}},
                 {'name': 'short_strict', 'bag': str(DEFAULT_BAG), 'limits': {'final_drift_pct': 0.0}}]})
    out = tmp_path / 'out'
    r = run_cli('check', suite, '--out', out, '--update-baseline', timeout=300)
    assert r.returncode == 1, r.stdout + r.stderr
    last = r.stdout.strip().splitlines()[-1]
    assert last.startswith('check: REGRESSION in 1 of 4 checks: short_strict final_drift_pct '), last

    results = json.loads((out / 'results.json').read_text())
    short = results['bags']['short']
    assert short['passed'] and short['error'] is None
    assert [c['figure'] for c in short['checks']] == ['ate_pct', 'final_drift_pct', 'odometry_share']
    assert short['figures']['frames'] == short['figures']['frames_with_odometry'] == 24   # 0 .. 2.875 s
    # the figures are the evaluator's, of the odometry the graph recorded
    m = evaluate_trajectories(load_trajectory(f'{DEFAULT_BAG}:/ground_truth/odom'),
                              load_trajectory(out / 'short' / 'odometry.tum'))
    assert short['figures']['ate_pct'] == m['ate_pct'] and 0 < m['ate_pct'] < 50
    # lockstep: both runs of the same 3 s measured the same
    assert results['bags']['short_strict']['figures'] == short['figures']
    for plot in short['plots']:
        assert (out / plot).stat().st_size > 0
    assert len(short['plots']) == 2

    root = ET.parse(out / 'junit.xml').getroot()
    (failure,) = root.iter('failure')
    assert failure.get('message').startswith('short_strict: final_drift_pct ')
    assert '| short_strict | final_drift_pct | ' in re.sub(' +', ' ', (out / 'summary.md').read_text())
    assert load_baseline(tmp_path / 'baseline.json')['short'] == short['figures']


def test_a_frame_stamped_between_microseconds_counts_as_having_odometry():
    """A KITTI times.txt stamp at x.5 us, its /odom stamp in float seconds: the same frame."""
    from multicam_ego_motion.check.figures import figures_from
    base = 1_704_067_200 * 10 ** 9
    frames = [base + 103_875_200, base + 5_123_456_500, base + 9_999_999_900]
    f = figures_from({'scale_error_pct': 0.0, 'path_length_m': 1.0}, frames, [ns * 1e-9 for ns in frames])
    assert f['frames_with_odometry'] == 3 and f['odometry_share'] == 1.0
    # a frame 30 ms from any /odom is still missing
    f = figures_from({'scale_error_pct': 0.0, 'path_length_m': 1.0}, frames, [ns * 1e-9 + 0.03 for ns in frames])
    assert f['frames_with_odometry'] == 0
