"""Run each build of a tick once with every stage's calls traced (``teleop_rt.tick_stages``);
print, as JSON, per build the stages in the order they ran and whose they were, and per build
the conditions each site meets. Run with ``NUMBA_DISABLE_JIT=1``: the kernels are then Python
functions, and a stage's call inside a kernel is looked up (and traced) at call time.

    NUMBA_DISABLE_JIT=1 python tests/tick_trace.py [BUILD ...]
"""

from __future__ import annotations

import importlib
import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.com.channel import TwoPort, make_ports  # noqa: E402
from teleop_rt.com.link import InProcessLink  # noqa: E402
from teleop_rt.mapping import PLANE  # noqa: E402
from teleop_rt.session import Session  # noqa: E402
from teleop_rt.tick_stages import LINK, PAIR, PAIR_NAME, SITE_STAGES  # noqa: E402

CONFIGS = ROOT / "configs"
SIDES = {0: "hsi", 1: "to"}
BOX = "{lower_m: [-9, -9, -9], upper_m: [9, 9, 9]}"  # a workspace box the tools stay inside
BOXED = [f"safety.workspace.hsi={BOX}", f"safety.workspace.to={BOX}", "duration_s=0.01"]
PLANE_CFG = CONFIGS / "task_space" / "scara_ur5_plane.yaml"
JOINT_CFG = CONFIGS / "paper_experiment.yaml"


class Tracer:
    """Records the outermost traced call of each stage, with whose it was."""

    def __init__(self, owners: dict[str, list[np.ndarray]], whole: np.ndarray | None) -> None:
        self.steps: list[tuple[str, str]] = []
        self.depth = 0
        self.owners = owners  # per site, the float buffers of its blocks
        self.whole = whole  # the packed float buffer (an argument that is all of it: nobody's)

    def whose(self, args: tuple[Any, ...]) -> str:
        """The site owning the first float array argument that starts inside one of its blocks
        (the whole packed buffer skipped: it starts where the first block does)."""
        start = None if self.whole is None else self.whole.ctypes.data
        for a in args:
            if not (isinstance(a, np.ndarray) and a.dtype == np.float64) or a.size == 0:
                continue
            p = a.ctypes.data
            if p == start:
                continue
            for site, buffers in self.owners.items():
                if any(b.ctypes.data <= p < b.ctypes.data + b.nbytes for b in buffers):
                    return site
        return "?"

    def wrap(self, stage: str, runs: str, func: Callable[..., Any], site: str | None = None):
        def traced(*args: Any, **kwargs: Any) -> Any:
            if self.depth == 0:
                who = site or (PAIR_NAME if runs in (LINK, PAIR) else self.whose(args))
                self.steps.append((stage, who))
            self.depth += 1
            try:
                return func(*args, **kwargs)
            finally:
                self.depth -= 1

        return traced


@contextmanager
def traced_functions(tracer: Tracer) -> Iterator[None]:
    """Every "module:function" call of a stage, wherever a teleop_rt module (or pinocchio)
    holds it, replaced by its traced self; restored after."""
    undo: list[tuple[Any, str, Any]] = []
    for stage in SITE_STAGES:
        for call in stage.calls:
            if ":" not in call:
                continue
            module, name = call.split(":")
            func = getattr(importlib.import_module(module), name)
            traced = tracer.wrap(stage.name, stage.runs, func)
            holders = [m for k, m in list(sys.modules.items()) if k.startswith("teleop_rt")]
            if module == "pinocchio":
                holders = [pinocchio]
            for holder in holders:
                for attr, value in list(vars(holder).items()):
                    if value is func:
                        undo.append((holder, attr, value))
                        setattr(holder, attr, traced)
    try:
        yield
    finally:
        for holder, attr, value in reversed(undo):
            setattr(holder, attr, value)


def trace_methods(
    tracer: Tracer, sites: dict[str, Any], link: Any = None, backends: bool = True
) -> None:
    """The stages made by a method ("Class.method"), traced on the objects of this build
    (``backends``: False where the plants run inside the kernels)."""
    by_call = {c: s for s in SITE_STAGES for c in s.calls if ":" not in c}
    for name, site in sites.items():
        calls = [("RobotGuard.check_workspace", site.guard)]
        if backends:
            calls += [("Backend.read", site.backend), ("Backend.write", site.backend)]
        for call, obj in calls:
            stage, method = by_call[call], call.split(".")[1]
            setattr(obj, method, tracer.wrap(stage.name, stage.runs, getattr(obj, method), name))
    if link is not None:
        for call in ("Link.send", "Link.receive", "Link.end_tick"):
            stage, method = by_call[call], call.split(".")[1]
            original = getattr(link, method)

            def per_side(side: int, *args: Any, _o=original, _s=stage) -> Any:
                return tracer.wrap(_s.name, _s.runs, _o, SIDES[side])(side, *args)

            setattr(link, method, per_side)


