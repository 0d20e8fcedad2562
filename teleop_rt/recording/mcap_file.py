"""The log's MCAP file, written by one owner: header, schemas and channels, metadata,
attachments, prebuilt chunks, and at the end the summary and footer (MCAP specification,
https://mcap.dev/spec).

Small records are serialised by ``mcap``'s own record classes (``mcap.records``, the same
library that reads the logs back); what is per message is not built here but handed over as a
chunk's uncompressed records with their message indexes (``teleop_rt.recording.chunks``): this
writes the Chunk record (LZ4 frame, ``lz4.frame``, CRC-32 of the uncompressed records), its
Message Index records and keeps its Chunk Index and the Statistics for the summary.

Layout of a file: magic, Header, the Schema and Channel records (top level, before any chunk:
a streaming reader has them before the first message), Metadata and Attachment records, then
Chunk records each followed by its Message Index records; at ``close`` Metadata written late
(the summary), Data End (the data section's CRC), the summary section (schemas, channels,
statistics, chunk, attachment and metadata indexes, summary offsets), Footer and magic.

The first write error (a full disk, a file size limit) is reported once through ``on_error``
(the writer puts its errno in the control block) and ends writing: later records, the summary
included, are dropped, so the file keeps every record written before the error, and a reader
reads it to the last complete chunk. A chunk and its indexes go in one ``os.write``."""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import lz4.frame
import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import LIBRARY_IDENTIFIER

MAGIC = b"\x89MCAP0\r\n"
_INDEX_HEAD = struct.Struct("<BQHI")  # Message Index: opcode, length, channel id, entries' bytes


@dataclass
class ChunkIndexes:
    """What a chunk's records hold, for its Message Index records: per channel id an (m, 2)
    array of uint64 (log time, offset of the record in the uncompressed chunk), in order."""

    by_channel: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def messages(self) -> int:
        return sum(len(x) for x in self.by_channel.values())


