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

import math

import numpy as np

from teleop_rt.config import ControllerSpec, per_joint
from teleop_rt.flat import Block, Int, Scalar, Vector, as_floats, jit, vec
from teleop_rt.model import RobotModel, friction_torque


class ComputedTorque(Block):
    """Input-output linearisation to diagonal virtual masses (eq 2 / 12).

    ``g = M(q) M_v^-1 a_ref + n(q, v) - tau_ext``, evaluated as one RNEA call with the
    acceleration ``M_v^-1 a_ref`` (equal to M a + n, without forming M); the model's joint
    friction is added when ``compensate_friction`` (it belongs to the paper's n). The tick runs
    ``ct_prepare`` (a_des), Pinocchio's RNEA on a_des, then ``ct_finish`` (tau).
    """

    inv_mass = Vector("M_v^-1 per joint, 1/(kg m^2)", param=True)
    a_des = Vector("M_v^-1 a_ref: the acceleration RNEA is evaluated at, rad/s^2")
    tau = Vector("the motor torque, N m")
    damping = Vector("the model's viscous friction, N m s/rad", param=True)
    coulomb = Vector("the model's Coulomb friction, N m", param=True)
    inv_v_s = Scalar("1 / the Coulomb smoothing speed", param=True)
    compensate_friction = Int("1: the model's friction is added", param=True)

    def __init__(
        self, model: RobotModel, virtual_mass: list[float], compensate_friction: bool
    ) -> None:
        super().__init__(model.nv)
        self.model = model
        self.inv_mass[:] = [1.0 / float(m) for m in virtual_mass]
        self.damping[:] = model.damping
        self.coulomb[:] = model.coulomb
        self.inv_v_s = model.inv_v_s
        self.compensate_friction = int(compensate_friction)

    def step(self, q: np.ndarray, v: np.ndarray, a_ref, tau_ext) -> np.ndarray:
        """Motor torques for the reference acceleration; returns self.tau (updated in place)."""
        ct_prepare(self.f, self.n, as_floats(a_ref))
        rnea = self.model.rnea(q, v, self.a_des)
        ct_finish(self.f, self.i, self.n, rnea, as_floats(tau_ext), as_floats(v))
        return self.tau


@jit
def ct_prepare(f: np.ndarray, n: int, a_ref: np.ndarray) -> None:
    """a_des = M_v^-1 a_ref: the acceleration RNEA is evaluated at."""
    Ct = ComputedTorque.idx
    inv_m, a_des = vec(f, Ct.INV_MASS, n), vec(f, Ct.A_DES, n)
    for j in range(n):
        a_des[j] = a_ref[j] * inv_m[j]


@jit
def ct_finish(
    f: np.ndarray, i: np.ndarray, n: int, rnea: np.ndarray, tau_ext: np.ndarray, v: np.ndarray
) -> None:
    """tau = RNEA(q, v, a_des) - tau_ext (+ the model's friction at v)."""
    Ct = ComputedTorque.idx
    tau = vec(f, Ct.TAU, n)
    for j in range(n):
        tau[j] = rnea[j] - tau_ext[j]
    if i[Ct.COMPENSATE_FRICTION]:
        damping, coulomb = vec(f, Ct.DAMPING, n), vec(f, Ct.COULOMB, n)
        inv_v_s = f[Ct.N_VECTORS * n + Ct.INV_V_S]
        for j in range(n):
            tau[j] += friction_torque(damping[j], coulomb[j], inv_v_s, v[j])


