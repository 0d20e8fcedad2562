"""The writer's own MCAP chunks (teleop_rt.recording.chunks, mcap_file): the same messages as
the Foxglove SDK wrote for the same rows, a file whose summary, indexes and CRCs agree with
its records (MCAP specification), and a cut file that reads to its last complete chunk."""

from __future__ import annotations

import errno
import os
import struct
import zlib
from pathlib import Path

import foxglove
import lz4.frame
import numpy as np
from foxglove.channels import FrameTransformsChannel
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Chunk, MessageIndex
from mcap.stream_reader import StreamReader

from teleop_rt import config
from teleop_rt.recording.chunks import TickRecords
from teleop_rt.recording.mcap_file import McapFile
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.scene import SceneChannels, scene_spec
from teleop_rt.recording.schema import CDR_HEADER, SCHEMA_VERSION, LogLayout
from teleop_rt.recording.writer import _describe, _Output, write_options
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PERIOD_NS = 1_000_000
START_NS = 1_767_225_600_123_456_789
BATCHES = (1000, 37, 1, 2500, 700)  # uneven, so chunks are cut inside batches


def ring_rows(layout: LogLayout, ticks: int, seed: int = 1) -> np.ndarray:
    """Random ring rows (so a column mix-up shows); ticks and times in order, one gap."""
    rng = np.random.default_rng(seed)
    rows = rng.standard_normal((ticks, layout.ring_width))
    k = np.arange(ticks)
    k[ticks // 2 :] += 5  # five ticks lost (a stalled writer's gap): log times skip them
    rows[:, 0], rows[:, 1] = k, k * 1e-3
    return rows


def new_file(path: Path, layout: LogLayout, rows: np.ndarray, spec=None) -> None:
    """What the writer process writes for ``rows`` (its _Output, batch by batch)."""
    ctrl = np.zeros(8, np.int64)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        out = _Output(fd, ctrl, layout, spec, None)
        meta = {"schema_version": str(SCHEMA_VERSION), "joints": str(layout.n),
                "env_elements": str(layout.n_env), "rate_hz": "1000.0",
                "period_ns": str(PERIOD_NS), "name": "chunks", "backend": "sim"}  # fmt: skip
        _describe(out.file, START_NS, meta, {"config.yaml": b"a: 1\n"})
        scene = SceneChannels(spec, layout, out.scene) if spec is not None else None
        if scene is not None:
            scene.describe(START_NS)
        at = 0
        for n in BATCHES:
            batch = rows[at : at + n]
            at += n
            chunked = out.ticks(batch, PERIOD_NS, START_NS)
            if scene is not None:
                scene.emit(batch, START_NS, PERIOD_NS)
            if chunked:
                out.scene_records.flush()
        out.tick_records.flush()
        out.scene_records.flush()
        out.file.metadata("teleop_rt.summary", {"json": "{}"})
        out.file.close()
    finally:
        os.close(fd)
    assert ctrl[4] == 0  # no write error


def sdk_file(path: Path, layout: LogLayout, rows: np.ndarray) -> None:
    """The four topics as the writer logged them before: the SDK's BaseChannel.log, a message
    per topic and tick, with the same MCAP options."""
    context = foxglove.Context()
    writer = foxglove.open_mcap(str(path), context=context, writer_options=write_options())
    columns = layout.columns()
    for topic in layout.topics:
        channel = foxglove.Channel(
            topic.name, message_encoding="cdr", context=context,
            schema=foxglove.Schema(name=topic.type_name, encoding="ros2msg",
                                   data=topic.definition),
        )  # fmt: skip
        payload = layout.encode(rows, topic, columns[topic.name]).view(np.uint8)
        blocks = payload.reshape(len(rows), -1)
        for k, stamp in enumerate((START_NS + rows[:, 0].astype(np.int64) * PERIOD_NS).tolist()):
            channel.base.log(CDR_HEADER + blocks[k].tobytes(), stamp, None)
    writer.close()


def messages(path: Path, seeking: bool = True) -> dict[str, list[tuple]]:
    out: dict[str, list[tuple]] = {}
    with open(path, "rb") as f:
        reader = SeekingReader(f, validate_crcs=True) if seeking else NonSeekingReader(
            f, validate_crcs=True
        )  # fmt: skip
        for schema, channel, m in reader.iter_messages(log_time_order=False):
            key = (channel.topic, channel.message_encoding, schema.name, schema.encoding,
                   schema.data)  # fmt: skip
            out.setdefault(key, []).append((m.sequence, m.log_time, m.publish_time, m.data))
    return {k: sorted(v, key=lambda x: x[0]) for k, v in out.items()}


def test_the_ticks_messages_are_the_sdks_for_the_same_rows(tmp_path: Path) -> None:
    layout = LogLayout(2, 1)
    rows = ring_rows(layout, sum(BATCHES))
    new_file(tmp_path / "new.mcap", layout, rows)
    sdk_file(tmp_path / "sdk.mcap", layout, rows)
    new, sdk = messages(tmp_path / "new.mcap"), messages(tmp_path / "sdk.mcap")
    assert list(new) == list(sdk)  # topics, encodings, schemas, in the same order
    for key in sdk:  # bytes, sequence numbers, log and publish times, message by message
        assert new[key] == sdk[key], key[0]
    assert len(new[next(iter(new))]) == sum(BATCHES)
    data = read_log(tmp_path / "new.mcap")  # the project's reader: every tick, not cut
    assert data.ticks == sum(BATCHES) and not data.truncated
    np.testing.assert_array_equal(data.topics["/hsi"]["tick"], rows[:, 0].astype(np.uint64))


def test_the_scene_is_encoded_as_the_sdks_typed_channels_log_it(tmp_path: Path) -> None:
    from teleop_rt.recording.scene import Scene

    spec = scene_spec(Session(config.load(CONFIGS / "paper_experiment.yaml")))
    message = Scene(spec).static_transforms(START_NS)
    context = foxglove.Context()
    writer = foxglove.open_mcap(str(tmp_path / "sdk.mcap"), context=context)
    FrameTransformsChannel("/tf", context=context).log(message, log_time=START_NS)
    writer.close()
    with open(tmp_path / "sdk.mcap", "rb") as f:
        [(schema, _, logged)] = list(SeekingReader(f).iter_messages())
    assert logged.data == message.encode()
    assert schema.data == bytes(type(message).get_schema().data)


def test_seeking_and_streaming_readers_agree_and_the_summary_counts_the_records(
    tmp_path: Path,
) -> None:
    session = Session(config.load(CONFIGS / "paper_experiment.yaml"))
    spec = scene_spec(session)
    layout = LogLayout(session.hsi.n, len(session.cfg.environment))
    rows = ring_rows(layout, sum(BATCHES))
    path = tmp_path / "new.mcap"
    new_file(path, layout, rows, spec)
    seek, stream = messages(path), messages(path, seeking=False)
    assert seek == stream
    topics = {key[0]: len(v) for key, v in seek.items()}
    assert topics["/hsi"] == topics["/timing"] == sum(BATCHES)
    assert topics["/tf"] == 1 + sum(1 for k in rows[:, 0] if k % spec.every == 0)
    blob = path.read_bytes()
    with open(path, "rb") as f:
        summary = SeekingReader(f).get_summary()
    stats = summary.statistics
    assert stats.message_count == sum(topics.values())
    assert {summary.channels[c].topic: n for c, n in stats.channel_message_counts.items()} == topics
    assert stats.chunk_count == len(summary.chunk_indexes) > len(BATCHES)
    assert stats.metadata_count == 2 and stats.attachment_count == 1
    for index in summary.chunk_indexes:  # each points at its chunk and its message indexes
        records, seen = _records(blob, index), 0
        for cid, at in index.message_index_offsets.items():
            mi = MessageIndex.read(_stream(blob[at + 9 : at + 9 + _length(blob, at)]))
            assert mi.channel_id == cid and mi.records
            for stamp, offset in mi.records:
                assert records[offset] == 0x05  # a message record, its channel and log time
                assert struct.unpack_from("<HIQ", records, offset + 9)[0] == cid
                assert struct.unpack_from("<Q", records, offset + 15)[0] == stamp
                assert index.message_start_time <= stamp <= index.message_end_time
            seen += len(mi.records)
        assert seen == _count_messages(records)  # the indexes list every message of the chunk
    # the CRCs of the data section (Data End) and of the summary (Footer)
    footer_at = len(blob) - 8 - 29
    summary_start, offsets_start, summary_crc = struct.unpack_from("<QQI", blob, footer_at + 9)
    assert zlib.crc32(blob[summary_start : footer_at + 9 + 16]) == summary_crc
    data_end = summary_start - 13
    assert blob[data_end] == 0x0F
    assert struct.unpack_from("<I", blob, data_end + 9)[0] == zlib.crc32(blob[:data_end])
    records = [type(r).__name__ for r in StreamReader(str(path)).records]
    assert records[:2] == ["Header", "Schema"] and records[-1] == "Footer"


def _stream(body: bytes):
    import io

    from mcap.data_stream import ReadDataStream

    return ReadDataStream(io.BytesIO(body))


def _length(blob: bytes, at: int) -> int:
    return struct.unpack_from("<Q", blob, at + 1)[0]


def _count_messages(records: bytes) -> int:
    at = n = 0
    while at < len(records):
        n += records[at] == 0x05
        at += 9 + struct.unpack_from("<Q", records, at + 1)[0]
    assert at == len(records)
    return n


def test_a_cut_file_reads_to_its_last_complete_chunk(tmp_path: Path) -> None:
    layout = LogLayout(2, 1)
    rows = ring_rows(layout, sum(BATCHES))
    path = tmp_path / "new.mcap"
    new_file(path, layout, rows)
    blob = path.read_bytes()
    with open(path, "rb") as f:
        chunks = SeekingReader(f).get_summary().chunk_indexes
    per_chunk = [_count_messages(_records(blob, c)) // 4 for c in chunks]  # ticks per chunk
    assert len(chunks) > 3 and sum(per_chunk) == sum(BATCHES)
    for i in (0, 2, len(chunks) - 1):  # cut inside chunk i: the chunks before it are read
        cut = tmp_path / f"cut-{i}.mcap"
        cut.write_bytes(blob[: chunks[i].chunk_start_offset + chunks[i].chunk_length // 2])
        data = read_log(cut)
        assert data.truncated and data.ticks == sum(per_chunk[:i])
        np.testing.assert_array_equal(
            data.topics["/channel"]["tick"], rows[: data.ticks, 0].astype(np.uint64)
        )


def _records(blob: bytes, index) -> bytes:
    """The uncompressed records of the chunk at ``index``, its CRC checked."""
    head = blob[index.chunk_start_offset : index.chunk_start_offset + index.chunk_length]
    chunk = Chunk.read(_stream(head[9:]))
    records = lz4.frame.decompress(chunk.data)
    assert chunk.uncompressed_crc == zlib.crc32(records)
    assert len(records) == chunk.uncompressed_size == index.uncompressed_size
    return records


def test_a_write_error_is_reported_once_and_ends_writing() -> None:
    reported: list[int] = []
    fd = os.open("/dev/full", os.O_WRONLY)  # every write fails: ENOSPC
    try:
        file = McapFile(fd, "ros2", "test", reported.append)
        ticks = TickRecords(file, [file.channel("/a", "cdr", ("A", "ros2msg", b"uint64 x\n"))],
                            [8], chunk_bytes=64)  # fmt: skip
        ticks.add([np.zeros((100, 8), np.uint8)], np.arange(100, dtype=np.int64))
        ticks.flush()
        file.metadata("m", {"a": "b"})
        file.close()
    finally:
        os.close(fd)
    assert reported == [errno.ENOSPC] and file.failed
