"""Processes that start together from an empty kernel cache compile one at a time
(``teleop_rt.kernel_lock``): numba's cache is not safe for concurrent writers (numba/numba#4807),
which made one of two sites started at once fail with "no compiled object yet for ...".

The race itself is not deterministic (it failed now and then, never on demand), so the first
test checks the property that prevents it directly: a process that compiles while another holds
the cache's lock blocks on that lock (seen in /proc/locks) until it is released. The second runs
the two sites' warm-ups at once from an empty cache: both succeed, and one waited for the other.
A cache that cannot be written (no folder, a read-only one, a write beyond RLIMIT_FSIZE) is one
note per start and an uncached kernel: no traceback, no cache in numba's unkeyed fallbacks.
"""

from __future__ import annotations

import ctypes
import fcntl
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from teleop_rt.flat import _source_hash
from teleop_rt.kernel_lock import LOCK_NAME, UNCACHED_COST
from tests.conftest import CONFIGS

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 300  # a fresh compilation on a loaded host; never reached when the lock works

KERNEL = """
import json
import numpy as np
from teleop_rt.flat import COMPILE_LOCK, jit

@jit
def twice(x):
    return 2.0 * x

@jit
def plus_one(x):
    return x + 1.0

y = plus_one(twice(np.float64(1.0)))  # two kernels: two compilations, each takes the lock
print(json.dumps({"y": float(y), "waited": COMPILE_LOCK.waited}))
"""

CACHED = """
import json
import numpy as np
from teleop_rt.flat import jit

@jit
def twice(x):
    return 2.0 * x

y = twice(np.float64(1.0))

@jit  # decorated after a compilation (a module imported late): after a failed write too
def plus_one(x):
    return x + 1.0

y = plus_one(y)
hits = sum(twice.stats.cache_hits.values()) + sum(plus_one.stats.cache_hits.values())
print(json.dumps({"y": float(y), "hits": hits}))
"""
NO_NAMESPACE = 77  # the child's exit status when it cannot have a mount namespace of its own


def read_only(folder: Path):
    """A preexec for a child that sees ``folder`` read-only, root included (its own mount
    namespace, private: the host's mounts are untouched); NO_NAMESPACE if refused."""
    path = str(folder).encode()
    ms_rdonly, ms_remount, ms_bind, ms_rec, ms_private = 1, 32, 4096, 16384, 1 << 18

    def preexec() -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        if (libc.unshare(0x00020000) != 0  # CLONE_NEWNS
                or libc.mount(b"none", b"/", None, ms_rec | ms_private, None) != 0
                or libc.mount(path, path, None, ms_bind, None) != 0
                or libc.mount(b"none", path, None, ms_remount | ms_bind | ms_rdonly, None) != 0):
            os._exit(NO_NAMESPACE)

    return preexec


WARM_UP = """
import json, os, sys, time
from types import SimpleNamespace
name, barrier = sys.argv[1], sys.argv[2]
open(barrier + "." + name, "w").close()
while not all(os.path.exists(barrier + "." + n) for n in ("hsi", "to")):
    time.sleep(0.001)
from teleop_rt import config
from teleop_rt.com.zenoh_link import ZenohLink
from teleop_rt.flat import COMPILE_LOCK
from teleop_rt.site import HsiSite, ToSite
cfg = config.load(sys.argv[3], ["channel.delay_ms=20"])
site = (HsiSite if name == "hsi" else ToSite)(cfg, None)
site.warm_up()
ZenohLink._warm_up(SimpleNamespace(n=site.n, cfg=cfg, side=site.side))  # the codec's kernels
print(json.dumps({"waited": COMPILE_LOCK.waited}))
"""


def env_with_cache(cache: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(cache)}


def blocked_on(pid: int, inode: int) -> bool:
    """Whether process ``pid`` waits for a flock on the file with ``inode`` (a '->' entry)."""
    for line in Path("/proc/locks").read_text().splitlines():
        fields = line.split()
        if "->" in fields and "FLOCK" in fields:
            rest = fields[fields.index("->") + 1 :]  # FLOCK ADVISORY WRITE pid dev:inode ...
            if int(rest[3]) == pid and int(rest[4].split(":")[2]) == inode:
                return True
    return False


