"""The stateful nodes' last state snapshots, one file per node in a folder of this host.

Workers the coordinator starts write their nodes' snapshots straight into the folder (on
/dev/shm, i.e. memory, where the host has it): no control-channel message, no HMAC, and no
wake-up of the coordinator's process for each one. Through the channel, framing,
authenticating, receiving and keeping them cost about 1 ms of CPU per frame of the default bag
on top of pickling them (the general arbiter every frame, a quarter every 5th: ~250 kB a
frame), on the same two cores as the estimator. Remote workers cannot reach the folder: their snapshots come over the channel
and the coordinator puts them here, as it does a detached node's state; so the folder always
holds each node's newest state, and a restore reads it from there.

A node's file has two slots and a header naming the valid one. A write goes into the other
slot, then the header (one small write) switches to it: a worker killed in the middle leaves
the previous snapshot intact. Kept open, a write is three system calls (~6 us for a
quarter's 70 kB) where writing a new file and renaming it over the old one was ~45 us. The
slots lie apart in a sparse file, so only what is written takes memory.

The folder is named after the coordinator's process id: a coordinator that was killed
cannot remove its folder, so the next one on the host removes the folders of processes that
are gone.
"""
import os
import shutil
import struct
import tempfile
from pathlib import Path
from typing import Dict, Optional

SUFFIX = '.state'
HEADER = struct.Struct('<4sIQQ')      # magic, valid slot, sequence, length
MAGIC = b'EGS1'
SLOT_OFFSET = 4096                     # slot 0; slot 1 one span further
SLOT_SPAN = 1 << 24                    # largest snapshot (a quarter's is ~70 kB)
PREFIX = 'ego_motion_state_'


def default_parent() -> Optional[str]:
    """/dev/shm when the host has it (a snapshot is then a copy in memory), else the
    temporary folder."""
    shm = Path('/dev/shm')
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def remove_orphans(parent: Path):
    """Remove the snapshot folders of coordinators that no longer run."""
    for d in parent.glob(f'{PREFIX}*_*'):
        pid = d.name[len(PREFIX):].split('_')[0]
        if pid.isdigit() and not _running(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:     # another user's
        return True
    return True


class SnapshotStore:
    def __init__(self, folder: Optional[str] = None):
        """folder: an existing store's folder (a worker writing into its coordinator's);
        None: a new private folder, removed by close()."""
        self.owned = folder is None
        if folder is None:
            parent = default_parent()
            remove_orphans(Path(parent or tempfile.gettempdir()))
            folder = tempfile.mkdtemp(prefix=f'{PREFIX}{os.getpid()}_', dir=parent)
        self.folder = Path(folder)
        self._fds: Dict[str, int] = {}

    def _path(self, key: str) -> Path:
        # node keys are 'general_arbiter', '<camera>/q<l>', '<camera>/arbiter'
        return self.folder / (key.replace('/', '__') + SUFFIX)

    def _fd(self, key: str) -> int:
        fd = self._fds.get(key)
        if fd is None:
            fd = self._fds[key] = os.open(self._path(key), os.O_RDWR | os.O_CREAT, 0o600)
        return fd

    @staticmethod
    def _header(fd):
        raw = os.pread(fd, HEADER.size, 0)
        if len(raw) < HEADER.size:
            return None
        magic, slot, seq, length = HEADER.unpack(raw)
        return (slot, seq, length) if magic == MAGIC and slot in (0, 1) else None

    def put(self, key: str, data: bytes):
        if len(data) > SLOT_SPAN:
            raise ValueError(f'state of {key} is {len(data)} bytes, more than a snapshot slot holds')
        fd = self._fd(key)
        # Into the slot the header does not name (another process, the coordinator, may
        # have written this key last: after a move or for a remote worker).
        h = self._header(fd)
        slot, seq = (1 - h[0], h[1] + 1) if h else (0, 0)
        os.pwrite(fd, data, SLOT_OFFSET + slot * SLOT_SPAN)
        os.pwrite(fd, HEADER.pack(MAGIC, slot, seq, len(data)), 0)

    def get(self, key: str) -> Optional[bytes]:
        try:
            fd = os.open(self._path(key), os.O_RDONLY)
        except FileNotFoundError:
            return None
        try:
            h = self._header(fd)
            if h is None:
                return None
            slot, _, length = h
            data = os.pread(fd, length, SLOT_OFFSET + slot * SLOT_SPAN)
            return data if len(data) == length else None
        finally:
            os.close(fd)

    def close(self):
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()
        if self.owned:
            shutil.rmtree(self.folder, ignore_errors=True)
