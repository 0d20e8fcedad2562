"""Simulated backend: a robot's full nonlinear rigid-body dynamics (Pinocchio ABA, Coriolis,
gravity, joint friction) with its operator or environment loads, integrated over one period
per ``write`` with a configurable integrator and number of sub-steps.

The plant owns its own ``RobotModel`` (its own Pinocchio Data), separate from the controller's:
it stands for the real robot. Sensors are ideal unless noise is configured (seeded, so fast mode
stays deterministic).

The plant's state and its loads are flat blocks (``teleop_rt.flat``, ``teleop_rt.world``) packed
into one pair of buffers; the arithmetic between Pinocchio's calls is compiled. The common case
(semi-implicit Euler, one sub-step, no faults) is a ``write`` of three compiled calls around ABA
and the tool Jacobian, and a ``read`` of one; sub-steps, RK4 and faults run the same compiled
pieces from a Python loop. Two simulated plants in the common case (``compiled_common_case``)
can run inside a one-process session's compiled tick: the session (``teleop_rt.lockstep_fused``)
packs their blocks with its own and calls these kernels (``SimBackend.rebind``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pinocchio as pin

from teleop_rt.config import FaultSpec, SessionConfig
from teleop_rt.errors import ConfigError
from teleop_rt.flat import Block, Int, Packed, Scalar, Vector, as_floats, bound_kernel, jit
from teleop_rt.hal.base import Backend
from teleop_rt.hal.signals import Feedback, WorldSnapshot
from teleop_rt.model import RobotModel, friction_torque
from teleop_rt.world import (
    Load,
    ScriptedHand,
    advance_load,
    build_environment,
    build_operator,
    cartesian_load,
    joint_load,
    load_width,
    snapshot_load,
)

# seeds of the two plants' noise generators differ so their noise is independent
_SIDE_SEED = {"hsi": 1, "to": 2}


class PlantState(Block):
    """The simulated robot: joint state, the torques on it (motor, loads, total) and its
    friction parameters; time and tick; the tool's velocity (world frame) when loads act there."""

    q = Vector("joint angles, rad")
    v = Vector("joint velocities, rad/s")
    tau_motor = Vector("the motor torque held over the period, N m")
    tau_load = Vector("the loads' joint torques, N m")
    tau = Vector("the total torque: motor + loads - friction, N m")
    damping = Vector(param=True)
    coulomb = Vector(param=True)
    t = Scalar("time, s")
    dt = Scalar(param=True)
    h = Scalar("integration step, s", param=True)
    inv_v_s = Scalar(param=True)
    tool_vx = Scalar("the tool's velocity (world frame), m/s")
    tool_vy = Scalar()
    tool_vz = Scalar()
    tick = Int()


# The kernels below index the packed buffers directly, by ``PlantState.idx``: ``o`` holds the
# plant's offsets (its state block first, then its loads, a hand followed by its trajectory),
# as a view of whatever buffers hold them (its own, or a session's, see ``SimBackend.rebind``);
# a slice costs a compiled function tens of ns, more than the arithmetic it serves.


@jit
def total_torque(f: np.ndarray, s: int, n: int) -> None:
    """tau = tau_motor + tau_load - friction(v), for the plant state at f[s:]."""
    Ps = PlantState.idx
    inv_v_s = f[s + Ps.N_VECTORS * n + Ps.INV_V_S]
    for j in range(n):
        friction = friction_torque(
            f[s + Ps.DAMPING * n + j], f[s + Ps.COULOMB * n + j], inv_v_s, f[s + Ps.V * n + j]
        )
        f[s + Ps.TAU * n + j] = f[s + Ps.TAU_MOTOR * n + j] + f[s + Ps.TAU_LOAD * n + j] - friction


@jit
def command(f: np.ndarray, o: np.ndarray, n: int, tau_cmd: np.ndarray) -> None:
    """Hold the motor torque tau_cmd for the period; the total torque at the tick's start."""
    Ps = PlantState.idx
    s = o[0]
    for j in range(n):
        f[s + Ps.TAU_MOTOR * n + j] = tau_cmd[j]
    total_torque(f, s, n)


