"""The fused simulated tick (teleop_rt.sim_tick): on two simulated plants in their common case a
session runs the controller's and the plants' compiled pieces in four calls instead of through
``Backend.read`` / ``write``. It must compute exactly what the backends' own entry points do,
bit for bit, and only run where it applies."""

from __future__ import annotations

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.errors import SafetyStop
from teleop_rt.hal import sim
from teleop_rt.hal.base import register_backend
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PAPER = CONFIGS / "paper_experiment.yaml"


def general_step(session: Session) -> None:
    """The tick through the backends' read and write, whatever the session chose."""
    Session.step(session)


def test_the_fused_tick_equals_the_backends_entry_points_bit_for_bit() -> None:
    """The whole paper experiment (free space, foam, the wall) with 20 ms of delay, tick by
    tick: every signal and state of the session and of both plants (one packed buffer pair
    holds them all) agrees exactly."""
    cfg = config.load(PAPER, ["channel.delay_ms=20"])
    fused, general = Session(cfg), Session(cfg)
    assert fused.fused and general.fused
    contacts = np.zeros(2)
    for k in range(cfg.n_ticks):
        fused.step()
        general_step(general)
        assert np.array_equal(fused.packed.f, general.packed.f), k
        assert np.array_equal(fused.packed.i, general.packed.i), k
        contacts += fused.to.backend.world.contacts
    assert contacts.min() > 500, f"foam and wall must both have been pressed: {contacts}"
    assert fused.tick == general.tick == cfg.n_ticks


def test_a_safety_stop_in_the_fused_tick_reaches_no_plant() -> None:
    """A wildly unstable HSI: both ticks stop at the same tick with the same finding, and the
    plants keep the motor torques of the last tick that passed the checks."""
    cfg = config.load(PAPER, ["duration_s=3", "hsi.controller.kp=1e6"])
    fused, general = Session(cfg), Session(cfg)

    def run_to_stop(session: Session, step) -> tuple[int, str, list[np.ndarray]]:
        checked = []
        with pytest.raises(SafetyStop) as err:
            for _ in range(cfg.n_ticks):
                step()
                checked = [s.computed_torque.tau.copy() for s in (session.hsi, session.to)]
        return session.tick, str(err.value), checked

    tick, finding, checked = run_to_stop(fused, fused.step)
    assert (tick, finding) == run_to_stop(general, lambda: general_step(general))[:2]
    assert 0 < tick < cfg.n_ticks
    assert np.array_equal(fused.packed.f, general.packed.f)
    for side, tau in zip((fused.hsi, fused.to), checked, strict=True):
        assert np.array_equal(side.backend.tau_motor, tau), side.name
    assert not np.array_equal(fused.hsi.backend.tau_motor, fused.hsi.computed_torque.tau)


@pytest.mark.parametrize(
    "overrides",
    [
        ["plant.integrator=rk4"],
        ["plant.substeps=2"],
        ["plant.velocity_noise_std_rad_s=0.001"],
        ["plant.faults=[{kind: stuck, robot: hsi, start_s: 100.0}]"],
    ],
)
def test_the_general_path_runs_where_the_fused_tick_does_not_apply(overrides) -> None:
    session = Session(config.load(PAPER, overrides))
    assert not session.fused
    session.step()  # and the plants, packed with the session, still step
    assert session.hsi.backend.state.tick == 1


class _Recording(sim.SimBackend):
    """A sim backend that overrides write: the session must call it."""

    def write(self, tau) -> None:
        self.written += 1
        super().write(tau)


@register_backend("test_sim_recording_writes")
def _recording(cfg, side, model, operator=None):
    backend = sim._make_sim(cfg, side, model, operator)
    backend.__class__ = _Recording
    backend.written = 0
    return backend


def test_a_backend_that_overrides_its_entry_points_is_called_through_them() -> None:
    session = Session(config.load(PAPER, ["backend=test_sim_recording_writes"]))
    assert not session.fused
    for _ in range(3):
        session.step()
    assert session.hsi.backend.written == session.to.backend.written == 3
