"""The MCAP writer process: turns rows from the shared-memory ring into messages on disk.

The file has one owner, ``McapFile`` (``teleop_rt.recording.mcap_file``: header, schemas and
channels, metadata, attachments, chunks, summary, footer, serialised by the ``mcap`` package's
record classes). The four per-tick topics' message records are built with numpy a batch at a
time and cut into LZ4 chunks with their message indexes (``teleop_rt.recording.chunks``):
no Python call per message. The Foxglove SDK's per-message ``BaseChannel.log`` that wrote
them before cost about 0.5 us a message, most of the writer's CPU (docs/benchmarks.md). The
3D scene's messages (50 Hz) are encoded by the SDK's message classes (``encode``) and go in
chunks of their own. (``mcap``, ``teleop_rt.recording.reader``, reads the logs back.)

It runs in its own process (the other core), so the control loop pays only for packing one
row. It ignores SIGINT/SIGTERM (the control process handles them and closes the log), and
finishes the file by itself when the control process dies, so a killed session still leaves
a valid MCAP holding every row that reached the ring.

A write error (a full disk, a file size limit) is caught once in ``McapFile``: it is reported
in the control block and nothing more is written, and the process ends; the file keeps every
chunk written before the error (a chunk and its message indexes are one write).

Shared memory: ``CONTROL_BYTES`` of int64 control words, then ``capacity`` rows of float64:
  ctrl[0] rows published by the control process (written after the row itself)
  ctrl[1] 1 once the control process has published its last row
  ctrl[2] rows consumed by this writer (the producer reuses slots below it)
  ctrl[3] heartbeat: + 1 per pass of the writer's loop (shows a live writer that has no work)
  ctrl[4] status: 0 writing, WRITE_FAILED after a write error, whose errno is ctrl[5]
    ctrl[6] UTC of the session start, ns since the epoch (the recorder's creation until its
          first row, then the time tick 0 ran)

Beside the four topics of the schema it writes the 3D scene (``teleop_rt.recording.scene``:
robots, transforms, environment, hand target) from the same rows, and with ``--live`` serves
everything it writes over Foxglove's WebSocket protocol from a foxglove context that has the
server and no file sink (``teleop_rt.recording.live``): only then are the four topics logged
message by message, through the SDK, to the server; the ring's rows carry the scene's few
extra columns (``LogLayout.ring_width``).

Log times are wall-clock: the start time plus the tick's time (``start_time_ns + k *
period_ns``), so a log lines up with the world in Foxglove and beside other recordings. The
``teleop_rt`` metadata and the attachments are written once the first row (or the end) has
come, when the start time is known; the header's profile is ``ros2`` (ros2msg schemas, CDR).
"""

from __future__ import annotations

import datetime as _dt
import json
import multiprocessing
import os
import signal
import time
from multiprocessing.shared_memory import SharedMemory
from typing import TYPE_CHECKING, Any

import foxglove
import numpy as np
from foxglove.mcap import MCAPCompression, MCAPWriteOptions

from teleop_rt import __version__
from teleop_rt.declarations import (
    CLOSED,
    CONSUMED,
    CONTROL_WORDS,
    ERRNO,
    HEARTBEAT,
    PUBLISHED,
    START_NS,
    STATUS,
    WRITE_FAILED,
)
from teleop_rt.process_name import set_process_name
from teleop_rt.recording.chunks import MessageRecords, TickRecords
from teleop_rt.recording.mcap_file import McapFile
from teleop_rt.recording.schema import CDR_HEADER, LogLayout

if TYPE_CHECKING:
    from teleop_rt.recording.live import LiveAddress, LiveServer
    from teleop_rt.recording.scene import SceneSpec

