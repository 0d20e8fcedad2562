"""The Backend interface (hardware side of the loop: ``read`` / ``write``) and the fuse
capability. Backends are found by name in ``teleop_rt.hal.registry``; the blocks they fill are
in ``teleop_rt.hal.signals``. This module imports no implementation.

A backend drives one robot. Per tick the session calls ``read()`` once, then ``write(tau)``
once; ``write`` must not block beyond what the hardware protocol needs, and a simulated backend
advances its plant by one period there (the command is held for the period, like a drive's
zero-order hold).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from teleop_rt.flat import Block
from teleop_rt.hal.signals import Feedback, WorldSnapshot

__all__ = ["Backend", "Feedback", "FusedPlants", "WorldSnapshot"]


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

    def fuse(self, peer: Backend) -> FusedPlants | None:
        """A capability, not a duty: where this backend and the peer's (the HSI's first) can
        run inside a one-process session's compiled tick, the object that does it; None (the
        default) keeps the plain ``read`` / ``write`` path."""
        return None


class FusedPlants(ABC):
    """Two backends' periods run inside a lock-step session's tick kernels (a simulation's
    fast path, ``teleop_rt.hal.sim_fused``): the same arithmetic as both backends' ``read``
    and ``write``, in fewer calls. The session packs ``blocks`` after its own blocks
    (``teleop_rt.lockstep.SESSION_BLOCKS``) and calls ``bind``; then per tick ``before`` in
    place of both reads and the lock-step's first kernel, ``after`` in place of its second
    (and, without a finding, the writes' commands), and ``advance`` for the rest of the
    writes."""

    blocks: list[Block]

    @abstractmethod
    def bind(
        self, f: np.ndarray, i: np.ndarray, offsets: np.ndarray, port_n: int | None = None
    ) -> None:  # fmt: skip
        """The packed buffers and the session's offsets (all blocks), once packed; ``port_n``:
        the channel's size where it is not the joints' (a task-space channel)."""

    @abstractmethod
    def before(self) -> int:
        """Both reads and the lock-step's first half; the finding (0: none)."""

    @abstractmethod
    def after(self, rnea_h: np.ndarray, rnea_t: np.ndarray) -> int:
        """The lock-step's second half and, without a finding, both motor commands."""

    @abstractmethod
    def advance(self) -> None:
        """The rest of both writes: each plant's period."""
