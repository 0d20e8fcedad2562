"""The wave impedance scheduled by the delay (``channel.wave_impedance_schedule``, s38 of
docs/transparency_under_loss.md; ``teleop_rt.com.port.schedule_b``): each port sets its b from
the age of the packet it uses (b_0 D / age, between WAVE_B_FLOOR b_0 and b_0, moving by at most
WAVE_B_RATE b_0 per second). Checked here: the schedule against its closed form; the ports
passive (each port's balance and the two-port's energy >= -1e-9 J) for random ages (so random
time-varying b on both ports, each its own), floors, rates, losses and inputs; off, the
ports compute what they computed before, bit for bit; and a transform whose b moves without
its sqrt(2b) (the energy the waves carry no longer the port's) is caught."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt.com.port import HSI, TO, Packet, Port, port_input, port_step
from teleop_rt.declarations import RECONSTRUCTIONS, WAVE
from tests.test_passive_channels import PASSIVE_J, Harness

DT = 1e-3
POWER_GAP_J = 1e-9  # the port's energy against its waves': rounding over a run, far below


def scheduled_port(side: int, d: int, floor: float, rate: float, on: bool = True,
                   b0: float = 2.0, filter_hz: float | None = 30.0) -> Port:  # fmt: skip
    return Port(side, [b0], d, DT, WAVE, filter_hz, RECONSTRUCTIONS["reflected"],
                wave_impedance_schedule=on, b_floor=floor, b_rate=rate)  # fmt: skip


def closed_form(ages: list[int], floor: float, rate: float, b0: float) -> list[float]:
    """b after each tick: toward b0 min(1, max(floor, a_min / age)), by at most rate b0 dt,
    a_min the least age so far (the path's own delay)."""
    b, out, d = b0, [], math.inf
    for a in ages:
        d = min(d, a)
        target = b0 * (1.0 if a <= d else max(floor, d / a))
        b = min(max(target, b - rate * b0 * DT), b + rate * b0 * DT, b0)
        out.append(b)
    return out


def step_with_age(port: Port, k: int, age: int, rx: Packet, tx: Packet) -> None:
    port_input(port.f, port.i, 1, np.zeros(1), tx.f)
    rx.valid, rx.tick, rx.seq = 1, k - age, k - age
    port.now_tick = k
    port_step(port.f, port.i, 1, rx.f, rx.i, tx.f)


def test_the_schedule_follows_its_closed_form() -> None:
    """Age 20 (the least: the reference), then 80 (target 0.25 b0), then the floor (age 400:
    0.05 -> 0.125 b0), then back at 20: b ramps at 2 b0/s each way, holds on a tick with no
    packet, and is b0 again with b0's own sqrt(2b), bit for bit."""
    d, floor, rate, b0 = 20, 0.125, 2.0, 2.0
    ages = [20] * 50 + [80] * 300 + [400] * 300 + [20] * 600
    port, rx, tx = scheduled_port(TO, d, floor, rate, b0=b0), Packet(1), Packet(1)
    got = []
    for k, a in enumerate(ages):
        step_with_age(port, k + 1000, a, rx, tx)
        got.append(float(port.b_now[0]))
    want = closed_form(ages, floor, rate, b0)
    assert np.allclose(got, want, rtol=0, atol=1e-12)
    assert got[49] == b0 and abs(got[149] - 0.8 * b0) < 1e-12  # 100 ticks at 2 b0 / s
    assert abs(got[649] - floor * b0) < 1e-12  # held at the floor
    assert got[-1] == b0 and port.sqrt_2b_now[0] == math.sqrt(2.0 * b0)
    assert abs(port.sqrt_2_over_b_now[0] - math.sqrt(2.0 / b0)) == 0.0
    # a tick with no packet measures no age: b is held
    port2 = scheduled_port(TO, d, floor, rate, b0=b0)
    for k in range(50):
        step_with_age(port2, k + 1000, 20 if k == 0 else 80, rx, tx)
    held = float(port2.b_now[0])
    rx.valid = 0
    port2.now_tick = 2000
    port_step(port2.f, port2.i, 1, rx.f, rx.i, tx.f)
    assert port2.b_now[0] == held and held < b0


def test_switched_off_the_port_keeps_b_and_computes_as_before() -> None:
    """The same ages with the schedule off: b stays b0; with the age at D (a clean link) the
    scheduled port computes exactly what the unscheduled one does."""
    ports = {on: scheduled_port(HSI, 20, 0.125, 2.0, on) for on in (False, True)}
    rx, tx = Packet(1), Packet(1)
    for k in range(200):
        step_with_age(ports[False], k + 100, 60, rx, tx)
    assert ports[False].b_now[0] == 2.0
    a, b = scheduled_port(HSI, 20, 0.125, 2.0, False), scheduled_port(HSI, 20, 0.125, 2.0, True)
    for k in range(300):
        for p, t in ((a, Packet(1)), (b, Packet(1))):
            port_input(p.f, p.i, 1, np.full(1, math.sin(0.01 * k)), t.f)
            rx.valid, rx.tick, rx.seq = 1, k - 20, k - 20
            rx.wave[0] = math.cos(0.02 * k)
            p.now_tick = k
            port_step(p.f, p.i, 1, rx.f, rx.i, t.f)
        assert a.effort[0] == b.effort[0] and a.wave_out[0] == b.wave_out[0]


class Scheduled(Harness):
    """The two-port harness (arbitrary delay per tick and direction, losses) with both ports'
    b scheduled by the age each measures: D = 1, so any delay beyond a tick lowers b."""

    def __init__(self, floor: float, rate: float, filter_hz: float | None, n: int = 1) -> None:
        super().__init__("wave", "reflected", n, filter_hz)
        self.ports = [Port(side, [1.5] * n, 1, DT, WAVE, filter_hz, RECONSTRUCTIONS["reflected"],
                           wave_impedance_schedule=True, b_floor=floor, b_rate=rate)
                      for side in (HSI, TO)]  # fmt: skip

    def step(self, k, inputs, delays, lost) -> None:
        for port in self.ports:
            port.now_tick = k
        super().step(k, inputs, delays, lost)


def varying(ticks: int):
    """Per tick and direction a delay in runs (1..60 ticks), a loss flag; inputs in [-5, 5]."""
    runs = st.lists(st.tuples(st.integers(1, 40), st.integers(1, 60)), min_size=1, max_size=10)

    def expand(r):
        out = [v for length, v in r for _ in range(length)]
        return (out * (ticks // len(out) + 1))[:ticks]

    lost = st.lists(st.booleans(), min_size=ticks, max_size=ticks)
    signal = st.lists(st.floats(-5, 5, allow_nan=False), min_size=ticks, max_size=ticks)
    return st.tuples(runs.map(expand), runs.map(expand), lost, lost, signal, signal)


def power_gap(port: Port) -> float:
    """How far the port's energy (the integral of omega tau into the channel) is from its
    waves' (dt / 2 times the sum of sent^2 minus received^2, as the filter gave them), J: 0 up
    to rounding when the transform conserves power at the b it used in each tick."""
    return float(np.abs(port.energy - (port.wave_energy - port.out_energy)).max())


def drive_scheduled(harness: Scheduled, schedule) -> tuple[float, float, float]:
    """The lowest balance or two-port energy seen, the range b took on either port, and the
    largest power gap (``power_gap``) of either port."""
    d_h, d_t, l_h, l_t, x_h, x_t = schedule
    low, b_lo, b_hi, gap = 0.0, math.inf, -math.inf, 0.0
    for k in range(len(d_h)):
        inputs = (np.full(harness.n, x_h[k]), np.full(harness.n, x_t[k]))
        harness.step(k, inputs, (d_h[k], d_t[k]), (l_h[k], l_t[k]))
        low = min(low, harness.lowest())
        for p in harness.ports:
            b_lo, b_hi = min(b_lo, float(p.b_now.min())), max(b_hi, float(p.b_now.max()))
            gap = max(gap, power_gap(p))
    return low, b_hi - b_lo, gap


@settings(max_examples=150, deadline=None)
@given(schedule=varying(200), floor=st.floats(0.02, 1.0), rate=st.floats(0.5, 2000.0),
       filter_hz=st.sampled_from([None, 30.0]))  # fmt: skip
def test_scheduled_ports_are_passive_for_any_b_delays_losses_and_inputs(schedule, floor, rate,
                                                                       filter_hz) -> None:
    """Each port's b moves with the age it measures (at rate 2000 b0/s, from tick to tick),
    each its own: every port's balance and the two-port's energy stay >= -1e-9 J, and each
    port's energy is its waves' (the transform conserves power at each tick's b)."""
    low, _, gap = drive_scheduled(Scheduled(floor, rate, filter_hz), schedule)
    assert low >= PASSIVE_J
    assert gap <= POWER_GAP_J


def test_the_check_sees_a_b_moved_without_its_transform() -> None:
    """The case the passivity test is for: b ramping between 1.5 and its floor while the ports
    exchange waves. A transform that used sqrt(2 b0) with the scheduled b (the waves carrying
    other energy than the port's power) is caught by the power gap; the scheduled transform
    is not. (The two-port's energy alone need not catch it here: the budget keeps the waves'
    account, and what the mismatch makes can stay within the energy stored in flight.)"""
    ticks = 600
    rng = np.random.default_rng(3)
    d = [1 + 30 * ((k // 100) % 2) for k in range(ticks)]
    schedule = (d, d[::-1], [False] * ticks, [False] * ticks,
                list(rng.uniform(-5, 5, ticks)), list(rng.uniform(-5, 5, ticks)))
    low, moved, gap = drive_scheduled(Scheduled(0.1, 200.0, None), schedule)
    assert moved > 1.0 and low >= PASSIVE_J and gap <= POWER_GAP_J
    broken = Scheduled(0.1, 200.0, None)
    for p in broken.ports:  # the mutation: b moves, its sqrt(2b) and sqrt(2/b) stay b0's
        p.sqrt_2b_now[:] = p.sqrt_2b
    original = broken.step

    def step(k, inputs, delays, lost) -> None:
        original(k, inputs, delays, lost)
        for p in broken.ports:
            p.sqrt_2b_now[:], p.sqrt_2_over_b_now[:] = p.sqrt_2b, p.sqrt_2_over_b

    broken.step = step  # type: ignore[method-assign]
    low, moved, gap = drive_scheduled(broken, schedule)
    assert moved > 1.0 and gap > 1e3 * POWER_GAP_J
