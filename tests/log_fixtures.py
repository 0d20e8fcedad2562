"""Synthetic teleop_rt logs with known signals, written exactly as the recording format says.

The file is written with mcap's own ``Writer`` from ``LogLayout.encode`` (independent of the
teleop_rt writer), tick by tick: /hsi, /to, /channel, /timing of tick k, then tick k + 1.
The live summary stored in it is computed the way a session does (TransparencyAccumulator,
TimingStats), so readers and metrics can be checked against it bit for bit.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer

from teleop_rt.loop import TimingStats
from teleop_rt.recording.schema import CDR_HEADER, SCHEMA_VERSION, LogLayout, Topic
from teleop_rt.transparency_tick import TransparencyAccumulator

URDF = b'<robot name="synthetic"><link name="base"/></robot>\n'
START_NS = 1_767_225_600_123_456_789  # 2026-01-01T00:00:00.123456789Z: log times are wall-clock


@dataclass
class SyntheticLog:
    path: Path
    layout: LogLayout
    rows: np.ndarray  # (ticks, row_width) float64, what was written
    meta: dict[str, str]
    summary: dict | None  # the live summary stored (None if with_summary=False)
    config_yaml: str
    dt: float

    def field(self, topic: str, name: str) -> np.ndarray:
        return self.rows[:, field_slice(self.layout, topic, name)]


def field_slice(layout: LogLayout, topic: str, name: str) -> slice:
    """Columns of one field of one topic in a row (tick and t are the shared columns 0, 1)."""
    if name == "tick":
        return slice(0, 1)
    if name == "t":
        return slice(1, 2)
    start = layout.columns()[topic].start
    for f in next(t for t in layout.topics if t.name == topic).fields[2:]:
        if f.name == name:
            return slice(start, start + f.count)
        start += f.count
    raise KeyError(f"{topic}.{name}")


def synthetic_rows(
    layout: LogLayout, ticks: int, dt: float, delay: int = 3, seed: int = 0, **signals: np.ndarray
) -> np.ndarray:
    """Rows with random values everywhere (so column mix-ups show) and known main signals.

    q_h = q0_h + 0.3 sin(2 pi 0.5 t + j), q_t = q0_t + q_h(k - delay) - q0_h,
    tau_ext(/hsi) = 0.5 cos(2 pi t + j), tau_ext(/to) = -tau_ext(/hsi)(k - delay) + 0.01 sin(7 t).
    ``signals`` override a field by the name ``<topic>_<field>``, e.g. ``hsi_q=array``.
    """
    rng = np.random.default_rng(seed)
    n = layout.n
    rows = rng.standard_normal((ticks, layout.row_width))
    k = np.arange(ticks)
    t = k * dt
    rows[:, 0] = k
    rows[:, 1] = t
    j = np.arange(n)
    q0_h, q0_t = -0.8 + 0.1 * j, 1.8 - 0.2 * j
    past = np.maximum(k - delay, 0)

    def put(topic: str, name: str, values: np.ndarray) -> None:
        rows[:, field_slice(layout, topic, name)] = np.asarray(values).reshape(ticks, -1)

    phase = 2 * np.pi * 0.5 * t[:, None] + j
    q_h = q0_h + 0.3 * np.sin(phase)
    put("/hsi", "q", q_h)
    put("/to", "q", q0_t + q_h[past] - q0_h)
    tau_h = 0.5 * np.cos(2 * np.pi * t[:, None] + j)
    put("/hsi", "tau_ext", tau_h)
    put("/to", "tau_ext", -tau_h[past] + 0.01 * np.sin(7 * t)[:, None])
    put("/channel", "total_energy", 0.01 * np.sin(3 * t) - 0.002)
    put("/timing", "compute_ns", rng.integers(20_000, 90_000, ticks))
    put("/timing", "lateness_ns", rng.integers(0, 40_000, ticks))
    put("/timing", "missed", rng.random(ticks) < 0.02)
    if layout.n_env:
        put("/to", "in_contact", rng.random((ticks, layout.n_env)) < 0.5)
    for key, values in signals.items():
        topic, name = key.split("_", 1)
        put("/" + topic, name, values)
    return rows


def live_summary(layout: LogLayout, rows: np.ndarray, dt: float, name: str, delay: int) -> dict:
    """The summary a live session would report for these rows (same code paths)."""
    q_h, q_t = rows[:, field_slice(layout, "/hsi", "q")], rows[:, field_slice(layout, "/to", "q")]
    tau_h = rows[:, field_slice(layout, "/hsi", "tau_ext")]
    tau_ext_t = rows[:, field_slice(layout, "/to", "tau_ext")]
    acc = TransparencyAccumulator(q_h.shape[1], dt)
    for a, b, c, d in zip(
        q_h.tolist(), q_t.tolist(), tau_h.tolist(), tau_ext_t.tolist(), strict=True
    ):
        acc.add(a, b, c, [-x for x in d])
    stats = TimingStats(len(rows), int(round(dt * 1e9)))
    comp = rows[:, field_slice(layout, "/timing", "compute_ns")][:, 0]
    late = rows[:, field_slice(layout, "/timing", "lateness_ns")][:, 0]
    missed = rows[:, field_slice(layout, "/timing", "missed")][:, 0]
    for c, la, m in zip(comp.tolist(), late.tolist(), missed.tolist(), strict=True):
        stats.add(int(c), int(la), bool(m))
    energy = rows[:, field_slice(layout, "/channel", "total_energy")][:, 0].tolist()
    lowest = 0.0
    for e in energy:
        lowest = min(lowest, e)
    timing = stats.summary()
    timing["wall_s"] = 1.25
    return {
        "name": name,
        "ticks": len(rows),
        "simulated_time_s": len(rows) * dt,
        "delay_ticks": delay,
        "t_p": acc.t_p.tolist(),
        "t_tau": acc.t_tau.tolist(),
        "channel_energy_j": energy[-1] if energy else 0.0,
        "min_channel_energy_j": lowest,
        "timing": timing,
        "realtime": False,
        "notes": [],
        "stopped_early": None,
        "t_p_total": float(sum(acc.t_p)),
        "t_tau_total": float(sum(acc.t_tau)),
    }


def config_yaml(name: str, rate_hz: int, ticks: int, delay: int) -> str:
    """A resolved session config (as a session stores it), from configs/free_space.yaml."""
    import yaml

    from teleop_rt import config

    sets = [f"name={name}", f"rate_hz={rate_hz}", f"duration_s={ticks / rate_hz}"]
    sets.append(f"channel.delay_ms={delay * 1000 / rate_hz}")
    cfg = config.load(Path(__file__).resolve().parents[1] / "configs" / "free_space.yaml", sets)
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)


def write_synthetic_log(
    path: str | Path,
    ticks: int,
    n: int = 2,
    n_env: int = 1,
    *,
    rate_hz: int = 1000,
    delay: int = 3,
    chunk_size: int = 1024 * 1024,
    truncate_bytes: int | None = None,
    with_summary: bool = True,
    finish: bool = True,
    meta: dict[str, str] | None = None,
    rows: np.ndarray | None = None,
    seed: int = 0,
    compression: CompressionType = CompressionType.ZSTD,
    chunked: bool = True,
    schema_names: dict[str, str] | None = None,
    skip: tuple[str, ...] = (),
    pad: dict[str, int] | None = None,
    start_ns: int = START_NS,
    **signals: np.ndarray,
) -> SyntheticLog:
    """Write a log of ``ticks`` ticks; return what was written.

    ``finish=False`` stops like a killed process (no last partial chunk, no summary metadata,
    no summary section); ``truncate_bytes`` then cuts the file to that many bytes. Faults for
    error tests: ``meta`` overrides metadata keys (None drops one), ``schema_names`` renames a
    topic's schema, ``skip`` leaves topics out, ``pad`` adds zero bytes to a topic's payloads.
    ``rows`` replaces the generated rows; ``signals`` override fields (see synthetic_rows).
    Log times are ``start_ns + k * period`` (``start_ns=0``: as logs before wall-clock times).
    """
    path = Path(path)
    layout = LogLayout(n, n_env)
    dt = 1.0 / rate_hz
    period_ns = round(1e9 / rate_hz)
    if rows is None:
        rows = synthetic_rows(layout, ticks, dt, delay, seed, **signals)
    name = "synthetic"
    info = {
        "software_version": "0.1.0",
        "schema_version": str(SCHEMA_VERSION),
        "joints": str(n),
        "env_elements": str(n_env),
        "rate_hz": str(rate_hz),
        "delay_ticks": str(delay),
        "name": name,
        "backend": "sim",
        "operator": "hand",
    }
    if start_ns:
        info["start_time_ns"] = str(start_ns)
    for key, value in (meta or {}).items():
        if value is None:
            info.pop(key, None)
        else:
            info[key] = value
    cfg = config_yaml(name, rate_hz, max(ticks, 1), delay)
    summary = live_summary(layout, rows, dt, name, delay) if with_summary else None
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=compression, use_chunking=chunked)
        w.start(profile="ros2", library="tests/log_fixtures")
        w.add_metadata("teleop_rt", info)
        w.add_attachment(0, 0, "config.yaml", "application/yaml", cfg.encode())
        w.add_attachment(0, 0, "urdf/hsi.urdf", "application/xml", URDF)
        w.add_attachment(0, 0, "urdf/to.urdf", "application/xml", URDF)
        cols = layout.columns()
        topics = [t for t in layout.topics if t.name not in skip]
        channels = []
        for topic in topics:
            schema = (schema_names or {}).get(topic.name, topic.type_name)
            sid = w.register_schema(schema, "ros2msg", topic.definition)
            channels.append(w.register_channel(topic.name, "cdr", sid))
        extra = pad or {}
        for start in range(0, len(rows), 8192):  # in blocks: a 600 000-tick log fits in memory
            block = rows[start : start + 8192]
            payloads = [
                _payloads(layout, block, t, cols[t.name], extra.get(t.name, 0)) for t in topics
            ]
            for i in range(len(block)):
                k = start + i
                stamp = start_ns + k * period_ns
                for cid, data in zip(channels, payloads, strict=True):
                    w.add_message(cid, stamp, data[i], stamp, sequence=k)
        if finish:  # a killed process writes neither the summary nor the summary section
            if summary is not None:
                w.add_metadata("teleop_rt.summary", {"json": json.dumps(summary)})
            w.finish()
    if truncate_bytes is not None:
        os.truncate(path, truncate_bytes)
    return SyntheticLog(path, layout, rows, info, summary if finish else None, cfg, dt)


def _payloads(
    layout: LogLayout, rows: np.ndarray, topic: Topic, cols: slice, pad: int = 0
) -> list[bytes]:
    size = topic.dtype.itemsize
    raw = np.zeros((len(rows), 4 + size + pad), dtype=np.uint8)
    raw[:, :4] = np.frombuffer(CDR_HEADER, dtype=np.uint8)
    raw[:, 4 : 4 + size] = layout.encode(rows, topic, cols).view(np.uint8).reshape(len(rows), -1)
    return [r.tobytes() for r in raw]