@jit
def euler_step(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, a: np.ndarray) -> None:
    """One semi-implicit (symplectic) Euler step of h with acceleration a: the stateful loads,
    then v, then q with the new v."""
    Ps = PlantState.idx
    s = o[0]
    h = f[s + Ps.N_VECTORS * n + Ps.H]
    b = 1
    while b < o.size // 2:
        advance_load(f, i, o, b, h)
        b += load_width(i, o, b)
    for j in range(n):
        vj = f[s + Ps.V * n + j] + h * a[j]
        f[s + Ps.V * n + j] = vj
        f[s + Ps.Q * n + j] += h * vj
    f[s + Ps.N_VECTORS * n + Ps.T] += h


@jit
def evaluate_loads(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, jac: np.ndarray, x: np.ndarray
) -> None:
    """tau_load: the sum of the loads' joint torques at the plant's (t, q, v), with the tool at x
    (world frame) and jac its translational Jacobian (rows 0-2, world-aligned)."""
    Ps = PlantState.idx
    s = o[0]
    t, tool_v = f[s + Ps.N_VECTORS * n + Ps.T], s + Ps.N_VECTORS * n + Ps.TOOL_VX
    vx = vy = vz = 0.0
    for j in range(n):
        vj = f[s + Ps.V * n + j]
        vx += jac[0, j] * vj
        vy += jac[1, j] * vj
        vz += jac[2, j] * vj
    f[tool_v], f[tool_v + 1], f[tool_v + 2] = vx, vy, vz
    cartesian = False
    fx = fy = fz = 0.0
    blocks = o.size // 2
    b = 1
    while b < blocks:
        force = cartesian_load(f, i, o, b, t, x[0], x[1], x[2], vx, vy, vz)
        if force >= 0:
            cartesian = True
            fx, fy, fz = fx + f[force], fy + f[force + 1], fz + f[force + 2]
        b += load_width(i, o, b)
    tau_load = s + Ps.TAU_LOAD * n
    for j in range(n):  # tau = J^T F
        f[tau_load + j] = jac[0, j] * fx + jac[1, j] * fy + jac[2, j] * fz if cartesian else 0.0
    b = 1
    while b < blocks:
        joint_load(f, i, o, b, n, t, s + Ps.Q * n, s + Ps.V * n, tau_load)
        b += load_width(i, o, b)


@jit
def sense(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int,
    fb_f: np.ndarray, fb_i: np.ndarray, world: np.ndarray,
) -> None:  # fmt: skip
    """Ideal sensors: the feedback (q, v, tau_ext = tau_load, fresh) and the world snapshot (the
    hand's reference and force, or the environment's force and contacts)."""
    Ps, Fb = PlantState.idx, Feedback.idx
    s = o[0]
    for j in range(n):
        fb_f[Fb.Q * n + j] = f[s + Ps.Q * n + j]
        fb_f[Fb.V * n + j] = f[s + Ps.V * n + j]
        fb_f[Fb.TAU_EXT * n + j] = f[s + Ps.TAU_LOAD * n + j]
    fb_i[Fb.AGE_TICKS] = 0
    hand = False
    fx = fy = fz = 0.0
    contact = 0
    b = 1
    while b < o.size // 2:
        shown = snapshot_load(f, i, o, b, world, contact)
        if shown == -1:
            hand = True
        elif shown >= 0:
            fx, fy, fz = fx + f[shown], fy + f[shown + 1], fz + f[shown + 2]
            contact += 1
        b += load_width(i, o, b)
    if not hand and contact:
        force = 3 * WorldSnapshot.idx.FORCE  # (vectors of 3)
        world[force], world[force + 1], world[force + 2] = fx, fy, fz


@jit
def next_tick(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, jac: np.ndarray, x: np.ndarray
) -> None:
    """The end of a write: the next tick's time and the loads there."""
    Ps = PlantState.idx
    tick = o[1] + Ps.TICK
    i[tick] += 1
    scalars = o[0] + Ps.N_VECTORS * n
    f[scalars + Ps.T] = i[tick] * f[scalars + Ps.DT]  # no drift from sums
    evaluate_loads(f, i, o, n, jac, x)


