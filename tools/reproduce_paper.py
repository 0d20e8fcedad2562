#!/usr/bin/env python3
"""Reproduce Kuschel & Buss's Figs 3, 4, 6 and 7 with this project's own blocks (issue 4, item 5).

    python tools/reproduce_paper.py [--quick] [--out DIR]

Writes DIR/figures/fig3_mass.png, fig4_spring.png, fig6_experiment.png, fig7_masses.png and the
report DIR/paper_reproduction.md (DIR defaults to docs/), and prints progress and the numbers.
``--quick`` runs few points and short runs (for the tests; its figures are coarse); without
``--out`` it writes into a new temporary folder, never over the committed docs/. DIR is
checked (and created) before any work.

* Figs 3 and 4: |Z_h(j omega)| against |Z_e(j omega)| for a mass Z_e = 10 s and a spring
  Z_e = 10/s with a damper operator Z_o = 10 (joint space, SI): several delays T_d with
  T1 = T2 = 0.05 s and wave impedance (a) b = Z_o = 10, (b) b = 500 (the paper does not state
  b; below 200 the sampled chain cannot hold the delayed mass), (c) several T1 = T2 with
  T_d = 0. Lines: the paper's model (eq 20-24, the
  delay as eq 28's 1st-order Pade), the same with the exact delay, and the exact discrete
  model of the 1 kHz chain as implemented (with its 30 Hz received-wave filter when T_d > 0).
  Points: ``teleop_rt.analysis.bode.measure_displayed_impedance`` on the running blocks; a
  frequency that does not settle is marked at the bottom of the axes, never drawn as a value.
* Fig 6: the paper experiment (configs/paper_experiment.yaml: free space, foam, stiff wall,
  scripted hand operator) at several delays: tool trajectories of HSI (dashed) and TO
  (solid); the mass effect in free space; the loss of stiffness at the wall; task time.
* Fig 7: T_p (eq 18) against M2 and T_tau against M1 (T_d = 0), each from full sessions.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.analysis import experiment  # noqa: E402
from teleop_rt.analysis.bode import BodeResult, measure_displayed_impedance  # noqa: E402
from teleop_rt.analysis.discrete import (  # noqa: E402
    DT,
    chain_modes,
    continuous_params,
    displayed_impedance_z,
    filter_group_delay_s,
    matched_filter_hz,
    spectral_radius,
)
from teleop_rt.analysis.impedance import ImpedanceParams, displayed_impedance  # noqa: E402
from teleop_rt.output import report_folder_problem  # noqa: E402
from teleop_rt.session import Session  # noqa: E402

EXPERIMENT = ROOT / "configs" / "paper_experiment.yaml"

# --- Figs 3 and 4: the chain -------------------------------------------------------------------
Z_O = 10.0  # operator damping, N m s/rad (paper Sec 4)
ENV_VALUE = 10.0  # Z_e = 10 s (kg m^2) or 10 / s (N m/rad)
M_VIRTUAL = 0.1  # M1 = M2, kg m^2 (this project's virtual masses); gains set T1, T2
T_NOMINAL = 0.05  # T1 = T2, s (paper Sec 4)
# Wave impedance. The paper does not state b. A joint-space mass m behind the sampled TO
# termination has a local pole at z = -m / (T2 b) (the channel's TO side solves omega_t from the
# torque the mass measured one tick earlier): it rings up for b < m / T2 = 200 N m s/rad at any
# delay (``teleop_rt.analysis.discrete.spectral_radius``). b = 500 keeps every mass case stable
# and makes the mass effect b T_d visible against 10 kg m^2 at delays of 10-100 ms.
B_WAVE = 500.0
B_PAPER = 10.0  # b = Z_o, a matched operator: the paper-like picture (the paper omits b)
FILTER_HZ = 30.0  # the project's received-wave filter (needed: without it every mass or spring
# behind a delay rings up in the 1 kHz chain)
JOINT = 1  # the excited joint (the SCARA's second)
SETTLED_TOL = 1e-3  # measured vs discrete model, relative (issue 4: 0.1 %)
CONT_TOL_MAG, CONT_TOL_DEG, CONT_OMEGA_MAX = 0.02, 2.0, 10.0  # issue 4: 2 %, 2 deg, <= 10 rad/s

# --- Fig 6: task definition ----------------------------------------------------------------------
TASK_TOL_M = 0.002  # task done when HSI and TO tools stay within 2 mm of the final target


@dataclass(frozen=True)
class Settings:
    """What one run of the script computes (full or quick)."""

    quick: bool
    delays_34_s: tuple[float, ...]
    time_constants_34_s: tuple[float, ...]
    omegas_measured: tuple[float, ...]
    max_seconds: float  # simulated time per frequency before "not settled"
    delays_6_ms: tuple[int, ...]  # trend runs of Fig 6
    shown_6_ms: tuple[int, ...]  # trajectories drawn
    duration_6_s: float  # the experiment run extended to see the task end
    masses_7: tuple[float, ...]


FULL = Settings(
    quick=False,
    delays_34_s=(0.0, 0.01, 0.05, 0.1),
    time_constants_34_s=(0.01, 0.05, 0.2, 0.5),
    omegas_measured=(0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0),
    max_seconds=40.0,
    delays_6_ms=(0, 10, 20, 50, 100, 150, 200),
    shown_6_ms=(0, 50, 200),
    duration_6_s=20.0,
    masses_7=(0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0),
)
QUICK = Settings(
    quick=True,
    delays_34_s=(0.0, 0.02),
    time_constants_34_s=(0.05, 0.2),
    omegas_measured=(5.0, 50.0),
    max_seconds=10.0,
    delays_6_ms=(0, 50),
    shown_6_ms=(0, 50),
    duration_6_s=13.0,
    masses_7=(0.05, 0.2, 0.8),
)


def log(msg: str) -> None:
    print(msg, flush=True)


# =============================================================================================
# Figs 3 and 4
# =============================================================================================
def chain_params(env: str, delay_s: float, t1: float, t2: float, b: float = B_WAVE):
    """The chain as implemented (filter on behind a delay); gains realise T1 and T2 (eq 31-32).

    T1 = M1 / (c1 Z_o) -> c1 = M1 / (Z_o T1); T2 = M2 / c2 -> c2 = M2 / T2.
    """
    env_kw = {"env_mass": ENV_VALUE} if env == "mass" else {"env_stiffness": ENV_VALUE}
    return ImpedanceParams(
        m1=M_VIRTUAL,
        m2=M_VIRTUAL,
        c1=M_VIRTUAL / (Z_O * t1),
        c2=M_VIRTUAL / t2,
        z_o=Z_O,
        b=b,
        delay_s=delay_s,
        wave_filter_hz=FILTER_HZ if delay_s > 0 else None,
        **env_kw,
    )


def paper_model(p: ImpedanceParams, model: str) -> ImpedanceParams:
    """The paper's continuous model: no received-wave filter, delay ``model`` (pade / exact)."""
    return replace(p, delay_model=model, wave_filter_hz=None)


def z_env(env: str, omega: np.ndarray) -> np.ndarray:
    s = 1j * np.asarray(omega)
    return ENV_VALUE * s if env == "mass" else ENV_VALUE / s


def effective_delay_s(delay_s: float) -> float:
    """T_d plus the 1 kHz filter's DC group delay (teleop_rt.analysis.displayed)."""
    return delay_s + filter_group_delay_s(FILTER_HZ, DT) if delay_s > 0 else 0.0


def nominal_continuous(p: ImpedanceParams) -> ImpedanceParams:
    """The continuous model with the filter at its nominal cut-off (what the comparison used
    before the matched cut-off, ``discrete.matched_filter_hz``): shows what matching buys."""
    return replace(continuous_params(p, DT), wave_filter_hz=p.wave_filter_hz if p.delay_s else None)


def _mag_deg(measured: np.ndarray, model: np.ndarray) -> tuple[float, float]:
    """Largest relative magnitude error and phase error (deg) of measured against model."""
    ratio = measured / model
    return float(np.max(np.abs(np.abs(ratio) - 1.0))), float(np.max(np.abs(np.angle(ratio, True))))


