"""The Backend interface (hardware side of the loop: ``read`` / ``write``). Backends are found
by name in ``teleop_rt.hal.registry``; the blocks they fill are in ``teleop_rt.hal.signals``.
This module imports no implementation, and knows no session: a one-process session's fast
path for two simulated plants is ``teleop_rt.lockstep_fused``.

A backend drives one robot. Per tick the session calls ``read()`` once, then ``write(tau)``
once; ``write`` must not block beyond what the hardware protocol needs, and a simulated backend
advances its plant by one period there (the command is held for the period, like a drive's
zero-order hold).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from teleop_rt.hal.signals import Feedback, WorldSnapshot

__all__ = ["Backend", "Feedback", "WorldSnapshot"]


class Backend(ABC):
    """One robot's hardware (real or simulated)."""

    def __init__(self, n: int, n_contacts: int = 0) -> None:
        self.n = n
        self.feedback = Feedback(n)
        self.world = WorldSnapshot(n_contacts)

    @abstractmethod
    def start(self) -> None:
        """Bring the hardware to a state where torque may be commanded."""

    @abstractmethod
    def read(self) -> Feedback:
        """Measure q, v and tau_ext into ``self.feedback`` and return it."""

    @abstractmethod
    def write(self, tau: np.ndarray) -> None:
        """Command the motor torques tau (N m per joint) for the coming period."""

    @abstractmethod
    def stop(self) -> None:
        """Leave the hardware safe: zero torque, drives disabled. Must be idempotent."""

    def begin_stop(self) -> None:
        """Start ``stop`` without blocking: ``stop_step`` then does one period of it per call,
        so ``teleop_rt.hal.stopping.stop_all`` steps every robot's stop together (no bus goes
        without its SYNC while another robot stops). Default: nothing to begin."""
        return

    def stop_step(self) -> bool:
        """One period of the stop begun by ``begin_stop``: True once stopped (and on every
        later call). Bounded: a backend is done within a number of calls it documents.
        Default: the whole ``stop()`` at once (a simulated robot needs no periods)."""
        self.stop()
        return True

    def notes(self) -> list[str]:
        """What the session summary should say of this backend once it is stopped (what went
        wrong while stopping, warnings that were not faults); none by default."""
        return []
