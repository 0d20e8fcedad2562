"""The safety layer between the controllers and the backends (tick step 7).

Every tick, for both robots, before anything is written to a motor:

* every measured and commanded value must be finite (a NaN from a sensor or a diverging
  loop must never reach a motor);
* joint angles inside the URDF position limits and speeds inside the URDF velocity limits
  (where the URDF gives them: a zero limit means none);
* commanded torques inside the URDF effort limits: saturated (and counted) by default, or a
  stop (``safety.torque_limits: stop``); saturation lasting ``saturation_stop_ticks`` ticks in
  a row is a stop too.

A violation raises ``SafetyStop`` naming the tick, the robot, the joint and the reason; the
session then commands zero torque on both backends, finishes the log and ends (exit code 3).
"""

from __future__ import annotations

import math

import numpy as np

from teleop_rt.config import SafetySpec
from teleop_rt.errors import SafetyStop
from teleop_rt.hal.base import Feedback
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
        # the same as flat lists for the per-tick loop: infinite where there is no limit
        inf = math.inf
        self.lo = [b[0] if b else -inf for b in self.position]
        self.hi = [b[1] if b else inf for b in self.position]
        self.vmax = [x if x is not None else inf for x in self.velocity]
        self.emax = [x if x is not None else inf for x in self.effort]

    def clamp_effort(self, tau: list[float]) -> None:
        """Clamp torques in place to the URDF effort limits (whatever the safety spec says:
        the safe-stop reaction uses it)."""
        for j, emax in enumerate(self.effort):
            if emax is not None:
                tau[j] = min(max(tau[j], -emax), emax)

    def disable(self, position: bool, velocity: bool, effort: bool) -> None:
        """Switch off kinds of checks by making their limits infinite."""
        n = len(self.lo)
        if position:
            self.lo, self.hi = [-math.inf] * n, [math.inf] * n
        if velocity:
            self.vmax = [math.inf] * n
        if effort:
            self.emax = [math.inf] * n


class RobotGuard:
    """All of one robot's per-tick checks in one pass over its joints: limits, commands and
    tracking.

    Tracking: under computed torque the measured acceleration (v[k] - v[k-1]) / dt equals the
    one commanded at k-1 (eq 3 / 13); a saturated or blocked actuator, or a wrong model,
    breaks that for ``tracking_error_ticks`` ticks in a row."""

    def __init__(self, spec: SafetySpec, model: RobotModel, name: str, dt: float) -> None:
        self.name = name
        self.limits = RobotLimits(model, name)
        self.limits.disable(
            not spec.position_limits, not spec.velocity_limits, spec.torque_limits == "off"
        )
        self.stop_on_torque = spec.torque_limits == "stop"
        self.stale_ticks = spec.stale_ticks
        self.tolerance = spec.tracking_error_rad_s2
        self.tracking_ticks = spec.tracking_error_ticks
        self.inv_dt = 1.0 / dt
        n = model.nv
        self.tracking_valid = False  # prev_v holds a fresh velocity
        self.prev_v = [0.0] * n
        self.prev_a = [0.0] * n
        self.run = [0] * n  # ticks in a row above the tracking tolerance
        box = getattr(spec.workspace, name)
        self.model = model
        self.workspace = None
        if box is not None:  # (axis, lower, upper) for each bounded axis
            self.workspace = list(zip("xyz", box.lower_m, box.upper_m, strict=False))

    def check_measured(
        self, tick: int, q: list[float], v: list[float], tau_ext: list[float]
    ) -> None:
        """Finite measurements (checked for both robots before any command is looked at, so a
        stop names the sensor at fault, not the command it poisoned through the channel)."""
        if not math.isfinite(sum(q) + sum(v) + sum(tau_ext)):
            for signal, values in (("angle", q), ("speed", v), ("measured torque", tau_ext)):
                for j, x in enumerate(values):
                    if not math.isfinite(x):
                        self.stop(tick, j, f"{signal} is {x}")

    def check(self, tick: int, fb: Feedback, tau_cmd: list[float], a_cmd: list[float]) -> bool:
        """Stale feedback, limits, commands and tracking; saturates tau_cmd in place. True if a
        torque was saturated. a_cmd: the acceleration commanded this tick."""
        q, v = fb.q_list, fb.v_list
        track = self.tracking_ticks > 0
        if fb.age_ticks:
            self.tracking_valid = track = False  # no fresh velocity: nothing to compare
            if fb.age_ticks >= self.stale_ticks:
                raise SafetyStop(
                    f"tick {tick}: {self.name} feedback stale for {fb.age_ticks} ticks "
                    "(sensor dropout)"
                )
        lim = self.limits
        lo, hi, vmax, emax = lim.lo, lim.hi, lim.vmax, lim.emax
        prev_v, prev_a, run = self.prev_v, self.prev_a, self.run
        compare = track and self.tracking_valid
        tol, inv_dt = self.tolerance, self.inv_dt
        saturated = False
        for j in range(len(q)):
            if not lo[j] <= q[j] <= hi[j]:
                self.stop(tick, j, f"angle {q[j]:.4g} rad outside [{lo[j]:g}, {hi[j]:g}]")
            vj = v[j]
            if not -vmax[j] <= vj <= vmax[j]:
                self.stop(tick, j, f"speed {vj:.4g} rad/s above {vmax[j]:g}")
            if compare:
                error = (vj - prev_v[j]) * inv_dt - prev_a[j]
                if error > tol or error < -tol:
                    run[j] += 1
                    if run[j] >= self.tracking_ticks:
                        self.stop(tick, j, self._tracking_reason())
                else:
                    run[j] = 0
            c = tau_cmd[j]
            if not -emax[j] <= c <= emax[j]:  # also NaN
                if c != c:
                    self.stop(tick, j, "commanded torque is nan")
                if self.stop_on_torque:
                    self.stop(tick, j, f"torque {c:.4g} N m above {emax[j]:g}")
                tau_cmd[j] = emax[j] if c > 0 else -emax[j]
                saturated = True
        if track:
            prev_v[:] = v
            prev_a[:] = a_cmd
            self.tracking_valid = True
        if self.workspace is not None:
            self.check_workspace(tick, fb.q)
        return saturated

    def check_workspace(self, tick: int, q: np.ndarray) -> None:
        """The tool frame inside its workspace box (forward kinematics at the measured q)."""
        position = self.model.tool_position(q)
        for axis, (name, lower, upper) in enumerate(self.workspace):
            x = position[axis]
            if not lower <= x <= upper:
                raise SafetyStop(
                    f"tick {tick}: {self.name} tool frame '{self.model.ee_frame}' at {name} = "
                    f"{x:.4g} m, outside its workspace [{lower:g}, {upper:g}] m"
                )

    def _tracking_reason(self) -> str:
        return (
            f"does not follow its commanded acceleration (off by more than "
            f"{self.tolerance:g} rad/s^2 for {self.tracking_ticks} ticks: saturated or "
            "blocked actuator)"
        )

    def stop(self, tick: int, joint: int, what: str) -> None:
        """Raise the SafetyStop naming the tick, this robot and the joint."""
        raise SafetyStop(
            f"tick {tick}: {self.name} joint {joint} ({self.limits.joint_names[joint]}): {what}"
        )


