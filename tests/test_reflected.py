"""Energy reflection (issue 23): the ``reflected`` wave reconstruction holds a static push
through a burst of losses and stays passive. Proven on the two ports alone.

In a static push the TO's port takes almost no net power, (u^2 - v^2) / 2 = omega_t tau_t ~ 0:
the wave it uses is reflected back to the HSI. A per-direction budget (``bounded``) forbids
using a wave beyond the energy received, so a burst takes the wall away. The two-port only
needs the sum over both directions: a port may emit beyond its budget what it reflects, if it
removes the excess from the energy it declares to the peer (then the peer cannot spend the
reflected energy a second time). Checked here: the two-port's own energy (the integral of the
power into both ports, no bookkeeping) and each port's room stay >= -1e-9 J for any inputs,
delays, losses and reorderings; the wall's force stays through a burst; with the excess not
removed from the declaration (the mutation) the two-port makes energy.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt.com.port import HSI, TO
from tests.test_passive_channels import PASSIVE_J, Harness, drive, schedules
from tests.test_wave_drift import positions


class Reordering(Harness):
    """The harness, but a port also gets packets older than the last one it used (a link
    that reorders with no playout to sort them out)."""

    def step(self, k: int, inputs, delays, lost) -> None:  # type: ignore[override]
        self.last = [-1, -1]
        super().step(k, inputs, delays, lost)


@settings(max_examples=150, deadline=None)
@given(schedule=schedules(150), filter_hz=st.sampled_from([None, 30.0]),
       n=st.sampled_from([1, 2]), reorder=st.booleans())  # fmt: skip
def test_reflected_ports_are_passive_for_any_delays_losses_reorderings_and_inputs(
    schedule, filter_hz, n, reorder
) -> None:
    harness = (Reordering if reorder else Harness)("wave", "reflected", n, filter_hz)
    assert drive(harness, schedule) >= PASSIVE_J


def push(how: str, burst: range, ticks: int = 3000, extract: float = 0.0) -> dict:
    """The HSI held still (omega_c = 0, then ``extract`` rad/s from the burst on) against the
    TO pressed by a constant 2 N m (a static push on a wall), 5 ticks each way, 30 Hz filter;
    both directions silent during ``burst``. The HSI's effort per tick and the lowest
    two-port energy or balance seen."""
    harness = Harness("wave", how, 1, 30.0)
    tau_c, low = np.zeros(ticks), 0.0
    for k in range(ticks):
        omega = extract if k >= burst.start else 0.0
        lost = k in burst
        harness.step(k, (np.full(1, omega), np.full(1, 2.0)), (5, 5), (lost, lost))
        tau_c[k] = harness.ports[HSI].effort[0]
        low = min(low, harness.lowest())
    return {"tau_c": tau_c, "low": low, "to_flow": float(harness.ports[TO].flow[0])}


def test_a_static_push_is_held_through_a_burst() -> None:
    """The push settles at tau_c = 2 N m; through 40 lost ticks each way ``reflected`` keeps
    it within 1 % (the TO's held wave is reflected, the HSI's held wave too); ``bounded`` runs
    out of budget in the burst and the force goes (it keeps less than half)."""
    burst = range(2000, 2040)
    held = push("reflected", burst)
    assert abs(held["tau_c"][1999] - 2.0) < 1e-3  # settled
    assert np.all(np.abs(held["tau_c"][burst] - 2.0) < 0.02)
    assert held["low"] >= PASSIVE_J
    cut = push("bounded", burst)
    assert abs(cut["tau_c"][1999] - 2.0) < 1e-3
    assert np.abs(cut["tau_c"][burst][-10:]).max() < 1.0


def test_the_reflected_energy_is_not_spent_twice() -> None:
    """The HSI -> TO direction lost for good: the TO brakes and
    reflects the push, the HSI moves back and the held push would do work on it. What the TO
    emitted beyond its budget is taken off its declaration, so the HSI has no budget for it
    and the two-port's energy stays >= 0 (with the declaration not reduced it goes negative:
    the mutation this guards)."""
    harness = Harness("wave", "reflected", 1, 30.0)
    low = 0.0
    for k in range(3000):
        omega = -0.3 if k >= 1000 else 0.0
        harness.step(k, (np.full(1, omega), np.full(1, 2.0)), (5, 5), (False, k >= 1000))
        low = min(low, harness.lowest())
    assert low >= PASSIVE_J
    assert abs(harness.ports[TO].flow[0]) < 1e-12  # braked: the TO holds its place


def test_on_a_clean_link_reflected_is_bounded_bit_for_bit() -> None:
    a = positions("bounded", range(0), 3000)
    b = positions("reflected", range(0), 3000)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
