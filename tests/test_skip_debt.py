"""The skip debt (s37, issue 23; an option, channel.wave_skip_time_s): the part of the wave
integral's debt that a change of the delay brought under the ``newest`` playout (packets
skipped with no silence at a delay drop, silent ticks with no packet missed as it grows) is
paid back at 1 / wave_skip_time_s, the rest (an outage's, a loss's: as many silent ticks as
packets missed) at 1 / wave_drift_time_s
(the drift correction of Niemeyer & Slotine, IJRR 2004; Chopra, Spong, Hirche & Buss, ACC
2003). The energy bound, not the rates, keeps the ports passive."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt import config
from teleop_rt.com.channel import make_port
from teleop_rt.com.port import HSI, TO
from teleop_rt.declarations import WAVE_DRIFT_TIME_S, WAVE_SKIP_TIME_S
from teleop_rt.errors import ConfigError
from teleop_rt.session import Session
from tests.test_passive_channels import PASSIVE_J, Harness, drive, schedules

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import transparency_study as ts  # noqa: E402

DT = 1e-3
DROP_AT, FROM, TO_TICKS = 700, 40, 2  # the delay drops 40 -> 2 ticks: 37 packets skipped


def dropped(how: str, skip_s: float | None, outage: bool = False) -> dict[str, np.ndarray]:
    """A free TO (tau_t = 0, no filter) while the HSI moves (0.5 Hz); the HSI -> TO delay
    drops at DROP_AT (``outage``: instead the direction is silent for as many ticks, at a
    constant delay): the TO's debt and skip debt after each tick, and whether its bound cut."""
    harness = Harness("wave", how, 1, None)
    harness.ports = [make_port(side, "wave", [1.5], 1, DT, None, how, None, WAVE_DRIFT_TIME_S,
                               skip_s) for side in (HSI, TO)]  # fmt: skip
    out: dict[str, list] = {"debt": [], "skip": [], "acted": []}
    skipped = FROM - TO_TICKS - 1
    for k in range(3000):
        omega = 0.5 * np.sin(2 * np.pi * 0.5 * k * DT)
        before = int(harness.ports[TO].acted)
        d_to = FROM if outage or k < DROP_AT else TO_TICKS
        silent = outage and DROP_AT <= k < DROP_AT + skipped
        harness.step(k, (np.full(1, omega), np.zeros(1)), (20, d_to), (False, silent))
        out["debt"].append(float(harness.ports[TO].debt[0]))
        out["skip"].append(float(harness.ports[TO].skip_debt[0]))
        out["acted"].append(int(harness.ports[TO].acted) > before)
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("how", ["corrected", "reflected"])
def test_a_delay_drop_s_debt_is_paid_back_at_the_skip_time_constant(how: str) -> None:
    """Closed form: the skipped samples' integral is all skip debt, and with consecutive
    packets after the drop it decays as d (1 - dt / T_skip), not at the drift's 1 - dt / T."""
    t_skip = 2.0
    run = dropped(how, t_skip)
    assert np.all(run["skip"][:DROP_AT] == 0.0)  # no delay change yet
    first = run["skip"][DROP_AT]
    assert abs(first) > 1e-3  # the 37 skipped samples' integral (the HSI moved meanwhile)
    assert first == run["debt"][DROP_AT]  # all of it (no debt before: no pay-back to leave out)
    k = np.arange(DROP_AT + 1, DROP_AT + 1500)
    free = k[~run["acted"][k]]
    assert free.size > 1000
    ratio = run["skip"][free] / run["skip"][free - 1]
    assert np.allclose(ratio, 1.0 - DT / t_skip, rtol=0.0, atol=1e-9), (ratio.min(), ratio.max())


