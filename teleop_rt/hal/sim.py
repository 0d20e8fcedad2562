"""Simulated backend: a robot's full nonlinear rigid-body dynamics (Pinocchio ABA, Coriolis,
gravity, joint friction) with its operator or environment loads, integrated over one period
per ``write`` with a configurable integrator and number of sub-steps.

The plant owns its own ``RobotModel`` (its own Pinocchio Data), separate from the controller's:
it stands for the real robot. Sensors are ideal unless noise is configured (seeded, so fast mode
stays deterministic).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from teleop_rt.config import FaultSpec, SessionConfig
from teleop_rt.errors import ConfigError
from teleop_rt.hal.base import Backend, Feedback, register_backend
from teleop_rt.model import RobotModel
from teleop_rt.scalar import assign, shared_vector
from teleop_rt.world import Load, ScriptedHand, build_environment, build_operator

# seeds of the two plants' noise generators differ so their noise is independent
_SIDE_SEED = {"hsi": 1, "to": 2}


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
        contact_loads = [ld for ld in loads if ld.cartesian and not ld.is_operator]
        super().__init__(plant.nv, len(contact_loads))
        self.contact_loads = contact_loads
        self.hand = next((ld for ld in loads if isinstance(ld, ScriptedHand)), None)
        if integrator not in ("semi_implicit_euler", "rk4"):
            raise ValueError(f"unknown integrator {integrator!r}")
        n = plant.nv
        self.plant = plant
        self.joint_loads = [ld for ld in loads if not ld.cartesian]
        self.cartesian_loads = [ld for ld in loads if ld.cartesian]
        self.loads = loads
        self.stateful = [ld for ld in loads if ld.stateful]
        self.dt = dt
        self.h = dt / substeps
        self.substeps = substeps
        self.rk4 = integrator == "rk4"
        self._single_euler_step = substeps == 1 and not self.rk4 and not faults
        # state: lists for the scalar arithmetic, numpy mirrors for Pinocchio
        self.ql = [float(x) for x in q0]
        self.vl = [0.0] * n
        self.q, self._q_view = shared_vector(n)  # Pinocchio's inputs, written element-wise
        self.v, self._v_view = shared_vector(n)
        self.q[:] = self.ql
        self.t = 0.0
        self.tick = 0
        self.tau_motor = [0.0] * n
        self.tau_load = [0.0] * n  # loads at the current state (what an ideal sensor reads)
        self._tau, self._tau_view = shared_vector(n)
        self._qs, self._vs = np.zeros(n), np.zeros(n)
        self.torque_noise_std = torque_noise_std
        self.velocity_noise_std = velocity_noise_std
        self.rng = np.random.default_rng(seed)
        self._noise = np.zeros(n)
        self.faults = list(faults or [])
        self._held: dict[int, float] = {}  # stuck joints: the angle they are held at
        self._eval_loads(self.t, self.q, self.vl)

    # --- Backend --------------------------------------------------------------------------
    def start(self) -> None:
        """Nothing to power up: the simulated robot accepts torque from construction on."""

    def _active(self, kind: str) -> list[FaultSpec]:
        t = self.tick * self.dt
        return [
            f for f in self.faults if f.kind == kind and f.start_s <= t < f.start_s + f.duration_s
        ]

    def read(self) -> Feedback:
        fb = self.feedback
        if self.faults and self._active("dropout"):
            fb.age_ticks += 1  # the sensors did not deliver: the last values stay
            return fb
        fb.age_ticks = 0
        # q, v: the plant's state (a memcpy each); tau_ext: what an ideal sensor reads
        fb.copy_arrays(self._q_view, self._v_view)
        tau_mv = fb.tau_mv
        for j, x in enumerate(self.tau_load):
            tau_mv[j] = x
        if self.torque_noise_std:
            self._add_noise(tau_mv, self.torque_noise_std)
        if self.velocity_noise_std:
            self._add_noise(fb.v_mv, self.velocity_noise_std)
        if self.faults:
            self._corrupt_sensors(fb)  # (the torque sensors only)
        self._snapshot_world()
        return fb

    def _corrupt_sensors(self, fb: Feedback) -> None:
        for f in self._active("nan"):
            fb.tau_ext[f.joint] = float("nan")
        for f in self._active("bias"):
            fb.tau_ext[f.joint] += f.magnitude
        for f in self._active("noise_burst"):
            fb.tau_ext[f.joint] += f.magnitude * float(self.rng.standard_normal())

    def _snapshot_world(self) -> None:
        # the loads were last evaluated at this tick's time (end of the previous write)
        world = self.world
        if self.hand is not None:
            trajectory, force = self.hand.trajectory, self.hand.last_force
            world.reference_mv[0], world.reference_mv[1], world.reference_mv[2] = trajectory.pos
            vel = world.reference_velocity_mv
            vel[0], vel[1], vel[2] = trajectory.vel
            world.force_mv[0], world.force_mv[1], world.force_mv[2] = force
        elif self.contact_loads:
            fx = fy = fz = 0.0
            contacts = world.contacts_mv
            for j, load in enumerate(self.contact_loads):
                f = load.last_force
                fx += f[0]
                fy += f[1]
                fz += f[2]
                contacts[j] = 1.0 if load.in_contact else 0.0
            world.force_mv[0], world.force_mv[1], world.force_mv[2] = fx, fy, fz

    def _add_noise(self, values: memoryview, std: float) -> None:
        self.rng.standard_normal(out=self._noise)
        for j, x in enumerate(self._noise.tolist()):
            values[j] += std * x

    def write(self, tau: list[float] | np.ndarray) -> None:
        self.tau_motor[:] = tau.tolist() if isinstance(tau, np.ndarray) else tau
        if self._single_euler_step:  # the common case, without the loop
            self._euler_substep()
        elif self.faults:
            self._advance_with_faults()
        else:
            self._advance()
        self.tick += 1
        self.t = self.tick * self.dt  # no drift from summing sub-steps
        self._eval_loads(self.t, self.q, self.vl)

    def _advance(self, stuck: Sequence[FaultSpec] = ()) -> None:
        substep = self._rk4_substep if self.rk4 else self._euler_substep
        for i in range(self.substeps):
            if i:  # the loads at the tick's start were evaluated at the end of the last write
                self._eval_loads(self.t, self.q, self.vl)
            substep()
            for f in stuck:  # a blocked joint: held in place whatever the torque
                j = f.joint
                self.ql[j] = self._q_view[j] = self._held[j]
                self.vl[j] = self._v_view[j] = 0.0

    def _advance_with_faults(self) -> None:
        for f in self._active("saturation"):
            lim = f.magnitude
            self.tau_motor[f.joint] = min(max(self.tau_motor[f.joint], -lim), lim)
        stuck = self._active("stuck")
        for f in stuck:
            self._held.setdefault(f.joint, self.ql[f.joint])
        self._advance(stuck)

    def stop(self) -> None:
        self.tau_motor[:] = [0.0] * self.n

    # --- dynamics -------------------------------------------------------------------------
    def _eval_loads(self, t: float, q: np.ndarray, v: list[float]) -> None:
        """tau_load = sum of the loads' joint torques at (t, q, v)."""
        tl = self.tau_load
        if self.cartesian_loads:
            plant = self.plant
            plant.update_ee(q, v)
            x, xd = plant.ee_pos, plant.ee_vel
            fx = fy = fz = 0.0
            for load in self.cartesian_loads:
                f = load.force(t, x, xd)
                fx += f[0]
                fy += f[1]
                fz += f[2]
            jx, jy, jz = plant.ee_jac[0], plant.ee_jac[1], plant.ee_jac[2]
            for j in range(self.n):  # tau = J^T F
                tl[j] = jx[j] * fx + jy[j] * fy + jz[j] * fz
        else:
            for j in range(self.n):
                tl[j] = 0.0
        for load in self.joint_loads:
            load.add_joint_torque(t, q, v, tl)

    def _acceleration(self, q: np.ndarray, v_arr: np.ndarray, v: list[float]) -> list[float]:
        # M a + n = g + tau_ext - friction
        fric = self.plant.friction(v)
        tm, tl, tau = self.tau_motor, self.tau_load, self._tau_view
        for j in range(self.n):
            tau[j] = tm[j] + tl[j] - fric[j]
        return self.plant.forward_dynamics(q, v_arr, self._tau)

    def _euler_substep(self) -> None:
        # semi-implicit (symplectic) Euler: v first, then q with the new v
        h, ql, vl = self.h, self.ql, self.vl
        a = self._acceleration(self.q, self.v, vl)
        for load in self.stateful:
            load.advance(h)
        q, v = self._q_view, self._v_view
        for j in range(self.n):
            vj = vl[j] + h * a[j]
            qj = ql[j] + h * vj
            vl[j] = v[j] = vj
            ql[j] = q[j] = qj
        self.t += h

    def _rk4_substep(self) -> None:
        # classic RK4 on (q, v) and the stateful loads' states; every stage re-evaluates the
        # loads at its own (t, q, v, load state)
        h, ql, vl, n = self.h, self.ql, self.vl, self.n
        qs, vs, stateful = self._qs, self._vs, self.stateful
        s0 = [load.state() for load in stateful]
        k1v = list(vl)
        k1a = self._acceleration(self.q, self.v, vl)  # loads already at (t, q, v, s0)
        stages = [(k1v, k1a, [load.derivative() for load in stateful])]
        for frac in (0.5, 0.5, 1.0):
            dq, dv, ds = stages[-1]
            q_stage = [ql[j] + frac * h * dq[j] for j in range(n)]
            v_stage = [vl[j] + frac * h * dv[j] for j in range(n)]
            for load, x0, dx in zip(stateful, s0, ds, strict=True):
                load.set_state(tuple(a + frac * h * b for a, b in zip(x0, dx, strict=True)))
            assign(qs, q_stage)
            assign(vs, v_stage)
            self._eval_loads(self.t + frac * h, qs, v_stage)
            accel = self._acceleration(qs, vs, v_stage)
            stages.append((v_stage, accel, [load.derivative() for load in stateful]))
        (v1, a1, d1), (v2, a2, d2), (v3, a3, d3), (v4, a4, d4) = stages
        w = h / 6.0
        for j in range(n):
            ql[j] += w * (v1[j] + 2.0 * v2[j] + 2.0 * v3[j] + v4[j])
            vl[j] += w * (a1[j] + 2.0 * a2[j] + 2.0 * a3[j] + a4[j])
        for i, load in enumerate(stateful):
            load.set_state(
                tuple(
                    x + w * (p1 + 2.0 * p2 + 2.0 * p3 + p4)
                    for x, p1, p2, p3, p4 in zip(s0[i], d1[i], d2[i], d3[i], d4[i], strict=True)
                )
            )
        assign(self._q_view, ql)
        assign(self._v_view, vl)
        self.t += h


@register_backend("sim")
def _make_sim(
    cfg: SessionConfig, side: str, model: RobotModel, operator: Load | None = None
) -> SimBackend:
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
