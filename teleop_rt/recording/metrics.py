"""The live session summary's numbers, recomputed from a log alone.

T_p and T_tau (eq 18) go through the live TransparencyAccumulator itself, tick after tick, so
a whole log gives the live figures bit for bit. Timing goes through ``TimingStats.summary``
itself.

Windows (``t_from <= t < t_to``) keep the offset of the session start (q_h - q_t at tick 0):
alpha in eq 18 is the angle moved since the start of the session, not of the window. The
window's channel energy is its last value and its minimum is taken with 0.0 as the live one.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from teleop_rt.analysis.transparency import add_series, transparency_labels
from teleop_rt.loop import TimingStats, format_percentiles
from teleop_rt.recording.reader import LogData, LogError, check_window, read_log, require_ticks
from teleop_rt.transparency_tick import TransparencyAccumulator

TOPICS = ("/hsi", "/to", "/channel", "/timing")
_COMPARED = ("ticks", "t_p", "t_tau", "channel_energy_j", "min_channel_energy_j")


def log_metrics(data: LogData, offset: np.ndarray | None = None) -> dict:
    """Summary figures of the ticks in ``data`` (all four topics read).

    ``offset``: q_h - q_t at the session start; default the first tick in ``data``.
    """
    hsi, to, channel, timing = (data.topics[name] for name in TOPICS)
    n, dt = len(hsi), data.dt
    t_p, t_tau = transparency_sums(*compared(data), dt, offset)
    energy = channel["total_energy"]
    finite = energy[~np.isnan(energy)]
    return {
        "name": data.meta.get("name", ""),
        "space": data.channel_space(),
        "ticks": n,
        "simulated_time_s": n * dt,
        "delay_ticks": int(data.meta.get("delay_ticks", 0)),
        "t_p": t_p,
        "t_tau": t_tau,
        "t_p_total": float(sum(t_p)),
        "t_tau_total": float(sum(t_tau)),
        "channel_energy_j": float(energy[-1]) if n else 0.0,
        "min_channel_energy_j": min(0.0, float(finite.min())) if len(finite) else 0.0,
        "timing": _timing(timing, int(round(dt * 1e9))),
        "first_tick": int(hsi["tick"][0]) if n else None,
        "gaps": [list(g) for g in data.gaps],
        "missing_ticks": data.missing_ticks,
        "truncated": data.truncated,
        "cut_reason": data.cut_reason,
    }


def compared(data: LogData) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """q_h, q_t, tau_h, tau_e as the session's metrics take them: the robots' own (tau_e the
    torque the TO applies to the environment), or a mapped log's mapped ones (in the plane the
    tools' positions and forces: ``LogLayout.mapped``)."""
    hsi, to = data.topics["/hsi"], data.topics["/to"]
    if data.layout.mapped:
        return hsi["q_mapped"], to["q_mapped"], hsi["tau_mapped"], to["tau_mapped"]
    return hsi["q"], to["q"], hsi["tau_ext"], -to["tau_ext"]


def transparency_sums(
    q_h: np.ndarray,
    q_t: np.ndarray,
    tau_h: np.ndarray,
    tau_e: np.ndarray,
    dt: float,
    offset: np.ndarray | None = None,
) -> tuple[list[float], list[float]]:
    """T_p and T_tau per joint (eq 18) of aligned (ticks, joints) series, by the live
    accumulator; ``offset``: q_h - q_t at the session start (default: the first row's). The one
    function for a session's log, two sites' logs and their tick records."""
    acc = TransparencyAccumulator(q_h.shape[1], dt, None if offset is None else list(offset))
    add_series(acc, q_h, q_t, tau_h, tau_e)
    return acc.t_p.tolist(), acc.t_tau.tolist()


def _timing(timing: np.ndarray, period_ns: int) -> dict:
    stats = TimingStats(0, period_ns)
    stats.compute_ns = timing["compute_ns"].astype(np.int64)
    stats.lateness_ns = timing["lateness_ns"].astype(np.int64)
    stats.count = len(timing)
    stats.missed = int(np.count_nonzero(timing["missed"]))
    return stats.summary()


def agrees_with_live(metrics: dict, summary: dict | None) -> bool | None:
    """Whether a whole log's figures equal its live summary exactly (None: nothing to compare,
    as for a log with gaps, whose figures cover the recorded ticks only)."""
    if summary is None or metrics["first_tick"] not in (0, None) or metrics["gaps"]:
        return None
    same = all(metrics[key] == summary.get(key) for key in _COMPARED)
    live = summary.get("timing", {})
    return same and all(metrics["timing"][k] == live.get(k) for k in metrics["timing"])