def meets(sites: dict[str, Any]) -> dict[str, list[str]]:
    """The conditions (``tick_stages.CONDITIONS``) each site meets."""
    out: dict[str, list[str]] = {}
    for name, site in sites.items():
        got = []
        if site.guard.workspace is not None and site.guard.enabled:
            got.append("workspace_box")
        if site.mapping.space == PLANE:
            got.append("task_space")
        out[name] = got
    return out


def session_owners(session: Session) -> dict[str, list[np.ndarray]]:
    return {"hsi": [b.f for b in session.hsi.blocks], "to": [b.f for b in session.to.blocks]}


def run_session(
    cfg: config.SessionConfig, fuse: bool, ticks: int = 3, python_link: bool = False
) -> dict:
    """``python_link``: the session steps its in-process link through the ``Link`` methods,
    as it steps an impaired link (whose wire kernels need numba: the CRC's integer types)."""
    session = Session(cfg, fuse=fuse)
    if python_link:
        session.compiled_link = False
    sites = {"hsi": session.hsi, "to": session.to}
    tracer = Tracer(session_owners(session), session.packed.f)
    for _ in range(ticks - 1):
        session.step()
    trace_methods(tracer, sites, None if session.compiled_link else session.link,
                  backends=not session.fused)  # fmt: skip
    with traced_functions(tracer):
        rebind_maps(session)
        session.step()
    return {"steps": tracer.steps, "meets": meets(sites), "fused": session.fused}


def rebind_maps(session: Session) -> None:
    """The task-space maps bound again (``Site._bound_map``), now that ``map_tool`` is traced:
    they are bound once, to the function as it was (a fused pair's own are not traced)."""
    for site in session.sites:
        if site._kin is not None:
            site._kin = site._bound_map()
    session._maps = [site._kin for site in session.sites if site._kin is not None]
    if session._pair_plants is None or session._maps_fused:
        session._maps_fused = session._maps


def run_alone(cfg: config.SessionConfig, ticks: int = 3) -> dict:
    """Both sites on buffers of their own over a Python-stepped in-process link."""
    session = Session(cfg, fuse=False)
    sites = {"hsi": session.hsi, "to": session.to}
    link = InProcessLink(session.n, cfg.delay_ticks)
    owners = {}
    for name, site in sites.items():
        site.bind(type(session.packed)(site.blocks))
        owners[name] = [b.f for b in site.blocks]
    tracer = Tracer(owners, None)

    def tick() -> None:
        for phase in ("sense", "update"):
            for site in sites.values():
                getattr(site, phase)(link)

    for _ in range(ticks - 1):
        tick()
    trace_methods(tracer, sites, link)
    wholes = {name: site.packed.f for name, site in sites.items()}
    with traced_functions(tracer):
        for site in sites.values():  # (bound to ``map_tool`` before it was traced)
            site._kin = site._bound_map()
        for phase in ("sense", "update"):
            for name, site in sites.items():
                tracer.whole = wholes[name]
                getattr(site, phase)(link)
    return {"steps": tracer.steps, "meets": meets(sites)}


def run_two_port(ticks: int = 3) -> dict:
    n, dt = 2, 1e-3
    port_h, port_t = make_ports("wave", [5.0, 5.0], 2, dt, None)
    tp = TwoPort(n, port_h, port_t, 2, dt)
    owners = {"hsi": [port_h.f, tp.tx_h.f, tp.rx_h.f], "to": [port_t.f, tp.tx_t.f, tp.rx_t.f]}
    tracer = Tracer(owners, tp.packed.f)
    for _ in range(ticks - 1):
        tp.step([0.1, 0.2], [1.0, 2.0])
    with traced_functions(tracer):
        tp.step([0.1, 0.2], [1.0, 2.0])
    return {"steps": tracer.steps, "meets": {}}


def builds() -> dict[str, Callable[[], dict]]:
    plane = config.load(PLANE_CFG, BOXED)
    joint = config.load(JOINT_CFG, BOXED)
    delayed = config.load(JOINT_CFG, [*BOXED, "channel.delay_ms=5"])
    return {
        "alone": lambda: run_alone(plane),
        "lockstep": lambda: run_session(plane, fuse=False),
        "fused": lambda: run_session(joint, fuse=True),
        "phased": lambda: run_session(delayed, fuse=False, python_link=True),
        "two_port": run_two_port,
    }


def main(names: list[str]) -> int:
    table = builds()
    out = {name: table[name]() for name in (names or table)}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
