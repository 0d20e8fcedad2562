"""``--can-log PATH``: every frame of every CAN bus of a session, in a file python-can writes
(``can.Logger`` picks the format by the extension: ``.asc``, ``.blf``, ``.log``, ``.csv``,
``.trc``, ``.txt``) and reads back (``can.LogReader``).

Off the tick path, as the MCAP log is: the backend's bus is wrapped (``TappedBus``) so that each
frame it sends or receives, start-up and stop included, is packed into a shared-memory ring
(one ``struct.pack_into``: no queue object, no system call); a writer process (``teleop-rt-can``
in ``ps``) turns records into ``can.Message`` objects for python-can's writer. The robots' two
buses are python-can channels 0 (HSI) and 1 (TO); ASC and BLF number them from 1.

A frame that finds the ring full is dropped and counted (real time never waits); in fast mode
with emulated drives nothing real waits, so a full ring waits for a writer that makes progress.
Frames dropped, or a writer that could not write, make the CAN log incomplete: one line and exit
code 4, as for the session's log.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import struct
import threading
import time
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import can

from teleop_rt.declarations import (
    CLOSED,
    CONSUMED,
    CONTROL_WORDS,
    ERRNO,
    HEARTBEAT,
    PUBLISHED,
    STATUS,
    WRITE_FAILED,
)
from teleop_rt.errors import ConfigError
from teleop_rt.process_name import set_process_name

FORMATS = (".asc", ".blf", ".log", ".csv", ".trc", ".txt")  # python-can's own, no extra package
CHANNELS = {"hsi": 0, "to": 1}
# timestamp (s since the epoch: the interface's for a received frame, time.time() at the send
# for a sent one), id, data length, flags, channel, pad, data
RECORD = struct.Struct("<dIBBBx64s")
EXTENDED, RX, ERROR, REMOTE, FD, BRS, ESI = (1 << k for k in range(7))
CAPACITY = 1 << 15  # records (2.6 MB): 1.6 s of the 20 000 frames a second of two robots
CONTROL = struct.Struct(f"@{CONTROL_WORDS}q")  # the writer's control words (declarations)
PROCESS_NAME = "teleop-rt-can"
POLL_S = 0.005
BATCH = 1024  # records written between two reports of progress
STALL_S = 2.0  # a writer without progress this long has failed (a full ring, or closing)


def check_can_log_path(text: str) -> Path:
    """The --can-log path, checked before any work: a known extension, an existing folder, not
    an existing file (logs are never overwritten)."""
    path = Path(text)
    if path.suffix.lower() not in FORMATS:
        raise ConfigError(
            f"--can-log {text}: the format comes from the extension, one of {', '.join(FORMATS)}"
        )
    if path.is_dir():
        raise ConfigError(f"--can-log {text}: is a folder")
    if path.exists():
        raise ConfigError(f"--can-log {text}: the file exists; choose another path")
    if not path.parent.is_dir():
        raise ConfigError(f"--can-log {text}: no such folder: {path.parent}")
    return path


class CanLog:
    """The ring and the writer process of one CAN log file; ``tap(side)`` is what a backend's
    bus calls for each frame (``TappedBus``)."""

    def __init__(self, path: Path, wait_for_room: bool = False, capacity: int = CAPACITY) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "xb"):  # reserved now; python-can's writer opens it again
                pass
        except OSError as err:
            raise ConfigError(f"--can-log {path}: cannot create ({err.strerror})") from None
        self.capacity = capacity
        self.wait_for_room = wait_for_room
        self.shm = SharedMemory(create=True, size=CONTROL.size + capacity * RECORD.size)
        buf = self.shm.buf
        assert buf is not None  # (None only once the mapping is closed)
        self.buf: memoryview = buf
        CONTROL.pack_into(self.buf, 0, *[0] * CONTROL_WORDS)
        self._word = struct.Struct("@q")
        self.published = 0
        self._consumed = 0
        self.dropped = 0
        self.failure: str | None = None
        self._lock = threading.Lock()  # a keepalive thread and the loop may both send
        fork = "fork" in multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("fork") if fork else multiprocessing.get_context("spawn")
        self.process = ctx.Process(
            target=_writer_main,
            args=(self.shm.name, capacity, str(self.path)),
            name="teleop-rt-can-writer",
            daemon=False,
        )
        self.process.start()
        self.closed = False

    def tap(self, side: str):
        """The function a bus calls with each frame: (message, received, time.time() of it)."""
        channel = CHANNELS[side]

        def record(msg: can.Message, rx: bool, stamp: float) -> None:
            self._record(msg, rx, channel, stamp)

        return record

    def _ctrl(self, word: int) -> int:
        return self._word.unpack_from(self.buf, word * 8)[0]

    def _record(self, msg: can.Message, rx: bool, channel: int, stamp: float) -> None:
        with self._lock:
            i = self.published
            if i - self._consumed >= self.capacity and not self._room(i):
                self.dropped += 1
                return
            flags = (
                (EXTENDED if msg.is_extended_id else 0) | (RX if rx else 0)
                | (ERROR if msg.is_error_frame else 0) | (REMOTE if msg.is_remote_frame else 0)
                | (FD if msg.is_fd else 0) | (BRS if msg.bitrate_switch else 0)
                | (ESI if msg.error_state_indicator else 0)
            )  # fmt: skip
            data = msg.data
            RECORD.pack_into(
                self.buf, CONTROL.size + (i % self.capacity) * RECORD.size,
                stamp, msg.arbitration_id, len(data), flags, channel, data,
            )  # fmt: skip
            self.published = i + 1
            self._word.pack_into(self.buf, PUBLISHED * 8, i + 1)

    def _room(self, i: int) -> bool:
        """Whether record i fits now (read the writer's progress; in fast mode wait for it)."""
        self._consumed = self._ctrl(CONSUMED)
        if i - self._consumed < self.capacity:
            return True
        if not self.wait_for_room or self.failure:
            return False
        progress, since = self._consumed, time.monotonic()
        while self._ctrl(STATUS) != WRITE_FAILED and self.process.is_alive():
            time.sleep(0.0005)
            self._consumed = self._ctrl(CONSUMED)
            if i - self._consumed < self.capacity:
                return True
            if self._consumed != progress:
                progress, since = self._consumed, time.monotonic()
            elif time.monotonic() - since > STALL_S:
                self._fail(f"the CAN log writer made no progress for {STALL_S:g} s")
                return False
        self._fail("the CAN log writer stopped")  # close() says why
        return False

    def close(self) -> dict:
        """Let the writer finish the file (bounded); return ``status()``."""
        if not self.closed:
            self.closed = True
            self._word.pack_into(self.buf, CLOSED * 8, 1)
            progress, since = self._ctrl(CONSUMED), time.monotonic()
            while self.process.exitcode is None:
                self.process.join(0.05)
                now = self._ctrl(CONSUMED)
                if now != progress:
                    progress, since = now, time.monotonic()
                elif time.monotonic() - since > STALL_S:
                    self.process.kill()
                    self.process.join()
                    self._fail(f"the CAN log writer made no progress for {STALL_S:g} s")
            if self._ctrl(STATUS) == WRITE_FAILED:  # the cause, before what came of it
                self.failure = f"cannot write {self.path} ({os.strerror(self._ctrl(ERRNO))})"
            elif self.process.exitcode:
                self._fail(f"the CAN log writer ended with code {self.process.exitcode}")
            self.frames_written = self._ctrl(CONSUMED)
            self.buf = None  # type: ignore[assignment]  # released with the mapping: unused after
            self.shm.close()
            self.shm.unlink()
        return self.status()

    def _fail(self, why: str) -> None:
        self.failure = self.failure or why

    def status(self) -> dict:
        return {
            "path": str(self.path),
            "frames": self.published,
            "dropped_frames": self.dropped,
            "complete": self.failure is None and self.dropped == 0,
            "failure": self.failure,
        }


class TappedBus(can.BusABC):
    """A bus that hands every frame it sends or receives to ``tap``; everything else is the
    wrapped bus's."""

    def __init__(self, inner: can.BusABC, tap) -> None:
        self._inner = inner
        self._tap = tap
        # python-can keeps the channel as given; an inner bus without one has None
        super().__init__(channel=getattr(inner, "channel_id", None))  # type: ignore[arg-type]
        self.channel_info = inner.channel_info

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        # logged first, so that the file stays in time order (an in-process emulator answers
        # inside the send); a send that fails stops the session, its frame logged all the same
        self._tap(msg, False, time.time())
        self._inner.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self._inner.recv(timeout)
        if msg is not None:
            self._tap(msg, True, msg.timestamp or time.time())  # the interface's own time
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), True

    @property
    def state(self) -> can.BusState:
        return self._inner.state

    @state.setter
    def state(self, value: can.BusState) -> None:
        self._inner.state = value

    def shutdown(self) -> None:
        super().shutdown()
        self._inner.shutdown()

    def __getattr__(self, name: str) -> Any:  # the emulator, interface specifics
        return getattr(self._inner, name)


