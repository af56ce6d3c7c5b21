"""What runs on this machine, from /proc: to check that a replay leaves no process behind.

Every replay a fault test starts carries a marker in its environment (inherited by the
workers it spawns), so its processes can be found however the coordinator names them.
"""
import os
import time
from pathlib import Path

MARKER = 'EGO_MOTION_FAULT_TEST_RUN'


def alive(pid: int) -> bool:
    """Running (a zombie only waits for its parent to reap it: it is gone for our purpose)."""
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rsplit(')', 1)[1].split()[0] != 'Z'


def marked(run_id: str):
    """Pids of live processes whose environment carries MARKER=run_id."""
    needle = f'{MARKER}={run_id}'.encode()
    pids = []
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            env = (entry / 'environ').read_bytes().split(b'\0')
        except OSError:
            continue
        if needle in env and alive(int(entry.name)):
            pids.append(int(entry.name))
    return pids


def children(pid: int):
    """Live direct children of pid."""
    out = []
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / 'stat').read_text().rsplit(')', 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid and alive(int(entry.name)):
            out.append(int(entry.name))
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ').decode()
    except OSError:
        return ''


def environment(pid: int) -> dict:
    raw = Path(f'/proc/{pid}/environ').read_bytes().split(b'\0')
    return dict(kv.decode(errors='replace').split('=', 1) for kv in raw if b'=' in kv)


def wait_gone(pids, timeout_s: float):
    """The pids still alive after waiting up to timeout_s for all of them to end."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        left = [p for p in pids if alive(p)]
        if not left:
            return []
        time.sleep(0.1)
    return [p for p in pids if alive(p)]
