"""Every signal ends cleanly: SIGINT, SIGTERM and SIGHUP end a command the way Ctrl-C does.

Who sends them: Ctrl-C in a terminal (SIGINT, to the whole foreground process group);
systemd, `timeout`, CI runners and launch systems (SIGTERM); a closed terminal or SSH
session (SIGHUP). Python's default for SIGTERM and SIGHUP ends the process at once, no
`finally` runs, and an open bag loses its summary and footer. With `handling()` installed,
the first of them raises `Interrupted` (a KeyboardInterrupt) in the main thread, so the
`finally` clauses stop the workers and close the bag in order; the entry point then prints
one line saying what was interrupted and what was kept (`line()`) and exits with 128 + the
signal number (SIGINT 130, SIGTERM 143, SIGHUP 129), as a shell reports it.

One module for every entry point (`ego-motion` in cli.py, the `coordinator` node):

    with interrupt.handling():
        ...                              # any command; Interrupted propagates out of it
    interrupt.note(progress=fn, kept=s)  # the command's state, for the final line
    with interrupt.deferred():           # must not be cut in the middle (closing a bag):
        ...                              # a signal here is raised when the block ends
    interrupt.requested()                # polling loops (record, coordinator) instead
    interrupt.on_signal(fn)              # fn() runs in the handler: it may only set flags

A signal that was ignored when the process started (`nohup`, a background job's SIGINT) stays
ignored. Signals after the first are ignored while the command closes (a second Ctrl-C does
not cut the closing short); SIGKILL remains, and `ego-motion reindex` recovers a bag it left.
"""
import signal
import threading
from contextlib import contextmanager
from typing import Callable, Optional

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Interrupted(KeyboardInterrupt):
    """Raised in the main thread by the first of SIGNALS (a KeyboardInterrupt: code that
    already ends cleanly on Ctrl-C does so on SIGTERM and SIGHUP too)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class _State:
    def __init__(self):
        self.reset()

    def reset(self):
        self.signum = None        # the first signal received
        self.raised = False       # Interrupted was raised for it (once only)
        self.depth = 0            # nesting of deferred()
        self.hooks = []
        self.progress: Optional[Callable[[], str]] = None
        self.kept: Optional[str] = None
        self.installed = False


_state = _State()


def _handler(signum, frame):
    if _state.signum is not None:
        return                    # already ending: let the closing finish
    _state.signum = signum
    for hook in list(_state.hooks):
        try:
            hook()
        except Exception:         # a hook must never keep the command from closing
            pass
    if _state.depth == 0:
        _state.raised = True
        raise Interrupted(signum)


@contextmanager
def handling():
    """Install the handlers for SIGINT, SIGTERM and SIGHUP (main thread only); restore the
    previous ones when the block ends."""
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError('signal handlers can only be installed from the main thread')
    _state.reset()
    previous = {}
    for sig in SIGNALS:
        old = signal.getsignal(sig)
        if old == signal.SIG_IGN:
            continue              # nohup, background job: keep it ignored
        previous[sig] = old
        signal.signal(sig, _handler)
    _state.installed = True
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old if old is not None else signal.SIG_DFL)
        _state.installed = False


@contextmanager
def deferred():
    """A block a signal must not cut in the middle: the signal is held and Interrupted raised
    when the (outermost) block ends normally. If the block ends with another exception, that
    one propagates; `received()` still tells the entry point a signal came."""
    _state.depth += 1
    try:
        yield
    finally:
        _state.depth -= 1
    if _state.depth == 0 and _state.signum is not None and not _state.raised:
        _state.raised = True
        raise Interrupted(_state.signum)


def requested() -> bool:
    """A signal came (for loops that poll instead of taking the exception)."""
    return _state.signum is not None


def received() -> Optional[int]:
    """The signal that came, or None."""
    return _state.signum


def on_signal(hook: Callable[[], None]):
    """Call hook() from the handler at the first signal, before anything is unwound: e.g. the
    coordinator stops restarting workers that the same signal (sent to the whole process
    group or cgroup) ends. It runs between two bytecodes of the main thread: set flags only."""
    _state.hooks.append(hook)


def remove_hook(hook: Callable[[], None]):
    if hook in _state.hooks:
        _state.hooks.remove(hook)


def note(progress: Optional[Callable[[], str]] = None, kept: Optional[str] = None):
    """What the command is doing (`progress()`, called when the line is printed, e.g.
    'at 5.2 s of the bag's 20.0 s') and what it has kept ('kept out/output: ...')."""
    if progress is not None:
        _state.progress = progress
    if kept is not None:
        _state.kept = kept


def line(prog: str, command: Optional[str] = None, signum: Optional[int] = None) -> str:
    """The one line an entry point prints for an interrupted command."""
    signum = signum if signum is not None else _state.signum
    name = signal.Signals(signum).name if signum is not None else 'a signal'
    progress = ''
    if _state.progress is not None:
        try:
            progress = _state.progress() or ''
        except Exception:
            progress = ''
    what = f'{command} interrupted' if command else 'interrupted'
    return (f'{prog}: {what} by {name}' + (f' {progress}' if progress else '')
            + (f'; {_state.kept}' if _state.kept else ''))
