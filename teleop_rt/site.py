"""A site: one robot's complete 1 kHz control loop (Fig 1's operator site or remote site).

A site owns its robot's backend and Pinocchio model, its controller (C1 on the HSI, C2 on the
TO), computed torque, safety guard, its port of the channel with the packets it sends and
receives, and its own signals. It knows the other site only through packets. ``HsiSite`` and
``ToSite`` differ in their port's side and their controller's error (``teleop_rt.site_tick``).

A site runs alone (``sense`` and ``update``, on buffers of its own, against any ``Link``), or
as half of a one-process session, which packs both sites and steps them in lock-step
(``teleop_rt.session``, ``teleop_rt.lockstep``); the arithmetic is the same compiled kernels.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from teleop_rt.com.channel import make_port
from teleop_rt.com.link import Link
from teleop_rt.com.port import HSI, TO, Packet, Port
from teleop_rt.config import SessionConfig, per_joint
from teleop_rt.control import ComputedTorque, Pid
from teleop_rt.errors import SafetyStop
from teleop_rt.flat import Block, Packed
from teleop_rt.hal.base import Backend, create_backend
from teleop_rt.model import RobotModel
from teleop_rt.safety import RobotGuard
from teleop_rt.site_tick import (
    SITE_ORDER,
    SiteSignals,
    site_after_models,
    site_before_models,
    site_sense,
)

if TYPE_CHECKING:
    from teleop_rt.world import Load

SIDES = {"hsi": HSI, "to": TO}
REST_SPEED_RAD_S = 1e-3  # a robot slower than this on every joint is at rest


class SensorsUnusable(Exception):
    """A robot's sensors cannot be trusted while stopping: zero torque at once."""


class Site:
    """One robot's loop; ``name`` is 'hsi' or 'to'."""

    name = ""

    def __init__(
        self, cfg: SessionConfig, backend_name: str | None = None, operator: Load | None = None
    ) -> None:
        """``backend_name`` replaces the config's backend for this robot; ``operator`` the
        config's operator model (HSI only: replay drives it from a log)."""
        name = self.name
        spec = getattr(cfg, name)
        self.cfg = cfg
        model = RobotModel.from_spec(spec.robot, name, cfg.plant.coulomb_smoothing_rad_s)
        n = model.nv
        self.virtual_mass = per_joint(spec.virtual_mass, n, f"{name}.virtual_mass")
        self.backend_name = backend_name or cfg.backend_for(name)
        self._assemble(
            model,
            create_backend(self.backend_name, cfg, name, model, operator),
            Pid(spec.controller, n, cfg.dt, f"{name}.controller"),
            ComputedTorque(model, self.virtual_mass, spec.compensate_friction),
            RobotGuard(cfg.safety, model, name, cfg.dt),
            port_for(cfg, n, SIDES[name]),
            cfg.dt,
        )
        self.stop_damping = cfg.safety.stop_damping_nm_s_per_rad

    @classmethod
    def from_parts(
        cls, model: RobotModel, backend: Backend, controller: Pid,
        computed_torque: ComputedTorque, guard: RobotGuard, port: Port, dt: float,
    ) -> Site:  # fmt: skip
        """A site of given parts (the analysis's open chain builds its own from parameters)."""
        site = cls.__new__(cls)
        site._assemble(model, backend, controller, computed_torque, guard, port, dt)
        return site

    def _assemble(
        self, model: RobotModel, backend: Backend, controller: Pid,
        computed_torque: ComputedTorque, guard: RobotGuard, port: Port, dt: float,
    ) -> None:  # fmt: skip
        self.side, self.dt = SIDES[self.name], dt
        self.stop_damping = 0.5  # N m s/rad (safety.stop_damping_nm_s_per_rad)
        self.model, self.n = model, model.nv
        self.controller, self.computed_torque, self.guard = controller, computed_torque, guard
        self.backend = backend
        self.feedback = backend.feedback
        self.world = backend.world
        self.signals = SiteSignals(self.n, self.side)
        if port.side != self.side:
            raise ValueError(f"the {self.name} site needs the {self.name}'s port")
        self.port = port
        self.tx, self.rx = Packet(self.n), Packet(self.n)
        self.tick = 0
        self.blocks: list[Block] = [getattr(self, attr) for attr in SITE_ORDER]
        self.bind(Packed(self.blocks))  # alone until a session packs it with the other site

    def bind(self, packed: Packed, first: int = 0) -> None:
        """Work on the site's blocks where they are now: blocks ``first`` on of ``packed``."""
        self.packed = packed
        end = first + len(SITE_ORDER)
        self._buffers = (packed.f, packed.i, packed.offsets[2 * first : 2 * end], self.n)
        self._pin = (self.model.model, self.model.data, self.feedback.q, self.feedback.v,
                     self.computed_torque.a_des)  # fmt: skip

    def warm_up(self) -> None:
        """Load (or, on a fresh install, compile) the site's kernels now, on scratch copies."""
        f, i, o, n = self._buffers
        f, i = f.copy(), i.copy()
        site_sense(f, i, o, n)
        site_before_models(f, i, o, n)
        site_after_models(f, i, o, n, np.zeros(n))

    @property
    def a_ref(self) -> np.ndarray:
        """Reference acceleration times the virtual mass (the controller's output)."""
        return self.controller.out

    @property
    def tau_cmd(self) -> np.ndarray:
        """Motor torque command (after the safety layer's saturation)."""
        return self.computed_torque.tau

    # --- a site alone: sense, exchange over a link, update ---------------------------------
    def sense(self, link: Link) -> None:
        """Read the backend, check the measurements, and hand the link this tick's packet
        with its port input (its wave follows in ``update``)."""
        f, i, o, n = self._buffers
        self.backend.read()
        code = site_sense(f, i, o, n)
        if code:
            raise self.stop_for(code)
        link.send(self.side, self.tx)

    def update(self, link: Link) -> None:
        """The packet due this tick, the port, the controller, computed torque, the checks,
        the write; then the link may carry this tick's (now complete) packet."""
        f, i, o, n = self._buffers
        link.receive(self.side, self.rx)
        site_before_models(f, i, o, n)
        link.end_tick(self.side)
        model, data, q, v, a = self._pin
        rnea = pin.rnea(model, data, q, v, a)
        self.check_workspace()
        code = site_after_models(f, i, o, n, rnea)
        if code:
            raise self.stop_for(code)
        self.backend.write(self.computed_torque.tau)
        self.tick += 1

    def check_workspace(self) -> None:
        """The tool frame inside its workspace box (Pinocchio's forward kinematics, outside the
        compiled checks; a non-finite angle is left to them, which name it)."""
        guard = self.guard
        if guard.workspace is not None and guard.enabled:
            q = self.feedback.q
            if np.isfinite(q).all():
                guard.check_workspace(self.tick, q)

    def rest_step(self) -> bool:
        """One tick of the staged stop after a safety finding: the HSI damped (gravity
        compensated, ``safety.stop_damping_nm_s_per_rad``), the TO brought to zero velocity
        under its own velocity loop; True once this robot is at rest. ``SensorsUnusable`` if
        its sensors cannot be trusted (the caller then commands zero torque)."""
        fb = self.backend.read()
        usable = (fb.q, fb.v, fb.tau_ext) if self.side == TO else (fb.q, fb.v)
        if fb.age_ticks or not all(np.isfinite(x).all() for x in usable):
            raise SensorsUnusable(self.name)
        if self.side == HSI:
            zeros = np.zeros(self.n)
            g = self.model.rnea(fb.q, zeros, zeros) - self.stop_damping * fb.v
        else:
            g = self.computed_torque.step(fb.q, fb.v, -self.controller.kp * fb.v, fb.tau_ext)
        self.guard.limits.clamp_effort(g)
        self.backend.write(g)
        return float(np.abs(fb.v).max()) < REST_SPEED_RAD_S

    def stop_for(self, code: int) -> SafetyStop:
        """The SafetyStop that words a finding of this site's compiled checks."""
        return self.guard.stop_for(self.tick, code, self.feedback.age_ticks)


