"""A log as a figure: joint angles and torques of HSI (dashed) and TO (solid), as the paper's
Fig 6, both tools' paths in the plane with the environment drawn (walls, foam, springs, the
mass at rest), and the channel energy. matplotlib without pyplot (no display); the format
comes from the output's extension (``teleop_rt.output``).

The two site logs of one session (``plot HSI.mcap TO.mcap``) are drawn as one session's log,
paired by tick as ``metrics`` pairs them (``teleop_rt.recording.pair.paired_log``). A replay's
plot (``replay --plot``) draws the original run under it: the same colours and dashes, wide
and faint.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from teleop_rt.errors import TeleopError
from teleop_rt.output import check_output, save_figure
from teleop_rt.recording.metrics import compared
from teleop_rt.recording.reader import (
    LogData,
    LogError,
    check_window,
    read_log,
    require_ticks,
)

TOPICS = ("/hsi", "/to", "/channel")
MAX_POINTS = 20_000  # per line; longer signals are drawn as their min / max envelope
PATH_POINTS = 4_000  # tool path samples (forward kinematics per sample)
HSI_STYLE: dict[str, Any] = {"ls": "--", "color": "C0"}
TO_STYLE: dict[str, Any] = {"ls": "-", "color": "C1"}
ENV_COLORS = {"wall": "0.35", "foam": "C8", "spring": "C2", "damper": "C2", "mass": "C5"}
ORIGINAL_STYLE: dict[str, Any] = {"lw": 4.0, "alpha": 0.3}  # a replay's original run, under it


def _faint(style: dict[str, str]) -> dict[str, Any]:
    """``style`` as the original run of a replay is drawn."""
    return {**style, **ORIGINAL_STYLE}


def make_figure(data: LogData, title: str | None = None, original: LogData | None = None) -> Figure:
    """Rows: one per joint (angles left, torques middle), the tool paths to the right of them,
    the channel energy below (left out when it is zero throughout, as without delay).
    ``original``: the run ``data`` replays, drawn under it (``ORIGINAL_STYLE``)."""
    hsi, to, channel = (data.topics[name] for name in TOPICS)
    n = data.layout.n
    energy = channel["total_energy"]
    show_energy = _nonzero(energy) or (original is not None and _nonzero(
        original.topics["/channel"]["total_energy"]))  # fmt: skip
    paths, why_no_path = tool_paths(data)
    cols = 3 if paths is not None else 2
    height = 2.0 * n + (1.5 if show_energy else 0.0) + 1.2
    fig = Figure(figsize=(16 if cols == 3 else 11, max(height, 5.0)), layout="constrained")
    ratios = [1.0] * n + ([0.75] if show_energy else [])
    grid = fig.add_gridspec(len(ratios), cols, height_ratios=ratios)
    t = hsi["t"]
    if original is not None and _robots(original) != _robots(data):
        original = None  # not the same robots: nothing to draw under (replays keep them)
    # what T_p and T_tau compare: per joint, or a mapped log's mapped series (the tools' x, y)
    q_h, q_t, tau_h, tau_e = compared(data)
    q_label, tau_label = ("mapped q{}", "mapped tau{}") if data.layout.mapped else (
        "q{} (rad)", "tau{} (N m)")  # fmt: skip
    for j in range(n):
        ax = fig.add_subplot(grid[j, 0])
        ax_tau = fig.add_subplot(grid[j, 1])
        if original is not None:
            _draw_original(ax, ax_tau, original, j)
        # TO first: the dashed HSI line stays visible where the two coincide
        ax.plot(*_envelope(t, q_t[:, j]), **TO_STYLE, label="TO q_t")
        ax.plot(*_envelope(t, q_h[:, j]), **HSI_STYLE, label="HSI q_h")
        ax.set_ylabel(q_label.format(j + 1))
        ax = ax_tau
        ax.plot(*_envelope(t, tau_e[:, j]), **TO_STYLE, label="TO tau_e")
        ax.plot(*_envelope(t, tau_h[:, j]), **HSI_STYLE, label="HSI tau_h")
        ax.set_ylabel(tau_label.format(j + 1))
    for ax in fig.axes[-2:]:
        ax.set_xlabel("t (s)")
    handles = [
        Line2D([], [], **HSI_STYLE, label="HSI (q_h, tau_h)"),
        Line2D([], [], **TO_STYLE, label="TO (q_t, tau_e)"),
    ]
    if original is not None:
        handles += [
            Line2D([], [], **_faint(HSI_STYLE), label="HSI, original run"),
            Line2D([], [], **_faint(TO_STYLE), label="TO, original run"),
        ]
    if paths is not None:
        handles += _draw_paths(fig.add_subplot(grid[:, 2]), paths)
    if show_energy:
        ax = fig.add_subplot(grid[n, :2])
        if original is not None:
            was = original.topics["/channel"]
            ax.plot(*_envelope(was["t"], was["total_energy"]), **_faint({"color": "C2"}))
        ax.plot(*_envelope(channel["t"], energy), "-", color="C2")
        ax.set_ylabel("channel energy (J)")
        ax.set_xlabel("t (s)")
    for ax in fig.axes:
        ax.grid(True, alpha=0.3)
    # one legend outside the axes: it covers no data
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 6))
    if title is None:
        title = default_title(data, show_energy, why_no_path)
    fig.suptitle(title)
    return fig


def _robots(data: LogData) -> tuple:
    """What a log's robot rows are: the channel's size, each robot's joints, mapped or not."""
    lay = data.layout
    return lay.n, lay.joints_hsi, lay.joints_to, lay.mapped


