"""`ego-motion profile`: the attribution of own time to stage x kind on small synthetic
pstats-like graphs, and the table on the first frames of the default bag."""
import math
import pstats

import pytest

from conftest import REPO, run_cli
from multicam_ego_motion.bench.profile_table import (MATH, OPENCV, OTHER, PYTHON, ROSMSG, STAGES,
                                               attribute, kind_of)

ROOTS = {('a.py', 'A'): 'stage a', ('b.py', 'B'): 'stage b'}


def fn(path, name):
    return (path, 1, name)


MAIN = fn('/p/multicam_ego_motion/main.py', 'main')
A = fn('/p/multicam_ego_motion/a.py', 'A')
B = fn('/p/multicam_ego_motion/b.py', 'B')
HELPER = fn('/p/camera_pose_nodes/helper.py', 'helper')


def entry(tt, ct, callers):
    """pstats' (cc, nc, tt, ct, callers); callers: {caller: (nc, cc, tt, ct)}."""
    return (1, 1, tt, ct, callers)


def total(stats):
    return sum(v[2] for v in stats.values())


def test_helper_split_by_caller_time():
    np_array = ('~', 0, '<built-in method numpy.array>')
    stats = {
        MAIN: entry(0.5, 10.0, {}),
        A: entry(1.0, 7.0, {MAIN: (1, 1, 1.0, 7.0)}),
        B: entry(1.0, 3.0, {MAIN: (1, 1, 1.0, 3.0)}),
        # called from A for 3/4 of its time, from B for 1/4
        HELPER: entry(4.0, 6.0, {A: (3, 3, 3.0, 4.5), B: (1, 1, 1.0, 1.5)}),
        np_array: entry(2.0, 2.0, {HELPER: (4, 4, 2.0, 2.0)}),
    }
    cells = attribute(stats, ROOTS)
    assert cells[('stage a', PYTHON)] == pytest.approx(1.0 + 3.0)
    assert cells[('stage b', PYTHON)] == pytest.approx(1.0 + 1.0)
    # the helper's callee goes up by the helper's per-caller cumulative times: 4.5 : 1.5
    assert cells[('stage a', MATH)] == pytest.approx(1.5)
    assert cells[('stage b', MATH)] == pytest.approx(0.5)
    assert cells[(OTHER, PYTHON)] == pytest.approx(0.5)
    assert sum(cells.values()) == pytest.approx(total(stats))


def test_builtins_of_no_library_count_as_their_callers_kind():
    mcap = fn('/venv/site-packages/mcap/reader.py', 'read')
    append = ('~', 0, "<method 'append' of 'list' objects>")
    stats = {
        A: entry(1.0, 4.0, {}),
        mcap: entry(1.0, 2.0, {A: (1, 1, 1.0, 2.0)}),
        append: entry(2.0, 2.0, {A: (1, 1, 1.0, 1.0), mcap: (1, 1, 1.0, 1.0)}),
    }
    cells = attribute(stats, ROOTS)
    assert cells[('stage a', PYTHON)] == pytest.approx(1.0 + 1.0)
    assert cells[('stage a', ROSMSG)] == pytest.approx(1.0 + 1.0)


def test_nearest_root_wins_and_recursion_ends():
    process = fn('/p/camera_pose_nodes/quarter_estimator.py', 'process_image')
    track = fn('/p/camera_pose_nodes/klt_tracker.py', 'track')
    flow = fn('/p/camera_pose_nodes/klt_tracker.py', 'flow')
    lk = ('~', 0, '<calcOpticalFlowPyrLK>')
    ekf = fn('/p/camera_pose_nodes/pose_ekf.py', 'update')
    # g and h call each other and themselves, and are reached from the pose stage and from
    # nowhere (a cycle with no root above it)
    g, h = fn('/p/camera_pose_nodes/x.py', 'g'), fn('/p/camera_pose_nodes/x.py', 'h')
    stats = {
        process: entry(1.0, 10.0, {}),
        track: entry(0.5, 3.5, {process: (1, 1, 0.5, 3.5)}),
        flow: entry(0.5, 3.0, {track: (1, 1, 0.5, 3.0)}),
        lk: entry(2.5, 2.5, {flow: (2, 2, 2.5, 2.5)}),
        ekf: entry(1.0, 3.0, {process: (1, 1, 1.0, 3.0)}),
        g: entry(1.0, 2.0, {ekf: (1, 1, 0.5, 1.0), h: (5, 5, 0.5, 1.0), g: (3, 0, 0.2, 0.5)}),
        h: entry(1.0, 2.0, {g: (5, 5, 1.0, 2.0), h: (2, 0, 0.1, 0.1)}),
    }
    cells = attribute(stats)
    assert cells[('track', OPENCV)] == pytest.approx(2.5)
    assert cells[('track', PYTHON)] == pytest.approx(1.0)
    # everything else ends in process_image: h only through g, g through ekf (the cycle is cut)
    assert cells[('pose', PYTHON)] == pytest.approx(1.0 + 1.0 + 1.0 + 1.0)
    assert sum(cells.values()) == pytest.approx(total(stats))
    assert set(s for s, _ in cells) <= set(STAGES)