class Pid(Block):
    """Per-joint P or PID law on an error signal, discretised with the tick period dt.

    ``out = kp e + I + kd D`` where I integrates ``ki e`` (forward Euler) and D is the
    derivative of e through a first-order filter with time constant ``derivative_filter_s``
    (a backward difference when 0). Anti-windup: I is clamped to +-integral_limit, and it is
    not integrated further while the output sits at +-output_limit in the direction of e.
    Continuous-time equivalent: C(s) = kp + ki/s + kd s / (1 + derivative_filter_s s).
    Absent limits are stored as infinite ones.
    """

    out = Vector("the controller's output: M_v a_ref, N m")
    kp = Vector(param=True)
    ki = Vector(param=True)
    kd = Vector(param=True)
    integral_limit = Vector(param=True)
    output_limit = Vector(param=True)
    integral = Vector("I")
    deriv = Vector("the filtered derivative of the error")
    prev_error = Vector()
    saturated = Vector("1.0 where the output is at its limit")
    dt = Scalar(param=True)
    d_alpha = Scalar("derivative filter coefficient", param=True)
    proportional_only = Int(param=True)
    has_i = Int(param=True)
    has_d = Int(param=True)
    started = Int()

    def __init__(self, spec: ControllerSpec, n: int, dt: float, key: str) -> None:
        super().__init__(n)
        self.kp[:] = per_joint(spec.kp, n, f"{key}.kp")
        self.ki[:] = per_joint(spec.ki, n, f"{key}.ki")
        self.kd[:] = per_joint(spec.kd, n, f"{key}.kd")
        integral_limit = per_joint(spec.integral_limit, n, f"{key}.integral_limit")
        output_limit = per_joint(spec.output_limit, n, f"{key}.output_limit")
        self.integral_limit[:] = integral_limit or [math.inf] * n
        self.output_limit[:] = output_limit or [math.inf] * n
        self.has_i = int(self.ki.any())
        self.has_d = int(self.kd.any())
        self.proportional_only = int(not (self.has_i or self.has_d or output_limit))
        self.dt = dt
        # filtered derivative: d_k = a d_{k-1} + (1 - a) (e_k - e_{k-1}) / dt
        self.d_alpha = spec.derivative_filter_s / (spec.derivative_filter_s + dt)

    def reset(self) -> None:
        for arr in (self.integral, self.deriv, self.prev_error, self.saturated):
            arr[:] = 0.0
        self.started = 0

    def step(self, error) -> np.ndarray:
        """Controller output for this tick's error; returns self.out (updated in place)."""
        pid_step(self.f, self.i, self.n, as_floats(error))
        return self.out


@jit
def pid_step(f: np.ndarray, i: np.ndarray, n: int, error: np.ndarray) -> None:
    Pd = Pid.idx
    out, kp = vec(f, Pd.OUT, n), vec(f, Pd.KP, n)
    if i[Pd.PROPORTIONAL_ONLY]:
        for j in range(n):
            out[j] = kp[j] * error[j]
        return
    ki, kd = vec(f, Pd.KI, n), vec(f, Pd.KD, n)
    i_lim, o_lim = vec(f, Pd.INTEGRAL_LIMIT, n), vec(f, Pd.OUTPUT_LIMIT, n)
    integral, deriv, prev = vec(f, Pd.INTEGRAL, n), vec(f, Pd.DERIV, n), vec(f, Pd.PREV_ERROR, n)
    sat = vec(f, Pd.SATURATED, n)
    dt, d_alpha = f[Pd.N_VECTORS * n + Pd.DT], f[Pd.N_VECTORS * n + Pd.D_ALPHA]
    has_i, has_d = i[Pd.HAS_I] != 0, i[Pd.HAS_D] != 0
    if not i[Pd.STARTED]:
        for j in range(n):
            prev[j] = error[j]
        i[Pd.STARTED] = 1
    for j in range(n):
        e = error[j]
        u = kp[j] * e + integral[j]
        if has_d:
            deriv[j] = d_alpha * deriv[j] + (1.0 - d_alpha) * (e - prev[j]) / dt
            prev[j] = e
            u += kd[j] * deriv[j]
        saturated = False
        lim = o_lim[j]
        if u > lim or u < -lim:
            saturated = True
            u = lim if u > 0 else -lim
        sat[j] = 1.0 if saturated else 0.0
        out[j] = u
        if has_i and not (saturated and (u > 0) == (e > 0)):
            # conditional integration: hold I while saturated in the direction of e
            i_new = integral[j] + ki[j] * e * dt
            lim = i_lim[j]
            integral[j] = min(max(i_new, -lim), lim)
