#!/usr/bin/env python3
"""The channels over an impaired network: a study like the paper's (issue 17).

    python tools/network_study.py [--quick] [--out DIR]
    python tools/network_study.py --codec [--quick] [--out DIR]   (tools/codec_study.py)

Sweeps the network's one-way delay, its jitter and its loss (the seeded impairment stage of a
one-process fast-mode session, ``link.impairment``) for the paper experiment
(configs/paper_experiment.yaml) and the stiff wall (configs/stiff_wall.yaml), with the wave
channel losing packets to a zero wave, the protected wave channel (the energy-bounded wave
integral), TDPA, and, unprotected, the wave channel holding its last wave and plain delayed
force feedback. Per run: stability (safety stop, divergence, the ports' energy balance and
the two-port's channel energy, what the protection removed and how often it acted), T_p and
T_tau (eq 18), the displayed mass in free space, the wall stiffness the operator feels, the
task time and the drift between the two robots.

Writes DIR/network_study.md and DIR/figures/network_*.png, and prints progress and the
numbers. Without ``--out`` it writes into a new temporary folder, so that no run replaces the
committed report; ``--out docs`` regenerates it (a ``--quick`` run is refused there). DIR is
checked (and created) before any work. ``--quick`` runs a few cases (for the tests).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib import rc_context
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.analysis import experiment  # noqa: E402
from teleop_rt.analysis.discrete import filter_group_delay_s  # noqa: E402
from teleop_rt.output import report_folder_problem, wrap_title  # noqa: E402
from teleop_rt.session import Session  # noqa: E402

CONFIGS = {
    "paper_experiment": ROOT / "configs" / "paper_experiment.yaml",
    "stiff_wall": ROOT / "configs" / "stiff_wall.yaml",
}
TITLES = {"paper_experiment": "the paper experiment", "stiff_wall": "the stiff wall"}
SEED = 1  # the network's seed: every channel of a case meets the same network, packet for packet
TASK_TOL_M = 0.002  # task done: both tools within 2 mm of the final target for good
DIVERGED_RAD = 0.5  # |q_h - q_t| beyond this on a joint: the robots have come apart
BURST_PACKETS = 10  # mean length of a loss burst (Gilbert-Elliott, 1 / r)


@dataclass(frozen=True)
class Channel:
    """One channel kind of the study and its config overrides."""

    key: str
    label: str
    overrides: tuple[str, ...]
    protected: bool


CHANNELS = (
    Channel("zero", "wave, zero wave on loss",
            ("channel.mode=wave", "channel.wave_reconstruction=zero"), True),
    Channel("bounded", "protected wave (bounded)",
            ("channel.mode=wave", "channel.wave_reconstruction=bounded"), True),
    Channel("reflected", "energy-reflecting wave (reflected, the default)",
            ("channel.mode=wave", "channel.wave_reconstruction=reflected"), True),
    Channel("tdpa", "TDPA", ("channel.mode=tdpa",), True),
    Channel("hold", "unprotected wave (hold)",
            ("channel.mode=wave", "channel.wave_reconstruction=hold"), False),
    Channel("direct", "direct force feedback (not passive)", ("channel.mode=direct",), False),
)  # fmt: skip
CHANNEL = {c.key: c for c in CHANNELS}
WAVE_CHANNELS = ("zero", "bounded", "reflected", "hold")


@dataclass(frozen=True)
class Case:
    """One network condition: the impairment and the receivers' playout."""

    sweep: str  # a key of SWEEPS, or "reference"
    value: float  # the swept quantity (ms or %)
    delay_ms: float = 0.0  # the network's mean one-way delay
    jitter_ms: float = 0.0  # its standard deviation (normal)
    correlation_percent: float = 0.0  # of successive delays (0: netem's default)
    loss_percent: float = 0.0
    burst: bool = False  # the loss in bursts (Gilbert-Elliott) rather than independent
    playout: str = "fixed"
    playout_ms: int = 0  # channel.delay_ms: the playout delay D (0: no network at all)

    def overrides(self) -> list[str]:
        sets = [f"channel.delay_ms={self.playout_ms}", f"link.playout={self.playout}"]
        if self.sweep == "reference":
            return sets
        spec = [f"seed: {SEED}", f"delay_ms: {self.delay_ms:g}"]
        if self.jitter_ms:
            spec.append(f"jitter_ms: {self.jitter_ms:g}")
        if self.correlation_percent:
            spec.append(f"correlation_percent: {self.correlation_percent:g}")
        if self.loss_percent and self.burst:
            r = 100.0 / BURST_PACKETS  # bad -> good, %; the rate p / (p + r) is the loss
            p = r * self.loss_percent / (100.0 - self.loss_percent)
            spec.append(f"gilbert_elliott: {{p_percent: {p:.6g}, r_percent: {r:g}}}")
        elif self.loss_percent:
            spec.append(f"loss_percent: {self.loss_percent:g}")
        return [*sets, "link.impairment={" + ", ".join(spec) + "}"]

    @property
    def label(self) -> str:
        if self.sweep == "reference":
            return "no network (D = 0)"
        parts = [f"{self.delay_ms:g} ms"]
        if self.jitter_ms:
            rho = f" (corr. {self.correlation_percent:g} %)" if self.correlation_percent else ""
            parts.append(f"jitter {self.jitter_ms:g} ms{rho}")
        if self.loss_percent:
            parts.append(f"{'burst' if self.burst else ''} loss {self.loss_percent:g} %".strip())
        return ", ".join(parts) + f"; {self.playout} D = {self.playout_ms} ms"

    @property
    def channel_delay_s(self) -> float:
        """The one-way delay the channel sees when every packet arrives (s)."""
        return 1e-3 * (self.playout_ms if self.playout == "fixed" else self.delay_ms)


CORRELATED = 99.0  # percent: successive delays of the correlated jitter sweep (netem's corr.)
# the sweeps: what varies, the fixed rest, and the playout (why: the report's playout section)
SWEEPS = {
    "delay": ("network delay (ms)", "constant delay, fixed playout at D = the delay"),
    "jitter_newest": ("jitter (ms)", "20 ms and jitter, newest playout at D = 1 ms"),
    "jitter_correlated": (
        "jitter (ms)",
        f"20 ms and jitter correlated {CORRELATED:g} %, newest D = 1",
    ),
    "jitter_fixed": ("jitter (ms)", "20 ms and jitter, fixed playout at D = 20 ms + 3 jitter"),
    "loss": ("loss (%)", "20 ms and independent loss, fixed playout at D = 20 ms"),
    "burst": ("loss (%)", f"20 ms and burst loss ({BURST_PACKETS} packets mean), fixed D = 20"),
}
BASE_MS = 20.0  # the network delay of the jitter and loss sweeps