def case_numbers(env: str, label: str, value: float, res: BodeResult) -> dict:
    """Agreement figures of one measured sweep (relative errors, degrees)."""
    p = res.params
    ok = res.settled
    w, meas = res.omega, res.measured
    out: dict = {
        "env": env,
        "label": label,
        "value": value,
        "params": p,
        "omega": w,
        "measured": meas,
        "settled": ok,
        "reasons": [pt.reason for pt in res.points],
        "n_points": len(w),
        "n_settled": int(ok.sum()),
        "radius": spectral_radius(p),
        "dev_discrete": math.nan,
        "dev_cont_mag": math.nan,
        "dev_cont_deg": math.nan,
        "dev_nominal_mag": math.nan,
        "dev_nominal_deg": math.nan,
        "dev_paper_mag": math.nan,
        "dev_paper_deg": math.nan,
        "lowest_omega": math.nan,
        "ratio_lowest": math.nan,
        "ratio_lowest_model": math.nan,
        "displayed_mass": math.nan,
        "expected": math.nan,
        "paper": math.nan,
    }
    if ok.any():
        disc = res.discrete[ok]
        out["dev_discrete"] = float(np.max(np.abs(meas[ok] / disc - 1.0)))
        low = ok & (w <= CONT_OMEGA_MAX)
        if low.any():
            # exact delay, the filter (T_d > 0) at its matched cut-off: res.analytic
            mag_deg = _mag_deg(meas[low], res.analytic[low])
            out["dev_cont_mag"], out["dev_cont_deg"] = mag_deg
            nominal = displayed_impedance(1j * w[low], nominal_continuous(p))
            out["dev_nominal_mag"], out["dev_nominal_deg"] = _mag_deg(meas[low], nominal)
        # the paper's model (Pade, no filter) where eq 28 holds: omega < 1 / (3 T_d)
        valid = low & (w * 3.0 * p.delay_s < 1.0)
        if valid.any():
            pade = displayed_impedance(1j * w[valid], paper_model(p, "pade"))
            out["dev_paper_mag"] = float(np.max(np.abs(np.abs(meas[valid] / pade) - 1.0)))
            out["dev_paper_deg"] = float(np.max(np.abs(np.degrees(np.angle(meas[valid] / pade)))))
        i = int(np.flatnonzero(ok)[0])
        out["lowest_omega"] = float(w[i])
        out["ratio_lowest"] = float(abs(meas[i] / z_env(env, w[i])))
        out["ratio_lowest_model"] = float(abs(res.discrete[i] / z_env(env, w[i])))
        if env == "mass":  # Im Z_h / omega: the displayed mass at the lowest frequency
            out["displayed_mass"] = float(meas[i].imag / w[i])
    if env == "mass":  # low-frequency limit: eq 29's b T added to Z_e
        out["expected"] = ENV_VALUE + p.b * effective_delay_s(p.delay_s)
        out["paper"] = ENV_VALUE + p.b * p.delay_s
    return out


def measure_case(p: ImpedanceParams, st: Settings) -> BodeResult:
    return measure_displayed_impedance(
        p, st.omegas_measured, joint=JOINT, max_seconds=st.max_seconds
    )


# (key, wave impedance b, title); T_d = 0 couples the channel directly: b plays no part there
PANELS = (
    ("delay_paper_b", B_PAPER, "(a) delays, T1 = T2 = 0.05 s, b = {b:g} N m s/rad (= Z_o)"),
    ("delay_stable_b", B_WAVE, "(b) delays, T1 = T2 = 0.05 s, b = {b:g} N m s/rad"),
    ("time_constant", B_WAVE, "(c) robot time constants T1 = T2, T_d = 0"),
)


def impedance_figure_data(env: str, st: Settings) -> dict:
    """The three panels of Fig 3 (env 'mass') or Fig 4 ('spring'): measured sweeps, numbers."""
    panels: dict = {}
    for key, b, _ in PANELS:
        panels[key] = []
        values = st.time_constants_34_s if key == "time_constant" else st.delays_34_s
        for v in values:
            t0 = time.perf_counter()
            if key == "time_constant":
                p, label = chain_params(env, 0.0, v, v, b), f"T1 = T2 = {v:g} s"
            else:
                p, label = chain_params(env, v, T_NOMINAL, T_NOMINAL, b), f"T_d = {v * 1e3:g} ms"
            c = case_numbers(env, label, v, measure_case(p, st))
            c["b"] = b
            if key == "time_constant":  # the lags, not a mass, shape Z_h here
                c["displayed_mass"] = c["expected"] = c["paper"] = math.nan
            panels[key].append(c)
            log(f"  {env}, b = {b:g}, {label}: {_case_line(c)}  ({time.perf_counter() - t0:.1f} s)")
    return panels


def _case_line(c: dict) -> str:
    text = f"settled {c['n_settled']}/{c['n_points']} (model |z|max {c['radius']:.6f})"
    if c["n_settled"]:
        text += (
            f", vs z-model {_pct(c['dev_discrete'], 3)}, vs continuous (<= 10 rad/s) "
            f"{_pct(c['dev_cont_mag'])} / {_deg(c['dev_cont_deg'])}"
        )
    if c["env"] == "mass" and not math.isnan(c["displayed_mass"]):
        text += (
            f", displayed mass {c['displayed_mass']:.4g} kg m^2 at {c['lowest_omega']:g} rad/s "
            f"(10 + b (T_d + filter) = {c['expected']:.4g}, 10 + b T_d = {c['paper']:.4g})"
        )
    return text