def _nonzero(energy: np.ndarray) -> bool:
    return bool(np.any(energy[~np.isnan(energy)] != 0))


def _draw_original(ax_q, ax_tau, original: LogData, j: int) -> None:
    """Joint ``j`` of the run a replay replays, wide and faint, under the replay's lines."""
    q_h, q_t, tau_h, tau_e = compared(original)
    t = original.topics["/hsi"]["t"]
    for q, tau, style in ((q_t, tau_e, TO_STYLE), (q_h, tau_h, HSI_STYLE)):
        ax_q.plot(*_envelope(t, q[:, j]), **_faint(style))
        ax_tau.plot(*_envelope(t, tau[:, j]), **_faint(style))


def default_title(data: LogData, show_energy: bool = True, why_no_path: str | None = None) -> str:
    """What the log is: name, ticks, delay in ms, the window, replay and overrides, notes."""
    meta = data.meta
    lines = [f"{meta.get('name', data.path.stem)}: {data.ticks} ticks"]
    delay = meta.get("delay_ticks")
    if delay is not None:
        lines[0] += f", delay {int(delay) * 1000 / data.rate_hz:g} ms"
    if data.ticks:
        t = data.topics["/hsi"]["t"]
        lines[0] += f", t = {t[0]:.3f} to {t[-1] + data.dt:.3f} s"
    if data.truncated:
        lines[0] += " (log cut short)"
    overrides = _overrides(meta)
    if "replay_of" in meta:
        backend = meta.get("replay_of_backend", "sim")
        via = "" if backend == "sim" else f" (recorded on {backend}, replayed on sim)"
        lines.append(f"replay of {meta['replay_of']}{via}; " + (overrides or "no overrides"))
    elif overrides:
        lines.append(overrides)
    if "paired_with" in meta:
        lines.append(f"two site logs paired by tick: {data.path.name} and {meta['paired_with']}")
    notes = [] if show_energy else ["channel energy 0 throughout (not drawn)"]
    if why_no_path:
        notes.append(f"no tool path: {why_no_path}")
    if notes:
        lines.append("; ".join(notes))
    return "\n".join(lines)


def _overrides(meta: dict[str, str]) -> str:
    try:
        items = json.loads(meta.get("overrides", "[]"))
    except ValueError:
        return ""
    return ("--set " + ", ".join(map(str, items))) if items else ""


