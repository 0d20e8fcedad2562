"""Operator and environment models acting on the simulated robots.

Every model is a *load*. A joint load adds the joint torque it applies to the robot in
``add_joint_torque(t, q, v, out)`` (``tau_ext`` in the sign of ``teleop_rt.control``: torque
applied TO the robot). A Cartesian load returns the force on the end-effector point in
``force(t, x, xd)``; the plant maps it to joints with the translational Jacobian,
``tau = J^T F``. Stateful loads (a pushed mass) advance their own state in ``advance(dt)``.
Vectors are plain 3-lists and tuples: these run in the plant's inner loop.

Half-plane geometry: a plane through ``point_m`` with unit normal ``n`` pointing to free space;
penetration ``d = (p0 - x) . n`` (> 0 inside), penetration rate ``dd = -xdot . n``.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from teleop_rt.config import (
    DamperOperatorSpec,
    Environment,
    HandOperatorSpec,
    MassSpec,
    SpringSpec,
    WallSpec,
    per_joint,
)
from teleop_rt.model import RobotModel


class Load:
    """Something that pushes on a robot."""

    cartesian = False
    stateful = False
    is_operator = False  # operators load the HSI; everything else is environment
    in_contact = False

    def advance(self, dt: float) -> None:
        """Advance internal state by dt (stateful loads only; semi-implicit Euler)."""

    # RK4 needs the state itself: stateful loads also implement these three
    def state(self) -> tuple[float, ...]:
        return ()

    def set_state(self, state: tuple[float, ...]) -> None:
        """Set the internal state (RK4 stages)."""

    def derivative(self) -> tuple[float, ...]:
        """d(state)/dt with the force of the last ``force`` call."""
        return ()


class JointLoad(Load):
    def add_joint_torque(self, t: float, q: np.ndarray, v: list[float], out: list[float]) -> None:
        raise NotImplementedError


class CartesianLoad(Load):
    cartesian = True

    def __init__(self) -> None:
        self.last_force = (0.0, 0.0, 0.0)  # for recording

    def force(self, t: float, x: list[float], xd: list[float]) -> tuple[float, float, float]:
        raise NotImplementedError


def _vec(v: list[float]) -> tuple[float, float, float]:
    a = [0.0, 0.0, 0.0]
    a[: len(v)] = v
    return (a[0], a[1], a[2])


def _unit(v: list[float]) -> tuple[float, float, float]:
    x, y, z = _vec(v)
    norm = math.sqrt(x * x + y * y + z * z)
    return (x / norm, y / norm, z / norm)


# --- operators (HSI side) ---------------------------------------------------------------------
class JointDamperOperator(JointLoad):
    """The paper's operator Z_o: a joint damper to the ground, tau = -Z_o v."""

    is_operator = True

    def __init__(self, spec: DamperOperatorSpec, n: int) -> None:
        self.damping = per_joint(spec.damping_nm_s_per_rad, n, "operator.damping_nm_s_per_rad")
        self.in_contact = True

    def add_joint_torque(self, t, q, v, out):  # noqa: D102 - see JointLoad
        for j, d in enumerate(self.damping):
            out[j] -= d * v[j]


class JointSpringDamper(JointLoad):
    """A joint-space environment Z_e = c + k/s per joint, about the rest angles q_rest:
    tau_ext = -(k (q - q_rest) + c v). The displayed-impedance analysis (eq 19-32) is per joint;
    this load realises its environment exactly on a simulated joint."""

    def __init__(self, stiffness: list[float], damping: list[float], q_rest: list[float]) -> None:
        self.k, self.c, self.q_rest = list(stiffness), list(damping), list(q_rest)
        self.in_contact = True

    def add_joint_torque(self, t, q, v, out):  # noqa: D102 - see JointLoad
        for j in range(len(out)):
            out[j] -= self.k[j] * (q[j] - self.q_rest[j]) + self.c[j] * v[j]


