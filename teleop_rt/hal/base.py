"""The Backend interface (hardware side of the loop: ``read`` / ``write``). Backends are found
by name in ``teleop_rt.hal.registry``; the blocks they fill are in ``teleop_rt.hal.signals``.
This module imports no implementation, and knows no session: a one-process session's fast
path for two simulated plants is ``teleop_rt.lockstep_fused``.

A backend drives one robot. Per tick the session calls ``read()`` once, then ``write(tau)``
once; ``write`` must not block beyond what the hardware protocol needs, and a simulated backend
advances its plant by one period there (the command is held for the period, like a drive's
zero-order hold).

Around the ticks a backend has explicit lifecycle states, those of ros2_control's hardware
components (after ROS 2's managed nodes, design.ros2.org/articles/node_lifecycle.html):

    unconfigured --configure--> inactive --activate--> active
    active --deactivate (stepped: deactivating)--> inactive --cleanup--> unconfigured
    any but finalized --shutdown--> finalized

``configure`` does what needs no motor (a CAN robot: open its bus, the drives' start-up),
``activate`` makes torque commandable (the drives enabled), ``deactivate`` leaves the robot
safe (zero torque, drives disabled) one period per ``deactivate_step`` so that
``teleop_rt.hal.stopping.stop_all`` steps every robot's together, ``shutdown`` releases
everything (from ``active`` it deactivates first). The loop (``teleop_rt.runner``) drives
them; a backend implements the ``on_*`` hooks it needs. Any other transition raises
``LifecycleError`` (``shutdown`` alone may be repeated: a safety path may always call it).
``read`` / ``write`` do not check the state (a check per tick costs, and a session stepped by
hand, as tests and the analysis do, runs its simulated plants without a lifecycle).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from teleop_rt.hal.signals import Feedback, WorldSnapshot

__all__ = [
    "ACTIVE", "DEACTIVATING", "FINALIZED", "INACTIVE", "UNCONFIGURED", "Backend", "Feedback",
    "LifecycleError", "WorldSnapshot",
]  # fmt: skip


UNCONFIGURED, INACTIVE, ACTIVE, DEACTIVATING, FINALIZED = (
    "unconfigured", "inactive", "active", "deactivating", "finalized"
)  # fmt: skip
# each transition: the states it may start from
_FROM = {
    "configure": (UNCONFIGURED,),
    "activate": (INACTIVE,),
    "deactivate": (ACTIVE,),
    "cleanup": (INACTIVE,),
}


class LifecycleError(RuntimeError):
    """A lifecycle transition the backend's state does not allow (a bug in the caller)."""


class Backend(ABC):
    """One robot's hardware (real or simulated), in one lifecycle state (``lifecycle``)."""

    def __init__(self, n: int, n_contacts: int = 0) -> None:
        self.n = n
        self.feedback = Feedback(n)
        self.world = WorldSnapshot(n_contacts)
        self.lifecycle = UNCONFIGURED

    @abstractmethod
    def read(self) -> Feedback:
        """Measure q, v and tau_ext into ``self.feedback`` and return it."""

    @abstractmethod
    def write(self, tau: np.ndarray) -> None:
        """Command the motor torques tau (N m per joint) for the coming period."""

    # --- the lifecycle's transitions (the caller's side) ------------------------------------
    def configure(self) -> None:
        """unconfigured -> inactive. If ``on_configure`` raises, the backend stays unconfigured
        (``shutdown`` then releases what it opened)."""
        self._require("configure")
        self.on_configure()
        self.lifecycle = INACTIVE

    def activate(self) -> None:
        """inactive -> active. The state is active as soon as the hook starts: an activation
        that fails half-way may have enabled drives, so it must be deactivated like any (a
        hook that refuses before touching the hardware raises LifecycleError: inactive)."""
        self._require("activate")
        self.lifecycle = ACTIVE
        try:
            self.on_activate()
        except LifecycleError:
            self.lifecycle = INACTIVE
            raise

    def begin_deactivate(self) -> None:
        """active -> deactivating, without blocking: ``deactivate_step`` then does one period
        of it per call."""
        self._require("deactivate")
        self.lifecycle = DEACTIVATING
        self.on_begin_deactivate()

    def deactivate_step(self) -> bool:
        """One period of the deactivation: True once inactive (and on every later call).
        Bounded: a backend is done within a number of calls it documents."""
        if self.lifecycle == INACTIVE:
            return True
        if self.lifecycle != DEACTIVATING:
            raise self._illegal("deactivate_step", "begin_deactivate first")
        if not self.on_deactivate_step():
            return False
        self.lifecycle = INACTIVE
        return True

    def deactivate(self) -> None:
        """active -> inactive, the stepped deactivation run to its end here (paced by
        ``wait_period``)."""
        self.begin_deactivate()
        while True:
            self.wait_period()
            if self.deactivate_step():
                return

    def cleanup(self) -> None:
        """inactive -> unconfigured: release what ``configure`` took."""
        self._require("cleanup")
        self.on_cleanup()
        self.lifecycle = UNCONFIGURED

    def shutdown(self) -> None:
        """Any state -> finalized: from active the deactivation runs to its end first (from
        deactivating, whose steps ``stop_all`` gave up on, it does not); ``on_shutdown``
        runs whatever happens. A second call does nothing."""
        if self.lifecycle == FINALIZED:
            return
        try:
            if self.lifecycle == ACTIVE:
                self.deactivate()
        finally:
            self.lifecycle = FINALIZED
            self.on_shutdown()

    # --- the hooks (the backend's side): nothing by default ---------------------------------
    def on_configure(self) -> None:
        """What ``configure`` does."""
        return

    def on_activate(self) -> None:
        """Bring the hardware to a state where torque may be commanded."""
        return

    def on_begin_deactivate(self) -> None:
        """Begin leaving the hardware safe (zero torque, drives disabled), without blocking."""
        return

    def on_deactivate_step(self) -> bool:
        """One period of it: True once done. Default: done at once."""
        return True

    def wait_period(self) -> None:
        """Between two steps of a deactivation run by ``deactivate`` (a bus's SYNC period)."""
        return

    def on_cleanup(self) -> None:
        """What ``cleanup`` does."""
        return

    def on_shutdown(self) -> None:
        """Release everything (a bus, threads); must not raise for a half-done start-up."""
        return

    def _require(self, transition: str) -> None:
        if self.lifecycle not in _FROM[transition]:
            raise self._illegal(transition, f"it needs {' or '.join(_FROM[transition])}")

    def _illegal(self, transition: str, why: str) -> LifecycleError:
        return LifecycleError(
            f"{type(self).__name__}: cannot {transition} in state {self.lifecycle} ({why})"
        )

    def notes(self) -> list[str]:
        """What the session summary should say of this backend once it is stopped (what went
        wrong while stopping, warnings that were not faults); none by default."""
        return []