class Supervisor:
    """Checks both robots every tick; saturates torques; raises SafetyStop on a violation."""

    def __init__(self, spec: SafetySpec, hsi: RobotModel, to: RobotModel, dt: float = 1e-3) -> None:
        self.spec = spec
        self.enabled = spec.enabled
        self.guards = {
            "hsi": RobotGuard(spec, hsi, "hsi", dt),
            "to": RobotGuard(spec, to, "to", dt),
        }
        self.limits = {name: guard.limits for name, guard in self.guards.items()}
        self.saturated_ticks = 0  # ticks in which at least one torque was saturated
        self.saturated_run = 0  # ... of them in a row, up to this tick

    def step(
        self,
        tick: int,
        fb_h: Feedback,
        tau_h: list[float],
        g_h: list[float],
        a_h: list[float],
        fb_t: Feedback,
        tau_t: list[float],
        g_t: list[float],
        a_t: list[float],
    ) -> None:
        """All of one tick's checks (the tick path's single call): per robot stale feedback,
        limits, commands and tracking, then saturation. A NaN or inf measurement always trips
        one of them (comparisons with NaN fail; a NaN torque sensor makes its command NaN), and
        the stop then names the measurement. For each robot: feedback, measured tau_ext,
        commanded torque (saturated in place), commanded acceleration."""
        if not self.enabled:
            return
        guard_h, guard_t = self.guards["hsi"], self.guards["to"]
        try:  # a non-finite value fails the limit comparisons or makes a command NaN
            saturated = guard_h.check(tick, fb_h, g_h, a_h)
            saturated = guard_t.check(tick, fb_t, g_t, a_t) or saturated
        except SafetyStop:
            # name the sensor at fault, not the command it poisoned (maybe through the channel)
            guard_h.check_measured(tick, fb_h.q_list, fb_h.v_list, tau_h)
            guard_t.check_measured(tick, fb_t.q_list, fb_t.v_list, tau_t)
            raise
        if saturated or self.saturated_run:
            self.saturation(tick, saturated)

    def saturation(self, tick: int, saturated: bool) -> None:
        """Count saturated ticks; stop when they last ``saturation_stop_ticks`` in a row."""
        if not saturated:
            self.saturated_run = 0
            return
        self.saturated_ticks += 1
        self.saturated_run += 1
        limit = self.spec.saturation_stop_ticks
        if limit and self.saturated_run >= limit:
            raise SafetyStop(
                f"tick {tick}: a motor torque has been at its effort limit for {limit} ticks "
                "in a row (unstable loop or blocked joint)"
            )
