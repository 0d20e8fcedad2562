"""Operator and environment models acting on the simulated robots.

Every model is a *load*, and every load is a flat state block (``teleop_rt.flat``): its
parameters and state live in its buffers, and its physics is a compiled function on them, so
that the simulated plant (``teleop_rt.hal.sim``) evaluates all of its loads in one compiled call.
``load_kind`` (the block's int 0) says which function applies.

A joint load adds the joint torque it applies to the robot (``tau_ext`` in the sign of
``teleop_rt.control``: torque applied TO the robot). A Cartesian load applies a force at the
end-effector point (``force(t, x, xd)``); the plant maps the sum to joints with the
translational Jacobian, ``tau = J^T F``. Stateful loads (a pushed mass) advance their own state
once per integration step.

Half-space geometry: a plane through ``p0`` with unit normal ``normal`` pointing to free space;
penetration ``d = (p0 - x) . n`` (> 0 inside), penetration rate ``dd = -xdot . n``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

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
from teleop_rt.flat import Block, Int, Scalar, Vector, jit
from teleop_rt.hal.signals import WorldSnapshot
from teleop_rt.model import RobotModel

# load_kind codes; a hand's trajectory is the block right after the hand
JOINT_DAMPER, JOINT_SPRING_DAMPER, JOINT_MASS, HAND, HALF_SPACE = range(5)
MIN_JERK, LOGGED = range(2)  # trajectory_kind codes


class Load(Block):
    """Something that pushes on a robot."""

    cartesian = False
    stateful = False
    is_operator = False  # operators load the HSI; everything else is environment
    load_kind = Int("which load function applies (JOINT_DAMPER, ...)", param=True)

    @property
    def in_contact(self) -> bool:
        return True

    # a ``stateful`` load has a state of its own that the plant integrates with it (RK4 steps
    # it through these three); the others have none
    def state(self) -> tuple[float, ...]:
        raise NotImplementedError(f"{type(self).__name__} has no state")

    def set_state(self, state: tuple[float, ...]) -> None:
        raise NotImplementedError(f"{type(self).__name__} has no state")

    def derivative(self) -> tuple[float, ...]:
        raise NotImplementedError(f"{type(self).__name__} has no state")


class JointLoad(Load):
    """A load in joint space: vectors of one entry per joint."""


class CartesianLoad(Load):
    """A force at the tool; ``last_force`` (3, world frame) is the last one applied."""

    cartesian = True

    def __init__(self, tail: int = 0) -> None:
        super().__init__(3, tail)


def _vec(v: Sequence[float]) -> list[float]:
    a = [0.0, 0.0, 0.0]
    a[: len(v)] = v
    return a


def _xyz(v: Sequence[float]) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def _unit(v: Sequence[float]) -> list[float]:
    x, y, z = _vec(v)
    norm = math.sqrt(x * x + y * y + z * z)
    return [x / norm, y / norm, z / norm]


# --- joint loads ------------------------------------------------------------------------------
class JointDamperOperator(JointLoad):
    """The paper's operator Z_o: a joint damper to the ground, tau = -Z_o v."""

    is_operator = True
    damping = Vector("N m s/rad per joint", param=True)

    def __init__(self, spec: DamperOperatorSpec, n: int) -> None:
        super().__init__(n)
        self.load_kind = JOINT_DAMPER
        self.damping[:] = per_joint(spec.damping_nm_s_per_rad, n, "operator.damping_nm_s_per_rad")


class JointSpringDamper(JointLoad):
    """A joint-space environment Z_e = c + k/s per joint, about the rest angles q_rest:
    tau_ext = -(k (q - q_rest) + c v). The displayed-impedance analysis (eq 19-32) is per joint;
    this load realises its environment exactly on a simulated joint."""

    k = Vector("N m/rad per joint", param=True)
    c = Vector("N m s/rad per joint", param=True)
    q_rest = Vector("rad", param=True)

    def __init__(self, stiffness: list[float], damping: list[float], q_rest: list[float]) -> None:
        super().__init__(len(stiffness))
        self.load_kind = JOINT_SPRING_DAMPER
        self.k[:], self.c[:], self.q_rest[:] = stiffness, damping, q_rest


