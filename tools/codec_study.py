#!/usr/bin/env python3
"""The deadband codec studied (issue 24): what it saves and what it costs.

    python tools/codec_study.py [--quick] [--out DIR] [--parts P,..] [--rows C:D:CH,..]
                                [--codec-set KEY=VALUE]   (or: network_study.py --codec)

Seven parts, one-process fast-mode sessions (deterministic):

1. acceptance: the paper experiment, foam and the stiff wall at D = 1 (the least delay a
   network carries: the codec needs one), 20 and 50 ms, the bounded wave channel and TDPA,
   without and with the codec at a 10 % deadband: the packets each way, T_p and T_tau (eq 18),
   the wall (or foam) stiffness the operator feels, the displayed mass in free space, and the
   two-port's and the ports' energy;
2. the curve: reduction and transparency against the deadband, 1 to 30 %, paper experiment at
   20 ms (DIR/figures/codec_curve.png);
3. passivity: the codec on over one case of every impairment class of tools/network_study.py;
4. where the error comes from: the paper experiment and the stiff wall at 20 ms with parts of
   the codec switched off or replaced one at a time (the reserve, the reconstruction between
   packets, TDPA's integral reconstruction; the codec's constants set for the run);
5. TDPA's energy deadband (``channel.deadband.exchange_j``): every TDPA row with the setting
   measured best at D = 1 ms, and the stiff wall at 1 ms against the energy step;
6. TDPA: every TDPA row with each energy setting, the onset stiffness next to the study's;
7. pace: every TDPA row with the energy deadband paced (``exchange_min_ticks``).

``--parts`` runs some of them, ``--rows`` some acceptance rows (``config:D:channel``),
``--codec-set`` adds an override to the acceptance part's runs with the codec.

Writes DIR/codec_study.md (and the figure); without ``--out`` a new temporary folder.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from network_study import SWEEPS, make_case  # noqa: E402

from teleop_rt import config  # noqa: E402
from teleop_rt.analysis import experiment  # noqa: E402
from teleop_rt.com import codec  # noqa: E402
from teleop_rt.output import report_folder_problem  # noqa: E402
from teleop_rt.session import Session  # noqa: E402

CONFIGS = {name: ROOT / "configs" / f"{name}.yaml"
           for name in ("paper_experiment", "foam", "stiff_wall")}  # fmt: skip
CHANNELS = {"wave": ("channel.mode=wave",), "tdpa": ("channel.mode=tdpa",)}
DELAYS_MS = (1, 20, 50)
WEBER = 0.10
CURVE = (0.01, 0.02, 0.05, 0.10, 0.20, 0.30)
PASSIVE_J = -1e-9
# the split of the error (part 4): label -> (overrides, codec constants for the run, modes)
HOLD = ["channel.deadband.prediction_hsi=hold", "channel.deadband.prediction_to=hold"]
LINEAR = ["channel.deadband.prediction_hsi=linear", "channel.deadband.prediction_to=linear"]
NO_SUM = {"SUM_TIME_S": math.inf}
EVERY_TICK = ["channel.deadband.max_interval_ticks=1"]
SPLIT = {
    "every tick (max interval 1): the reserve alone": (EVERY_TICK, {}, ("wave",)),
    "no reserve (intervals set by the energy room)": ([], {"RESERVE": 0.0}, ("wave",)),
    "hold both ways (the codec before this study)": (HOLD, NO_SUM, ("wave", "tdpa")),
    "hold both ways, integral reconstruction": (HOLD, {}, ("tdpa",)),
    "linear both ways": (LINEAR, {}, ("wave", "tdpa")),
    "default (wave: linear from the HSI; TDPA: from the TO)": ([], {}, ("wave", "tdpa")),
}
CLASS_VALUES = {"delay": 50, "jitter_newest": 10, "jitter_correlated": 10, "jitter_fixed": 10,
                "loss": 20, "burst": 20}  # fmt: skip


def codec_sets(weber: float | None) -> list[str]:
    if weber is None:
        return ["channel.codec=none"]
    return ["channel.codec=deadband", f"channel.deadband.weber_hsi={weber:g}",
            f"channel.deadband.weber_to={weber:g}"]  # fmt: skip


def run(name: str, sets: list[str], duration_s: float | None = None) -> dict:
    """One session; its figures."""
    extra = [] if duration_s is None else [f"duration_s={duration_s}"]
    cfg = config.load(CONFIGS[name], [*sets, *extra])
    s = Session(cfg)
    ticks, n = cfg.n_ticks, s.n
    v_h, tau_h, m_t_q = np.zeros((ticks, n)), np.zeros((ticks, n)), np.zeros((ticks, n))
    x_h, x_t, force = np.zeros((ticks, 2)), np.zeros((ticks, 2)), np.zeros((ticks, 2))
    fb_h, fb_t, world = s.hsi.feedback, s.to.feedback, s.hsi.backend.world
    m_h, m_t = s.hsi.model, s.to.model

    def observe(session: Session) -> None:
        k = session.tick - 1
        v_h[k], tau_h[k], force[k] = fb_h.v, session.tau_h, world.force[:2]
        x_h[k], x_t[k] = m_h.ee_position(fb_h.q)[:2], m_t.ee_position(fb_t.q)[:2]
        m_t_q[k] = fb_t.q

    summary = s.run(observer=observe)
    k = summary.ticks
    t = np.arange(k) * cfg.dt
    env = next(e for e in cfg.environment if e.kind in ("wall", "foam"))
    normal = np.asarray(env.normal[:2], float) / np.linalg.norm(env.normal[:2])
    point = np.asarray(env.point_m[:2], float)
    pen_t = experiment.penetration(x_t[:k], point, normal)
    pen_h = experiment.penetration(x_h[:k], point, normal)
    f_n = -force[:k] @ normal
    touch = (pen_t > 0) & (pen_h > 0)
    # felt stiffness: the hand's force against the HSI's own penetration, least squares
    # through the origin over the ticks in contact
    stiffness = float(f_n[touch] @ pen_h[touch] / (pen_h[touch] @ pen_h[touch])) \
        if touch.sum() > 20 else math.nan  # fmt: skip
    onset = onset_stiffness(pen_h, f_n, touch, round(ONSET_S / cfg.dt))
    first = t[np.flatnonzero(pen_t > 0)[0]] if (pen_t > 0).any() else math.inf
    wps = cfg.operator.waypoints
    free = t < min(wps[1].t_s if len(wps) > 1 else math.inf, first)
    mass = float(np.mean(experiment.displayed_mass(v_h[:k], tau_h[:k], cfg.dt, free))) \
        if free.sum() > 50 else math.nan  # fmt: skip
    ch = summary.channel or {}
    c = ch.get("codec")
    return {
        "q_t": m_t_q[:k],
        "tau_h": tau_h[:k].copy(),
        "complete": k == cfg.n_ticks and not summary.safety_stop,
        "t_p": summary.t_p_total,
        "t_tau": summary.t_tau_total,
        # the same as RMS over the run (T_p: rad^2 s, T_tau: (N m)^2 s): what a JND compares
        "rms_p": math.sqrt(summary.t_p_total / (k * cfg.dt)),
        "rms_tau": math.sqrt(summary.t_tau_total / (k * cfg.dt)),
        "stiffness": stiffness,
        "onset_stiffness": onset,
        "mass": mass,
        "min_energy": float(summary.min_channel_energy_j),
        "min_balance": min(ch["hsi"]["min_balance_j"], ch["to"]["min_balance_j"]),
        "red_hsi": c["hsi"]["reduction"] if c else 0.0,
        "red_to": c["to"]["reduction"] if c else 0.0,
        "rate_hsi": c["hsi"]["rate_hz"] if c else 1.0 / cfg.dt,
        "rate_to": c["to"]["rate_hz"] if c else 1.0 / cfg.dt,
        "codec": c,
    }


# the felt stiffness over the first contact (docs/codec.md, "TDPA's stiff wall"): what a
# person judges a hard surface by is its response at the onset of contact (rate-hardness:
# Lawrence, Pao, Dougherty, Salada & Pavlou, IEEE Trans. Robot. Autom. 16(4), 2000), and
# TDPA's wall, with no position feedback, gives way within a second of it
ONSET_S = 0.5


def onset_stiffness(pen_h: np.ndarray, f_n: np.ndarray, touch: np.ndarray, ticks: int) -> float:
    """The operator's force against the HSI's penetration, least squares through the origin,
    over the ticks in contact within ``ticks`` of the first (nan: fewer than 20 such)."""
    if not touch.any():
        return math.nan
    m = touch.copy()
    first = int(np.flatnonzero(touch)[0])
    m[:first], m[first + ticks:] = False, False
    if m.sum() <= 20:
        return math.nan
    return float(f_n[m] @ pen_h[m] / (pen_h[m] @ pen_h[m]))


@contextlib.contextmanager
def constants(**values: float):
    """The codec's constants set for the runs inside (read when a port is configured)."""
    old = {name: getattr(codec, name) for name in values}
    for name, value in values.items():
        setattr(codec, name, value)
    try:
        yield
    finally:
        for name, value in old.items():
            setattr(codec, name, value)


