"""A site: one robot's complete 1 kHz control loop (Fig 1's operator site or remote site).

A site owns its robot's backend and Pinocchio model, its controller (C1 on the HSI, C2 on the
TO), computed torque, safety guard, its port of the channel with the packets it sends and
receives, and its own signals. It knows the other site only through packets. ``HsiSite`` and
``ToSite`` differ in their port's side and their controller's error (``teleop_rt.site_tick``).

A site runs alone (``sense`` and ``update``, on buffers of its own, against any ``Link``), or
as half of a one-process session, which packs both sites and steps them in lock-step
(``teleop_rt.session``, ``teleop_rt.lockstep``); the arithmetic is the same compiled kernels,
and the order of both is ``teleop_rt.tick_stages``'s (``sense``: its sense phase, ``update``:
the rest).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from teleop_rt.com import codec
from teleop_rt.com.channel import make_port
from teleop_rt.com.link import Link
from teleop_rt.com.port import HSI, TO, Packet, Port
from teleop_rt.config import SafetySpec, SessionConfig, per_joint
from teleop_rt.control import ComputedTorque, Pid
from teleop_rt.errors import ConfigError, SafetyStop
from teleop_rt.flat import Block, Packed, bound_kernel, compiled_for
from teleop_rt.hal.base import Backend
from teleop_rt.hal.registry import create_backend
from teleop_rt.keys import AT_START as KEYS_AT_START
from teleop_rt.mapping import (
    JOINT,
    POSE,
    PRESENCE_LOST,
    Mapping,
    map_tool,
    mapping_for,
    port_size,
    start_orientation,
)
from teleop_rt.model import RobotModel
from teleop_rt.safety import RobotGuard
from teleop_rt.site_tick import (
    SITE_ORDER,
    SiteSignals,
    site_after_models,
    site_before_models,
    site_sense,
)
from teleop_rt.task_limits import TOOL_FORCE

if TYPE_CHECKING:
    from teleop_rt.world import Load

SIDES = {"hsi": HSI, "to": TO}
LWA = pin.LOCAL_WORLD_ALIGNED  # the task-space map's Jacobian: world axes, at the tool
# a task-space map's per-tick call: Pinocchio's frame Jacobian, its arguments, and the map
# that takes its result (``Site._bound_map``)
MapCall = tuple[Callable[..., np.ndarray], tuple, Callable[[np.ndarray], None]]
REST_SPEED_RAD_S = 1e-3  # a robot slower than this on every joint is at rest
STOP_GAIN_OF_DEADBEAT = 0.5  # the TO's stop gain at most half the deadbeat gain M_v / dt
STOP_DAMPING_DEFAULT = SafetySpec.model_fields["stop_damping_nm_s_per_rad"].default


def require_task_span(model: RobotModel, space: str, task: int, name: str) -> None:
    """ConfigError unless the tool Jacobian's rows the task takes (world-aligned, the first
    ``task`` of x, y, z, then the angular ones) can span the task: their rank at a generic
    configuration (a seeded random one: the rank anywhere else is at most that, and equal
    but on a set of measure zero), so a start pose at a singularity is not refused (the DLS
    takes it), while a robot that cannot span the task is."""
    pm = model.model
    rng = np.random.default_rng(0)
    q = pin.integrate(pm, pin.neutral(pm), rng.uniform(-1.0, 1.0, pm.nv))
    jac = pin.computeFrameJacobian(pm, model.model.createData(), q, model.ee_frame_id, LWA)
    rank = int(np.linalg.matrix_rank(jac[:task], tol=1e-9))
    if rank < task:
        axes = {2: "x, y", 3: "x, y, z", 6: "x, y, z and 3 rotations"}[task]
        raise ConfigError(
            f"channel.space: {space} couples {task} directions ({axes}) of the tool; the "
            f"{name}'s tool Jacobian ({model.nv} joints, frame {model.ee_frame}) spans at most "
            f"{rank}"
        )


def require_posture(
    model: RobotModel, posture: list[float] | None, space: str, task: int, gain: float = 0.0
) -> None:
    """ConfigError unless ``mapping.posture_rad`` (None: the first tick's q) fits the TO: one
    angle per joint, each within its joint limits, and joints to spare over the task; a
    posture gain (``mapping.posture_gain_per_s``) needs the spare joints too (without them the
    DLS's projector is its damping's leak, no null space)."""
    n = model.nv
    if posture is None and gain > 0 and n <= task:
        raise ConfigError(
            f"mapping.posture_gain_per_s: the TO's {n} joints have none to spare over the {task} "
            f"directions of channel.space: {space} (a posture needs a redundant TO; 0 turns "
            "it off)"
        )
    if posture is None:
        return
    if len(posture) != n:
        raise ConfigError(f"mapping.posture_rad: has {len(posture)} entries but the TO has {n} "
                          "joints")  # fmt: skip
    if n <= task:
        raise ConfigError(
            f"mapping.posture_rad: the TO's {n} joints have none to spare over the {task} "
            f"directions of channel.space: {space} (a posture needs a redundant TO)"
        )
    low, high = model.position_limits
    for j, angle in enumerate(posture):
        if not low[j] <= angle <= high[j]:
            raise ConfigError(
                f"mapping.posture_rad: {angle:g} rad for joint {j} ({model.joint_names[j]}) is "
                f"outside its limits [{low[j]:g}, {high[j]:g}] rad"
            )


# a gain within this fraction of the sampled limit: near the limit the loop's poles approach
# the unit circle (at 99 % of it a 6 s run of scara_ur5_plane.yaml rang into a safety stop)
TASK_GAIN_FRACTION = 0.5


def require_stable_task_gains(cfg: SessionConfig, n: int) -> None:
    """ConfigError for a posture or orientation gain at or above TASK_GAIN_FRACTION of the
    sampled loop's limit.

    Each adds k (target - x) to the TO's velocity reference, which its P velocity loop tracks
    with T2 = M2/c2: per direction the loop of teleop_rt.analysis.contact with K / b = k, so
    k < (4 T2 - 2 dt) / dt^2 (Jury), taken at the joint with the smallest T2. A gain beyond it
    ran into a safety stop at the first ticks; now it is refused before any."""
    from teleop_rt.analysis.contact import contact_stiffness_limit

    m2 = per_joint(cfg.to.virtual_mass, n, "to.virtual_mass")
    c2 = per_joint(cfg.to.controller.kp, n, "to.controller.kp")
    limits = [contact_stiffness_limit(1.0, m2[j], c2[j], cfg.dt) for j in range(n)]
    # a joint whose velocity loop is at or past its own limit (dt / T2 >= 2: 0 here) bounds no
    # gain: that is the loop's, not the correction's (contact_warnings says so in joint space)
    limits = [x if x > 0 else np.inf for x in limits]
    j = int(np.argmin(limits))
    gains = [("posture_gain_per_s", cfg.mapping.posture_gain_per_s)]
    if cfg.channel.space == "pose":
        gains.append(("orientation_gain_per_s", cfg.mapping.orientation_gain_per_s))
    for key, gain in gains:
        if gain > 0 and gain >= TASK_GAIN_FRACTION * limits[j]:
            raise ConfigError(
                f"mapping.{key} = {gain:g} 1/s is at or above {TASK_GAIN_FRACTION:.0%} of the "
                f"limit of the TO's sampled velocity loop, {limits[j]:.4g} 1/s at rate_hz = "
                f"{cfg.rate_hz} ((4 T2 - 2 dt) / dt^2, T2 = M2/c2 = {m2[j] / c2[j]:.3g} s at "
                f"joint {j}; see teleop_rt/analysis/contact.py): the correction would ring or "
                "be unstable"
            )


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
        if name == "to" and cfg.channel.space != "joint":  # (before the map takes it)
            m = cfg.mapping
            require_posture(model, m.posture_rad, cfg.channel.space,
                            port_size(cfg.channel.space, n), m.posture_gain_per_s)  # fmt: skip
            require_stable_task_gains(cfg, n)
        self.virtual_mass = per_joint(spec.virtual_mass, n, f"{name}.virtual_mass")
        self.backend_name = backend_name or cfg.backend_for(name)
        self._assemble(
            model,
            create_backend(self.backend_name, cfg, name, model, operator),
            Pid(spec.controller, n, cfg.dt, f"{name}.controller"),
            ComputedTorque(model, self.virtual_mass, spec.compensate_friction),
            RobotGuard(cfg.safety, model, name, cfg.dt),
            port_for(cfg, port_size(cfg.channel.space, n), SIDES[name]),
            cfg.dt,
            mapping_for(cfg, n, SIDES[name]),
        )
        self.stop_damping = cfg.safety.stop_damping_nm_s_per_rad
        if cfg.mapping.keys and name == "hsi":  # (until a key says otherwise: teleop_rt.keys)
            self.feedback.inputs = KEYS_AT_START
        if self.mapping.space != JOINT:
            require_task_span(model, cfg.channel.space, self.m, name)
        self.map_kinematics(np.array(spec.robot.q0_rad or [0.0] * n, dtype=float))
        if self.mapping.space == POSE:
            start_orientation(self.mapping.f, self.mapping.i)

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
        mapping: Mapping | None = None,
    ) -> None:  # fmt: skip
        """``mapping``: the map between the robot and its port (None: the identity)."""
        self.side, self.dt = SIDES[self.name], dt
        self.mapping = mapping or Mapping(model.nv, SIDES[self.name], dt)
        self.stop_damping = STOP_DAMPING_DEFAULT
        self.model, self.n = model, model.nv
        self.m = port.n  # the port's size: the joints, or the task's dimension
        self.controller, self.computed_torque, self.guard = controller, computed_torque, guard
        self.backend = backend
        self.feedback = backend.feedback
        self.world = backend.world
        self.signals = SiteSignals(self.n, self.side)
        if port.side != self.side:
            raise ValueError(f"the {self.name} site needs the {self.name}'s port")
        self.port = port
        self.tx, self.rx = Packet(self.m), Packet(self.m)
        # the staged stop's buffers, and the TO's stop gain: its controller's kp, at most
        # STOP_GAIN_OF_DEADBEAT of the sampled velocity loop's deadbeat gain M_v / dt, so that
        # the stop converges whatever kp is (the loop v[k+1] = (1 - k dt / M_v) v[k] is stable
        # for k dt / M_v < 2; a kp beyond it may be the very fault that stopped the run)
        self._zeros, self._stop_tau, self._stop_a_ref, self._stop_v, self._stop_a = (
            np.zeros(self.n) for _ in range(5)
        )
        self.found_fault = False  # this site's own guard found what stopped the run
        self.begin_rest()
        deadbeat = 1.0 / (computed_torque.inv_mass * dt)
        self._stop_gain = np.minimum(np.nan_to_num(controller.kp, nan=0.0),
                                     STOP_GAIN_OF_DEADBEAT * deadbeat)  # fmt: skip
        self.tick = 0
        self.blocks: list[Block] = [getattr(self, attr) for attr in SITE_ORDER]
        self.bind(Packed(self.blocks))  # alone until a session packs it with the other site

    def map_kinematics(self, q: np.ndarray | None = None) -> None:
        """A task-space map's Jacobian, its inverse and the tool's place at the measured q (or
        ``q``), for the next tick (after this tick's torques: one Pinocchio call)."""
        kin = self._kin
        if kin is None:
            return
        jacobian, args, mapped = kin
        if q is not None:
            model, data, _, frame, frames = args
            args = (model, data, q, frame, frames)
        # (the pose: the tool's rotation too, which oMf holds after the Jacobian's call)
        mapped(jacobian(*args))

    def bind(self, packed: Packed, first: int = 0) -> None:
        """Work on the site's blocks where they are now: blocks ``first`` on of ``packed``."""
        self.packed = packed
        end = first + len(SITE_ORDER)
        self._buffers = b = (packed.f, packed.i, packed.offsets[2 * first : 2 * end], self.m)
        # the tick's kernels bound to the buffers (no dispatcher typing 3-4 arrays a call, three
        # calls a tick); the RNEA's torque, Pinocchio's, is a float64 vector like np.zeros
        self._kernels = (
            bound_kernel(site_sense, b), bound_kernel(site_before_models, b),
            bound_kernel(site_after_models, b, np.zeros(self.n)),
        )  # fmt: skip
        self._pin = (self.model.model, self.model.data, self.feedback.q, self.feedback.v,
                     self.computed_torque.a_des)  # fmt: skip
        self._kin = None if self.mapping.space == JOINT else self._bound_map()

    def _bound_map(self) -> MapCall:
        """A task-space map's per-tick call, looked up once: Pinocchio's frame Jacobian, its
        arguments, and ``map_tool``'s compiled entry point with every argument but the
        Jacobian bound (``flat.compiled_for``: no dispatcher typing five arrays a tick)."""
        m, mapping = self.model, self.mapping
        frame = m.ee_frame_id
        x, rotation = m._ee_translation, m.data.oMf[frame].rotation  # (views of data.oMf)
        bound = (mapping.f, mapping.i, x, rotation)
        example = np.zeros((6, m.nv))  # (the Jacobian's type: Pinocchio's (6, n), C order)
        mapped = partial(compiled_for(map_tool, *bound, example), *bound)
        return pin.computeFrameJacobian, (m.model, m.data, self.feedback.q, frame, LWA), mapped

    def warm_up(self) -> None:
        """Load (or, on a fresh install, compile) the site's kernels now, on scratch copies."""
        f, i, o, n = self._buffers
        f, i = f.copy(), i.copy()
        site_sense(f, i, o, n)
        site_before_models(f, i, o, n)
        site_after_models(f, i, o, n, np.zeros(self.n))

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
        self.backend.read()
        code = self._kernels[0]()
        if code:
            raise self.stop_for(code)
        link.send(self.side, self.tx)

    def update(self, link: Link) -> None:
        """The packet due this tick, the port, the controller, computed torque, the checks,
        the write; then the link may carry this tick's (now complete) packet."""
        _, before, after = self._kernels
        link.receive(self.side, self.rx)
        before()
        link.end_tick(self.side)
        model, data, q, v, a = self._pin
        rnea = pin.rnea(model, data, q, v, a)
        self.check_workspace()
        code = after(rnea)
        if code:
            raise self.stop_for(code)
        self.backend.write(self.computed_torque.tau)
        self.map_kinematics()
        self.tick += 1

    def check_workspace(self) -> None:
        """The tool frame inside its workspace box (Pinocchio's forward kinematics, outside the
        compiled checks; a non-finite angle is left to them, which name it)."""
        guard = self.guard
        if guard.workspace is not None and guard.enabled:
            q = self.feedback.q
            if np.isfinite(q).all():
                try:
                    guard.check_workspace(self.tick, q)
                except SafetyStop:
                    self.found_fault = True
                    raise

    def begin_rest(self) -> None:
        """Before the staged stop's first tick. The TO may feed its torque sensor forward (and
        so hold still in a contact) only if its own guard did not find the fault: a fault of
        this robot may be that very sensor (a bias trips the tracking or saturation checks
        first), and a biased τ_ext fed forward would drive it at its effort limits."""
        self._force_trusted = self.side == TO and not self.found_fault
        self._stop_ticks = self._stop_ticks_trusted = 0

    def rest_step(self) -> bool:
        """One tick of the staged stop after a safety finding: the HSI damped (gravity
        compensated, ``safety.stop_damping_nm_s_per_rad``), the TO brought to zero velocity
        under a velocity loop of its own; True once this robot is at rest.

        The stop trusts as little as it can. It acts on angles and speeds only once they pass
        the guard's measurement checks (fresh, finite, speeds within the plausibility bounds).
        The TO's torque sensor is fed forward only while trusted (see ``begin_rest``), within
        its plausibility bound, and while the TO follows the acceleration commanded the tick
        before (eq 3 / 13 again: a wrong τ_ext shows as an acceleration off by M⁻¹ times its
        error); once it fails it is dropped for the rest of the stop, and the TO's virtual mass
        is then damped against whatever touches it. The command passes the checks every write
        passes: finite, then clamped to the URDF effort limits. ``SensorsUnusable`` otherwise:
        the caller then commands zero torque."""
        fb = self.backend.read()
        guard = self.guard
        if fb.age_ticks or not guard.motion_usable(fb.q, fb.v):
            raise SensorsUnusable(self.name)
        tau = self._stop_tau
        if self.side == HSI:
            tau[:] = self.model.rnea(fb.q, self._zeros, self._zeros)
            tau -= self.stop_damping * fb.v
        else:  # M M_v^-1 (-k v) + n(q, v) - τ_ext (when trusted)
            if self._force_trusted and (
                not guard.force_plausible(fb.tau_ext)
                or (self._stop_ticks and not guard.follows(fb.v, self._stop_v, self._stop_a))
            ):
                self._force_trusted = False
                self._stop_ticks_trusted = self._stop_ticks
            tau_ext = fb.tau_ext if self._force_trusted else self._zeros
            np.multiply(self._stop_gain, fb.v, out=self._stop_a_ref)
            np.negative(self._stop_a_ref, out=self._stop_a_ref)
            tau[:] = self.computed_torque.step(fb.q, fb.v, self._stop_a_ref, tau_ext)
            self._stop_v[:] = fb.v
            self._stop_a[:] = self.computed_torque.a_des
        self._stop_ticks += 1
        if not guard.clamp_command(tau):
            raise SensorsUnusable(self.name)
        self.backend.write(tau)
        return float(np.abs(fb.v).max()) < REST_SPEED_RAD_S

    def write_zero_torque(self) -> None:
        """Command zero torque (a staged stop that cannot trust this robot's sensors)."""
        self._stop_tau[:] = 0.0
        self.backend.write(self._stop_tau)

    def zero_torque_period(self) -> str | None:
        """A period of the staged stop for a robot on zero torque: its backend still reads
        (a CAN bus gets its SYNC: the drives watch it by the wall clock and act on the last
        command until it comes) and is commanded zero torque. What the read measures is not
        used, and a fault it finds is returned, not raised: this robot is already on zero
        torque, and the others' stop goes on."""
        fault = None
        try:
            self.backend.read()
        except SafetyStop as exc:
            fault = str(exc)
        self.write_zero_torque()
        return fault

    def stop_note(self) -> str:
        """What the staged stop did without the TO's torque sensor ('' when nothing)."""
        if self.side != TO or self._force_trusted:
            return ""
        if self.found_fault:
            return "the TO stopped without its torque sensor (its own fault)"
        ticks = self._stop_ticks_trusted
        return f"the TO's torque sensor disagreed with its motion after {ticks} ticks; dropped"

    def stop_for(self, code: int) -> SafetyStop:
        """The SafetyStop that words a finding of this site's compiled checks."""
        self.found_fault = True
        if code == TOOL_FORCE:
            m = self.mapping
            return SafetyStop(f"tick {self.tick}: {self.name} tool force "
                              f"{m.peak_tool_force:.4g} N above {m.force_limit:g} N "
                              "(safety.tool.force_limit_n)")  # fmt: skip
        if code == PRESENCE_LOST:
            timeout = self.mapping.timeout_ticks * self.dt
            return SafetyStop(f"tick {self.tick}: {self.name}: the operator has been away for "
                              f"more than {timeout:g} s (mapping.presence_timeout_s)")  # fmt: skip
        return self.guard.stop_for(self.tick, code, self.feedback.age_ticks)


def bring_to_rest(sites: list[Site], until: Site, wait: Callable[[], object], limit: int) -> str:
    """The staged stop after a safety finding, one tick at a time (``wait`` paces it: the
    clock's, in real time): every site's ``rest_step`` until ``until`` is at rest, at most
    ``limit`` ticks; what happened, for the summary's notes (zero torque follows, the backends'
    stop). A site whose sensors become unusable is commanded zero torque from then on while
    the others go on stopping, its backend still read every period (a CAN bus keeps its SYNC,
    whatever the other robot does); a further fault of a robot still stopping ends it at
    once."""
    for site in sites:
        site.begin_rest()
    stopping = list(sites)
    faulted: list[Site] = []  # on zero torque, and a further fault said
    said: list[str] = []
    ending = f"{until.name.upper()} not at rest after {limit} ticks; zero torque"
    try:
        for k in range(limit):
            wait()
            resting = False
            for site in sites:
                if site not in stopping:
                    fault = site.zero_torque_period()
                    if fault is not None and site not in faulted:
                        faulted.append(site)
                        said.append(f"{site.name.upper()} on zero torque: {fault}")
                    continue
                try:
                    at_rest = site.rest_step()
                except SensorsUnusable:
                    stopping.remove(site)
                    site.write_zero_torque()  # its read this period was rest_step's
                    said.append(f"{site.name.upper()}'s sensors unusable after {k} ticks: "
                                "zero torque from then on")  # fmt: skip
                    continue
                resting = resting or (site is until and at_rest)
            if resting:
                ending = f"{until.name.upper()} at rest after {k + 1} ticks, then zero torque"
                break
            if until not in stopping:
                ending = "zero torque"
                break
    except SafetyStop as exc:
        ending = f"a further fault while stopping ({exc}): zero torque"
    said += [note for site in sites if (note := site.stop_note())]
    return "; ".join([*said, ending])


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
    port = make_port(side, ch.mode, b, cfg.delay_ticks, cfg.dt, ch.wave_filter_hz,
                     ch.wave_reconstruction, ch.tdpa_drift_time_s,
                     ch.wave_drift_time_s, ch.wave_skip_time_s,
                     ch.wave_impedance_schedule)  # fmt: skip
    if ch.codec != "none":
        db, own = ch.deadband, "hsi" if side == HSI else "to"
        of_hsi, of_to = codec.predictions(ch.mode, db.prediction_hsi, db.prediction_to)
        mine, peers = (of_hsi, of_to) if side == HSI else (of_to, of_hsi)
        codec.configure(port, getattr(db, f"weber_{own}"), getattr(db, f"floor_{own}"),
                        db.min_interval_ticks, db.max_interval_ticks,
                        db.velocity_gain_s_per_rad, mine, peers, db.exchange_j,
                        db.exchange_weber, db.exchange_min_ticks)  # fmt: skip
    return port


def channel_figures(cfg: SessionConfig, ports: dict[str, Port]) -> dict:
    """The channel's kind and what its protection did at each port given (a summary's)."""
    ch = cfg.channel
    kind: dict[str, str] = {"mode": ch.mode, "playout": cfg.link.playout}
    if ch.mode == "wave":
        kind["reconstruction"] = ch.wave_reconstruction
    out = {**kind, **{name: port.protection() for name, port in ports.items()}}
    if ch.codec != "none":  # what each site's codec sent, and held of its peer's
        out["codec"] = {"kind": ch.codec, **{name: codec.figures(port)
                                             for name, port in ports.items()}}  # fmt: skip
    return out
