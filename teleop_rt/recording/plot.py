"""A log as a figure: joint angles and torques of HSI (dashed) and TO (solid), as the paper's
Fig 6, and the channel energy. Uses matplotlib's Agg canvas directly (no pyplot, no display).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from teleop_rt.recording.reader import LogData, LogError, read_log, require_ticks

TOPICS = ("/hsi", "/to", "/channel")
MAX_POINTS = 20_000  # per line; longer signals are drawn as their min / max envelope


def make_figure(data: LogData, title: str | None = None) -> Figure:
    """Rows: one per joint (angles left, torques right), then the channel energy."""
    hsi, to, channel = (data.topics[name] for name in TOPICS)
    n = data.layout.n
    fig = Figure(figsize=(11, 2.0 * (n + 1) + 0.6), layout="constrained")
    grid = fig.add_gridspec(n + 1, 2)
    t = hsi["t"]
    for j in range(n):
        ax = fig.add_subplot(grid[j, 0])
        # TO first: the dashed HSI line stays visible where the two coincide
        ax.plot(*_envelope(t, to["q"][:, j]), "-", color="C1", label="TO")
        ax.plot(*_envelope(t, hsi["q"][:, j]), "--", color="C0", label="HSI")
        ax.set_ylabel(f"q{j + 1} (rad)")
        ax = fig.add_subplot(grid[j, 1])
        ax.plot(*_envelope(t, -to["tau_ext"][:, j]), "-", color="C1", label="TO tau_e")
        ax.plot(*_envelope(t, hsi["tau_ext"][:, j]), "--", color="C0", label="HSI tau_h")
        ax.set_ylabel(f"tau{j + 1} (N m)")
    ax = fig.add_subplot(grid[n, :])
    ax.plot(*_envelope(channel["t"], channel["total_energy"]), "-", color="C2")
    ax.set_ylabel("channel energy (J)")
    ax.set_xlabel("t (s)")
    for ax in fig.axes[:2]:
        ax.legend(loc="upper right", fontsize="small")
    for ax in fig.axes:
        ax.grid(True, alpha=0.3)
    if title is None:
        title = f"{data.meta.get('name', data.path.stem)}: {data.ticks} ticks, delay "
        title += f"{data.meta.get('delay_ticks', '?')} ticks"
        if data.truncated:
            title += " (log cut short)"
    fig.suptitle(title)
    return fig


def _envelope(t: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At most MAX_POINTS points keeping every bucket's min and max (spikes stay visible)."""
    if len(y) <= MAX_POINTS:
        return t, y
    starts = np.arange(0, len(y), -(-len(y) // (MAX_POINTS // 2)))
    low, high = np.minimum.reduceat(y, starts), np.maximum.reduceat(y, starts)
    return np.repeat(t[starts], 2), np.column_stack((low, high)).reshape(-1)


def plot_log(data: LogData, out_png: str | Path, title: str | None = None) -> Path:
    """Draw the log to a new PNG (an existing file, the log itself above all, is never
    overwritten); return its path."""
    out = Path(out_png)
    fig = make_figure(data, title)
    try:
        with open(out, "xb") as stream:
            FigureCanvasAgg(fig).print_png(stream)
    except FileExistsError:
        raise LogError(f"{out}: the file exists; choose another output path") from None
    except OSError as err:
        raise LogError(f"{out}: cannot write the plot ({err.strerror})") from None
    return out


def plot_main(path: str | Path, out: str | Path | None = None) -> int:
    """``teleop-rt plot LOG [-o OUT.png]`` (default: the log's path with .png); exit code."""
    data = read_log(path, TOPICS)
    require_ticks(data)  # an empty figure is no plot
    target = plot_log(data, Path(path).with_suffix(".png") if out is None else out)
    if data.truncated:
        print(f"teleop-rt: warning: {data.path}: {data.cut_reason}", file=sys.stderr)
    print(f"wrote {target}")
    return 0