def make_case(sweep: str, value: float) -> Case:
    if sweep == "delay":
        return Case(sweep, value, delay_ms=value, playout_ms=int(value))
    if sweep == "jitter_newest":
        return Case(sweep, value, BASE_MS, jitter_ms=value, playout="newest", playout_ms=1)
    if sweep == "jitter_correlated":
        return Case(sweep, value, BASE_MS, jitter_ms=value, correlation_percent=CORRELATED,
                    playout="newest", playout_ms=1)  # fmt: skip
    if sweep == "jitter_fixed":
        d = int(math.ceil(BASE_MS + 3.0 * value))
        return Case(sweep, value, BASE_MS, jitter_ms=value, playout_ms=d)
    if sweep in ("loss", "burst"):
        return Case(sweep, value, BASE_MS, loss_percent=value, burst=sweep == "burst",
                    playout_ms=int(BASE_MS))  # fmt: skip
    raise ValueError(sweep)


@dataclass(frozen=True)
class Settings:
    """What one run of the script computes (full or quick)."""

    quick: bool
    grid: dict  # config -> sweep -> values
    channels: tuple[str, ...]
    duration_s: dict  # config -> simulated seconds per run
    traces: dict  # config -> (sweep, value): the case whose signals are drawn over time


FULL = Settings(
    quick=False,
    grid={
        name: {
            "delay": (5, 20, 50, 100),
            "jitter_newest": (2, 5, 10),
            "jitter_correlated": (2, 5, 10),
            "jitter_fixed": (2, 5, 10),
            "loss": (1, 5, 20),
            "burst": (5, 20),
        }
        for name in CONFIGS
    },
    channels=tuple(c.key for c in CHANNELS),
    duration_s={"paper_experiment": 15.0, "stiff_wall": 6.0},
    traces={"paper_experiment": ("jitter_newest", 10), "stiff_wall": ("loss", 20)},
)
QUICK = Settings(
    quick=True,
    grid={
        "paper_experiment": {"jitter_newest": (10,)},
        "stiff_wall": {"jitter_newest": (10,), "loss": (20,)},
    },
    channels=("zero", "bounded", "tdpa", "hold"),
    # the paper task's last waypoint is at 11.5 s: a run that ends before it never finishes it
    duration_s={"paper_experiment": 13.0, "stiff_wall": 6.0},
    traces={"paper_experiment": ("jitter_newest", 10), "stiff_wall": ("loss", 20)},
)


def log(msg: str) -> None:
    print(msg, flush=True)


# =============================================================================================
# one run
# =============================================================================================
def run_case(name: str, case: Case, channel: Channel, duration_s: float, keep: bool) -> dict:
    """One session of config ``name`` over the case's network; its figures (and, with
    ``keep``, the signals over time for the traces figure)."""
    cfg = config.load(
        CONFIGS[name], [*channel.overrides, *case.overrides(), f"duration_s={duration_s}"]
    )
    session = Session(cfg)
    n_ticks, n = cfg.n_ticks, session.n
    q_h, q_t, v_h = np.zeros((n_ticks, n)), np.zeros((n_ticks, n)), np.zeros((n_ticks, n))
    tau_h, tau_e = np.zeros((n_ticks, n)), np.zeros((n_ticks, n))
    force = np.zeros((n_ticks, 3))
    energy, balance = np.zeros(n_ticks), np.zeros(n_ticks)
    fb_h, fb_t = session.hsi.feedback, session.to.feedback
    world_h = session.hsi.backend.world
    port_h, port_t, monitor = session.hsi.port, session.to.port, session.monitor

    def observe(s: Session) -> None:
        k = s.tick - 1
        q_h[k], q_t[k], v_h[k] = fb_h.q, fb_t.q, fb_h.v
        tau_h[k], tau_e[k], force[k] = s.tau_h, s.tau_e, world_h.force
        energy[k] = monitor.total_energy
        balance[k] = min(port_h.balance, port_t.balance)

    t0 = time.perf_counter()
    summary = session.run(observer=observe)
    wall = time.perf_counter() - t0
    ticks = summary.ticks
    t = np.arange(ticks) * cfg.dt
    x_h = np.array([session.hsi.model.ee_position(q)[:2] for q in q_h[:ticks]])
    x_t = np.array([session.to.model.ee_position(q)[:2] for q in q_t[:ticks]])
    sig = {
        "t": t, "q_h": q_h[:ticks], "q_t": q_t[:ticks], "v_h": v_h[:ticks],
        "tau_h": tau_h[:ticks], "tau_e": tau_e[:ticks], "force": force[:ticks, :2],
        "x_h": x_h, "x_t": x_t, "energy": energy[:ticks], "balance": balance[:ticks],
    }  # fmt: skip
    row = figures(cfg, case, summary, sig)
    row.update(config=name, case=case, channel=channel.key, wall_s=wall)
    if keep:
        row["signals"] = sig
    return row