class JointMass(JointLoad):
    """Z_e = m s per joint as a sampled sensor sees a rigid payload (``teleop_rt.analysis.bode``):
    tau_ext = -m (v[k] - v[k-1]) / dt, held over the tick. The velocity is remembered per
    distinct evaluation time, so repeated evaluations at one time (sub-steps) agree."""

    mass = Vector("kg m^2 per joint", param=True)
    v_now = Vector()
    v_before = Vector()
    dt = Scalar(param=True)
    t_last = Scalar()
    started = Int()

    def __init__(self, mass: list[float], dt: float) -> None:
        super().__init__(len(mass))
        self.load_kind = JOINT_MASS
        self.mass[:] = mass
        self.dt = dt


@jit
def joint_load_torque(
    f: np.ndarray, i: np.ndarray, fo: int, io: int, n: int, t: float, q: int, v: int, out: int
) -> None:
    """f[out:out+n] -= the torque of the joint load at f[fo:], i[io:] at time t and joint state
    f[q:q+n], f[v:v+n] (one buffer holds them all: index arithmetic, no slices, is what keeps
    a compiled call of this size in tens of ns)."""
    kind = i[io + Load.idx.LOAD_KIND]
    if kind == JOINT_DAMPER:
        damping = fo + JointDamperOperator.idx.DAMPING * n
        for j in range(n):
            f[out + j] -= f[damping + j] * f[v + j]
    elif kind == JOINT_SPRING_DAMPER:
        Jsd = JointSpringDamper.idx
        k, c, q_rest = fo + Jsd.K * n, fo + Jsd.C * n, fo + Jsd.Q_REST * n
        for j in range(n):
            f[out + j] -= f[k + j] * (f[q + j] - f[q_rest + j]) + f[c + j] * f[v + j]
    elif kind == JOINT_MASS:
        Jm = JointMass.idx
        mass, v_now, v_before = fo + Jm.MASS * n, fo + Jm.V_NOW * n, fo + Jm.V_BEFORE * n
        dt, t_last = fo + Jm.N_VECTORS * n + Jm.DT, fo + Jm.N_VECTORS * n + Jm.T_LAST
        started = io + Jm.STARTED
        if i[started] == 0 or t != f[t_last]:  # a new time: the velocity a tick ago moves back
            for j in range(n):
                f[v_before + j] = f[v_now + j] if i[started] else f[v + j]
                f[v_now + j] = f[v + j]
            f[t_last] = t
            i[started] = 1
        inv_dt = 1.0 / f[dt]
        for j in range(n):
            f[out + j] -= f[mass + j] * (f[v_now + j] - f[v_before + j]) * inv_dt


# --- hand trajectories ------------------------------------------------------------------------
class Trajectory(Block):
    """A hand reference: ``pos`` (m) and ``vel`` (m/s) at the time of the last ``evaluate``."""

    pos = Vector("the reference, m")
    vel = Vector("its velocity, m/s")
    trajectory_kind = Int("which trajectory function applies (MIN_JERK, LOGGED)", param=True)

    def evaluate(self, t: float) -> None:
        """Fill pos and vel at time t (s)."""
        evaluate_trajectory(self.f, self.i, 0, 0, t)


class HandTrajectory(Trajectory):
    """Minimum-jerk segments through waypoints, from ``start`` at t = 0; holds the last one.

    Tail: the segment start times, then the points (3 each), with a sentinel segment at
    t = inf that holds the last point."""

    segment = Int()
    count = Int(param=True)
    TAIL_IS_STATE = False  # the waypoints

    def __init__(self, start: list[float], times: list[float], points: list[list[float]]) -> None:
        self.times = [0.0, *times, math.inf]
        self.points = [list(start), *[list(p) for p in points]]
        count = len(self.times)
        super().__init__(3, tail=4 * count)
        self.trajectory_kind = MIN_JERK
        self.count = count
        self.pos[:] = start
        tail = self.f[self.tail_start :]
        tail[:count] = self.times
        tail[count:] = [x for p in (*self.points, self.points[-1]) for x in p]


