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


class Supervisor:
    """Checks both robots every tick; saturates torques; raises SafetyStop on a violation."""

    def __init__(self, spec: SafetySpec, hsi: RobotModel, to: RobotModel) -> None:
        self.spec = spec
        self.limits = {"hsi": RobotLimits(hsi, "hsi"), "to": RobotLimits(to, "to")}
        self.saturated_ticks = 0  # ticks in which at least one torque was saturated
        self.saturated_run = 0  # ... of them in a row, up to this tick

    def check(
        self,
        tick: int,
        name: str,
        q: list[float],
        v: list[float],
        tau_ext: list[float],
        tau_cmd: list[float],
    ) -> bool:
        """Check one robot's tick; saturate tau_cmd in place. True if it saturated."""  # fmt: skip
        if not self.spec.enabled:
            return False
        if not math.isfinite(sum(q) + sum(v) + sum(tau_ext) + sum(tau_cmd)):
            self._non_finite(tick, name, q, v, tau_ext, tau_cmd)
        lim = self.limits[name]
        if self.spec.position_limits:
            for j, bounds in enumerate(lim.position):
                if bounds is not None and not bounds[0] <= q[j] <= bounds[1]:
                    self._stop(tick, name, j, f"angle {q[j]:.4g} rad outside [{bounds[0]:g}, "
                               f"{bounds[1]:g}]")  # fmt: skip
        if self.spec.velocity_limits:
            for j, vmax in enumerate(lim.velocity):
                if vmax is not None and abs(v[j]) > vmax:
                    self._stop(tick, name, j, f"speed {v[j]:.4g} rad/s above {vmax:g}")
        saturated = False
        if self.spec.torque_limits != "off":
            for j, emax in enumerate(lim.effort):
                if emax is not None and abs(tau_cmd[j]) > emax:
                    if self.spec.torque_limits == "stop":
                        self._stop(tick, name, j, f"torque {tau_cmd[j]:.4g} N m above {emax:g}")
                    tau_cmd[j] = emax if tau_cmd[j] > 0 else -emax
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
