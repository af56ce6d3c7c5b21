"""RecentOutputs: the last few outputs of a node by stamp (sent again for re-published
frames), bounded, and carried in a snapshot."""
import pickle

from multicam_ego_motion.ros_plumbing.recent_outputs import RecentOutputs


def test_keeps_the_newest_outputs_only():
    r = RecentOutputs(kept=3)
    for stamp in (10, 20, 30, 40):
        r.add(stamp, f'estimate {stamp}')
    assert r.get(10) is None
    assert [r.get(s) for s in (20, 30, 40)] == ['estimate 20', 'estimate 30', 'estimate 40']


def test_a_stamp_added_again_is_the_newest():
    r = RecentOutputs(kept=2)
    r.add(10, 'a')
    r.add(20, 'b')
    r.add(10, 'a2')
    r.add(30, 'c')
    assert r.get(20) is None and r.get(10) == 'a2' and r.get(30) == 'c'


def test_state_round_trip_through_a_snapshot():
    r = RecentOutputs()
    r.add(5, {'pose': 1})
    restored = RecentOutputs()
    restored.set_state(pickle.loads(pickle.dumps(r.get_state())))
    assert restored.get(5) == {'pose': 1}
    restored.set_state(None)           # a snapshot from before this field existed
    assert restored.get(5) is None
