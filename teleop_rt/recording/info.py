"""``teleop-rt info LOG [--json]``: what a log holds, like ``ros2 bag info``.

Start time, duration, ticks, topics with their message counts, the session (config name, the
command line's config path and overrides, backends, operator, environment), whether the file is
complete, cut short or was never finished, and the live summary's headline figures. A file
that is not a readable teleop_rt log is one line and exit code 2 (``LogError``).
"""

from __future__ import annotations

import datetime as _dt
import json
import sys
from pathlib import Path

from teleop_rt.recording.reader import LogData, read_log


def log_info(data: LogData) -> dict:
    """Everything ``info`` reports, as plain JSON-able values."""
    meta = data.meta
    ticks = data.ticks
    first = int(data.topics[data.layout.topics[0].name]["tick"][0]) if ticks else None
    cfg = _config(data)
    return {
        "path": str(data.path),
        "size_bytes": data.path.stat().st_size,
        "profile": data.profile,
        "library": data.library,
        "software_version": meta.get("software_version"),
        "start_time_utc": meta.get("start_time_utc") or _utc(data.start_ns),
        "start_time_ns": data.start_ns,
        "rate_hz": data.rate_hz,
        "ticks": ticks,
        "first_tick": first,
        "duration_s": ticks * data.dt,
        "delay_ms": int(meta.get("delay_ticks", 0)) * 1000 / data.rate_hz,
        "topics": [
            {"topic": t.name, "type": t.type_name, "messages": data.message_counts.get(t.name, 0)}
            for t in data.layout.topics
        ]
        + [
            {"topic": name, "type": kind, "messages": count}
            for name, (kind, count) in data.other_topics.items()
        ],
        "name": meta.get("name"),
        "site": data.site or None,  # a site's own log: which, and its session
        "session_id": meta.get("session_id"),
        "config": meta.get("config"),
        "overrides": _json_list(meta.get("overrides")),
        "replay_of": meta.get("replay_of"),
        "backends": _backends(meta, cfg),
        "operator": meta.get("operator"),
        "environment": [e.get("kind") for e in (cfg or {}).get("environment", [])],
        "status": _status(data),
        "cut_reason": _loss(data),
        "missing_ticks": data.missing_ticks,
        "gaps": [list(g) for g in data.gaps],
        "summary": _headline(data.summary),
    }


def _config(data: LogData) -> dict | None:
    if not data.config_yaml:
        return None
    import yaml

    try:
        raw = yaml.safe_load(data.config_yaml)
    except yaml.YAMLError:
        return None
    return raw if isinstance(raw, dict) else None


