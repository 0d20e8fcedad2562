"""The safety layer between the controllers and the backends (tick step 7): one guard per
site, checking its own robot.

Every tick, before anything is written to a motor:

* every measured value must be finite, checked when the site reads its sensors, before
  anything is computed or sent from them (``measured_fault``), and every commanded torque must
  be finite: a NaN from a sensor or a diverging loop never reaches a motor, whatever the config
  (``safety.enabled: false`` switches off the checks below, never these);
* joint angles inside the URDF position limits and speeds inside the URDF velocity limits
  (where the URDF gives them: a zero limit means none);
* commanded torques inside the URDF effort limits: saturated (and counted) by default, or a
  stop (``safety.torque_limits: stop``); saturation lasting ``saturation_stop_ticks`` ticks in
  a row is a stop too.

A violation raises ``SafetyStop`` naming the tick, the robot, the joint and the reason; the
session then brings both robots to rest and commands zero torque, finishes the log and ends
(exit code 3).
"""

from __future__ import annotations

import math
from collections import namedtuple
from collections.abc import Callable
from enum import IntEnum, unique
from typing import Any

import numpy as np

from teleop_rt.config import SafetySpec, SessionConfig, per_joint
from teleop_rt.errors import SafetyStop
from teleop_rt.flat import Block, Int, Scalar, Vector, as_floats, jit, vec
from teleop_rt.hal.signals import Feedback
from teleop_rt.model import RobotModel


class RobotLimits:
    """One robot's limits as lists (``None`` where the URDF gives none)."""

    def __init__(self, model: RobotModel, name: str) -> None:
        lo, hi = model.position_limits
        self.name = name
        self.joint_names = model.joint_names
        self.position = [
            (a, b) if math.isfinite(a) and math.isfinite(b) and a < b else None
            for a, b in zip(lo.tolist(), hi.tolist(), strict=True)
        ]
        self.velocity = [v if v > 0 else None for v in model.model.velocityLimit.tolist()]
        self.effort = [e if e > 0 else None for e in model.effort_limits.tolist()]


@unique
class Finding(IntEnum):
    """What a robot's compiled checks found, each declared once: its code (what the kernels
    return, as the compile-time constants of ``FOUND``; 0: nothing; the sites' own findings,
    ``mapping.PRESENCE_LOST`` and ``task_limits.TOOL_FORCE``, are from 200), its wording
    (``RobotGuard.stop_for`` formats it with the guard's figures: ``RobotGuard.wording``) and
    whether it names a joint (then "<robot> joint j (<name>): " comes first; else the text
    names the robot itself). MEASURED_*: a non-finite measurement; SATURATION: a torque at
    its limit for too long."""

    text: str
    joint: bool

    def __new__(cls, code: int, text: str = "", joint: bool = True) -> Finding:
        member = int.__new__(cls, code)
        member._value_ = code
        member.text, member.joint = text, joint
        return member

    OK = 0, ""
    STALE = 1, "{robot} feedback stale for {age_ticks} ticks (sensor dropout)", False
    ANGLE = 2, "angle {x:.4g} rad outside [{lo:g}, {hi:g}]"
    SPEED = 3, "speed {x:.4g} rad/s above {vmax:g}"
    TRACKING = 4, (
        "does not follow its commanded acceleration (off by more than {tolerance:g} rad/s^2 "
        "for {tracking_ticks} ticks: saturated or blocked actuator)"
    )
    TORQUE_NAN = 5, "commanded torque is {x}"
    TORQUE_LIMIT = 6, "torque {x:.4g} N m above {emax:g}"
    MEASURED_ANGLE = 7, "angle is {x}"
    MEASURED_SPEED = 8, "speed is {x}"
    MEASURED_TORQUE = 9, "measured torque is {x}"
    IMPLAUSIBLE_TORQUE = 10, (
        "measured torque {x:.4g} N m is implausible (above {tau_ext_max:.4g}: a sensor "
        "fault? safety.measured_torque_limit_nm)"
    )
    IMPLAUSIBLE_SPEED = 11, (
        "measured speed {x:.4g} rad/s is implausible (above {v_measured_max:.4g}: a sensor "
        "fault? safety.measured_velocity_limit_rad_s)"
    )
    SATURATION = 100, (
        "{robot}: a motor torque has been at its effort limit for {saturation_stop_ticks} "
        "ticks in a row (unstable loop or blocked joint)"
    ), False


