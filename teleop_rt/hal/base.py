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
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from teleop_rt.errors import ConfigError
from teleop_rt.flat import Block, Int, Vector, float_view

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig
    from teleop_rt.model import RobotModel


class Feedback(Block):
    """What a backend measures each tick (SI, joint space), preallocated: ``q``, ``v`` and
    ``tau_ext`` (the torque the outside world applies to the robot, see teleop_rt.control),
    float64 views a backend fills, and ``age_ticks``: ticks since the sensors last delivered
    (0: fresh this tick). The ``*_mv`` memoryviews of the same memory take element writes and
    buffer copies at a fraction of numpy's per-call cost."""

    q = Vector("joint angles, rad")
    v = Vector("joint velocities, rad/s")
    tau_ext = Vector("torque the outside applies to the robot, N m")
    age_ticks = Int("ticks since the sensors last delivered (0: fresh)")

    def _bind(self) -> None:
        super()._bind()
        self.q_mv, self.v_mv, self.tau_mv = (
            float_view(x) for x in (self.q, self.v, self.tau_ext)
        )

    def copy_arrays(self, q: memoryview, v: memoryview) -> None:
        """q, v = q, v given as float64 memoryviews of n entries (a memcpy each)."""
        self.q_mv[:] = q
        self.v_mv[:] = v


# where a kernel finds the feedback's signals (vector k at k * n; age_ticks is int 0)
FB_Q, FB_V, FB_TAU_EXT = Feedback.q.k, Feedback.v.k, Feedback.tau_ext.k
FB_AGE_TICKS = Feedback.age_ticks.k


class WorldSnapshot(Block):
    """What a simulated world knows at the tick's read (zeros for real hardware): the operator's
    hand reference and force (HSI) or the environment force and contacts (TO: 1.0 in contact),
    for logging and replay. Vectors of 3 in the world frame, SI units."""

    reference = Vector("the operator's hand reference, m")
    reference_velocity = Vector("its velocity, m/s")
    force = Vector("operator force on the HSI tool, or environment force on the TO's, N")

    def __init__(self, n_contacts: int = 0) -> None:
        super().__init__(3, tail=n_contacts)

    def _bind_tail(self) -> None:
        self.contacts = self.f[self.tail_start :]
        # for a backend's element writes each tick (cheaper than numpy's)
        self.reference_mv, self.reference_velocity_mv, self.force_mv, self.contacts_mv = (
            float_view(x)
            for x in (self.reference, self.reference_velocity, self.force, self.contacts)
        )


# where a kernel finds the world snapshot's signals (vectors of 3, then the contacts)
W_REFERENCE, W_REFERENCE_VELOCITY, W_FORCE = (
    3 * x.k
    for x in (WorldSnapshot.reference, WorldSnapshot.reference_velocity, WorldSnapshot.force)
)
W_CONTACTS = 3 * len(WorldSnapshot.VECTORS)


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


# factory(config, side, controller model, operator=None): operator replaces the config's
# operator model on the HSI of a simulated backend (replay drives it from a log)
BackendFactory = Callable[..., Backend]
_REGISTRY: dict[str, BackendFactory] = {}


_Factory = TypeVar("_Factory", bound=BackendFactory)


def register_backend(name: str) -> Callable[[_Factory], _Factory]:
    """Decorator: make a factory ``(config, side, model) -> Backend`` available by name (the
    factory keeps its own type: a ``SimBackend`` factory still returns a ``SimBackend``)."""

    def deco(factory: _Factory) -> _Factory:
        _REGISTRY[name] = factory
        return factory

    return deco


def available_backends() -> list[str]:
    _load_builtin()
    return sorted({*_REGISTRY, *_entry_point_names()})


def create_backend(
    name: str, cfg: SessionConfig, side: str, model: RobotModel, operator: object = None
) -> Backend:
    """Build the backend ``name`` for side 'hsi' or 'to'; ConfigError for an unknown name."""
    _load_builtin()
    factory = _REGISTRY.get(name) or _from_entry_point(name)
    if factory is None:
        raise ConfigError(
            f"backend: unknown backend {name!r} (available: {', '.join(available_backends())})"
        )
    return factory(cfg, side, model, operator=operator)


ENTRY_POINT_GROUP = "teleop_rt.backends"


def _from_entry_point(name: str) -> BackendFactory | None:
    """A third-party backend, found by name as python-can finds its interfaces: a package
    declares ``[project.entry-points."teleop_rt.backends"] NAME = "module:factory"``, the
    factory taking ``(config, side, model, operator=None)``. Loaded only when asked for."""
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP, name=name):
        try:
            factory = ep.load()
        except Exception as err:  # its package is broken: say which, not a traceback
            raise ConfigError(
                f"backend: {name!r} is declared by {ep.value!r} but does not load "
                f"({type(err).__name__}: {err})"
            ) from None
        _REGISTRY[name] = factory
        return factory
    return None


def _entry_point_names() -> list[str]:
    from importlib.metadata import entry_points

    return [ep.name for ep in entry_points(group=ENTRY_POINT_GROUP)]


def _load_builtin() -> None:
    # importing registers them; kept lazy so the CAN stack is only imported when used
    from teleop_rt.hal import sim  # noqa: F401
    from teleop_rt.hal.can import backend  # noqa: F401  (python-can / canopen load on start)