class HandTrajectory:
    """Minimum-jerk segments through waypoints, from ``start`` at t = 0; holds the last one."""

    def __init__(self, start: list[float], times: list[float], points: list[list[float]]) -> None:
        self.times = [0.0, *times]
        self.points = [list(start), *[list(p) for p in points]]
        self.pos = list(start)
        self.vel = [0.0, 0.0, 0.0]
        # the segment of the last evaluation, followed forward tick by tick; a sentinel time
        # after the last waypoint lets the final hold use the same check
        self._segment = 0
        self.times.append(math.inf)
        self.points.append(self.points[-1])

    def evaluate(self, t: float) -> None:
        """Fill pos (m) and vel (m/s) at time t (s)."""
        times = self.times
        i = self._segment
        if not times[i] <= t < times[i + 1]:  # time moved to another segment (rarely)
            i = bisect.bisect_right(times, t) - 1
            if i >= len(times) - 1:
                self.pos[:] = self.points[-1]
                self.vel[:] = [0.0, 0.0, 0.0]
                return
            self._segment = i
        t0 = times[i]
        duration = times[i + 1] - t0
        s = (t - t0) / duration
        shape = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
        rate = 30.0 * s * s * (1.0 - s) * (1.0 - s) / duration
        p0, p1, pos, vel = self.points[i], self.points[i + 1], self.pos, self.vel
        dx, dy, dz = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
        pos[0], pos[1], pos[2] = p0[0] + dx * shape, p0[1] + dy * shape, p0[2] + dz * shape
        vel[0], vel[1], vel[2] = dx * rate, dy * rate, dz * rate


class LoggedTrajectory:
    """A hand reference replayed from a log, tick-locked: at tick times it returns the logged
    samples exactly; between ticks (sub-steps) it interpolates linearly; after the last sample
    it holds the last position at rest."""

    def __init__(self, pos: np.ndarray, vel: np.ndarray, dt: float) -> None:
        self.samples_pos = np.asarray(pos, dtype=float)
        self.samples_vel = np.asarray(vel, dtype=float)
        self.dt = dt
        self.last = len(self.samples_pos) - 1
        self.pos = self.samples_pos[0].tolist()
        self.vel = self.samples_vel[0].tolist()

    def evaluate(self, t: float) -> None:
        x = t / self.dt
        k = round(x)
        if abs(x - k) < 1e-9:  # on a tick: the logged sample itself
            if k > self.last:
                self.pos[:] = self.samples_pos[self.last].tolist()
                self.vel[:] = [0.0, 0.0, 0.0]
            else:
                self.pos[:] = self.samples_pos[k].tolist()
                self.vel[:] = self.samples_vel[k].tolist()
            return
        k0 = min(int(x), self.last)
        k1 = min(k0 + 1, self.last)
        w = x - int(x)
        self.pos[:] = ((1 - w) * self.samples_pos[k0] + w * self.samples_pos[k1]).tolist()
        self.vel[:] = ((1 - w) * self.samples_vel[k0] + w * self.samples_vel[k1]).tolist()


class ScriptedHand(CartesianLoad):
    """An active operator: F = K (x_ref - x) + D (xd_ref - xd) at the tool. The reference is a
    script (``from_spec``: minimum-jerk waypoints) or a log (``LoggedTrajectory``, replay)."""

    is_operator = True

    def __init__(
        self, trajectory: HandTrajectory | LoggedTrajectory, stiffness: float, damping: float
    ) -> None:
        super().__init__()
        self.trajectory = trajectory
        self.k = stiffness
        self.d = damping
        self.in_contact = True

    @classmethod
    def from_spec(cls, spec: HandOperatorSpec, start: list[float]) -> ScriptedHand:
        points = []
        for wp in spec.waypoints:
            p = list(start)  # a 2-number waypoint keeps the start's z
            p[: len(wp.position_m)] = wp.position_m
            points.append(p)
        trajectory = HandTrajectory(start, [w.t_s for w in spec.waypoints], points)
        return cls(trajectory, spec.stiffness_n_per_m, spec.damping_n_s_per_m)

    @property
    def reference(self) -> list[float]:
        return self.trajectory.pos

    def force(self, t, x, xd):  # noqa: D102 - see CartesianLoad
        traj = self.trajectory
        traj.evaluate(t)
        k, d, p, pv = self.k, self.d, traj.pos, traj.vel
        f = (
            k * (p[0] - x[0]) + d * (pv[0] - xd[0]),
            k * (p[1] - x[1]) + d * (pv[1] - xd[1]),
            k * (p[2] - x[2]) + d * (pv[2] - xd[2]),
        )
        self.last_force = f
        return f


