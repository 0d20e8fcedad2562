"""Displayed impedance (Kuschel & Buss Section 3) against the paper's closed forms."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt.analysis.discrete import (
    continuous_params,
    displayed_impedance_z,
    filter_group_delay_s,
    matched_filter_hz,
)
from teleop_rt.analysis.impedance import (
    AnalysisParamError,
    ControllerGains,
    ImpedanceParams,
    channel_impedance,
    controller_tf,
    delay_factor,
    displayed_impedance,
    displayed_impedance_parts,
    displayed_mass_free_space,
    displayed_stiffness_wall,
    environment_impedance,
    g_omega,
    g_tau,
    reflection_coefficient,
    round_trip_factor,
    time_constant_hsi,
    time_constant_to,
    wave_filter_tf,
)
from teleop_rt.errors import ConfigError

B, M1, M2, C1, C2, ZO = 2.0, 0.1, 0.1, 2.0, 20.0, 1.0  # paper-like single joint
S = 1j * np.logspace(-2, 3, 400)  # rad/s grid
DELAYS = [1e-3, 0.05, 1.0]


def params(delay_s=0.05, **kw):
    base = dict(m1=M1, m2=M2, c1=C1, c2=C2, z_o=ZO, b=B, delay_s=delay_s)
    return ImpedanceParams(**(base | kw))


def rel_err(a, b):
    return np.max(np.abs(np.asarray(a) / np.asarray(b) - 1.0))


def err_vs_b(a, ref):
    """Error relative to max(|ref|, b): eq (22) as printed cancels to ~eps b when Z_c << b."""
    return np.max(np.abs(a - ref) / np.maximum(np.abs(ref), B))


def test_building_blocks_closed_forms():
    s = np.array([[0.3j, 2 + 5j], [-1j, 40j]])  # any shape is kept
    z = environment_impedance(s, mass=0.5, damping=3.0, stiffness=100.0)
    assert z.shape == s.shape
    np.testing.assert_allclose(z, 0.5 * s + 3.0 + 100.0 / s, rtol=1e-15)
    np.testing.assert_allclose(environment_impedance(s), 0.0)  # free space
    c = controller_tf(s, kp=2.0, ki=3.0, kd=0.5, derivative_filter_s=0.01)
    np.testing.assert_allclose(c, 2.0 + 3.0 / s + 0.5 * s / (1 + 0.01 * s), rtol=1e-15)
    # filtered derivative: C(inf) = kp + kd / T_f
    np.testing.assert_allclose(controller_tf(1e12j, 2.0, 0.0, 0.5, 0.01), 52.0, rtol=1e-9)
    np.testing.assert_allclose(delay_factor(s, 0.0), 1.0)
    np.testing.assert_allclose(delay_factor(s, 0.0, "pade"), 1.0)


def test_invalid_parameters_raise_one_error_type():
    for bad in (
        dict(m1=0.0),
        dict(b=-1.0),
        dict(delay_s=-1e-3),
        dict(env_stiffness=-1.0),
        dict(delay_model="taylor"),
        dict(wave_filter_hz=0.0),
    ):
        with pytest.raises(AnalysisParamError):
            params(**bad)
    with pytest.raises(ConfigError):
        delay_factor(S, 0.1, "taylor")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        ControllerGains(kp=1.0, derivative_filter_s=-1.0)


@pytest.mark.parametrize(
    "zt", [0.0, 0.3 * B, B, 7.0 * B, 5.0 / S, 0.2 * S, 1.0 + 0.4 * S + 30.0 / S, 3.0 - 1.0j]
)
@pytest.mark.parametrize("td", [0.0, 0.013, 0.4])
def test_eq22_equals_reflection_form(zt, td):
    e = np.exp(-2 * td * S)
    eq22 = B - 2 * B * e * (B - zt) / (B + zt + e * (B - zt))
    assert err_vs_b(channel_impedance(S, B, td, zt), eq22) < 1e-12
    for fc in (None, 3.0):
        gamma = round_trip_factor(S, td, "exact", fc) * reflection_coefficient(zt, B)
        zc = channel_impedance(S, B, td, zt, wave_filter_hz=fc)
        assert err_vs_b(zc, B * (1 - gamma) / (1 + gamma)) < 1e-12


def test_rigid_termination_is_handled():
    np.testing.assert_array_equal(reflection_coefficient([np.inf, 1e300, 0.0], B), [-1, -1, 1])
    for zt in (np.inf, 1e300):
        assert rel_err(channel_impedance(S, B, 0.05, zt), B / np.tanh(0.05 * S)) < 1e-12
    assert np.all(channel_impedance(S, B, 0.0, np.inf) == np.inf)  # T_d = 0: rigid, no nan


@pytest.mark.parametrize(
    "env, td, model",
    [
        (dict(env_stiffness=1000.0), 0.0, "exact"),
        (dict(env_mass=0.5, env_damping=3.0, env_stiffness=1000.0), 0.0, "exact"),
        (dict(env_damping=3.0), 0.05, "exact"),
        (dict(env_damping=3.0, env_mass=0.5), 1.0, "pade"),
        (dict(env_damping=30.0), 0.05, "exact"),
    ],
)
def test_eq25_static_limit_matches_environment(env, td, model):
    p = params(td, delay_model=model, **env)
    parts = displayed_impedance_parts(1e-6j, p)
    assert abs(parts.z_h / parts.z_e - 1) < 1e-4


@pytest.mark.parametrize("model", ["exact", "pade"])
def test_eq25_spring_behind_a_delay_is_softened(model):
    # With T_d > 0 eq (25) holds only as Z_h(0) = Z_e(0) = inf: at low frequency the channel is
    # the spring b/T_d of eq (30) in series with k, so Z_h/Z_e -> 1/(1 + k T_d/b), not 1.
    k, td = 1000.0, 0.05
    parts = displayed_impedance_parts(1e-6j, params(td, env_stiffness=k, delay_model=model))
    assert abs(parts.z_h / parts.z_e * (1 + k * td / B) - 1) < 1e-4
    assert abs(parts.z_h) > 1e6


def test_eq25_high_frequency_limit():
    s = 1j * np.logspace(6, 9, 3000)
    # environment with mass: Z_t -> c2 m/M2 > 0, |Gamma| <= rho < 1, so Z_c is bounded by
    # b (1 + rho)/(1 - rho) and Z_h = G_tau Z_c falls like |G_tau| ~ c1 Z_o/(M1 omega).
    p = params(0.05, env_mass=0.5, env_damping=3.0, env_stiffness=1000.0)
    parts = displayed_impedance_parts(s, p)
    rho = np.abs(reflection_coefficient(parts.z_t, B))
    assert np.all(np.abs(parts.z_h) <= np.abs(parts.g_tau) * B * (1 + rho) / (1 - rho))
    assert np.max(np.abs(parts.z_h[s.imag > 1e8])) < 1e-4
    # a pure spring: -> 0 without delay, and with delay once the wave filter is on
    for p in (
        params(0.0, env_stiffness=1000.0),
        params(0.05, env_stiffness=1000.0, wave_filter_hz=30.0),
    ):
        assert np.max(np.abs(displayed_impedance(s[s.imag > 1e8], p))) < 1e-4


def test_pade_free_space_does_not_decay():
    # outside eq (28)'s range the Pade channel is the mass b T_d for ever, so
    # Z_h -> (c1 Z_o/(M1 s)) b T_d s = b T_d c1 Z_o/M1: a Pade artefact, not the plant.
    # (The spring still seen through the TO adds a relative c2 k T_d/(M2 b omega) = 5e-6 here.)
    td = 0.05
    zh = displayed_impedance(1e9j, params(td, env_stiffness=1000.0, delay_model="pade"))
    assert abs(zh / (B * td * C1 * ZO / M1) - 1) < 1e-4


@pytest.mark.parametrize("td", [0.0, *DELAYS])
@pytest.mark.parametrize("model", ["exact", "pade"])
def test_eq26_matched_termination(td, model):
    for fc in (None, 20.0):
        zc = channel_impedance(S, B, td, B, model, fc)
        assert rel_err(zc, B) < 1e-12
    # environment chosen so Z_t = G_omega Z_e = b: damper b plus mass b M2/c2
    parts = displayed_impedance_parts(
        S, params(td, delay_model=model, env_damping=B, env_mass=B * M2 / C2)
    )
    assert rel_err(parts.z_t, B) < 1e-12
    assert rel_err(parts.z_h, B * parts.g_tau) < 1e-12


@pytest.mark.parametrize(
    "env",
    [
        dict(env_stiffness=1000.0),
        dict(env_mass=0.5),
        dict(env_damping=3.0),
        dict(env_mass=0.5, env_damping=3.0, env_stiffness=1000.0),
    ],
)
def test_eq27_no_delay(env):
    p = params(0.0, **env)
    parts = displayed_impedance_parts(S, p)
    assert rel_err(parts.z_h, parts.g_tau * parts.g_omega * parts.z_e) < 1e-12
    assert rel_err(parts.z_c, parts.z_t) < 1e-12


@pytest.mark.parametrize("td", DELAYS)
def test_eq29_30_free_space_and_wall(td):
    # Pade (eq 28): exactly the mass b T_d (eq 29) and the spring b/T_d (eq 30)
    assert rel_err(channel_impedance(S, B, td, 0.0, "pade"), B * td * S) < 1e-13
    assert rel_err(channel_impedance(S, B, td, np.inf, "pade"), B / (td * S)) < 1e-13
    np.testing.assert_allclose(displayed_mass_free_space(B, td), B * td)
    np.testing.assert_allclose(displayed_stiffness_wall(B, td), B / td)
    # exact delay: b tanh(T_d s) and b coth(T_d s)
    assert rel_err(channel_impedance(S, B, td, 0.0), B * np.tanh(td * S)) < 1e-12
    assert rel_err(channel_impedance(S, B, td, np.inf), B / np.tanh(td * S)) < 1e-12


def test_exact_delay_approaches_pade_at_low_frequency():
    td = 0.05
    for wtd, within in ((0.05, True), (0.5, False)):  # eq (28): omega < 1/(3 T_d)
        s = 1j * wtd / td
        mass = channel_impedance(s, B, td, 0.0) / s
        stiffness = channel_impedance(s, B, td, np.inf) * s
        assert bool(abs(mass / displayed_mass_free_space(B, td) - 1) < 0.01) is within
        assert bool(abs(stiffness / displayed_stiffness_wall(B, td) - 1) < 0.01) is within
    assert displayed_stiffness_wall(B, 0.0) == np.inf


def test_eq31_32_first_order_lags():
    t1, t2 = time_constant_hsi(M1, C1, ZO), time_constant_to(M2, C2)
    assert (t1, t2) == pytest.approx((0.05, 0.005), rel=1e-15)
    assert rel_err(g_tau(S, M1, C1, ZO), 1 / (S * t1 + 1)) < 1e-12
    assert rel_err(g_omega(S, M2, C2), 1 / (S * t2 + 1)) < 1e-12
    parts = displayed_impedance_parts(S, params())
    assert rel_err(parts.g_tau, 1 / (S * t1 + 1)) < 1e-12
    assert rel_err(parts.g_omega, 1 / (S * t2 + 1)) < 1e-12


def test_wave_filter_high_cutoff_equals_none():
    for zt in (0.5 * B, 1000.0 / S):  # F^2 - 1 ~ 2 omega/omega_c ~ 3e-7, lossless spring x 30
        ref = channel_impedance(S, B, 0.05, zt)
        assert rel_err(channel_impedance(S, B, 0.05, zt, wave_filter_hz=1e9), ref) < 1e-5
        assert rel_err(channel_impedance(S, B, 0.05, zt, wave_filter_hz=5.0), ref) > 1e-2


@pytest.mark.parametrize("td", [0.0, *DELAYS])
@pytest.mark.parametrize("model", ["exact", "pade"])
def test_wave_filter_keeps_channel_passive(td, model):
    # Re Z_c = b (1 - |Gamma|^2)/|1 + Gamma|^2 and Gamma = F^2 e Gamma_t with |F| <= 1,
    # |e| = 1 and |Gamma_t| <= 1 for a passive Z_t (Re Z_t >= 0), so |Gamma| <= 1, Re Z_c >= 0.
    s = 1j * np.logspace(-2, 5, 2000)
    for zt in (3.0 * B, 0.2 * B, 1000.0 / s, 1e-3 / s):  # dampers and springs
        zc = channel_impedance(s, B, td, zt, model, wave_filter_hz=30.0)
        gamma = round_trip_factor(s, td, model, 30.0) * reflection_coefficient(zt, B)
        assert np.all(np.abs(gamma) <= 1.0)
        assert np.all(zc.real >= -1e-12 * np.abs(zc))


@settings(max_examples=200, deadline=None)
@given(
    re=st.floats(0.0, 1e4),
    im=st.floats(-1e4, 1e4),
    b=st.floats(0.01, 100.0),
    td=st.floats(0.0, 2.0),
    fc=st.one_of(st.none(), st.floats(0.1, 1e3)),
    w=st.floats(1e-3, 1e4),
    model=st.sampled_from(["exact", "pade"]),
)
def test_passive_termination_gives_passive_channel(re, im, b, td, fc, w, model):
    zc = channel_impedance(1j * w, b, td, complex(re, im), model, fc)
    assert zc.real >= -1e-9 * abs(zc)


def test_pid_integral_action():
    pid = ControllerGains(kp=C2, ki=50.0, kd=0.01, derivative_filter_s=1e-3)
    w = np.array([1e-3, 1e-6, 1e-9])
    c = controller_tf(1j * w, pid.kp, pid.ki, pid.kd, pid.derivative_filter_s)
    assert np.all(np.diff(np.abs(c)) > 0)  # |C| grows without bound as s -> 0
    assert rel_err(np.abs(c[1:]), pid.ki / w[1:]) < 1e-6
    assert np.max(np.abs(g_omega(1j * w[1:], M2, c[1:]) - 1)) < 1e-10
    assert abs(g_omega(1e-6j, M2, C2) - 1) > 1e-9  # P control only has O(s) accuracy
    parts = displayed_impedance_parts(1e-6j, params(0.0, c2=pid, env_stiffness=1000.0))
    assert abs(parts.z_h / parts.z_e - 1) < 1e-4


# --- the continuous model of the 1 kHz chain: matched wave-filter cut-off ----------------------
DT = 1e-3


def sampled_filter(omega, cutoff_hz, dt=DT):
    """F(e^{j omega dt}) of the channel's y += alpha (x - y), alpha = 1 - exp(-2 pi f_c dt)."""
    alpha = 1.0 - np.exp(-2.0 * np.pi * cutoff_hz * dt)
    return alpha / (1.0 - (1.0 - alpha) * np.exp(-1j * np.asarray(omega) * dt))


