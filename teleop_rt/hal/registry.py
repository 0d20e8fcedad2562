"""Backends by name, in the spirit of python-can's ``can.Bus(interface=...)``: the built-in ones
are a table of ``"module:factory"`` names (as python-can's ``can.interfaces.BACKENDS``),
imported only when one is asked for, so that neither this table nor the interface imports an
implementation (the CAN stack loads only for a CAN robot). Third-party backends are found the
same way through the ``teleop_rt.backends`` entry-point group; tests and tools may register a
factory at run time (``register_backend``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

from teleop_rt.errors import ConfigError

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig
    from teleop_rt.hal.base import Backend
    from teleop_rt.model import RobotModel

# factory(config, side, controller model, operator=None): operator replaces the config's
# operator model on the HSI of a simulated backend (replay drives it from a log)
BackendFactory = Callable[..., "Backend"]

BACKENDS: dict[str, str] = {
    "sim": "teleop_rt.hal.sim:make_sim",
    "can": "teleop_rt.hal.can.backend:make_can",
}
ENTRY_POINT_GROUP = "teleop_rt.backends"

_REGISTRY: dict[str, BackendFactory] = {}  # registered at run time, and those resolved once
_Factory = TypeVar("_Factory", bound=BackendFactory)


def register_backend(name: str) -> Callable[[_Factory], _Factory]:
    """Decorator: make a factory ``(config, side, model) -> Backend`` available by name (the
    factory keeps its own type: a ``SimBackend`` factory still returns a ``SimBackend``)."""

    def deco(factory: _Factory) -> _Factory:
        _REGISTRY[name] = factory
        return factory

    return deco


def available_backends() -> list[str]:
    """Every name ``create_backend`` takes (nothing is imported to list them)."""
    return sorted({*BACKENDS, *_REGISTRY, *_entry_point_names()})


def create_backend(
    name: str, cfg: SessionConfig, side: str, model: RobotModel, operator: object = None
) -> Backend:
    """Build the backend ``name`` for side 'hsi' or 'to'; ConfigError for an unknown name."""
    factory = _REGISTRY.get(name) or _resolve(name)
    if factory is None:
        raise ConfigError(
            f"backend: unknown backend {name!r} (available: {', '.join(available_backends())})"
        )
    return factory(cfg, side, model, operator=operator)


def _resolve(name: str) -> BackendFactory | None:
    """The factory of a built-in or an entry point's backend, imported now (and kept); a
    package that does not load is one line naming it, not a traceback."""
    from importlib.metadata import EntryPoint, entry_points

    if name in BACKENDS:
        declared = [EntryPoint(name, BACKENDS[name], ENTRY_POINT_GROUP)]
    else:  # a package declares [project.entry-points."teleop_rt.backends"] NAME = "mod:factory"
        declared = list(entry_points(group=ENTRY_POINT_GROUP, name=name))
    for ep in declared:
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
