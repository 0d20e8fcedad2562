"""MCAP message records built a batch at a time, and cut into chunks for ``McapFile``.

``TickRecords``: the per-tick topics (one message per topic and tick, each of one fixed size,
``teleop_rt.recording.schema``). A tick's records (its topics in order) are one numpy record
of a packed structured dtype: opcode, length, channel id, sequence, log time, publish time,
CDR payload, per topic (MCAP specification, Message record). A batch of ticks is one array
filled by a few column assignments, its bytes are the chunk's records, and its Message Index
entries are arithmetic (record k of a topic sits at ``k * tick_bytes + its offset``): no
Python call per message. This replaced the Foxglove SDK's per-message ``BaseChannel.log``
(about 0.5 us a message, four a tick: most of the writer's CPU; docs/benchmarks.md).

``MessageRecords``: the few variable-size messages (the 3D scene, 50 Hz), one ``struct``
pack each, kept in their own chunks beside the ticks' (so a chunk of ticks holds records of
four fixed sizes only, which the reader gathers with one strided view per topic).

Sequence numbers count a channel's messages from 1, and publish time is the log time: what
the SDK wrote."""

from __future__ import annotations

import struct

import numpy as np
from mcap.opcode import Opcode

from teleop_rt.recording.mcap_file import ChunkIndexes, McapFile

CHUNK_BYTES = 256 * 1024  # uncompressed records per chunk (the SDK's chunk size before)
_MESSAGE_HEAD = 31  # opcode 1, length 8, channel 2, sequence 4, log and publish time 16
_HEAD = struct.Struct("<BQHIQQ")


def tick_dtype(sizes: list[int]) -> tuple[np.dtype, list[int]]:
    """The packed dtype of one tick's message records (their data of ``sizes`` bytes) and each
    record's offset in it."""
    names, formats, offsets, at, starts = [], [], [], 0, []
    for i, size in enumerate(sizes):
        starts.append(at)
        for name, fmt, width in (("op", "u1", 1), ("len", "<u8", 8), ("ch", "<u2", 2),
                                 ("seq", "<u4", 4), ("log", "<u8", 8), ("pub", "<u8", 8),
                                 ("data", ("u1", (size,)), size)):  # fmt: skip
            names.append(f"{name}{i}")
            formats.append(fmt)
            offsets.append(at)
            at += width
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": at})
    return dtype, starts


class TickRecords:
    """The per-tick topics' message records, written as chunks of about ``chunk_bytes``.
    ``sizes``: each topic's payload bytes after ``prefix`` (the CDR header, the same in every
    message: written once, in the template of the records)."""

    def __init__(
        self, file: McapFile, channel_ids: list[int], sizes: list[int], prefix: bytes = b"",
        chunk_bytes: int = CHUNK_BYTES,
    ) -> None:  # fmt: skip
        self.file, self.ids, self.prefix = file, list(channel_ids), prefix
        self.sizes = [len(prefix) + size for size in sizes]
        self.dtype, self.starts = tick_dtype(self.sizes)
        self.per_chunk = max(1, chunk_bytes // self.dtype.itemsize)
        self.sequence = 0  # messages per channel so far (every channel has one a tick)
        # the pending ticks' records, in place: the constant fields (opcode, length, channel,
        # CDR header) are written once when the buffer is made, a batch fills the rest, and a
        # chunk's records are compressed from the buffer itself (no copy per batch)
        self.buf = self._blank(self.per_chunk + 1024)
        self.pending = 0

    def _blank(self, n: int) -> np.ndarray:
        """Records of n ticks with the constant fields filled."""
        t = np.zeros(n, self.dtype)
        prefix = np.frombuffer(self.prefix, np.uint8)
        for i, (cid, size) in enumerate(zip(self.ids, self.sizes, strict=True)):
            t[f"op{i}"] = Opcode.MESSAGE
            t[f"len{i}"] = _MESSAGE_HEAD - 9 + size
            t[f"ch{i}"] = cid
            t[f"data{i}"][:, : len(prefix)] = prefix
        return t

    def add(self, payloads: list[np.ndarray], stamps: np.ndarray) -> bool:
        """A batch: per topic an (n, size) uint8 array of payloads (after the prefix), and the
        ticks' log times (int64 ns). Whole chunks are written as soon as they are full: True
        if one was."""
        n = len(stamps)
        if n == 0:
            return False
        if self.pending + n > len(self.buf):  # a larger batch than before: a larger buffer
            bigger = self._blank(self.pending + n + self.per_chunk)
            bigger[: self.pending] = self.buf[: self.pending]
            self.buf = bigger
        recs = self.buf[self.pending : self.pending + n]
        seq = (np.arange(self.sequence + 1, self.sequence + n + 1) & 0xFFFFFFFF).astype("<u4")
        skip = len(self.prefix)
        for i, payload in enumerate(payloads):
            recs[f"seq{i}"] = seq
            recs[f"log{i}"] = stamps
            recs[f"pub{i}"] = stamps
            recs[f"data{i}"][:, skip:] = payload
        self.sequence += n
        self.pending += n
        return self.flush(whole_only=True)

    def flush(self, whole_only: bool = False) -> bool:
        """Write the pending ticks as chunks (``whole_only``: full chunks only, the rest stays
        pending); True if a chunk was written."""
        pending, per = self.pending, self.per_chunk
        if not pending or (whole_only and pending < per):
            return False
        cut = pending - pending % per if whole_only else pending
        for lo in range(0, cut, per):
            self._chunk(self.buf[lo : min(lo + per, cut)])
        if cut < pending:  # the rest to the front (fewer than a chunk's ticks)
            self.buf[: pending - cut] = self.buf[cut:pending].copy()
        self.pending = pending - cut
        return True

    def _chunk(self, recs: np.ndarray) -> None:
        m, step = len(recs), self.dtype.itemsize
        stamps = recs["log0"]
        where = np.arange(m, dtype=np.uint64) * np.uint64(step)
        indexes = ChunkIndexes()
        for i, cid in enumerate(self.ids):
            entries = np.empty((m, 2), "<u8")
            entries[:, 0] = stamps
            entries[:, 1] = where + np.uint64(self.starts[i])
            indexes.by_channel[cid] = entries
        self.file.chunk(recs.view(np.uint8).data, indexes)  # the buffer itself


class MessageRecords:
    """Variable-size messages (one ``struct`` pack each), written as one chunk on ``flush``."""

    def __init__(self, file: McapFile) -> None:
        self.file = file
        self.parts: list[bytes] = []
        self.size = 0
        self.sequence: dict[int, int] = {}
        self.index: dict[int, list[tuple[int, int]]] = {}

    def add(self, channel_id: int, data: bytes, stamp: int) -> None:
        seq = self.sequence.get(channel_id, 0) + 1
        self.sequence[channel_id] = seq
        head = _HEAD.pack(Opcode.MESSAGE, _MESSAGE_HEAD - 9 + len(data), channel_id,
                          seq & 0xFFFFFFFF, stamp, stamp)  # fmt: skip
        self.index.setdefault(channel_id, []).append((stamp, self.size))
        self.parts += [head, data]
        self.size += len(head) + len(data)

    def flush(self) -> None:
        if not self.parts:
            return
        indexes = ChunkIndexes({cid: np.array(e, "<u8").reshape(-1, 2)
                                for cid, e in self.index.items()})  # fmt: skip
        self.file.chunk(b"".join(self.parts), indexes)
        self.parts, self.size, self.index = [], 0, {}