def figures(cfg, case: Case, summary, sig: dict) -> dict:
    """Stability, transparency and drift of one run (SI; see the report's definitions)."""
    geo = experiment.experiment_geometry(cfg)
    t, dt = sig["t"], cfg.dt
    complete = summary.ticks == cfg.n_ticks
    finite = all(np.isfinite(v).all() for v in sig.values())
    dq = np.abs(sig["q_h"] - sig["q_t"])
    drift_max = float(dq.max()) if dq.size else math.nan
    ports = summary.channel or {}
    sides = [ports[s] for s in ("hsi", "to") if s in ports]
    # free space: before the first waypoint's end of the stroke and before the TO touches
    # anything (the stiff wall's approach has no separate free stroke)
    contact = np.zeros(len(t), bool)
    for env in cfg.environment:
        if env.kind in ("wall", "foam"):
            nrm = np.asarray(env.normal[:2], float) / np.linalg.norm(env.normal[:2])
            contact |= experiment.penetration(sig["x_t"], np.asarray(env.point_m[:2]), nrm) > 0
    first_contact = t[np.flatnonzero(contact)[0]] if contact.any() else math.inf
    at_wall = experiment.penetration(sig["x_t"], geo.wall_point, geo.wall_normal) > 0
    first_wall = t[np.flatnonzero(at_wall)[0]] if at_wall.any() else math.inf
    free = t < min(geo.free_end_s, first_contact)
    masses = (
        experiment.displayed_mass(sig["v_h"], sig["tau_h"], dt, free)
        if free.sum() > 10
        else [math.nan] * sig["v_h"].shape[1]
    )
    m1, c1 = float(cfg.hsi.virtual_mass), float(cfg.hsi.controller.kp)
    b = float(cfg.channel.wave_impedance)
    filt = filter_group_delay_s(cfg.channel.wave_filter_hz, dt) if case.playout_ms else 0.0
    h0, h1 = geo.wall_hold_s
    hold = (t >= h0) & (t < h1)
    pen_h = pen_t = f_n = chatter = math.nan
    if hold.any():
        pen_h = float(np.mean(experiment.penetration(sig["x_h"][hold], geo.wall_point,
                                                     geo.wall_normal)))  # fmt: skip
        pen_t = float(np.mean(experiment.penetration(sig["x_t"][hold], geo.wall_point,
                                                     geo.wall_normal)))  # fmt: skip
        f_n = float(np.mean(-sig["force"][hold] @ geo.wall_normal))
        chatter = float(sig["tau_e"][hold].std(axis=0).max())
    err = np.maximum(
        np.linalg.norm(sig["x_h"] - geo.final_target, axis=1),
        np.linalg.norm(sig["x_t"] - geo.final_target, axis=1),
    )
    link = summary.link or {}
    used = [d["used"] / max(summary.ticks, 1) for d in link.values()]
    late = [d["late"] / max(d["sent"], 1) for d in link.values()]
    p99 = [d["delay_ticks"]["p99"] for d in link.values() if d["delay_ticks"]["p99"] is not None]
    return {
        "complete": complete,
        "safety_stop": bool(summary.safety_stop),
        "stopped": summary.stopped_early,
        "stop_s": summary.ticks * dt if not complete else math.nan,
        "first_wall_s": first_wall,  # the TO's first tick beyond the wall's surface
        "diverged": (not finite) or drift_max > DIVERGED_RAD,
        "min_balance_j": min((s["min_balance_j"] for s in sides), default=math.nan),
        "min_energy_j": float(summary.min_channel_energy_j),
        "removed_j": float(sum(s["removed_j"] for s in sides)),
        "acted_ticks": int(sum(s["acted_ticks"] for s in sides)),
        "t_p": summary.t_p_total,
        "t_tau": summary.t_tau_total,
        "mass": masses,
        "mass_model": m1 / c1 + b * (case.channel_delay_s + filt),
        "pen_hsi_m": pen_h,
        "pen_to_m": pen_t,
        "wall_force_n": f_n,
        # undefined where the HSI stays short of the wall (or the run ended before the hold)
        "stiffness": experiment.felt_stiffness(f_n, pen_h) if pen_h > 0 else math.nan,
        "chatter_nm": chatter,
        "task_time_s": experiment.task_time(t, err, TASK_TOL_M) if complete else math.nan,
        "drift_end_rad": float(dq[-1].max()) if dq.size else math.nan,
        "drift_max_rad": drift_max,
        "used": float(np.mean(used)) if used else 1.0,
        "late": float(np.mean(late)) if late else 0.0,  # arrived after their playout tick
        "delay_p99_ticks": max(p99) if p99 else case.playout_ms,
    }


def run_all(st: Settings) -> dict:
    """Every run of the settings, with a progress bar (stderr) and a line per run (stdout)."""
    plan: list[tuple[str, Case, str]] = []
    for name, sweeps in st.grid.items():
        plan.append((name, Case("reference", 0.0), "bounded"))  # D = 0: every channel the same
        for sweep, values in sweeps.items():
            for v in values:
                for ch in st.channels:
                    plan.append((name, make_case(sweep, v), ch))
    rows: list[dict] = []
    columns = (TextColumn("[bold]{task.description}"), BarColumn(),
               TextColumn("{task.completed}/{task.total} runs"), TimeElapsedColumn(),
               TimeRemainingColumn())  # fmt: skip
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("network study", total=len(plan))
        for k, (name, case, ch) in enumerate(plan, 1):
            bar.update(task, description=f"{name}: {case.label}, {ch}")
            keep = st.traces.get(name) == (case.sweep, case.value) or case.sweep == "reference"
            row = run_case(name, case, CHANNEL[ch], st.duration_s[name], keep)
            rows.append(row)
            bar.advance(task)
            log(f"[{k}/{len(plan)}] {name}, {case.label}, {ch}: {_line(row)}")
    return {"rows": rows}


def _line(r: dict) -> str:
    stop = f"STOPPED at {r['stop_s']:.2f} s, " if not r["complete"] else ""
    task = r["task_time_s"]
    return (
        f"{stop}{'DIVERGED, ' if r['diverged'] else ''}min balance {r['min_balance_j']:.3g} J, "
        f"min energy {r['min_energy_j']:.3g} J, removed {r['removed_j']:.3g} J in "
        f"{r['acted_ticks']} ticks; T_p {r['t_p']:.3g}, T_tau {r['t_tau']:.3g}; mass "
        f"{_num(r['mass'][0], 3)}/{_num(r['mass'][1], 3)}; stiffness {_num(r['stiffness'], 0)} "
        f"N/m; task {'not done' if math.isnan(task) else f'{task:.2f} s'}; drift "
        f"{r['drift_end_rad'] * 1e3:.2f}/{r['drift_max_rad'] * 1e3:.1f} mrad  ({r['wall_s']:.1f} s)"
    )


def _num(x: float, digits: int) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


# =============================================================================================
# figures
# =============================================================================================
STYLE = {"zero": ("C0", "o", "-"), "bounded": ("C2", "s", "-"), "tdpa": ("C1", "^", "-"),
         "reflected": ("C4", "P", "-"),
         "hold": ("C3", "v", "--"), "direct": ("C7", "D", ":")}  # fmt: skip
PANELS = (  # (key, label, scale)
    ("t_p", "T_p (rad^2 s)", "log"),
    ("t_tau", "T_tau (N^2 m^2 s)", "log"),
    ("mass0", "displayed mass, joint 1 (kg m^2)", "log"),
    ("stiffness", "felt wall stiffness (N/m)", "symlog"),
    ("drift_end_mrad", "drift at the end (mrad)", "symlog"),
    ("made_j", "energy the channel made: -min port balance (J)", "symlog"),
)
LINTHRESH = {"stiffness": 10.0, "drift_end_mrad": 0.1, "made_j": 1e-9}


def _value(r: dict, key: str) -> float:
    if key == "mass0":
        return r["mass"][0]
    if key == "drift_end_mrad":
        return r["drift_end_rad"] * 1e3
    if key == "made_j":
        return max(0.0, -r["min_balance_j"])
    return r[key]


def rows_of(results: dict, name: str, sweep: str, channel: str | None = None) -> list[dict]:
    rows = [r for r in results["rows"] if r["config"] == name and r["case"].sweep == sweep]
    if channel is not None:
        rows = [r for r in rows if r["channel"] == channel]
    return sorted(rows, key=lambda r: r["case"].value)


def reference(results: dict, name: str) -> dict:
    return rows_of(results, name, "reference")[0]


FONT_PT = 14  # the study grid is wide: its text at this size stays readable once shrunk
STOP_MARK = {"marker": "x", "color": "r", "ms": 10, "mew": 2, "ls": "none"}


