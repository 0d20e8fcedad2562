"""``teleop-rt metrics HSI.mcap TO.mcap``: the pair's figures from the two sites' own logs.

Alignment: by tick number. Both sites start their tick clocks at the instant their handshake
agreed on (each log's start_time_ns is that instant), so tick k of the HSI's log and tick k of
the TO's are the same moment (on one host exactly; across hosts as well as their clocks
agree). T_p and T_tau (eq 18) pair the TO's q and tau_e (= -tau_ext) with the HSI's q and tau_h
(= tau_ext) at every tick both logs hold, with the arithmetic of the live figures
(``transparency_sums``), so that two complete logs give exactly the pair figures ``run --link
zenoh`` prints from its sites' tick records. alpha in eq 18 counts from tick 0 (both logs' first
tick). The channel's energy at tick k is the sum of the two ports' energies at tick k (eq 7, 8).

Two logs pair only if both are site logs (not a session's, not a replay), of the two sides, of
one session (its id, start instant, rate, joints and shared config hash): anything else is one
line and exit code 2.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from teleop_rt.analysis.transparency import transparency_labels
from teleop_rt.recording.metrics import _timing, gap_text, transparency_sums
from teleop_rt.recording.reader import LogData, LogError, check_window, read_log, require_ticks
from teleop_rt.recording.schema import LogLayout

SAME = ("session_id", "start_time_ns", "rate_hz", "joints", "delay_ticks", "config_hash")


def read_pair(a: str | Path, b: str | Path, command: str = "metrics") -> tuple[LogData, LogData]:
    """The HSI's and the TO's log (in either order), refused unless they pair (``command``:
    who asks, for the message)."""
    logs = [read_log(p) for p in (a, b)]
    for data in logs:
        if not data.site:
            raise LogError(
                f"{data.path} is {data.what()}: {command} takes it alone; two logs must be the "
                "two site logs of one session (teleop-rt site, run --link zenoh)"
            )
        if "replay_of" in data.meta:
            raise LogError(
                f"{data.path} is a replay of {data.meta['replay_of']}: it pairs with no other "
                "site's log; give the logs the two sites wrote"
            )
    x, y = logs
    if x.site == y.site:
        raise LogError(f"{x.path} and {y.path} are both the {x.site} site's log; give the "
                       "HSI's and the TO's")  # fmt: skip
    hsi, to = (x, y) if x.site == "hsi" else (y, x)
    for key in SAME:
        mine, theirs = hsi.meta.get(key), to.meta.get(key)
        if mine != theirs or mine is None:
            what = "different sessions" if key == "session_id" else "one session's, but not"
            raise LogError(
                f"{hsi.path} and {to.path} are logs of {what} ({key} {mine or '?'} and "
                f"{theirs or '?'})"
            )
    return hsi, to


def _common_ticks(
    hsi: LogData, to: LogData, t_from: float | None = None, t_to: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ticks both logs hold (in the window ``t_from <= k dt < t_to``, if given) and their
    rows in each log."""
    dt = hsi.dt
    ticks, ih, it = np.intersect1d(
        hsi.topics["/hsi"]["tick"], to.topics["/to"]["tick"], assume_unique=True,
        return_indices=True,
    )  # fmt: skip
    k = ticks.astype(np.int64)
    keep = np.ones(len(k), dtype=bool)
    if t_from is not None:
        keep &= k >= np.ceil(round(t_from / dt, 6))
    if t_to is not None:
        keep &= k < np.ceil(round(t_to / dt, 6))
    return k[keep], ih[keep], it[keep]


def paired_log(
    hsi: LogData, to: LogData, t_from: float | None = None, t_to: float | None = None
) -> LogData:
    """The two site logs as one session's log for ``teleop-rt plot``: /hsi and /to at the
    ticks both hold (in the window), /channel's energy the two ports' sum (eq 7, 8); the HSI
    log's metadata and attachments (the config and both URDFs: each site attaches both)."""
    k, ih, it = _common_ticks(hsi, to, t_from, t_to)
    channel = np.zeros(len(k), dtype=[("t", "f8"), ("total_energy", "f8")])
    channel["t"] = hsi.topics["/hsi"]["t"][ih]
    channel["total_energy"] = (hsi.topics["/port"]["total_energy"][ih]
                               + to.topics["/port"]["total_energy"][it])  # fmt: skip
    return dataclasses.replace(
        hsi,
        meta={**hsi.meta, "paired_with": to.path.name},
        layout=LogLayout(hsi.layout.n, to.layout.n_env),
        topics={"/hsi": hsi.topics["/hsi"][ih], "/to": to.topics["/to"][it], "/channel": channel},
        truncated=hsi.truncated or to.truncated,
        cut_reason="; ".join(d.cut_reason for d in (hsi, to) if d.cut_reason) or None,
        gaps=[],
    )


