"""Position drift compensation within the passivity budget (issue 23): the ``corrected`` wave
reconstruction keeps the wave integral's debt (what an outage lost or the bound cut: the
peer's integral minus the one used) and pays it back at 1 / WAVE_DRIFT_TIME_S, spending only
the honest budget (the energy of waves that reached the port in time), after Niemeyer &
Slotine's wave integrals (IJRR 2004). On a clean link it computes what ``bounded`` computes,
bit for bit (the debt is exactly 0)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt import config
from teleop_rt.com.channel import make_port
from teleop_rt.com.port import HSI, TO
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_passive_channels import PASSIVE_J, SWEEP, Harness, drive, schedules

DT = 1e-3


def positions(how: str, outage: range, ticks: int = 6000) -> tuple[np.ndarray, np.ndarray, float]:
    """The HSI moved back and forth (0.5 Hz, 1 rad/s peak) against a free TO (tau_t = 0), the
    HSI -> TO direction silent for ``outage``: both ports' positions (integrals of their
    flows) and the lowest balance or two-port energy seen."""
    harness = Harness("wave", how, 1, 30.0)
    x_h, x_t = np.zeros(ticks), np.zeros(ticks)
    low, pos_h, pos_t = 0.0, 0.0, 0.0
    for k in range(ticks):
        omega = np.sin(2 * np.pi * 0.5 * k * DT)
        harness.step(k, (np.full(1, omega), np.zeros(1)), (20, 20), (False, k in outage))
        pos_h += omega * DT
        pos_t += float(harness.ports[TO].flow[0]) * DT
        x_h[k], x_t[k] = pos_h, pos_t
        low = min(low, harness.lowest())
    return x_h, x_t, low


def drift(x_h: np.ndarray, x_t: np.ndarray) -> float:
    """The TO's offset from the HSI over the last two periods (the delay's lag averages out)."""
    return float(np.mean(x_h[-4000:] - x_t[-4000:]))


def test_the_correction_brings_the_to_back_after_an_outage_within_the_budget() -> None:
    outage = range(600, 1100)  # 0.5 s of the stroke lost
    lost = {how: positions(how, outage) for how in ("bounded", "corrected")}
    x_h, x_t, low = lost["bounded"]
    offset = drift(x_h, x_t)
    assert abs(offset) > 0.1  # rad: the outage's motion, lost for good without the correction
    x_h, x_t, low = lost["corrected"]
    assert abs(drift(x_h, x_t)) < 0.01 * abs(offset)
    assert low >= PASSIVE_J
    clean = positions("corrected", range(0))
    assert abs(drift(clean[0], clean[1])) < 1e-6  # the clean link's own lag, for scale


def test_on_a_clean_link_corrected_is_bounded_bit_for_bit() -> None:
    a = positions("bounded", range(0), 3000)
    b = positions("corrected", range(0), 3000)
    assert np.array_equal(a[1], b[1])


@settings(max_examples=100, deadline=None)
@given(schedule=schedules(150), filter_hz=st.sampled_from([None, 30.0]))
def test_corrected_ports_are_passive_for_any_delays_losses_and_inputs(schedule, filter_hz) -> None:
    assert drive(Harness("wave", "corrected", 1, filter_hz), schedule) >= PASSIVE_J


def sawtooth(tmp_path) -> str:
    """The issue's measured case: the network's delay ramps 20 -> 80 ms every 2 s."""
    ticks = np.arange(2000)
    rows = ["send_tick,delay_ms", *(f"{k},{20 + 60 * k / 2000:.3f}" for k in ticks)]
    path = tmp_path / "sawtooth.csv"
    path.write_text("\n".join(rows) + "\n")
    return str(path)


@pytest.mark.parametrize("how", ["bounded", "corrected"])
def test_the_measured_sawtooth_case(how: str, tmp_path) -> None:
    """Free-space sweeps, fixed playout D = 50 ms, delay 20 -> 80 ms (2 s): the packets beyond
    50 ms are late, so the TO is silent for 0.5 s of every 2 s. Before the honest credit
    ``bounded`` ended in a safety stop at 19.9 s (a held stale wave); now it loses the outages'
    motion like a zero wave, and still drifts into the TO's elbow limit (14.3 s); ``corrected``
    brings the TO back and runs to the end, passive."""
    impairment = json.dumps({"seed": 1, "trace": sawtooth(tmp_path)})
    overrides = ["duration_s=20", "channel.delay_ms=50", "link.playout=fixed",
                 f"channel.wave_reconstruction={how}", "operator.waypoints=" + json.dumps(SWEEP),
                 "link.impairment=" + impairment]  # fmt: skip
    session = Session(config.load(CONFIGS / "free_space.yaml", overrides))
    s = session.run()
    assert min(session.hsi.port.min_balance, session.to.port.min_balance) >= PASSIVE_J
    assert s.min_channel_energy_j >= PASSIVE_J
    if how == "bounded":
        assert s.safety_stop and "outside" in s.stopped_early, s.stopped_early
    else:
        assert not s.safety_stop and s.stopped_early is None, s.stopped_early
        assert s.t_p_total < 0.5  # rad^2 s (zero wave: 2.1 when it stopped)


def paid_back(how: str, time_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A free TO (tau_t = 0, no filter) after a 0.3 s outage of the HSI -> TO direction, the
    drift correction's time constant ``time_s``: the TO's debt after each tick, and whether
    its protection acted in that tick (the bound's cut breaks the geometric decay)."""
    harness = Harness("wave", how, 1, None)
    harness.ports = [make_port(side, "wave", [1.5], 1, DT, None, how, None, time_s)
                     for side in (HSI, TO)]  # fmt: skip
    debts, acted = [], []
    for k in range(2500):
        omega = 0.5 * np.sin(2 * np.pi * 0.5 * k * DT)
        before = int(harness.ports[TO].acted)
        harness.step(k, (np.full(1, omega), np.zeros(1)), (20, 20), (False, 200 <= k < 500))
        debts.append(float(harness.ports[TO].debt[0]))
        acted.append(int(harness.ports[TO].acted) > before)
    return np.array(debts), np.array(acted)


