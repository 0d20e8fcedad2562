"""The operator's clutch and presence as keys of the terminal, in real time (``teleop-rt run
--keys``, ``teleop-rt site hsi --keys``: ``mapping.keys``).

A thread reads stdin in cbreak mode (each key at once, no echo; Ctrl-C still signals) and
toggles the bits the CAN backend's digital inputs set (``teleop_rt.hal.signals``
``INPUT_CLUTCH``, ``INPUT_PRESENT``) in the HSI's ``Feedback.inputs``; the tick reads that int
as it reads a drive's 0x60FD bits, so it never waits for the terminal. The mapping
(``teleop_rt.mapping``) then decouples and re-engages with its ramp, and the TO follows the
HSI's packets. Why a thread and not a poll in the tick: a read of the terminal is a system
call, which the 1 kHz tick must not make.

The terminal's mode is restored on every way out: the context's exit (the run's end, a
signal the loop caught, an exception) and, should the process end without it, at exit.
With stdin not a terminal (a pipe, a test, a service) the reader does nothing and the inputs
stay at their start: the operator present, the clutch released.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import select
import sys
import termios
import threading
import tty
from types import TracebackType
from typing import TYPE_CHECKING, TextIO

from teleop_rt.hal.signals import INPUT_CLUTCH, INPUT_PRESENT, Feedback

if TYPE_CHECKING:
    from teleop_rt.site import Site

CLUTCH_KEYS = b" c"  # space or c: press / release the clutch
PRESENCE_KEYS = b"p"  # p: the operator leaves / returns (the dead-man)
AT_START = INPUT_PRESENT  # the operator present, the clutch released
POLL_S = 0.1  # how often the reader looks whether it is to stop (it sleeps in select)
HELP = "keys: space or c toggles the clutch, p the operator's presence"


class KeyReader:
    """Toggle ``feedback.inputs`` from the keys of ``stdin`` while the context is open."""

    def __init__(self, feedback: Feedback, stdin: TextIO | None = None,
                 say: TextIO | None = None) -> None:  # fmt: skip
        """``say``: where each toggle is announced (default stderr; None in tests' hands)."""
        self.feedback = feedback
        self.stdin = sys.stdin if stdin is None else stdin
        self.say = sys.stderr if say is None else say
        self.presses = 0
        self._saved: list | None = None
        self._fd = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> KeyReader:
        self.feedback.inputs = AT_START
        try:
            fd = self.stdin.fileno()
        except (AttributeError, ValueError, OSError):
            return self  # no file behind stdin: nothing to read
        if not os.isatty(fd):
            return self
        self._fd = fd
        self._saved = termios.tcgetattr(fd)
        atexit.register(self._restore)
        tty.setcbreak(fd)
        print(HELP, file=self.say, flush=True)
        self._thread = threading.Thread(target=self._read, name="teleop-rt-keys", daemon=True)
        self._thread.start()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None,
        trace: TracebackType | None,
    ) -> None:  # fmt: skip
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2 * POLL_S + 1.0)
        self._restore()

    @property
    def active(self) -> bool:
        """The terminal is in cbreak mode and read."""
        return self._saved is not None

    def _restore(self) -> None:
        saved, self._saved = self._saved, None
        if saved is not None:
            termios.tcsetattr(self._fd, termios.TCSADRAIN, saved)
            atexit.unregister(self._restore)

    def _read(self) -> None:
        fd = self._fd
        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], POLL_S)
            if not ready:
                continue
            try:
                keys = os.read(fd, 64)
            except OSError:
                return
            if not keys:
                return  # the terminal closed
            for key in keys:
                self.press(key)

    def press(self, key: int) -> None:
        """One key (a byte): the clutch or the presence bit toggled, announced."""
        fb = self.feedback
        if key in CLUTCH_KEYS:
            fb.inputs = fb.inputs ^ INPUT_CLUTCH
            state = "pressed" if fb.inputs & INPUT_CLUTCH else "released"
            print(f"clutch {state}", file=self.say, flush=True)
        elif key in PRESENCE_KEYS:
            fb.inputs = fb.inputs ^ INPUT_PRESENT
            state = "present" if fb.inputs & INPUT_PRESENT else "away"
            print(f"operator {state}", file=self.say, flush=True)
        else:
            return
        self.presses += 1


def key_reader(site: Site) -> contextlib.AbstractContextManager:
    """The keys' reader of ``site`` for a run: a ``KeyReader`` on the HSI of a config with
    ``mapping.keys``, else nothing."""
    if site.name == "hsi" and site.cfg.mapping.keys:
        return KeyReader(site.feedback)
    return contextlib.nullcontext()
