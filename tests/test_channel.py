"""Wave-variable channel (eq 7-10): direct coupling at T_d = 0, exact passivity of the discrete
delay lines, and the port impedances b tanh(T_d s) and b coth(T_d s) of a free / rigid end."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt.analysis.impedance import channel_impedance
from teleop_rt.com.direct import DirectChannel
from teleop_rt.com.wave import WaveChannel
from tests.conftest import lock_in

DT = 1e-3


def test_delay_lines_output_zeros_until_filled_then_the_sample_d_ticks_ago() -> None:
    ch = DirectChannel(1, 3, DT)
    forward, backward = [], []
    for k in range(8):
        ch.step([float(k + 1)], [-float(k + 1)])
        forward.append(ch.omega_t[0])
        backward.append(ch.tau_c[0])
    assert forward == [0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert backward == [-x for x in forward]
    with pytest.raises(ValueError):
        DirectChannel(1, -1, DT)


def test_zero_delay_couples_directly() -> None:
    ch = WaveChannel([2.0, 0.5], 0, DT)
    rng = np.random.default_rng(0)
    for _ in range(100):
        w, tau = rng.normal(size=2).tolist(), rng.normal(size=2).tolist()
        ch.step(w, tau)
        assert ch.omega_t.tolist() == w and ch.tau_c.tolist() == tau
    assert ch.total_energy == 0.0


@settings(max_examples=60, deadline=None)
@given(
    b=st.floats(0.01, 100.0),
    delay_ticks=st.integers(1, 300),
    seed=st.integers(0, 2**32 - 1),
    scale_w=st.floats(1e-3, 1e2),
    scale_tau=st.floats(1e-3, 1e2),
)
def test_energy_in_equals_wave_energy_in_the_delay_lines(b, delay_ticks, seed, scale_w, scale_tau):
    """sum dt (omega_c tau_c - omega_t tau_t) == dt/2 sum(u^2 + v^2) over buffered samples,
    every tick, for any b, any delay and any port signals (filter off: exact identity)."""
    rng = np.random.default_rng(seed)
    ch = WaveChannel([b, 2.0 * b], delay_ticks, DT, filter_hz=None)
    ticks = delay_ticks + 200
    omega = rng.normal(scale=scale_w, size=(ticks, 2))
    tau = rng.normal(scale=scale_tau, size=(ticks, 2))
    for k in range(ticks):
        ch.step(omega[k].tolist(), tau[k].tolist())
        stored = ch.stored_energy()
        assert ch.total_energy >= -1e-12 * max(stored, 1e-30)
        # rounding only: relative 1e-9 of the stored energy (plus an absolute floor)
        assert abs(ch.total_energy - stored) <= 1e-9 * stored + 1e-15


@settings(max_examples=30, deadline=None)
@given(
    b=st.floats(0.05, 50.0),
    delay_ticks=st.integers(1, 100),
    cutoff=st.floats(1.0, 400.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_filtered_channel_stays_passive(b, delay_ticks, cutoff, seed):
    """With the received-wave low-pass on, the energy that entered is never below what the
    delay lines hold: the filter only dissipates."""
    rng = np.random.default_rng(seed)
    ch = WaveChannel([b], delay_ticks, DT, filter_hz=cutoff)
    for _ in range(delay_ticks + 300):
        ch.step(rng.normal(size=1).tolist(), rng.normal(size=1).tolist())
        assert ch.total_energy >= ch.stored_energy() - 1e-12 * (1.0 + ch.stored_energy())


def drive_hsi_port(b: float, delay_ms: float, omega: float, periods_s: float, termination):
    """Impose omega_c = sin(omega t) at the HSI port; termination(omega_t_prev) -> tau_t.
    Return tau_c / omega_c at omega, measured over the last periods_s seconds."""
    d = round(delay_ms)
    ch = WaveChannel([b], d, DT, filter_hz=None)
    settle = 4 * d * 10  # whole multiples of the round trip's period 4 D
    window = round(periods_s / DT)
    ticks = settle + window
    w_c = np.sin(omega * DT * np.arange(ticks))
    tau_c = np.zeros(ticks)
    state = {"p": 0.0}
    for k in range(ticks):
        ch.step([float(w_c[k])], [termination(state)])
        state["p"] += DT * ch.omega_t[0]
        tau_c[k] = ch.tau_c[0]
    return lock_in(tau_c[settle:], omega, DT) / lock_in(w_c[settle:], omega, DT)


B, DELAY_MS = 2.0, 100.0
T_D = DELAY_MS / 1000


@pytest.mark.parametrize("hz", [0.25, 0.5, 1.0])
def test_free_end_is_b_tanh_and_a_mass_b_td(hz: float) -> None:
    omega = 2 * math.pi * hz
    z = drive_hsi_port(B, DELAY_MS, omega, 4.0, lambda s: 0.0)  # tau_t = 0: free space
    exact = B * np.tanh(1j * omega * T_D)
    # the discrete channel is exact at the sample instants: only rounding separates them
    assert abs(z / exact - 1) < 1e-6
    if omega * T_D <= 0.32:  # low frequency: a mass b T_d, within a few per cent
        mass = (z / (1j * omega)).real
        assert abs(mass / (B * T_D) - 1) < 0.04


@pytest.mark.parametrize("hz", [0.25, 0.5])
def test_stiff_end_is_b_coth_and_a_spring_b_over_td(hz: float) -> None:
    omega = 2 * math.pi * hz
    k_spring = 1000.0  # N m/rad: stiff against b/T_d = 20, and K dt / b < 2 (stable sampling)
    z = drive_hsi_port(B, DELAY_MS, omega, 4.0, lambda s: k_spring * s["p"])
    # discrete prediction: the spring sees omega_t one tick late, Z_t = K dt / (z - 1). That
    # termination is slightly active (Re Z_t = -K dt / 2), so the lossless channel's start-up
    # transient does not die out and leaks a little into the window: 2e-3, not rounding.
    z_t = k_spring * DT / (np.exp(1j * omega * DT) - 1)
    predicted = channel_impedance(1j * omega, B, T_D, z_t)
    assert abs(z / predicted - 1) < 2e-3
    # against the rigid-end closed form and the spring b / T_d: within a few per cent
    assert abs(z / (B / np.tanh(1j * omega * T_D)) - 1) < 0.05
    # displayed stiffness: the channel's b / T_d in series with the spring, 1/k = 1/K + T_d/b
    stiffness = (z * 1j * omega).real
    assert abs(stiffness * (1 / k_spring + T_D / B) - 1) < 0.04
    if omega * T_D < 0.2:
        # the free end's mass over the stiff end's stiffness is T_d^2 at low frequency (the
        # series spring and the tan / cot curvature cost about 3 % here)
        z_free = drive_hsi_port(B, DELAY_MS, omega, 4.0, lambda s: 0.0)
        ratio = (z_free / (1j * omega)).real / stiffness
        assert abs(ratio / T_D**2 - 1) < 0.05


@settings(max_examples=25, deadline=None)
@given(
    b=st.floats(0.01, 100.0),
    delay_ticks=st.integers(0, 2000),
    seed=st.integers(0, 2**32 - 1),
    filtered=st.booleans(),
)
def test_channel_is_passive_for_delays_up_to_two_seconds(b, delay_ticks, seed, filtered):
    """Energy that entered the channel is never negative, for 0-2000 ticks of delay, any b,
    random port signals, filter on or off (stored energy checked at a few ticks: it costs O(D))."""
    rng = np.random.default_rng(seed)
    ch = WaveChannel([b], delay_ticks, DT, filter_hz=30.0 if filtered else None)
    ticks = delay_ticks + 100
    checkpoints = set(rng.integers(0, ticks, size=5).tolist()) | {ticks - 1}
    omega, tau = rng.normal(size=ticks).tolist(), rng.normal(size=ticks).tolist()
    for k in range(ticks):
        ch.step([omega[k]], [tau[k]])
        assert ch.total_energy >= -1e-12
        if k in checkpoints:
            assert ch.total_energy >= ch.stored_energy() * (1 - 1e-9) - 1e-12