# the codes as the kernels read them: a named tuple of ints, which numba folds into a kernel
# as constants (an IntEnum member is a type of its own there, which ``if code:`` refuses);
# made at run time, so typed Any (as ``Block.idx``)
_codes: Callable[..., Any] = namedtuple
FOUND: Any = _codes("FindingCodes", [x.name for x in Finding], module=__name__)(
    *(int(x) for x in Finding)
)

# default plausibility bounds of measurements, as multiples of the URDF's limits
MEASURED_TORQUE_FACTOR, MEASURED_VELOCITY_FACTOR = 3.0, 2.0


def safety_warnings(cfg: SessionConfig) -> list[str]:
    """What ``check`` and ``run`` should warn about in the config's safety section."""
    spec, out = cfg.safety, []
    if not spec.enabled:
        out.append(
            "safety.enabled is false: no limit, saturation, tracking or workspace checks; only "
            "non-finite or implausible measurements and non-finite torques still stop the robots"
        )
    elif spec.torque_limits == "off":
        out.append("safety.torque_limits is off: commanded torques are not bounded")
    return out


def plausible(
    given: float | list[float] | None, urdf: list[float | None], factor: float, n: int, key: str
) -> list[float]:
    """Per-joint plausibility bounds: the config's, else factor x the URDF limit (inf where the
    URDF gives none)."""
    values = per_joint(given, n, key)
    if values is not None:
        return values
    return [factor * x if x is not None else math.inf for x in urdf]