def plot_impedance_figure(env: str, panels: dict, path: Path) -> None:
    dense = np.geomspace(0.1, 1000.0, 500)
    fig = Figure(figsize=(9.5, 13.5), layout="constrained")
    axes = [fig.add_subplot(3, 1, i + 1) for i in range(3)]
    for ax, (key, b, title) in zip(axes, PANELS, strict=True):
        ax.plot(dense, np.abs(z_env(env, dense)), "-", color="k", lw=2.4, alpha=0.6, label="|Z_e|")
        any_unsettled = False
        for i, c in enumerate(panels[key]):
            color = f"C{i}"
            p = c["params"]
            pade = displayed_impedance(1j * dense, paper_model(p, "pade"))
            ax.plot(dense, np.abs(pade), "-", color=color, lw=1.4, label=c["label"])
            if p.delay_s > 0:
                exact = displayed_impedance(1j * dense, paper_model(p, "exact"))
                ax.plot(dense, np.abs(exact), "--", color=color, lw=0.9)
            ax.plot(dense, np.abs(displayed_impedance_z(dense, p)), ":", color=color, lw=1.3)
            ok = c["settled"]
            ax.plot(
                c["omega"][ok],
                np.abs(c["measured"][ok]),
                "o",
                color=color,
                mfc="none",
                ms=7,
                mew=1.3,
            )
            if (~ok).any():
                any_unsettled = True
                ax.plot(
                    c["omega"][~ok],
                    np.full((~ok).sum(), 0.03 + 0.035 * i),
                    "v",
                    color=color,
                    transform=ax.get_xaxis_transform(),
                    clip_on=False,
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(dense[0], dense[-1])
        ax.grid(True, which="both", alpha=0.3)
        ax.set_ylabel("|Z| (N m s/rad)")
        ax.set_title(title.format(b=b), fontsize="medium", loc="left")
        first = ax.legend(
            loc="upper center",
            fontsize="small",
            title="paper's model (Pade)",
            title_fontsize="small",
        )
        ax.add_artist(first)
        styles = [
            Line2D([], [], color="gray", ls="--", lw=0.9, label="exact delay e^{-2 T_d s}"),
            Line2D([], [], color="gray", ls=":", lw=1.3, label="1 kHz chain as implemented"),
            Line2D(
                [],
                [],
                color="gray",
                ls="",
                marker="o",
                mfc="none",
                label="measured, running blocks",
            ),
        ]
        if any_unsettled:
            styles.append(
                Line2D([], [], color="gray", ls="", marker="v", label="not settled: no value")
            )
        ax.legend(
            handles=styles,
            # the spring's curves are high on the left; keep clear of the triangles below
            loc="upper left" if env == "mass" else "lower left",
            bbox_to_anchor=(0.0, 0.0 if env == "mass" else 0.16, 1.0, 1.0),
            fontsize="small",
        )
    axes[-1].set_xlabel("omega (rad/s)")
    what = "mass Z_e = 10 s" if env == "mass" else "spring Z_e = 10/s"
    fig.suptitle(
        f"Fig {3 if env == 'mass' else 4}: displayed impedance |Z_h| against |Z_e| "
        f"(thick), {what}, Z_o = {Z_O:g} N m s/rad"
    )
    FigureCanvasAgg(fig).print_png(str(path))


# =============================================================================================
# Fig 6: the paper experiment at several delays
# =============================================================================================
def run_experiment(delay_ms: int, duration_s: float, overrides: tuple[str, ...] = ()) -> dict:
    """One session of configs/paper_experiment.yaml; every tick's signals (tick-start values)."""
    cfg = config.load(
        EXPERIMENT, [f"channel.delay_ms={delay_ms}", f"duration_s={duration_s}", *overrides]
    )
    session = Session(cfg)
    n_ticks, n = cfg.n_ticks, session.n
    q_h, q_t = np.zeros((n_ticks, n)), np.zeros((n_ticks, n))
    v_h, tau_h, tau_e = np.zeros((n_ticks, n)), np.zeros((n_ticks, n)), np.zeros((n_ticks, n))
    ref, force = np.zeros((n_ticks, 3)), np.zeros((n_ticks, 3))
    fb_h, fb_t = session.hsi.feedback, session.to.feedback
    world_h = session.hsi.backend.world

    def observe(s: Session) -> None:
        k = s.tick - 1
        q_h[k], q_t[k], v_h[k] = fb_h.q, fb_t.q, fb_h.v
        tau_h[k], tau_e[k] = s.tau_h, s.tau_e
        ref[k], force[k] = world_h.reference, world_h.force

    t0 = time.perf_counter()
    summary = session.run(observer=observe)
    wall = time.perf_counter() - t0
    ticks = summary.ticks
    x_h = np.array([session.hsi.model.ee_position(q)[:2] for q in q_h[:ticks]])
    x_t = np.array([session.to.model.ee_position(q)[:2] for q in q_t[:ticks]])
    return {
        "cfg": cfg,
        "delay_ms": delay_ms,
        "summary": summary,
        "wall_s": wall,
        "t": np.arange(ticks) * cfg.dt,
        "q_h": q_h[:ticks],
        "q_t": q_t[:ticks],
        "v_h": v_h[:ticks],
        "tau_h": tau_h[:ticks],
        "tau_e": tau_e[:ticks],
        "ref": ref[:ticks, :2],
        "force": force[:ticks, :2],
        "x_h": x_h,
        "x_t": x_t,
    }


def experiment_geometry(cfg) -> dict:
    """Phases of the scripted task (teleop_rt.analysis.experiment), and the paper's length."""
    g = experiment.experiment_geometry(cfg)
    return {
        "free_end_s": g.free_end_s,
        "wall_point": g.wall_point,
        "wall_normal": g.wall_normal,
        "wall_hold_s": g.wall_hold_s,
        "final_target": g.final_target,
        "last_waypoint_s": g.last_waypoint_s,
        "paper_duration_s": 12.0,
    }


def experiment_numbers(run: dict, geo: dict) -> dict:
    """Mass effect, stiffness at the wall and task time of one run (SI; positions in m)."""
    cfg, t = run["cfg"], run["t"]
    dt = cfg.dt
    m1, c1 = float(cfg.hsi.virtual_mass), float(cfg.hsi.controller.kp)
    b = float(cfg.channel.wave_impedance)
    t_eff = effective_delay_s(run["delay_ms"] * 1e-3)
    # free space: tau_h = m a_h + d v_h per joint (a_h: the tick's acceleration)
    free = t < geo["free_end_s"]
    masses = experiment.displayed_mass(run["v_h"], run["tau_h"], dt, free)
    peak_tau = float(np.abs(run["tau_h"][free]).max())
    peak_force = float(np.linalg.norm(run["force"][free], axis=1).max())
    # wall: penetration along the wall normal, averaged over the last half of the hold
    h0, h1 = geo["wall_hold_s"]
    hold = (t >= h0) & (t < h1)
    nrm, pt = geo["wall_normal"], geo["wall_point"]
    pen_h = float(np.mean(experiment.penetration(run["x_h"][hold], pt, nrm)))
    pen_t = float(np.mean(experiment.penetration(run["x_t"][hold], pt, nrm)))
    f_n = float(np.mean(-run["force"][hold] @ nrm))  # the hand pushing into the wall, N
    dq = (run["q_h"] - run["q_t"])[hold].mean(axis=0)
    dq_expected = run["tau_h"][hold].mean(axis=0) * t_eff / b  # eq 30: compliance T / b
    big = np.abs(dq_expected) > 1e-9
    dq_err = float(np.max(np.abs(dq[big] / dq_expected[big] - 1.0))) if big.any() else math.nan
    # task time: both tools within TASK_TOL_M of the final target from then to the run's end
    err = np.maximum(
        np.linalg.norm(run["x_h"] - geo["final_target"], axis=1),
        np.linalg.norm(run["x_t"] - geo["final_target"], axis=1),
    )
    task = experiment.task_time(t, err, TASK_TOL_M)
    err_12 = float(err[min(len(t) - 1, round(geo["paper_duration_s"] / dt) - 1)])
    return {
        "delay_ms": run["delay_ms"],
        "t_eff_s": t_eff,
        "peak_tau_free": peak_tau,
        "peak_force_free": peak_force,
        "mass_fit": masses,
        "mass_expected": m1 / c1 + b * t_eff,
        "mass_paper": m1 / c1 + b * run["delay_ms"] * 1e-3,
        "pen_hsi_m": pen_h,
        "pen_to_m": pen_t,
        "deviation_m": pen_h - pen_t,
        "wall_force_n": f_n,
        "stiffness_cart": experiment.felt_stiffness(f_n, pen_h),
        "joint_compliance_err": dq_err,
        "task_time_s": task,
        "error_at_12s_m": err_12,
        "t_p": run["summary"].t_p_total,
        "t_tau": run["summary"].t_tau_total,
        "stopped": run["summary"].stopped_early,
        "wall_s": run["wall_s"],
    }


def experiment_data(st: Settings) -> dict:
    runs, rows = {}, []
    geo = None
    for d in sorted(set(st.delays_6_ms) | set(st.shown_6_ms)):
        run = run_experiment(d, st.duration_6_s)
        geo = geo or experiment_geometry(run["cfg"])
        row = experiment_numbers(run, geo)
        rows.append(row)
        if d in st.shown_6_ms:
            runs[d] = run
        task = row["task_time_s"]
        log(
            f"  T_d = {d:3d} ms: free-space peak tau_h {row['peak_tau_free']:.3f} N m, displayed "
            f"mass {row['mass_fit'][0]:.4f}/{row['mass_fit'][1]:.4f} (expected "
            f"{row['mass_expected']:.4f}) kg m^2; wall: HSI {row['pen_hsi_m'] * 1e3:.1f} mm, TO "
            f"{row['pen_to_m'] * 1e3:.1f} mm in, {row['stiffness_cart']:.0f} N/m; task "
            f"{'not done' if math.isnan(task) else f'{task:.2f} s'}  ({row['wall_s']:.1f} s)"
        )
        if row["stopped"]:
            log(f"    run stopped early: {row['stopped']}")
    return {"runs": runs, "rows": rows, "geometry": geo}


def plot_experiment(data: dict, path: Path) -> None:
    runs, rows, geo = data["runs"], data["rows"], data["geometry"]
    shown = sorted(runs)
    fig = Figure(figsize=(13, 3.0 * len(shown) + 6.5), layout="constrained")
    grid = fig.add_gridspec(len(shown) + 2, 2, height_ratios=[1.0] * len(shown) + [1.1, 1.1])
    for r, d in enumerate(shown):
        run = runs[d]
        for col, (axis, name) in enumerate(((0, "x"), (1, "y"))):
            ax = fig.add_subplot(grid[r, col])
            t = run["t"]
            ax.plot(t, run["ref"][:, axis], ":", color="0.5", lw=1.0, label="hand reference")
            ax.plot(t, run["x_t"][:, axis], "-", color="C1", lw=1.3, label="TO")
            ax.plot(t, run["x_h"][:, axis], "--", color="C0", lw=1.3, label="HSI")
            if name == "x":
                foam = next(e for e in run["cfg"].environment if e.kind == "foam")
                ax.axhline(foam.point_m[0], color="C2", lw=0.8, label="foam surface")
            else:
                ax.axhline(geo["wall_point"][1], color="C3", lw=0.8, label="wall surface")
            ax.axvline(geo["paper_duration_s"], color="k", lw=0.6, alpha=0.4)
            ax.set_ylabel(f"tool {name} (m)")
            ax.set_title(f"T_d = {d} ms: tool {name}", fontsize="medium", loc="left")
            ax.grid(True, alpha=0.3)
            if r == 0:
                ax.legend(loc="best", fontsize="x-small", ncol=2)
            if r == len(shown) - 1:
                ax.set_xlabel("t (s)")
    d_ms = np.array([row["delay_ms"] for row in rows], float)
    # mass effect
    ax = fig.add_subplot(grid[len(shown), 0])
    for j in range(len(rows[0]["mass_fit"])):
        ax.plot(
            d_ms,
            [row["mass_fit"][j] for row in rows],
            "o",
            mfc="none",
            color=f"C{j}",
            label=f"fitted, joint {j + 1}",
        )
    ax.plot(
        d_ms,
        [row["mass_expected"] for row in rows],
        "-",
        color="k",
        label="M1/c1 + b (T_d + filter delay)",
    )
    ax.plot(d_ms, [row["mass_paper"] for row in rows], "--", color="0.5", label="M1/c1 + b T_d")
    ax.set_ylabel("displayed mass (kg m^2)")
    ax.set_title("mass effect in free space (eq 29)", fontsize="medium", loc="left")
    ax2 = ax.twinx()
    ax2.plot(
        d_ms,
        [row["peak_tau_free"] for row in rows],
        "s-",
        color="C3",
        ms=4,
        lw=0.8,
        label="peak operator torque",
    )
    ax2.set_ylabel("peak |tau_h| in free space (N m)", color="C3")
    ax.legend(loc="upper left", fontsize="x-small")
    ax2.legend(loc="lower right", fontsize="x-small")
    # stiffness
    ax = fig.add_subplot(grid[len(shown), 1])
    ax.plot(
        d_ms,
        [row["pen_hsi_m"] * 1e3 for row in rows],
        "o--",
        color="C0",
        label="HSI beyond the wall surface",
    )
    ax.plot(
        d_ms, [row["pen_to_m"] * 1e3 for row in rows], "o-", color="C1", label="TO into the wall"
    )
    ax.set_ylabel("penetration at the wall (mm)")
    ax.set_title("loss of stiffness in contact (eq 30)", fontsize="medium", loc="left")
    ax2 = ax.twinx()
    ax2.semilogy(
        d_ms,
        [row["stiffness_cart"] for row in rows],
        "s-",
        color="C3",
        ms=4,
        lw=0.8,
        label="displayed stiffness (force / HSI penetration)",
    )
    ax2.axhline(5000.0, color="C3", lw=0.6, ls=":")
    ax2.set_ylabel("N/m (wall: 5000)", color="C3")
    handles = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    # below the panel, not over it: the three curves cross its whole height
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.06), ncols=2,
              fontsize="x-small")  # fmt: skip
    # task time
    ax = fig.add_subplot(grid[len(shown) + 1, 0])
    task = np.array([row["task_time_s"] for row in rows])
    done = ~np.isnan(task)
    ax.plot(d_ms[done], task[done], "o-", color="k", label="task time")
    if (~done).any():
        ax.plot(
            d_ms[~done],
            np.full((~done).sum(), geo["paper_duration_s"]),
            "x",
            color="r",
            label="not done by the end of the run",
        )
    ax.axhline(geo["last_waypoint_s"], color="0.5", lw=0.8, ls=":", label="last hand waypoint")
    ax.axhline(geo["paper_duration_s"], color="0.5", lw=0.8, ls="--", label="paper run (12 s)")
    ax.set_ylabel("task time (s)")
    ax.set_xlabel("one-way delay T_d (ms)")
    ax.set_title(
        f"task time: HSI and TO within {TASK_TOL_M * 1e3:g} mm of the final target for good",
        fontsize="medium",
        loc="left",
    )
    ax.legend(loc="upper left", fontsize="x-small")
    ax.grid(True, alpha=0.3)
    # transparency measures
    ax = fig.add_subplot(grid[len(shown) + 1, 1])
    ax.semilogy(d_ms, [row["t_p"] for row in rows], "o-", color="C0", label="T_p (rad^2 s)")
    ax.semilogy(d_ms, [row["t_tau"] for row in rows], "s--", color="C1", label="T_tau (N^2 m^2 s)")
    ax.set_xlabel("one-way delay T_d (ms)")
    ax.set_title("transparency measures (eq 18) over the run", fontsize="medium", loc="left")
    ax.legend(loc="best", fontsize="x-small")
    ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(
        "Fig 6: the paper experiment (free space -> foam -> stiff wall) with delay; "
        "HSI dashed, TO solid"
    )
    FigureCanvasAgg(fig).print_png(str(path))