@pytest.mark.parametrize("how", ["corrected", "reflected"])
@pytest.mark.parametrize("time_s", [0.25, 2.0])
def test_the_debt_is_paid_back_at_the_channel_s_time_constant(how: str, time_s: float) -> None:
    """Closed form: with consecutive packets the wave used is the sample plus debt / T, so the
    debt left after each packet is d (1 - dt / T): geometric, at the configured T."""
    debts, acted = paid_back(how, time_s)
    free = np.nonzero(~acted[1:] & (np.arange(1, debts.size) > 600))[0] + 1  # uncut ticks
    assert free.size > 1000 and np.all(np.abs(debts[free - 1]) > 1e-6)  # the outage's motion
    ratio = debts[free] / debts[free - 1]
    assert np.allclose(ratio, 1.0 - DT / time_s, rtol=0.0, atol=1e-9), (ratio.min(), ratio.max())


def test_the_config_s_time_constant_reaches_both_ports() -> None:
    cfg = config.load(CONFIGS / "free_space.yaml", ["channel.wave_drift_time_s=2.0"])
    session = Session(cfg)
    assert session.hsi.port.wave_drift_rate == session.to.port.wave_drift_rate == 0.5
    with pytest.raises(ValueError, match="time constant must be >= one tick"):
        make_port(TO, "wave", [1.5], 1, DT, None, "reflected", None, 0.0)


@settings(max_examples=60, deadline=None)
@given(schedule=schedules(150), how=st.sampled_from(["corrected", "reflected"]),
       time_s=st.floats(0.002, 10.0), filter_hz=st.sampled_from([None, 30.0]))  # fmt: skip
def test_the_ports_are_passive_at_any_pay_back_time_constant(schedule, how, time_s,
                                                             filter_hz) -> None:  # fmt: skip
    """The bound, not the pay-back's gain, keeps the ports passive: any time constant."""
    harness = Harness("wave", how, 1, filter_hz)
    harness.ports = [make_port(side, "wave", [1.5], 1, DT, filter_hz, how, None, time_s)
                     for side in (HSI, TO)]  # fmt: skip
    assert drive(harness, schedule) >= PASSIVE_J