class LoggedTrajectory(Trajectory):
    """A hand reference replayed from a log, tick-locked: at tick times the logged samples
    exactly; between ticks (sub-steps) linear interpolation; after the last sample the last
    position at rest. Tail: the positions, then the velocities (3 per sample)."""

    dt = Scalar(param=True)
    last = Int(param=True)
    TAIL_IS_STATE = False  # the logged samples

    def __init__(self, pos: np.ndarray, vel: np.ndarray, dt: float) -> None:
        pos, vel = np.asarray(pos, dtype=float), np.asarray(vel, dtype=float)
        super().__init__(3, tail=pos.size + vel.size)
        self.trajectory_kind = LOGGED
        self.dt = dt
        self.last = len(pos) - 1
        self.f[self.tail_start :] = np.concatenate([pos.ravel(), vel.ravel()])
        self.pos[:], self.vel[:] = pos[0], vel[0]


@jit
def evaluate_trajectory(f: np.ndarray, i: np.ndarray, fo: int, io: int, t: float) -> None:
    """pos, vel (the trajectory block's vectors of 3, at f[fo:]) at time t."""
    if i[io + Trajectory.idx.TRAJECTORY_KIND] == MIN_JERK:
        _min_jerk(f, i, fo, io, t)
    else:
        _logged(f, i, fo, io, t)


@jit
def _min_jerk(f: np.ndarray, i: np.ndarray, fo: int, io: int, t: float) -> None:
    Ht = HandTrajectory.idx
    pos, vel = fo + 3 * Ht.POS, fo + 3 * Ht.VEL
    count = i[io + Ht.COUNT]
    times = fo + 3 * Ht.N_VECTORS + Ht.N_SCALARS  # the tail
    points = times + count
    s = i[io + Ht.SEGMENT]  # the segment of the last evaluation, followed forward tick by tick
    if not f[times + s] <= t < f[times + s + 1]:  # time moved to another segment (rarely)
        s = np.searchsorted(f[times : times + count], t, side="right") - 1
        if s >= count - 1:  # t = inf
            for a in range(3):
                f[pos + a] = f[points + 3 * (count - 1) + a]
                f[vel + a] = 0.0
            return
        i[io + Ht.SEGMENT] = s
    t0 = f[times + s]
    duration = f[times + s + 1] - t0
    u = (t - t0) / duration
    shape = u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
    rate = 30.0 * u * u * (1.0 - u) * (1.0 - u) / duration
    for a in range(3):
        p0 = f[points + 3 * s + a]
        d = f[points + 3 * s + 3 + a] - p0
        f[pos + a] = p0 + d * shape
        f[vel + a] = d * rate


@jit
def _logged(f: np.ndarray, i: np.ndarray, fo: int, io: int, t: float) -> None:
    Lt = LoggedTrajectory.idx
    out_pos, out_vel = fo + 3 * Lt.POS, fo + 3 * Lt.VEL
    last = i[io + Lt.LAST]
    pos = fo + 3 * Lt.N_VECTORS + Lt.N_SCALARS  # the tail: the positions, then the velocities
    vel = pos + 3 * (last + 1)
    x = t / f[fo + 3 * Lt.N_VECTORS + Lt.DT]
    k = int(np.rint(x))
    if abs(x - k) < 1e-9:  # on a tick: the logged sample itself
        for a in range(3):
            f[out_pos + a] = f[pos + 3 * min(k, last) + a]
            f[out_vel + a] = f[vel + 3 * k + a] if k <= last else 0.0
        return
    k0 = min(int(x), last)
    k1 = min(k0 + 1, last)
    w = x - int(x)
    for a in range(3):
        f[out_pos + a] = (1 - w) * f[pos + 3 * k0 + a] + w * f[pos + 3 * k1 + a]
        f[out_vel + a] = (1 - w) * f[vel + 3 * k0 + a] + w * f[vel + 3 * k1 + a]