class RobotGuard(Block):
    """All of one robot's per-tick checks in one pass over its joints: limits, commands and
    tracking (compiled: ``guard_check``; this class sets it up and words its findings).

    Tracking: under computed torque the measured acceleration (v[k] - v[k-1]) / dt equals the
    one commanded at k-1 (eq 3 / 13); a saturated or blocked actuator, or a wrong model,
    breaks that for ``tracking_error_ticks`` ticks in a row."""

    lo = Vector("lower position limit, rad (-inf: none)", param=True)
    hi = Vector("upper position limit, rad (inf: none)", param=True)
    vmax = Vector("speed limit, rad/s", param=True)
    emax = Vector("effort limit, N m (inf: none, or torque_limits: off)", param=True)
    urdf_emax = Vector("the URDF's effort limit, N m, whatever the spec (the stop's)", param=True)
    prev_v = Vector("last tick's velocity (tracking)")
    prev_a = Vector("last tick's commanded acceleration (tracking)")
    run = Vector("ticks in a row off the commanded acceleration")
    tau_ext_max = Vector("plausible measured |tau_ext|, N m (inf: no bound)", param=True)
    v_measured_max = Vector("plausible measured |v|, rad/s (inf: no bound)", param=True)
    tolerance = Scalar("tracking tolerance, rad/s^2", param=True)
    inv_dt = Scalar(param=True)
    value = Scalar("the offending value of a finding")
    enabled = Int("0: only non-finite values are checked (safety.enabled: false)", param=True)
    stale_ticks = Int(param=True)
    tracking_ticks = Int(param=True)
    stop_on_torque = Int(param=True)
    saturation_stop_ticks = Int("saturation this long in a row is a stop (0: never)", param=True)
    tracking_valid = Int()
    joint = Int("the joint of a finding")
    saturated = Int("1: a torque was saturated this tick")
    saturated_run = Int("ticks in a row with a saturated torque")
    saturated_ticks = Int("ticks with a saturated torque")

    def __init__(self, spec: SafetySpec, model: RobotModel, name: str, dt: float) -> None:
        super().__init__(model.nv)
        self.name = name
        lim = self.limits = RobotLimits(model, name)
        # the checked limits: infinite where the URDF gives none or the spec switches them off
        inf = math.inf
        position = lim.position if spec.position_limits else [None] * self.n
        self.lo[:] = [b[0] if b else -inf for b in position]
        self.hi[:] = [b[1] if b else inf for b in position]
        velocity = lim.velocity if spec.velocity_limits else [None] * self.n
        self.vmax[:] = [x if x is not None else inf for x in velocity]
        effort = lim.effort if spec.torque_limits != "off" else [None] * self.n
        self.emax[:] = [x if x is not None else inf for x in effort]
        self.urdf_emax[:] = [x if x is not None else inf for x in lim.effort]
        self.tau_ext_max[:] = plausible(
            spec.measured_torque_limit_nm, lim.effort, MEASURED_TORQUE_FACTOR, self.n,
            "safety.measured_torque_limit_nm",
        )  # fmt: skip
        self.v_measured_max[:] = plausible(
            spec.measured_velocity_limit_rad_s, lim.velocity, MEASURED_VELOCITY_FACTOR, self.n,
            "safety.measured_velocity_limit_rad_s",
        )  # fmt: skip
        self.stop_on_torque = int(spec.torque_limits == "stop")
        self.enabled = int(spec.enabled)
        self.saturation_stop_ticks = spec.saturation_stop_ticks
        self.stale_ticks = spec.stale_ticks
        self.tolerance = spec.tracking_error_rad_s2
        self.tracking_ticks = spec.tracking_error_ticks
        self.inv_dt = 1.0 / dt
        box = getattr(spec.workspace, name)
        self.model = model
        self.workspace = None
        if box is not None:  # (axis, lower, upper) for each bounded axis
            self.workspace = list(zip("xyz", box.lower_m, box.upper_m, strict=False))

    def check_measured(self, tick: int, q, v, tau_ext) -> None:
        """Finite measurements (checked for both robots before any command is looked at, so a
        stop names the sensor at fault, not the command it poisoned through the channel)."""
        q, v, tau_ext = as_floats(q), as_floats(v), as_floats(tau_ext)
        code = measured_fault(self.f, self.i, self.n, q, v, tau_ext)
        if code:
            raise self.stop_for(tick, code, 0)

    def check(self, tick: int, fb: Feedback, tau_cmd, a_cmd) -> bool:
        """Stale feedback, limits, commands and tracking; saturates tau_cmd in place. True if a
        torque was saturated. a_cmd: the acceleration commanded this tick."""
        cmd = as_floats(tau_cmd)
        code = guard_check(self.f, self.i, self.n, fb.q, fb.v, fb.age_ticks, cmd, as_floats(a_cmd))
        tau_cmd[:] = cmd
        if code:
            raise self.stop_for(tick, code, fb.age_ticks)
        if self.workspace is not None:
            self.check_workspace(tick, fb.q)
        return bool(self.saturated)

    def motion_usable(self, q: np.ndarray, v: np.ndarray) -> bool:
        """Angles finite and speeds finite within the plausibility bounds: what the staged stop
        may act on (the checks ``measured_fault`` makes of them every tick)."""
        return motion_plausible(self.f, self.n, as_floats(q), as_floats(v))

    def force_plausible(self, tau_ext: np.ndarray) -> bool:
        """Measured external torques finite and within their plausibility bounds."""
        return force_plausible(self.f, self.n, as_floats(tau_ext))

    def follows(self, v: np.ndarray, prev_v: np.ndarray, prev_a: np.ndarray) -> bool:
        """The acceleration measured from ``prev_v`` to ``v`` within the tracking tolerance of
        the one commanded, ``prev_a``, on every joint (the tracking check's criterion)."""
        return follows_command(self.f, self.n, as_floats(v), prev_v, prev_a)

    def clamp_command(self, tau: np.ndarray) -> bool:
        """A staged stop's command: False if any torque is not finite (nothing may be written
        then), else clamped in place to the URDF effort limits, whatever the safety spec says
        (``torque_limits: off`` and ``enabled: false`` included)."""
        return clamp_to_effort(self.f, self.n, tau)

    def stop_for(self, tick: int, code: int, age_ticks: int) -> SafetyStop:
        """The SafetyStop that words a finding of the compiled checks (``Finding``)."""
        finding = Finding(code)
        text = finding.text.format(**self.wording(age_ticks, finding.joint))
        if finding.joint:
            j = self.joint
            text = f"{self.name} joint {j} ({self.limits.joint_names[j]}): {text}"
        return SafetyStop(f"tick {tick}: {text}")

    def wording(self, age_ticks: int, joint: bool) -> dict[str, Any]:
        """What a finding's text may name: the robot, the offending value ``x``, the counts and
        tolerances, and (a joint's finding) that joint's limits."""
        out: dict[str, Any] = {
            "robot": self.name, "x": self.value, "age_ticks": age_ticks,
            "tolerance": self.tolerance, "tracking_ticks": self.tracking_ticks,
            "saturation_stop_ticks": self.saturation_stop_ticks,
        }  # fmt: skip
        if joint:
            j = self.joint
            out.update({name: getattr(self, name)[j] for name in
                        ("lo", "hi", "vmax", "emax", "tau_ext_max", "v_measured_max")})  # fmt: skip
        return out

    def check_workspace(self, tick: int, q: np.ndarray) -> None:
        """The tool frame inside its workspace box (forward kinematics at the measured q)."""
        position = self.model.tool_position(q)
        for axis, (name, lower, upper) in enumerate(self.workspace or ()):
            x = position[axis]
            if not lower <= x <= upper:
                raise SafetyStop(
                    f"tick {tick}: {self.name} tool frame '{self.model.ee_frame}' at {name} = "
                    f"{x:.4g} m, outside its workspace [{lower:g}, {upper:g}] m"
                )


