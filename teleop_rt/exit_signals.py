"""SIGTERM, SIGINT and SIGHUP outside a running session: a clean exit (143 / 130 / 129), never a
traceback.

Python's default SIGTERM (and SIGHUP: a closed terminal) kills the process where it stands
(exit -15). While the CLI imports, loads kernels or builds a session, SIGTERM and SIGHUP raise
``Terminated`` here instead and SIGINT, as by default, ``KeyboardInterrupt``, each once, for
``main`` to turn into one line and 128 + the signal number. A running session installs its
own handlers (``loop.StopSignals``, a stop at the next tick boundary) and puts these back when
it ends.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

# what ends a process that is not told otherwise, short of SIGKILL: each is a stop at a tick
# boundary in a running loop (``loop.StopSignals``), and passed on to a run's site processes
TERMINATING = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


# the signals this module's handler took while its context is open. Python ignores (prints and
# drops) an exception raised in a signal handler that runs inside a finaliser or a logging lock
# release; the run would then go on as if never asked to stop. A loop that starts checks here
# (``unanswered``) and stops at once.
_received: list[int] = []


def unanswered() -> int | None:
    """The first signal taken here whose exception may have been dropped (None if none); it
    is answered by the caller from now on, so it is returned once."""
    signum = _received[0] if _received else None
    _received.clear()
    return signum


class Terminated(BaseException):
    """A signal ended the process outside a session's run (BaseException: no ``except
    Exception`` on the way swallows it)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


@contextmanager
def exit_on_signals() -> Iterator[None]:
    """Within: the first SIGTERM or SIGHUP raises ``Terminated``, the first SIGINT
    ``KeyboardInterrupt``; later ones are ignored (the process is already on its way out,
    through ``except`` and ``finally`` blocks a second exception would cut short). The
    previous handlers come back on leaving."""
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread may install handlers (and receives the signals)
        return
    raised = False

    def handle(signum: int, frame: object) -> None:
        nonlocal raised
        _received.append(signum)
        if not raised:
            raised = True
            raise KeyboardInterrupt if signum == signal.SIGINT else Terminated(signum)

    def unraisable(info: sys.UnraisableHookArgs) -> None:
        # a stop signal whose exception Python dropped (raised in a finaliser): it is
        # recorded in _received and answered there, not a traceback for the user
        if isinstance(info.exc_value, (Terminated, KeyboardInterrupt)):
            return
        hook(info)

    sigs = TERMINATING
    hook = sys.unraisablehook
    sys.unraisablehook = unraisable
    previous = {sig: signal.signal(sig, handle) for sig in sigs}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sys.unraisablehook = hook
        _received.clear()