def _writer_main(shm_name: str, capacity: int, path: str) -> None:
    """The writer process: records to ``can.Message`` to python-can's writer for the file."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    set_process_name(PROCESS_NAME)
    shm = SharedMemory(name=shm_name)
    buf = shm.buf
    assert buf is not None  # (None only once the mapping is closed)
    word = struct.Struct("@q")
    parent = multiprocessing.parent_process()
    try:
        writer = can.Logger(path)
    except OSError as err:
        word.pack_into(buf, ERRNO * 8, err.errno or 0)
        word.pack_into(buf, STATUS * 8, WRITE_FAILED)
        shm.close()
        return
    consumed = 0
    try:
        while True:
            word.pack_into(buf, HEARTBEAT * 8, consumed)
            published = word.unpack_from(buf, PUBLISHED * 8)[0]
            closed = word.unpack_from(buf, CLOSED * 8)[0]
            if published > consumed:
                end = min(published, consumed + BATCH)
                for i in range(consumed, end):
                    writer.on_message_received(_message(buf, i % capacity))
                consumed = end
                word.pack_into(buf, CONSUMED * 8, consumed)  # its slots may be reused now
                continue
            if closed or (parent is not None and not parent.is_alive()):
                break
            time.sleep(POLL_S)
    except OSError as err:
        word.pack_into(buf, ERRNO * 8, err.errno or 0)
        word.pack_into(buf, STATUS * 8, WRITE_FAILED)
    finally:
        try:
            writer.stop()
        except OSError as err:
            word.pack_into(buf, ERRNO * 8, err.errno or 0)
            word.pack_into(buf, STATUS * 8, WRITE_FAILED)
        del buf
        shm.close()


def _message(buf, slot: int) -> can.Message:
    stamp, can_id, length, flags, channel, data = RECORD.unpack_from(
        buf, CONTROL.size + slot * RECORD.size
    )
    return can.Message(
        timestamp=stamp,
        arbitration_id=can_id,
        is_extended_id=bool(flags & EXTENDED),
        is_rx=bool(flags & RX),
        is_error_frame=bool(flags & ERROR),
        is_remote_frame=bool(flags & REMOTE),
        is_fd=bool(flags & FD),
        bitrate_switch=bool(flags & BRS),
        error_state_indicator=bool(flags & ESI),
        dlc=length,
        data=data[:length],
        channel=channel,
        check=False,
    )


def status_line(status: dict) -> str | None:
    """One line for stderr when the CAN log is incomplete (None when it is whole)."""
    if status["complete"]:
        return None
    why = status["failure"] or "the writer fell behind"
    return (
        f"teleop-rt: CAN log {status['path']} is incomplete: {why} "
        f"(frames dropped: {status['dropped_frames']})"
    )


def open_can_log(session, path: Path, wait_for_room: bool) -> CanLog:
    """A CAN log for every CAN backend of the session (their buses are tapped when opened)."""
    # a CAN backend is one with a bus to tap (CanBackend.can_tap): found by that attribute,
    # so that the log does not import the backend, which imports the log's TappedBus
    backends = [s.backend for s in session.sites if hasattr(s.backend, "can_tap")]
    if not backends:
        raise ConfigError(
            "--can-log records CAN frames: no robot runs on the can backend "
            "(--backend can, or hsi:can / to:can)"
        )
    log = CanLog(path, wait_for_room=wait_for_room)
    for backend in backends:
        backend.can_tap = log.tap(backend.side)
    return log