def stepped(how: str) -> dict[str, np.ndarray]:
    """``dropped``'s free TO under a schedule that makes a gap while a debt is owed: an outage
    (37 silent ticks at 40) leaves a drift debt, the delay drops 40 -> 21 -> 2 (19 packets
    skipped at each, the second with a skip debt owed too), then grows 2 -> 12 a tick every
    20 ticks (a silent tick, then a packet with none missed); per tick, as ``dropped``, and
    whether a packet reached the TO."""
    harness = Harness("wave", how, 1, None)
    harness.ports = [make_port(side, "wave", [1.5], 1, DT, None, how, None, WAVE_DRIFT_TIME_S,
                               SKIP_S) for side in (HSI, TO)]  # fmt: skip
    out: dict[str, list] = {"debt": [], "skip": [], "acted": [], "got": []}
    for k in range(2000):
        omega = 0.5 * np.sin(2 * np.pi * 0.5 * k * DT)
        before = int(harness.ports[TO].acted)
        d_to = 40 if k < 900 else 21 if k < 1200 else 2 + min(10, max(0, (k - 1480) // 20))
        harness.step(k, (np.full(1, omega), np.zeros(1)), (20, d_to), (False, 700 <= k < 737))
        out["debt"].append(float(harness.ports[TO].debt[0]))
        out["skip"].append(float(harness.ports[TO].skip_debt[0]))
        out["acted"].append(int(harness.ports[TO].acted) > before)
        out["got"].append(int(harness.rx[TO].valid) == 1)
    return {k: np.array(v) for k, v in out.items()}


SKIP_S = 2.0
GAPS = [900, 1200, *range(1501, 1700, 20)]  # the ticks whose packet closes a delay change's gap


@pytest.mark.parametrize("how", ["corrected", "reflected"])
def test_a_gap_while_a_debt_is_owed_leaves_the_rest_of_it_at_its_rate(how: str) -> None:
    """Closed form, with debt d = s + r (s the skip debt, r the rest) at a tick whose packet
    closes a gap that adds a: each part is paid back at its own rate and the gap's share goes to
    s, so s' = s (1 - dt / T_skip) + a and r' = r (1 - dt / T) on the gap tick as on any other
    tick with a packet (and no cut of the bound). A review found the share booked as the debt's
    change, which holds this tick's pay-back of both parts: s lost that, r was not paid (at a
    delay drop r' = r, here 0.0070 owed from the outage)."""
    run = stepped(how)
    rest, skip = run["debt"] - run["skip"], run["skip"]
    k = np.arange(738, 2000)
    free = k[run["got"][k] & ~run["acted"][k] & (np.abs(rest[k - 1]) > 1e-6)]
    gaps = np.array(GAPS)
    assert set(GAPS) <= set(free)
    assert min(abs(rest[gaps[0] - 1]), abs(skip[gaps[1] - 1])) > 5e-3  # (owed at the gaps)
    ratio = rest[free] / rest[free - 1]
    assert np.allclose(ratio, 1.0 - DT / WAVE_DRIFT_TIME_S, rtol=0.0, atol=1e-9), free[
        np.abs(ratio - (1.0 - DT / WAVE_DRIFT_TIME_S)) > 1e-9]  # fmt: skip
    paying = free[~np.isin(free, gaps) & (np.abs(skip[free - 1]) > 1e-6)]
    assert paying.size > 500
    assert np.allclose(skip[paying] / skip[paying - 1], 1.0 - DT / SKIP_S, rtol=0.0, atol=1e-9)
    # the gap's own: the debt beyond the last one less this tick's pay-back of both parts
    left = run["debt"][gaps - 1] - DT * (rest[gaps - 1] / WAVE_DRIFT_TIME_S
                                         + skip[gaps - 1] / SKIP_S)  # fmt: skip
    a = run["debt"][gaps] - left
    assert np.all(np.abs(a[:2]) > 1e-4)  # (a rise adds the held wave: nothing on reflected's)
    assert np.allclose(skip[gaps], skip[gaps - 1] * (1.0 - DT / SKIP_S) + a, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("how", ["corrected", "reflected"])
def test_an_outage_s_debt_is_no_skip_debt(how: str) -> None:
    """As many silent ticks as packets missed: the debt is the drift correction's, paid at
    1 / WAVE_DRIFT_TIME_S as before, and the skip debt stays exactly 0."""
    run = dropped(how, 2.0, outage=True)
    assert np.all(run["skip"] == 0.0)
    k = np.arange(DROP_AT + FROM, DROP_AT + 1500)
    free = k[~run["acted"][k] & (np.abs(run["debt"][k - 1]) > 1e-6)]
    assert free.size > 500
    ratio = run["debt"][free] / run["debt"][free - 1]
    assert np.allclose(ratio, 1.0 - DT / WAVE_DRIFT_TIME_S, rtol=0.0, atol=1e-9)


def test_off_by_default_a_delay_drop_s_debt_is_one_debt() -> None:
    """WAVE_SKIP_TIME_S (None): no skip debt, the drop's debt paid at the drift correction's
    1 - dt / WAVE_DRIFT_TIME_S per tick (the channel before s37)."""
    assert WAVE_SKIP_TIME_S is None
    run = dropped("reflected", WAVE_SKIP_TIME_S)
    assert np.all(run["skip"] == 0.0) and abs(run["debt"][DROP_AT]) > 1e-3
    k = np.arange(DROP_AT + 1, DROP_AT + 1500)
    free = k[~run["acted"][k] & (np.abs(run["debt"][k - 1]) > 1e-6)]
    assert free.size > 500
    ratio = run["debt"][free] / run["debt"][free - 1]
    assert np.allclose(ratio, 1.0 - DT / WAVE_DRIFT_TIME_S, rtol=0.0, atol=1e-9)


def test_the_config_s_skip_time_constant_reaches_both_ports() -> None:
    cfg = config.load(Path(config.__file__).parents[1] / "configs" / "free_space.yaml",
                      ["channel.wave_skip_time_s=4.0"])  # fmt: skip
    session = Session(cfg)
    assert session.hsi.port.skip_rate == session.to.port.skip_rate == 0.25
    with pytest.raises(ValueError, match="skip debt's time constant must be >= one tick"):
        make_port(TO, "wave", [1.5], 1, DT, None, "reflected", None, 0.25, 0.0)


@pytest.mark.parametrize("key", ["wave_skip_time_s", "wave_drift_time_s", "tdpa_drift_time_s"])
def test_a_time_constant_under_a_tick_is_refused(key: str) -> None:
    """Paid back per tick as debt (1 - dt / T), a T under dt / 2 makes the debt grow: reflected's
    port went to inf and a ZeroDivisionError at T = 0.4 ms (found by a review). Refused by the
    config in one line naming the key, and by the port; one tick is taken."""
    path = Path(config.__file__).parents[1] / "configs" / "free_space.yaml"
    with pytest.raises(ConfigError, match=f"channel.{key} = 0.0004 s is shorter than one tick"):
        config.load(path, [f"channel.{key}=0.0004"])
    config.load(path, [f"channel.{key}=0.001"])
    with pytest.raises(ValueError, match="wave drift correction's time constant must be >= one"):
        make_port(TO, "wave", [1.5], 1, DT, None, "reflected", None, 0.0004, None)


@settings(max_examples=60, deadline=None)
@given(schedule=schedules(150), how=st.sampled_from(["corrected", "reflected"]),
       drift_s=st.floats(DT, 10.0), skip_s=st.floats(DT, 10.0),
       filter_hz=st.sampled_from([None, 30.0]))  # fmt: skip
def test_the_ports_are_passive_at_any_skip_time_constant(schedule, how, drift_s, skip_s,
                                                         filter_hz) -> None:  # fmt: skip
    """Random delays (1..40 ticks: drops skip packets, rises insert silent ticks) and losses:
    the bound keeps the ports passive at any pair of time constants of a tick or more (the
    shortest the config and the ports take)."""
    harness = Harness("wave", how, 1, filter_hz)
    harness.ports = [make_port(side, "wave", [1.5], 1, DT, filter_hz, how, None, drift_s,
                               skip_s) for side in (HSI, TO)]  # fmt: skip
    assert drive(harness, schedule) >= PASSIVE_J


def test_the_foam_sawtooth_row_meets_t_tau_with_the_skip_debt(tmp_path: Path, monkeypatch) -> None:
    """Issue 23's row (c): foam taps, sawtooth 6 -> 111 ms + 5 % loss, newest D = 20 ms. With
    one debt (the default, s36) T_tau is 3.84 against 2.97; with the skip debt paid in 2 s it
    is within 2 x the clean link's + 0.05, T_p too, passive."""
    monkeypatch.setitem(ts.CHANNELS, "skip", (*ts.CHANNELS["reflected"],
                                              "channel.wave_skip_time_s=2.0"))  # fmt: skip
    traces = ts.write_traces(tmp_path)
    net = ts.Net("sawtooth", "newest", 20, {"trace": traces["sawtooth 6-111 ms, 5 % loss"]})
    clean = ts.run("foam taps", net.clean, "reflected")
    limit = ts.T_FACTOR * clean["t_tau"] + ts.T_SLACK
    assert ts.run("foam taps", net, "reflected")["t_tau"] > limit  # one debt: the s36 miss
    row = ts.run("foam taps", net, "skip")
    assert row["t_tau"] <= limit, (row["t_tau"], clean["t_tau"])
    assert row["t_p"] <= ts.T_FACTOR * clean["t_p"] + ts.T_SLACK
    assert row["stop_s"] != row["stop_s"]  # NaN: no stop
    assert min(row["min_energy_j"], row["min_balance_j"]) >= PASSIVE_J