@pytest.mark.parametrize("fc", [5.0, 30.0, 100.0])
def test_matched_cutoff_closed_form(fc):
    alpha = 1.0 - np.exp(-2.0 * np.pi * fc * DT)
    matched = matched_filter_hz(fc, DT)
    assert matched == pytest.approx(alpha / (2.0 * np.pi * (1.0 - alpha) * DT), rel=1e-12)
    assert matched > fc  # the sampled filter is faster than its nominal continuous namesake
    # the same DC group delay as the sampled filter: -d arg F / d omega at omega -> 0
    w = 1e-4
    group_delay = -np.angle(sampled_filter(w, fc)) / w
    assert 1.0 / (2.0 * np.pi * matched) == pytest.approx(group_delay, rel=1e-6)
    assert filter_group_delay_s(fc, DT) == pytest.approx(group_delay, rel=1e-6)
    # ... half a tick shorter than 1 / (2 pi f_c), to O(f_c dt)
    half_tick = 1.0 / (2.0 * np.pi * fc) - group_delay
    assert half_tick == pytest.approx(DT / 2.0, rel=2.0 * np.pi * fc * DT)


def test_matched_cutoff_values_and_limits():
    assert matched_filter_hz(30.0, DT) == pytest.approx(33.014, abs=5e-4)  # 30 Hz at 1 kHz
    assert filter_group_delay_s(30.0, DT) == pytest.approx(4.82e-3, abs=5e-6)
    assert matched_filter_hz(None, DT) is None and filter_group_delay_s(None, DT) == 0.0
    # dt -> 0: the sampled filter becomes the continuous one, f_m = f_c (1 + x/2 + x^2/6 + ...),
    # x = 2 pi f_c dt
    x = 2.0 * np.pi * 30.0 * 1e-7
    assert matched_filter_hz(30.0, 1e-7) == pytest.approx(30.0 * (1 + x / 2 + x**2 / 6), 1e-14)
    with pytest.raises(AnalysisParamError):
        matched_filter_hz(0.0, DT)