def sweep_legend(st: Settings) -> list:
    """The grid's one legend: every channel's line, the no-network reference, the stop mark."""
    handles = []
    for ch in st.channels:
        color, marker, ls = STYLE[ch]
        handles.append(Line2D([], [], ls=ls, color=color, marker=marker, ms=5, mfc="none",
                              lw=1.1, label=CHANNEL[ch].label))  # fmt: skip
    handles.append(Line2D([], [], color="k", lw=0.7, ls=":", label="no network (D = 0)"))
    handles.append(Line2D([], [], **STOP_MARK, label="safety stop or divergence"))
    return handles


def plot_sweeps(results: dict, st: Settings, name: str, path: Path) -> None:
    FigureCanvasAgg(sweep_figure(results, st, name)).print_png(str(path))


def sweep_figure(results: dict, st: Settings, name: str) -> Figure:
    """A panel per figure (rows) and sweep (columns): every channel, the reference, the
    stops; one legend below the panels, titles wrapped to their width."""
    with rc_context({"font.size": FONT_PT}):  # fonts are fixed when each text is made
        return _sweep_figure(results, st, name)


def _sweep_figure(results: dict, st: Settings, name: str) -> Figure:
    sweeps = list(st.grid[name])
    ref = reference(results, name)
    width = 4.4 * len(sweeps) + 1.5
    fig = Figure(figsize=(width, 3.0 * len(PANELS) + 2.5), layout="constrained")
    for col, sweep in enumerate(sweeps):
        for row, (key, label, scale) in enumerate(PANELS):
            ax = fig.add_subplot(len(PANELS), len(sweeps), row * len(sweeps) + col + 1)
            for ch in st.channels:
                color, marker, ls = STYLE[ch]
                rs = rows_of(results, name, sweep, ch)
                x = [r["case"].value for r in rs]
                y = [_value(r, key) for r in rs]
                if scale == "log":  # nothing at or below 0 on a log axis
                    y = [v if v > 0 else math.nan for v in y]
                ax.plot(x, y, ls, color=color, marker=marker, ms=5, mfc="none", lw=1.1,
                        label=CHANNEL[ch].label)  # fmt: skip
                bad = [(xi, yi) for xi, yi, r in zip(x, y, rs, strict=True)
                       if not r["complete"] or r["diverged"]]  # fmt: skip
                if bad:
                    ax.plot(*zip(*bad, strict=True), **STOP_MARK)
            ref_y = _value(ref, key)
            if scale != "log" or ref_y > 0:
                ax.axhline(ref_y, color="k", lw=0.7, ls=":", label="no network (D = 0)")
            ax.set_yscale(scale, **({"linthresh": LINTHRESH[key]} if scale == "symlog" else {}))
            if scale == "symlog":  # these are >= 0
                ax.set_ylim(bottom=0.0)
            ax.grid(True, which="both", alpha=0.3)
            if row == 0:  # wrapped to its column's width
                column = width / len(sweeps) - 0.8  # inches, less the tick labels
                ax.set_title(wrap_title(SWEEPS[sweep][1], column, FONT_PT / 12),
                             fontsize="medium", loc="left")  # fmt: skip
            if row == len(PANELS) - 1:
                ax.set_xlabel(SWEEPS[sweep][0])
            if col == 0:
                ax.set_ylabel(label, fontsize="small")
    handles = sweep_legend(st)  # outside the axes: it covers no data
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 4))
    fig.suptitle(wrap_title(f"Network study, {TITLES[name]} ({name}.yaml): channels against "
                            "delay, jitter and loss", width, FONT_PT / 12))  # fmt: skip
    return fig


def plot_traces(results: dict, st: Settings, path: Path) -> None:
    names = list(st.grid)
    fig = Figure(figsize=(16, 4.4 * len(names)), layout="constrained")
    rows_of_fig = fig.subfigures(len(names), 1, squeeze=False)[:, 0]
    for i, name in enumerate(names):
        sweep, value = st.traces[name]
        rows = [r for r in results["rows"] if r["config"] == name and "signals" in r
                and (r["case"].sweep, r["case"].value) == (sweep, value)]  # fmt: skip
        if not rows:
            continue
        geo = experiment.experiment_geometry(config.load(CONFIGS[name]))
        sub = rows_of_fig[i]
        axes = [sub.add_subplot(1, 3, k + 1) for k in range(3)]
        ref = reference(results, name)["signals"]
        depth = experiment.penetration(ref["x_t"], geo.wall_point, geo.wall_normal)
        axes[0].plot(ref["t"], depth * 1e3, color="k", lw=0.8, ls=":", label="TO, no network")
        for r in rows:
            s, (color, _, _) = r["signals"], STYLE[r["channel"]]
            label = CHANNEL[r["channel"]].label
            for x, ls in ((s["x_t"], "-"), (s["x_h"], "--")):
                pen = experiment.penetration(x, geo.wall_point, geo.wall_normal) * 1e3
                axes[0].plot(s["t"], pen, ls, color=color, lw=1.0)
            axes[1].plot(s["t"], s["energy"], color=color, lw=1.0, label=label)
            axes[2].plot(s["t"], s["balance"], color=color, lw=1.0, label=label)
        case = rows[0]["case"]
        axes[0].axhline(0.0, color="C3", lw=0.6)
        axes[0].set_ylabel("depth beyond the wall surface (mm)")
        sub.suptitle(f"{TITLES[name]}: {case.label}")
        axes[0].set_title("tools at the wall", fontsize="medium", loc="left")
        axes[1].set_ylabel("two-port channel energy (J)")
        axes[1].set_title("energy that entered the channel (eq 7)", fontsize="medium", loc="left")
        axes[2].set_yscale("symlog", linthresh=1e-6)
        axes[2].set_ylabel("min port balance (J)")
        axes[2].set_title("the ports' balance, as each method accounts it", fontsize="medium",
                          loc="left")  # fmt: skip
        for ax in axes:
            ax.grid(True, alpha=0.3)
            ax.set_xlabel("t (s)")
    # one legend for both rows (the same channels), outside the axes: it covers no data
    handles = [Line2D([], [], color="k", lw=0.8, ls=":", label="TO, no network")]
    handles += [Line2D([], [], color=STYLE[ch][0], lw=1.0, label=CHANNEL[ch].label)
                for ch in st.channels]  # fmt: skip
    handles += [Line2D([], [], color="0.3", lw=1.0, ls=ls, label=f"{what} (tools at the wall)")
                for ls, what in (("-", "TO"), ("--", "HSI"))]  # fmt: skip
    fig.legend(handles=handles, loc="outside lower center", ncols=4)
    FigureCanvasAgg(fig).print_png(str(path))