# --- Cartesian loads --------------------------------------------------------------------------
class ScriptedHand(CartesianLoad):
    """An active operator: F = K (x_ref - x) + D (xd_ref - xd) at the tool. The reference is a
    script (``from_spec``: minimum-jerk waypoints) or a log (``LoggedTrajectory``, replay)."""

    is_operator = True
    last_force = Vector("the force on the tool, N (world frame)")
    k = Scalar("N/m", param=True)
    d = Scalar("N s/m", param=True)

    def __init__(self, trajectory: Trajectory, stiffness: float, damping: float) -> None:
        super().__init__()
        self.load_kind = HAND
        self.trajectory = trajectory
        self.k, self.d = stiffness, damping

    @classmethod
    def from_spec(cls, spec: HandOperatorSpec, start: list[float]) -> ScriptedHand:
        points = []
        for wp in spec.waypoints:
            p = list(start)  # a 2-number waypoint keeps the start's z
            p[: len(wp.position_m)] = wp.position_m
            points.append(p)
        trajectory = HandTrajectory(start, [w.t_s for w in spec.waypoints], points)
        return cls(trajectory, spec.stiffness_n_per_m, spec.damping_n_s_per_m)

    def force(self, t: float, x: Sequence[float], xd: Sequence[float]) -> tuple[float, ...]:
        """The force on the tool at (t, x, xd), N (also kept in ``last_force``)."""
        traj = self.trajectory
        hand_force(self.f, 0, traj.f, traj.i, 0, 0, t, *_xyz(x), *_xyz(xd))
        return tuple(self.last_force.tolist())


@jit
def hand_force(
    f: np.ndarray, fo: int, tf: np.ndarray, ti: np.ndarray, to: int, tio: int, t: float,
    x: float, y: float, z: float, vx: float, vy: float, vz: float,
) -> None:  # fmt: skip
    """The hand's force (block at f[fo:]) into its ``last_force``, its trajectory (at tf[to:],
    ti[tio:]) evaluated at t first; the tool at (x, y, z) moving at (vx, vy, vz)."""
    evaluate_trajectory(tf, ti, to, tio, t)
    Sh, Tr = ScriptedHand.idx, Trajectory.idx
    scalars = fo + 3 * Sh.N_VECTORS
    k, d = f[scalars + Sh.K], f[scalars + Sh.D]
    pos, vel, out = to + 3 * Tr.POS, to + 3 * Tr.VEL, fo + 3 * Sh.LAST_FORCE
    f[out] = k * (tf[pos] - x) + d * (tf[vel] - vx)
    f[out + 1] = k * (tf[pos + 1] - y) + d * (tf[vel + 1] - vy)
    f[out + 2] = k * (tf[pos + 2] - z) + d * (tf[vel + 2] - vz)


class HalfSpaceLoad(CartesianLoad):
    """Spring-damper along the normal of a plane; the plane moves by ``s`` along -n when a
    mass is behind it (``PushedMass``), else it stays put (s = 0). Unilateral loads never
    pull (f >= 0), so a fast retreat does not stick."""

    p0 = Vector("a point of the plane, m", param=True)
    normal = Vector("unit normal to free space", param=True)
    last_force = Vector("the force on the tool, N (world frame)")
    k = Scalar("N/m", param=True)
    c = Scalar("N s/m", param=True)
    unilateral = Scalar("1: pushes only (wall, foam)", param=True)
    s = Scalar("the plane's displacement along -normal (a pushed mass), m")
    s_dot = Scalar()
    normal_force = Scalar("N")
    mass = Scalar("kg (0: a fixed plane)", param=True)
    contact = Int()

    def __init__(self, point: Sequence[float], normal: Sequence[float], unilateral: bool) -> None:
        super().__init__()
        self.load_kind = HALF_SPACE
        self.p0[:], self.normal[:] = _vec(point), _unit(normal)
        self.unilateral = float(unilateral)
        self.contact = int(not unilateral)

    @property
    def in_contact(self) -> bool:
        return bool(self.contact)

    def force(self, t: float, x: Sequence[float], xd: Sequence[float]) -> tuple[float, ...]:
        """The force on the tool at (x, xd), N (also kept in ``last_force``)."""
        half_space_force(self.f, self.i, 0, 0, *_xyz(x), *_xyz(xd))
        return tuple(self.last_force.tolist())


