"""Per-tick recording without blocking the tick.

``Recorder.record`` copies the tick's signals from the session's packed state into one row of
a shared-memory ring (one compiled call) and publishes it; the writer process
(``teleop_rt.recording.writer``) turns rows into MCAP messages on the other core. The ring holds
``capacity`` rows (65 s at 1 kHz by default); the producer waits only if the writer falls a whole
ring behind, so no row is ever dropped.
"""

from __future__ import annotations

import datetime as _dt
import multiprocessing
import struct
import time
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from teleop_rt.errors import TeleopError
from teleop_rt.flat import jit
from teleop_rt.recording.schema import SCHEMA_VERSION, LogLayout
from teleop_rt.recording.writer import (
    CLOSED,
    CONSUMED,
    CONTROL_BYTES,
    PUBLISHED,
    START_NS,
    writer_main,
)
from teleop_rt.version import software_version

if TYPE_CHECKING:
    from teleop_rt.session import Session

DEFAULT_LOG_DIR = Path("logs")


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
        raise LogPathError(f"--log {path}: the file exists; choose another path") from None
    except OSError as err:
        raise LogPathError(f"--log {path}: cannot create ({err.strerror})") from None
    return path


class Recorder:
    """Owns the ring and the writer process of one log file.

    ``metadata``: further ``teleop_rt`` metadata keys (the CLI's config path and overrides)."""

    def __init__(
        self,
        session: Session,
        path: Path,
        capacity: int = 65536,
        metadata: dict[str, str] | None = None,
    ) -> None:
        cfg = session.cfg
        self.path = create_log_file(Path(path))
        self.layout = LogLayout(session.n, len(cfg.environment))
        self.session = session
        width = self.layout.row_width
        self.capacity = capacity
        self.row_bytes = width * 8
        self._count = struct.Struct("@q")
        self.shm = SharedMemory(create=True, size=CONTROL_BYTES + capacity * self.row_bytes)
        self.buf = self.shm.buf
        # the ring as rows of float64 (native order, as the writer reads it), and where each
        # signal column of a row sits in the session's packed state
        self.ring = np.ndarray((capacity, width), np.float64, self.shm.buf, CONTROL_BYTES)
        self.gather = row_sources(session, self.layout)
        fill_row(np.zeros(width), session.packed.f, self.gather, 0, 0.0, 0, 0, False)  # load
        self.published = 0
        self._consumed_known = 0
        self._period_ns = round(cfg.dt * 1e9)
        # the session's start on the wall clock: now, until the first tick says when it ran
        self._count.pack_into(self.buf, START_NS * 8, time.time_ns())
        # fork: the writer starts in milliseconds (spawn would re-import numpy and mcap, and
        # needs an importable __main__); it touches nothing of the parent but the ring
        method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        ctx = multiprocessing.get_context(method)
        self._summary_rx, self._summary_tx = ctx.Pipe(duplex=False)
        self.process = ctx.Process(
            target=writer_main,
            args=(
                self.shm.name,
                capacity,
                (self.layout.n, self.layout.n_env),
                str(self.path),
                self._period_ns,
                {**_metadata(session), **(metadata or {})},
                _attachments(session),
                self._summary_rx,
            ),
            name="teleop-rt-log-writer",
            daemon=False,
        )
        self.process.start()
        self.closed = False

    def record(self, compute_ns: int, lateness_ns: int, missed: bool) -> None:
        """Copy the tick the session just ran (its tick - 1) into the ring and publish it."""
        s = self.session
        k = s.tick - 1
        i = self.published
        if i - self._consumed_known >= self.capacity:
            self._wait_for_room(i)
        if i == 0:  # once: UTC of tick 0, which log times count from (read before PUBLISHED)
            start = time.time_ns() - compute_ns - k * self._period_ns
            self._count.pack_into(self.buf, START_NS * 8, start)
        fill_row(
            self.ring[i % self.capacity], s.packed.f, self.gather, k, k * s.dt,
            compute_ns, lateness_ns, missed,
        )  # fmt: skip
        self.published = i + 1
        self._count.pack_into(self.buf, PUBLISHED * 8, i + 1)

    def _wait_for_room(self, i: int) -> None:
        while True:
            self._consumed_known = self._count.unpack_from(self.buf, CONSUMED * 8)[0]
            if i - self._consumed_known < self.capacity:
                return
            if not self.process.is_alive():
                raise TeleopError(f"log writer for {self.path} stopped unexpectedly")
            time.sleep(0.0005)

    def close(self, summary: dict | None, timeout_s: float = 120.0) -> None:
        """Publish the end, hand over the summary, wait for the file to be finished."""
        if self.closed:
            return
        self.closed = True
        try:
            if summary is not None:
                self._summary_tx.send(summary)
            self._count.pack_into(self.buf, CLOSED * 8, 1)
            self.process.join(timeout_s)
            if self.process.is_alive():  # pragma: no cover - a stuck disk
                self.process.terminate()
                raise TeleopError(f"log writer for {self.path} did not finish in {timeout_s} s")
        finally:
            self.buf = self.ring = None
            self.shm.close()
            self.shm.unlink()


def row_sources(session: Session, layout: LogLayout) -> np.ndarray:
    """For each signal column of a log row (between the tick and time and the timing
    columns), its position in the session's packed state."""
    packed, hsi, to, ch = session.packed, session.hsi, session.to, session.channel
    robot = {
        "q": "feedback.q", "v": "feedback.v", "tau_ext": "feedback.tau_ext",
        "tau_cmd": "computed_torque.tau", "a_ref": "controller.out",
    }  # fmt: skip
    world = {
        "operator_reference_m": "reference",
        "operator_reference_velocity_m_s": "reference_velocity",
        "operator_force_n": "force",
        "environment_force_n": "force",
        "in_contact": "contacts",
    }
    out: list[int] = []
    for topic in layout.topics[:3]:  # /hsi, /to, /channel; /timing is the record's own
        side = {"/hsi": hsi, "/to": to}.get(topic.name)
        for field in topic.fields[2:]:
            if side is None:
                block, name = ch, field.name
            elif field.name in robot:
                owner, name = robot[field.name].split(".")
                block = getattr(side, owner)
            else:
                block, name = side.backend.world, world[field.name]
            first = packed.index_of(block, name)
            out += range(first, first + field.count)
    return np.array(out, dtype=np.int64)


@jit
def fill_row(
    row: np.ndarray,
    f: np.ndarray,
    gather: np.ndarray,
    tick: int,
    t: float,
    compute_ns: int,
    lateness_ns: int,
    missed: bool,
) -> None:
    """One log row (``teleop_rt.recording.schema``): tick, time, the signals at the packed
    positions ``gather``, then the timing columns."""
    row[0] = tick
    row[1] = t
    for c in range(gather.size):
        row[2 + c] = f[gather[c]]
    m = gather.size + 2
    row[m] = compute_ns
    row[m + 1] = lateness_ns
    row[m + 2] = 1.0 if missed else 0.0


def _metadata(session: Session) -> dict[str, str]:
    cfg = session.cfg
    operator = cfg.operator.kind if cfg.backend == "sim" else "none"
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
