"""Per-tick recording that never holds the tick.

``Recorder.record`` copies the tick's signals from the session's packed state into one row of
a shared-memory ring (one compiled call) and publishes it; the writer process
(``teleop_rt.recording.writer``) turns rows into MCAP messages on the other core. The ring holds
``recording.ring_s`` seconds of rows.

The tick never waits for the writer (real time): a row that finds the ring full is dropped and
counted, its tick range kept for the summary (the reader finds the gap from the ticks logged).
A dead writer or one that cannot write (a full disk: it says so in the control block) is seen
without a system call per tick: the control block is read, and the process polled, every
``CHECK_TICKS`` ticks and whenever the ring is full. Any loss is a recording failure: the
session stops at the tick boundary (``recording.on_loss: stop``, raising ``RecordingFailure``)
or runs on without a log (``continue``), and the log is reported incomplete. In fast mode with
simulated robots (``wait_for_room``) no deadline exists, so a full ring waits for a writer that
makes progress, keeping the log whole and the run deterministic.

Closing is bounded: the writer may take as long as it needs while it makes progress; one that
makes none for ``CLOSE_STALL_S`` (or a second Ctrl-C) is killed and the log reported incomplete.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import errno
import json
import math
import multiprocessing
import os
import resource
import signal
import struct
import time
from dataclasses import dataclass
from functools import partial
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from teleop_rt.declarations import (
    CLOSED,
    CONSUMED,
    ERRNO,
    HEARTBEAT,
    PUBLISHED,
    START_NS,
    STATUS,
    WRITE_FAILED,
)
from teleop_rt.errors import RecordingFailure, TeleopError
from teleop_rt.flat import compiled_for, jit
from teleop_rt.loop import StopSignals
from teleop_rt.mapping import JOINT, frame_rotation
from teleop_rt.recording.scene import scene_spec, shift_sources
from teleop_rt.recording.schema import MAPPED_FIELDS, SCHEMA_VERSION, LogLayout
from teleop_rt.recording.writer import (
    CONTROL_BYTES,
    writer_main,
)
from teleop_rt.version import software_version

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig
    from teleop_rt.recording.live import LiveAddress
    from teleop_rt.recording.scene import SceneSpec
    from teleop_rt.session import Session

DEFAULT_LOG_DIR = Path("logs")
CHECK_TICKS = 256  # the writer's health is read every this many ticks (and on a full ring)
MIN_RING_ROWS = 16
MAX_GAPS = 1024  # dropped tick ranges kept one by one; more are merged into the last
STALL_S = 2.0  # a full ring in fast mode: a writer without progress this long has failed
CLOSE_STALL_S = 3.0  # closing: a writer without progress this long is killed
LIVE_START_TIMEOUT_S = 10.0  # the live view's server: listening within this, or no session


class LiveError(TeleopError):
    """The live view cannot listen where it was asked (an address in use, not this host's)."""

    exit_code = 2


class LogPathError(TeleopError):
    """The log file cannot be created (exists already, or its folder is not writable)."""

    exit_code = 2


def default_log_path(name: str, directory: Path | None = None) -> Path:
    """logs/<name>-<UTC timestamp>.mcap; a numbered suffix if that exists (never overwrites)."""
    directory = DEFAULT_LOG_DIR if directory is None else directory
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    path = directory / f"{name}-{stamp}.mcap"
    i = 1
    while path.exists():
        path = directory / f"{name}-{stamp}-{i}.mcap"
        i += 1
    return path


def create_log_file(path: Path) -> Path:
    """Create the file exclusively: an existing file is never overwritten."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "xb"):
            pass
    except FileExistsError:
        what = "is a folder; give a file name" if path.is_dir() else "the file exists"
        raise LogPathError(f"--log {path}: {what}; choose another path") from None
    except OSError as err:
        raise LogPathError(f"--log {path}: cannot create ({err.strerror})") from None
    return path


@dataclass
class LogParts:
    """What a log is made of: its layout, where each ring column sits in the source's packed
    state, the environment's shifts (for the scene), its metadata, attachments and 3D scene."""

    layout: LogLayout
    gather: np.ndarray
    shifts: np.ndarray
    metadata: dict[str, str]
    attachments: dict[str, bytes]
    scene: SceneSpec | None


def session_parts(session: Session) -> LogParts:
    """A one-process session's log: both robots (each with its own joints), the channel (of its
    size), the timing; a session whose sites map their ports also logs what its T_p and T_tau
    compare."""
    layout = session_layout(session)
    return LogParts(
        layout, row_sources(session, layout), shift_sources(session),
        {**_metadata(session), **_shape(layout), **mapping_metadata(session.cfg, layout,
                                                                   session.sites)},
        _attachments(session), scene_spec(session),
    )  # fmt: skip


def session_layout(session: Session) -> LogLayout:
    """The log layout of ``session``: the channel's size, each robot's joints, mapped or not."""
    mapped = any(site.mapping.active for site in session.sites)
    return LogLayout(
        session.n, len(session.cfg.environment), "", session.hsi.n, session.to.n, mapped
    )


class Recorder:
    """Owns the ring and the writer process of one log file, and the policy on losing rows.

    ``session``: a one-process ``Session``, or any source with ``cfg``, ``n``, ``dt``,
    ``packed``, ``tick`` and ``log_parts()`` (a site's own log: ``teleop_rt.recording.site_log``).
    ``wait_for_room``: a full ring waits for the writer (fast mode with simulated robots only:
    nothing real is held) instead of dropping the row. ``metadata``: further ``teleop_rt``
    metadata keys (the CLI's config path and overrides)."""

    def __init__(
        self,
        session: Session | Any,
        path: Path,
        capacity: int | None = None,
        wait_for_room: bool = False,
        metadata: dict[str, str] | None = None,
        live: LiveAddress | None = None,
    ) -> None:
        cfg = session.cfg
        self.path = create_log_file(Path(path))
        try:
            self._open(session, cfg, capacity, wait_for_room, metadata, live)
        except BaseException:  # a signal (Terminated) or an error while starting: no session
            self._abandon()
            raise

    def _open(self, session, cfg, capacity, wait_for_room, metadata, live) -> None:
        parts = session.log_parts() if hasattr(session, "log_parts") else session_parts(session)
        self.layout = parts.layout
        self.session = session
        width = self.layout.ring_width
        if capacity is None:
            capacity = max(MIN_RING_ROWS, math.ceil(cfg.recording.ring_s * cfg.rate_hz))
        self.capacity = capacity
        self.row_bytes = width * 8
        self.stop_on_loss = cfg.recording.on_loss == "stop"
        self.wait_for_room = wait_for_room
        self._count = struct.Struct("@q")
        size = CONTROL_BYTES + capacity * self.row_bytes
        try:
            _check_room_for_ring(size)
            self.shm = SharedMemory(create=True, size=size)
        except OSError as err:
            self.path.unlink()  # created empty just now, by this recorder
            raise TeleopError(
                f"cannot make the log's ring of {size / 1e6:.1f} MB in shared memory "
                f"({err.strerror}); a smaller recording.ring_s needs less"
            ) from None
        buf = self.shm.buf
        assert buf is not None  # (None only once the mapping is closed)
        self.buf: memoryview = buf
        self.ctrl = np.ndarray((CONTROL_BYTES // 8,), np.int64, self.shm.buf)
        # the ring as rows of float64 (native order, as the writer reads it), and where each
        # signal column of a row sits in the session's packed state
        self.ring = np.ndarray((capacity, width), np.float64, self.shm.buf, CONTROL_BYTES)
        self.ring.fill(0.0)  # its pages now, not as page faults on the tick path
        self.gather = parts.gather
        self.shifts = parts.shifts  # for the 3D scene only (ring_width)
        # the hot-path kernel, loaded (or compiled) now and bound to the ring and the session's
        # buffers: per tick only the row's count, the tick and the timing go in
        args = (self.ring, session.packed.f, session.packed.i, self.gather, self.shifts, session.dt)
        fill_row(np.zeros((1, width)), *args[1:], 0, 0, 0, 0, False)
        self._fill = partial(compiled_for(fill_row, *args, 0, 0, 0, 0, False), *args)
        self.published = 0
        self._consumed_known = 0
        # what did not reach the log: rows dropped, their tick ranges (preallocated: the
        # tick path allocates nothing), the first failure, and whether the writer is gone
        self.dropped = 0
        self._gaps = np.zeros((MAX_GAPS, 2), np.int64)
        self._n_gaps = 0
        self.failure: str | None = None
        self.writer_gone = False
        self._full = False  # the ring was full at the last look
        self._period_ns = round(cfg.dt * 1e9)
        self._start_fixed = False  # describe() gave the start instant
        # the session's start on the wall clock: now, until the first tick says when it ran
        self._count.pack_into(self.buf, START_NS * 8, time.time_ns())
        # fork: the writer starts in milliseconds (spawn would re-import numpy and mcap, and
        # needs an importable __main__); it touches nothing of the parent but the ring
        fork = "fork" in multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("fork") if fork else multiprocessing.get_context("spawn")
        self._summary_rx, self._summary_tx = ctx.Pipe(duplex=False)
        live_rx, live_tx = ctx.Pipe(duplex=False) if live is not None else (None, None)
        self.process = ctx.Process(
            target=writer_main,
            args=(
                self.shm.name,
                capacity,
                dataclasses.astuple(self.layout),
                str(self.path),
                self._period_ns,
                {**parts.metadata, **(metadata or {})},
                parts.attachments,
                self._summary_rx,
                parts.scene,
                live,
                live_tx,
            ),
            name="teleop-rt-log-writer",
            daemon=False,
        )
        self.process.start()
        if live_tx is not None:
            live_tx.close()  # the writer's end: a writer that dies unheard is an EOF here
        self.closed = False
        self.live: LiveAddress | None = None  # where the live view listens
        if live is not None:
            self._await_live(live, live_rx)

    def _abandon(self) -> None:
        """Undo a start that did not finish (a SIGTERM while the kernel loads or the writer
        starts): no writer left behind, no ring, and no file, which holds no session (an
        empty or half-written file would be no log and block a rerun on the same path)."""
        self.closed = True
        process = getattr(self, "process", None)
        if process is not None and process.pid is not None and process.exitcode is None:
            process.kill()  # it ignores SIGINT and SIGTERM
            process.join(5.0)
        shm = getattr(self, "shm", None)
        if shm is not None:
            self.buf = self.ring = self.ctrl = self._fill = None  # type: ignore[assignment]  # released with the mapping: unused after
            with contextlib.suppress(OSError, BufferError):
                shm.close()
            with contextlib.suppress(OSError):
                shm.unlink()
        self.path.unlink(missing_ok=True)

    def _await_live(self, asked: LiveAddress, conn) -> None:
        """Wait (before the session starts) for the writer's server to listen; one line and
        no log file when it cannot."""
        why = f"the log writer {_ended(self.process.exitcode)}"
        if conn.poll(LIVE_START_TIMEOUT_S):
            try:
                state, what = conn.recv()
            except (EOFError, OSError):
                state, what = "failed", why
            if state == "listening":
                self.live = what
                return
            why = what
        else:
            why = f"the server did not start within {LIVE_START_TIMEOUT_S:g} s"
        self.closed = True
        self.process.join(CLOSE_STALL_S)
        if self.process.exitcode is None:
            self.process.kill()
            self.process.join()
        self.buf = self.ring = self.ctrl = self._fill = None  # type: ignore[assignment]  # released with the mapping: unused after
        self.shm.close()
        self.shm.unlink()
        self.path.unlink()  # created empty by this recorder; nothing was written
        raise LiveError(f"--live {asked}: cannot serve the session there ({why})")

    def describe(self, metadata: dict[str, str], start_ns: int | None = None) -> None:
        """Before the first tick: further ``teleop_rt`` metadata learnt after the writer started
        (a site's session id, from its handshake) and, if given, the instant tick 0 is due at,
        which log times count from (a site's: the one agreed with its peer), instead of when it
        ran."""
        if self.published:
            raise RuntimeError("describe() comes before the first tick")
        if start_ns is not None:
            self._count.pack_into(self.buf, START_NS * 8, start_ns)
            self._start_fixed = True
        self._summary_tx.send(("metadata", metadata))

    def record(self, compute_ns: int, lateness_ns: int, missed: bool) -> None:
        """Copy the tick the session just ran (its tick - 1) into the ring and publish it, or
        drop it if the writer cannot take it; raise ``RecordingFailure`` on a loss when the
        config says stop."""
        s = self.session
        k = s.tick - 1
        i = self.published
        if i == 0 and not self._start_fixed:  # UTC of tick 0 (read before PUBLISHED)
            start = time.time_ns() - compute_ns - k * self._period_ns
            self._count.pack_into(self.buf, START_NS * 8, start)
        if (
            k % CHECK_TICKS == 0 or i - self._consumed_known >= self.capacity or self.writer_gone
        ) and not self._room(i, k):
            self._drop(k)
            if self.stop_on_loss:
                raise RecordingFailure(self.failure)
            return
        self._fill(i, k, compute_ns, lateness_ns, missed)
        self.published = i + 1
        self._count.pack_into(self.buf, PUBLISHED * 8, i + 1)

    def _room(self, i: int, k: int) -> bool:
        """Whether row i (tick k) can go into the ring; on False, ``failure`` says why."""
        if self.writer_gone:
            return False
        self._consumed_known = int(self.ctrl[CONSUMED])
        full = i - self._consumed_known >= self.capacity
        if k % CHECK_TICKS == 0 or (full and not self._full):  # not a system call per tick
            self._check_writer(k)
            if self.writer_gone:
                return False
        self._full = full
        if not full:
            return True
        if self.wait_for_room and self._wait_for_room(i, k):
            self._full = False
            return True
        self._fail(
            f"the log writer fell {self.capacity} rows behind at tick {k} (its ring was full); "
            "ticks were dropped"
        )
        return False

    def _check_writer(self, k: int) -> None:
        """A writer that cannot write or has died: nothing more reaches the log."""
        if self.ctrl[STATUS] == WRITE_FAILED:
            why = f"cannot write {self.path} ({os.strerror(int(self.ctrl[ERRNO]))})"
        elif not self.process.is_alive():
            why = f"the log writer {_ended(self.process.exitcode)}"
        else:
            return
        self.writer_gone = True
        self._fail(f"{why} at tick {k}; rows not yet on disk are lost")

    def _fail(self, reason: str, also: bool = False) -> None:
        """Keep the first cause; ``also`` adds what came of it (a writer killed at close)."""
        if self.failure is None:
            self.failure = reason
        elif also:
            self.failure += f"; then {reason}"

    def _wait_for_room(self, i: int, k: int) -> bool:
        """Fast mode: wait while the writer makes progress (a batch frees room in tens of ms);
        no progress for STALL_S, a dead writer or a stop request (Ctrl-C) end the wait."""
        progress, since = self._progress(), time.monotonic()
        while True:
            time.sleep(0.0005)
            self._consumed_known = int(self.ctrl[CONSUMED])
            if i - self._consumed_known < self.capacity:
                return True
            self._check_writer(k)
            if self.writer_gone or StopSignals.pending():
                return False
            now = self._progress()
            if now != progress:
                progress, since = now, time.monotonic()
            elif time.monotonic() - since > STALL_S:
                self.wait_for_room = False  # from here on a full ring drops rows, as in real time
                self._fail(f"the log writer made no progress for {STALL_S:g} s at tick {k}")
                return False

    def _progress(self) -> tuple[int, int]:
        return int(self.ctrl[CONSUMED]), int(self.ctrl[HEARTBEAT])

    def _drop(self, k: int) -> None:
        self.dropped += 1
        j = self._n_gaps
        if j and self._gaps[j - 1, 1] == k - 1:
            self._gaps[j - 1, 1] = k
        elif j < MAX_GAPS:
            self._gaps[j, 0] = self._gaps[j, 1] = k
            self._n_gaps = j + 1
        else:  # out of room: the last range grows over what it skips (the count stays exact)
            self._gaps[j - 1, 1] = k

    def status(self) -> dict:
        """Whether the log holds every tick: rows dropped (never handed to the writer), their
        tick ranges [first, last], and the first failure (None if there was none)."""
        return {
            "complete": self.failure is None and self.dropped == 0,
            "dropped_rows": self.dropped,
            "gaps": self._gaps[: self._n_gaps].tolist(),
            "failure": self.failure,
        }

    def close(self, summary: dict | None) -> dict:
        """Publish the end, hand over the summary (with ``status()``), wait for the file to be
        finished (bounded: see CLOSE_STALL_S); return the final ``status()``."""
        if self.closed:
            return self.status()
        self.closed = True
        try:
            try:
                if summary is not None:
                    self._summary_tx.send(("summary", {**summary, "recording": self.status()}))
                self._count.pack_into(self.buf, CLOSED * 8, 1)
                self._finish()
            except KeyboardInterrupt:  # a second Ctrl-C: the user will not wait
                self._end_writer("a second interrupt while the log was being finished")
        finally:
            self.buf = self.ring = self.ctrl = self._fill = None  # type: ignore[assignment]  # released with the mapping: unused after
            self.shm.close()
            self.shm.unlink()
        return self.status()

    def discard(self) -> None:
        """Before the first tick, when the run cannot start (its link cannot open, the peer
        never answered): end the writer and remove the file, which holds no tick."""
        if not self.closed:
            self.close(None)
        if self.published == 0:
            self.path.unlink(missing_ok=True)

    def _finish(self) -> None:
        progress, since = self._progress(), time.monotonic()
        while True:
            self.process.join(0.05)
            if self.process.exitcode is not None:
                break
            now = self._progress()
            if now != progress:
                progress, since = now, time.monotonic()
            elif time.monotonic() - since > CLOSE_STALL_S:
                self._end_writer(f"no progress for {CLOSE_STALL_S:g} s while finishing the log")
                return
        if self.ctrl[STATUS] == WRITE_FAILED:
            self._fail(f"cannot write {self.path} ({os.strerror(int(self.ctrl[ERRNO]))})")
        elif self.process.exitcode != 0:
            self._fail(f"the log writer {_ended(self.process.exitcode)} while finishing")

    def _end_writer(self, why: str) -> None:
        self.process.kill()  # SIGKILL: it ignores SIGINT and SIGTERM, and may be stopped
        self.process.join(5.0)
        self._fail(f"{why}: the writer was killed and the log is cut short", also=True)


def _check_room_for_ring(size: int) -> None:
    """Raise OSError if the ring cannot be made whole: checked before, as a shared-memory file
    larger than RLIMIT_FSIZE fails inside SharedMemory with a traceback from its resource
    tracker, and one larger than the free space of /dev/shm kills the process (SIGBUS) when
    a row is written to a page that cannot be allocated."""
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY and size > limit:
        raise OSError(errno.EFBIG, f"more than the file size limit of {limit} bytes")
    if os.path.isdir("/dev/shm"):
        fs = os.statvfs("/dev/shm")
        if size > fs.f_bavail * fs.f_frsize:
            raise OSError(errno.ENOSPC, f"/dev/shm has {fs.f_bavail * fs.f_frsize} bytes free")


def _ended(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        return f"was killed by {signal.Signals(-exitcode).name}"
    return f"exited with code {exitcode}"


def _mapped_source(site, name: str) -> tuple[Any, str]:
    """The block and vector of a mapped field: what the session's metrics take from the site
    (``teleop_rt.site_tick.site_position``, ``site_torque``)."""
    active = bool(site.mapping.active)
    if name == "q_mapped":
        return (site.mapping, "q_mapped") if active else (site.feedback, "q")
    torque_mapped = active and (site.name != "hsi" or site.mapping.space != JOINT)
    return (site.mapping, "tau_mapped") if torque_mapped else (site.signals, "tau")


MAPPED_NAMES = {name for name, _ in MAPPED_FIELDS}


def row_sources(session: Session, layout: LogLayout) -> np.ndarray:
    """For each signal column of a log row (between the tick and time and the timing
    columns), its position in the session's packed state."""
    packed, hsi, to, ch = session.packed, session.hsi, session.to, session.channel
    out: list[int] = []
    for topic in layout.topics[:3]:  # /hsi, /to, /channel; /timing is the record's own
        site = {"/hsi": hsi, "/to": to}.get(topic.name)
        if site is not None:
            out += robot_columns(packed, site, topic)
            continue
        for field in topic.fields[2:]:
            block, name = ch.source(field.name)
            first = packed.index_of(block, name)
            out += range(first, first + field.count)
    return np.array(out, dtype=np.int64)


def robot_columns(packed, site, topic) -> list[int]:
    """Where the fields of a robot's topic (/hsi or /to) sit in ``packed``, column by column."""
    out: list[int] = []
    for field in topic.fields[2:]:
        if field.name in MAPPED_NAMES:  # (its block depends on the site's map)
            block, name = _mapped_source(site, field.name)
        else:  # the site's block and field the schema names (schema.ROBOT_FIELDS, the world's)
            assert field.source is not None
            owner, name = field.source
            block = getattr(site, owner)
        first = packed.index_of(block, name)
        out += range(first, first + field.count)
    return out


@jit
def fill_row(
    ring: np.ndarray,
    f: np.ndarray,
    i: np.ndarray,
    gather: np.ndarray,
    shifts: np.ndarray,
    dt: float,
    published: int,
    tick: int,
    compute_ns: int,
    lateness_ns: int,
    missed: bool,
) -> None:
    """Ring row ``published`` modulo the ring's rows (``LogLayout.ring_width`` wide): tick,
    time (tick dt), the signals at the packed positions ``gather`` (``Packed.index_of``: >= 0
    in ``f``, -1 - k for ``i[k]``), the timing columns, then the environment's shifts at the
    positions ``shifts`` (0 where the position is -1). The ring is indexed here, not sliced
    in Python: a row's view would be an object made per tick."""
    row = ring[published % ring.shape[0]]
    row[0] = tick
    row[1] = tick * dt
    for c in range(gather.size):
        g = gather[c]
        row[2 + c] = f[g] if g >= 0 else float(i[-1 - g])
    m = gather.size + 2
    row[m] = compute_ns
    row[m + 1] = lateness_ns
    row[m + 2] = 1.0 if missed else 0.0
    for e in range(shifts.size):
        row[m + 3 + e] = f[shifts[e]] if shifts[e] >= 0 else 0.0


def _shape(layout: LogLayout) -> dict[str, str]:
    """The metadata of a layout that is not the plain one of ``joints`` (LogLayout.plain)."""
    if layout.plain:
        return {}
    return {"joints_hsi": str(layout.joints_hsi), "joints_to": str(layout.joints_to),
            "mapped": str(int(layout.mapped))}  # fmt: skip


def mapping_metadata(cfg: SessionConfig, layout: LogLayout, sites) -> dict[str, str]:
    """A mapped log's ``mapping`` metadata (JSON): the map's constants (the space, alpha, beta,
    the frames' offset and rotation, R as the TO applies it) and how its sites took the
    operator's live inputs: the HSI's ``live_inputs`` (INPUT_* bits read from the backend's
    feedback, logged per tick as ``inputs``), the TO's ``follows_packets`` (it decoupled on the
    packets' ``engaged``); a replay runs its sites so (``teleop_rt.recording.site_replay``)."""
    if not layout.mapped:
        return {}
    spec = cfg.mapping
    out: dict[str, Any] = {
        "space": cfg.channel.space, "motion_scale": spec.motion_scale,
        "force_scale": spec.force_scale, "offset_m": list(spec.offset_m),
        "rotation_rpy_deg": list(spec.rotation_rpy_deg),
        "rotation": frame_rotation(spec.rotation_rpy_deg).tolist(),
    }  # fmt: skip
    for site in sites:
        if site.name == "hsi":
            out["live_inputs"] = int(site.mapping.live)
        else:
            out["follows_packets"] = int(site.mapping.follow)
    return {"mapping": json.dumps(out)}


def _metadata(session: Session) -> dict[str, str]:
    cfg = session.cfg
    operator = cfg.operator.kind if cfg.backend_for("hsi") == "sim" else "none"
    return {
        "software_version": software_version(),
        "schema_version": str(SCHEMA_VERSION),
        "joints": str(session.n),
        "env_elements": str(len(cfg.environment)),
        "rate_hz": str(cfg.rate_hz),
        # log time of tick k: start_time_ns + k * period_ns (the writer adds the start time)
        "period_ns": str(round(cfg.dt * 1e9)),
        "delay_ticks": str(cfg.delay_ticks),
        "name": cfg.name,
        "backend": cfg.backend,
        "backend_hsi": cfg.backend_for("hsi"),
        "backend_to": cfg.backend_for("to"),
        "operator": operator,
    }


def _attachments(session: Session) -> dict[str, bytes]:
    cfg = session.cfg
    data = cfg.model_dump(mode="json")
    out = {"config.yaml": yaml.safe_dump(data, sort_keys=False).encode()}
    for side in ("hsi", "to"):
        urdf = getattr(cfg, side).robot.urdf
        if urdf is not None:
            out[f"urdf/{side}.urdf"] = Path(urdf).read_bytes()
    return out
