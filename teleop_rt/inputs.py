"""The one rule for every file the command line reads (configs, traces, URDFs, logs): it must
be a regular file, checked with ``stat`` before it is opened (a FIFO would block the open or
the read forever, a device such as /dev/zero never ends), and it is read with a bound on its
size before the read, not after it.

Importing this module stays cheap (the config imports it): the standard library only.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from teleop_rt.errors import ConfigError, TeleopError, quote

SHOWN_PATH_CHARS = 120  # a longer path is cut in the middle in a message (still one line)

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def shown(path: str | Path) -> str:
    """A path for a one-line message: as it is, or cut in the middle when very long."""
    text = str(path)
    return text if len(text) <= SHOWN_PATH_CHARS else quote(text, SHOWN_PATH_CHARS)


def file_problem(path: str | Path) -> str | None:
    """What keeps ``path`` from being read as a regular file ('no such file', 'is a folder',
    'is a FIFO (named pipe)', 'cannot be read (File name too long)', ...), None if nothing.
    Only ``stat``: nothing is opened."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file"
    except (OSError, ValueError) as err:  # ENAMETOOLONG, ENOTDIR, EACCES; ValueError: a NUL
        return f"cannot be read ({getattr(err, 'strerror', None) or err})"
    if stat.S_ISREG(mode):
        return None
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    return f"is {kind}, not a regular file"


def check_regular(path: str | Path, what: str = "", error: type[TeleopError] = ConfigError) -> None:
    """Raise ``error`` ('WHAT PATH: is a FIFO (named pipe), not a regular file') unless
    ``path`` is a regular file."""
    problem = file_problem(path)
    if problem is not None:
        raise error(f"{what}{shown(path)}: {problem}")


def read_bounded(
    path: str | Path, limit: int, what: str = "", error: type[TeleopError] = ConfigError
) -> bytes:
    """The bytes of the regular file ``path``, refused (``error``, naming it) beyond ``limit``
    bytes: at most limit + 1 bytes are read, whatever the file claims to hold."""
    check_regular(path, what, error)
    try:
        with open(path, "rb") as f:
            raw = f.read(limit + 1)
    except OSError as err:
        raise error(f"{what}{shown(path)}: cannot be read ({err.strerror or err})") from None
    if len(raw) > limit:
        raise error(f"{what}{shown(path)}: larger than {limit} bytes")
    return raw
