"""The backends' lifecycle (teleop_rt.hal.base, after ros2_control's hardware components):
unconfigured -> configure -> inactive -> activate -> active -> deactivate -> inactive ->
cleanup -> unconfigured, shutdown from any state to finalized; every other transition one
clear LifecycleError; the loop drives the transitions; a CAN robot through the emulator is
NMT operational but disabled once configured, enabled once active, disabled and NMT
pre-operational once deactivated."""

from __future__ import annotations

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.hal import base
from teleop_rt.hal.base import Backend, LifecycleError
from teleop_rt.hal.sim import SimBackend
from teleop_rt.hal.stopping import stop_all
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_can_backend import FAST, make_backend, make_cfg, run_ticks

PAPER = CONFIGS / "paper_experiment.yaml"
UNCONFIGURED, INACTIVE, ACTIVE = base.UNCONFIGURED, base.INACTIVE, base.ACTIVE
DEACTIVATING, FINALIZED = base.DEACTIVATING, base.FINALIZED


def sim_backend() -> SimBackend:
    session = Session(config.load(PAPER, ["duration_s=0.01"]))
    backend = session.hsi.backend
    assert isinstance(backend, SimBackend)
    return backend


def test_the_transitions_and_their_states() -> None:
    backend = sim_backend()
    assert backend.lifecycle == UNCONFIGURED
    backend.configure()
    assert backend.lifecycle == INACTIVE
    backend.activate()
    assert backend.lifecycle == ACTIVE
    backend.write(np.array([1.5, -0.5]))
    assert backend.tau_motor.tolist() == [1.5, -0.5]  # held over the period
    backend.begin_deactivate()
    assert backend.lifecycle == DEACTIVATING
    assert backend.deactivate_step() and backend.lifecycle == INACTIVE
    assert backend.deactivate_step()  # and on every later call
    assert backend.tau_motor.tolist() == [0.0, 0.0]  # deactivated: zero torque
    backend.activate()  # a simulated robot may be activated again
    backend.deactivate()
    backend.cleanup()
    assert backend.lifecycle == UNCONFIGURED
    backend.configure()
    backend.activate()
    backend.write(np.array([2.0, 1.0]))
    backend.shutdown()  # from active: deactivated first
    assert backend.lifecycle == FINALIZED and backend.tau_motor.tolist() == [0.0, 0.0]
    backend.shutdown()  # the one transition that may be repeated


@pytest.mark.parametrize(
    ("path", "transition", "state"),
    [
        ([], "activate", UNCONFIGURED),
        ([], "begin_deactivate", UNCONFIGURED),
        ([], "cleanup", UNCONFIGURED),
        (["configure"], "configure", INACTIVE),
        (["configure"], "begin_deactivate", INACTIVE),
        (["configure", "activate"], "activate", ACTIVE),
        (["configure", "activate"], "configure", ACTIVE),
        (["configure", "activate"], "cleanup", ACTIVE),
        (["configure", "activate", "begin_deactivate"], "activate", DEACTIVATING),
        (["configure", "activate", "begin_deactivate"], "cleanup", DEACTIVATING),
        (["shutdown"], "configure", FINALIZED),
        (["configure", "shutdown"], "activate", FINALIZED),
    ],
)
def test_an_illegal_transition_is_one_clear_error(path, transition, state) -> None:
    backend = sim_backend()
    for step in path:
        getattr(backend, step)()
    name = transition.removeprefix("begin_")
    with pytest.raises(LifecycleError, match=rf"^SimBackend: cannot {name} in state {state} "):
        getattr(backend, transition)()
    assert backend.lifecycle == state  # unchanged


def test_a_deactivation_step_before_it_began_is_an_error() -> None:
    backend = sim_backend()
    backend.configure()
    backend.activate()
    with pytest.raises(LifecycleError, match="cannot deactivate_step in state active"):
        backend.deactivate_step()


class _Logged(SimBackend):
    """A simulated robot that logs its transitions (read / write untouched: the fused path)."""

    log: list[tuple[str, str]] = []

    def _note(self, what: str) -> None:
        self.log.append((self.side, what))

    def on_configure(self) -> None:
        self._note("configure")

    def on_activate(self) -> None:
        self._note("activate")

    def on_begin_deactivate(self) -> None:
        self._note("begin_deactivate")

    def on_deactivate_step(self) -> bool:
        self._note("deactivate_step")
        return super().on_deactivate_step()

    def on_cleanup(self) -> None:
        self._note("cleanup")


def logged_session(*overrides: str) -> Session:
    session = Session(config.load(PAPER, ["duration_s=0.05", *overrides]))
    for site in session.sites:
        site.backend.__class__ = _Logged  # (the same plant, its transitions logged)
        site.backend.side = site.name
    return session


