"""Issue 4, items 2-4: the displayed impedance measured on the running blocks (open chain,
1 kHz) against the exact discrete-time model (0.1 %) and the continuous model with the wave
filter at its matched cut-off (2 % / 2 deg for omega <= 10 rad/s), unsettled and slowly
settling chains reported as not settled, the displayed mass and stiffness fitted from
time-domain runs, and ``teleop-rt bode --json``."""

from __future__ import annotations

import json
import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from teleop_rt.analysis.bode import BodeResult, choose_window, measure_displayed_impedance
from teleop_rt.analysis.discrete import (
    displayed_impedance_z,
    spectral_radius,
    window_decay,
)
from teleop_rt.analysis.displayed import (
    effective_delay,
    fit_displayed_mass,
    fit_displayed_stiffness,
)
from teleop_rt.analysis.impedance import ControllerGains, ImpedanceParams, displayed_impedance
from teleop_rt.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
BASE = dict(m1=0.1, m2=0.1, c1=2.0, c2=20.0, z_o=10.0, b=2.0)  # the paper's chain
OMEGAS = (3.0, 10.0, 40.0)  # rad/s; few, a sweep point costs ~0.4 s here
PID = dict(
    c1=ControllerGains(kp=2.0, ki=5.0, kd=0.01, derivative_filter_s=0.005),
    c2=ControllerGains(kp=20.0, ki=100.0, kd=0.05, derivative_filter_s=0.002),
)

# (id, chain parameters): delays 0 to 50 ms, free space, joint springs and masses, filter on and
# off, PID controllers; all settle (spectral radius <= 1). Behind a delay a joint mass must stay
# below M2 b / c2 = 0.01 and a soft spring at 50 ms needs c_e >= k_e M2 / c2 (module docs).
FILTER = dict(wave_filter_hz=30.0)
CASES = {
    "0ms-free": dict(delay_s=0.0),
    "0ms-spring": dict(delay_s=0.0, env_stiffness=20.0),
    "20ms-free-nofilter": dict(delay_s=0.02),
    "20ms-free-filter": dict(delay_s=0.02, wave_filter_hz=30.0),
    "20ms-spring-filter": dict(delay_s=0.02, env_stiffness=20.0, wave_filter_hz=30.0),
    "0ms-mass-damper": dict(delay_s=0.0, env_mass=0.005, env_damping=0.5),
    "20ms-spring-pid-filter": dict(delay_s=0.02, env_stiffness=20.0, wave_filter_hz=30.0, **PID),
    # the nominal 30 Hz continuous filter is 4.9 % off here (test_analysis_impedance)
    "5ms-free-filter": dict(delay_s=0.005, **FILTER),
    "5ms-mass-filter": dict(delay_s=0.005, env_mass=0.005, **FILTER),
    "10ms-spring-filter": dict(delay_s=0.01, env_stiffness=20.0, **FILTER),
    "10ms-mass-damper-filter": dict(delay_s=0.01, env_mass=0.005, env_damping=0.5, **FILTER),
    "50ms-mass-filter": dict(delay_s=0.05, env_mass=0.005, **FILTER),
    "50ms-spring-damper-filter": dict(delay_s=0.05, env_stiffness=20.0, env_damping=0.2, **FILTER),
    "50ms-stiff-spring-filter": dict(delay_s=0.05, env_stiffness=1000.0, **FILTER),
}


def params_of(case: str) -> ImpedanceParams:
    return ImpedanceParams(**{**BASE, **CASES[case]})


@cache
def sweep(case: str) -> BodeResult:
    return measure_displayed_impedance(params_of(case), OMEGAS, joint=1)