def bring_to_rest(sites: list[Site], until: Site, wait: Callable[[], object], limit: int) -> str:
    """The staged stop after a safety finding, one tick at a time (``wait`` paces it: the
    clock's, in real time): every site's ``rest_step`` until ``until`` is at rest, at most
    ``limit`` ticks; what happened, for the summary's notes (zero torque follows, the backends'
    stop). Sensors that are not usable, or a further fault, end it at once."""
    name = until.name.upper()
    try:
        for k in range(limit):
            wait()
            resting = [site.rest_step() for site in sites]
            if resting[sites.index(until)]:
                return f"{name} at rest after {k + 1} ticks, then zero torque"
    except SensorsUnusable:
        return f"sensors unusable after {k} ticks: zero torque"
    except SafetyStop as exc:
        return f"a further fault while stopping ({exc}): zero torque"
    return f"{name} not at rest after {limit} ticks; zero torque"


class HsiSite(Site):
    """The operator's site: the HSI robot, C1 on tau_h - tau_c, the channel's HSI port."""

    name = "hsi"

    @property
    def tau_h(self) -> np.ndarray:
        """The operator's torque on the HSI, as measured this tick."""
        return self.signals.tau


class ToSite(Site):
    """The remote site: the TO robot, C2 on omega_t - v_t, the channel's TO port."""

    name = "to"

    @property
    def tau_e(self) -> np.ndarray:
        """The TO's torque on the environment this tick (-tau_ext of the TO)."""
        return self.signals.tau


def port_for(cfg: SessionConfig, n: int, side: int) -> Port:
    """Site ``side``'s port of the config's channel."""
    ch = cfg.channel
    b = per_joint(ch.wave_impedance, n, "channel.wave_impedance")
    return make_port(side, ch.mode, b, cfg.delay_ticks, cfg.dt, ch.wave_filter_hz,
                     ch.wave_reconstruction, ch.tdpa_drift_time_s)  # fmt: skip


def channel_figures(cfg: SessionConfig, ports: dict[str, Port]) -> dict:
    """The channel's kind and what its protection did at each port given (a summary's)."""
    ch = cfg.channel
    kind = {"mode": ch.mode, "playout": cfg.link.playout}
    if ch.mode == "wave":
        kind["reconstruction"] = ch.wave_reconstruction
    return {**kind, **{name: port.protection() for name, port in ports.items()}}
