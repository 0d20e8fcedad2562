"""The fused simulated tick (teleop_rt.lockstep_fused, chosen by ``fuse_plants``): on two
simulated plants in their common case a session packs the plants with its own blocks and runs
the lock-step's and the plants' compiled pieces in four calls instead of through
``Backend.read`` / ``write``. It must compute exactly what plants on their own buffers compute,
bit for bit, and only run where it applies."""

from __future__ import annotations

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.errors import SafetyStop
from teleop_rt.hal import sim
from teleop_rt.hal.registry import register_backend
from teleop_rt.lockstep import SESSION_BLOCKS
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PAPER = CONFIGS / "paper_experiment.yaml"


def through_backends(session: Session) -> Session:
    """The session, told to tick through the backends' read and write whatever it chose."""
    session.fused = False
    return session


def unpacked_session(cfg: config.SessionConfig) -> Session:
    """A session whose plants keep their own buffers and are stepped through read / write, as
    before the fused tick existed: the reference."""
    session = Session(cfg, fuse=False)
    assert not session.fused and len(session.packed.blocks) == SESSION_BLOCKS
    return session


def states(session: Session) -> list[np.ndarray]:
    """Every block of the session and of both plants, wherever they are packed."""
    plants = [b for side in (session.hsi, session.to) for b in side.backend.blocks]
    return [x for b in [*session.packed.blocks[:SESSION_BLOCKS], *plants] for x in (b.f, b.i)]


# the paper experiment with delay: a hand, foam and a wall; a damper operator (a joint load)
# with a TO pulled by a spring against a mass it pushes
CASES = {
    "paper, 20 ms": ["channel.delay_ms=20"],
    "damper, spring, mass": [
        "duration_s=4",
        "operator={kind: damper, damping_nm_s_per_rad: 0.2}",
        "environment=[{kind: spring, point_m: [0.38, 0.0], normal: [-1, 0], "
        "stiffness_n_per_m: 200}, {kind: mass, point_m: [0.0, -0.012], normal: [0, 1], "
        "mass_kg: 0.5}]",
    ],
}


@pytest.mark.parametrize("case", CASES)
def test_the_fused_tick_equals_plants_on_their_own_buffers_bit_for_bit(case) -> None:
    """Tick by tick, every signal and state of the session and of both plants agrees exactly
    with a session whose plants keep their own buffers and are stepped through read / write;
    so does the packed session stepped through read / write."""
    cfg = config.load(PAPER, CASES[case])
    fused, reference = Session(cfg), unpacked_session(cfg)
    general = through_backends(Session(cfg))
    assert fused.fused
    q0, moved, touched = np.array(cfg.hsi.robot.q0_rad), 0.0, np.zeros(len(cfg.environment))
    for k in range(cfg.n_ticks):
        fused.step()
        general.step()
        reference.step()
        for a, b, c in zip(states(fused), states(general), states(reference), strict=True):
            assert np.array_equal(a, c) and np.array_equal(b, c), k
        moved = max(moved, np.abs(fused.hsi.feedback.q - q0).max())
        touched += fused.to.backend.world.contacts
    assert fused.tick == cfg.n_ticks
    assert moved > 0.05, f"the HSI must have moved: {moved} rad"
    assert touched.min() >= 5, f"the TO must have touched every element: {touched} ticks"


def test_a_safety_stop_in_the_fused_tick_reaches_no_plant() -> None:
    """A wildly unstable HSI: both paths stop at the same tick with the same finding, and the
    plants keep the motor torques of the last tick that passed the checks."""
    cfg = config.load(PAPER, ["duration_s=3", "hsi.controller.kp=1e6"])
    fused, general = Session(cfg), through_backends(Session(cfg))

    def run_to_stop(session: Session, step) -> tuple[int, str, list[np.ndarray]]:
        checked = []
        with pytest.raises(SafetyStop) as err:
            for _ in range(cfg.n_ticks):
                step()
                checked = [s.computed_torque.tau.copy() for s in (session.hsi, session.to)]
        return session.tick, str(err.value), checked

    tick, finding, checked = run_to_stop(fused, fused.step)
    assert (tick, finding) == run_to_stop(general, general.step)[:2]
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
def test_the_general_path_runs_where_the_fused_tick_does_not_apply(overrides):
    """Sub-steps, RK4, noise, faults: the plants, packed with the session, step through read /
    write, exactly as on their own buffers."""
    cfg = config.load(PAPER, ["duration_s=0.3", *overrides])
    session, reference = Session(cfg), unpacked_session(cfg)
    assert not session.fused
    for k in range(cfg.n_ticks):
        session.step()
        reference.step()
        for a, b in zip(states(session), states(reference), strict=True):
            assert np.array_equal(a, b), k


class _CountingWrites(sim.SimBackend):
    def write(self, tau) -> None:
        self.calls += 1
        super().write(tau)


class _CountingReads(sim.SimBackend):
    def read(self):
        self.calls += 1
        return super().read()


def _counting(cls):
    def factory(cfg, side, model, operator=None):
        backend = sim.make_sim(cfg, side, model, operator)
        backend.__class__ = cls
        backend.calls = 0
        return backend

    return factory


register_backend("test_sim_counting_writes")(_counting(_CountingWrites))
register_backend("test_sim_counting_reads")(_counting(_CountingReads))


@register_backend("test_sim_write_replaced")
def _write_replaced(cfg, side, model, operator=None):
    backend = sim.make_sim(cfg, side, model, operator)
    plain = backend.write
    backend.calls = 0

    def write(tau) -> None:
        backend.calls += 1
        plain(tau)

    backend.write = write
    return backend


@pytest.mark.parametrize(
    "backend", ["test_sim_counting_writes", "test_sim_counting_reads", "test_sim_write_replaced"]
)
def test_a_backend_whose_entry_points_are_overridden_is_called_through_them(backend) -> None:
    session = Session(config.load(PAPER, [f"backend={backend}"]))
    assert not session.fused
    for _ in range(3):
        session.step()
    assert session.hsi.backend.calls == session.to.backend.calls == 3