# --- tool paths in the plane -----------------------------------------------------------------
def tool_paths(data: LogData) -> tuple[dict | None, str | None]:
    """Tool positions of both robots (forward kinematics of the logged angles, with the URDFs
    attached to the log) and the environment; (None, why) when the log does not allow it."""
    if not data.ticks:
        return None, "no ticks"
    from teleop_rt.model import RobotModel
    from teleop_rt.recording.replay import replay_config

    try:
        cfg = replay_config(data, [])
        models = {t: RobotModel.from_spec(getattr(cfg, t[1:]).robot, t[1:]) for t in TOPICS[:2]}
    except TeleopError as err:
        return None, str(err)
    joints = {"/hsi": data.layout.joints_hsi, "/to": data.layout.joints_to}
    for topic, model in models.items():
        if model.model.nq != joints[topic]:
            nq, n = model.model.nq, joints[topic]
            return None, f"the attached {topic[1:]} robot has {nq} joints, not {n}"
    stride = max(1, -(-data.ticks // PATH_POINTS))
    xyz = {}
    for topic, model in models.items():
        q = data.topics[topic]["q"][::stride]
        xyz[topic] = np.array([model.ee_position(qk) for qk in q])
    # a channel in the plane couples the tools' x, y: drawn there, whatever else drifts
    return {"xyz": xyz, "environment": cfg.environment, "plane": cfg.channel.space == "plane"}, None


def _plane(points: np.ndarray) -> tuple[int, int]:
    """The two world axes the tools move along most (x, y for a planar SCARA)."""
    spread = np.ptp(points, axis=0)
    if not np.any(spread > 1e-9):
        return 0, 1
    a, b = sorted(np.argsort(spread)[-2:])
    return int(a), int(b)


def _draw_paths(ax, paths: dict) -> list:
    xyz = paths["xyz"]
    points = np.vstack(list(xyz.values()))
    a, b = (0, 1) if paths.get("plane") else _plane(points)
    names = "xyz"
    ax.plot(xyz["/to"][:, a], xyz["/to"][:, b], **TO_STYLE)
    ax.plot(xyz["/hsi"][:, a], xyz["/hsi"][:, b], **HSI_STYLE)
    ax.plot(*xyz["/hsi"][0, [a, b]], "o", color="k", ms=4)
    ax.set_xlabel(f"{names[a]} (m)")
    ax.set_ylabel(f"{names[b]} (m)")
    ax.set_title("tool paths (o: start)", fontsize="medium")
    handles = []
    elements = [e for e in paths["environment"] if _in_plane(e, a, b)]
    flat = points[:, [a, b]]
    center = 0.5 * (flat.min(axis=0) + flat.max(axis=0))
    # each surface where it passes closest to the paths (its point_m may be anywhere on it)
    feet = [_foot(center, e, a, b) for e in elements]
    span = np.vstack([flat, *feet]) if feet else flat
    lo, hi = span.min(axis=0), span.max(axis=0)
    margin = 0.15 * max(float(np.max(hi - lo)), 0.02)
    lo, hi = lo - margin, hi + margin
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_autoscale_on(False)  # the environment's large patches must not move the limits
    ax.set_aspect("equal", adjustable="box")
    size = 10.0 * float(np.max(hi - lo))
    seen = set()
    for e in elements:
        label = _env_label(e)
        color = ENV_COLORS.get(e.kind, "0.5")
        p = np.array([_axis(e.point_m, a), _axis(e.point_m, b)])
        normal = np.array([_axis(e.normal, a), _axis(e.normal, b)])
        normal /= np.linalg.norm(normal)
        along = np.array([-normal[1], normal[0]]) * size
        ax.plot(*np.column_stack([p - along, p + along]), color=color, lw=2)
        if e.kind in ("wall", "foam"):  # the material side: opposite the normal
            inside = -normal * size
            corners = np.array([p - along, p + along, p + along + inside, p - along + inside])
            ax.fill(corners[:, 0], corners[:, 1], color=color, alpha=0.25, lw=0)
        if label not in seen:
            seen.add(label)
            handles.append(Patch(color=color, alpha=0.6, label=label))
    return handles


def _foot(center: np.ndarray, element, a: int, b: int) -> np.ndarray:
    """The point of the element's surface line nearest to ``center`` (drawing plane)."""
    p = np.array([_axis(element.point_m, a), _axis(element.point_m, b)])
    normal = np.array([_axis(element.normal, a), _axis(element.normal, b)])
    normal /= np.linalg.norm(normal)
    return center - np.dot(center - p, normal) * normal


def _axis(v: list[float], i: int) -> float:
    return float(v[i]) if i < len(v) else 0.0


def _in_plane(element, a: int, b: int) -> bool:
    """Whether the element's surface crosses the drawing plane as a line."""
    return float(np.hypot(_axis(element.normal, a), _axis(element.normal, b))) > 1e-9


def _env_label(e) -> str:
    if e.kind in ("wall", "foam"):
        return f"{e.kind} {e.stiffness_n_per_m:g} N/m"
    if e.kind == "mass":
        return f"mass {e.mass_kg:g} kg (at rest)"
    return f"{e.kind} {e.stiffness_n_per_m:g} N/m, {e.damping_n_s_per_m:g} N s/m"


def _envelope(t: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At most MAX_POINTS points keeping every bucket's min and max (spikes stay visible)."""
    if len(y) <= MAX_POINTS:
        return t, y
    starts = np.arange(0, len(y), -(-len(y) // (MAX_POINTS // 2)))
    low, high = np.minimum.reduceat(y, starts), np.maximum.reduceat(y, starts)
    return np.repeat(t[starts], 2), np.column_stack((low, high)).reshape(-1)


def plot_log(
    data: LogData,
    out: str | Path,
    title: str | None = None,
    force: bool = False,
    option: str = "-o",
    original: LogData | None = None,
) -> Path:
    """Draw the log to ``out`` (format by its extension), ``original`` under it (a replay's);
    an existing file only with ``force``, and never a log drawn. Return the path."""
    inputs = (data.path,) if original is None else (data.path, original.path)
    check_output(out, option, force=force, image=True, inputs=inputs)
    return save_figure(make_figure(data, title, original), out, option, force)


def plot_main(
    path: str | Path,
    out: str | Path | None = None,
    force: bool = False,
    t_from: float | None = None,
    t_to: float | None = None,
    partner: str | Path | None = None,
) -> int:
    """``teleop-rt plot LOG [TO_LOG] [-o OUT] [--force] [--from S] [--to S]`` (default output:
    the (first) log's path with .png); ``partner``: the other site's log of a site log, the
    two drawn as one session's; exit code."""
    check_window(t_from, t_to)
    target = Path(path).with_suffix(".png") if out is None else Path(out)
    inputs = (path,) if partner is None else (path, partner)
    check_output(target, "-o", force=force, image=True, inputs=inputs)  # before reading
    if partner is not None:
        from teleop_rt.recording.pair import paired_log, read_pair

        data = paired_log(*read_pair(path, partner, "plot"), t_from, t_to)
    else:
        data = read_log(path, None, t_from, t_to)  # a session's, or a site's (refused)
        if data.site:
            raise LogError(
                f"{data.path} is the {data.site} site's log, one robot: plot it with its "
                "partner's (teleop-rt plot HSI.mcap TO.mcap)"
            )
    if not data.ticks:  # an empty figure is no plot; the same line as metrics
        from teleop_rt.recording.metrics import empty_window

        if t_from is not None or t_to is not None:
            raise empty_window(data, t_from, t_to)
        require_ticks(data)
    plot_log(data, target, force=force)
    if data.truncated:
        print(f"teleop-rt: warning: {data.path}: {data.cut_reason}", file=sys.stderr)
    print(f"wrote {target}")
    return 0