@pytest.mark.parametrize("case", CASES)
def test_measured_matches_the_discrete_model_to_0_1_percent(case: str) -> None:
    result = sweep(case)
    assert spectral_radius(params_of(case)) <= 1.0 + 1e-9  # the model says: settles
    assert result.settled.all(), [pt.reason for pt in result.points]
    measured, discrete = result.measured, result.discrete
    # 0.1 % of |Z_h| (free space at zero delay displays exactly nothing: Z_h = 0)
    assert np.all(np.abs(measured - discrete) <= 1e-3 * np.abs(discrete) + 1e-12)
    # each settled with at most 1e-4 of transient left (extrapolated from the slowest mode)
    assert all(pt.error_bound <= 1e-4 for pt in result.points)
    # the frequencies were moved by at most 1 % to fit whole periods in whole round trips
    assert np.allclose(result.omega, OMEGAS, rtol=0.01)


@pytest.mark.parametrize("case", CASES)
def test_measured_matches_the_continuous_model_below_10_rad_s(case: str) -> None:
    result = sweep(case)
    low = np.array(OMEGAS) <= 10.0
    measured, analytic = result.measured[low], result.analytic[low]
    if case == "0ms-free":
        assert np.all(np.abs(measured) < 1e-12) and np.all(np.abs(analytic) < 1e-12)
        return
    # 2 % and 2 deg (issue 4); measured here: at most 0.3 % / 0.7 deg (50 ms, damped spring).
    # The analytic model gives the filter its matched cut-off (33.0 Hz for 30 Hz): with the
    # nominal one the 5 ms cases would be 4-5 % off.
    assert np.all(np.abs(np.abs(measured) / np.abs(analytic) - 1.0) < 0.02)
    assert np.all(np.abs(np.degrees(np.angle(measured / analytic))) < 2.0)


def test_a_chain_that_rings_up_is_reported_unsettled() -> None:
    # a stiff joint spring behind 50 ms without the wave filter: Re Z_t < 0 and a lossless
    # channel, the reflections grow (the discrete model agrees: spectral radius > 1)
    params = ImpedanceParams(**BASE, delay_s=0.05, env_stiffness=1000.0)
    assert spectral_radius(params) > 1.005
    result = measure_displayed_impedance(params, [5.0], joint=1)
    point = result.points[0]
    assert not point.settled and point.reason in ("diverged", "growing")
    assert math.isnan(point.z.real) and math.isnan(point.z.imag)
    doc = result.to_dict()
    assert doc["measured"] == {"re": [None], "im": [None], "settled": [False]}
    assert doc["analytic"]["re"][0] is not None  # the models still give numbers


def test_a_chain_with_a_slow_echo_mode_is_not_reported_as_a_number() -> None:
    # Fig 4's spring (Z_e = 10/s, b = 500, T1 = T2 = 0.05 s) behind 100 ms: an echo mode decays
    # by 2.4e-5 per tick (a 42 s time constant), 2 % per 0.8 s window. Two windows agreeing to
    # 1e-4 then leave up to r / (1 - r) = 50 times that in the estimate: before the transient
    # was extrapolated such a point was reported 0.12 % off the exact model.
    params = ImpedanceParams(
        m1=0.1, m2=0.1, c1=0.2, c2=2.0, z_o=10.0, b=500.0, delay_s=0.1, wave_filter_hz=30.0,
        env_stiffness=10.0,
    )  # fmt: skip
    assert spectral_radius(params) <= 1.0 + 1e-9  # stable, but barely damped
    point = measure_displayed_impedance(params, [500.0], joint=1, max_seconds=40.0).points[0]
    r = window_decay(params, point.window_ticks)
    assert 0.97 < r < 1.0 and point.window_ticks == 800
    assert not point.settled and point.reason in ("changing", "slow")
    assert math.isnan(point.z.real) and point.error_bound > 1e-4


