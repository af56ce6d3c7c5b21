"""Fault injection, bags: damaged files and bag contents the product must name, not trip over.

Input errors found before the graph starts end in one line on stderr, exit code 2, no
traceback. A bag damaged in the middle fails the replay at the damage with the same kind of
message, and the output bag holds everything the graph published until then.
"""
import pytest
from mcap.reader import make_reader
from std_msgs.msg import String

import fault_injection as fi
from fault_replays import FRAMES
from replay_run import ReplayRun, replay


def assert_one_line_error(run: ReplayRun, *words, graph_started=False):
    """Exit code 2 and the error as one line, no traceback. Once the graph has started, the
    replay's own ROS log lines (INFO, on stderr) come before it: the error is the last line."""
    assert run.returncode == 2, run
    lines = run.stderr.strip().splitlines()
    errors = [l for l in lines if l.startswith('ego-motion: error: ')]
    assert len(errors) == 1 and lines[-1] == errors[0], run
    if not graph_started:
        assert len(lines) == 1, run
    assert 'Traceback' not in run.stderr
    for w in words:
        assert w in errors[0], (w, errors[0])


@pytest.mark.parametrize('fraction', [0.002, 0.6])
def test_truncated_mcap_is_named_before_the_graph_starts(tmp_path, fraction):
    # Cut short, a file looks like one whose writer was killed: unfinished, and recoverable.
    bag = fi.rewrite_bag(tmp_path / 'bag', 2)
    fi.truncate(bag, fraction)
    run = replay(bag, tmp_path / 'out', timeout=60)
    assert_one_line_error(run, 'is unfinished', str(fi.mcap_file(bag)), f'`ego-motion reindex {bag}`')
    assert not (tmp_path / 'out' / 'output').exists()
    assert run.leftover_processes() == []


def test_corrupt_chunk_fails_at_the_damage_and_keeps_what_was_recorded(tmp_path):
    # Small chunks so that the damage lands about 1 s into the bag.
    bag = fi.rewrite_bag(tmp_path / 'bag', 3, chunk_size=256 * 1024)
    with open(fi.mcap_file(bag), 'rb') as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    damaged = 4
    fi.corrupt_chunk(bag, damaged)
    # Frames wholly before the damaged chunk are played (and acknowledged) before it is read.
    frame_times = sorted({it.log_ns for it in fi.load_items(3) if it.topic.endswith('/image_raw')})
    complete = sum(t < chunks[damaged].message_start_time for t in frame_times)
    assert 2 <= complete < len(frame_times)

    run = replay(bag, tmp_path / 'out', timeout=180)
    assert_one_line_error(run, 'is corrupt', str(fi.mcap_file(bag)), graph_started=True)
    stamps, _, _, _ = run.odometry()                 # the output bag is complete and readable
    assert len(stamps) == complete
    assert list(stamps) == sorted(set(stamps))
    assert run.odom_problems() == []
    assert run.leftover_processes() == []


def test_missing_camera_info_is_reported_and_the_replay_finishes(calibration_run):
    """Decision: a camera without CameraInfo is a degraded camera, not a fatal error (a
    live driver may start publishing it late); its quarter nodes say so in /diagnostics
    for every frame they cannot process, the others carry on."""
    run = calibration_run
    assert run.returncode == 0, run
    back = run.diagnostics('ego_motion/back/q')
    assert back and all(d.level == 2 for d in back)
    assert all('no CameraInfo on /back/camera_info' in d.message for d in back)
    assert {d.name for d in back} == {f'ego_motion/back/q{q}' for q in range(1, 5)}
    assert len(run.odometry()[0]) == FRAMES and run.odom_problems() == []


def test_missing_tf_static_without_rig_file_is_a_clear_error(tmp_path):
    bag = fi.rewrite_bag(tmp_path / 'bag', 1, fi.drop_topic('/tf_static'), rig=False)
    run = replay(bag, tmp_path / 'out', timeout=60)
    assert_one_line_error(run, '/tf_static', '--rig')


def test_wrong_message_type_on_a_camera_topic_is_a_clear_error(tmp_path):
    """Decision: a clear error before the graph starts (a bag recorded with the wrong topic
    mapping; waiting for images that never match would hang the lockstep player)."""
    bag = fi.rewrite_bag(tmp_path / 'bag', 1, fi.replace_type(
        '/front/image_raw', lambda it: String(data='not an image')))
    run = replay(bag, tmp_path / 'out', timeout=60)
    assert_one_line_error(run, '/front/image_raw', 'std_msgs/msg/String', 'sensor_msgs/msg/Image')
    assert run.leftover_processes() == []
