"""Controllers of the paper: computed torque (eq 2, 12), torque control C1 (eq 4) on the HSI and
velocity control C2 (eq 14) on the TO. Each ``step`` writes into an output array it is given.

Sign convention (the one place it is written; ``tests/test_displayed_impedance_sign.py`` checks it
against eq 20-24):

* ``tau_ext`` of a robot is the joint torque the outside world applies TO the robot, so its
  dynamics read ``M(q) a + n(q, v) = g + tau_ext`` (``g``: motor torque). The paper writes
  ``M a + n = g - tau_o``, i.e. its tau_o and tau_e are the torques the robot applies to the
  operator / environment: ``tau_o = -tau_ext``.
* HSI: ``tau_h = tau_ext_h`` is the torque the operator applies to the HSI (positive pushes the
  joint positive). Impedances are "torque needed to move a port at omega", so the operator feels
  the channel impedance when ``tau_h`` equals the channel torque ``tau_c``. C1 therefore acts on
  ``tau_h - tau_c``: ``M1 a_h = C1(tau_h - tau_c)``. With the paper's damper operator
  (a damper from the HSI to the ground, ``tau_h = -Z_o v_h``) this gives exactly
  ``tau_h = G_tau tau_c`` with eq 21's ``G_tau = C1 Z_o / (s M1 + C1 Z_o)``.
  (The paper's own ``C1(tau_c - tau_h)`` holds with its opposite sign of tau_h; read with this
  file's sign it would be positive feedback in contact.)
* TO: ``tau_t = tau_e = -tau_ext_t`` is the torque the TO applies to the environment (for a
  spring environment ``tau_e = k q``), and ``M2 a_t = C2(omega_t - v_t)``.
* Computed torque cancels the measured external torque: ``g = M M_v^-1 a_ref + n - tau_ext``,
  so ``a = M_v^-1 a_ref`` whatever the operator or environment does (eq 3, 13).
"""

from __future__ import annotations

import numpy as np

from teleop_rt.config import ControllerSpec, per_joint
from teleop_rt.model import RobotModel
from teleop_rt.scalar import shared_vector


class ComputedTorque:
    """Input-output linearisation to diagonal virtual masses (eq 2 / 12).

    ``g = M(q) M_v^-1 a_ref + n(q, v) - tau_ext``, evaluated as one RNEA call with the
    acceleration ``M_v^-1 a_ref`` (equal to M a + n, without forming M); the model's joint
    friction is added when ``compensate_friction`` (it belongs to the paper's n).
    """

    def __init__(
        self, model: RobotModel, virtual_mass: list[float], compensate_friction: bool
    ) -> None:
        self.model = model
        self.inv_mass = [1.0 / float(m) for m in virtual_mass]
        self.compensate_friction = compensate_friction
        self.n = model.nv
        self.a_des, self._a_des_view = shared_vector(model.nv)  # Pinocchio input
        self.a_des_list = [0.0] * model.nv  # the same, for the scalar path (safety tracking)
        self.tau = [0.0] * model.nv

    def step(
        self,
        q: np.ndarray,
        v: np.ndarray,
        a_ref: list[float],
        tau_ext: list[float],
        v_list: list[float],
    ) -> list[float]:
        """Motor torques for the reference acceleration; returns self.tau (updated in place).

        q, v (numpy) feed Pinocchio; v_list is the same v as a list for the friction term."""
        a_des, a_list, inv_m = self._a_des_view, self.a_des_list, self.inv_mass
        for j in range(self.n):
            a_list[j] = a_des[j] = a_ref[j] * inv_m[j]
        rnea = self.model.rnea(q, v, self.a_des)
        tau = self.tau
        if self.compensate_friction:
            fric = self.model.friction(v_list)
            for j in range(self.n):
                tau[j] = rnea[j] - tau_ext[j] + fric[j]
        else:
            for j in range(self.n):
                tau[j] = rnea[j] - tau_ext[j]
        return tau


class Pid:
    """Per-joint P or PID law on an error signal, discretised with the tick period dt.

    ``out = kp e + I + kd D`` where I integrates ``ki e`` (forward Euler) and D is the
    derivative of e through a first-order filter with time constant ``derivative_filter_s``
    (a backward difference when 0). Anti-windup: I is clamped to +-integral_limit, and it is
    not integrated further while the output sits at +-output_limit in the direction of e.
    Continuous-time equivalent: C(s) = kp + ki/s + kd s / (1 + derivative_filter_s s).
    """

    def __init__(self, spec: ControllerSpec, n: int, dt: float, key: str) -> None:
        self.n = n
        self.kp = per_joint(spec.kp, n, f"{key}.kp")
        self.ki = per_joint(spec.ki, n, f"{key}.ki")
        self.kd = per_joint(spec.kd, n, f"{key}.kd")
        self.has_i = any(self.ki)
        self.has_d = any(self.kd)
        self.integral_limit = per_joint(spec.integral_limit, n, f"{key}.integral_limit")
        self.output_limit = per_joint(spec.output_limit, n, f"{key}.output_limit")
        self.proportional_only = not (self.has_i or self.has_d or self.output_limit)
        self.dt = dt
        # filtered derivative: d_k = a d_{k-1} + (1 - a) (e_k - e_{k-1}) / dt
        self.d_alpha = spec.derivative_filter_s / (spec.derivative_filter_s + dt)
        self.integral = [0.0] * n
        self.deriv = [0.0] * n
        self.prev_error = [0.0] * n
        self.saturated = [False] * n
        self.out = [0.0] * n
        self._started = False

    def reset(self) -> None:
        for arr in (self.integral, self.deriv, self.prev_error):
            arr[:] = [0.0] * self.n
        self.saturated[:] = [False] * self.n
        self._started = False

    def step(self, error: list[float]) -> list[float]:
        """Controller output for this tick's error; returns self.out (updated in place)."""
        out, kp = self.out, self.kp
        if self.proportional_only:
            for j in range(self.n):
                out[j] = kp[j] * error[j]
            return out
        if not self._started:
            self.prev_error[:] = error
            self._started = True
        for j in range(self.n):
            e = error[j]
            u = kp[j] * e + self.integral[j]
            if self.has_d:
                self.deriv[j] = (
                    self.d_alpha * self.deriv[j]
                    + (1.0 - self.d_alpha) * (e - self.prev_error[j]) / self.dt
                )
                self.prev_error[j] = e
                u += self.kd[j] * self.deriv[j]
            saturated = False
            if self.output_limit is not None:
                lim = self.output_limit[j]
                if u > lim or u < -lim:
                    saturated = True
                    u = lim if u > 0 else -lim
            self.saturated[j] = saturated
            out[j] = u
            if self.has_i and not (saturated and (u > 0) == (e > 0)):
                # conditional integration: hold I while saturated in the direction of e
                i_new = self.integral[j] + self.ki[j] * e * self.dt
                if self.integral_limit is not None:
                    lim = self.integral_limit[j]
                    i_new = min(max(i_new, -lim), lim)
                self.integral[j] = i_new
        return out