# =============================================================================================
# report
# =============================================================================================
def _g(x: float, digits: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    return "0" if x == 0 else f"{x:.{digits}g}"


def _f(x: float, digits: int) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _stop(r: dict) -> str:
    return "no" if r["complete"] else f"at {r['stop_s']:.2f} s"


def _task(r: dict) -> str:
    return "not done" if math.isnan(r["task_time_s"]) else f"{r['task_time_s']:.2f}"


def _stiffness(r: dict) -> str:
    k = r["stiffness"]
    return _f(k, 0) if math.isfinite(k) and abs(k) >= 10 else _g(k, 2)


def _network(r: dict) -> str:
    return r["case"].label


def ordered(results: dict, st: Settings, name: str) -> list[dict]:
    """A config's rows: the reference, then each sweep by value, channels in study order."""
    out = [reference(results, name)]
    for sweep in st.grid[name]:
        for r in rows_of(results, name, sweep):
            out.append(r)
    order = {c: k for k, c in enumerate(st.channels)}
    out[1:] = sorted(out[1:], key=lambda r: (list(st.grid[name]).index(r["case"].sweep),
                                             r["case"].value, order[r["channel"]]))  # fmt: skip
    return out


def _channel_cell(r: dict) -> str:
    return (
        "all (direct coupling)" if r["case"].sweep == "reference" else CHANNEL[r["channel"]].label
    )


def stability_table(rows: list[dict]) -> list[str]:
    out = [
        "| network | channel | safety stop | diverged | min port balance (J) | "
        "min two-port energy (J) | removed (J) | acted (ticks) | packets used (%) | "
        "one-way delay p99 (ticks) | wall chatter (N m) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        out.append(
            f"| {_network(r)} | {_channel_cell(r)} | {_stop(r)} | "
            f"{'yes' if r['diverged'] else 'no'} | {_g(r['min_balance_j'])} | "
            f"{_g(r['min_energy_j'])} | {_g(r['removed_j'])} | {r['acted_ticks']} | "
            f"{r['used'] * 100:.1f} | {r['delay_p99_ticks']} | {_g(r['chatter_nm'])} |"
        )
    return out


def transparency_table(rows: list[dict]) -> list[str]:
    out = [
        "| network | channel | T_p (rad^2 s) | T_tau (N^2 m^2 s) | displayed mass j1 / j2 "
        "(kg m^2) | wave model M1/c1 + b T (kg m^2) | HSI beyond wall (mm) | TO in wall (mm) | "
        "felt stiffness (N/m) | task time (s) | drift end / max (mrad) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        m = r["mass"]
        wave = r["case"].sweep == "reference" or r["channel"] in WAVE_CHANNELS
        model = _f(r["mass_model"], 4) if wave else "—"
        out.append(
            f"| {_network(r)} | {_channel_cell(r)} | {_g(r['t_p'])} | {_g(r['t_tau'])} | "
            f"{_f(m[0], 4)} / {_f(m[1], 4)} | {model} | "
            f"{_f(r['pen_hsi_m'] * 1e3, 2)} | {_f(r['pen_to_m'] * 1e3, 2)} | {_stiffness(r)} | "
            f"{_task(r)} | {_f(r['drift_end_rad'] * 1e3, 2)} / {_f(r['drift_max_rad'] * 1e3, 1)} |"
        )
    return out


def definitions(st: Settings) -> list[str]:
    d = st.duration_s
    return [
        f"Each run is one fast-mode session of {d['paper_experiment']:g} s "
        f"(paper experiment) or {d['stiff_wall']:g} s (stiff wall), simulated robots, the "
        "network between the sites emulated in the same process (`link.impairment`, seed "
        f"{SEED}: the same seed for every channel, so that at a case every channel meets the "
        "same network, packet for packet; the draws never depend on what the packets carry). "
        "Every figure is computed from that run's ticks:",
        "",
        "* **safety stop**: the safety layer ended the run (when; the reasons are listed under "
        "the tables). **diverged**: a signal became non-finite or the two robots' joint angles "
        f"came more than {DIVERGED_RAD:g} rad apart.",
        "* **min port balance**: the smallest, over both ports and the run, of each port's "
        "energy balance as its method accounts it (`Port.protection()`): for a wave channel the "
        "wave energy received minus the wave energy emitted back into the channel, for TDPA "
        "(and, for comparison, the direct channel) the peer's E_in received minus this port's "
        "E_out, the smaller joint. Below 0 the channel has made energy (more than rounding, "
        "~1e-16 J, means it is not passive).",
        "* **min two-port energy**: the running minimum of the energy that entered the two-port "
        "through both ports, the integral of omega_c tau_c - omega_t tau_t (eq 7, 8; the "
        "session's monitor, which sees both ports). Below 0 the channel delivered more energy "
        "than it was given.",
        "* **removed**: energy the protection took out, both ports (the bound's cut of the wave "
        "energy, or TDPA's dissipation); **acted**: the ticks in which it acted, both ports "
        "added.",
        "* **packets used**: the share of ticks at which a port received a new packet (the mean "
        "of both directions); **one-way delay p99**: of the packets that arrived, in ticks "
        "(the larger direction); a packet that arrives after its playout tick is **late** "
        "(the discussion quotes their share). **wall chatter**: the spread (standard "
        "deviation, the larger joint) of the TO's torque on the environment over the last "
        "half of the hold against the wall.",
        "* **T_p, T_tau**: the session's eq 18 sums over both joints, the whole run.",
        "* **displayed mass**: per joint, the least-squares fit of tau_h = m a_h + d v_h over "
        "the free-space ticks (`teleop_rt.analysis.experiment.displayed_mass`): the paper "
        "experiment's stroke out and back (before 3 s), the stiff wall's approach before the TO "
        "first touches the wall. The **wave model** beside it is what a wave channel displays "
        "at a constant delay T (M1/c1 + b T, with T the channel's one-way delay plus the 30 Hz "
        "received-wave filter's 4.82 ms; the delay of the playout for `fixed`, the network's "
        "mean for `newest`); for TDPA and direct force feedback it does not apply (—).",
        "* **HSI beyond wall / TO in wall**: each tool's mean depth beyond the wall's surface "
        "over the last half of the hold (negative: short of it). **felt stiffness**: the "
        "hand's mean force into the wall over the HSI's depth (eq 30's loss of stiffness; the "
        "wall is 5000 N/m; n/a where the HSI stays short of the wall or the run ended before "
        "the hold).",
        f"* **task time**: when both tools come within {TASK_TOL_M * 1e3:g} mm of the task's "
        "final target for good; not done if not by the end of the run.",
        "* **drift**: the larger joint's |q_h - q_t| at the last tick (the robots are back at "
        "rest there) and its maximum over the run. A lost wave shifts the TO for good unless "
        "the channel carries position (the wave integral catches up what was lost).",
    ]


def playout_section(st: Settings) -> list[str]:
    jitters = sorted({v for g in st.grid.values() for v in g.get("jitter_fixed", ())})
    fixed_d = ", ".join(f"{make_case('jitter_fixed', v).playout_ms} ms" for v in jitters)
    fixed_d = f"({fixed_d})" if jitters else "(a sweep this run did not make)"
    return [
        "Every case has a network delay, and the receiver's playout rule "
        "(`teleop_rt/com/playout.py`) decides what of it reaches the ports:",
        "",
        "* **delay** and **loss** sweeps: constant network delay, `fixed` playout at D = the "
        "network's delay. Every packet arrives exactly at its playout tick (or never), so the "
        "channel sees the constant delay D and the losses (the `newest` playout would compute "
        "the same here: bit-identical figures at 50 ms).",
        f"* **jitter, newest**: {BASE_MS:g} ms mean delay with normal jitter (uncorrelated, as "
        "netem's `delay 20ms Xms`, so packets 1 ms apart overtake each other), `newest` "
        "playout at the minimum playout delay D = 1 ms: a port uses the newest packet that has "
        "arrived, so the network's variation reaches the ports (a delay that drops skips "
        "packets, one that grows leaves ticks with none). This is the case the protections "
        "are for.",
        f"* **jitter, correlated**: the same with successive delays correlated {CORRELATED:g} % "
        "(`correlation_percent`: the delay wanders over about 100 packets and packets "
        "overtake each other far less), `newest` playout at D = 1 ms.",
        f"* **jitter, fixed**: the uncorrelated network, `fixed` playout at D = 20 ms + 3 jitter "
        f"{fixed_d}: jitter within D is absorbed and becomes the constant delay D; only the "
        "tail beyond D is lost (late). It costs latency instead of passivity.",
        "",
        "The in-process link of a session with no network (D = 0) couples the ports directly "
        "(tau_c = tau_t, omega_t = omega_c): every channel computes the same, so it is run "
        "once per task as the reference.",
    ]


def write_report(results: dict, st: Settings, out_dir: Path, seconds: float) -> Path:
    lines: list[str] = []
    add = lines.append
    docs = out_dir.resolve() == (ROOT / "docs").resolve()
    cmd = "python tools/network_study.py" + (" --quick" if st.quick else "")
    cmd += " --out docs" if docs else " --out DIR"
    add("# Network study: passive channels over delay, jitter and loss")
    add("")
    add(
        f"Generated by `{cmd}` in {seconds:.0f} s (wall time on the machine that ran it; "
        f"{len(results['rows'])} runs). Every number below comes from that run; the tables "
        "are written by the script from its results. Joint space per joint (kg m^2, N m, "
        "rad), tool positions in the plane (mm, N/m)."
    )
    add("")
    add("## Channels")
    add("")
    for key in st.channels:
        ch = CHANNEL[key]
        sets = " ".join(f"--set {o}" for o in ch.overrides)
        add(f"* **{ch.label}**: `{sets}`" + ("" if ch.protected else " (unprotected)"))
    add("")
    add(
        "All with the configs' wave impedance b = 2 N m s/rad and 30 Hz received-wave filter; "
        "`teleop_rt/com/port.py` describes each. The zero wave is passive by construction (no "
        "protection acts); the bounded wave integral catches lost samples up and clips what it "
        "emits to the wave energy it received; TDPA's passivity controllers dissipate what the "
        "observers find in excess; holding the last wave and direct force feedback have no "
        "protection."
    )
    add("")
    add("## The network and the playout")
    add("")
    lines += playout_section(st)
    add("")
    add("## Definitions")
    add("")
    lines += definitions(st)
    add("")
    for name in st.grid:
        rows = ordered(results, st, name)
        add(f"## {TITLES[name].capitalize()} (`configs/{name}.yaml`)")
        add("")
        add(f"![{name}](figures/network_{name}.png)")
        add("")
        add(
            "Where channels compute the same (the wave reconstructions at a constant delay) "
            "their lines lie on top of each other; the dotted line is the run with no network."
        )
        add("")
        add("### Stability and energy")
        add("")
        lines += stability_table(rows)
        add("")
        stops = [r for r in rows if r["stopped"]]
        if stops:
            add("Runs that ended early:")
            add("")
            for r in stops:
                add(f"* {_network(r)}, {_channel_cell(r)}: {r['stopped']}")
            add("")
        add("### Transparency and drift")
        add("")
        lines += transparency_table(rows)
        add("")
    add("## Over time")
    add("")
    add("![traces](figures/network_traces.png)")
    add("")
    add(
        "One case per task: "
        + "; ".join(f"{TITLES[n]}: {make_case(*st.traces[n]).label}" for n in st.grid)
        + ". Left: each tool's depth beyond the wall's surface (TO solid, HSI dashed; the "
        "dotted line is the TO with no network). Middle: the two-port's energy. Right: the "
        "smaller port balance."
    )
    add("")
    add("## Discussion")
    add("")
    for para in discussion(results, st):
        add(para)
        add("")
    path = out_dir / "network_study.md"
    path.write_text("\n".join(lines))
    return path


class NotRun(LookupError):
    """A case the settings did not run (a quick run's coarse grid)."""


def pick(results: dict, name: str, sweep: str, value: float, channel: str) -> dict:
    """The run of a case and channel (NotRun if the settings did not run it)."""
    for r in results["rows"]:
        c = r["case"]
        if (r["config"], c.sweep, c.value, r["channel"]) == (name, sweep, value, channel):
            return r
    raise NotRun((name, sweep, value, channel))


def swept(st: Settings, name: str, sweep: str) -> tuple:
    """The values a sweep ran for a task (NotRun if none)."""
    values = st.grid.get(name, {}).get(sweep)
    if not values:
        raise NotRun((name, sweep))
    return values


def _same(a: dict, b: dict) -> bool:
    keys = ("t_p", "t_tau", "stiffness", "drift_end_rad", "min_energy_j", "pen_to_m")
    return all(a[k] == b[k] for k in keys) and a["mass"] == b["mass"]


def _list(values: list[float], fmt: str) -> str:
    return " / ".join(format(v, fmt) for v in values)


def _impaired(results: dict, channels: tuple[str, ...]) -> list[dict]:
    return [r for r in results["rows"] if r["case"].sweep not in ("reference", "delay")
            and r["channel"] in channels]  # fmt: skip


def discussion(results: dict, st: Settings) -> list[str]:
    """Paragraphs written from the results; one whose cases the settings lack is left out."""
    out = []
    for part in (_stability, _constant_delay, _tdpa, _unprotected, _loss, _jitter):
        try:
            out.append(part(results, st))
        except NotRun:
            continue
    if st.quick:
        out.insert(0, "(A quick run: a coarse grid; only what it ran is discussed.)")
    return out


def _stability(results: dict, st: Settings) -> str:
    prot = [r for r in results["rows"] if r["case"].sweep != "reference"
            and r["channel"] in ("zero", "bounded", "tdpa")]  # fmt: skip
    if not prot:
        raise NotRun("protected")
    bad = [r for r in prot if not r["complete"] or r["diverged"]]
    return (
        f"**Stability.** Of the {len(prot)} runs with a protected channel (zero wave, bounded "
        f"wave, TDPA), {len(bad)} stopped or diverged; their port balances never went below "
        f"{min(r['min_balance_j'] for r in prot):.3g} J and their two-port energy never below "
        f"{min(r['min_energy_j'] for r in prot):.3g} J: rounding, so all three stay passive "
        "under every delay, jitter and loss of the study, as each method accounts it. What "
        "they cost is transparency, and the cost differs a great deal."
    )


def _constant_delay(results: dict, st: Settings) -> str:
    delays = swept(st, "paper_experiment", "delay")
    runs = [(n, d) for n in st.grid for d in st.grid[n].get("delay", ())]
    same = all(
        _same(pick(results, n, "delay", d, "zero"), pick(results, n, "delay", d, c))
        for n, d in runs
        for c in ("bounded", "hold")
    )
    acted = sum(pick(results, n, "delay", d, "bounded")["acted_ticks"] for n, d in runs)
    rows = [pick(results, "paper_experiment", "delay", d, "bounded") for d in delays]
    return (
        "**Constant delay, no loss (the paper's case).** The three wave reconstructions "
        + ("give identical figures in every run" if same else "differ")
        + f" (the bound acted in {acted} ticks): with nothing lost there is nothing to "
        "reconstruct. They show the paper's effects: the displayed mass (paper experiment, "
        f"joint 1) is {_list([r['mass'][0] for r in rows], '.4f')} kg m^2 at "
        f"{_list(delays, 'g')} ms against M1/c1 + b T = "
        f"{_list([r['mass_model'] for r in rows], '.4f')}, and the felt stiffness falls to "
        f"{_list([r['stiffness'] for r in rows], '.0f')} N/m (the wall is 5000; eq 30's "
        "b / T). The robots end where they should: drift at the end at most "
        f"{max(r['drift_end_rad'] for r in rows) * 1e3:.2f} mrad."
    )


def _tdpa(results: dict, st: Settings) -> str:
    name = "stiff_wall"
    t = pick(results, name, "delay", 20, "tdpa")
    w = pick(results, name, "delay", 20, "bounded")
    td = [r for r in results["rows"] if r["channel"] == "tdpa" and r["case"].sweep != "reference"]
    masses = [m for r in td for m in r["mass"]]
    stiff = [r["stiffness"] for r in td if math.isfinite(r["stiffness"])]
    drift = [r["drift_end_rad"] * 1e3 for r in td]
    return (
        "**TDPA** displays no mass in free space: the fitted mass is "
        + (
            f"{min(masses):.4f}"
            if f"{min(masses):.4f}" == f"{max(masses):.4f}"
            else f"{min(masses):.4f}-{max(masses):.4f}"
        )
        + " kg m^2 in every run, the HSI's own M1/c1, where "
        "the wave channel shows b T more (force feedback of a TO that touches nothing is "
        f"zero). It pays at the wall. At a constant 20 ms (stiff wall) the TO stays "
        f"{t['pen_to_m'] * 1e3:.2f} mm in the wall while the HSI goes "
        f"{t['pen_hsi_m'] * 1e3:.2f} mm beyond it: the operator feels {_stiffness(t)} N/m "
        f"(wave: {_stiffness(w)}), the two robots end {t['drift_end_rad'] * 1e3:.1f} mrad "
        f"apart and the task is not done (T_p {t['t_p']:.3g} against the wave's "
        f"{w['t_p']:.3g}). Over every case of both tasks TDPA's felt stiffness is at most "
        f"{max(stiff):.0f} N/m and its drift at the end {min(drift):.0f}-{max(drift):.0f} "
        "mrad, whatever the network. The bookkeeping explains it: the TO's admittance-type "
        "controller may put into the wall only the energy that has entered at the HSI, and "
        "until the TO touches the wall the operator has put in none (nothing pushed back). "
        f"So the controller stops the TO at the surface (it acted in {t['acted_ticks']} "
        f"ticks, removing {t['removed_j']:.3g} J), the HSI meets almost no resistance and "
        "moves on to the hand's target, and with velocity forward and no position term "
        "nothing brings the two back together."
    )


def _unprotected(results: dict, st: Settings) -> str:
    direct = [r for r in results["rows"] if r["channel"] == "direct"]
    if not direct:
        raise NotRun("direct")
    stops = [r for r in direct if not r["complete"]]
    hold = _impaired(results, ("hold",))
    negative = [r for r in hold if r["min_balance_j"] < -1e-9]
    bad = [r for r in hold if not r["complete"] or r["diverged"]]
    h20 = pick(results, "stiff_wall", "loss", 20, "hold")
    h0 = pick(results, "stiff_wall", "delay", 20, "hold")
    at_wall = all(r.get("first_wall_s", math.inf) < r["stop_s"] for r in stops)
    return (
        "**Unprotected.** Direct force feedback is not passive: its two-port energy goes "
        f"below zero in {sum(r['min_energy_j'] < -1e-9 for r in direct)} of its "
        f"{len(direct)} runs, down to {min(r['min_energy_j'] for r in direct):.3g} J, and "
        f"{len(stops)} of its {len(direct)} runs end in a safety stop"
        + (", every one after the TO has met the wall" if at_wall and stops else "")
        + " (the reasons are listed with the tables). The held wave is the "
        "opposite case: the most transparent channel under loss and jitter (stiff wall at "
        f"20 % loss: {_stiffness(h20)} N/m felt and {h20['drift_end_rad'] * 1e3:.2f} mrad of "
        f"drift, against {_stiffness(h0)} N/m with no loss), but not passive: its balance "
        f"goes below zero in {len(negative)} of its {len(hold)} runs with jitter or loss, "
        f"down to {min(r['min_balance_j'] for r in hold):.3g} J (the two-port energy to "
        f"{min(r['min_energy_j'] for r in hold):.3g} J). On these two tasks the energy it "
        "makes (millijoules) is less than the hand's damping and the TO's controller "
        f"dissipate: {len(bad)} hold runs stopped or diverged. The failure shows in the "
        "accounting, not in the motion; nothing bounds it on a task that dissipates less."
    )


def _loss(results: dict, st: Settings) -> str:
    name = "stiff_wall"
    losses = swept(st, name, "loss")
    z = [pick(results, name, "loss", v, "zero") for v in losses]
    b = [pick(results, name, "loss", v, "bounded") for v in losses]
    h = [pick(results, name, "loss", v, "hold") for v in losses]
    top = max(swept(st, name, "burst"))
    zb, bb = pick(results, name, "burst", top, "zero"), pick(results, name, "burst", top, "bounded")
    return (
        "**Loss costs the passive wave channels their contact.** Felt stiffness at the "
        f"stiff wall for {_list(losses, 'g')} % independent loss: zero wave "
        f"{_list([r['stiffness'] for r in z], '.0f')}, bounded "
        f"{_list([r['stiffness'] for r in b], '.0f')}, held wave "
        f"{_list([r['stiffness'] for r in h], '.0f')} N/m; drift at the end: zero "
        f"{_list([r['drift_end_rad'] * 1e3 for r in z], '.1f')}, bounded "
        f"{_list([r['drift_end_rad'] * 1e3 for r in b], '.1f')} mrad. A static push through a "
        "wave channel is a standing wave (at rest the wave each side sends back equals the "
        "one it received), and every lost sample takes part of it out: the zero "
        "reconstruction emits nothing for it; the bounded one holds it, but with the "
        "integral in step the wave energy it has emitted equals exactly what it received, "
        "so the bound leaves no room and cuts the held sample to zero as well, and the "
        "catch-up after m lost samples, (m + 1) w in one tick, is clipped to sqrt(m + 1) w: "
        "the energy is kept, the integral (and with it position and static force) is not. "
        "So the force on the wall leaks away, the TO slides back to the surface and the HSI "
        "goes on to the hand's target. The bound keeps more than the zero wave, and much more "
        f"when the same loss comes in bursts ({top:g} % in bursts of {BURST_PACKETS}: "
        f"bounded {_stiffness(bb)}, zero {_stiffness(zb)} N/m, drift "
        f"{bb['drift_end_rad'] * 1e3:.1f} against {zb['drift_end_rad'] * 1e3:.1f} mrad): a "
        "burst is one clipped catch-up where independent loss makes many."
    )


def _jitter(results: dict, st: Settings) -> str:
    name = "paper_experiment"
    jit = swept(st, name, "jitter_newest")
    new = [pick(results, name, "jitter_newest", v, "bounded") for v in jit]
    cor = [pick(results, name, "jitter_correlated", v, "bounded") for v in jit]
    zero = [pick(results, name, "jitter_newest", v, "zero") for v in jit]
    hold = [pick(results, name, "jitter_newest", v, "hold") for v in jit]
    fix = [pick(results, name, "jitter_fixed", v, "bounded") for v in jit]
    ref = pick(results, name, "delay", 20, "bounded")
    return (
        "**Jitter: the playout decides.** With the newest playout the network's variation "
        f"reaches the ports: uncorrelated jitter of {_list(jit, 'g')} ms leaves "
        f"{_list([r['used'] * 100 for r in new], '.0f')} % of the ticks with a new packet "
        "(packets 1 ms apart overtake each other and the older ones are dropped), correlated "
        f"jitter {_list([r['used'] * 100 for r in cor], '.0f')} %. The passive wave channels "
        "then lose the wall as under loss (paper experiment, the TO short of the wall by "
        f"{_list([-r['pen_to_m'] * 1e3 for r in zero], '.1f')} mm with the zero wave and "
        f"{_list([-r['pen_to_m'] * 1e3 for r in new], '.1f')} mm bounded; drift at the end "
        f"{_list([r['drift_end_rad'] * 1e3 for r in new], '.0f')} mrad bounded), while the "
        f"held wave keeps {_list([r['stiffness'] for r in hold], '.0f')} N/m and makes up to "
        f"{-min(r['min_balance_j'] for r in hold):.2g} J. With the fixed playout at D = 20 ms "
        "+ 3 jitter the same networks cost the wave channel only the longer delay: displayed "
        f"mass {_list([r['mass'][0] for r in fix], '.4f')} against M1/c1 + b D = "
        f"{_list([r['mass_model'] for r in fix], '.4f')} kg m^2, felt stiffness "
        f"{_list([r['stiffness'] for r in fix], '.0f')} N/m (20 ms constant: "
        f"{ref['stiffness']:.0f}), {_list([r['late'] * 100 for r in fix], '.2f')} % of "
        f"the packets late, the bound acting in {_list([r['acted_ticks'] for r in fix], 'd')} "
        f"ticks and removing {_list([r['removed_j'] * 1e3 for r in fix], '.1f')} mJ. For a "
        "wave channel, buffering the jitter is the cheap protection: it turns the network "
        "into the constant delay the channel is passive for, at the price of b (D - T) more "
        "displayed mass, and the energy bound guards against the few packets that come later "
        "still."
    )


# =============================================================================================
def study(quick: bool, out_dir: Path) -> dict:
    """Run everything, write the figures and the report; return the results."""
    st = QUICK if quick else FULL
    fig_dir = out_dir / "figures"
    start = time.perf_counter()
    results = run_all(st)
    for name in st.grid:
        path = fig_dir / f"network_{name}.png"
        plot_sweeps(results, st, name, path)
        log(f"wrote {path}")
    path = fig_dir / "network_traces.png"
    plot_traces(results, st, path)
    log(f"wrote {path}")
    seconds = time.perf_counter() - start
    report = write_report(results, st, out_dir, seconds)
    log(f"wrote {report}")
    log(f"wall time {seconds:.1f} s")
    results["seconds"] = seconds
    return results


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a few cases, both tasks (tests, CI); refused with --out docs",
    )
    parser.add_argument(
        "--acceptance",
        action="store_true",
        help="issue 23's acceptance study instead (tools/transparency_study.py): "
        "transparency_under_loss.md",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="output folder: network_study.md and figures/network_*.png (default: a new "
        "temporary folder; --out docs regenerates the committed report)",
    )
    return parser.parse_args(argv)


def prepare_out(out: Path, quick: bool) -> str | None:
    """Create DIR and DIR/figures before the work; the reason it cannot be used, else None."""
    if quick and out.resolve() == (ROOT / "docs").resolve():
        return f"--out {out}: a quick run never writes over the committed report"
    return report_folder_problem(out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--codec" in argv:  # the deadband codec's own study (issue 24)
        sys.path.insert(0, str(ROOT / "tools"))
        import codec_study

        return codec_study.main([a for a in argv if a != "--codec"])
    args = parse_args(argv)
    out = args.out
    if out is None:
        out = Path(tempfile.mkdtemp(prefix="teleop-rt-network-study-"))
    problem = prepare_out(out, args.quick)
    if problem is not None:
        print(f"network_study: error: {problem}", file=sys.stderr)
        return 2
    log(f"writing into {out}")
    if args.acceptance:
        from transparency_study import study as acceptance  # tools/, beside this script

        acceptance(out, quick=args.quick)
        return 0
    study(args.quick, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
