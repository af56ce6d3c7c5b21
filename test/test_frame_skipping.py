"""Live, a graph slower than its cameras skips frames, and every quarter skips the same ones.

The default bag played at 6 times its rate (48 Hz: about 1.5 times what two cores can process) through
the whole graph over DDS in rate mode: the general arbiter raises the frame stride
(/ego_motion/frame_schedule, /diagnostics frame_stride), the quarters follow it, and every
quarter takes only frames the schedule takes, and most frames with odometry were estimated by
all 16 quarters.
Behaviour only: how many frames are skipped depends on the machine."""
from collections import defaultdict

import pytest

from conftest import run_cli
from test_replay_graph import DEFAULT_BAG, read_topic

RATE = 6.0


@pytest.fixture(scope='module')
def overloaded(tmp_path_factory):
    out = tmp_path_factory.mktemp('skipping') / 'run'
    r = run_cli('replay', DEFAULT_BAG, '--out', out, '--workers', 2, '--rate', RATE,
                '--no-rebalance', timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return out


def stamp_ns(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def test_the_general_arbiter_raises_the_stride_and_says_so(overloaded):
    schedules = read_topic(overloaded / 'output', '/ego_motion/frame_schedule')
    strides = [int(m.data[2]) for m in schedules]
    assert strides and max(strides) >= 2, strides
    diag = read_topic(overloaded / 'output', '/diagnostics')
    reported = [int(kv.value) for m in diag for s in m.status if s.name == 'ego_motion/general_arbiter'
                for kv in s.values if kv.key == 'frame_stride']
    assert max(reported) >= 2
    # and the rate it achieves against the cameras'
    rates = [{kv.key: kv.value for kv in s.values} for m in diag for s in m.status
             if s.name == 'ego_motion/general_arbiter']
    behind = [r for r in rates if int(r['frame_stride']) >= 2]
    assert behind
    for r in behind:
        keep, stride = (int(x) for x in r['frames_kept'].split('/'))
        assert float(r['achieved_rate_hz']) == pytest.approx(float(r['camera_rate_hz']) * keep / stride, rel=1e-3)
        assert float(r['achieved_rate_hz']) < float(r['camera_rate_hz'])
    skipped = sum(int(kv.value) for m in diag for s in m.status if '/q' in s.name
                  for kv in s.values if kv.key == 'images_skipped')
    assert skipped > 0


def test_every_quarter_follows_the_schedule_and_fused_frames_are_whole(overloaded):
    from camera_pose_nodes.frame_schedule import FrameSchedule, ScheduleBook
    odom = {stamp_ns(m) for m in read_topic(overloaded / 'output', '/odom')}
    quarters = defaultdict(set)
    for cam in ('front', 'left', 'back', 'right'):
        for q in range(1, 5):
            for m in read_topic(overloaded / 'output', f'/{cam}/q{q}/pose'):
                quarters[stamp_ns(m)].add(f'{cam}/q{q}')
    book = ScheduleBook()
    for m in read_topic(overloaded / 'output', '/ego_motion/frame_schedule'):
        book.add(FrameSchedule.from_list(m.data))
    # No odometry from a frame the schedule skips: under load a schedule reaches some quarters
    # after they took frames it skips (one worker's 8 quarters took up to 12 such frames beside
    # a CPU hog), and the general arbiter leaves those estimates out rather than fuse the
    # frame from part of the rig (before, such frames were a third of the /odom under load).
    assert sorted(s for s in odom if not book.takes(s)) == []
    diag = read_topic(overloaded / 'output', '/diagnostics')
    left_out = max([int(kv.value) for m in diag for s in m.status if s.name == 'ego_motion/general_arbiter'
                    for kv in s.values if kv.key == 'estimates_off_schedule'], default=0)
    taken_off = sum(len(quarters[s]) for s in quarters if not book.takes(s))
    # what quarters took off the schedule reached the general arbiter and was left out
    # (camera estimates: at most one per camera and frame)
    assert (left_out > 0) == (taken_off > 0), (left_out, taken_off)
    whole = [s for s in odom if len(quarters[s]) == 16]
    # A frame may still miss a camera now and then: rate mode drops what comes too late.
    assert len(whole) >= 0.5 * len(odom), (len(whole), len(odom))
    assert len(odom) >= 20
