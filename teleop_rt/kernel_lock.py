"""One process at a time compiles into (or loads from) the kernel cache.

numba's on-disk cache is not safe for processes that fill one folder at once (numba/numba#4807):
two sites started together from an empty cache (after an install or an upgrade) could fail with
"RuntimeError: no compiled object yet for ...". So every kernel's compilation, which first tries
the cache, holds an exclusive ``flock`` on a lock file in the cache folder: a second process
waits for the first's kernel and then loads it from the cache. Kernels compile at warm-up (the
site's, the backends', the link's, a session's start), before any real-time loop starts, so
the wait holds no tick. Held per kernel, not per run: a process that only loads (a warm cache)
holds it for milliseconds, and a process that forks (the log's writer) never forks it held.

A cache that cannot be written (a read-only or full folder, a file size limit) costs every start
a compilation of every kernel; numba either stops with a traceback (a failed write) or caches
elsewhere, in a folder not keyed by the sources (its own fallbacks: stale code after an edit).
So a folder that fails numba's own probe (make it, write a file in it) is not cached in at all,
a write that fails is given up, and the first compilation of such a process says so in one
line on stderr (``CompileLock.uncached``).
"""

from __future__ import annotations

import fcntl
import os
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

LOCK_NAME = "compile.lock"
# what a start without the cache pays: the HSI site's warm-up from an empty cache took 33 s on
# this project's idle 2-vCPU machine (two sites at once about 75 s: tests/test_kernel_cache.py)
UNCACHED_COST = "about 30 s a site on an idle 2-core host, more under load"
# a wait longer than this is worth a note: a compilation takes seconds, so the holder is
# stopped or stuck (a process under a debugger, SIGSTOP), and the start would look hung
WAIT_NOTE_S = 10.0


class CompileLock:
    """Reentrant (a kernel's compilation compiles its callees) within a process, exclusive
    across processes; without a usable lock file (a read-only install) it says so once on
    stderr and lets numba go on unlocked (numba then falls back on its own)."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / LOCK_NAME
        self._threads = threading.RLock()  # one flock per process: a second fd would block
        self._depth = 0
        self._fd: int | None = None
        self.waited = 0  # how many times another process held it (tests, diagnosis)
        # why kernels are not cached in ``folder`` (None: they are); nothing is written then,
        # so there is nothing to lock (and no note of the lock's)
        self.uncached = cache_problem(folder)
        self.caches = self.uncached is None  # (the folder passed numba's probe: kernels cache)
        self._unusable = not self.caches
        self._said = False

    def unwritable(self, err: OSError) -> None:
        """A cache write failed (``err``): noted once per process; the kernel runs uncached."""
        self.uncached = self.uncached or (err.strerror or str(err))
        self._say_uncached()

    def _say_uncached(self) -> None:
        if self._said:
            return
        self._said = True
        print(f"teleop-rt: note: the kernel cache {self.path.parent} cannot be written "
              f"({self.uncached}): every start compiles the kernels again ({UNCACHED_COST}); "
              "NUMBA_CACHE_DIR moves it", file=sys.stderr, flush=True)  # fmt: skip

    def __enter__(self) -> CompileLock:
        self._threads.acquire()
        self._depth += 1
        if self._depth == 1 and self.uncached is not None:
            self._say_uncached()  # (at the first compilation: a process that compiles nothing
            # pays nothing and hears nothing)
        if self._depth == 1 and not self._unusable:
            self._fd = self._take()
        return self

    def __exit__(self, *exc: object) -> None:
        self._depth -= 1
        if self._depth == 0 and self._fd is not None:
            os.close(self._fd)  # closing the file releases its flock
            self._fd = None
        self._threads.release()

    def _take(self) -> int | None:
        fd = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                self.waited += 1
                note = threading.Timer(WAIT_NOTE_S, self._say_waiting, (fd,))
                note.daemon = True
                note.start()
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX)
                finally:
                    note.cancel()
            return fd
        except OSError as err:
            if fd is not None:
                os.close(fd)
            self._unusable = True
            print(f"teleop-rt: note: kernels compile without the cache lock ({self.path}: "
                  f"{err.strerror or err}); two processes starting at once from an empty "
                  "cache may race", file=sys.stderr)  # fmt: skip
            return None

    def _say_waiting(self, fd: int) -> None:
        try:  # the lock may have come (and the fd gone) just as the timer fired
            holders = _holders(os.fstat(fd).st_ino)
        except OSError:
            return
        who = f"pid {', '.join(map(str, holders))}" if holders else "another process"
        print(f"teleop-rt: note: waiting {WAIT_NOTE_S:g} s so far for the kernel cache lock "
              f"{self.path} (held by {who})", file=sys.stderr, flush=True)  # fmt: skip


def cache_problem(folder: Path) -> str | None:
    """Why numba cannot cache kernels in ``folder`` (its own probe: the folder made, a file
    written in it), or None."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as err:
        return err.strerror or str(err)
    return None


def _holders(inode: int) -> list[int]:
    """The pids holding a flock on the file with ``inode`` (from /proc/locks; [] if unknown)."""
    pids = []
    try:
        for line in Path("/proc/locks").read_text().splitlines():
            fields = line.split()
            if "->" not in fields and "FLOCK" in fields and len(fields) >= 6:
                if int(fields[5].split(":")[2]) == inode:
                    pids.append(int(fields[4]))
    except (OSError, ValueError, IndexError):
        return []
    return pids


def locked(dispatcher: Any, lock: CompileLock) -> Any:
    """``dispatcher`` (a numba one) compiling under ``lock``; a plain function (with
    ``NUMBA_DISABLE_JIT=1``) as it is. numba's dispatchers call ``self.compile`` both for a
    call from Python and for a call from another kernel, so this covers every compilation."""
    compile_: Callable[[Any], Any] | None = getattr(dispatcher, "compile", None)
    if compile_ is None:
        return dispatcher
    cache = getattr(dispatcher, "_cache", None)
    if lock.caches and cache is not None:  # a write that fails (a full disk, a size limit)
        save = cache.save_overload  # raised out of the compilation: now it runs uncached

        def save_overload(sig: Any, data: Any) -> None:
            try:
                save(sig, data)
            except OSError as err:
                lock.unwritable(err)

        cache.save_overload = save_overload

    def compile(sig: Any) -> Any:
        with lock:
            return compile_(sig)

    dispatcher.compile = compile
    return dispatcher
