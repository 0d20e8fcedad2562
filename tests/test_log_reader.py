"""read_log: round trips, agreement with mcap's own readers, cut-short files, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from log_fixtures import URDF, write_synthetic_log
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer
from mcap_ros2.decoder import DecoderFactory

from teleop_rt.errors import TeleopError
from teleop_rt.recording.reader import LogData, LogError, read_log
from teleop_rt.recording.schema import CDR_HEADER, SCHEMA_VERSION

TOPICS = ("/hsi", "/to", "/channel", "/timing")


def assert_matches_rows(data: LogData, log, ticks: slice = slice(None)) -> None:
    """Every field of every topic read equals the rows written (exactly)."""
    for topic in log.layout.topics:
        if topic.name not in data.topics:
            continue
        arr = data.topics[topic.name]
        assert arr.dtype == topic.dtype
        for f in topic.fields:
            got = arr[f.name].reshape(len(arr), -1).astype(np.float64)
            np.testing.assert_array_equal(got, log.field(topic.name, f.name)[ticks], f.name)


@pytest.mark.parametrize(
    "n, n_env, compression, chunked",
    [
        (2, 1, CompressionType.ZSTD, True),
        (3, 0, CompressionType.LZ4, True),
        (1, 2, CompressionType.NONE, True),
        (2, 1, CompressionType.ZSTD, False),
    ],
)
def test_round_trip_every_field(tmp_path, n, n_env, compression, chunked):
    log = write_synthetic_log(
        tmp_path / "a.mcap", 700, n, n_env, chunk_size=4096, compression=compression,
        chunked=chunked,
    )  # fmt: skip
    data = read_log(log.path)
    assert set(data.topics) == set(TOPICS)
    assert data.ticks == 700
    assert_matches_rows(data, log)
    assert not data.truncated and data.cut_reason is None


def test_metadata_attachments_summary(tmp_path):
    log = write_synthetic_log(tmp_path / "a.mcap", 300)
    data = read_log(log.path)
    assert data.meta == log.meta
    assert data.layout.n == 2 and data.layout.n_env == 1
    assert data.dt == 1e-3 and data.rate_hz == 1000.0
    assert data.config_yaml == log.config_yaml
    assert data.attachments["urdf/hsi.urdf"] == URDF
    assert set(data.attachments) == {"config.yaml", "urdf/hsi.urdf", "urdf/to.urdf"}
    assert data.summary == log.summary
    cfg = data.config()
    assert cfg.name == "synthetic" and cfg.rate_hz == 1000 and cfg.delay_ticks == 3


def test_only_requested_topics_and_window(tmp_path):
    log = write_synthetic_log(tmp_path / "a.mcap", 2000, chunk_size=4096)
    data = read_log(log.path, topics=["/timing"])
    assert list(data.topics) == ["/timing"]
    np.testing.assert_array_equal(data.topics["/timing"]["tick"], np.arange(2000))
    win = read_log(log.path, t_from=0.5, t_to=1.25)
    for arr in win.topics.values():
        np.testing.assert_array_equal(arr["tick"], np.arange(500, 1250))
    assert_matches_rows(win, log, slice(500, 1250))
    assert read_log(log.path, t_from=5.0).ticks == 0
    with pytest.raises(ValueError, match="unknown topic"):
        read_log(log.path, topics=["/nope"])


def test_same_bytes_as_mcap_reader(tmp_path):
    """mcap's own (slow, per-message) reader sees exactly the payloads read_log decodes."""
    log = write_synthetic_log(tmp_path / "a.mcap", 500, chunk_size=2048)
    data = read_log(log.path)
    payloads: dict[str, list[bytes]] = {t: [] for t in TOPICS}
    with open(log.path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            payloads[channel.topic].append(message.data)
    for topic in TOPICS:
        expected = b"".join(p[4:] for p in payloads[topic])
        assert data.topics[topic].tobytes() == expected
        assert all(p[:4] == CDR_HEADER for p in payloads[topic])


def test_independent_ros2_decode(tmp_path):
    """mcap_ros2 decodes a message with the schema stored in the file to the same values."""
    log = write_synthetic_log(tmp_path / "a.mcap", 50, n=3, n_env=2)
    data = read_log(log.path)
    factory = DecoderFactory()
    seen = set()
    with open(log.path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if message.sequence != 17 or channel.topic in seen:
                continue
            seen.add(channel.topic)
            decoded = factory.decoder_for(channel.message_encoding, schema)(message.data)
            row = data.topics[channel.topic][17]
            for name in row.dtype.names:
                value = getattr(decoded, name)
                if isinstance(value, bytes):  # ROS 2 decodes uint8[N] as bytes
                    value = np.frombuffer(value, np.uint8)
                np.testing.assert_array_equal(np.asarray(value), row[name], name)
    assert seen == set(TOPICS)


def complete_chunk_ticks(path: Path, cut: int) -> int:
    """Ticks whose four messages all lie in chunks that end before byte ``cut`` (via mcap)."""
    counts = dict.fromkeys(TOPICS, 0)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topic_of = {cid: c.topic for cid, c in summary.channels.items()}
        for index in summary.chunk_indexes:
            if index.chunk_start_offset + index.chunk_length > cut:
                continue
            f.seek(index.chunk_start_offset + 9)
            for record in breakup_chunk(Chunk.read(ReadDataStream(f))):
                if isinstance(record, Message):
                    counts[topic_of[record.channel_id]] += 1
    return min(counts.values())


def chunk_ends(path: Path) -> list[int]:
    with open(path, "rb") as f:
        indexes = make_reader(f).get_summary().chunk_indexes
    return [i.chunk_start_offset + i.chunk_length for i in indexes]


@pytest.mark.parametrize("fraction", [0.6, 0.99])
def test_cut_file_keeps_complete_chunks(tmp_path, fraction):
    full = write_synthetic_log(tmp_path / "full.mcap", 3000, chunk_size=4096)
    size = full.path.stat().st_size
    cut = int(size * fraction)
    expected = complete_chunk_ticks(full.path, cut)
    log = write_synthetic_log(tmp_path / "cut.mcap", 3000, chunk_size=4096, truncate_bytes=cut)
    data = read_log(log.path)
    assert data.truncated and data.cut_reason
    assert 0 < data.ticks == expected
    assert_matches_rows(data, full, slice(0, expected))
    assert data.meta == full.meta and data.config_yaml == full.config_yaml


@pytest.mark.parametrize("after_chunk", [-100, 0, 20])
def test_cut_around_a_chunk_end(tmp_path, after_chunk):
    """Cut inside a chunk: it is dropped; cut after it but before or inside its message
    index records: it is still read (record by record)."""
    full = write_synthetic_log(tmp_path / "full.mcap", 3000, chunk_size=4096)
    cut = chunk_ends(full.path)[10] + after_chunk
    expected = complete_chunk_ticks(full.path, cut)
    log = write_synthetic_log(tmp_path / "cut.mcap", 3000, chunk_size=4096, truncate_bytes=cut)
    data = read_log(log.path)
    assert data.truncated and data.ticks == expected > 0
    assert_matches_rows(data, full, slice(0, expected))


def test_killed_writer(tmp_path):
    """A process killed mid-session leaves complete chunks, no summary, no footer."""
    log = write_synthetic_log(tmp_path / "k.mcap", 3000, chunk_size=4096, finish=False)
    full = write_synthetic_log(tmp_path / "full.mcap", 3000, chunk_size=4096)
    expected = complete_chunk_ticks(full.path, log.path.stat().st_size)
    data = read_log(log.path)
    assert data.truncated and data.summary is None and "footer" in data.cut_reason
    assert 2500 < data.ticks == expected < 3000
    assert_matches_rows(data, log, slice(0, expected))


def test_cut_inside_first_chunk(tmp_path):
    log = write_synthetic_log(tmp_path / "k.mcap", 3000, chunk_size=4096)
    first_end = chunk_ends(log.path)[0]
    write_synthetic_log(log.path, 3000, chunk_size=4096, truncate_bytes=first_end - 10)
    data = read_log(log.path)
    assert data.truncated and data.ticks == 0
    assert all(len(a) == 0 for a in data.topics.values())


def test_missing_summary_metadata(tmp_path):
    log = write_synthetic_log(tmp_path / "a.mcap", 400, with_summary=False)
    data = read_log(log.path)
    assert data.truncated and data.summary is None
    assert "teleop_rt.summary" in data.cut_reason
    assert data.ticks == 400


def error_of(path, **kwargs) -> str:
    with pytest.raises(LogError) as info:
        read_log(path, **kwargs)
    err = info.value
    assert isinstance(err, TeleopError) and err.exit_code == 2
    text = str(err)
    assert "\n" not in text and str(path) in text
    return text


def test_bad_files(tmp_path):
    assert "no such file" in error_of(tmp_path / "missing.mcap")
    assert "is a folder, not a regular file" in error_of(tmp_path)
    (tmp_path / "text.mcap").write_text("hello, this is not an MCAP file\n")
    assert "bad magic" in error_of(tmp_path / "text.mcap")
    (tmp_path / "empty.mcap").write_bytes(b"")
    assert "bad magic" in error_of(tmp_path / "empty.mcap")


def test_mcap_from_another_program(tmp_path):
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(library="some-other-tool")
        sid = w.register_schema("Pose", "jsonschema", b"{}")
        cid = w.register_channel("/pose", "json", sid)
        w.add_message(cid, 0, b"{}", 0)
        w.finish()
    text = error_of(path)
    assert "not a teleop_rt log" in text and "some-other-tool" in text


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"schema_names": {"/hsi": "other/msg/Foo"}}, "not a teleop_rt log: /hsi has schema"),
        ({"skip": ("/timing",)}, "required topic /timing is missing"),
        ({"pad": {"/to": 8}}, "/to payloads are"),
        ({"meta": {"schema_version": str(SCHEMA_VERSION + 1)}}, "newer than this software reads"),
        ({"meta": {"joints": None}}, "lacks 'joints'"),
        ({"meta": {"joints": "x"}}, "is not an integer"),
        ({"meta": {"joints": "3"}}, "schema of /hsi does not match"),
        ({"meta": {"joints_to": "9"}}, "schema of /to does not match"),
        ({"meta": {"joints_hsi": "0"}}, "a robot of 0 joints"),
        ({"meta": {"mapped": "2"}}, "is not 0 or 1"),
        ({"meta": {"mapped": "1"}}, "schema of /hsi does not match"),
    ],
)
def test_bad_logs(tmp_path, kwargs, message):
    log = write_synthetic_log(tmp_path / "bad.mcap", 100, **kwargs)
    assert message in error_of(log.path)