class HalfPlaneContact(HalfSpaceLoad):
    """A fixed plane: unilateral (wall, foam) or bilateral (spring, damper)."""

    def __init__(self, spec: WallSpec | SpringSpec) -> None:
        super().__init__(spec.point_m, spec.normal, spec.kind in ("wall", "foam"))
        self.k, self.c = spec.stiffness_n_per_m, spec.damping_n_s_per_m


class PushedMass(HalfSpaceLoad):
    """A free mass m resting against the plane, pushed (or held, if attached) by the
    end-effector through a stiff contact spring-damper; it slides along -n without friction.
    At frequencies well below the contact resonance the end-effector feels Z_e = m s."""

    stateful = True

    def __init__(self, spec: MassSpec) -> None:
        super().__init__(spec.point_m, spec.normal, not spec.attached)
        self.mass = spec.mass_kg
        self.k, self.c = spec.contact_stiffness_n_per_m, spec.contact_damping_n_s_per_m

    def advance(self, dt: float) -> None:
        """Move the mass over dt under the last contact force (semi-implicit Euler)."""
        push_mass(self.f, 0, dt)

    # RK4 (``teleop_rt.hal.sim``) works on the state itself
    def state(self) -> tuple[float, float]:
        return (self.s, self.s_dot)

    def set_state(self, state: tuple[float, ...]) -> None:
        self.s, self.s_dot = state

    def derivative(self) -> tuple[float, float]:
        """d(s, s_dot)/dt under the force of the last evaluation."""
        return (self.s_dot, self.normal_force / self.mass)


@jit
def half_space_force(
    f: np.ndarray, i: np.ndarray, fo: int, io: int,
    x: float, y: float, z: float, vx: float, vy: float, vz: float,
) -> None:  # fmt: skip
    """The plane's (block at f[fo:], i[io:]) force on the tool at (x, y, z) moving at
    (vx, vy, vz) into ``last_force``; the contact flag into its int ``contact``."""
    Hs = HalfSpaceLoad.idx
    p0, normal, sc = fo + 3 * Hs.P0, fo + 3 * Hs.NORMAL, fo + 3 * Hs.N_VECTORS
    nx, ny, nz = f[normal], f[normal + 1], f[normal + 2]
    depth = (f[p0] - x) * nx + (f[p0 + 1] - y) * ny + (f[p0 + 2] - z) * nz - f[sc + Hs.S]
    rate = -(vx * nx + vy * ny + vz * nz) - f[sc + Hs.S_DOT]
    force = f[sc + Hs.K] * depth + f[sc + Hs.C] * rate
    if f[sc + Hs.UNILATERAL]:
        i[io + Hs.CONTACT] = depth > 0.0
        if not i[io + Hs.CONTACT] or force < 0.0:
            force = 0.0
    f[sc + Hs.NORMAL_FORCE] = force
    out = fo + 3 * Hs.LAST_FORCE
    f[out], f[out + 1], f[out + 2] = force * nx, force * ny, force * nz


@jit
def push_mass(f: np.ndarray, fo: int, dt: float) -> None:
    """The mass behind the plane (block at f[fo:]) feels the contact force's reaction along -n."""
    Hs = HalfSpaceLoad.idx
    sc = fo + 3 * Hs.N_VECTORS
    if f[sc + Hs.MASS] > 0.0:
        f[sc + Hs.S_DOT] += dt * f[sc + Hs.NORMAL_FORCE] / f[sc + Hs.MASS]
        f[sc + Hs.S] += dt * f[sc + Hs.S_DOT]