def session_offset(path: str | Path, dt: float) -> np.ndarray | None:
    """q_h - q_t of the log's first tick (tick 0 at time 0), None if the log has none."""
    first = read_log(path, ("/hsi", "/to"), None, dt)
    if not first.ticks:
        return None
    q_h, q_t = compared(first)[:2]
    return q_h[0] - q_t[0]


def format_metrics(m: dict) -> str:
    """Plain-text table of ``log_metrics`` (plus ``window_s`` / ``live_summary_agrees``)."""

    def row(what: str, value: str) -> tuple[str, str]:
        return what, value

    def vec(values: list[float]) -> str:
        return "  ".join(f"{v:.6g}" for v in values)

    t = m["timing"]
    t_p_label, t_tau_label = transparency_labels(m.get("space", "joint"))
    lines = [
        row("session", f"{m['name']} (delay {m['delay_ticks']} ticks)"),
        row("ticks", f"{m['ticks']} ({m['simulated_time_s']:.3f} s)"),
    ]
    if m.get("window_s"):
        lo, hi = m["window_s"]
        end = "the end" if hi is None else f"{hi:g}"
        lines.append(row("window (s)", f"{0.0 if lo is None else lo:g} to {end}"))
    lines += [
        row(t_p_label, vec(m["t_p"])),
        row("T_p total", f"{m['t_p_total']:.6g}"),
        row(t_tau_label, vec(m["t_tau"])),
        row("T_tau total", f"{m['t_tau_total']:.6g}"),
        row(
            "channel energy (J)",
            f"{m['channel_energy_j']:.6g} (minimum {m['min_channel_energy_j']:.6g})",
        ),
    ]
    for key, what in (("compute_us", "tick compute (us)"), ("lateness_us", "lateness (us)")):
        s = t[key]
        lines.append(row(what, format_percentiles(s)))
    lines.append(row("missed deadlines", str(t["missed_deadlines"])))
    lines.append(row("ticks started over a period late", str(t["late_over_period"])))
    agrees = m.get("live_summary_agrees")
    if agrees is not None:
        lines.append(row("live summary", "agrees exactly" if agrees else "DIFFERS from the log"))
    if m["gaps"]:
        lines.append(row("log gaps", gap_text(m["gaps"], m["missing_ticks"])))
    if m["truncated"]:
        lines.append(row("log cut short", m["cut_reason"] or ""))
    width = max(len(what) for what, _ in lines) + 2  # the longest label still gets a gap
    return "\n".join(f"{what:<{width}}{value}" for what, value in lines)


def gap_text(gaps: list, missing: int) -> str:
    """'N ticks missing in M ranges (a-b, ...)': the figures cover the recorded ticks only."""
    shown = ", ".join(f"{a}-{b}" for a, b in gaps[:3]) + (", ..." if len(gaps) > 3 else "")
    return f"{missing} ticks missing in {len(gaps)} range(s) ({shown}); figures of the rest"


def empty_window(data: LogData, t_from: float | None, t_to: float | None) -> LogError:
    """The error of a window without ticks, saying where the log's ticks are (metrics and plot
    say the same)."""
    lo, hi = f"{t_from or 0.0:g} s", "the end" if t_to is None else f"{t_to:g} s"
    ticks = read_log(data.path, ("/timing",)).topics["/timing"]["tick"]
    if len(ticks):
        where = f"the log's ticks run from {data.dt * ticks[0]:g} to {data.dt * ticks[-1]:g} s"
    else:
        where = "the log holds no ticks at all" + (f": {data.cut_reason}" if data.truncated else "")
    return LogError(f"{data.path}: the window {lo} to {hi} holds no ticks ({where})")


def metrics_main(
    path: str | Path, as_json: bool = False, t_from: float | None = None, t_to: float | None = None
) -> int:
    """``teleop-rt metrics LOG [--json] [--from S] [--to S]``: print the figures; exit code."""
    check_window(t_from, t_to)
    data = read_log(path, TOPICS, t_from, t_to)
    if not data.ticks and (t_from is not None or t_to is not None):
        raise empty_window(data, t_from, t_to)
    require_ticks(data)
    offset = None
    if data.ticks and int(data.topics["/hsi"]["tick"][0]) != 0:
        offset = session_offset(path, data.dt)
    m = log_metrics(data, offset)
    m["window_s"] = None if t_from is None and t_to is None else [t_from, t_to]
    m["live_summary_agrees"] = None if m["window_s"] else agrees_with_live(m, data.summary)
    if as_json:
        json.dump(m, sys.stdout, indent=2)
        print()
    else:
        print(format_metrics(m))
    if data.gaps:
        print(f"teleop-rt: warning: {data.path}: {gap_text(m['gaps'], m['missing_ticks'])}",
              file=sys.stderr)  # fmt: skip
    if data.truncated:
        print(f"teleop-rt: warning: {data.path}: {data.cut_reason}", file=sys.stderr)
    return 0
