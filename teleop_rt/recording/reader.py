"""Read a teleop_rt MCAP log into one numpy structured array per topic.

Why not ``mcap``'s ``iter_messages``: it builds Python objects for every message of every chunk
(about 12 us per message here: 30 s for a 10-minute log, even when one topic is asked for).
Every message of a topic has the same fixed size, so this reader walks the file's top-level
records itself, decompresses each chunk once and gathers all messages of a topic with one numpy
fancy index, at the offsets listed by the chunk's message index records. ``mcap``'s record
classes parse the few other records. The same linear walk reads finished and cut-short files:
it stops at the first record that does not fit in the file and keeps every chunk before it.
"""

from __future__ import annotations

import io
import json
import math
import mmap
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Header, Metadata, Schema

from teleop_rt.declarations import SITES
from teleop_rt.errors import TeleopError, quote
from teleop_rt.inputs import check_regular
from teleop_rt.recording.schema import CDR_HEADER, SCHEMA_VERSION, LogLayout, Topic

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig

MAGIC = b"\x89MCAP0\r\n"
META = "teleop_rt"
SUMMARY_META = "teleop_rt.summary"
_HEAD = 31  # message record: opcode 1, length 8, channel 2, sequence 4, log and publish time 16
_META_INTS = ("joints", "env_elements", "schema_version")
# a log of robots with their own joint counts, or of mapped sites (LogLayout): absent in others
_OPTIONAL_INTS = ("delay_ticks", "joints_hsi", "joints_to", "mapped")


class LogError(TeleopError):
    """A log file is missing, not a teleop_rt MCAP log, or malformed (exit code 2)."""

    exit_code = 2


@dataclass
class LogData:
    """A log read into memory: metadata, attachments and per-topic arrays in tick order."""

    path: Path
    meta: dict[str, str]
    layout: LogLayout
    config_yaml: str | None
    attachments: dict[str, bytes]
    summary: dict | None
    truncated: bool
    cut_reason: str | None
    topics: dict[str, np.ndarray] = field(default_factory=dict)
    # tick ranges [first, last] missing inside the ticks read (rows the session dropped when
    # its writer fell behind, at the end too if the summary counts more ticks): not a cut
    gaps: list[tuple[int, int]] = field(default_factory=list)
    # messages read per topic, before topics cut at different ticks are trimmed to their common
    # ticks (in the window, if one was asked for)
    message_counts: dict[str, int] = field(default_factory=dict)
    # the other topics of the file (the 3D scene's): topic -> (schema name, messages indexed)
    other_topics: dict[str, tuple[str, int]] = field(default_factory=dict)
    profile: str = ""  # the MCAP header's profile and library
    library: str = ""
    footer: bool = False  # the file ends with its footer and closing magic

    @property
    def start_ns(self) -> int:
        """UTC of tick 0 in ns since the epoch (0 for logs written before log times were
        wall-clock): the log time of tick k is start_ns + k * period."""
        return int(self.meta.get("start_time_ns", 0))

    @property
    def rate_hz(self) -> float:
        return float(self.meta["rate_hz"])

    @property
    def dt(self) -> float:
        """Tick period, computed as the session does (1.0 / rate_hz)."""
        return 1.0 / self.rate_hz

    @property
    def ticks(self) -> int:
        return min((len(a) for a in self.topics.values()), default=0)

    @property
    def site(self) -> str:
        """'hsi' or 'to' for a site's own log (``teleop-rt site``), '' for a session's."""
        return self.layout.site

    def what(self) -> str:
        """What the log is, in words (for messages that refuse it)."""
        return _what(self.layout, self.meta)

    damaged: dict[str, str] = field(default_factory=dict)  # attachment name -> what is wrong

    @property
    def missing_ticks(self) -> int:
        return sum(last - first + 1 for first, last in self.gaps)

    def attachment(self, name: str) -> bytes | None:
        """An attachment's bytes (None if the log has none by that name); LogError if damaged."""
        if name in self.damaged:
            raise LogError(f"{self.path}: the {name} attachment is damaged ({self.damaged[name]})")
        return self.attachments.get(name)

    def raw_config(self) -> dict | None:
        """The config.yaml attachment as a plain mapping (None if the log has none); LogError
        if it is damaged, not YAML or not a mapping."""
        self.attachment("config.yaml")
        if self.config_yaml is None:
            return None
        from teleop_rt import config

        where = f"{self.path}: the config.yaml attachment"
        try:
            data = config.parse_yaml(self.config_yaml.encode(), where)
        except config.ConfigError as err:
            raise LogError(str(err)) from None
        if not isinstance(data, dict):
            raise LogError(f"{where} is not a mapping but {quote(repr(data))}")
        return data

    def channel_space(self) -> str:
        """The channel's space in the config attachment: joint when it says none (or the
        attachment is damaged: the figures stand without it, only their row names need it)."""
        try:
            raw = self.raw_config()
        except LogError:
            return "joint"
        channel = (raw or {}).get("channel")
        return str(channel.get("space", "joint")) if isinstance(channel, dict) else "joint"

    def config(self) -> SessionConfig | None:
        """The session config stored in the log (None if the log has no config.yaml); LogError
        naming the attachment if it is not a valid config."""
        raw = self.raw_config()
        if raw is None:
            return None
        from teleop_rt import config

        try:
            return config.from_dict(raw)
        except config.ConfigError as err:
            raise LogError(f"{self.path}: the config.yaml attachment: {err}") from None