CONTROL_BYTES = 8 * CONTROL_WORDS
PROCESS_NAME = "teleop-rt-log"  # the writer's name in ps / top / /proc/PID/comm
PROFILE = "ros2"
LIBRARY = f"teleop_rt/{__version__}"  # the Header's library (with mcap's own)
BATCH_ROWS = 4096
# wait for this many rows before encoding: the numpy work of a batch (about 0.3 ms) is paid
# rarely; at 1 kHz this is a second, about what a 256 kB chunk holds (900 ticks of the paper
# experiment), which reaches the disk only when full anyway
MIN_BATCH_ROWS = 1024
# between looks at the ring the writer sleeps until the rows it waits for are due (at the
# session's rate; fast mode fills it sooner), within these bounds: a look costs CPU, and the
# longest sleep is how late the writer notices the end or its parent's death
POLL_S, MAX_SLEEP_S = 0.005, 0.1
LIVE_BATCH_S = 0.02  # a live view without a scene is sent this often


def writer_main(
    shm_name: str,
    capacity: int,
    layout: tuple[int, int, str],
    path: str,
    period_ns: int,
    metadata: dict[str, str],
    attachments: dict[str, bytes],
    summary_conn: Any,
    scene: SceneSpec | None = None,
    live: LiveAddress | None = None,
    live_conn: Any = None,
) -> None:
    """Process entry point (must stay importable and picklable for 'spawn'). ``scene``: the 3D
    topics (``teleop_rt.recording.scene``); ``live``: serve the session there too, saying on
    ``live_conn`` ("listening", address) or ("failed", why) before the first row.
    ``summary_conn`` carries ("metadata", dict) before the first row (what the control process
    learns after starting the writer: a site's session id, from its handshake) and
    ("summary", dict) at the end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    set_process_name(PROCESS_NAME)
    log_layout = LogLayout(*layout)
    shm = SharedMemory(name=shm_name)
    try:
        ctrl = np.ndarray((CONTROL_BYTES // 8,), dtype=np.int64, buffer=shm.buf)
        ring = np.ndarray(
            (capacity, log_layout.ring_width), np.float64, buffer=shm.buf, offset=CONTROL_BYTES
        )
        context = foxglove.Context()  # private: no other channel of this process is logged
        server = _serve(live, context, live_conn) if live is not None else None
        if live is not None and server is None:
            return  # the recorder reports why and removes the (empty) file
        try:
            _write(
                path, ctrl, ring, log_layout, period_ns, metadata, attachments, summary_conn,
                context, scene, server,
            )  # fmt: skip
        finally:
            if server is not None:
                server.stop()
    finally:
        shm.close()


def _serve(live: LiveAddress, context, conn) -> LiveServer | None:
    from teleop_rt.recording.live import LiveServer
    from teleop_rt.recording.scene import ENVIRONMENT, ROBOT_DESCRIPTION, TF

    try:  # a client that subscribes to these is sent what they carry only now and then
        server = LiveServer(live, context, {ROBOT_DESCRIPTION, TF, ENVIRONMENT})
    except Exception as err:  # the SDK's error for an address that cannot be bound
        conn.send(("failed", str(err) or type(err).__name__))
        return None
    conn.send(("listening", server.address))
    return server


def _write(
    path, ctrl, ring, layout, period_ns, metadata, attachments, summary_conn, context,
    scene_spec, server,
) -> None:  # fmt: skip
    fd = os.open(path, os.O_WRONLY | os.O_TRUNC)  # created by the control process
    try:
        out = _Output(fd, ctrl, layout, scene_spec, context if server is not None else None)
        _loop(out, ctrl, ring, layout, period_ns, metadata, attachments, summary_conn,
              scene_spec, server)  # fmt: skip
    finally:
        os.close(fd)


def _loop(
    out, ctrl, ring, layout, period_ns, metadata, attachments, summary_conn, scene_spec, server
) -> None:  # fmt: skip
    inbox = _Inbox(summary_conn, metadata)
    scene = None
    if scene_spec is not None:
        from teleop_rt.recording.scene import SceneChannels

        scene = SceneChannels(scene_spec, layout, out.scene)
    parent = multiprocessing.parent_process()
    capacity = len(ring)
    # a small ring (tests, ring_s) is emptied before it fills; a live view is sent at the
    # scene's rate (or LIVE_BATCH_S without a scene), not in seconds
    wanted = MIN_BATCH_ROWS
    if server is not None:
        live_rows = max(1, round(LIVE_BATCH_S * 1e9 / period_ns))
        wanted = scene_spec.every if scene_spec is not None else live_rows
    min_batch = min(wanted, MIN_BATCH_ROWS, max(1, capacity // 4))
    max_batch = min(BATCH_ROWS, capacity)
    consumed = 0
    start_ns: int | None = None  # known once the first row (or the end) has come
    while not out.file.failed:
        ctrl[HEARTBEAT] += 1
        published = int(ctrl[PUBLISHED])
        closed = bool(ctrl[CLOSED])
        if published - consumed >= min_batch or (published > consumed and closed):
            end = min(published, consumed + max_batch)
            start_slot, end_slot = consumed % capacity, (end - 1) % capacity + 1
            if end_slot > start_slot:
                rows = ring[start_slot:end_slot].copy()
            else:  # the batch wraps around the ring's end
                rows = np.concatenate([ring[start_slot:], ring[:end_slot]])
            ctrl[CONSUMED] = end  # the slots are copied: the producer may reuse them
            if start_ns is None:
                start_ns = _describe(out.file, int(ctrl[START_NS]), inbox.metadata(), attachments)
                if scene is not None:
                    scene.describe(start_ns)
            chunked = out.ticks(rows, period_ns, start_ns)
            if scene is not None:
                scene.emit(rows, start_ns, period_ns)
                if server is not None and server.resend.is_set():  # a client subscribed
                    server.resend.clear()
                    scene.describe(start_ns + int(rows[-1, 0]) * period_ns)
            if chunked:  # the scene's chunk follows the ticks' (about as many seconds)
                out.scene_records.flush()
            consumed = end
            continue
        if closed or (parent is not None and not parent.is_alive()):
            if int(ctrl[PUBLISHED]) > consumed:  # rows published just before closing
                ctrl[CLOSED] = 1  # drain whatever is left, however little
                continue
            break
        due = (min_batch - (published - consumed)) * period_ns / 1e9
        time.sleep(min(max(due, POLL_S), MAX_SLEEP_S))
    if start_ns is None:  # no tick ran
        _describe(out.file, int(ctrl[START_NS]), inbox.metadata(), attachments)
    out.tick_records.flush()
    out.scene_records.flush()
    summary = None if out.file.failed else inbox.summary()
    if summary is not None:
        out.file.metadata("teleop_rt.summary", {"json": json.dumps(summary)})
    out.file.close()  # after a write error the file drops this too


class _Output:
    """Where the writer's messages go: the MCAP file (its one owner, ``McapFile``), the ticks'
    records built per batch (``TickRecords``), the scene's (``MessageRecords``), and with a
    live view the SDK's channels on the server's context (``live``: no file sink on it)."""

    def __init__(self, fd: int, ctrl: np.ndarray, layout: LogLayout, scene_spec, live) -> None:
        def failed(errno: int) -> None:  # once: the file writes nothing after it
            ctrl[ERRNO] = errno
            ctrl[STATUS] = WRITE_FAILED

        self.file = McapFile(fd, PROFILE, LIBRARY, failed)
        self.layout, self.columns = layout, layout.columns()
        ids = [
            self.file.channel(t.name, "cdr", (t.type_name, "ros2msg", t.definition))
            for t in layout.topics
        ]
        sizes = [t.dtype.itemsize for t in layout.topics]
        self.tick_records = TickRecords(self.file, ids, sizes, prefix=CDR_HEADER)
        self.scene_records = MessageRecords(self.file)
        self.scene_ids: dict[str, int] = {}
        self.live_scene: dict[str, Any] = {}
        self.live_ticks: list[Any] = []
        scene_channels = []
        if scene_spec is not None:
            from teleop_rt.recording.scene import scene_topics

            scene_channels = scene_topics(scene_spec)
        for topic, encoding, schema in scene_channels:
            self.scene_ids[topic] = self.file.channel(topic, encoding, schema)
        if live is not None:
            self.live_ticks = [
                _live_channel(live, t.name, "cdr", (t.type_name, "ros2msg", t.definition)).base.log
                for t in layout.topics
            ]
            self.live_scene = {
                topic: _live_channel(live, topic, encoding, schema).log
                for topic, encoding, schema in scene_channels
            }

    def ticks(self, rows: np.ndarray, period_ns: int, start_ns: int) -> bool:
        """A batch of rows as the four topics' records (True if a chunk was written), and on
        the live view message by message."""
        stamps = start_ns + rows[:, 0].astype(np.int64) * period_ns
        payloads = [
            self.layout.encode(rows, t, self.columns[t.name]).view(np.uint8).reshape(len(rows), -1)
            for t in self.layout.topics
        ]
        chunked = self.tick_records.add(payloads, stamps)
        if self.live_ticks:
            _live_emit(payloads, self.live_ticks, stamps)
        return chunked

    def scene(self, topic: str, data: bytes, stamp: int) -> None:
        self.scene_records.add(self.scene_ids[topic], data, stamp)
        live = self.live_scene.get(topic)
        if live is not None:
            live(data, log_time=stamp)


def _live_channel(context, topic: str, encoding: str, schema: tuple[str, str, bytes]):
    name, schema_encoding, data = schema
    return foxglove.Channel(
        topic, message_encoding=encoding, context=context,
        schema=foxglove.Schema(name=name, encoding=schema_encoding, data=data),
    )  # fmt: skip


def write_options() -> MCAPWriteOptions:
    """The SDK's MCAP options of a log before this writer built its own chunks (LZ4, 256 kB
    chunks): tools/bench.py's floor of the SDK's per-message log call."""
    return MCAPWriteOptions(compression=MCAPCompression.Lz4, chunk_size=256 * 1024, profile=PROFILE)


def _describe(file: McapFile, start_ns: int, metadata: dict[str, str], attachments) -> int:
    """The ``teleop_rt`` metadata with the start time, and the attachments; return start_ns."""
    seconds, ns = divmod(start_ns, 1_000_000_000)
    utc = _dt.datetime.fromtimestamp(seconds, _dt.timezone.utc)
    utc += _dt.timedelta(microseconds=ns // 1000)
    start = {
        "start_time_ns": str(start_ns),
        "start_time_utc": utc.isoformat(timespec="microseconds").replace("+00:00", "Z"),
    }
    file.metadata("teleop_rt", {**metadata, **start})
    for name, data in attachments.items():
        media = "application/yaml" if name.endswith(".yaml") else "application/xml"
        file.attach(name, media, data, start_ns)
    return start_ns


def _live_emit(payloads: list[np.ndarray], logs: list, stamps: np.ndarray) -> None:
    """The live view's four topics, tick by tick through the SDK's ``BaseChannel.log`` (the
    server sends a message per tick; only with --live)."""
    prefix = np.frombuffer(CDR_HEADER, np.uint8)
    blocks = []
    for log, payload in zip(logs, payloads, strict=True):
        block = np.empty((len(payload), len(prefix) + payload.shape[1]), np.uint8)
        block[:, : len(prefix)] = prefix
        block[:, len(prefix) :] = payload
        blocks.append((log, block.tobytes(), block.shape[1]))
    for i, stamp in enumerate(stamps.tolist()):
        for log, data, size in blocks:
            log(data[i * size : (i + 1) * size], stamp, None)


class _Inbox:
    """What the control process sends on the pipe: metadata it learnt after starting the
    writer (taken when the first row comes), and the summary at the end."""

    def __init__(self, conn: Any, metadata: dict[str, str]) -> None:
        self.conn, self.meta = conn, dict(metadata)
        self.last: dict | None = None

    def _take(self, timeout: float) -> bool:
        """One message, if one comes within ``timeout``; False if none (or the pipe closed)."""
        try:
            if not self.conn.poll(timeout):
                return False
            kind, body = self.conn.recv()
        except (EOFError, OSError, ValueError, TypeError):
            return False
        if kind == "metadata":
            self.meta.update(body)
        else:
            self.last = body
        return True

    def metadata(self) -> dict[str, str]:
        while self._take(0.0):
            pass
        return self.meta

    def summary(self) -> dict | None:
        while self.last is None and self._take(0.5):
            pass
        return self.last