# =============================================================================================
# Fig 7: T_p against M2 and T_tau against M1
# =============================================================================================
def masses_data(st: Settings) -> dict:
    out: dict = {"masses": list(st.masses_7), "to": [], "hsi": []}
    geo = None
    for side in ("to", "hsi"):
        for m in st.masses_7:
            run = run_experiment(0, 12.0, (f"{side}.virtual_mass={m}",))
            geo = geo or experiment_geometry(run["cfg"])
            summary = run["summary"]
            h0, h1 = geo["wall_hold_s"]
            hold = (run["t"] >= h0) & (run["t"] < h1)
            row = {
                "mass": m,
                "t_p": summary.t_p_total,
                "t_tau": summary.t_tau_total,
                # chatter against the wall: spread of the TO's contact torque over the hold
                "wall_tau_e_std": float(run["tau_e"][hold].std(axis=0).max()),
                "stopped": summary.stopped_early,
            }
            out[side].append(row)
            log(
                f"  {'M2' if side == 'to' else 'M1'} = {m:5g} kg m^2: T_p {row['t_p']:.4g} rad^2 "
                f"s, T_tau {row['t_tau']:.4g} N^2 m^2 s, tau_e spread at the wall "
                f"{row['wall_tau_e_std']:.3f} N m  ({run['wall_s']:.1f} s)"
                + (f"  stopped early: {row['stopped']}" if row["stopped"] else "")
            )
    out["t_p_increasing_in_m2"] = _increasing([r["t_p"] for r in out["to"]])
    out["t_tau_increasing_in_m1"] = _increasing([r["t_tau"] for r in out["hsi"]])
    out["t_p_increasing_in_m1"] = _increasing([r["t_p"] for r in out["hsi"]])
    out["t_tau_increasing_in_m2"] = _increasing([r["t_tau"] for r in out["to"]])
    return out


def _increasing(values: list[float]) -> bool:
    return all(b > a for a, b in zip(values, values[1:], strict=False))


def plot_masses(data: dict, path: Path) -> None:
    m = np.array(data["masses"])
    fig = Figure(figsize=(8, 7.5), layout="constrained")
    for i, (key, unit, title) in enumerate(
        (
            ("t_p", "rad^2 s", "position deviation T_p: large for a heavy TO"),
            ("t_tau", "N^2 m^2 s", "torque deviation T_tau: large for a heavy HSI"),
        )
    ):
        ax = fig.add_subplot(2, 1, i + 1)
        ax.loglog(
            m, [r[key] for r in data["to"]], "o-", color="C1", label="against M2 (TO), M1 = 0.1"
        )
        ax.loglog(
            m, [r[key] for r in data["hsi"]], "s--", color="C0", label="against M1 (HSI), M2 = 0.1"
        )
        ax.set_ylabel(f"{key.replace('t_tau', 'T_tau').replace('t_p', 'T_p')} ({unit})")
        ax.set_title(title, fontsize="medium", loc="left")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper left", fontsize="small")
    fig.axes[-1].set_xlabel("virtual mass (kg m^2)")
    fig.suptitle(
        "Fig 7: transparency (eq 18) against the robots' virtual masses, T_d = 0\n"
        "paper experiment, c1 = 2, c2 = 20 N m s/rad fixed"
    )
    FigureCanvasAgg(fig).print_png(str(path))