def test_missing_topic_not_asked_for(tmp_path):
    log = write_synthetic_log(tmp_path / "a.mcap", 100, skip=("/timing",))
    assert read_log(log.path, topics=["/hsi", "/to"]).ticks == 100


def test_mixed_payload_sizes(tmp_path):
    """One topic whose messages are not all of the fixed size: LogError, not a cut."""
    log = write_synthetic_log(tmp_path / "a.mcap", 20)
    data = read_log(log.path)
    path = tmp_path / "mixed.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("teleop_rt", log.meta)
        cids = {}
        for topic in log.layout.topics:
            sid = w.register_schema(topic.type_name, "ros2msg", topic.definition)
            cids[topic.name] = w.register_channel(topic.name, "cdr", sid)
        for k in range(20):
            for name, cid in cids.items():
                body = CDR_HEADER + data.topics[name][k].tobytes()
                w.add_message(cid, k * 10**6, body + (b"\0" if k == 7 else b""), k * 10**6)
        w.finish()
    assert "/hsi payloads: messages of sizes [172, 173] bytes" in error_of(path)


def test_arrays_outlive_the_file(tmp_path):
    """The arrays own their memory (not views of the closed memory map)."""
    log = write_synthetic_log(tmp_path / "a.mcap", 100)
    data = read_log(log.path)
    log.path.unlink()
    for arr in data.topics.values():
        root = arr
        while isinstance(root.base, np.ndarray):
            root = root.base
        assert root.base is None and root.flags.owndata  # numpy's memory, not the file's
    np.testing.assert_array_equal(data.topics["/hsi"]["q"], log.field("/hsi", "q"))


@pytest.mark.parametrize(
    "rate, t_from, t_to, first, stop",
    [(1000, 0.3, 0.7, 300, 700), (3000, 0.1, 0.3, 300, 900), (1000, None, 0.0015, 0, 2)],
)
def test_window_is_whole_ticks(tmp_path, rate, t_from, t_to, first, stop):
    """Seconds pick ticks k with t_from <= k / rate < t_to, also when the period is not a
    whole number of ns (3 kHz: log times are k * 333333 ns)."""
    log = write_synthetic_log(tmp_path / "a.mcap", 1200, rate_hz=rate, chunk_size=2048)
    data = read_log(log.path, t_from=t_from, t_to=t_to)
    for arr in data.topics.values():
        np.testing.assert_array_equal(arr["tick"], np.arange(first, stop))
