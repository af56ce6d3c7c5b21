"""The coordinator's snapshot folder (coordinator/snapshot_store.py), without ROS: what a
restore reads is always a whole snapshot, the newest one written by whichever process."""
import os

import pytest

from multicam_ego_motion.coordinator.snapshot_store import HEADER, SLOT_OFFSET, SLOT_SPAN, SnapshotStore


@pytest.fixture
def store():
    s = SnapshotStore()
    yield s
    s.close()


def test_the_newest_snapshot_of_either_writer_is_read(store):
    worker = SnapshotStore(str(store.folder))     # a worker writes into its coordinator's folder
    quarter = os.urandom(70_000)
    worker.put('front/q1', quarter)
    assert store.get('front/q1') == quarter
    store.put('front/q1', b'detached state')      # the coordinator after a move
    assert worker.get('front/q1') == b'detached state'
    worker.put('front/q1', quarter[:1000])         # the new host's next snapshot
    assert store.get('front/q1') == quarter[:1000]
    assert store.get('back/q2') is None
    worker.close()
    assert store.folder.is_dir()                   # the worker's close leaves the folder


def test_a_write_cut_short_leaves_the_previous_snapshot(store):
    store.put('general_arbiter', b'frame 41')
    path = store._path('general_arbiter')
    slot, seq = HEADER.unpack(path.read_bytes()[:HEADER.size])[1:3]
    # a worker killed after writing the other slot but before switching the header
    with open(path, 'r+b') as f:
        f.seek(SLOT_OFFSET + (1 - slot) * SLOT_SPAN)
        f.write(b'frame 42, half writ')
    assert store.get('general_arbiter') == b'frame 41'
    store.put('general_arbiter', b'frame 42')
    assert store.get('general_arbiter') == b'frame 42'
    assert HEADER.unpack(path.read_bytes()[:HEADER.size])[2] == seq + 1


def test_close_removes_the_folder_and_oversized_states_are_refused(store, monkeypatch):
    from multicam_ego_motion.coordinator import snapshot_store
    monkeypatch.setattr(snapshot_store, 'SLOT_SPAN', 1000)
    with pytest.raises(ValueError, match='front/arbiter'):
        store.put('front/arbiter', b'\0' * 1001)
    store.put('front/arbiter', b'x')
    store.close()
    assert not store.folder.exists()


def test_folders_of_coordinators_that_are_gone_are_removed(tmp_path, monkeypatch):
    from multicam_ego_motion.coordinator import snapshot_store
    monkeypatch.setattr(snapshot_store, 'default_parent', lambda: str(tmp_path))
    gone = tmp_path / f'{snapshot_store.PREFIX}999999999_abc'      # no such process
    alive = tmp_path / f'{snapshot_store.PREFIX}{os.getpid()}_abc'
    for d in (gone, alive):
        d.mkdir()
        (d / 'front__q1.state').write_bytes(b'x')
    s = SnapshotStore()
    assert s.folder.parent == tmp_path and s.folder.name.startswith(f'{snapshot_store.PREFIX}{os.getpid()}_')
    assert not gone.exists() and alive.exists()
    s.close()