def test_matched_filter_follows_the_sampled_one_to_second_order():
    # 1/F_z = (1 - (1 - alpha) e^{-j omega dt}) / alpha = 1 + s T_m + ((1 - alpha)/alpha)
    # (omega dt)^2 / 2 + O((omega dt)^3) with T_m = 1 / (2 pi f_m): the matched continuous filter
    # is off by that second-order term; the nominal one by omega (1/(2 pi f_c) - T_m) in phase
    omega = np.array([1.0, 3.0, 10.0])
    f_z = sampled_filter(omega, 30.0)
    alpha = 1.0 - np.exp(-2.0 * np.pi * 30.0 * DT)
    second_order = (1.0 - alpha) / alpha * (omega * DT) ** 2 / 2.0
    matched = wave_filter_tf(1j * omega, matched_filter_hz(30.0, DT))
    assert np.all(np.abs(matched / f_z - 1.0) <= 1.05 * second_order)
    nominal = wave_filter_tf(1j * omega, 30.0)
    lag = omega * (1.0 / (2.0 * np.pi * 30.0) - filter_group_delay_s(30.0, DT))
    np.testing.assert_allclose(-np.angle(nominal / f_z), lag, rtol=0.02)


def test_continuous_params_of_the_sampled_chain():
    p = params(0.02, wave_filter_hz=30.0, delay_model="pade")
    c = continuous_params(p, DT)
    assert c.delay_model == "exact" and c.wave_filter_hz == matched_filter_hz(30.0, DT)
    assert (c.m1, c.b, c.delay_s) == (p.m1, p.b, p.delay_s)
    # zero delay: the channel couples directly, no received waves, no filter
    assert continuous_params(params(0.0, wave_filter_hz=30.0), DT).wave_filter_hz is None


