"""The name a helper process shows in ps, top and /proc/PID/comm: the log writer and the CAN log
writer name themselves, so that a user sees which process is which."""

from __future__ import annotations

import ctypes


def set_process_name(name: str) -> None:
    """Linux: prctl PR_SET_NAME (15 bytes at most); elsewhere nothing."""
    try:
        # the process's own symbols (libc among them): find_library would run ldconfig, a
        # child process that cost the writer 3 ms of CPU at every start
        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass
