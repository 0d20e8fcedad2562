"""The staged stop (site.py ``rest_step``) from outside: a spy on every ``write()`` of both
robots' backends, through the normal ticks and the stop, with the faults that broke it
(issue 29). Every write must be finite and inside the URDF effort limits; during the stop the
robots must slow down, never be driven into their speed or position limits; a stop whose
sensors are not plausible commands zero torque."""

from __future__ import annotations

import re

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.session import Session
from tests.conftest import CONFIGS

FAULT_START_S = 4.5  # the operator is pressing the TO into the foam (paper experiment)


class WriteSpy:
    """Every torque a robot's backend is given, with the site's tick and the measured q, v."""

    def __init__(self, site) -> None:
        self.site, self.rows, self.stopping = site, [], False
        backend = site.backend
        self._write, self._begin_rest = backend.write, site.begin_rest
        backend.write = self.write  # (instance attributes: the site calls backend.write)
        site.begin_rest = self.begin_rest

    def begin_rest(self) -> None:
        self.stopping = True
        self._begin_rest()

    def write(self, tau) -> None:
        fb = self.site.backend.feedback
        tau = np.array(tau, dtype=float)
        self.rows.append((self.stopping, tau, fb.q.copy(), fb.v.copy()))
        self._write(tau)

    def during_stop(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Torques, angles and speeds of the staged stop's writes."""
        rows = [r for r in self.rows if r[0]]
        n = self.site.n
        return tuple(np.array([r[k] for r in rows]).reshape(len(rows), n) for k in (1, 2, 3))


def run_spied(*overrides: str, fault: str | None = None):
    items = list(overrides)
    if fault is not None:
        items.append(f"plant.faults=[{fault}]")
    cfg = config.load(CONFIGS / "paper_experiment.yaml", items)
    session = Session(cfg, fuse=False)  # reads and writes through the backends
    spies = {name: WriteSpy(getattr(session, name)) for name in ("hsi", "to")}
    summary = session.run()
    assert summary.safety_stop, "the fault did not stop the session"
    (note,) = [n for n in summary.notes if n.startswith("after the stop")]
    return session, spies, note


def assert_every_write_safe(session, spies) -> None:
    for name, spy in spies.items():
        limits = getattr(session, name).guard.limits
        emax = np.array([e if e is not None else np.inf for e in limits.effort])
        taus = np.array([r[1] for r in spy.rows]).reshape(len(spy.rows), -1)
        assert np.isfinite(taus).all(), f"{name}: a non-finite torque was written"
        assert (np.abs(taus) <= emax).all(), f"{name}: a torque beyond the effort limits"


def bias_on_to(magnitude: float, joint: int = 1) -> str:
    return (
        f"{{kind: bias, robot: to, joint: {joint}, start_s: {FAULT_START_S}, "
        f"magnitude: {magnitude}}}"
    )


@pytest.mark.parametrize("magnitude", [1000.0, 100.0, 20.0])
def test_a_biased_torque_sensor_does_not_drive_the_to_during_its_stop(magnitude) -> None:
    # Before the fix: 1000 N m of bias was fed forward by the stop, 500 ticks at the effort
    # limits [-20, 10] N m, the TO at 43 and 64 rad/s (limits 6, 8), q0 at -13 rad (limit -2.6).
    session, spies, note = run_spied(fault=bias_on_to(magnitude))
    assert_every_write_safe(session, spies)
    to = session.to
    taus, qs, vs = spies["to"].during_stop()
    assert len(taus) > 100  # the stop ran (a zero-torque bail-out would prove nothing)
    lo, hi = to.model.position_limits
    assert (qs >= lo).all() and (qs <= hi).all()
    # damped: never faster than at the stop's first tick (what the 20 ticks the checks took to
    # find the fault left: 2.4 rad/s at 20 N m), except as it yields to the foam, which pushes
    # it out at up to 0.2 rad/s (under a tenth of its speed limits); slower by the stop's end
    vmax = np.array(to.guard.limits.velocity)
    assert (np.abs(vs) <= np.maximum(1.05 * np.abs(vs[0]), 0.1 * vmax)).all()
    assert np.abs(vs[-1]).max() < 0.5 * np.abs(vs[:20]).max()
    assert "the TO stopped without its torque sensor (its own fault)" in note


def test_a_gain_that_diverges_is_stopped_without_a_nan_written() -> None:
    # kp = 1e308: the TO's 4th write was [nan, nan] (the stop used the same gain)
    session, spies, note = run_spied("to.controller.kp=1e308")
    assert_every_write_safe(session, spies)
    _, _, vs = spies["to"].during_stop()
    assert len(vs) > 0 and np.abs(vs[-1]).max() < 1e-3  # brought to rest at a bounded gain
    assert re.search(r"TO at rest after \d+ ticks", note)


def test_implausible_speeds_get_zero_torque_not_a_command_from_them() -> None:
    # velocity noise of 1e200 rad/s: the stop read those speeds and wrote [nan, nan]
    session, spies, note = run_spied("plant.velocity_noise_std_rad_s=1e200")
    assert_every_write_safe(session, spies)
    for spy in spies.values():
        taus, _, _ = spy.during_stop()
        assert len(taus) > 0 and (taus == 0.0).all()
    assert "sensors unusable after 0 ticks: zero torque" in note


def test_the_stop_clamps_to_the_urdf_limits_even_with_safety_off() -> None:
    # safety.enabled: false lets normal ticks through unsaturated; the stop never is (here the
    # HSI's stop damping of 1e6 N m s/rad asks for far more than the motors have)
    session, spies, _ = run_spied(
        "safety.enabled=false", "safety.torque_limits='off'",
        "safety.stop_damping_nm_s_per_rad=1e6", fault=bias_on_to(1000.0),
    )  # fmt: skip
    for name, spy in spies.items():
        taus, _, _ = spy.during_stop()
        emax = np.array(getattr(session, name).guard.limits.effort)
        assert len(taus) > 100 and np.isfinite(taus).all() and (np.abs(taus) <= emax).all()
    hsi_taus, _, _ = spies["hsi"].during_stop()
    assert np.isclose(np.abs(hsi_taus).max(), max(session.hsi.guard.limits.effort))


def test_a_torque_sensor_that_goes_wrong_during_the_stop_is_dropped() -> None:
    # the HSI's sensor fails (its guard finds it: the TO may hold still in the foam with its
    # force fed forward); at the same instant a 5 N m bias appears on the TO's sensor, inside
    # its plausibility bound: the motion disagrees with the command and the sensor is dropped
    hsi_nan = f"{{kind: nan, robot: hsi, joint: 1, start_s: {FAULT_START_S}}}"
    to_bias = bias_on_to(5.0, joint=0)
    session, spies, note = run_spied(f"plant.faults=[{hsi_nan}, {to_bias}]")
    assert_every_write_safe(session, spies)
    assert "the TO's torque sensor disagreed with its motion after 1 ticks; dropped" in note
    taus, _, _ = spies["to"].during_stop()
    # after the first tick no 5 N m is fed forward: the shoulder's command stays small
    assert np.abs(taus[2:, 0]).max() < 2.0


def test_with_a_healthy_to_the_stop_holds_it_in_contact() -> None:
    # the fault is the HSI's: the TO keeps its torque sensor and comes to rest in the foam
    hsi_bias = f"{{kind: bias, robot: hsi, joint: 1, start_s: {FAULT_START_S}, magnitude: 0.5}}"
    session, spies, note = run_spied(fault=hsi_bias)
    assert_every_write_safe(session, spies)
    assert re.search(r"^after the stop: TO at rest after \d+ ticks, then zero torque$", note)


def test_a_non_finite_command_is_a_stop_with_every_check_switched_off() -> None:
    # safety.enabled: false and torque_limits: off leave no limit to compare a command with;
    # a non-finite one (kp = 1e308 over a virtual mass of 1e-300 overflows to inf - inf: NaN)
    # must still stop the run (run_spied asserts it) before it reaches a motor; measurements
    # are still finite at that tick, so only the command guard can catch it (issue 25's mutant)
    session, spies, _ = run_spied(
        "to.controller.kp=1e308", "to.virtual_mass=1e-300", "safety.enabled=false",
        "safety.torque_limits='off'",
    )
    for name, spy in spies.items():
        taus = np.array([r[1] for r in spy.rows]).reshape(len(spy.rows), -1)
        assert len(taus) > 0 and np.isfinite(taus).all(), f"{name}: a non-finite torque written"