def felt(on: dict, off: dict) -> tuple[float, float]:
    """What the codec changed, tick by tick, against the same run without it: the RMS
    difference of the TO's joint angles (mrad) and of the operator's torque, relative to the
    RMS operator torque (a force JND is 7-10 %, the deadband's own Weber fraction)."""
    k = min(len(on["q_t"]), len(off["q_t"]))
    dq = 1e3 * float(np.sqrt(np.mean((on["q_t"][:k] - off["q_t"][:k]) ** 2)))
    dtau = float(np.sqrt(np.mean((on["tau_h"][:k] - off["tau_h"][:k]) ** 2)))
    return dq, dtau / float(np.sqrt(np.mean(off["tau_h"][:k] ** 2)))


def ratio(a: float, b: float) -> float:
    return a / b if b and math.isfinite(a) and math.isfinite(b) else math.nan


def _changes(on: dict, off: dict) -> str:
    """A table's reduction and the changes of T_p, T_tau, stiffness and mass of ``on``
    against ``off`` (the same row without the codec), as cells."""
    cells = [f"{100 * on['red_hsi']:.1f} / {100 * on['red_to']:.1f} %"]
    cells += [_pct(ratio(on[k], off[k]) - 1) for k in ("t_p", "t_tau", "stiffness", "mass")]
    return " | ".join(cells) + " "


