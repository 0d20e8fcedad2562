"""stdout and stderr whose reader went away (``teleop-rt run --json | head``, ``| true``, a
parent that was killed): the command's exit code stays the one its work earned.

The loss of a pipe's reader is the reader's choice, not an outcome of the run: a run that
ended in a safety stop still exits 3, a complete one 0, and a log is finished either way.
Python raises ``BrokenPipeError`` at the first write (or flush) after the reader closed; left
alone it would unwind the command from wherever it printed. Here the first one is absorbed,
the stream's descriptor is pointed at /dev/null (the recipe of the Python docs, "Note on
SIGPIPE": nothing more is sent, and the interpreter's flush at exit does not fail again), and
for stdout one line says so on stderr while stderr is open. rich's consoles look
``sys.stdout`` up at every write, so they write through this too.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Any, TextIO


class _Guarded:
    """A text stream whose broken pipe ends its output instead of the program."""

    def __init__(self, stream: TextIO, name: str) -> None:
        self._stream = stream
        self._name = name
        self.broken = False

    def write(self, text: str) -> int:
        if not self.broken:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._broke()
        return len(text)

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        if not self.broken:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._broke()

    def _broke(self) -> None:
        self.broken = True
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())  # what is still buffered goes there
            os.close(devnull)
        if self._name == "stdout":
            say(
                "teleop-rt: stdout was closed by its reader; the rest of the output is "
                "discarded (the exit code is the command's own)"
            )

    def __getattr__(self, name: str) -> Any:  # fileno, isatty, encoding, ...
        return getattr(self._stream, name)


def say(line: str) -> None:
    """One line on stderr, if anyone still reads it."""
    try:
        print(line, file=sys.stderr, flush=True)
    except (BrokenPipeError, OSError, ValueError):
        pass


@contextlib.contextmanager
def guarded() -> Iterator[None]:
    """Within: writes to a closed stdout or stderr are dropped (see the module's text); the
    streams are flushed before leaving, so a pipe that broke after the last write is met here
    rather than by the interpreter at exit."""
    saved = sys.stdout, sys.stderr
    sys.stdout = _Guarded(saved[0], "stdout")
    sys.stderr = _Guarded(saved[1], "stderr")
    try:
        yield
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        sys.stdout, sys.stderr = saved
