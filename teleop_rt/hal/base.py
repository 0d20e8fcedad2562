"""The Backend interface (hardware side of the loop: ``read`` / ``write``) and a registry of
backends by name, in the spirit of python-can's ``can.Bus(interface=...)``.

A backend drives one robot. Per tick the session calls ``read()`` once, then ``write(tau)``
once; ``write`` must not block beyond what the hardware protocol needs, and a simulated backend
advances its plant by one period there (the command is held for the period, like a drive's
zero-order hold).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from teleop_rt.errors import ConfigError
from teleop_rt.scalar import shared_vector

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig
    from teleop_rt.model import RobotModel


class Feedback:
    """What a backend measures each tick (SI, joint space), preallocated.

    ``q_list``, ``v_list`` (lists, for the scalar path) and ``tau_ext`` (a list: the torque the
    outside world applies to the robot, see teleop_rt.control) are what a backend fills;
    ``sync_arrays()`` then copies q and v into the numpy arrays ``q``, ``v`` (Pinocchio's inputs).
    """

    __slots__ = ("q", "v", "q_list", "v_list", "tau_ext", "age_ticks", "_q_view", "_v_view")

    def __init__(self, n: int) -> None:
        self.age_ticks = 0  # ticks since the sensors last delivered (0: fresh this tick)
        self.q, self._q_view = shared_vector(n)
        self.v, self._v_view = shared_vector(n)
        self.q_list = [0.0] * n
        self.v_list = [0.0] * n
        self.tau_ext = [0.0] * n

    def copy_arrays(self, q: memoryview, v: memoryview) -> None:
        """q, v (numpy) = q, v given as float64 memoryviews (a memcpy each): for a backend
        whose state mirrors q_list, v_list in such views (see teleop_rt.scalar.shared_vector)."""
        self._q_view[:] = q
        self._v_view[:] = v

    def sync_arrays(self) -> None:
        """q, v (numpy) = q_list, v_list."""
        qv, vv = self._q_view, self._v_view
        for j, x in enumerate(self.q_list):
            qv[j] = x
        for j, x in enumerate(self.v_list):
            vv[j] = x


class WorldSnapshot:
    """What a simulated world knows at the tick's read (zeros for real hardware): the operator's
    hand reference and force (HSI) or the environment force and contacts (TO), for logging and
    replay. Vectors are 3-lists in the world frame, SI units."""

    __slots__ = ("reference", "reference_velocity", "force", "contacts")

    def __init__(self, n_contacts: int = 0) -> None:
        self.reference = [0.0, 0.0, 0.0]
        self.reference_velocity = [0.0, 0.0, 0.0]
        self.force = [0.0, 0.0, 0.0]
        self.contacts = [0.0] * n_contacts


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

    def notes(self) -> list[str]:
        """What the session summary should say of this backend once it is stopped (what went
        wrong while stopping, warnings that were not faults); none by default."""
        return []


# factory(config, side, controller model, operator=None): operator replaces the config's
# operator model on the HSI of a simulated backend (replay drives it from a log)
BackendFactory = Callable[..., Backend]
_REGISTRY: dict[str, BackendFactory] = {}


def register_backend(name: str) -> Callable[[BackendFactory], BackendFactory]:
    """Decorator: make a factory ``(config, side, model) -> Backend`` available by name."""

    def deco(factory: BackendFactory) -> BackendFactory:
        _REGISTRY[name] = factory
        return factory

    return deco


def available_backends() -> list[str]:
    _load_builtin()
    return sorted(_REGISTRY)


def create_backend(
    name: str, cfg: SessionConfig, side: str, model: RobotModel, operator: object = None
) -> Backend:
    """Build the backend ``name`` for side 'hsi' or 'to'; ConfigError for an unknown name."""
    _load_builtin()
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise ConfigError(
            f"backend: unknown backend {name!r} (available: {', '.join(available_backends())})"
        ) from None
    return factory(cfg, side, model, operator=operator)


def _load_builtin() -> None:
    # importing registers them; kept lazy so the CAN stack is only imported when used
    from teleop_rt.hal import sim  # noqa: F401
    from teleop_rt.hal.can import backend  # noqa: F401  (python-can / canopen load on start)