def run_behind_a_held_lock(tmp_path: Path, preamble: str = "", hold_s: float = 0.0):
    """Run KERNEL (after ``preamble``) while this process holds the cache's lock ("another
    process" compiling): once the child blocks on it (and ``hold_s`` more), release it; the
    child's (returncode, stdout, stderr)."""
    cache = tmp_path / "cache"
    lock_path = cache / _source_hash() / LOCK_NAME
    lock_path.parent.mkdir(parents=True)
    script = tmp_path / "kernel.py"  # a file: numba caches only kernels with a source file
    script.write_text(preamble + KERNEL)
    with open(lock_path, "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        child = subprocess.Popen(
            [sys.executable, str(script)], env=env_with_cache(cache),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            deadline = time.monotonic() + TIMEOUT_S
            while not blocked_on(child.pid, os.fstat(held.fileno()).st_ino):
                assert child.poll() is None, f"compiled without waiting: {child.communicate()}"
                assert time.monotonic() < deadline, "never waited for the cache's lock"
                time.sleep(0.05)
            time.sleep(hold_s)
        finally:
            fcntl.flock(held, fcntl.LOCK_UN)
        out, err = child.communicate(timeout=TIMEOUT_S)
    return child.returncode, out, err


def test_a_compilation_waits_for_the_lock_another_process_holds(tmp_path: Path) -> None:
    code, out, err = run_behind_a_held_lock(tmp_path)
    assert code == 0, err
    assert json.loads(out) == {"y": 3.0, "waited": 1}


def test_a_long_wait_for_the_lock_is_a_note_naming_the_holder(tmp_path: Path) -> None:
    """A holder that is stopped or stuck made a start look hung, with nothing on stderr (the
    CAN emulator's test, twice): past WAIT_NOTE_S the waiter says whom it waits for."""
    preamble = "import teleop_rt.kernel_lock as kl\nkl.WAIT_NOTE_S = 0.3\n"
    code, out, err = run_behind_a_held_lock(tmp_path, preamble, hold_s=1.0)
    assert code == 0, err
    notes = [line for line in err.splitlines() if "kernel cache lock" in line]
    assert len(notes) == 1, err
    assert notes[0].startswith("teleop-rt: note: waiting") and f"pid {os.getpid()}" in notes[0]


def uncached_runs(tmp_path: Path, why: str, preexec=None) -> None:
    """CACHED run against the (fresh) folder tmp_path / "cache" that cannot be written
    (``preexec`` makes it so in the child): it compiles and runs its kernel, writes no cache
    anywhere (numba's fallback was a __pycache__ by the script, not keyed by the sources), so
    the next start compiles again, and says so in one line on stderr naming the folder and
    ``why``."""
    script = tmp_path / "kernel.py"  # a file: numba caches only kernels with a source file
    script.write_text(CACHED)
    folder = tmp_path / "cache" / _source_hash()
    run = subprocess.run([sys.executable, str(script)], env=env_with_cache(tmp_path / "cache"),
                         capture_output=True, text=True, timeout=TIMEOUT_S,
                         preexec_fn=preexec)  # fmt: skip
    if run.returncode == NO_NAMESPACE:
        pytest.skip("no mount namespace here (unshare refused)")
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout) == {"y": 3.0, "hits": 0}
    assert run.stderr.splitlines() == [
        f"teleop-rt: note: the kernel cache {folder} cannot be written ({why}): every start "
        f"compiles the kernels again ({UNCACHED_COST}); NUMBA_CACHE_DIR moves it"
    ], run.stderr
    assert not list(tmp_path.rglob("*.nb*"))


def test_an_unusable_cache_folder_is_one_note_and_the_kernel_still_runs(tmp_path: Path) -> None:
    """No folder can be made (a file where it should be; unwritable for root too): one note on
    stderr (no lock is needed: nothing is written), the kernel compiled and run uncached (numba
    cached it by the script instead, unkeyed, and only the lock said anything)."""
    (tmp_path / "cache").write_text("not a folder")
    uncached_runs(tmp_path, "Not a directory")


def test_a_read_only_cache_folder_is_one_note_and_nothing_is_cached_elsewhere(
    tmp_path: Path,
) -> None:  # fmt: skip
    """A read-only folder (for root: bind-mounted read-only in the child's own mount namespace;
    else its mode): the start compiles, caches nowhere else and says so, once."""
    cache = tmp_path / "cache"
    cache.mkdir()
    if os.geteuid() != 0:
        cache.chmod(0o555)
        uncached_runs(tmp_path, "Permission denied")
    else:
        uncached_runs(tmp_path, "Read-only file system", read_only(cache))


def test_a_cache_write_beyond_the_file_size_limit_is_one_note_not_a_traceback(
    tmp_path: Path,
) -> None:  # fmt: skip
    """RLIMIT_FSIZE (as a full disk: the folder probes fine, the write fails): numba raised
    "OSError: [Errno 27] File too large" out of the first compilation, a traceback; now the
    kernel runs uncached and the start says so once."""

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (1024, 1024))

    uncached_runs(tmp_path, "File too large", limited)


def test_two_sites_warming_up_at_once_from_an_empty_cache_both_succeed(tmp_path: Path) -> None:
    pytest.importorskip("zenoh")
    cache, barrier = tmp_path / "cache", str(tmp_path / "barrier")
    script = tmp_path / "warm_up.py"
    script.write_text(WARM_UP)
    procs = {
        name: subprocess.Popen(
            [sys.executable, str(script), name, barrier, str(CONFIGS / "paper_experiment.yaml")],
            env=env_with_cache(cache), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        for name in ("hsi", "to")
    }
    results = {name: p.communicate(timeout=TIMEOUT_S) for name, p in procs.items()}
    for name, p in procs.items():
        assert p.returncode == 0, f"{name}: {results[name][1]}"
    waited = [json.loads(out)["waited"] for out, _ in results.values()]
    assert sum(waited) >= 1, "neither site ever found the other compiling"