@jit
def _found(f: np.ndarray, i: np.ndarray, n: int, code: int, j: int, x: float) -> int:
    Rg = RobotGuard.idx
    i[Rg.JOINT] = j
    f[Rg.N_VECTORS * n + Rg.VALUE] = x
    return code


@jit
def measured_fault(
    f: np.ndarray, i: np.ndarray, n: int, q: np.ndarray, v: np.ndarray, tau_ext: np.ndarray
) -> int:
    """The first non-finite measurement (angle, speed, torque), then the first implausible one
    (torque, speed beyond the plausibility bounds), or FOUND.OK. One pass without slices in the
    common case (every tick of every site runs it); the finding's wording only on a fault."""
    Rg = RobotGuard.idx
    t0, v0 = Rg.TAU_EXT_MAX * n, Rg.V_MEASURED_MAX * n
    for j in range(n):
        tj, vj = tau_ext[j], v[j]
        if not (
            math.isfinite(q[j]) and -f[t0 + j] <= tj <= f[t0 + j] and -f[v0 + j] <= vj <= f[v0 + j]
        ):
            return _measured_finding(f, i, n, q, v, tau_ext)  # (a NaN fails the comparisons)
    return FOUND.OK


@jit
def _measured_finding(
    f: np.ndarray, i: np.ndarray, n: int, q: np.ndarray, v: np.ndarray, tau_ext: np.ndarray
) -> int:
    Rg = RobotGuard.idx
    j = _first_non_finite(q, n)
    if j >= 0:
        return _found(f, i, n, FOUND.MEASURED_ANGLE, j, q[j])
    j = _first_non_finite(v, n)
    if j >= 0:
        return _found(f, i, n, FOUND.MEASURED_SPEED, j, v[j])
    j = _first_non_finite(tau_ext, n)
    if j >= 0:
        return _found(f, i, n, FOUND.MEASURED_TORQUE, j, tau_ext[j])
    tmax, vmax = vec(f, Rg.TAU_EXT_MAX, n), vec(f, Rg.V_MEASURED_MAX, n)
    for j in range(n):
        if not -tmax[j] <= tau_ext[j] <= tmax[j]:
            return _found(f, i, n, FOUND.IMPLAUSIBLE_TORQUE, j, tau_ext[j])
        if not -vmax[j] <= v[j] <= vmax[j]:
            return _found(f, i, n, FOUND.IMPLAUSIBLE_SPEED, j, v[j])
    return FOUND.OK