def require_ticks(data: LogData) -> None:
    """LogError unless ``data`` holds a tick: figures of no ticks are no result."""
    if not data.ticks:
        why = f" ({data.cut_reason})" if data.truncated and data.cut_reason else ""
        raise LogError(f"{data.path}: the log holds no ticks{why}")


class _Damaged(Exception):
    """A record inside the file cannot be parsed: treated as the end of the readable data."""


class _BadSize(Exception):
    """Messages of one channel differ in size or encoding: not the fixed layout."""


@dataclass
class _Chunk:
    at: int  # file offset of the chunk record
    body: memoryview
    start_ns: int
    end_ns: int
    index: dict[int, np.ndarray] = field(default_factory=dict)  # channel -> (log_time, offset)


def read_log(
    path: str | Path,
    topics: Iterable[str] | None = None,
    t_from: float | None = None,
    t_to: float | None = None,
) -> LogData:
    """Read ``topics`` (default: all the log has) of the ticks k with
    ``t_from <= k / rate_hz < t_to``.

    A file cut short (no footer, or no ``teleop_rt.summary``) is read up to its last complete
    chunk and flagged ``truncated`` with a ``cut_reason``. Anything else wrong raises LogError.
    """
    path = Path(path)
    check_regular(path, error=LogError)  # before opening: a FIFO would block, a device not end
    with open(path, "rb") as f:
        if path.stat().st_size < len(MAGIC) or f.read(len(MAGIC)) != MAGIC:
            raise LogError(f"{path}: not an MCAP file (bad magic)")
        # Unmapped when the last view is gone (the arrays returned are copies, not views).
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    return _Reader(path, memoryview(mm)).read(topics, t_from, t_to)