# =============================================================================================
# report
# =============================================================================================
def _pct(x: float, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    return f"{x * 100:.{digits}g} %" if x * 100 < 0.01 else f"{x * 100:.{digits}f} %"


def _reasons(c: dict) -> str:
    """' (slow 2, changing 1)': why the case's unsettled points did not settle."""
    counts: dict[str, int] = {}
    for reason in c["reasons"]:
        if reason != "settled":
            counts[reason] = counts.get(reason, 0) + 1
    return f" ({', '.join(f'{k} {v}' for k, v in counts.items())})" if counts else ""


def _deg(x: float) -> str:
    return "n/a" if x is None or math.isnan(x) else f"{x:.2f} deg"


def _nanmax(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return max(vals) if vals else math.nan


def _cases(results: dict, fig: str) -> list[dict]:
    return [c for key, _, _ in PANELS for c in results[fig][key]]


def _near(c: dict, omega: float) -> float:
    """Measured |Z_h / Z_e| at the settled point nearest omega (nan if none)."""
    ok = c["settled"]
    if not ok.any():
        return math.nan
    w = c["omega"][ok]
    i = int(np.argmin(np.abs(np.log(w / omega))))
    return float(abs(c["measured"][ok][i] / z_env(c["env"], w[i])))


def pade_departure(delay_s: float, env: str, b: float, tol: float = 0.1) -> float:
    """Lowest omega (rad/s) where the paper's Pade model is off the exact delay by > tol."""
    if delay_s <= 0:
        return math.inf
    p = chain_params(env, delay_s, T_NOMINAL, T_NOMINAL, b)
    w = np.geomspace(0.1, 1000.0, 2000)
    pade = displayed_impedance(1j * w, paper_model(p, "pade"))
    exact = displayed_impedance(1j * w, paper_model(p, "exact"))
    off = np.flatnonzero(np.abs(np.abs(pade / exact) - 1.0) > tol)
    return float(w[off[0]]) if len(off) else math.inf


def slowest_mode(p: ImpedanceParams) -> float:
    """|z| of the z-model's slowest decaying mode other than z = 1 (a spring's offset)."""
    modes = chain_modes(p, DT)
    modes = modes[np.abs(modes - 1.0) > 1e-7]
    return float(np.abs(modes).max()) if len(modes) else 0.0


def summarise(results: dict) -> dict:
    """Per-figure headline numbers (also what docs/reproduction.md quotes)."""
    out: dict = {}
    for fig in ("fig3", "fig4"):
        cases = _cases(results, fig)
        stable = results[fig]["delay_stable_b"]
        out[fig] = {
            "n_points": sum(c["n_points"] for c in cases),
            "n_settled": sum(c["n_settled"] for c in cases),
            "dev_discrete": _nanmax([c["dev_discrete"] for c in cases]),
            "dev_cont_mag": _nanmax([c["dev_cont_mag"] for c in cases]),
            "dev_cont_deg": _nanmax([c["dev_cont_deg"] for c in cases]),
            "dev_nominal_mag": _nanmax([c["dev_nominal_mag"] for c in cases]),
            "dev_nominal_deg": _nanmax([c["dev_nominal_deg"] for c in cases]),
            # unsettled points in cases the z-model calls stable (|z|max <= 1 + 1e-9)
            "unsettled_but_stable": sum(
                c["n_points"] - c["n_settled"] for c in cases if c["radius"] <= 1.0 + 1e-9
            ),
            "settled_but_unstable": sum(c["n_settled"] for c in cases if c["radius"] > 1.0 + 1e-9),
            "low_freq_by_delay": [
                abs(c["measured"][0]) if c["settled"][0] else math.nan for c in stable
            ],
        }
        out[fig]["low_freq_rises_with_delay"] = _increasing(out[fig]["low_freq_by_delay"])
    out["fig6"] = {
        "mass_rises": _increasing([r["mass_fit"][0] for r in results["fig6"]["rows"]]),
        "pen_hsi_rises": _increasing([r["pen_hsi_m"] for r in results["fig6"]["rows"]]),
    }
    out["fig7"] = {k: v for k, v in results["fig7"].items() if k.startswith("t_")}
    return out


def write_report(results: dict, st: Settings, out_dir: Path, seconds: float) -> Path:
    lines: list[str] = []
    add = lines.append
    s = summarise(results)
    add("# Paper reproduction: Kuschel & Buss, Figs 3, 4, 6 and 7")
    add("")
    add(
        f"Generated by `python tools/reproduce_paper.py{' --quick' if st.quick else ''}` "
        f"in {seconds:.0f} s (wall time on the machine that ran it). Every number below "
        "comes from that run. All quantities are per joint in joint space (the paper's "
        "single-link analysis): inertia kg m^2, torque N m, damping and wave impedance "
        "N m s/rad, stiffness N m/rad."
    )
    add("")
    # --- Figs 3 and 4 ----------------------------------------------------------------------
    add("## Figs 3 and 4: displayed impedance |Z_h| against |Z_e|")
    add("")
    add("![Fig 3](figures/fig3_mass.png)")
    add("")
    add("![Fig 4](figures/fig4_spring.png)")
    add("")
    c1 = M_VIRTUAL / (Z_O * T_NOMINAL)
    c2 = M_VIRTUAL / T_NOMINAL
    add(
        f"The chain: damper operator Z_o = {Z_O:g}; M1 = M2 = {M_VIRTUAL:g} kg m^2 with P "
        f"gains c1 = M1 / (Z_o T1), c2 = M2 / T2 (T1 = T2 = {T_NOMINAL:g} s: c1 = {c1:g}, "
        f"c2 = {c2:g} N m s/rad; only T1 and T2 enter the linear chain); the environment "
        f"Z_e = 10 s or 10/s in joint space on the SCARA's joint {JOINT + 1}. The paper does "
        f"not state the wave impedance b: panel (a) uses b = Z_o = {B_PAPER:g}, panel (b) "
        f"b = {B_WAVE:g} (why: below). Lines: the paper's model (eq 20-24 with the 1st-order "
        "Pade delay of eq 28, solid); the same with the exact delay e^{-2 T_d s} (dashed); the "
        "exact z-domain model of the 1 kHz chain as implemented (dotted: sampled plants, "
        "whole-tick delay lines, and the project's 30 Hz received-wave filter when T_d > 0). "
        "Circles: `measure_displayed_impedance` on the running blocks (an imposed operator "
        "velocity sine of 0.05 rad/s per frequency, lock-in after transients). Triangles at "
        "the bottom of a panel: frequencies whose measurement did not settle within "
        f"{st.max_seconds:g} s of simulated time; they have no value. A point settles when "
        "two consecutive lock-in windows agree to 1e-4, no signal grows, and the transient "
        "still in the estimate, extrapolated with the z-model's slowest mode (r / (1 - r) "
        "times the last change, r its decay per window), is below 1e-4 too; the reasons of "
        "those that did not are counted in the settled column. The continuous model the "
        "points are compared with is the implemented chain's: exact delay and, when T_d > 0, "
        f"the filter at its matched cut-off of {matched_filter_hz(FILTER_HZ, DT):.2f} Hz "
        f"(the continuous low-pass with the DC group delay of the 1 kHz {FILTER_HZ:g} Hz one, "
        f"{filter_group_delay_s(FILTER_HZ, DT) * 1e3:.2f} ms)."
    )
    add("")
    add(
        "| fig | panel | case | z-model max abs pole | settled | measured vs z-model (max) | "
        "vs continuous (matched filter), omega <= 10 (mag / phase) | vs paper's Pade "
        "model, omega <= 10 and "
        "< 1/(3 T_d) (mag / phase) | lowest settled omega: measured (model) abs(Z_h/Z_e) |"
    )
    add("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for fig in ("fig3", "fig4"):
        for key, b, _ in PANELS:
            panel = (
                "(c) T_d = 0"
                if key == "time_constant"
                else (f"({'a' if key == 'delay_paper_b' else 'b'}) b = {b:g}")
            )
            for c in results[fig][key]:
                ratio = (
                    "n/a"
                    if math.isnan(c["ratio_lowest"])
                    else f"{c['ratio_lowest']:.4f} ({c['ratio_lowest_model']:.4f}) at "
                    f"{c['lowest_omega']:g}"
                )
                add(
                    f"| {fig[-1]} | {panel} | {c['label']} | {c['radius']:.6f} | "
                    f"{c['n_settled']}/{c['n_points']}{_reasons(c)} | "
                    f"{_pct(c['dev_discrete'], 3)} | "
                    f"{_pct(c['dev_cont_mag'])} / {_deg(c['dev_cont_deg'])} | "
                    f"{_pct(c['dev_paper_mag'])} / {_deg(c['dev_paper_deg'])} | {ratio} |"
                )
    add("")
    f3, f4 = s["fig3"], s["fig4"]
    add(
        f"Agreement. {f3['n_settled']}/{f3['n_points']} measured points settled for the mass "
        f"and {f4['n_settled']}/{f4['n_points']} for the spring. Every settled point matches "
        f"the exact z-domain model of the implemented chain to {_pct(f3['dev_discrete'], 2)} "
        f"(mass) and {_pct(f4['dev_discrete'], 2)} (spring), and the continuous model of the "
        f"implemented chain (exact delay, matched filter) to {_pct(f3['dev_cont_mag'])} / "
        f"{_deg(f3['dev_cont_deg'])} and {_pct(f4['dev_cont_mag'])} / "
        f"{_deg(f4['dev_cont_deg'])} for omega <= 10 rad/s (issue 4 asks 0.1 % and 2 % / 2 "
        "deg). With the filter at its nominal "
        f"{FILTER_HZ:g} Hz the continuous model would be off by up to "
        f"{_pct(f3['dev_nominal_mag'])} / {_deg(f3['dev_nominal_deg'])} (mass) and "
        f"{_pct(f4['dev_nominal_mag'])} / {_deg(f4['dev_nominal_deg'])} (spring): its DC "
        "group delay is half a tick longer than the 1 kHz filter's, which weighs near the "
        "anti-resonances of |Z_h|."
    )
    add("")
    over = [
        (fig, c)
        for fig in ("fig3", "fig4")
        for c in _cases(results, fig)
        if c["dev_discrete"] > SETTLED_TOL
    ]
    if over:
        add(
            "Above the 0.1 %: "
            + "; ".join(
                f"Fig {fig[-1]} {c['label']}, b = {c['b']:g}: {_pct(c['dev_discrete'], 3)} at "
                + ", ".join(
                    f"{w:.4g} rad/s"
                    for w, z, ok in zip(c["omega"], c["measured"], c["settled"], strict=True)
                    if ok and abs(z / displayed_impedance_z(w, c["params"]) - 1.0) > SETTLED_TOL
                )
                for fig, c in over
            )
            + ". The settling test accepted these points although the transient it "
            "extrapolates was below 1e-4: a settled point is only as good as that test. They "
            "are shown as measured."
        )
        add("")
    paper_off = [
        (
            fig,
            _nanmax(
                [
                    c["dev_paper_mag"]
                    for c in _cases(results, fig)
                    if c["value"] > 0 and c["params"].delay_s > 0
                ]
            ),
        )
        for fig in ("fig3", "fig4")
    ]
    add(
        "Against the paper's own model (Pade delay, no filter) the measured chain differs, "
        "for omega <= 10 rad/s and omega < 1/(3 T_d), by up to "
        + " and ".join(f"{_pct(v)} (Fig {fig[-1]})" for fig, v in paper_off)
        + " behind a delay: mostly the filter's extra 4.82 ms of effective delay (the mass "
        "shows 10 + b (T_d + 4.82 ms)), and for the spring the shift of its anti-resonance, "
        "where |Z_h| is small; without delay the two agree to the 1 kHz sampling's O(omega dt)."
    )
    add("")
    if max(f3["dev_cont_mag"], f4["dev_cont_mag"]) > CONT_TOL_MAG:
        add("Above 2 % against the continuous model: see the table (column 'vs continuous').")
        add("")
    n_bad = f3["settled_but_unstable"] + f4["settled_but_unstable"]
    n_slow = f3["unsettled_but_stable"] + f4["unsettled_but_stable"]
    text = (
        "Settling agrees with the z-model's poles: no point settled where the model has a "
        f"pole outside the unit circle ({n_bad} such points); {n_slow} points did not settle "
        "although the model is (marginally) stable"
    )
    if n_slow:
        slow = ", ".join(
            f"|z| = {slowest_mode(c['params']):.6f} (Fig {fig[-1]}, {c['label']}, b = {c['b']:g})"
            for fig in ("fig3", "fig4")
            for c in _cases(results, fig)
            if c["params"].delay_s > 0
            and c["radius"] <= 1.0 + 1e-9
            and c["n_settled"] < c["n_points"]
        )
        text += (
            f": delayed chains whose slowest round-trip echo modes decay per tick as {slow}, "
            "time constants of seconds to tens of seconds, so within the "
            f"{st.max_seconds:g} s allowed per frequency two consecutive lock-in windows do "
            "not agree to 1e-4, or the transient extrapolated from their change stays above "
            "1e-4"
        )
    add(text + ".")
    add("")
    mass_b = results["fig3"]["delay_stable_b"]
    ringing_springs = [c for c in results["fig4"]["delay_paper_b"] if c["radius"] > 1.0 + 1e-6]
    add(
        "Why two values of b. A joint-space mass m behind the sampled TO termination has a "
        "pole at z = -m / (T2 b) whatever the delay (the channel's TO side solves omega_t "
        "from the torque the mass showed one tick earlier, a loop of gain m c2 / (M2 b)). "
        f"For b = {B_PAPER:g} it is at |z| = {ENV_VALUE / (T_NOMINAL * B_PAPER):g}: every "
        "delayed mass point of panel (a) diverges at once; only b > m / T2 = "
        f"{ENV_VALUE / T_NOMINAL:g} settles, hence panel (b) with b = {B_WAVE:g}. In "
        "continuous time Z_t = G_omega m s is passive for any b: this is a property of the "
        "1 kHz implementation (a sensed payload fed back through a velocity loop and a wave "
        "termination), not of the paper's model."
        + (
            " The delayed spring of panel (a) rings up where the z-model has a pole outside "
            "the unit circle ("
            + ", ".join(f"{c['label']}: {c['radius']:.5f}" for c in ringing_springs)
            + ") for the reason the paper's analysis gives: a velocity-controlled TO against "
            "a spring is active (Re Z_t < 0), and at long delays the 30 Hz filter no longer "
            "damps the round trip enough."
            if ringing_springs
            else ""
        )
    )
    add("")
    dm = ", ".join(
        f"{c['label']}: {c['displayed_mass']:.2f} (model {c['expected']:.2f}, paper "
        f"{c['paper']:.2f})"
        for c in mass_b
        if not math.isnan(c["displayed_mass"])
    )
    delays = [d for d in st.delays_34_s if d > 0]
    departures = ", ".join(
        f"{d * 1e3:g} ms: {pade_departure(d, 'mass', B_PAPER):.2g} rad/s" for d in delays
    )
    k = ENV_VALUE
    soft = ", ".join(
        f"{-(1.0 - 1.0 / (1.0 + k * effective_delay_s(d) / B_PAPER)) * 100:.1f} % at {d * 1e3:g} ms"
        for d in delays
    )
    cross = ", ".join(
        f"{math.sqrt(k / (B_WAVE * effective_delay_s(d))):.2g} rad/s at {d * 1e3:g} ms"
        for d in delays
    )
    tmax = effective_delay_s(max(st.delays_34_s))
    tc = results["fig3"]["time_constant"]
    add(
        "What the figures show, as the paper says. Mass (Fig 3): transparency at low "
        "frequency, spoiled by the delay's mass effect. With b = 10 the displayed mass "
        f"10 + b T is at most {B_PAPER * tmax / ENV_VALUE * 100:.0f} % above 10 and the effect "
        "shows mainly as the resonance of that mass with the channel's compliance near "
        "omega = sqrt(b / (m T)); with b = 500 the low-frequency displayed mass "
        f"(Im Z_h / omega, kg m^2) is {dm}: it rises with the delay, by b T with T the delay "
        "plus the filter's 4.82 ms (eq 29 added to Z_e). At high frequency |Z_h| falls below "
        "|Z_e|: the compliance effect of the HSI's and TO's lags. The Pade model departs from "
        f"the exact delay by 10 % (panel a) from {departures}, in line with its stated "
        "validity omega < 1/(3 T_d). Spring (Fig 4): with b = 10 the delay changes the "
        f"low-frequency stiffness to 1/(1/k + T/b) ({soft}), a smaller distortion than the "
        "mass's resonance, as the paper says; with b = 500 that series compliance is "
        "negligible, but the delay's mass b T adds to the spring's impedance and dominates it "
        f"above omega = sqrt(k / (b T)) ({cross}): how much the delay distorts which "
        "environment depends on b. T_d = 0 (panels c): |Z_h / Z_e| = |G_tau G_omega| = "
        "1 / (1 + (omega T)^2) for T1 = T2 = T; measured at about 10 rad/s "
        + ", ".join(f"{c['label']}: {_near(c, 10.0):.3f}" for c in tc)
        + ": the larger the robots' time constants, the narrower the transparent band "
        "(-3 dB at omega = 0.64 / T), the same for mass and spring."
    )
    add("")
    # --- Fig 6 -----------------------------------------------------------------------------
    exp = results["fig6"]
    geo = exp["geometry"]
    add("## Fig 6: the paper experiment with delay")
    add("")
    add("![Fig 6](figures/fig6_experiment.png)")
    add("")
    add(
        f"`configs/paper_experiment.yaml` (two SCARAs, M1 = M2 = 0.1 kg m^2, c1 = 2, "
        f"c2 = 20 N m s/rad, b = 2 N m s/rad, 30 Hz wave filter, a scripted hand operator: a "
        f"300 N/m, 20 N s/m Cartesian spring-damper to minimum-jerk waypoints) run for "
        f"{st.duration_6_s:g} s instead of 12 s (the hand holds its last waypoint) so that the "
        "task's end can be seen. Definitions:"
    )
    add("")
    add(
        f"* mass effect: the displayed joint-space mass fitted over the free-space stroke "
        f"(t < {geo['free_end_s']:g} s) as tau_h = m a_h + d v_h per joint, against "
        "M1/c1 + b T (the HSI's own M1/c1 plus eq 29 with T = T_d + the filter's 4.82 ms DC "
        "group delay); and the peak operator joint torque in free space;"
    )
    add(
        f"* stiffness: over the last half of the hold against the wall "
        f"({geo['wall_hold_s'][0]:g}-{geo['wall_hold_s'][1]:g} s), how far the HSI tool is "
        "beyond the wall surface and the TO tool in the wall; displayed stiffness = hand force "
        "normal to the wall / HSI penetration; and eq 30 in joint space: q_h - q_t = tau_h T / b;"
    )
    add(
        f"* task time: the time after which both the HSI and the TO tool stay within "
        f"{TASK_TOL_M * 1e3:g} mm of the task's final target (the last waypoint, reached by the "
        f"hand reference at {geo['last_waypoint_s']:g} s); the error at 12 s (the paper's run "
        "length) is listed too."
    )
    add("")
    add(
        "| T_d (ms) | peak tau_h free (N m) | displayed mass j1 / j2 (kg m^2) | M1/c1 + b T | "
        "M1/c1 + b T_d | HSI beyond wall (mm) | TO in wall (mm) | displayed stiffness (N/m) | "
        "eq 30 joint check | task time (s) | error at 12 s (mm) | T_p | T_tau |"
    )
    add("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in exp["rows"]:
        task = "not done" if math.isnan(r["task_time_s"]) else f"{r['task_time_s']:.2f}"
        add(
            f"| {r['delay_ms']} | {r['peak_tau_free']:.3f} | {r['mass_fit'][0]:.4f} / "
            f"{r['mass_fit'][1]:.4f} | {r['mass_expected']:.4f} | {r['mass_paper']:.4f} | "
            f"{r['pen_hsi_m'] * 1e3:.2f} | {r['pen_to_m'] * 1e3:.2f} | "
            f"{r['stiffness_cart']:.0f} | {_pct(r['joint_compliance_err'], 2)} | {task} | "
            f"{r['error_at_12s_m'] * 1e3:.2f} | {r['t_p']:.3g} | {r['t_tau']:.3g} |"
        )
    add("")
    add(_fig6_text(exp["rows"]))
    add("")
    # --- Fig 7 -----------------------------------------------------------------------------
    m7 = results["fig7"]
    add("## Fig 7: T_p against M2, T_tau against M1 (T_d = 0)")
    add("")
    add("![Fig 7](figures/fig7_masses.png)")
    add("")
    add(
        "The paper experiment at T_d = 0 with one virtual mass changed at a time (the other "
        "0.1 kg m^2; gains c1 = 2 and c2 = 20 N m s/rad unchanged, so T1 and T2 grow with the "
        "mass). T_p and T_tau are the sessions' own eq 18 figures (sums over both joints)."
    )
    add("")
    add("| mass (kg m^2) | T_p, M2 swept | T_tau, M2 swept | T_p, M1 swept | T_tau, M1 swept |")
    add("| --- | --- | --- | --- | --- |")
    for a, b in zip(m7["to"], m7["hsi"], strict=True):
        add(
            f"| {a['mass']:g} | {a['t_p']:.4g} | {a['t_tau']:.4g} | {b['t_p']:.4g} | "
            f"{b['t_tau']:.4g} |"
        )
    add("")
    add(_fig7_text(m7))
    add("")
    # --- differences ---------------------------------------------------------------------------
    add("## What differs from the paper, and why")
    add("")
    for item in _differences():
        add(f"* {item}")
    add("")
    path = out_dir / "paper_reproduction.md"
    path.write_text("\n".join(lines))
    return path


def _fig6_text(rows: list[dict]) -> str:
    r0, rl = rows[0], rows[-1]
    masses = [
        (r["delay_ms"], max(abs(m / r["mass_expected"] - 1) for m in r["mass_fit"])) for r in rows
    ]
    small = [f"{d} ms: {_pct(e, 1)}" for d, e in masses]
    checks = [r for r in rows if not math.isnan(r["joint_compliance_err"])]
    static = [r for r in checks if r["joint_compliance_err"] < 0.02]
    moving = [r for r in checks if r["joint_compliance_err"] >= 0.02]
    done = [r for r in rows if not math.isnan(r["task_time_s"])]
    undone = [r["delay_ms"] for r in rows if math.isnan(r["task_time_s"])]
    text = (
        f"The mass effect is there and grows with the delay: the peak operator torque in "
        f"free space grows from {r0['peak_tau_free']:.3f} N m at {r0['delay_ms']} ms to "
        f"{rl['peak_tau_free']:.3f} N m at {rl['delay_ms']} ms, and the fitted displayed mass "
        f"follows M1/c1 + b (T_d + filter delay) within {', '.join(small)}. The fit takes the "
        "low-frequency limit Z_c = b T s; at the stroke's few rad/s the channel shows "
        "j b tan(omega T), heavier by tan(omega T) / (omega T) - 1, which is a few per cent "
        "at 50 ms and tens of per cent at 150-200 ms. The stiffness drops: the HSI goes "
        f"{r0['pen_hsi_m'] * 1e3:.1f} mm beyond the wall surface at {r0['delay_ms']} ms and "
        f"{rl['pen_hsi_m'] * 1e3:.1f} mm at {rl['delay_ms']} ms while the TO stays "
        f"{r0['pen_to_m'] * 1e3:.1f}-{rl['pen_to_m'] * 1e3:.1f} mm in the wall: the operator "
        f"feels {r0['stiffness_cart']:.0f} N/m at {r0['delay_ms']} ms (the wall's 5000) and "
        f"{rl['stiffness_cart']:.0f} N/m at {rl['delay_ms']} ms."
    )
    if static:
        text += (
            " In joint space the HSI-TO offset at the wall is eq 30's compliance, "
            "q_h - q_t = tau_h T / b, within "
            f"{_pct(max(r['joint_compliance_err'] for r in static), 2)} for T_d = "
            + ", ".join(str(r["delay_ms"]) for r in static)
            + " ms"
        )
        if moving:
            text += (
                "; at "
                + ", ".join(str(r["delay_ms"]) for r in moving)
                + " ms the 0.5 s of hold are not static (the round trip and the heavy "
                "display ringing on the hand's spring outlast them), and the check does not "
                "apply"
            )
        text += "."
    text += (
        " Task time: "
        + ", ".join(f"{r['delay_ms']} ms {r['task_time_s']:.2f} s" for r in done)
        + (
            f"; not done by the end of the run at {', '.join(map(str, undone))} ms"
            if undone
            else ""
        )
        + ". Up to about 50 ms the scripted hand (a stiff 300 N/m spring on a fixed schedule) "
        "hides the delay and the schedule sets the task time; beyond, the displayed mass "
        "makes HSI and TO overshoot and ring on the hand's spring and the task ends later "
        f"(at 12 s, the paper's run length, the tools are still {rl['error_at_12s_m'] * 1e3:.1f}"
        f" mm off the target at {rl['delay_ms']} ms), as in the paper, whose human operator "
        "slowed down and at the largest delay did not finish."
    )
    return text


def _fig7_text(m7: dict) -> str:
    def yes(flag: bool) -> str:
        return "yes" if flag else "no"

    to = m7["to"]
    peak = max(to, key=lambda r: r["t_tau"])
    calm = [r for r in to if r["wall_tau_e_std"] < 0.1]
    chatter = [r for r in to if r["wall_tau_e_std"] >= 0.1]
    text = (
        f"The paper's trends hold: T_p increases monotonically with M2: "
        f"{yes(m7['t_p_increasing_in_m2'])} ({to[0]['t_p']:.3g} to {to[-1]['t_p']:.3g} rad^2 s "
        f"over the sweep); T_tau increases monotonically with M1: "
        f"{yes(m7['t_tau_increasing_in_m1'])} ({m7['hsi'][0]['t_tau']:.3g} to "
        f"{m7['hsi'][-1]['t_tau']:.3g} N^2 m^2 s). The cross effects: T_p against M1 "
        f"increasing: {yes(m7['t_p_increasing_in_m1'])}, but weakly (a heavy HSI lags the "
        "hand and the TO follows the HSI, so their angles stay together). T_tau against M2 "
        f"increasing: {yes(m7['t_tau_increasing_in_m2'])}"
        + (
            f"; it peaks at M2 = {peak['mass']:g} ({peak['t_tau']:.3g} N^2 m^2 s)."
            if not m7["t_tau_increasing_in_m2"]
            else ", and steeply above M2 = 0.2."
        )
    )
    if chatter:
        text += (
            " The cause is the stiff wall: with M2 >= "
            f"{min(r['mass'] for r in chatter):g} kg m^2 the TO chatters against it "
            f"throughout the hold (the spread of its contact torque is "
            + ", ".join(f"{r['wall_tau_e_std']:.2f}" for r in chatter)
            + " N m, against "
            + (f"<= {max(r['wall_tau_e_std'] for r in calm):.3f}" if calm else "n/a")
            + " N m for the lighter TOs). At T_d = 0, with the paper's damper operator Z_o, "
            "the loop HSI -> TO -> wall -> HSI is "
            "M1 s + c1 Z_o + c1 k / (s (1 + T2 s)) = 0, stable only while "
            "Z_o (M1 + c1 Z_o T2) > M1 T2 k (Z_o the operator's damping, k the wall in joint "
            "space): a slower TO (T2 = M2 / c2) against a stiff wall needs more operator "
            "damping than the hand gives, and the unilateral contact turns the instability "
            "into a bounded chatter. For a heavy HSI the condition tends to Z_o > T2 k"
        )
        heavy_hsi = [r for r in m7["hsi"] if r["wall_tau_e_std"] >= 0.1]
        if heavy_hsi:
            text += ", which is why the heaviest HSIs chatter too (spread " + ", ".join(
                f"{r['wall_tau_e_std']:.2f} N m at M1 = {r['mass']:g}" for r in heavy_hsi
            )
            text += ")"
        text += (
            ". The paper's heavy TO mainly spoils position; here it also spoils torque, "
            "through this contact instability."
        )
    return text


def _differences() -> list[str]:
    return [
        "Units: the paper's masses are in kg on its SCARAs; the analysis and this project "
        "work per joint in joint space (kg m^2, N m s/rad). Z_o = 10 and Z_e = 10 s, 10/s are "
        "taken as joint-space values.",
        f"The paper does not state b. Panel (a) of Figs 3/4 uses b = Z_o = {B_PAPER:g}; there "
        "the delayed mass cannot be measured at all, because the sampled TO termination with "
        f"a 10 kg m^2 mass is unstable for b < m / T2 = {ENV_VALUE / T_NOMINAL:g} (a "
        "discrete-time effect with no continuous-time counterpart), and the delayed spring "
        "rings up at 50 and 100 ms. Panel (b) uses b = 500, where every mass point settles. "
        "Which environment the delay distorts more depends on b: at b = 10 the mass's "
        "resonance against the spring's mild softening (the paper's statement), at b = 500 "
        "the spring is swamped by the delay's mass b T above about 1 rad/s.",
        "The implemented channel low-pass filters each received wave at 30 Hz (without it "
        "every mass or spring behind a delay rings up in the 1 kHz chain). The filter adds "
        "its DC group delay of 4.82 ms to the channel's effective delay, so the measured "
        "displayed mass is 10 + b (T_d + 4.82 ms), not the paper's 10 + b T_d, and it damps "
        "the standing-wave resonances of the exact delay; the implemented model (dotted) "
        "includes it, the paper's (solid) does not. A continuous model of the implemented "
        f"chain must give the filter its matched cut-off, {matched_filter_hz(FILTER_HZ, DT):.2f} "
        f"Hz, not {FILTER_HZ:g} Hz: the 1 kHz filter's DC group delay is half a tick shorter "
        "than 1 / (2 pi f_c), which near the anti-resonances of |Z_h| costs several per cent "
        "(the nominal figures are in the agreement paragraph above).",
        "The paper's Pade element (eq 28) is only valid for omega < 1/(3 T_d); above, the "
        "exact delay's curves depart from it, with resonances near odd multiples of "
        "pi / (2 T_d) (the standing waves of the lossless line).",
        "The operator in Fig 6 is a scripted hand (a Cartesian spring-damper on a fixed "
        "minimum-jerk schedule), not a person: it does not slow down or hesitate under delay. "
        "The task time is therefore defined by when both tools settle at the task's end, and "
        "the paper's 'operator was not able to complete the demanded trajectory' appears as "
        "HSI and TO still off the target at 12 s at the largest delays.",
        "Fig 7 sweeps this project's virtual masses (0.02-2 kg m^2; the paper's design point "
        "was 10 kg) at fixed gains; only the trends are comparable, not the values. A heavy "
        "TO also raises T_tau here, through a contact chatter at the stiff wall (above).",
        "Measured points that do not settle are reported as not settled, never as numbers; "
        "which ones, and why, is listed above.",
    ]


# =============================================================================================
def reproduce(quick: bool = False, out: Path | str | None = None) -> dict:
    """Compute everything, write the figures and the report; return the results."""
    st = QUICK if quick else FULL
    out_dir = Path(out) if out is not None else default_out(quick)
    fig_dir = out_dir / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    results: dict = {"settings": st}
    log(
        f"Figs 3 and 4 ({'quick' if quick else 'full'}): measured displayed impedance, "
        f"b = {B_PAPER:g} and {B_WAVE:g}, Z_o = {Z_O:g}"
    )
    for fig, env in (("fig3", "mass"), ("fig4", "spring")):
        results[fig] = impedance_figure_data(env, st)
        path = fig_dir / f"{fig}_{env}.png"
        plot_impedance_figure(env, results[fig], path)
        log(f"  wrote {path}")
    log("Fig 6: the paper experiment at several delays")
    results["fig6"] = experiment_data(st)
    path = fig_dir / "fig6_experiment.png"
    plot_experiment(results["fig6"], path)
    log(f"  wrote {path}")
    log("Fig 7: T_p against M2 and T_tau against M1, T_d = 0")
    results["fig7"] = masses_data(st)
    path = fig_dir / "fig7_masses.png"
    plot_masses(results["fig7"], path)
    log(f"  wrote {path}")
    results["summary"] = summarise(results)
    seconds = time.perf_counter() - start
    results["seconds"] = seconds
    report = write_report(results, st, out_dir, seconds)
    log(f"wrote {report} ({seconds:.1f} s)")
    return results


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "--quick",
        action="store_true",
        help="few points, short runs, coarse figures (tests); without --out into a new "
        "temporary folder, never over docs/",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="output folder: figures/*.png and paper_reproduction.md (default: docs/; with "
        "--quick a new temporary folder)",
    )
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = default_out(args.quick)
    return args


def default_out(quick: bool) -> Path:
    """docs/ for the full run; a new temporary folder for a quick one (its coarse figures
    must not replace the committed ones)."""
    return Path(tempfile.mkdtemp(prefix="teleop-rt-paper-quick-")) if quick else ROOT / "docs"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    problem = report_folder_problem(args.out)
    if problem is not None:
        print(f"reproduce_paper: error: {problem}", file=sys.stderr)
        return 2
    log(f"writing into {args.out}")
    reproduce(args.quick, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