def test_the_loop_drives_the_transitions_and_a_session_runs_again() -> None:
    _Logged.log.clear()
    session = logged_session()
    session.run()
    both = ["hsi", "to"]
    expected = [(s, t) for s in both for t in ("configure", "activate")]
    expected += [(s, "begin_deactivate") for s in both]
    expected += [(s, "deactivate_step") for s in both]
    expected += [(s, "cleanup") for s in both]
    assert _Logged.log == expected
    assert [s.backend.lifecycle for s in session.sites] == [UNCONFIGURED] * 2
    _Logged.log.clear()
    summary = session.run(ticks=10)  # unconfigured again: a simulated session may run again
    assert summary.ticks == 10 and _Logged.log == expected


def test_an_activation_that_fails_is_still_deactivated() -> None:
    """Active as soon as its hook starts: a half-done activation (drives enabled one by one)
    must be walked down like any."""

    class Failing(SimBackend):
        def on_activate(self) -> None:
            raise RuntimeError("drive 2 did not enable")

    backend = sim_backend()
    backend.__class__ = Failing
    backend.configure()
    with pytest.raises(RuntimeError, match="did not enable"):
        backend.activate()
    assert backend.lifecycle == ACTIVE
    backend.tau_motor[:] = 3.0
    assert stop_all([backend], 1e-5) == []
    assert backend.lifecycle == UNCONFIGURED and backend.tau_motor.tolist() == [0.0, 0.0]


def test_a_backend_that_never_configured_is_left_alone_by_the_stop() -> None:
    class Broken(Backend):
        def on_configure(self) -> None:
            raise OSError("no such bus")

        def read(self):
            return self.feedback

        def write(self, tau) -> None:
            raise AssertionError("never written")

        def on_begin_deactivate(self) -> None:
            raise AssertionError("nothing to deactivate")

    backend = Broken(2)
    with pytest.raises(OSError):
        backend.configure()
    assert backend.lifecycle == UNCONFIGURED
    assert stop_all([backend], 1e-5) == [] and backend.lifecycle == UNCONFIGURED


# --- CAN, through the drive emulator ----------------------------------------------------------
def test_can_states_as_the_drives_see_them() -> None:
    backend = make_backend(make_cfg())
    try:
        backend.configure()  # the start-up: NMT operational, nothing enabled yet
        assert backend.lifecycle == INACTIVE and backend.bus is not None
        for drive in backend.emulator.drives:
            assert drive.nmt_log[-1] == "start" and drive.state == "SWITCH ON DISABLED"
            assert all(torque == 0 for _, torque, _ in drive.commands)
        backend.activate()  # the sensor zeroed, the drives enabled
        assert backend.lifecycle == ACTIVE and backend.running
        assert [d.state for d in backend.emulator.drives] == ["OPERATION ENABLED"] * 2
        run_ticks(backend, 5, tau=0.5)
        backend.deactivate()  # quick stop, disable, NMT pre-operational, the bus closed
        assert backend.lifecycle == INACTIVE and backend.bus is None
        for drive in backend.emulator.drives:
            assert drive.state == "SWITCH ON DISABLED" and drive.nmt_log[-1] == "pre-op"
        with pytest.raises(LifecycleError, match=r"^CanBackend \(hsi\): cannot activate a "):
            backend.activate()  # a CAN robot runs once
        backend.cleanup()
        with pytest.raises(LifecycleError, match="cannot configure a second time"):
            backend.configure()
        assert backend.lifecycle == UNCONFIGURED
    finally:
        backend.shutdown()
    assert backend.lifecycle == FINALIZED


def test_a_can_start_up_that_fails_closes_its_bus_and_stays_unconfigured() -> None:
    from teleop_rt.errors import BackendError
    from teleop_rt.hal.can.emulator import emulated_bus

    backend = make_backend(make_cfg("can.hsi.drives.1.node_id=9", "can.boot_timeout_s=0.2"))
    backend.bus = emulated_bus(make_cfg(), "hsi")  # nodes 1 and 2 only
    with pytest.raises(BackendError, match="no boot-up"):
        backend.configure()
    assert backend.lifecycle == UNCONFIGURED and backend.bus is None


def test_a_can_session_ends_with_both_robots_unconfigured() -> None:
    session = Session(config.load(CONFIGS / "can_emulated.yaml", [*FAST, "duration_s=0.1"]))
    summary = session.run()
    assert summary.ticks == 100 and summary.stopped_early is None
    for site in session.sites:
        assert site.backend.lifecycle == UNCONFIGURED
        assert [d.nmt_log[-1] for d in site.backend.emulator.drives] == ["pre-op"] * 2
