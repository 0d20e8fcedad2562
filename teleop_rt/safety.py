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

from teleop_rt.config import SafetySpec
from teleop_rt.errors import SafetyStop
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


class Tracking:
    """Does a joint follow its commanded virtual dynamics? Under computed torque the measured
    acceleration (v[k] - v[k-1]) / dt equals the one commanded at k-1 (eq 3 / 13); a
    saturated or blocked actuator, or a wrong model, breaks that."""

    def __init__(self, n: int, dt: float) -> None:
        self.inv_dt = 1.0 / dt
        self.valid = False  # prev_v holds a fresh velocity
        self.prev_v = [0.0] * n
        self.prev_a = [0.0] * n
        self.run = [0] * n  # ticks in a row above the tolerance

    def update(self, v: list[float], a_cmd: list[float], tolerance: float) -> int | None:
        """Record this tick; return the joint that missed (over ``tolerance``), or None."""
        worst = None
        if self.valid:
            prev_v, prev_a, run, inv_dt = self.prev_v, self.prev_a, self.run, self.inv_dt
            longest = -1
            for j, vj in enumerate(v):
                error = (vj - prev_v[j]) * inv_dt - prev_a[j]
                r = run[j] + 1 if (error > tolerance or error < -tolerance) else 0
                run[j] = r
                if r > longest:
                    worst, longest = j, r
        self.prev_v[:] = v
        self.prev_a[:] = a_cmd
        self.valid = True
        return worst

    def reset(self) -> None:
        self.valid = False


class Supervisor:
    """Checks both robots every tick; saturates torques; raises SafetyStop on a violation."""

    def __init__(self, spec: SafetySpec, hsi: RobotModel, to: RobotModel, dt: float = 1e-3) -> None:
        self.spec = spec
        self.limits = {"hsi": RobotLimits(hsi, "hsi"), "to": RobotLimits(to, "to")}
        for lim in self.limits.values():
            lim.disable(
                not spec.position_limits, not spec.velocity_limits, spec.torque_limits == "off"
            )
        self.tracking = {"hsi": Tracking(hsi.nv, dt), "to": Tracking(to.nv, dt)}
        self.saturated_ticks = 0  # ticks in which at least one torque was saturated
        self.saturated_run = 0  # ... of them in a row, up to this tick

    def step(
        self,
        tick: int,
        hsi: tuple,
        to: tuple,
    ) -> None:
        """All of one tick's checks, in order (the tick path's single call): measurements of
        both robots, stale feedback and tracking, limits and commands, saturation. ``hsi``
        and ``to`` are (feedback, measured tau_ext, commanded torque, commanded a)."""
        if not self.spec.enabled:
            return
        fb_h, tau_h, g_h, a_h = hsi
        fb_t, tau_t, g_t, a_t = to
        if not math.isfinite(
            sum(fb_h.q_list) + sum(fb_h.v_list) + sum(tau_h)
            + sum(fb_t.q_list) + sum(fb_t.v_list) + sum(tau_t)
        ):  # fmt: skip
            self.check_measured(tick, "hsi", fb_h.q_list, fb_h.v_list, tau_h)
            self.check_measured(tick, "to", fb_t.q_list, fb_t.v_list, tau_t)
        self.check_feedback(tick, "hsi", fb_h.age_ticks, fb_h.v_list, a_h)
        self.check_feedback(tick, "to", fb_t.age_ticks, fb_t.v_list, a_t)
        saturated = self.check(tick, "hsi", fb_h.q_list, fb_h.v_list, tau_h, g_h)
        saturated = self.check(tick, "to", fb_t.q_list, fb_t.v_list, tau_t, g_t) or saturated
        if saturated or self.saturated_run:
            self.saturation(tick, saturated)

    def check_feedback(
        self, tick: int, name: str, age_ticks: int, v: list[float], a_cmd: list[float]
    ) -> None:
        """Stale sensors; a joint not following its commanded acceleration (last tick's)."""
        if not self.spec.enabled:
            return
        tracking = self.tracking[name]
        if age_ticks:
            tracking.reset()  # no fresh velocity: nothing to compare
            if age_ticks >= self.spec.stale_ticks:
                raise SafetyStop(
                    f"tick {tick}: {name} feedback stale for {age_ticks} ticks (sensor dropout)"
                )
            return
        ticks = self.spec.tracking_error_ticks
        if not ticks:
            return
        j = tracking.update(v, a_cmd, self.spec.tracking_error_rad_s2)
        if j is not None and tracking.run[j] >= ticks:
            self._stop(
                tick, name, j,
                f"does not follow its commanded acceleration (off by more than "
                f"{self.spec.tracking_error_rad_s2:g} rad/s^2 for {ticks} ticks: saturated or "
                "blocked actuator)",
            )  # fmt: skip

    def check_measured(
        self, tick: int, name: str, q: list[float], v: list[float], tau_ext: list[float]
    ) -> None:
        """Finite measurements: checked for both robots before any command is looked at, so a
        stop names the sensor at fault, not the command it poisoned through the channel."""
        if self.spec.enabled and not math.isfinite(sum(q) + sum(v) + sum(tau_ext)):
            self._non_finite(tick, name, q, v, tau_ext, [])

    def check(
        self,
        tick: int,
        name: str,
        q: list[float],
        v: list[float],
        tau_ext: list[float],
        tau_cmd: list[float],
    ) -> bool:
        """Check one robot's limits and its commands (its measurements were checked by
        ``check_measured``); saturate tau_cmd in place. True if it saturated."""
        if not self.spec.enabled:
            return False
        lim = self.limits[name]
        lo, hi, vmax, emax = lim.lo, lim.hi, lim.vmax, lim.emax
        saturated = False
        for j in range(len(q)):
            if not lo[j] <= q[j] <= hi[j]:
                self._stop(tick, name, j, f"angle {q[j]:.4g} rad outside [{lo[j]:g}, {hi[j]:g}]")
            if not -vmax[j] <= v[j] <= vmax[j]:
                self._stop(tick, name, j, f"speed {v[j]:.4g} rad/s above {vmax[j]:g}")
            c = tau_cmd[j]
            if not -emax[j] <= c <= emax[j]:  # also NaN
                if c != c:
                    self._stop(tick, name, j, "commanded torque is nan")
                if self.spec.torque_limits == "stop":
                    self._stop(tick, name, j, f"torque {c:.4g} N m above {emax[j]:g}")
                tau_cmd[j] = emax[j] if c > 0 else -emax[j]
                saturated = True
        return saturated

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

    def _non_finite(self, tick, name, q, v, tau_ext, tau_cmd) -> None:
        for signal, values in (("angle", q), ("speed", v), ("measured torque", tau_ext),
                               ("commanded torque", tau_cmd)):  # fmt: skip
            for j, x in enumerate(values):
                if not math.isfinite(x):
                    self._stop(tick, name, j, f"{signal} is {x}")

    def _stop(self, tick: int, name: str, joint: int, what: str) -> None:
        joint_name = self.limits[name].joint_names[joint]
        raise SafetyStop(f"tick {tick}: {name} joint {joint} ({joint_name}): {what}")