class _Reader:
    def __init__(self, path: Path, buf: memoryview) -> None:
        self.path, self.buf = path, buf
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.damaged: dict[str, str] = {}
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.chunks: list[_Chunk] = []
        self.loose: dict[int, list[int]] = {}  # messages outside chunks: file offsets
        self.library = ""
        self.profile = ""
        self.footer = False
        self.cut: str | None = None

    def fail(self, what: str) -> LogError:
        return LogError(f"{self.path}: {what}")

    # -- pass 1: top-level records (cheap: chunks are only located, not decompressed) --------

    def scan(self) -> None:
        buf, end, at = self.buf, len(self.buf), len(MAGIC)
        chunk: _Chunk | None = None
        while True:
            if at + 9 > end:
                where = "after" if at == end else "inside the header of"
                self.cut = f"file ends at byte {end} {where} a record, without a footer"
                return
            op = buf[at]
            length = int.from_bytes(buf[at + 1 : at + 9], "little")
            if at + 9 + length > end:
                self.cut = (
                    f"file ends at byte {end}, inside {_article(_op_name(op))} record "
                    f"starting at byte {at}"
                )
                return
            body = buf[at + 9 : at + 9 + length]
            try:
                if op == 0:
                    raise _Damaged("opcode 0: file cut short or overwritten")
                if op == Opcode.HEADER:
                    header = _read(Header, body)
                    self.library, self.profile = header.library, header.profile
                elif op == Opcode.CHUNK:
                    chunk = self._chunk(at, body)
                    self.chunks.append(chunk)
                elif op == Opcode.MESSAGE_INDEX and chunk is not None:
                    cid = int.from_bytes(body[:2], "little")
                    size = int.from_bytes(body[2:6], "little")
                    if size % 16 or 6 + size > len(body):
                        raise _Damaged("bad message index")
                    chunk.index[cid] = np.frombuffer(body, "<u8", size // 8, 6).reshape(-1, 2)
                elif op == Opcode.MESSAGE:
                    cid = int.from_bytes(body[:2], "little")
                    self.loose.setdefault(cid, []).append(at)
                else:
                    self._record(op, body)
            except (_Damaged, ValueError, UnicodeDecodeError) as err:
                self.cut = f"damaged record at byte {at} ({err}); read up to it"
                return
            if op != Opcode.MESSAGE_INDEX and op != Opcode.CHUNK:
                chunk = None
            at += 9 + length
            if op == Opcode.FOOTER:
                self.footer = True
                if bytes(buf[at : at + len(MAGIC)]) != MAGIC:
                    self.cut = "file ends inside its closing magic"
                return

    def _chunk(self, at: int, body: memoryview) -> _Chunk:
        start, end = int.from_bytes(body[:8], "little"), int.from_bytes(body[8:16], "little")
        return _Chunk(at, body, start, end)

    def _record(self, op: int, body: memoryview) -> None:
        """Schema, channel, metadata and attachment records (top level or inside a chunk)."""
        if op == Opcode.SCHEMA:
            schema = _read(Schema, body)
            self.schemas[schema.id] = schema
        elif op == Opcode.CHANNEL:
            channel = _read(Channel, body)
            self.channels[channel.id] = channel
        elif op == Opcode.METADATA:
            meta = _read(Metadata, body)
            self.metadata[meta.name] = meta.metadata
        elif op == Opcode.ATTACHMENT:
            att = _read(Attachment, body)
            crc = int.from_bytes(body[-4:], "little")  # of all fields before it; 0: not computed
            if crc and zlib.crc32(body[:-4]) != crc:
                self.damaged[att.name] = "CRC mismatch"
            else:
                self.attachments[att.name] = att.data

    # -- pass 2: messages --------------------------------------------------------------------

    def read(
        self, topics: Iterable[str] | None, t_from: float | None, t_to: float | None
    ) -> LogData:
        self.scan()
        layout, meta = self._layout()
        self.layout_topics = layout.topics
        wanted = {t.name: t for t in layout.topics}
        names = list(wanted) if topics is None else list(topics)
        unknown = [n for n in names if n not in wanted]
        if unknown and (layout.site or {"/port", "/link"} & set(unknown)):
            hint = " (metrics HSI.mcap TO.mcap takes both sites' logs)" if layout.site else ""
            raise self.fail(
                f"{_what(layout, meta)}: it holds no {', '.join(unknown)}{hint}"
            )  # fmt: skip
        if unknown:
            raise ValueError(f"unknown topic(s) {unknown}; a log has {list(wanted)}")
        first, stop, lo, hi = _window(float(meta["rate_hz"]), t_from, t_to)
        start = int(meta.get("start_time_ns", 0))  # log times are start + tick time
        lo += 0 if t_from is None else start
        hi = hi if t_to is None else min(hi + start, 2**64)
        parts: dict[str, list[np.ndarray]] = {n: [] for n in names}
        for chunk in self.chunks:
            known = all(any(c.topic == n for c in self.channels.values()) for n in names)
            if known and (chunk.end_ns < lo or chunk.start_ns >= hi):
                continue  # outside the window; channel records are already known
            try:
                self._messages(chunk, set(names), lo, hi, parts)
            except _Damaged as err:
                self.cut = f"damaged chunk at byte {chunk.at} ({err}); read up to it"
                break
        if self.loose:
            offsets = {c: np.asarray(o, np.int64) for c, o in self.loose.items()}
            try:
                self._gather(self.buf, offsets, set(names), lo, hi, parts)
            except _Damaged as err:
                self.cut = f"damaged message ({err})"
        arrays = {n: self._decode(wanted[n], parts[n]) for n in names}
        if t_from is not None or t_to is not None:
            arrays = {n: a[(a["tick"] >= first) & (a["tick"] < stop)] for n, a in arrays.items()}
        counts = {n: len(a) for n, a in arrays.items()}
        others = self._other_topics(set(wanted))
        arrays = self._common_ticks(arrays)
        summary = self._summary()
        truncated = self.cut is not None or summary is None
        cut = self.cut
        if cut is None and summary is None:
            cut = (
                f"no '{SUMMARY_META}' metadata: the session did not finish writing its log "
                "(killed or crashed)"
            )
        raw_config = self.attachments.get("config.yaml")
        config_yaml: str | None = None
        if raw_config is not None:
            try:
                config_yaml = raw_config.decode()
            except UnicodeDecodeError:
                self.damaged["config.yaml"] = "not UTF-8 text"
        return LogData(
            path=self.path,
            meta=meta,
            layout=layout,
            config_yaml=config_yaml,
            attachments=self.attachments,
            summary=summary,
            truncated=truncated,
            cut_reason=cut,
            topics=arrays,
            damaged=self.damaged,
            gaps=_gaps(arrays, first, stop, summary),
            message_counts=counts,
            other_topics=others,
            profile=self.profile,
            library=self.library,
            footer=self.footer,
        )

    def _other_topics(self, known: set[str]) -> dict[str, tuple[str, int]]:
        """Topics beyond the log's own, counted from the chunks' message indexes."""
        out: dict[str, tuple[str, int]] = {}
        for cid, channel in sorted(self.channels.items()):
            if channel.topic in known:
                continue
            count = sum(len(c.index.get(cid, ())) for c in self.chunks)
            schema = self.schemas.get(channel.schema_id)
            out[channel.topic] = (
                schema.name if schema else "",
                count + len(self.loose.get(cid, [])),
            )
        return out

    def _messages(self, chunk: _Chunk, names: set[str], lo: int, hi: int, parts) -> None:
        data = _decompress(chunk.body)
        offsets = {cid: idx[:, 1].astype(np.int64) for cid, idx in chunk.index.items()}
        # The message indexes list every message of the chunk exactly when their records fill
        # it; otherwise (schema / channel records inside, or indexes lost to a cut) walk it.
        if not offsets or _records_size(data, offsets) != len(data):
            offsets = self._walk(data)
        self._gather(data, offsets, names, lo, hi, parts)

    def _walk(self, data: bytes | memoryview) -> dict[int, np.ndarray]:
        """Offsets of the messages of a chunk, one record at a time (also reads its channels)."""
        found: dict[int, list[int]] = {}
        at, end = 0, len(data)
        while at < end:
            if at + 9 > end:
                raise _Damaged("record header past the chunk end")
            op = data[at]
            length = int.from_bytes(data[at + 1 : at + 9], "little")
            if at + 9 + length > end:
                raise _Damaged("record past the chunk end")
            if op == Opcode.MESSAGE:
                found.setdefault(int.from_bytes(data[at + 9 : at + 11], "little"), []).append(at)
            else:
                self._record(op, memoryview(data)[at + 9 : at + 9 + length])
            at += 9 + length
        return {cid: np.asarray(o, np.int64) for cid, o in found.items()}

    def _gather(self, data, offsets, names: set[str], lo: int, hi: int, parts) -> None:
        for cid, offs in offsets.items():
            channel = self.channels.get(cid)
            if channel is None:
                raise self.fail(f"message on channel {cid} before its channel record")
            if channel.topic in names and len(offs):
                try:
                    payload = _take(data, offs, lo, hi)
                except _BadSize as err:
                    raise self.fail(f"{channel.topic} payloads: {err.args[0]}") from None
                if len(payload):
                    parts[channel.topic].append(payload)

    # -- checks and assembly -----------------------------------------------------------------

    def _layout(self) -> tuple[LogLayout, dict[str, str]]:
        meta = self.metadata.get(META)
        if meta is None:
            if self.cut is not None and not self.chunks:
                raise self.fail(f"cut short before its '{META}' metadata ({self.cut})")
            by = f" (written by '{self.library}')" if self.library else ""
            raise self.fail(f"not a teleop_rt log: no '{META}' metadata record{by}")
        ints: dict[str, int] = {}
        for key in (*_META_INTS, *_OPTIONAL_INTS):
            if key not in meta:
                if key in _OPTIONAL_INTS:
                    continue
                raise self.fail(f"'{META}' metadata lacks '{key}'")
            try:
                value = int(meta[key]) if len(meta[key]) <= 20 else None
            except ValueError:
                value = None
            if value is None or value < 0:
                raise self.fail(
                    f"'{META}' metadata: {key} = {quote(meta[key])} is not an integer >= 0"
                ) from None
            ints[key] = value
        try:
            rate = float(meta["rate_hz"])
        except (KeyError, ValueError):
            raise self.fail(f"'{META}' metadata: missing or bad rate_hz") from None
        from teleop_rt.config import MAX_RATE_HZ, MIN_RATE_HZ

        if not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:  # also NaN; the times of ticks need it
            raise self.fail(
                f"'{META}' metadata: rate_hz = {quote(meta['rate_hz'])} is not a session's tick "
                f"rate ({MIN_RATE_HZ} to {MAX_RATE_HZ} Hz)"
            )
        try:
            start = int(meta.get("start_time_ns", 0))
        except ValueError:
            start = -1
        if not 0 <= start < 2**63:
            raise self.fail(f"'{META}' metadata: start_time_ns = {meta['start_time_ns']!r}")
        if ints["schema_version"] > SCHEMA_VERSION:
            raise self.fail(
                f"log schema version {ints['schema_version']} (teleop_rt "
                f"{meta.get('software_version', '?')}) is newer than this software reads "
                f"({SCHEMA_VERSION}); upgrade teleop_rt"
            )
        if ints["joints"] < 1:
            raise self.fail(f"'{META}' metadata: joints = 0")
        site = meta.get("site", "") if meta.get("log_kind") == "site" else ""
        if site not in ("", *SITES):
            raise self.fail(f"'{META}' metadata: site = {quote(site)} is neither hsi nor to")
        if ints.get("mapped", 0) > 1:
            raise self.fail(f"'{META}' metadata: mapped = {quote(meta['mapped'])} is not 0 or 1")
        if 0 in (ints.get("joints_hsi"), ints.get("joints_to")):
            raise self.fail(f"'{META}' metadata: a robot of 0 joints")
        shape = (ints.get("joints_hsi", 0), ints.get("joints_to", 0), bool(ints.get("mapped")))
        version = ints["schema_version"]  # (an older log's fields: as it was written)
        return LogLayout(ints["joints"], ints["env_elements"], site, *shape, version), meta

    def _decode(self, topic: Topic, parts: list[np.ndarray]) -> np.ndarray:
        channels = [c for c in self.channels.values() if c.topic == topic.name]
        if not channels:
            # the writer declares a channel with its first message: a log finished before the
            # first tick (a stop at tick 0) has none of its topics, and holds no ticks
            own = {t.name for t in self.layout_topics}
            never_ran = not own & {c.topic for c in self.channels.values()}
            if self.cut is None and not never_ran:
                present = ", ".join(sorted({c.topic for c in self.channels.values()})) or "none"
                raise self.fail(f"required topic {topic.name} is missing (topics: {present})")
            return np.empty(0, topic.dtype)
        for channel in channels:
            self._check_schema(topic, channel)
        size = topic.dtype.itemsize
        for part in parts:
            if part.shape[1] != size:
                raise self.fail(
                    f"{topic.name} payloads are {part.shape[1] + 4} bytes, expected {size + 4} "
                    f"({topic.type_name} with the metadata's joints and env_elements)"
                )
        body = np.concatenate(parts) if parts else np.empty((0, size), np.uint8)
        arr = body.view(topic.dtype).reshape(-1)
        tick = arr["tick"]
        if len(tick) > 1 and (tick[1:] <= tick[:-1]).any():
            arr = arr[np.argsort(tick, kind="stable")]
            tick = arr["tick"]
            if (tick[1:] == tick[:-1]).any():
                raise self.fail(f"{topic.name}: a tick appears twice")
        return arr

    def _check_schema(self, topic: Topic, channel: Channel) -> None:
        schema = self.schemas.get(channel.schema_id)
        name = schema.name if schema else "none"
        if schema is None or name != topic.type_name or schema.encoding != "ros2msg":
            raise self.fail(
                f"not a teleop_rt log: {topic.name} has schema '{name}', "
                f"expected ros2msg '{topic.type_name}'"
            )
        if channel.message_encoding != "cdr":
            raise self.fail(f"{topic.name}: message encoding {channel.message_encoding!r}, not cdr")
        if _fields(schema.data) != _fields(topic.definition):
            raise self.fail(
                f"schema of {topic.name} does not match the layout of {len(topic.fields)} "
                "fields this software derives from the metadata (joints, env_elements)"
            )

    def _common_ticks(self, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Topics cut at different messages of the same tick keep only their common ticks."""
        counts = {n: len(a) for n, a in arrays.items()}
        if len(set(counts.values())) <= 1:
            return arrays
        if self.cut is None and self.metadata.get(SUMMARY_META) is not None:
            raise self.fail(f"topics hold different numbers of ticks: {counts}")
        last = min((int(a["tick"][-1]) if len(a) else -1) for a in arrays.values())
        return {n: a[a["tick"] <= last] if last >= 0 else a[:0] for n, a in arrays.items()}

    def _summary(self) -> dict | None:
        record = self.metadata.get(SUMMARY_META)
        if record is None:
            return None
        try:
            summary = json.loads(record["json"])
        except (KeyError, ValueError):
            raise self.fail(f"'{SUMMARY_META}' metadata holds no valid 'json' value") from None
        if not isinstance(summary, dict):
            raise self.fail(f"'{SUMMARY_META}' json is not an object")
        return summary


def _gaps(
    arrays: dict[str, np.ndarray], first: int, stop: int, summary: dict | None
) -> list[tuple[int, int]]:
    """Ticks missing from [first, stop) (the window) before, between and (if the summary says
    how many ticks ran) after the ticks read; the topics hold the same ticks by now."""
    if not arrays:
        return []
    tick = next(iter(arrays.values()))["tick"].astype(np.int64)
    end = stop
    ran = summary.get("ticks") if summary is not None else None
    if isinstance(ran, int) and 0 <= ran <= 2**62:
        end = min(stop, ran)
    elif len(tick):
        end = int(tick[-1]) + 1  # a cut log: what came after the cut is not a gap
    else:
        return []
    bounds = np.concatenate(([first - 1], tick, [end]))
    jumps = np.flatnonzero(np.diff(bounds) > 1)
    return [(int(bounds[j]) + 1, int(bounds[j + 1]) - 1) for j in jumps]


def _what(layout: LogLayout, meta: dict[str, str]) -> str:
    if layout.site:
        return f"the {layout.site} site's log of session {meta.get('session_id', '?')}"
    return "a session's log (both robots)"


def check_window(t_from: float | None, t_to: float | None) -> None:
    """``--from`` / ``--to`` (seconds from the session start): finite, and a non-empty window."""
    for name, value in (("--from", t_from), ("--to", t_to)):
        if value is not None and not math.isfinite(value):
            raise LogError(f"{name} {value}: expected a finite time in seconds")
    if t_from is not None and t_to is not None and t_to <= t_from:
        raise LogError(f"--from {t_from:g} --to {t_to:g}: the window is empty")


def _article(word: str) -> str:
    return f"{'an' if word[:1] in 'aeiou' else 'a'} {word}"


def _op_name(op: int) -> str:
    try:
        return Opcode(op).name.lower()
    except ValueError:
        return f"opcode {op:#04x}"


def _window(rate: float, t_from: float | None, t_to: float | None) -> tuple[int, int, int, int]:
    """Ticks [first, stop) with t_from <= k / rate < t_to (seconds rounded to 1e-6 tick so that
    0.3 s is tick 300 at 1 kHz), and log-time bounds in ns that surely hold them (to skip
    chunks; a margin covers how the writer rounds its period to whole ns)."""
    first = 0 if t_from is None else _tick_at(t_from, rate)
    stop = 2**63 if t_to is None else _tick_at(t_to, rate)
    lo = 0 if t_from is None else max(0, math.floor((first - 1) * 1e9 / rate * (1 - 1e-6)))
    hi = 2**64 if t_to is None else math.ceil((stop + 1) * 1e9 / rate * (1 + 1e-6))
    return first, stop, lo, hi


def _tick_at(t: float, rate: float) -> int:
    """The first tick at or after ``t`` s, 0 to 2**62: a finite time past any log (--from
    1e308, whose ticks overflow a float) is past its last tick, not an OverflowError."""
    ticks = round(t * rate, 6)
    return max(0, math.ceil(ticks)) if ticks < 2**62 else 2**62


def _read(cls, body: memoryview):
    """Parse one record body with mcap's record class."""
    try:
        return cls.read(ReadDataStream(io.BytesIO(body)))
    except Exception as err:  # mcap raises EndOfFile, struct.error, ...
        raise _Damaged(f"{cls.__name__.lower()} record: {err}") from None


def _decompress(body: memoryview) -> bytes | memoryview:
    size = int.from_bytes(body[16:24], "little")
    n = int.from_bytes(body[28:32], "little")
    compression = bytes(body[32 : 32 + n]).decode()
    at = 32 + n
    length = int.from_bytes(body[at : at + 8], "little")
    data = body[at + 8 : at + 8 + length]
    if len(data) != length:
        raise _Damaged("chunk data past the record end")
    out: bytes | memoryview
    try:
        if compression == "zstd":
            import zstandard

            out = zstandard.decompress(data, size)
        elif compression == "lz4":
            import lz4.frame

            out = lz4.frame.decompress(data)
        elif compression == "":
            out = data
        else:
            raise _Damaged(f"unknown compression {compression!r}")
    except _Damaged:
        raise
    except Exception as err:
        raise _Damaged(f"{compression} data: {err}") from None
    if len(out) != size:
        raise _Damaged(f"chunk holds {len(out)} bytes, its header says {size}")
    # A flipped bit in LZ4 or zstd literals still decompresses, to wrong values (a recorded
    # torque of 874 N m replayed into a safety stop): the chunk's CRC is what catches it.
    crc = int.from_bytes(body[24:28], "little")  # of the uncompressed records; 0: not computed
    if crc and zlib.crc32(out) != crc:
        raise _Damaged("CRC mismatch")
    return out


def _records_size(data: bytes | memoryview, offsets: dict[int, np.ndarray]) -> int:
    """Bytes taken by the indexed message records (a channel's records all have one size)."""
    total = 0
    for offs in offsets.values():
        if len(offs):
            at = int(offs[0])
            if at < 0 or at + 9 > len(data):
                return -1
            total += len(offs) * (9 + int.from_bytes(data[at + 1 : at + 9], "little"))
    return total


def _rows(data: bytes, offs: np.ndarray, skip: int, width: int) -> np.ndarray:
    """Bytes [skip, skip + width) of the records at offs, one row each.

    Evenly spaced records (one channel of a tick-by-tick log) are a strided view of the chunk;
    otherwise a fancy index gathers them. Bounds are the caller's."""
    step = int(offs[1] - offs[0]) if len(offs) > 1 else 0
    if len(offs) == 1 or (step > 0 and (np.diff(offs) == step).all()):
        return np.ndarray((len(offs), width), np.uint8, data, int(offs[0]) + skip, (step, 1))
    windows = np.ndarray((len(data) - skip - width + 1, width), np.uint8, data, skip, (1, 1))
    return windows[offs]


def _take(data: bytes, offs: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """CDR bodies (messages, bytes; header checked and dropped) of one channel's records at
    offs, for log times in [lo, hi)."""
    if offs.min() < 0 or offs.max() + _HEAD + 4 > len(data):
        raise _Damaged("message offset past the chunk end")
    head = _rows(data, offs, 0, _HEAD + 4).copy()
    if (head[:, 0] != Opcode.MESSAGE).any():
        raise _Damaged("message index points at a non-message record")
    stamp = head[:, 15:23].copy().view("<u8")[:, 0]
    keep = (stamp >= lo) & (stamp < hi)
    if not keep.all():
        offs, head = offs[keep], head[keep]
    if not len(offs):
        return np.empty((0, 0), np.uint8)
    length = head[:, 1:9].copy().view("<u8")[:, 0]
    if (length != length[0]).any() or length[0] < 26:
        sizes = sorted(int(x) - 22 for x in np.unique(length))
        raise _BadSize(f"messages of sizes {sizes} bytes, not one fixed CDR layout")
    if (head[:, _HEAD : _HEAD + 2] != np.frombuffer(CDR_HEADER[:2], np.uint8)).any():
        raise _BadSize("not little-endian CDR (encapsulation header)")
    width = int(length[0]) - 26
    if offs.max() + _HEAD + 4 + width > len(data):
        raise _Damaged("message past the chunk end")
    return _rows(data, offs, _HEAD + 4, width).copy()


def _fields(definition: bytes) -> list[str]:
    """'type name' of each field of a ros2msg definition (comments and blank lines dropped)."""
    out = []
    for line in definition.decode(errors="replace").splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(" ".join(line.split()))
    return out