class McapFile:
    """An MCAP file written through ``fd`` (opened by the caller). ``library``: the Header's."""

    def __init__(
        self, fd: int, profile: str, library: str, on_error: Callable[[int], None]
    ) -> None:
        self.fd, self.on_error = fd, on_error
        self.failed = False
        self.pos = 0  # bytes handed to the file so far (the offsets of the indexes)
        self._crc = 0  # CRC-32 of the data section so far (Data End)
        self.schemas: dict[tuple[str, str, bytes], Schema] = {}
        self.channels: list[Channel] = []
        self.chunk_indexes: list[ChunkIndex] = []
        self.attachment_indexes: list[AttachmentIndex] = []
        self.metadata_indexes: list[MetadataIndex] = []
        self.stats = Statistics(
            message_count=0, schema_count=0, channel_count=0, attachment_count=0,
            metadata_count=0, chunk_count=0, message_start_time=0, message_end_time=0,
            channel_message_counts={},
        )  # fmt: skip
        builder = RecordBuilder()
        Header(profile=profile, library=f"{library} {LIBRARY_IDENTIFIER}").write(builder)
        self._put(MAGIC + builder.end())

    # -- the data section ------------------------------------------------------------------
    def _put(self, data: bytes | memoryview) -> None:
        """Write all of ``data`` at the end of the file, unless a write has failed."""
        self.pos += len(data)
        if self.failed:
            return
        self._crc = zlib.crc32(data, self._crc)
        view, done = memoryview(data), 0
        try:
            while done < len(view):
                done += os.write(self.fd, view[done:])
        except OSError as err:
            self.failed = True
            self.on_error(err.errno or 0)

    def _record(self, record) -> int:
        """Write one record (an ``mcap.records`` object); return its offset and length."""
        builder = RecordBuilder()
        record.write(builder)
        at = self.pos
        self._put(builder.end())
        return at

    def channel(self, topic: str, encoding: str, schema: tuple[str, str, bytes]) -> int:
        """Register a channel (its schema once per name, encoding and text); return its id."""
        known = self.schemas.get(schema)
        if known is None:
            name, schema_encoding, data = schema
            known = Schema(id=len(self.schemas) + 1, name=name, encoding=schema_encoding,
                           data=data)  # fmt: skip
            self.schemas[schema] = known
            self._record(known)
        channel = Channel(id=len(self.channels) + 1, topic=topic, message_encoding=encoding,
                          schema_id=known.id, metadata={})  # fmt: skip
        self.channels.append(channel)
        self._record(channel)
        self.stats.channel_message_counts[channel.id] = 0
        return channel.id

    def metadata(self, name: str, data: dict[str, str]) -> None:
        at = self._record(Metadata(name=name, metadata=data))
        self.metadata_indexes.append(MetadataIndex(offset=at, length=self.pos - at, name=name))

    def attach(self, name: str, media_type: str, data: bytes, log_time: int) -> None:
        record = Attachment(create_time=log_time, log_time=log_time, name=name,
                            media_type=media_type, data=data)  # fmt: skip
        at = self._record(record)  # (mcap's Attachment writes its CRC)
        self.attachment_indexes.append(AttachmentIndex(
            offset=at, length=self.pos - at, create_time=log_time, log_time=log_time,
            data_size=len(data), name=name, media_type=media_type,
        ))  # fmt: skip

    def chunk(self, records: bytes | memoryview, indexes: ChunkIndexes) -> None:
        """One Chunk of ``records`` (whole message records), LZ4-compressed, then its Message
        Index records, in one write; counted in the Statistics and the Chunk Indexes."""
        if not indexes.messages:
            return
        times = [x[:, 0] for x in indexes.by_channel.values() if len(x)]
        start = min(int(t.min()) for t in times)
        end = max(int(t.max()) for t in times)
        compressed = lz4.frame.compress(records)
        builder = RecordBuilder()
        Chunk(message_start_time=start, message_end_time=end, uncompressed_size=len(records),
              uncompressed_crc=zlib.crc32(records), compression="lz4",
              data=compressed).write(builder)  # fmt: skip
        head = builder.end()
        chunk_at, index_at = self.pos, self.pos + len(head)
        parts, offsets, at = [head], {}, index_at
        for cid, entries in indexes.by_channel.items():
            body = np.ascontiguousarray(entries, dtype="<u8").tobytes()
            parts += [_INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 6 + len(body), cid, len(body)), body]
            offsets[cid] = at
            at += 15 + len(body)
            self.stats.channel_message_counts[cid] += len(entries)
        self._put(b"".join(parts))
        self.chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_at,
            chunk_length=len(head), message_index_offsets=offsets,
            message_index_length=at - index_at, compression="lz4",
            compressed_size=len(compressed), uncompressed_size=len(records),
        ))  # fmt: skip
        stats = self.stats
        if stats.message_count == 0:
            stats.message_start_time, stats.message_end_time = start, end
        stats.message_start_time = min(stats.message_start_time, start)
        stats.message_end_time = max(stats.message_end_time, end)
        stats.message_count += indexes.messages
        stats.chunk_count += 1

    # -- the end -----------------------------------------------------------------------------
    def close(self) -> None:
        """Data End, the summary section, Footer and magic (nothing after a write error);
        the caller closes the descriptor."""
        stats = self.stats
        stats.schema_count, stats.channel_count = len(self.schemas), len(self.channels)
        stats.attachment_count = len(self.attachment_indexes)
        stats.metadata_count = len(self.metadata_indexes)
        self._record(DataEnd(data_section_crc=self._crc))
        start = self.pos
        builder, groups = RecordBuilder(), []
        for opcode, records in (
            (Opcode.SCHEMA, list(self.schemas.values())),
            (Opcode.CHANNEL, self.channels),
            (Opcode.STATISTICS, [stats]),
            (Opcode.CHUNK_INDEX, self.chunk_indexes),
            (Opcode.ATTACHMENT_INDEX, self.attachment_indexes),
            (Opcode.METADATA_INDEX, self.metadata_indexes),
        ):
            if records:
                group_at = builder.count
                for record in records:
                    record.write(builder)
                groups.append(SummaryOffset(group_opcode=opcode, group_start=start + group_at,
                                            group_length=builder.count - group_at))  # fmt: skip
        offsets_at = start + builder.count
        for offset in groups:
            offset.write(builder)
        summary = builder.end()
        # the Footer's CRC covers the summary section and the Footer's fields before it
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, start, offsets_at),
                         zlib.crc32(summary))  # fmt: skip
        footer = RecordBuilder()
        Footer(summary_start=start, summary_offset_start=offsets_at, summary_crc=crc).write(footer)
        self._put(summary + footer.end() + MAGIC)