def test_window_decay_closed_forms() -> None:
    # the P-controlled HSI and TO loops have one mode each, 1 - dt c1 Z_o / M1 = 1 - dt c2 / M2
    # = 0.8; free space behind 20 ms without the filter adds the lossless echoes z^40 = -1,
    # periodic over windows of 80 q ticks (then left out) and never decaying otherwise
    free = ImpedanceParams(**BASE, delay_s=0.02)
    assert window_decay(free, 80) == pytest.approx(0.8**80, rel=1e-6)
    assert window_decay(free, 160) == pytest.approx(0.8**160, rel=1e-6)
    assert window_decay(free, 100) == 1.0
    # a joint spring at zero delay: the offset mode z = 1 is periodic over any window
    spring = ImpedanceParams(**BASE, delay_s=0.0, env_stiffness=20.0)
    assert window_decay(spring, 7) == pytest.approx(0.8**7, rel=1e-9)
    # with the filter the echoes decay: r < 1 for any window, = |z|max^N
    echo = ImpedanceParams(**BASE, delay_s=0.02, wave_filter_hz=30.0)
    rho = spectral_radius(echo)
    assert 0.99 < rho < 1.0
    assert window_decay(echo, 100) == pytest.approx(rho**100, rel=1e-9)


def test_window_holds_whole_periods_in_whole_round_trips() -> None:
    dt = 1e-3
    for omega, d in ((0.5, 20), (3.0, 0), (40.0, 50), (40.0, 20)):
        w, n, p = choose_window(omega, dt, 4 * d, 2.0, 500, 60_000)
        assert n % max(4 * d, 1) == 0 and p >= 2 and n >= 500
        assert w * n * dt == pytest.approx(2 * math.pi * p, rel=1e-12)
        assert abs(w / omega - 1.0) <= 0.01


def test_discrete_model_tends_to_the_continuous_one_as_dt_shrinks() -> None:
    params = ImpedanceParams(
        **{**BASE, **PID}, delay_s=0.02, env_mass=0.01, env_damping=0.5, env_stiffness=20.0
    )
    omega = np.array([1.0, 10.0, 40.0])
    cont = displayed_impedance(1j * omega, params)
    errors = [
        np.abs(displayed_impedance_z(omega, params, dt) / cont - 1.0).max()
        for dt in (1e-3, 1e-4, 1e-5)
    ]
    assert errors[2] < 1e-3 and errors[2] < errors[1] < errors[0]  # O(omega dt)


# --- displayed parameters (item 4) ------------------------------------------------------------
@pytest.mark.parametrize("b", [2.0, 8.0])
def test_displayed_mass_in_free_space_is_b_times_delay(b: float) -> None:
    params = ImpedanceParams(**{**BASE, "b": b}, delay_s=0.05)  # no filter: T = T_d
    fit = fit_displayed_mass(params)
    assert fit.paper == pytest.approx(b * 0.05)
    assert fit.value == pytest.approx(b * 0.05, rel=0.01)  # eq 29; measured: +0.25 %


@pytest.mark.parametrize("b", [2.0, 8.0])
def test_displayed_stiffness_and_mass_ratio_is_the_delay_squared(b: float) -> None:
    # Stiff joint spring (3e4 N m/rad); a spring behind a delay needs the 30 Hz filter to
    # settle, which adds its DC group delay: T = T_d + (1 - alpha) dt / alpha = 54.8 ms.
    params = ImpedanceParams(**{**BASE, "b": b}, delay_s=0.05, wave_filter_hz=30.0)
    t = effective_delay(params)
    assert t == pytest.approx(0.05 + 0.00482, abs=1e-5)
    wall = ImpedanceParams(**{**BASE, "b": b}, delay_s=0.05, wave_filter_hz=30.0, env_stiffness=3e4)
    stiffness = fit_displayed_stiffness(wall)
    assert stiffness.value == pytest.approx(1.0 / (1.0 / 3e4 + t / b), rel=1e-3)
    assert stiffness.value == pytest.approx(b / t, rel=0.02)  # eq 30 with T
    assert stiffness.value == pytest.approx(b / 0.05 * 0.05 / t, rel=0.02)  # paper: b / T_d
    mass = fit_displayed_mass(params)
    assert mass.value == pytest.approx(b * t, rel=0.01)
    assert mass.value / stiffness.value == pytest.approx(t**2, rel=0.02)  # whatever b