def pair_metrics(
    hsi: LogData, to: LogData, t_from: float | None = None, t_to: float | None = None
) -> dict:
    """The pair's figures over the ticks both logs hold (in the window ``t_from <= k dt <
    t_to``, if given), and each site's own."""
    dt = hsi.dt
    h, t = hsi.topics["/hsi"], to.topics["/to"]
    offset = None  # alpha from tick 0, where both logs hold it (a window keeps it)
    every, first_h, first_t = _common_ticks(hsi, to)
    if len(every) and every[0] == 0:
        offset = h["q"][first_h[0]] - t["q"][first_t[0]]
    k, ih, it = _common_ticks(hsi, to, t_from, t_to)
    t_p, t_tau = transparency_sums(h["q"][ih], t["q"][it], h["tau_ext"][ih], -t["tau_ext"][it],
                                   dt, offset)  # fmt: skip
    energy = hsi.topics["/port"]["total_energy"][ih] + to.topics["/port"]["total_energy"][it]
    return {
        "name": hsi.meta.get("name", ""),
        "space": hsi.channel_space(),
        "session_id": hsi.meta.get("session_id"),
        "delay_ticks": int(hsi.meta.get("delay_ticks", 0)),
        "ticks": len(k),
        "first_tick": int(k[0]) if len(k) else None,
        "t_p": t_p,
        "t_tau": t_tau,
        "t_p_total": float(sum(t_p)),
        "t_tau_total": float(sum(t_tau)),
        "channel_energy_j": float(energy[-1]) if len(k) else 0.0,
        "min_channel_energy_j": min(0.0, float(energy.min())) if len(k) else 0.0,
        "window_s": None if t_from is None and t_to is None else [t_from, t_to],
        "sites": {d.site: _site(d) for d in (hsi, to)},
    }


def _site(data: LogData) -> dict:
    summary = data.summary or {}
    port = data.topics["/port"]["total_energy"]
    return {
        "log": str(data.path),
        "ticks": data.ticks,
        "port_energy_j": float(port[-1]) if len(port) else 0.0,
        "timing": _timing(data.topics["/timing"], int(round(data.dt * 1e9))),
        "from_peer": (summary.get("link") or {}).get("from_peer"),
        "exit": summary.get("stopped_early"),
        "gaps": [list(g) for g in data.gaps],
        "missing_ticks": data.missing_ticks,
        "truncated": data.truncated,
        "cut_reason": data.cut_reason,
    }


def format_pair(m: dict) -> str:
    """Plain-text table of ``pair_metrics``."""

    def vec(values: list[float]) -> str:
        return "  ".join(f"{v:.6g}" for v in values)

    t_p_label, t_tau_label = transparency_labels(m.get("space", "joint"))
    rows = [
        ("session", f"{m['name']} {m['session_id']} (delay {m['delay_ticks']} ticks), two sites"),
        ("ticks of both", f"{m['ticks']} (aligned by tick: both started at the agreed instant)"),
    ]
    if m["window_s"]:
        lo, hi = m["window_s"]
        rows.append(("window (s)", f"{0.0 if lo is None else lo:g} to "
                     f"{'the end' if hi is None else f'{hi:g}'}"))  # fmt: skip
    rows += [
        (t_p_label, vec(m["t_p"])),
        ("T_p total", f"{m['t_p_total']:.6g}"),
        (t_tau_label, vec(m["t_tau"])),
        ("T_tau total", f"{m['t_tau_total']:.6g}"),
        ("channel energy (J)",
         f"{m['channel_energy_j']:.6g} (minimum {m['min_channel_energy_j']:.6g})"),
    ]  # fmt: skip
    for name, s in m["sites"].items():
        timing = s["timing"]
        rows.append((f"{name} site", f"{s['ticks']} ticks; port energy {s['port_energy_j']:.6g} "
                     f"J; missed deadlines {timing['missed_deadlines']}"))  # fmt: skip
        peer = s["from_peer"]
        if peer:
            rows.append((f"{name} received", ", ".join(
                f"{k} {peer.get(k)}" for k in ("received", "used", "lost", "late",
                                               "silent_ticks") if k in peer)))  # fmt: skip
        if s["gaps"]:
            rows.append((f"{name} log gaps", gap_text(s["gaps"], s["missing_ticks"])))
        if s["truncated"]:
            rows.append((f"{name} log cut short", s["cut_reason"] or ""))
    width = max(len(k) for k, _ in rows) + 2
    return "\n".join(f"{k:<{width}}{v}" for k, v in rows)


def pair_main(
    a: str | Path, b: str | Path, as_json: bool = False, t_from: float | None = None,
    t_to: float | None = None,
) -> int:  # fmt: skip
    """``teleop-rt metrics HSI.mcap TO.mcap [--json] [--from S] [--to S]``; exit code."""
    check_window(t_from, t_to)
    hsi, to = read_pair(a, b)
    for data in (hsi, to):
        require_ticks(data)
    m = pair_metrics(hsi, to, t_from, t_to)
    if not m["ticks"]:
        raise LogError(f"{hsi.path} and {to.path}: no tick of both in the window")
    if as_json:
        json.dump(m, sys.stdout, indent=2)
        print()
    else:
        print(format_pair(m))
    for data in (hsi, to):
        if data.gaps:
            print(f"teleop-rt: warning: {data.path}: {gap_text(*_gaps(data))}", file=sys.stderr)
        if data.truncated:
            print(f"teleop-rt: warning: {data.path}: {data.cut_reason}", file=sys.stderr)
    return 0


def _gaps(data: LogData) -> tuple[list, int]:
    return [list(g) for g in data.gaps], data.missing_ticks