@jit
def _first_non_finite(values: np.ndarray, n: int) -> int:
    for j in range(n):
        if not math.isfinite(values[j]):
            return j
    return -1


@jit
def motion_plausible(f: np.ndarray, n: int, q: np.ndarray, v: np.ndarray) -> bool:
    """Every angle finite, every speed finite and within its plausibility bound."""
    Rg = RobotGuard.idx
    v0 = Rg.V_MEASURED_MAX * n
    for j in range(n):
        if not (math.isfinite(q[j]) and -f[v0 + j] <= v[j] <= f[v0 + j]):  # (NaN fails)
            return False
    return True


@jit
def force_plausible(f: np.ndarray, n: int, tau_ext: np.ndarray) -> bool:
    """Every measured external torque within its plausibility bound (NaN fails)."""
    Rg = RobotGuard.idx
    t0 = Rg.TAU_EXT_MAX * n
    for j in range(n):
        if not -f[t0 + j] <= tau_ext[j] <= f[t0 + j]:
            return False
    return True


@jit
def follows_command(
    f: np.ndarray, n: int, v: np.ndarray, prev_v: np.ndarray, prev_a: np.ndarray
) -> bool:
    """(v - prev_v) / dt within the tracking tolerance of prev_a on every joint."""
    Rg = RobotGuard.idx
    s = Rg.N_VECTORS * n
    tol, inv_dt = f[s + Rg.TOLERANCE], f[s + Rg.INV_DT]
    for j in range(n):
        error = (v[j] - prev_v[j]) * inv_dt - prev_a[j]
        if not -tol <= error <= tol:
            return False
    return True


@jit
def clamp_to_effort(f: np.ndarray, n: int, tau: np.ndarray) -> bool:
    """False if a torque is not finite (tau untouched), else tau clamped to the URDF limits."""
    Rg = RobotGuard.idx
    for j in range(n):
        if not math.isfinite(tau[j]):
            return False
    emax = vec(f, Rg.URDF_EMAX, n)
    for j in range(n):
        tau[j] = min(max(tau[j], -emax[j]), emax[j])
    return True