# --- environments (TO side) -------------------------------------------------------------------
class HalfPlaneContact(CartesianLoad):
    """Spring-damper along the normal of a plane: unilateral (wall, foam) or bilateral (spring,
    damper). The unilateral force never pulls (f >= 0), so a fast retreat does not stick."""

    def __init__(self, spec: WallSpec | SpringSpec) -> None:
        super().__init__()
        self.kind = spec.kind
        self.p0 = _vec(spec.point_m)
        self.n = _unit(spec.normal)
        self.k = spec.stiffness_n_per_m
        self.c = spec.damping_n_s_per_m
        self.unilateral = spec.kind in ("wall", "foam")
        self.in_contact = not self.unilateral

    def force(self, t, x, xd):  # noqa: D102 - see CartesianLoad
        (nx, ny, nz), p0 = self.n, self.p0
        depth = (p0[0] - x[0]) * nx + (p0[1] - x[1]) * ny + (p0[2] - x[2]) * nz
        rate = -(xd[0] * nx + xd[1] * ny + xd[2] * nz)
        f = self.k * depth + self.c * rate
        if self.unilateral:
            self.in_contact = depth > 0.0
            if not self.in_contact or f < 0.0:
                f = 0.0
        out = (f * nx, f * ny, f * nz)
        self.last_force = out
        return out


class PushedMass(CartesianLoad):
    """A free mass m resting against the plane, pushed (or held, if attached) by the
    end-effector through a stiff contact spring-damper; it slides along -n without friction.
    At frequencies well below the contact resonance the end-effector feels Z_e = m s."""

    stateful = True

    def __init__(self, spec: MassSpec) -> None:
        super().__init__()
        self.p0 = _vec(spec.point_m)
        self.n = _unit(spec.normal)
        self.m = spec.mass_kg
        self.attached = spec.attached
        self.k = spec.contact_stiffness_n_per_m
        self.c = spec.contact_damping_n_s_per_m
        self.s = 0.0  # displacement of the mass into the half-space (along -n), m
        self.s_dot = 0.0
        self._f = 0.0

    def force(self, t, x, xd):  # noqa: D102 - see CartesianLoad
        (nx, ny, nz), p0 = self.n, self.p0
        depth = (p0[0] - x[0]) * nx + (p0[1] - x[1]) * ny + (p0[2] - x[2]) * nz - self.s
        rate = -(xd[0] * nx + xd[1] * ny + xd[2] * nz) - self.s_dot
        f = self.k * depth + self.c * rate
        if self.attached:
            self.in_contact = True
        else:
            self.in_contact = depth > 0.0
            if not self.in_contact or f < 0.0:
                f = 0.0
        self._f = f
        out = (f * nx, f * ny, f * nz)
        self.last_force = out
        return out

    def advance(self, dt: float) -> None:
        # the mass feels the contact force's reaction, pushing it along -n (semi-implicit Euler)
        self.s_dot += dt * self._f / self.m
        self.s += dt * self.s_dot

    def state(self) -> tuple[float, float]:
        return (self.s, self.s_dot)

    def set_state(self, state: tuple[float, ...]) -> None:
        self.s, self.s_dot = state

    def derivative(self) -> tuple[float, float]:
        return (self.s_dot, self._f / self.m)


def build_operator(
    spec: DamperOperatorSpec | HandOperatorSpec, robot: RobotModel, q0: np.ndarray
) -> Load:
    """The operator load on the HSI, from its config section."""
    if isinstance(spec, DamperOperatorSpec):
        return JointDamperOperator(spec, robot.nv)
    return ScriptedHand.from_spec(spec, robot.ee_position(q0).tolist())


def build_environment(specs: list[Environment]) -> list[Load]:
    """The environment loads on the TO (an empty list is free space)."""
    return [PushedMass(s) if isinstance(s, MassSpec) else HalfPlaneContact(s) for s in specs]