def _pct(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{100 * x:+.1f} %"


def acceptance(quick: bool, only: set[tuple[str, int, str]] | None = None,
               extra: tuple[str, ...] = ()) -> list[dict]:  # fmt: skip
    """The acceptance rows (``only``: those (config, D, channel); ``extra``: overrides for
    the runs with the codec)."""
    rows = []
    names = ("stiff_wall",) if quick else tuple(CONFIGS)
    delays = (20,) if quick else DELAYS_MS
    for name in names:
        for d in delays:
            for ch, sets in CHANNELS.items():
                if only is not None and (name, d, ch) not in only:
                    continue
                base = [*sets, f"channel.delay_ms={d}"]
                off = run(name, [*base, *codec_sets(None)], 2.0 if quick else None)
                on = run(name, [*base, *codec_sets(WEBER), *extra], 2.0 if quick else None)
                rows.append({"config": name, "delay": d, "channel": ch, "off": off, "on": on})
                print(f"{name} {d} ms {ch}: reduction {on['red_hsi']:.3f}/{on['red_to']:.3f}, "
                      f"T_p {_pct(ratio(on['t_p'], off['t_p']) - 1)}, T_tau "
                      f"{_pct(ratio(on['t_tau'], off['t_tau']) - 1)}, stiffness "
                      f"{_pct(ratio(on['stiffness'], off['stiffness']) - 1)}, mass "
                      f"{_pct(ratio(on['mass'], off['mass']) - 1)}, min energy "
                      f"{on['min_energy']:.2e}", flush=True)  # fmt: skip
    return rows


# part 5, TDPA's energy deadband (channel.deadband.exchange_j; docs/codec.md): every TDPA row
# with the setting measured best at D = 1 ms, and the stiff wall at 1 ms against the step
EXCHANGE = ("channel.deadband.exchange_j=3e-5", "channel.deadband.prediction_hsi=linear")
EXCHANGE_SWEEP_J = (1e-5, 2e-5, 3e-5, 5e-5)


def energy(quick: bool) -> list[dict]:
    rows = []
    names = ("stiff_wall",) if quick else tuple(CONFIGS)
    delays = (1,) if quick else DELAYS_MS
    dur = 2.0 if quick else None
    step = float(EXCHANGE[0].split("=")[1])
    variants = [(f"{step:g} J, linear from the HSI", EXCHANGE)]
    sweep = [(f"{e:g} J, linear from the HSI",
              (f"channel.deadband.exchange_j={e:g}", EXCHANGE[1]))
             for e in (() if quick else EXCHANGE_SWEEP_J) if e != step]  # fmt: skip
    sweep += [(f"{1e-5:g} J, the default reconstruction (hold from the HSI)",
               ("channel.deadband.exchange_j=1e-5",))] if not quick else []  # fmt: skip
    for name in names:
        for d in delays:
            base = ["channel.mode=tdpa", f"channel.delay_ms={d}"]
            off = run(name, [*base, *codec_sets(None)], dur)
            for label, extra in variants + (sweep if (name, d) == ("stiff_wall", 1) else []):
                on = run(name, [*base, *codec_sets(WEBER), *extra], dur)
                rows.append({"config": name, "delay": d, "channel": f"tdpa ({label})",
                             "variant": label, "on": on, "off": off})  # fmt: skip
                print(f"energy {name} {d} ms {label}: reduction {on['red_hsi']:.3f}/"
                      f"{on['red_to']:.3f}, stiffness "
                      f"{_pct(ratio(on['stiffness'], off['stiffness']) - 1)}", flush=True)
    return rows


# part 6, TDPA's rows with every energy setting, the contact-onset stiffness next to the
# study's (docs/codec.md, "TDPA's stiff wall"): label -> overrides with the codec
# (Weber's rule with a smaller fixed step: measured best over the nine rows, docs/codec.md)
WEBER_STEP_J, WEBER_E = 2e-5, 0.1
WEBER_LABEL = f"{WEBER_STEP_J:g} J, Weber's rule {WEBER_E:g}"
TDPA_VARIANTS = {
    "the default codec": (),
    "energy deadband 3e-05 J": EXCHANGE,
    WEBER_LABEL: (f"channel.deadband.exchange_j={WEBER_STEP_J:g}", *EXCHANGE[1:],
                  f"channel.deadband.exchange_weber={WEBER_E:g}"),
}


# part 7, the energy deadband's pace (channel.deadband.exchange_min_ticks; docs/codec.md):
# a smaller step that sends no sooner than PACE_TICKS after the last packet
PACE_STEP_J, PACE_TICKS = 5.5e-6, 3
PACE_LABEL = f"{PACE_STEP_J:g} J, Weber's rule {WEBER_E:g}, pace {PACE_TICKS}"
PACE = {PACE_LABEL: (f"channel.deadband.exchange_j={PACE_STEP_J:g}", *EXCHANGE[1:],
                     f"channel.deadband.exchange_weber={WEBER_E:g}",
                     f"channel.deadband.exchange_min_ticks={PACE_TICKS}")}  # fmt: skip


def tdpa_rows(quick: bool, variants: dict | None = None) -> list[dict]:
    variants = TDPA_VARIANTS if variants is None else variants
    rows = []
    names = ("stiff_wall",) if quick else tuple(CONFIGS)
    delays = (20,) if quick else DELAYS_MS
    dur = 2.0 if quick else None
    for name in names:
        for d in delays:
            base = ["channel.mode=tdpa", f"channel.delay_ms={d}"]
            off = run(name, [*base, *codec_sets(None)], dur)
            for label, extra in variants.items():
                on = run(name, [*base, *codec_sets(WEBER), *extra], dur)
                rows.append({"config": name, "delay": d, "channel": f"tdpa ({label})",
                             "variant": label, "on": on, "off": off})  # fmt: skip
                print(f"tdpa {name} {d} ms {label}: reduction {on['red_hsi']:.3f}/"
                      f"{on['red_to']:.3f}, stiffness "
                      f"{_pct(ratio(on['stiffness'], off['stiffness']) - 1)}, at the onset "
                      f"{_pct(ratio(on['onset_stiffness'], off['onset_stiffness']) - 1)}",
                      flush=True)  # fmt: skip
    return rows


def curve(quick: bool) -> dict:
    out: dict = {}
    webers = (0.05, 0.2) if quick else CURVE
    for ch, sets in CHANNELS.items():
        base = [*sets, "channel.delay_ms=20"]
        dur = 3.0 if quick else None
        off = run("paper_experiment", [*base, *codec_sets(None)], dur)
        out[ch] = {"off": off, "on": []}
        for w in webers:
            on = run("paper_experiment", [*base, *codec_sets(w)], dur)
            out[ch]["on"].append((w, on))
            print(f"curve {ch} {w:.0%}: reduction {on['red_hsi']:.3f}/{on['red_to']:.3f}, T_p "
                  f"x{ratio(on['t_p'], off['t_p']):.3f}, T_tau "
                  f"x{ratio(on['t_tau'], off['t_tau']):.3f}", flush=True)  # fmt: skip
    return out


def passivity(quick: bool) -> list[dict]:
    rows = []
    classes = {"loss": 20} if quick else CLASS_VALUES
    for name in ("paper_experiment", "stiff_wall"):
        for sweep, value in classes.items():
            case = make_case(sweep, value)
            # (TDPA with the energy deadband too, and with Weber's rule on it: they only add
            # packets)
            for ch, sets in [*CHANNELS.items(),
                             ("tdpa, energy deadband", (*CHANNELS["tdpa"], *EXCHANGE)),
                             ("tdpa, energy deadband, Weber",
                              (*CHANNELS["tdpa"], *TDPA_VARIANTS[WEBER_LABEL]))]:
                r = run(name, [*sets, *case.overrides(), *codec_sets(WEBER)],
                        2.0 if quick else None)  # fmt: skip
                rows.append({"config": name, "case": case.label, "sweep": sweep, "channel": ch,
                             "r": r})  # fmt: skip
                print(f"passivity {name} {case.label} {ch}: min balance {r['min_balance']:.2e}, "
                      f"min energy {r['min_energy']:.2e}, reduction {r['red_hsi']:.3f}/"
                      f"{r['red_to']:.3f}", flush=True)  # fmt: skip
    return rows


def split(quick: bool) -> list[dict]:
    rows = []
    names = ("stiff_wall",) if quick else ("paper_experiment", "stiff_wall")
    for name in names:
        for ch, sets in CHANNELS.items():
            base = [*sets, "channel.delay_ms=20"]
            dur = 2.0 if quick else None
            off = run(name, [*base, *codec_sets(None)], dur)
            for label, (extra, consts, modes) in SPLIT.items():
                if ch not in modes:
                    continue
                with constants(**consts):
                    on = run(name, [*base, *codec_sets(WEBER), *extra], dur)
                rows.append({"config": name, "channel": ch, "variant": label, "on": on,
                             "off": off})  # fmt: skip
                print(f"split {name} {ch} {label}: reduction {on['red_hsi']:.3f}/"
                      f"{on['red_to']:.3f}, T_p {_pct(ratio(on['t_p'], off['t_p']) - 1)}",
                      flush=True)  # fmt: skip
    return rows


def plot_curve(data: dict, path: Path) -> None:
    fig = Figure(figsize=(10, 4))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    for ch, d in data.items():
        w = [100 * x for x, _ in d["on"]]
        red = [100 * 0.5 * (r["red_hsi"] + r["red_to"]) for _, r in d["on"]]
        ax1.plot(w, red, "o-", label=ch)
        for key, style in (("t_p", "o-"), ("t_tau", "s--")):
            ax2.plot(w, [ratio(r[key], d["off"][key]) for _, r in d["on"]], style,
                     label=f"{ch} {'T_p' if key == 't_p' else 'T_tau'}")  # fmt: skip
    ax1.set(xlabel="deadband (Weber fraction, %)", ylabel="packets saved, mean of both ways (%)",
            title="reduction")  # fmt: skip
    ax2.axhline(1.1, color="grey", lw=0.8, ls=":")
    ax2.set(xlabel="deadband (Weber fraction, %)", ylabel="with codec / without",
            title="transparency (paper experiment, 20 ms)")  # fmt: skip
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


GOAL_REDUCTION, GOAL_CHANGE = 0.85, 0.10


def misses(acc: list[dict]) -> str:
    """The acceptance rows that miss a goal, each with what it misses (the study's own figures)."""
    out = []
    for row in acc:
        on, off = row["on"], row["off"]
        bad = [f"reduction {100 * r:.1f} %" for r in (on["red_hsi"], on["red_to"])
               if r < GOAL_REDUCTION][:1]  # fmt: skip
        for key, label in (("t_p", "T_p"), ("t_tau", "T_tau"), ("stiffness", "stiffness"),
                           ("mass", "mass")):  # fmt: skip
            change = ratio(on[key], off[key]) - 1
            if not abs(change) <= GOAL_CHANGE:
                bad.append(f"{label} {_pct(change)}")
        if bad:
            out.append(f"{row['config']} {row['delay']} ms {row['channel']} ({', '.join(bad)})")
    return "; ".join(out) + "." if out else "none."


def report(
    acc: list[dict], cur: dict, pas: list[dict], spl: list[dict], out: Path, quick: bool,
    ene: list[dict] | None = None, tdpa: list[dict] | None = None,
    pace: list[dict] | None = None,
) -> Path:
    ene = ene or []
    lines = ["# The deadband codec, measured", "",
             "Generated by `tools/codec_study.py`" + (" --quick" if quick else "") +
             " (one-process fast mode, deterministic). Design: docs/codec.md.", "",
             f"## Acceptance: {WEBER:.0%} deadband against the same channel without codec", "",
             "Reduction: packets not sent, HSI -> TO / TO -> HSI. Changes are with / without "
             "the codec at the same D. Stiffness: the operator's force against the HSI's "
             "penetration of the wall (foam) surface while the TO is in contact; mass: the "
             "displayed mass fitted in free space (joint mean). D = 1 ms stands for 0: the "
             "codec needs a delay of at least one tick (at D = 0 the ports couple directly).",
             "",
             "Felt: what the codec changed tick by tick against the same run without it, the "
             "RMS difference of the TO's joint angles and of the operator's torque (relative "
             "to its RMS): the perceptual measure, next to the ratios of the integrals (T_p "
             "of a tiny figure at D = 1 ms is a ratio of tiny numbers).", "",
             "RMS: T_p and T_tau as the RMS over the run of what they integrate (the HSI's "
             "and the TO's joint angles' difference, mrad; the operator's and the "
             "environment's torque's, N m), without -> with the codec: what a position or "
             "force JND compares (docs/codec.md).", "",
             "| config | D (ms) | channel | reduction | T_p | T_tau | stiffness | mass | "
             "felt: TO angle (mrad) | felt: torque | RMS T_p (mrad) | RMS T_tau (N m) | "
             "min two-port energy (J) | min port balance (J) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for row in acc:
        on, off = row["on"], row["off"]
        dq, dtau = felt(on, off)
        lines.append(
            f"| {row['config']} | {row['delay']} | {row['channel']} | "
            f"{100 * on['red_hsi']:.1f} / {100 * on['red_to']:.1f} % | "
            f"{_pct(ratio(on['t_p'], off['t_p']) - 1)} | "
            f"{_pct(ratio(on['t_tau'], off['t_tau']) - 1)} | "
            f"{_pct(ratio(on['stiffness'], off['stiffness']) - 1)} | "
            f"{_pct(ratio(on['mass'], off['mass']) - 1)} | {dq:.2f} | {100 * dtau:.1f} % | "
            f"{1e3 * off['rms_p']:.2f} -> {1e3 * on['rms_p']:.2f} | "
            f"{off['rms_tau']:.3f} -> {on['rms_tau']:.3f} | "
            f"{on['min_energy']:.2g} | {on['min_balance']:.2g} |"
        )  # fmt: skip
    lines += ["", "Missed (the goal: reduction >= 85 % each way, T_p, T_tau, stiffness and mass "
              "within 10 % of the same channel without codec): " + misses(acc)]  # fmt: skip
    if cur:
        lines += ["", "## Reduction and transparency against the deadband", "",
                  "Paper experiment, D = 20 ms. ![curve](figures/codec_curve.png)", "",
                  "| channel | deadband | reduction | T_p ratio | T_tau ratio |",
                  "|---|---|---|---|---|"]  # fmt: skip
    for ch, d in cur.items():
        for w, r in d["on"]:
            lines.append(f"| {ch} | {w:.0%} | {100 * r['red_hsi']:.1f} / "
                         f"{100 * r['red_to']:.1f} % | "
                         f"{ratio(r['t_p'], d['off']['t_p']):.3f} | "
                         f"{ratio(r['t_tau'], d['off']['t_tau']):.3f} |")  # fmt: skip
    low = min((min(p["r"]["min_energy"], p["r"]["min_balance"]) for p in pas), default=0.0)
    passivity_head = ["", f"## Passivity with the codec over the impairment classes ({WEBER:.0%})",
              "", f"Lowest of every run's two-port energy and port balance: {low:.3g} J "
              f"({'passive' if low >= PASSIVE_J else 'NOT PASSIVE'}: the criterion is "
              f">= {PASSIVE_J:g} J).", "",
              "| config | network | channel | complete | min two-port energy (J) | "
              "min port balance (J) | reduction |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += passivity_head if pas else []
    for p in pas:
        r = p["r"]
        lines.append(f"| {p['config']} | {p['case']} ({SWEEPS[p['sweep']][1]}) | {p['channel']} | "
                     f"{'yes' if r['complete'] else 'STOPPED'} | {r['min_energy']:.2g} | "
                     f"{r['min_balance']:.2g} | {100 * r['red_hsi']:.1f} / "
                     f"{100 * r['red_to']:.1f} % |")  # fmt: skip
    split_head = ["", "## Where the error comes from (20 ms, 10 %)", "",
              "Each row switches one part of the codec off or replaces it; changes against the "
              "same channel without codec.", "",
              "| config | channel | codec | reduction | T_p | T_tau | stiffness | mass |",
              "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += split_head if spl else []
    for row in spl:
        on, off = row["on"], row["off"]
        lines.append(f"| {row['config']} | {row['channel']} | {row['variant']} | "
                     + _changes(on, off) + "|")  # fmt: skip
    energy_head = ["", "## TDPA's energy deadband (channel.deadband.exchange_j, 10 %)", "",
                   "A site also sends once that much energy has crossed its port since its "
                   "last packet (docs/codec.md); changes against TDPA without codec at the "
                   "same D.", "",
                   "| config | D (ms) | codec | reduction | T_p | T_tau | stiffness | mass | "
                   "RMS T_p (mrad) | RMS T_tau (N m) | min two-port energy (J) | "
                   "min port balance (J) |",
                   "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += energy_head if ene else []
    for row in ene:
        on, off = row["on"], row["off"]
        lines.append(f"| {row['config']} | {row['delay']} | {row['variant']} | "
                     + _changes(on, off) + "| "
                     f"{1e3 * off['rms_p']:.2f} -> {1e3 * on['rms_p']:.2f} | "
                     f"{off['rms_tau']:.3f} -> {on['rms_tau']:.3f} | "
                     f"{on['min_energy']:.2g} | {on['min_balance']:.2g} |")  # fmt: skip
    if ene:
        lines += ["", "Missed with the energy deadband: " + misses(ene)]
    lines += _tdpa_section(tdpa or [], "## TDPA: every energy setting, and the stiffness at "
                           f"the onset of contact ({WEBER:.0%})")
    lines += _tdpa_section(pace or [], "## TDPA: the energy deadband's pace "
                           f"(channel.deadband.exchange_min_ticks, {WEBER:.0%})")
    path = out / "codec_study.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _tdpa_section(tdpa: list[dict], head: str) -> list[str]:
    """A table of TDPA rows with the onset stiffness (parts 6 and 7)."""
    lines = ["", head, "",
             "Changes against TDPA without codec at the same D; every energy setting with the "
             "linear reconstruction from the HSI. Onset: the felt stiffness fitted over the "
             f"first {ONSET_S:g} s of contact only (docs/codec.md, \"TDPA's stiff wall\"), "
             "N/m without -> with.", "",
             "| config | D (ms) | codec | reduction | T_p | T_tau | stiffness | mass | "
             "onset stiffness | onset K (N/m) | RMS T_p (mrad) | RMS T_tau (N m) | "
             "min two-port energy (J) | min port balance (J) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"] if tdpa else []
    for row in tdpa:
        on, off = row["on"], row["off"]
        lines.append(f"| {row['config']} | {row['delay']} | {row['variant']} | "
                     + _changes(on, off) + "| "
                     f"{_pct(ratio(on['onset_stiffness'], off['onset_stiffness']) - 1)} | "
                     f"{off['onset_stiffness']:.0f} -> {on['onset_stiffness']:.0f} | "
                     f"{1e3 * off['rms_p']:.2f} -> {1e3 * on['rms_p']:.2f} | "
                     f"{off['rms_tau']:.3f} -> {on['rms_tau']:.3f} | "
                     f"{on['min_energy']:.2g} | {on['min_balance']:.2g} |")  # fmt: skip
    return lines


PARTS = ("acceptance", "curve", "passivity", "split", "energy", "tdpa", "pace")


def parse_rows(text: str) -> tuple[set[tuple[str, int, str]], str | None]:
    """``config:D:channel,...`` as a set of rows, or the problem with it."""
    rows = set()
    for item in text.split(","):
        bits = item.split(":")
        if len(bits) != 3 or bits[0] not in CONFIGS or bits[2] not in CHANNELS \
                or not bits[1].isdigit() or int(bits[1]) not in DELAYS_MS:  # fmt: skip
            return set(), (f"--rows: '{item}' is not config:D:channel with config one of "
                           f"{', '.join(CONFIGS)}, D one of {DELAYS_MS}, channel one of "
                           f"{', '.join(CHANNELS)}")  # fmt: skip
        rows.add((bits[0], int(bits[1]), bits[2]))
    return rows, None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("--quick", action="store_true", help="a few short runs (for the tests)")
    p.add_argument("--out", type=Path, help="report folder (default: a new temporary one)")
    p.add_argument("--parts", default=",".join(PARTS),
                   help=f"which parts to run, of {','.join(PARTS)} (default: all)")
    p.add_argument("--rows", help="acceptance rows only, e.g. stiff_wall:1:tdpa,foam:1:wave "
                   "(config:D in ms:channel)")  # fmt: skip
    p.add_argument("--codec-set", action="append", default=[], metavar="KEY=VALUE",
                   help="an override for the acceptance part's runs with the codec, e.g. "
                   "channel.deadband.exchange_j=1e-5 (repeatable)")  # fmt: skip
    args = p.parse_args(argv)
    parts = set(args.parts.split(","))
    problem = next((f"--parts: no part '{x}' (of {', '.join(PARTS)})"
                    for x in sorted(parts) if x not in PARTS), None)  # fmt: skip
    only = None
    if problem is None and args.rows:
        only, problem = parse_rows(args.rows)
    out = args.out or Path(tempfile.mkdtemp(prefix="codec_study_"))
    problem = problem or report_folder_problem(out)
    if problem:
        print(f"codec_study: error: {problem}", file=sys.stderr)
        return 2
    (out / "figures").mkdir(parents=True, exist_ok=True)
    extra = tuple(args.codec_set)
    acc = acceptance(args.quick, only, extra) if "acceptance" in parts else []
    cur = curve(args.quick) if "curve" in parts else {}
    pas = passivity(args.quick) if "passivity" in parts else []
    spl = split(args.quick) if "split" in parts else []
    ene = energy(args.quick) if "energy" in parts else []
    tdp = tdpa_rows(args.quick) if "tdpa" in parts else []
    pac = tdpa_rows(args.quick, PACE) if "pace" in parts else []
    if cur:
        plot_curve(cur, out / "figures" / "codec_curve.png")
    print(f"report: {report(acc, cur, pas, spl, out, args.quick, ene, tdp, pac)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