class SimBackend(Backend):
    """One simulated robot with the loads acting on it."""

    def __init__(
        self,
        plant: RobotModel,
        loads: list[Load],
        q0: np.ndarray,
        dt: float,
        substeps: int = 1,
        integrator: str = "semi_implicit_euler",
        torque_noise_std: float = 0.0,
        velocity_noise_std: float = 0.0,
        seed: int = 0,
        faults: list[FaultSpec] | None = None,
    ) -> None:
        if integrator not in ("semi_implicit_euler", "rk4"):
            raise ValueError(f"unknown integrator {integrator!r}")
        n = plant.nv
        for load in loads:
            if not load.cartesian and load.n != n:
                raise ValueError(f"{type(load).__name__} has {load.n} joints, the plant {n}")
        contacts = [ld for ld in loads if ld.cartesian and not ld.is_operator]
        super().__init__(n, len(contacts))
        self.plant = plant
        self.loads = loads
        self.stateful = [ld for ld in loads if ld.stateful]
        self.substeps = substeps
        self.rk4 = integrator == "rk4"
        self.faults = list(faults or [])
        self.torque_noise_std = torque_noise_std
        self.velocity_noise_std = velocity_noise_std
        self.rng = np.random.default_rng(seed)
        self._noise = np.zeros(n)
        self._held: dict[int, float] = {}  # stuck joints: the angle they are held at
        # the common case: one Euler step per write, ideal sensors
        self._one_euler_step = substeps == 1 and not self.rk4 and not self.faults
        self._ideal_sensors = not (self.faults or torque_noise_std or velocity_noise_std)

        state = PlantState(n)
        state.q[:] = q0
        state.dt, state.h = dt, dt / substeps
        state.damping[:] = plant.damping
        state.coulomb[:] = plant.coulomb if plant.has_coulomb else 0.0
        state.inv_v_s = plant.inv_v_s
        blocks: list[Block] = [state]
        for load in loads:
            blocks.append(load)
            if isinstance(load, ScriptedHand):
                blocks.append(load.trajectory)
        self.blocks = blocks
        self.state = state
        self._cartesian = any(ld.cartesian for ld in loads)
        self._no_jacobian = np.zeros((6, n))
        self._x = plant._ee_translation  # a view of data.oMf, updated by the Jacobian call
        packed = Packed(blocks)
        self.rebind(packed.f, packed.i, packed.offsets)
        self._evaluate_loads()
        self._warm_up()

    def _warm_up(self) -> None:
        """Load (or, on a fresh install, compile) the read's and write's kernels now, on scratch
        copies of the state, not at the first read or write: loading takes milliseconds, a
        period of a drive emulator or of a session that runs this plant."""
        f, i, o, n = self._buffers
        f, i, zeros = f.copy(), i.copy(), np.zeros(n)
        sense(f, i, o, n, self.feedback.f.copy(), self.feedback.i.copy(), self.world.f.copy())
        command(f, o, n, zeros)
        euler_step(f, i, o, n, zeros)
        next_tick(f, i, o, n, self._no_jacobian, np.zeros(3))
        total_torque(f, int(o[0]), n)

    def rebind(self, f: np.ndarray, i: np.ndarray, offsets: np.ndarray) -> None:
        """Work on ``self.blocks`` where they are now: the buffers f, i that hold them and
        their ``offsets`` there (a view, in ``blocks``' order). A session that packs the
        plant with its own blocks (``teleop_rt.lockstep_fused``) calls this after packing."""
        state, plant = self.state, self.plant
        self._buffers = (f, i, offsets, self.n)
        # Pinocchio's arguments, looked up once: the state's views and the tool's placement
        self._pin = (plant.model, plant.data, state.q, state.v, state.tau)
        self._tool = (plant.model, plant.data, state.q, plant.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
        # the tool's Jacobian as (call, its arguments): Pinocchio's call itself where what it
        # returns is the (6, n) Jacobian as it is (a fused session calls it per tick)
        direct = self._cartesian and self.n > 1
        call: tuple[Callable[..., np.ndarray], tuple[Any, ...]] = (
            (pin.computeFrameJacobian, self._tool) if direct else (self._jacobian, ())
        )
        self.jacobian_call = call
        # the read's and write's kernels bound to the plant's own buffers (``flat.bound_kernel``:
        # no dispatcher typing 4-6 arrays a call), for Pinocchio's ABA (a float64 vector) and
        # Jacobian ((6, n), C order, as ``_no_jacobian``); the feedback and world buffers are
        # passed per call (a site packs them after this)
        fb, b = self.feedback, self._buffers
        self._entries = (
            bound_kernel(sense, b, fb.f, fb.i, self.world.f),
            bound_kernel(euler_step, b, np.zeros(self.n)),
            bound_kernel(next_tick, b, self._no_jacobian, self._x),
        )

    @property
    def compiled_common_case(self) -> bool:
        """One semi-implicit Euler step per write, ideal sensors, no faults, and ``read`` and
        ``write`` as defined here (not a subclass's): what the fused simulated tick
        (``teleop_rt.lockstep_fused``) does in their place."""
        cls = type(self)
        own = cls.read is SimBackend.read and cls.write is SimBackend.write
        own = own and not {"read", "write"} & vars(self).keys()  # nor replaced on the instance
        return own and self._one_euler_step and self._ideal_sensors

    @property
    def tau_motor(self) -> np.ndarray:
        """The motor torque held over the current period (N m)."""
        return self.state.tau_motor

    # --- Backend --------------------------------------------------------------------------
    def read(self) -> Feedback:
        fb = self.feedback
        if self.faults and self._active("dropout"):
            fb.age_ticks += 1  # the sensors did not deliver: the last values stay
            return fb
        self._entries[0](fb.f, fb.i, self.world.f)
        if self._ideal_sensors:
            return fb
        if self.torque_noise_std:
            self._add_noise(fb.tau_ext, self.torque_noise_std)
        if self.velocity_noise_std:
            self._add_noise(fb.v, self.velocity_noise_std)
        if self.faults:
            self._corrupt_sensors(fb)  # (the torque sensors only)
        return fb

    def write(self, tau: list[float] | np.ndarray) -> None:
        tau = tau if isinstance(tau, np.ndarray) else as_floats(tau)
        f, i, o, n = self._buffers
        command(f, o, n, tau)  # (the dispatcher: ``tau`` is any caller's)
        _, step, to_next_tick = self._entries
        if self._one_euler_step:
            model, data, q, v, tau_total = self._pin
            step(pin.aba(model, data, q, v, tau_total))
        else:
            self._advance()
        to_next_tick(self._jacobian(), self._x)

    # --- lifecycle (teleop_rt.hal.base): nothing to configure or power up; torque is accepted
    # from construction on (a session stepped by hand needs none of it)
    def on_deactivate_step(self) -> bool:
        self.state.tau_motor[:] = 0.0
        return True

    # --- the general path: sub-steps, RK4, faults, noisy sensors ---------------------------
    def _active(self, kind: str) -> list[FaultSpec]:
        t = self.state.tick * self.state.dt
        return [
            f for f in self.faults if f.kind == kind and f.start_s <= t < f.start_s + f.duration_s
        ]

    def _corrupt_sensors(self, fb: Feedback) -> None:
        for f in self._active("nan"):
            fb.tau_ext[f.joint] = float("nan")
        for f in self._active("bias"):
            fb.tau_ext[f.joint] += f.magnitude
        for f in self._active("noise_burst"):
            fb.tau_ext[f.joint] += f.magnitude * float(self.rng.standard_normal())

    def _add_noise(self, values: np.ndarray, std: float) -> None:
        self.rng.standard_normal(out=self._noise)
        values += std * self._noise

    def _advance(self) -> None:
        state = self.state
        for f in self._active("saturation"):
            lim = f.magnitude
            state.tau_motor[f.joint] = min(max(state.tau_motor[f.joint], -lim), lim)
        stuck = self._active("stuck")
        for f in stuck:
            self._held.setdefault(f.joint, float(state.q[f.joint]))
        for k in range(self.substeps):
            if k:  # the loads at the tick's start were evaluated at the end of the last write
                self._evaluate_loads()
            if self.rk4:
                self._rk4_step()
            else:
                fb, i, o, n = self._buffers  # (f is the fault above)
                euler_step(fb, i, o, n, self._acceleration())
            for fault in stuck:  # a blocked joint: held in place whatever the torque
                state.q[fault.joint] = self._held[fault.joint]
                state.v[fault.joint] = 0.0

    def _evaluate_loads(self) -> None:
        f, i, o, n = self._buffers
        evaluate_loads(f, i, o, n, self._jacobian(), self._x)

    def _jacobian(self) -> np.ndarray:
        """The tool's Jacobian (6 x n, world-aligned) at the plant's q; it also places the tool
        (``_x``). Zeros when no load acts at the tool."""
        if not self._cartesian:
            return self._no_jacobian
        jac = pin.computeFrameJacobian(*self._tool)
        return jac if jac.ndim == 2 else jac.reshape(6, 1)  # a 1-DoF robot's comes flat

    def _acceleration(self) -> np.ndarray:
        """Joint acceleration at the plant's state with the loads last evaluated (ABA; M a + n
        = g + tau_motor + tau_load - friction)."""
        total_torque(self.state.f, 0, self.n)
        return pin.aba(*self._pin)

    def _rk4_step(self) -> None:
        # classic RK4 on (q, v) and the stateful loads' states; every stage re-evaluates the
        # loads at its own (t, q, v, load state)
        state, h, stateful = self.state, self.state.h, self.stateful
        q0, v0, t0 = state.q.copy(), state.v.copy(), state.t
        s0 = [load.state() for load in stateful]
        stages = [(v0, self._acceleration(), [load.derivative() for load in stateful])]
        for frac in (0.5, 0.5, 1.0):
            dq, dv, ds = stages[-1]
            state.q[:] = q0 + frac * h * dq
            state.v[:] = v0 + frac * h * dv
            for load, x0, dx in zip(stateful, s0, ds, strict=True):
                load.set_state(tuple(a + frac * h * b for a, b in zip(x0, dx, strict=True)))
            state.t = t0 + frac * h
            self._evaluate_loads()
            accel = self._acceleration()
            stages.append((state.v.copy(), accel, [load.derivative() for load in stateful]))
        (v1, a1, d1), (v2, a2, d2), (v3, a3, d3), (v4, a4, d4) = stages
        w = h / 6.0
        state.q[:] = q0 + w * (v1 + 2.0 * v2 + 2.0 * v3 + v4)
        state.v[:] = v0 + w * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        for i, load in enumerate(stateful):
            load.set_state(
                tuple(
                    x + w * (p1 + 2.0 * p2 + 2.0 * p3 + p4)
                    for x, p1, p2, p3, p4 in zip(s0[i], d1[i], d2[i], d3[i], d4[i], strict=True)
                )
            )
        state.t = t0 + h


def make_sim(
    cfg: SessionConfig, side: str, model: RobotModel | None, operator: Load | None = None
) -> SimBackend:
    """The simulated robot of side ``side`` (the registry's "sim"); ``operator`` replaces the
    config's operator model on the HSI (replay drives it from a log)."""
    spec = getattr(cfg, side)
    plant = RobotModel.from_spec(spec.robot, side, cfg.plant.coulomb_smoothing_rad_s)
    q0 = initial_configuration(spec.robot.q0_rad, plant, side)
    if side == "hsi":
        loads = [operator if operator is not None else build_operator(cfg.operator, plant, q0)]
    else:
        loads = build_environment(cfg.environment)
    return SimBackend(
        plant,
        loads,
        q0,
        cfg.dt,
        substeps=cfg.plant.substeps,
        integrator=cfg.plant.integrator,
        torque_noise_std=cfg.plant.torque_noise_std_nm,
        velocity_noise_std=cfg.plant.velocity_noise_std_rad_s,
        seed=cfg.seed * 1000 + _SIDE_SEED[side],
        faults=_faults_for(cfg, side, plant.nv),
    )


def _faults_for(cfg: SessionConfig, side: str, n: int) -> list[FaultSpec]:
    faults = []
    for i, f in enumerate(cfg.plant.faults):
        if f.robot != side:
            continue
        if f.joint >= n:
            raise ConfigError(f"plant.faults.{i}.joint: {f.joint} but the {side} has {n} joints")
        faults.append(f)
    return faults


def initial_configuration(q0: list[float] | None, model: RobotModel, side: str) -> np.ndarray:
    """q0 from the config (zeros if absent), length-checked against the model."""
    from teleop_rt.config import per_joint

    if q0 is None:
        return np.zeros(model.nq)
    return np.array(per_joint(q0, model.nq, f"{side}.robot.q0_rad"))