def test_a_cycle_without_a_root_is_other():
    g, h = fn('/p/camera_pose_nodes/x.py', 'g'), fn('/p/camera_pose_nodes/x.py', 'h')
    stats = {g: entry(1.0, 2.0, {h: (1, 1, 1.0, 2.0)}), h: entry(1.0, 2.0, {g: (1, 1, 1.0, 2.0)})}
    assert attribute(stats) == {(OTHER, PYTHON): pytest.approx(2.0)}


def test_closures_of_a_root_belong_to_it(tmp_path):
    # flow and extract both hand their per-item closure to one helper, mostly under flow:
    # one level of callers would put most of the corner search into track
    src = tmp_path / 'klt_tracker.py'
    src.write_text('\n'.join([
        'class KLTTracker:',                       # 1
        '    def _map(self, fn, items):',          # 2
        '        return [fn(i) for i in items]',   # 3
        '    def flow(self, crop):',               # 4
        '        def lk(chunk):',                  # 5
        '            return chunk',                # 6
        '        return self._map(lk, [1])',       # 7
        '    def extract(self, stamp_ns):',        # 8
        '        def corners(cell):',              # 9
        '            return cell',                 # 10
        '        return self._map(corners, [1])',  # 11
        '']))
    path = str(src)
    flow, extract = (path, 4, 'flow'), (path, 8, 'extract')
    helper, lk, corners = (path, 2, '_map'), (path, 5, 'lk'), (path, 9, 'corners')
    gftt = ('~', 0, '<goodFeaturesToTrack>')
    stats = {
        flow: entry(0.0, 9.0, {}),
        extract: entry(0.0, 1.0, {}),
        helper: entry(0.0, 10.0, {flow: (1, 1, 0.0, 9.0), extract: (1, 1, 0.0, 1.0)}),
        lk: entry(9.0, 9.0, {helper: (1, 1, 9.0, 9.0)}),
        corners: entry(0.0, 1.0, {helper: (1, 1, 0.0, 1.0)}),
        gftt: entry(1.0, 1.0, {corners: (1, 1, 1.0, 1.0)}),
    }
    cells = attribute(stats)
    assert cells == {('track', PYTHON): pytest.approx(9.0), ('extract', OPENCV): pytest.approx(1.0)}


@pytest.mark.parametrize('func, kind', [
    (('~', 0, '<calcOpticalFlowPyrLK>'), OPENCV),
    (('~', 0, '<goodFeaturesToTrack>'), OPENCV),
    (('~', 0, "<method 'reduce' of 'numpy.ufunc' objects>"), MATH),
    (('~', 0, '<built-in method scipy.linalg._batched_linalg._inv>'), MATH),
    (('~', 0, '<built-in method rclpy._rclpy_pybind11.rclpy_deserialize>'), ROSMSG),
    (('~', 0, "<method 'decompress' of 'zstandard.backend_c.ZstdDecompressor' objects>"), ROSMSG),
    (('~', 0, '<built-in method builtins.len>'), None),
    (('/v/site-packages/numpy/linalg/_linalg.py', 1, 'eigh'), MATH),
    (('/v/site-packages/filterpy/kalman/EKF.py', 1, 'update'), MATH),
    (('/v/site-packages/geometry_msgs/msg/_quaternion.py', 1, 'z'), ROSMSG),
    (('/v/site-packages/mcap/reader.py', 1, 'iter_messages'), ROSMSG),
    (('/r/multicam_ego_motion/bag/rosbag2_reader.py', 1, 'decoded'), ROSMSG),
    (('/r/multicam_ego_motion/ros_plumbing/pose_messages.py', 1, 'estimate_to_msg'), ROSMSG),
    (('/r/camera_pose_nodes/quarter_estimator.py', 1, '_triangulate'), PYTHON),
    (('/v/site-packages/yaml/reader.py', 1, 'forward'), None),
])
def test_kind_of(func, kind):
    assert kind_of(func) == kind


def _cells(line):
    return [c.strip() for c in line.strip().strip('|').split('|')]


def test_profile_table_on_the_default_bag(tmp_path):
    out = tmp_path / 'out'
    r = run_cli('profile', REPO / 'bags' / 'default', '--out', out, '--frames', 5, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    text = (out / 'profile.md').read_text()
    assert text in r.stdout
    rows = {}
    for line in text.splitlines():
        c = _cells(line)
        if line.startswith('| ') and len(c) == 7 and c[0].strip('*') in set(STAGES) | {'total'}:
            rows[c[0].strip('*')] = [float(v) for v in c[1:6]]
    assert set(rows) == set(STAGES) | {'total'}
    for name, vals in rows.items():       # the kinds add up to the row's total
        assert math.isclose(sum(vals[:4]), vals[4], rel_tol=0.02, abs_tol=0.03), name
    stage_sum = sum(vals[4] for name, vals in rows.items() if name != 'total')
    assert math.isclose(stage_sum, rows['total'][4], rel_tol=0.02)
    profile_ms = sum(v[2] for v in pstats.Stats(str(out / 'sequential.prof')).stats.values()) / 5 * 1e3
    assert math.isclose(rows['total'][4], profile_ms, rel_tol=0.03)
    # the work is where it should be
    assert rows['track'][0] > 0 and rows['extract'][0] > 0        # OpenCV: LK flow, corners
    assert rows['bag reading and image decoding'][3] > 0
    assert 'without the profiler' in text and 'Top 15 functions' in text
    assert len([l for l in text.splitlines() if '`' in l and l.startswith('| ')]) == 15
