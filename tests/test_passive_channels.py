"""Passive over any network (issue 17): the protected channels (the energy-bounded wave
integral, TDPA) stay passive under every impairment class of the link, in free space and
against the 5000 N/m wall; the unprotected ones (hold, integral) show what goes wrong; with
nothing to protect against, the protections compute today's channel or stay inactive.

"Passive" is checked two ways, each to -1e-9 J (rounding of sums of ~1e4 terms of ~1e-4 J):
each port's balance as its method accounts it (wave energy received minus emitted; TDPA's
peer E_in minus own E_out), and the two-port's own energy, the integral of the power entering
both ports (eq 7, 8), which needs neither method's bookkeeping.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt import config
from teleop_rt.com.channel import make_port
from teleop_rt.com.port import HOLD_TICKS, HSI, TO, Packet, port_input, port_step
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PASSIVE_J = -1e-9
SECONDS = 20.0
# the operator moves the HSI back and forth for the whole run (free space: the config's own
# script lasts 4 s), between two points a second apart
SWEEP = [
    {"t_s": 0.5 + k, "position_m": [0.29, -0.005] if k % 2 == 0 else [0.38, 0.035]}
    for k in range(int(SECONDS))
]
# the network's one-way delay around 20 ms; with the ``newest`` playout and a 2 ms minimum
# playout delay its variations reach the ports (the fixed playout would absorb them)
CLASSES = {
    "jitter": {"delay_ms": 20, "jitter_ms": 6, "correlation_percent": 25},
    "delay_step_down": {"delay_ms": 40, "delay_step": {"at_s": 6.0, "delay_ms": 8}},
    "loss": {"delay_ms": 20, "loss_percent": 5},
    "burst_loss": {"delay_ms": 20, "gilbert_elliott": {"p_percent": 1, "r_percent": 10}},
    "reordering": {"delay_ms": 20, "reorder_percent": 25, "reorder_gap": 3},
    "duplication": {"delay_ms": 20, "jitter_ms": 3, "duplicate_percent": 20},
}
PROTECTED = {"bounded wave": ["channel.mode=wave", "channel.wave_reconstruction=bounded"],
             "tdpa": ["channel.mode=tdpa"],
             "corrected wave": ["channel.mode=wave", "channel.wave_reconstruction=corrected"],
             "reflected wave": ["channel.mode=wave", "channel.wave_reconstruction=reflected"]}


def write_traces(folder: Path) -> dict[str, Path]:
    """Two traces of our own (seeded): a congested link whose delay ramps 10 -> 80 -> 10 ms
    every 2 s (beyond the playout's ring, in step with the free-space sweep) with 3 % loss,
    and a wireless-like one: 15 ms +- 4 with 50 ms outages every second."""
    rng = np.random.default_rng(7)
    ticks = np.arange(4000)
    ramp = 10 + 70 * (1 - np.abs((ticks % 2000) / 1000.0 - 1))
    wireless = 15 + 4 * rng.standard_normal(ticks.size).clip(-3, 3)
    outage = (ticks % 1000) >= 950
    out = {}
    for name, delay, lost in (
        ("trace_ramp", ramp, rng.random(ticks.size) < 0.03),
        ("trace_outages", wireless, outage),
    ):
        path = folder / f"{name}.csv"
        cells = ["lost" if gone else f"{d:.3f}" for d, gone in zip(delay, lost, strict=True)]
        rows = ["send_tick,delay_ms", *(f"{k},{c}" for k, c in enumerate(cells))]
        path.write_text("\n".join(rows) + "\n")
        out[name] = path
    return out


def run(
    path: Path, impairment: dict | None, channel: list[str], playout: str = "newest",
    delay_ms: int = 2, seconds: float = SECONDS, sweep: bool = True,
) -> Session:  # fmt: skip
    overrides = [f"duration_s={seconds}", f"channel.delay_ms={delay_ms}",
                 f"link.playout={playout}", *channel]  # fmt: skip
    if impairment is not None:
        overrides.append("link.impairment=" + json.dumps({"seed": 3, **impairment}))
    if path.stem == "free_space" and sweep:
        overrides.append("operator.waypoints=" + json.dumps(SWEEP))
    session = Session(config.load(path, overrides))
    session.summary = session.run()
    return session


def min_balance(session: Session) -> float:
    return min(session.hsi.port.min_balance, session.to.port.min_balance)


def assert_passive_and_bounded(session: Session) -> None:
    s = session.summary
    assert not s.safety_stop and s.stopped_early is None, s.stopped_early
    assert min_balance(session) >= PASSIVE_J
    assert s.min_channel_energy_j >= PASSIVE_J
    for site in session.sites:  # bounded motion: finite, and no faster than 10 rad/s
        assert np.isfinite(site.feedback.q).all()
        assert np.abs(site.feedback.v).max() < 10.0


ENVIRONMENTS = [CONFIGS / "free_space.yaml", CONFIGS / "stiff_wall.yaml"]


@pytest.mark.parametrize("protection", list(PROTECTED))
@pytest.mark.parametrize("impairment", [*CLASSES, "trace_ramp", "trace_outages"])
@pytest.mark.parametrize("path", ENVIRONMENTS, ids=lambda p: p.stem)
def test_protected_channels_stay_passive_under_every_impairment(
    path: Path, impairment: str, protection: str, tmp_path: Path
) -> None:
    spec = CLASSES.get(impairment) or {"trace": str(write_traces(tmp_path)[impairment])}
    session = run(path, spec, PROTECTED[protection])
    assert_passive_and_bounded(session)
    link = session.summary.link["to"]
    assert link["lost"] + link["skipped"] > 0  # the network did reach the ports


@pytest.mark.parametrize("protection", list(PROTECTED))
def test_protected_channels_stay_passive_with_the_fixed_playout(protection: str) -> None:
    """Jitter beyond the playout delay and loss: the fixed playout turns both into missing
    packets, at D = 20 ms."""
    spec = {"delay_ms": 15, "jitter_ms": 5, "loss_percent": 3}
    session = run(CONFIGS / "stiff_wall.yaml", spec, PROTECTED[protection], "fixed", 20)
    assert_passive_and_bounded(session)
    assert session.summary.link["to"]["late"] > 0


def test_the_unprotected_channel_makes_energy_when_packets_are_lost() -> None:
    """Holding the last wave through a loss emits wave energy the peer never sent; the bound
    on the same network does not."""
    hold = run(CONFIGS / "free_space.yaml", CLASSES["loss"], ["channel.wave_reconstruction=hold"])
    assert min_balance(hold) < -1e-5
    bounded = run(CONFIGS / "free_space.yaml", CLASSES["loss"],
                  ["channel.wave_reconstruction=bounded"])
    assert min_balance(bounded) >= PASSIVE_J
    assert bounded.hsi.port.acted + bounded.to.port.acted > 0  # the bound is what did it


@pytest.mark.parametrize(
    "how, step",
    [("integral", {"delay_ms": 30, "delay_step": {"at_s": 2.0, "delay_ms": 22}}),
     ("hold", {"delay_ms": 5, "delay_step": {"at_s": 2.0, "delay_ms": 40}})],
    ids=["integral, step down", "hold, step up"],
)  # fmt: skip
def test_the_unprotected_channel_makes_energy_when_the_delay_steps(how, step) -> None:
    """The two-port itself goes below zero energy: a step down (by 8 ticks, within CATCH_UP)
    lets the unbounded wave integral replay the skipped waves in one tick; a step up leaves
    ticks with no packet, which holding fills with a wave nobody sent. Bounded, the same steps
    stay passive."""
    path = CONFIGS / "stiff_wall.yaml"
    unprotected = run(path, step, [f"channel.wave_reconstruction={how}"], seconds=6)
    assert unprotected.summary.min_channel_energy_j < -1e-4
    bounded = run(path, step, [], seconds=6)
    assert bounded.summary.min_channel_energy_j >= PASSIVE_J
    assert min_balance(bounded) >= PASSIVE_J


def test_the_bound_that_never_acts_changes_nothing() -> None:
    """Jitter within the fixed playout's delay, no loss: the bounded channel computes the zero
    channel's numbers bit for bit (the bound compares the same sums, and never acts)."""
    spec = {"delay_ms": 8, "jitter_ms": 2}
    runs = [run(CONFIGS / "stiff_wall.yaml", spec, [f"channel.wave_reconstruction={how}"],
                "fixed", 20, seconds=4) for how in ("zero", "bounded")]  # fmt: skip
    zero, bounded = runs
    assert bounded.hsi.port.acted == bounded.to.port.acted == 0
    assert zero.summary.t_p == bounded.summary.t_p and zero.summary.t_tau == bounded.summary.t_tau
    assert np.array_equal(zero.to.feedback.q, bounded.to.feedback.q)


def test_with_no_delay_tdpa_is_the_direct_coupling_and_never_acts() -> None:
    runs = {}
    for mode in ("tdpa", "direct", "wave"):
        session = run(CONFIGS / "stiff_wall.yaml", None, [f"channel.mode={mode}"], delay_ms=0,
                      seconds=6)  # fmt: skip
        runs[mode] = session
    tdpa, direct = runs["tdpa"], runs["direct"]
    assert tdpa.hsi.port.acted == tdpa.to.port.acted == 0
    assert tdpa.hsi.port.limited.sum() == tdpa.to.port.limited.sum() == 0.0
    assert tdpa.summary.t_p == direct.summary.t_p and tdpa.summary.t_tau == direct.summary.t_tau
    assert tdpa.summary.t_tau == runs["wave"].summary.t_tau  # at D = 0 every kind couples directly


def test_tdpa_makes_the_delayed_direct_channel_passive() -> None:
    """Direct delayed force feedback against the wall makes energy and is stopped; TDPA on the
    same coupling dissipates what its observers see and stays passive."""
    direct = run(CONFIGS / "stiff_wall.yaml", None, ["channel.mode=direct"], "fixed", 20, 6)
    assert direct.summary.min_channel_energy_j < -0.1
    tdpa = run(CONFIGS / "stiff_wall.yaml", None, ["channel.mode=tdpa"], "fixed", 20, 6)
    assert_passive_and_bounded(tdpa)
    assert tdpa.hsi.port.acted > 0 and tdpa.to.port.acted > 0
    assert tdpa.summary.channel["to"]["removed_j"] > 0


# --- property tests: the ports alone, any inputs, any delays and losses ----------------------


class Harness:
    """Two ports stepped against each other through an arbitrary delivery schedule: at tick k a
    port gets the peer's packet sent at k - d_k, unless it is lost or not newer than the last
    one it used (what the playout guarantees), else none."""

    def __init__(self, mode: str, how: str, n: int, filter_hz: float | None) -> None:
        self.n = n
        self.ports = [make_port(side, mode, [1.5] * n, 1, 1e-3, filter_hz, how)
                      for side in (HSI, TO)]  # fmt: skip
        self.tx = [Packet(n), Packet(n)]
        self.rx = [Packet(n), Packet(n)]
        self.sent: list[list[tuple[np.ndarray, np.ndarray]]] = [[], []]
        self.last = [-1, -1]

    def step(self, k: int, inputs: tuple[np.ndarray, np.ndarray], delays: tuple[int, int],
             lost: tuple[bool, bool]) -> None:  # fmt: skip
        for side in (HSI, TO):
            port, tx = self.ports[side], self.tx[side]
            port_input(port.f, port.i, self.n, inputs[side], tx.f)
            tx.tick = tx.seq = k
            tx.valid = 1
        for side in (HSI, TO):
            rx, s = self.rx[side], k - delays[side]
            if 0 <= s < len(self.sent[1 - side]) and s > self.last[side] and not lost[side]:
                rx.f[:], rx.i[:] = self.sent[1 - side][s]
                self.last[side] = s
            else:
                rx.f[:], rx.i[:] = 0.0, 0
            port, tx = self.ports[side], self.tx[side]
            port_step(port.f, port.i, self.n, rx.f, rx.i, tx.f)
        for side in (HSI, TO):
            self.sent[side].append((self.tx[side].f.copy(), self.tx[side].i.copy()))

    def lowest(self) -> float:
        """The smaller of the ports' balances and the two-port's energy."""
        h, t = self.ports
        return min(h.balance, t.balance, h.total_energy + t.total_energy)


def schedules(ticks: int):
    """Per tick and direction: a delay (1..40 ticks, steps and runs included), a loss flag,
    and each port's input in [-5, 5]."""
    delay = st.lists(st.integers(1, 40), min_size=ticks, max_size=ticks)
    lost = st.lists(st.booleans(), min_size=ticks, max_size=ticks)
    signal = st.lists(st.floats(-5, 5, allow_nan=False), min_size=ticks, max_size=ticks)
    return st.tuples(delay, delay, lost, lost, signal, signal)


def drive(harness: Harness, schedule) -> float:
    d_h, d_t, l_h, l_t, x_h, x_t = schedule
    low = 0.0
    for k in range(len(d_h)):
        inputs = (np.full(harness.n, x_h[k]), np.full(harness.n, x_t[k]))
        harness.step(k, inputs, (d_h[k], d_t[k]), (l_h[k], l_t[k]))
        low = min(low, harness.lowest())
    return low


@settings(max_examples=150, deadline=None)
@given(
    schedule=schedules(150),
    channel=st.sampled_from([("wave", "bounded"), ("tdpa", "bounded")]),
    filter_hz=st.sampled_from([None, 30.0]),
)
def test_protected_ports_are_passive_for_any_delays_losses_and_inputs(
    schedule, channel, filter_hz
) -> None:
    assert drive(Harness(*channel, 1, filter_hz), schedule) >= PASSIVE_J


def test_the_harness_catches_an_active_channel() -> None:
    """The same harness finds the unprotected channels active: a constant push through a run
    of losses (hold) and a delay that drops from 9 ticks to 1 (integral: it catches up what
    it skipped, up to CATCH_UP packets, in one tick)."""
    ticks = 120
    losses = [20 <= k < 40 for k in range(ticks)]
    pushes = ([3.0] * ticks, [1.0] * ticks)
    hold = ([5] * ticks, [5] * ticks, losses, losses, *pushes)
    assert drive(Harness("wave", "hold", 1, None), hold) < -1e-3
    drop = ([9] * 60 + [1] * 60, [9] * 60 + [1] * 60, [False] * ticks, [False] * ticks, *pushes)
    assert drive(Harness("wave", "integral", 1, None), drop) < -1e-3
    for channel in (("wave", "bounded"), ("tdpa", "bounded")):
        assert drive(Harness(*channel, 1, None), hold) >= PASSIVE_J
        assert drive(Harness(*channel, 1, None), drop) >= PASSIVE_J


def test_tdpa_holds_the_peers_velocity_through_a_short_gap_only() -> None:
    """The TO moves on at the HSI's last velocity for HOLD_TICKS ticks of a gap, then stops: a
    held velocity would drive it for as long as the network is silent."""
    harness, ticks = Harness("tdpa", "bounded", 1, None), 60
    lost = [k >= 20 for k in range(ticks)]
    flows = []
    for k in range(ticks):
        harness.step(k, (np.full(1, 0.7), np.zeros(1)), (1, 1), (False, lost[k]))
        flows.append(float(harness.ports[TO].flow[0]))
    assert flows[1:20] == [0.7] * 19
    assert flows[20 : 20 + HOLD_TICKS] == [0.7] * HOLD_TICKS
    assert flows[20 + HOLD_TICKS :] == [0.0] * (ticks - 20 - HOLD_TICKS)


def test_tdpa_drift_compensation_brings_the_to_back_and_stays_passive() -> None:
    """Against the wall the passivity controllers cut the TO's velocity and it ends 0.05 rad
    from the HSI; with the compensation it ends where the HSI is, passive all the way. In free
    space with nothing lost (no controller acts) the compensation adds exactly nothing."""
    runs = {}
    for drift in ("null", "0.2"):
        channel = ["channel.mode=tdpa", f"channel.tdpa_drift_time_s={drift}"]
        wall = run(CONFIGS / "stiff_wall.yaml", None, channel, "fixed", 20, 6)
        runs[drift] = (wall, run(CONFIGS / "free_space.yaml", None, channel, "fixed", 20, 4))
    (wall_off, free_off), (wall_on, free_on) = runs["null"], runs["0.2"]

    def gap(s: Session) -> float:  # the operator holds still at the end of both scripts
        return float(np.abs(s.hsi.feedback.q - s.to.feedback.q).max())

    assert gap(wall_off) > 0.02 and gap(wall_on) < 0.01 * gap(wall_off)
    assert_passive_and_bounded(wall_on)
    assert wall_on.to.port.acted > 0
    assert free_on.to.port.acted == 0
    assert np.array_equal(free_on.to.feedback.q, free_off.to.feedback.q)