def test_soft_wall_stiffness_is_the_series_of_wall_and_channel() -> None:
    # 1/k_d = 1/k_e + T/b; a little damping (k_e M2 / c2) makes this soft wall settle
    params = ImpedanceParams(
        **BASE, delay_s=0.05, wave_filter_hz=30.0, env_stiffness=40.0, env_damping=0.2
    )
    fit = fit_displayed_stiffness(params)
    t = effective_delay(params)
    assert fit.expected == pytest.approx(1.0 / (1.0 / 40.0 + t / 2.0))
    assert fit.value == pytest.approx(fit.expected, rel=1e-3)
    assert fit.value < 0.55 * 40.0  # far from both the wall (40) and b / T (36)


# --- CLI --------------------------------------------------------------------------------------
def test_bode_json_schema_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, png = tmp_path / "bode.json", tmp_path / "bode.png"
    argv = ["bode", str(CONFIGS / "free_space.yaml"), "--set", "channel.delay_ms=20"]
    argv += ["--set", "operator={kind: damper, damping_nm_s_per_rad: 5.0}"]
    argv += ["--env-stiffness", "20", "--omegas", "10,40", "--json", str(out), "--plot", str(png)]
    assert main(argv) == 0, capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert set(doc) == {"params", "omega_rad_s", "analytic", "measured", "discrete"}
    assert set(doc["measured"]) == {"re", "im", "settled", "reason"}
    assert doc["measured"]["reason"] == ["settled", "settled"]
    assert set(doc["analytic"]) == set(doc["discrete"]) == {"re", "im"}
    n = len(doc["omega_rad_s"])
    assert n == 2
    for key in ("analytic", "measured", "discrete"):
        assert len(doc[key]["re"]) == len(doc[key]["im"]) == n
    assert doc["measured"]["settled"] == [True, True]
    p = doc["params"]
    assert p["z_o_nm_s_per_rad"] == 5.0 and p["z_o_source"] == "operator.damping_nm_s_per_rad"
    assert p["delay_s"] == 0.02 and p["delay_ticks"] == 20 and p["b_nm_s_per_rad"] == 2.0
    assert p["m1_kg_m2"] == 0.1 and p["c2"]["kp"] == 20.0 and p["wave_filter_hz"] == 30.0
    # the analytic model's filter: the matched cut-off, alpha / (2 pi (1 - alpha) dt)
    alpha = 1.0 - math.exp(-2.0 * math.pi * 30.0 * 1e-3)
    matched = alpha / (2.0 * math.pi * (1.0 - alpha) * 1e-3)
    assert p["wave_filter_matched_hz"] == pytest.approx(matched, rel=1e-12)
    assert p["env_stiffness_nm_per_rad"] == 20.0 and p["env_mass_kg_m2"] == 0.0
    meas = np.array(doc["measured"]["re"]) + 1j * np.array(doc["measured"]["im"])
    disc = np.array(doc["discrete"]["re"]) + 1j * np.array(doc["discrete"]["im"])
    assert np.all(np.abs(meas - disc) <= 1e-3 * np.abs(disc))
    ana = np.array(doc["analytic"]["re"]) + 1j * np.array(doc["analytic"]["im"])
    cont = ImpedanceParams(
        m1=0.1, m2=0.1, c1=2.0, c2=20.0, z_o=5.0, b=2.0, delay_s=0.02, env_stiffness=20.0,
        wave_filter_hz=matched,
    )  # fmt: skip
    expected = displayed_impedance(1j * np.array(doc["omega_rad_s"]), cont)
    np.testing.assert_allclose(ana, expected, rtol=1e-12)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bode_json_has_null_for_unsettled(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bode", str(CONFIGS / "free_space.yaml"), "--set", "channel.delay_ms=50"]
    argv += ["--set", "channel.wave_filter_hz=null", "--env-stiffness", "1000"]
    assert main([*argv, "--omegas", "5", "--json", "-"]) == 0
    doc = json.loads(capsys.readouterr().out)
    reason = doc["measured"].pop("reason")
    assert doc["measured"] == {"re": [None], "im": [None], "settled": [False]}
    assert reason in (["growing"], ["diverged"], ["changing"], ["slow"], ["marginal"])
    assert doc["params"]["z_o_source"].startswith("default")  # a hand operator: Z_o = 10
    assert doc["params"]["z_o_nm_s_per_rad"] == 10.0


@pytest.mark.parametrize(
    "extra,named",
    [
        (["--omegas", "1,x"], "--omegas"),
        (["--omegas", "5000"], "Nyquist"),
        (["--joint", "7", "--omegas", "5"], "joint 7"),
        (["--env-mass", "-1", "--omegas", "5"], "env_mass"),
        (["--set", "channel.mode=direct", "--omegas", "5"], "wave channel"),
    ],
)
def test_bode_bad_input_is_one_line_exit_2(
    extra: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # (with a delay: free space at T_d = 0 is itself refused, tested below)
    base = ["bode", str(CONFIGS / "free_space.yaml"), "--set", "channel.delay_ms=20"]
    assert main([*base, *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("teleop-rt: error: ") and named in err[0]


def test_bode_of_free_space_without_delay_is_one_line_not_an_empty_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # issue 28: every |Z| was 0 (eq 29 at T_d = 0), the log-scaled magnitude panel empty
    image = tmp_path / "bode_free.png"
    argv = ["bode", str(CONFIGS / "free_space.yaml"), "--points", "6", "--plot", str(image)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "displays Z_h = 0 at every frequency (eq 29" in err[0]
    assert not image.exists()
    # with a delay it is the channel's mass b T_d, a plot with a legend that matches its title
    assert main([*argv, "--set", "channel.delay_ms=20", "--set", "channel.wave_filter_hz=null",
                 "--max-seconds", "5"]) == 0  # fmt: skip
    assert image.stat().st_size > 10_000


def test_bode_legend_names_the_filter_only_when_there_is_one() -> None:
    # issue 28: the legend said "matched filter" where the title said "filter off"
    from teleop_rt.analysis.bode import _filter_text, continuous_label

    for filter_hz in (None, 30.0):
        p = ImpedanceParams(**BASE, delay_s=0.02, wave_filter_hz=filter_hz)
        label, title = continuous_label(p, 1e-3), _filter_text(p, 1e-3)
        assert ("matched" in label) == ("matched" in title) == (filter_hz is not None)


def test_bode_plot_title_is_wrapped_inside_the_figure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # issue 28: the one-line title ran past both edges of the 8-inch figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from teleop_rt import output

    drawn = []
    save = output.save_figure
    monkeypatch.setattr(
        output, "save_figure", lambda fig, *a, **k: (drawn.append(fig), save(fig, *a, **k))[1]
    )
    image = tmp_path / "bode.png"
    argv = ["bode", str(CONFIGS / "stiff_wall.yaml"), "--omegas", "10,40", "--plot", str(image),
            "--set", "channel.delay_ms=50", "--set", "channel.wave_filter_hz=30"]  # fmt: skip
    assert main(argv) == 0 and image.stat().st_size > 10_000
    capsys.readouterr()
    (fig,) = drawn
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    title = fig._suptitle
    box, whole = title.get_window_extent(canvas.get_renderer()), fig.bbox
    assert "\n" in title.get_text() and "Z_e =" in title.get_text()
    assert whole.x0 <= box.x0 and box.x1 <= whole.x1 and box.y1 <= whole.y1
