"""Issue 4, item 5: tools/reproduce_paper.py in its quick mode (few points, short runs) into a
temporary folder, and the physics its figures claim: the delay's mass effect (Fig 3, Fig 6),
the loss of stiffness at the wall (Fig 6), the monotonic trends of Fig 7, and measured points
that agree with the discrete model wherever they settle (Figs 3, 4)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from teleop_rt.analysis.impedance import displayed_impedance

ROOT = Path(__file__).resolve().parents[1]


def _load_tool():
    spec = importlib.util.spec_from_file_location(
        "reproduce_paper", ROOT / "tools" / "reproduce_paper.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while it loads
    spec.loader.exec_module(module)
    return module


rp = _load_tool()


@pytest.fixture(scope="module")
def quick(tmp_path_factory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("paper")
    args = rp.parse_args(["--quick", "--out", str(out)])
    assert args.quick and args.out == out
    return rp.reproduce(args.quick, args.out), out


def test_writes_the_figures_and_the_report(quick) -> None:
    _, out = quick
    names = ("fig3_mass.png", "fig4_spring.png", "fig6_experiment.png", "fig7_masses.png")
    for name in names:
        png = out / "figures" / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    report = (out / "paper_reproduction.md").read_text()
    for name in names:
        assert f"](figures/{name})" in report
    assert "## What differs from the paper" in report


def _cases(results: dict, fig: str) -> list[dict]:
    return [c for key, _, _ in rp.PANELS for c in results[fig][key]]


def test_measured_points_match_the_discrete_model_where_settled(quick) -> None:
    results, _ = quick
    for fig in ("fig3", "fig4"):
        for c in _cases(results, fig):
            if c["n_settled"]:
                # 0.1 % of |Z_h| at every settled frequency (issue 4, item 3)
                assert c["dev_discrete"] <= rp.SETTLED_TOL, (fig, c["label"], c["b"])
                # and 2 % / 2 deg of the continuous model for omega <= 10 rad/s, behind a
                # delay too: its wave filter has the matched cut-off (33.0 Hz for 30 Hz)
                if not math.isnan(c["dev_cont_mag"]):
                    assert c["dev_cont_mag"] < rp.CONT_TOL_MAG, (fig, c["label"], c["b"])
                    assert c["dev_cont_deg"] < rp.CONT_TOL_DEG, (fig, c["label"], c["b"])


def test_the_continuous_model_uses_the_matched_cutoff(quick) -> None:
    results, _ = quick
    delayed = [c for c in _cases(results, "fig3") if c["params"].delay_s > 0 and c["n_settled"]]
    assert delayed
    for c in delayed:
        assert c["params"].wave_filter_hz == rp.FILTER_HZ  # the chain runs the nominal 30 Hz
        cont = rp.continuous_params(c["params"], rp.DT)
        assert cont.wave_filter_hz == pytest.approx(33.014, abs=1e-3)
    # the report states both cut-offs
    report = (quick[1] / "paper_reproduction.md").read_text()
    assert "matched cut-off of 33.01 Hz" in report


def test_settling_follows_the_models_poles(quick) -> None:
    results, _ = quick
    cases = _cases(results, "fig3") + _cases(results, "fig4")
    for c in cases:
        if c["radius"] > 1.0 + 1e-6:  # the chain rings up: no number may be reported
            assert c["n_settled"] == 0, (c["env"], c["label"], c["b"])
            assert np.all(np.isnan(c["measured"]))
    # the delayed mass behind b = 10: the sampled termination's pole at -m / (T2 b) = -20
    delayed = [c for c in results["fig3"]["delay_paper_b"] if c["params"].delay_s > 0]
    assert delayed and all(c["n_settled"] == 0 for c in delayed)
    assert all(
        c["radius"] == pytest.approx(rp.ENV_VALUE / (rp.T_NOMINAL * 10.0), rel=0.01)
        for c in delayed
    )
    # everything else in quick mode settles (T_d = 0 always does)
    others = [c for c in cases if c["radius"] <= 1.0 + 1e-9]
    assert others and all(c["n_settled"] == c["n_points"] for c in others)


def test_fig3_displayed_mass_rises_with_the_delay(quick) -> None:
    results, _ = quick
    # measured, b = 500: |Z_h| at the lowest frequency grows with T_d
    stable = results["fig3"]["delay_stable_b"]
    assert len(stable) >= 2 and all(c["settled"][0] for c in stable)
    low = [abs(c["measured"][0]) for c in stable]
    assert all(b > a * 1.5 for a, b in zip(low, low[1:], strict=False)), low
    assert results["summary"]["fig3"]["low_freq_rises_with_delay"]
    # the paper's model, b = 10 and b = 500, at 0.2 rad/s: mass 10 + b T_d (eq 29 added to Z_e)
    for key in ("delay_paper_b", "delay_stable_b"):
        for c in results["fig3"][key]:
            p = rp.paper_model(c["params"], "pade")
            mass = displayed_impedance(0.2j, p).imag / 0.2
            assert mass == pytest.approx(rp.ENV_VALUE + p.b * p.delay_s, rel=0.01)


def test_fig6_mass_effect_and_loss_of_stiffness(quick) -> None:
    rows = quick[0]["fig6"]["rows"]
    assert [r["delay_ms"] for r in rows] == sorted(r["delay_ms"] for r in rows)
    assert len(rows) >= 2 and all(r["stopped"] is None for r in rows)
    for r in rows:
        # displayed joint-space mass in free space: M1/c1 + b (T_d + filter delay), eq 29
        for m in r["mass_fit"]:
            assert m == pytest.approx(r["mass_expected"], rel=0.03), r["delay_ms"]
    for a, b in zip(rows, rows[1:], strict=False):
        assert b["peak_tau_free"] > 2.0 * a["peak_tau_free"]  # the operator pushes a mass
        assert b["pen_hsi_m"] > 3.0 * a["pen_hsi_m"]  # the wall yields on the HSI side ...
        assert b["pen_to_m"] < 2e-3  # ... while the TO stays at the wall (5000 N/m)
        assert b["stiffness_cart"] < 0.2 * a["stiffness_cart"]
    # eq 30 in joint space: the HSI-TO offset at the wall is tau_h T / b (static hold)
    delayed = [r for r in rows if r["delay_ms"] > 0]
    assert delayed and all(r["joint_compliance_err"] < 0.02 for r in delayed)


def test_fig7_trends_are_monotonic(quick) -> None:
    m7 = quick[0]["fig7"]
    t_p_m2 = [r["t_p"] for r in m7["to"]]
    t_tau_m1 = [r["t_tau"] for r in m7["hsi"]]
    assert all(b > a for a, b in zip(t_p_m2, t_p_m2[1:], strict=False)), t_p_m2
    assert all(b > a for a, b in zip(t_tau_m1, t_tau_m1[1:], strict=False)), t_tau_m1
    assert m7["t_p_increasing_in_m2"] and m7["t_tau_increasing_in_m1"]
    assert all(r["stopped"] is None for r in m7["to"] + m7["hsi"])