def _utc(ns: int) -> str | None:
    if not ns:
        return None  # a log from before log times were wall-clock
    seconds, rest = divmod(ns, 1_000_000_000)
    t = _dt.datetime.fromtimestamp(seconds, _dt.timezone.utc)
    t += _dt.timedelta(microseconds=rest // 1000)
    return t.isoformat(timespec="microseconds").replace("+00:00", "Z")


def _json_list(text: str | None) -> list[str]:
    try:
        value = json.loads(text) if text else []
    except ValueError:
        return [str(text)]
    return [str(x) for x in value] if isinstance(value, list) else [str(value)]


def _backends(meta: dict[str, str], cfg: dict | None) -> dict[str, str]:
    """Per robot: the backend and, on CAN, the bus (or the in-process emulator)."""
    backend = meta.get("backend", "?")
    out = {}
    can = (cfg or {}).get("can") or {}
    for side in ("hsi", "to"):
        if backend != "can":
            out[side] = backend
        elif can.get("emulate"):
            out[side] = "can (emulated drives, in process)"
        else:
            bus = (can.get(side) or {}).get("bus") or {}
            where = " ".join(str(bus[k]) for k in ("interface", "channel") if bus.get(k))
            out[side] = f"can ({where})" if where else "can"
    return out


def _status(data: LogData) -> str:
    if data.truncated:
        if data.footer and data.summary is None:
            return "incomplete"  # finished by the writer; the session never handed its summary
        return "cut short"
    recording = (data.summary or {}).get("recording") or {}
    if data.gaps or recording.get("complete") is False:
        return "incomplete"  # ticks the session ran are missing (``_loss`` says which)
    if not data.ticks:
        return "never started"
    return "complete"


def _loss(data: LogData) -> str | None:
    """What a finished log lacks, or why it holds no tick, in words (None: nothing)."""
    summary = data.summary or {}
    recording = summary.get("recording") or {}
    dropped = recording.get("dropped_rows")
    missing = dropped if isinstance(dropped, int) and dropped else data.missing_ticks
    if data.truncated:
        return data.cut_reason
    if data.gaps or recording.get("complete") is False:
        gaps = ", ".join(f"{a}-{b}" for a, b in data.gaps[:5]) + (" ..." * (len(data.gaps) > 5))
        why = recording.get("failure")
        return (f"{missing} ticks dropped" + (f" (ticks {gaps})" if gaps else "")
                + (f": {why}" if why else ""))  # fmt: skip
    if not data.ticks:
        return f"0 ticks: {summary.get('stopped_early') or 'the run ended before its first tick'}"
    return None


def _headline(summary: dict | None) -> dict | None:
    if summary is None:
        return None
    timing = summary.get("timing", {})
    keys = ("t_p_total", "t_tau_total", "channel_energy_j", "min_channel_energy_j", "realtime",
            "port_energy_j")  # fmt: skip
    out = {k: summary.get(k) for k in keys}
    link = summary.get("link")
    if isinstance(link, dict) and isinstance(link.get("from_peer"), dict):  # a site's
        peer = link["from_peer"]
        from_peer = {k: peer.get(k) for k in ("received", "used", "lost", "late")}
        if "silent_ticks" in peer:  # the peer's codec: ticks with no packet, not losses
            from_peer["silent_ticks"] = peer["silent_ticks"]
        out["from_peer"] = from_peer
    out.update(
        missed_deadlines=timing.get("missed_deadlines"),
        late_over_period=timing.get("late_over_period"),
        wall_s=timing.get("wall_s"),
        stopped_early=summary.get("stopped_early"),
        safety_stop=summary.get("safety_stop"),
    )
    return out


def format_info(info: dict) -> str:
    """The plain-text report (aligned, no colours: it is read piped as often as not)."""
    rows: list[tuple[str, str]] = [
        ("file", f"{info['path']} ({_size(info['size_bytes'])})"),
        ("status", info["status"] + (f": {info['cut_reason']}" if info["cut_reason"] else "")),
        ("written by", f"teleop_rt {info['software_version'] or '?'} ({info['library']})"),
        ("profile", info["profile"] or "none"),
        ("start", info["start_time_utc"] or "unknown (log times start at 0)"),
        ("duration", f"{info['duration_s']:.3f} s"),
        ("ticks", f"{info['ticks']} at {info['rate_hz']:g} Hz" + _first(info["first_tick"])),
        ("session", f"{info['name']}, delay {info['delay_ms']:g} ms"),
    ]
    if info["site"]:
        rows.append(("site", f"{info['site']} (session {info['session_id'] or '?'})"))
    if info["config"]:
        rows.append(("config", info["config"]))
    if info["replay_of"]:
        rows.append(("replay of", info["replay_of"]))
    rows.append(("overrides", "  ".join(f"--set {o}" for o in info["overrides"]) or "none"))
    backends = info["backends"]
    same = len(set(backends.values())) == 1
    rows.append(
        (
            "backend",
            next(iter(backends.values()))
            if same
            else ", ".join(f"{k}: {v}" for k, v in backends.items()),
        )
    )
    rows.append(("operator", str(info["operator"])))
    rows.append(("environment", ", ".join(info["environment"]) or "free space"))
    for i, t in enumerate(info["topics"]):
        line = f"{t['topic']:<19} {t['messages']:>9} msgs  {t['type']}"
        rows.append(("topics" if i == 0 else "", line))
    s = info["summary"]
    if s is None:
        rows.append(("summary", "none"))
    elif info["site"]:
        peer = s.get("from_peer") or {}
        rows += [
            ("port energy (J)", _g(s["port_energy_j"])),
            ("peer's packets", ", ".join(f"{k} {peer.get(k)}" for k in peer) or "?"),
            ("mode", "real time" if s["realtime"] else "fast"),
            (
                "missed deadlines",
                f"{s['missed_deadlines']} (a period late: {s['late_over_period']})",
            ),
            ("stopped early", s["stopped_early"] or "no"),
        ]
    else:
        rows += [
            ("T_p total (rad^2 s)", _g(s["t_p_total"])),
            ("T_tau total (N^2 m^2 s)", _g(s["t_tau_total"])),
            (
                "channel energy (J)",
                f"{_g(s['channel_energy_j'])} (minimum {_g(s['min_channel_energy_j'])})",
            ),
            ("mode", "real time" if s["realtime"] else "fast"),
            (
                "missed deadlines",
                f"{s['missed_deadlines']} (a period late: {s['late_over_period']})",
            ),
            ("stopped early", s["stopped_early"] or "no"),
        ]
    width = max(len(k) for k, _ in rows) + 2
    return "\n".join(f"{k:<{width}}{v}" for k, v in rows)


def _g(x) -> str:
    return "?" if x is None else f"{x:.6g}"


def _first(first: int | None) -> str:
    return "" if first in (0, None) else f" (from tick {first})"


def _size(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return ""


def info_main(path: str | Path, as_json: bool = False) -> int:
    """``teleop-rt info LOG [--json]``; exit code."""
    info = log_info(read_log(path))
    if as_json:
        json.dump(info, sys.stdout, indent=2)
        print()
    else:
        print(format_info(info))
    return 0