# --- the one place that dispatches on a load's kind ----------------------------------------------
# The plant's kernels (teleop_rt.hal.sim) walk a robot's loads through these: a new kind of load
# is a block above, its kernels, a branch in each function here, and its builder below.
# ``o`` holds the loads' block offsets (float, int) from block 1 on (block 0 is the plant).


@jit
def load_width(i: np.ndarray, o: np.ndarray, b: int) -> int:
    """Blocks the load at block b takes: a hand is followed by its trajectory."""
    return 2 if i[o[2 * b + 1] + Load.idx.LOAD_KIND] == HAND else 1


@jit
def advance_load(f: np.ndarray, i: np.ndarray, o: np.ndarray, b: int, h: float) -> None:
    """A stateful load's own integration step of h (a mass pushed behind a plane)."""
    if i[o[2 * b + 1] + Load.idx.LOAD_KIND] == HALF_SPACE:
        push_mass(f, o[2 * b], h)


@jit
def cartesian_load(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, b: int, t: float,
    x: float, y: float, z: float, vx: float, vy: float, vz: float,
) -> int:  # fmt: skip
    """A Cartesian load's force on the tool at (x, y, z) moving at (vx, vy, vz), at time t, into
    its block; the float index of that force (-1: not a Cartesian load)."""
    fo, io = o[2 * b], o[2 * b + 1]
    kind = i[io + Load.idx.LOAD_KIND]
    if kind == HAND:
        hand_force(f, fo, f, i, o[2 * b + 2], o[2 * b + 3], t, x, y, z, vx, vy, vz)
        return fo + 3 * ScriptedHand.idx.LAST_FORCE
    if kind == HALF_SPACE:
        half_space_force(f, i, fo, io, x, y, z, vx, vy, vz)
        return fo + 3 * HalfSpaceLoad.idx.LAST_FORCE
    return -1


@jit
def joint_load(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, b: int, n: int, t: float,
    q: int, v: int, out: int,
) -> None:  # fmt: skip
    """A joint load's torque at time t, joint state at f[q:], f[v:], added to f[out:]."""
    fo, io = o[2 * b], o[2 * b + 1]
    kind = i[io + Load.idx.LOAD_KIND]
    if kind != HAND and kind != HALF_SPACE:
        joint_load_torque(f, i, fo, io, n, t, q, v, out)


@jit
def snapshot_load(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, b: int, world: np.ndarray, contact: int
) -> int:
    """What the world snapshot shows of the load: a hand's reference and force (returns -1),
    an environment plane's contact flag at contact slot ``contact`` (returns its force's float
    index, to be summed), nothing of a joint load (returns -2)."""
    fo, io = o[2 * b], o[2 * b + 1]
    Ws, Hs = WorldSnapshot.idx, HalfSpaceLoad.idx  # (vectors of 3: vector k at 3 k)
    kind = i[io + Load.idx.LOAD_KIND]
    if kind == HAND:
        trajectory = o[2 * b + 2]
        pos, vel = trajectory + 3 * Trajectory.idx.POS, trajectory + 3 * Trajectory.idx.VEL
        force = fo + 3 * ScriptedHand.idx.LAST_FORCE
        for a in range(3):
            world[3 * Ws.REFERENCE + a] = f[pos + a]
            world[3 * Ws.REFERENCE_VELOCITY + a] = f[vel + a]
            world[3 * Ws.FORCE + a] = f[force + a]
        return -1
    if kind == HALF_SPACE:
        world[3 * Ws.N_VECTORS + contact] = 1.0 if i[io + Hs.CONTACT] else 0.0
        return fo + 3 * Hs.LAST_FORCE
    return -2


# --- building from the config -----------------------------------------------------------------
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