@pytest.mark.parametrize("td", [0.005, 0.02])
def test_matched_cutoff_closes_the_gap_to_the_sampled_chain(td):
    # Free space behind T_d with the 30 Hz filter, low frequency: the z-model displays the mass
    # b (T_d + T_z), T_z the sampled filter's group delay; a continuous model with the nominal
    # cut-off b (T_d + 1/(2 pi f_c)), too heavy by (1/(2 pi f_c) - T_z) / (T_d + T_z): 4.9 % at
    # 5 ms, 2.0 % at 20 ms. The matched cut-off removes it (left: O(omega dt), < 0.1 %).
    p = ImpedanceParams(m1=0.1, m2=0.1, c1=2.0, c2=20.0, z_o=10.0, b=2.0, delay_s=td,
                        wave_filter_hz=30.0)  # fmt: skip
    omega = np.array([0.5, 1.0])
    z = displayed_impedance_z(omega, p, DT)
    t_z = filter_group_delay_s(30.0, DT)
    gap = (1.0 / (2.0 * np.pi * 30.0) - t_z) / (td + t_z)
    nominal = displayed_impedance(1j * omega, replace(p, delay_model="exact"))
    np.testing.assert_allclose(np.abs(nominal / z) - 1.0, gap, atol=5e-4)
    matched = displayed_impedance(1j * omega, continuous_params(p, DT))
    assert np.all(np.abs(np.abs(matched / z) - 1.0) < 1e-3)
    assert np.all(np.abs(np.angle(matched / z, deg=True)) < 0.1)