@jit
def guard_check(
    f: np.ndarray,
    i: np.ndarray,
    n: int,
    q: np.ndarray,
    v: np.ndarray,
    age_ticks: int,
    tau_cmd: np.ndarray,
    a_cmd: np.ndarray,
) -> int:
    """One robot's checks; saturates tau_cmd in place (int ``saturated``: whether it did). Returns
    the finding (joint and value in the block) or FOUND.OK."""
    Rg = RobotGuard.idx
    track = i[Rg.TRACKING_TICKS] > 0
    i[Rg.SATURATED] = 0
    if age_ticks:
        i[Rg.TRACKING_VALID] = 0  # no fresh velocity: nothing to compare
        track = False
        if age_ticks >= i[Rg.STALE_TICKS]:
            return FOUND.STALE
    lo, hi, vmax, emax = vec(f, Rg.LO, n), vec(f, Rg.HI, n), vec(f, Rg.VMAX, n), vec(f, Rg.EMAX, n)
    prev_v, prev_a, run = vec(f, Rg.PREV_V, n), vec(f, Rg.PREV_A, n), vec(f, Rg.RUN, n)
    compare = track and i[Rg.TRACKING_VALID] != 0
    s = Rg.N_VECTORS * n
    tol, inv_dt = f[s + Rg.TOLERANCE], f[s + Rg.INV_DT]
    for j in range(n):
        qj, vj = q[j], v[j]
        if not lo[j] <= qj <= hi[j]:
            return _found(f, i, n, FOUND.ANGLE, j, qj)
        if not -vmax[j] <= vj <= vmax[j]:
            return _found(f, i, n, FOUND.SPEED, j, vj)
        if compare:
            error = (vj - prev_v[j]) * inv_dt - prev_a[j]
            if error > tol or error < -tol:
                run[j] += 1.0
                if run[j] >= i[Rg.TRACKING_TICKS]:
                    return _found(f, i, n, FOUND.TRACKING, j, error)
            else:
                run[j] = 0.0
        c = tau_cmd[j]
        if not math.isfinite(c):  # first: an inf passes torque_limits: off's infinite limit
            return _found(f, i, n, FOUND.TORQUE_NAN, j, c)
        if not -emax[j] <= c <= emax[j]:
            if i[Rg.STOP_ON_TORQUE]:
                return _found(f, i, n, FOUND.TORQUE_LIMIT, j, c)
            tau_cmd[j] = emax[j] if c > 0 else -emax[j]
            i[Rg.SATURATED] = 1
    if track:
        for j in range(n):
            prev_v[j] = v[j]
            prev_a[j] = a_cmd[j]
        i[Rg.TRACKING_VALID] = 1
    return FOUND.OK


@jit
def guard_site(
    f: np.ndarray, i: np.ndarray, n: int, q: np.ndarray, v: np.ndarray, age_ticks: int,
    tau_cmd: np.ndarray, a_cmd: np.ndarray,
) -> int:  # fmt: skip
    """A site's checks of its commands, after its measurements passed ``measured_fault``: with
    safety on, ``guard_check`` and the saturation run; with it off, still no non-finite torque
    reaches the motors (whatever the config)."""
    Rg = RobotGuard.idx
    if not i[Rg.ENABLED]:
        for j in range(n):
            if not math.isfinite(tau_cmd[j]):
                return _found(f, i, n, FOUND.TORQUE_NAN, j, tau_cmd[j])
        return FOUND.OK
    code = guard_check(f, i, n, q, v, age_ticks, tau_cmd, a_cmd)
    if code != FOUND.OK:
        return code
    if i[Rg.SATURATED]:
        i[Rg.SATURATED_TICKS] += 1
        i[Rg.SATURATED_RUN] += 1
        limit = i[Rg.SATURATION_STOP_TICKS]
        if limit and i[Rg.SATURATED_RUN] >= limit:
            return FOUND.SATURATION
    else:
        i[Rg.SATURATED_RUN] = 0
    return FOUND.OK


def check_all(
    guard: RobotGuard, tick: int, fb: Feedback, tau_ext, tau_cmd: np.ndarray, a_cmd
) -> None:
    """One robot's checks of a tick as a site runs them (standalone use: tests): measured
    values, then the workspace, limits, commands, tracking and saturation (tau_cmd saturated in
    place); SafetyStop on a finding."""
    code = measured_fault(guard.f, guard.i, guard.n, fb.q, fb.v, as_floats(tau_ext))
    if code:
        raise guard.stop_for(tick, code, fb.age_ticks)
    if guard.workspace is not None and guard.enabled:
        guard.check_workspace(tick, fb.q)
    code = guard_site(
        guard.f, guard.i, guard.n, fb.q, fb.v, fb.age_ticks, tau_cmd, as_floats(a_cmd)
    )
    if code:
        raise guard.stop_for(tick, code, fb.age_ticks)
