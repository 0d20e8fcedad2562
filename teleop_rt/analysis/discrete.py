"""Exact discrete-time (z-domain) displayed impedance of the 1 kHz open chain as implemented.

The continuous model (``teleop_rt.analysis.impedance``, eq 19-32) describes the paper's chain;
this module describes what the project's blocks compute tick by tick, so a measurement of the
running loop (``teleop_rt.analysis.bode``) must match it to round-off once transients are gone.
Same ports, units and sign convention as the continuous module; same ``ImpedanceParams``
(``delay_model`` is ignored: the delay is exactly D = delay_s / dt whole ticks).

Tick k of the open chain (``bode.OpenChain``): every block reads the state at the start of the
tick, its output acts during [k, k+1]. Notation: x[k] at tick k, X(z) its z-transform,
z = exp(j omega dt) on the unit circle.

* Plants under computed torque, semi-implicit Euler with one sub-step: the cancellation of
  M, n, friction and the measured tau_ext is exact (the loads act during the tick with the
  torque the sensor read at its start), so per joint ``v[k+1] = v[k] + dt a[k]``,
  ``q[k+1] = q[k] + dt v[k+1]``, a[k] = a_ref[k] / M_v. Hence
  ``V = (dt / (z - 1)) A``: the plant integrates with ``s_f = (z - 1) / dt`` (forward Euler),
  and ``Q = (dt z / (z - 1)) V``: the position integrates with ``s_b = (1 - 1/z) / dt``
  (backward Euler).
* Controllers (``teleop_rt.control.Pid``): out[k] = kp e[k] + I[k] + kd d[k] with
  I[k+1] = I[k] + ki dt e[k] and d[k] = a d[k-1] + (1 - a)(e[k] - e[k-1]) / dt,
  a = T_f / (T_f + dt), so ``C(z) = kp + ki dt / (z - 1) + kd (1 - a) s_b / (1 - a/z)``.
* HSI, damper operator sampled at tick k: tau_h[k] = -Z_o v_h[k]; M1 s_f V_h = C1 (tau_h - tau_c).
  Eliminating V_h = -tau_h / Z_o: ``G_tau(z) = C1 Z_o / (M1 s_f + C1 Z_o)`` (eq 21 with s -> s_f).
* TO: M2 s_f V_t = C2 (omega_t - V_t), so ``G_omega(z) = C2 / (M2 s_f + C2)`` (eq 24, s -> s_f).
* Environment at tick start (``world.JointSpringDamper``, ``world.JointMass``):
  tau_e[k] = k (q[k] - q0) + c v[k] + m (v[k] - v[k-1]) / dt, so
  ``Z_e(z) = m s_b + c + k / s_b`` and ``Z_t(z) = G_omega Z_e``.
* Channel (``teleop_rt.com.wave``), both sides algebraic within a tick, the received waves
  delayed by D ticks and filtered by y[k] = y[k-1] + alpha (x[k] - y[k-1]),
  alpha = 1 - exp(-2 pi f_c dt): ``F(z) = alpha / (1 - (1 - alpha) / z)``. At the TO side
  v_r = Gamma_t u_r with Gamma_t = (b - Z_t)/(b + Z_t); u_r = F z^-D u_l, v_l = F z^-D v_r, so
  v_l = Gamma u_l with ``Gamma = F^2 z^-2D Gamma_t`` and, from u_l, v_l (eq 9),
  ``Z_c = b (1 - Gamma)/(1 + Gamma)`` = b (Z_t + b t)/(b + Z_t t), t = (1 - R)/(1 + R),
  R = F^2 z^-2D. With D = 0 the channel couples directly and has no filter: Z_c = Z_t.
* Displayed: ``Z_h(z) = G_tau(z) Z_c(z)``, exactly eq 20 with the substitutions above.

Two lines: the continuous model with s -> s_f = (z-1)/dt in the plants (G_tau, G_omega), s -> s_b
= (1-1/z)/dt in the environment and the controllers' I/D parts, and e^{-2 T_d s} F(s)^2 replaced
by z^-2D F(z)^2. Each substitution differs from s by O(omega dt): the continuous model is off
by a few 0.1 % at 10 rad/s, except through the filter, whose DC group delay (1 - alpha) dt /
alpha is half a tick shorter than 1 / (2 pi f_c): with the filter on, a continuous model with
the nominal f_c displays the mass b (T_d + 1/(2 pi f_c)), too large by about
dt / (2 (T_d + 1/(2 pi f_c))) at every frequency (2 % at T_d = 20 ms, 4.9 % at 5 ms). A
continuous filter with the matched cut-off ``matched_filter_hz`` = alpha / (2 pi (1 - alpha) dt)
(33.0 Hz for 30 Hz at 1 kHz) has the same DC group delay and removes it (0.02 % at 10 rad/s);
``continuous_params`` gives the continuous model of the sampled chain with it.

Stability (``spectral_radius``): the open chain's modes are the roots of the HSI loop polynomial
(denominator of G_tau) and of the channel-TO polynomial
``(b D_t + N_t) F_d^2 z^2D + F_n^2 (b D_t - N_t)`` (Z_t = N_t / D_t, F = F_n / F_d). With a
root outside the unit circle the chain rings up and the frequency response is not what a
measurement sees. Found this way (paper gains, b = 2): without the received-wave filter every
joint spring behind any delay rings up (Re Z_t < 0 and a lossless channel), with the 30 Hz
filter soft springs can still ring (k_e = 20 N m/rad at 50 ms, 40 at 20 ms) unless damped
(c_e >= k_e M2 / c2 makes G_omega Z_e passive in continuous time, and these settle).

Settling (``window_decay``): a measurement locks in over windows of N ticks; a mode z adds to
window k a leak c z^(kN), so the estimate moves by c z^(kN) (z^N - 1) from one window to the
next and is still c z^(kN) off its limit: at most r / (1 - r) times the last change, with
r = |z|^N. Modes on the unit circle that are periodic over the window (z^N = 1) leak nothing.
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numpy.polynomial import Polynomial
from numpy.typing import ArrayLike

from teleop_rt.analysis.impedance import (
    AnalysisParamError,
    Complex,
    ControllerGains,
    ImpedanceParams,
    ImpedanceParts,
)

DT = 1e-3


# the same factors as the continuous model, each over omega
DiscreteParts = ImpedanceParts


def delay_ticks(delay_s: float, dt: float = DT) -> int:
    """The one-way delay in whole ticks; AnalysisParamError if delay_s is not a whole number."""
    ticks = delay_s / dt
    if abs(ticks - round(ticks)) > 1e-6:
        raise AnalysisParamError(f"delay {delay_s} s is not a whole number of {dt:g} s ticks")
    return round(ticks)


def filter_alpha(cutoff_hz: float | None, dt: float = DT) -> float | None:
    """alpha of the channel's received-wave low-pass (None: no filter)."""
    return None if cutoff_hz is None else 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * dt)


def filter_group_delay_s(cutoff_hz: float | None, dt: float = DT) -> float:
    """DC group delay (1 - alpha) dt / alpha of the sampled received-wave low-pass, s (0: none).

    Half a tick shorter than the 1 / (2 pi f_c) of the continuous filter of the same cut-off.
    """
    alpha = filter_alpha(cutoff_hz, dt)
    return 0.0 if alpha is None else (1.0 - alpha) * dt / alpha


def matched_filter_hz(cutoff_hz: float | None, dt: float = DT) -> float | None:
    """Cut-off (Hz) of the continuous first-order low-pass with the DC group delay of the sampled
    one, y += alpha (x - y): alpha / (2 pi (1 - alpha) dt) = (e^(2 pi f_c dt) - 1) / (2 pi dt).

    Why: the continuous model with the nominal f_c delays each wave by half a tick more than the
    1 kHz filter does, which the displayed mass b (T_d + filter delay) shows as a few per cent
    (module doc); with this cut-off the two agree to O((omega dt)^2). None: no filter.
    """
    if cutoff_hz is None:
        return None
    if not cutoff_hz > 0:
        raise AnalysisParamError(f"wave filter cut-off must be > 0 Hz, got {cutoff_hz}")
    return math.expm1(2.0 * math.pi * cutoff_hz * dt) / (2.0 * math.pi * dt)


def continuous_params(params: ImpedanceParams, dt: float = DT) -> ImpedanceParams:
    """The continuous model (eq 20) of the chain sampled at dt: exact delay, the wave filter at
    its matched cut-off, and no filter at zero delay (the channel then couples directly and
    has no received waves to filter)."""
    filt = params.wave_filter_hz if delay_ticks(params.delay_s, dt) > 0 else None
    return replace(params, delay_model="exact", wave_filter_hz=matched_filter_hz(filt, dt))


def _gains(c: ControllerGains | float) -> ControllerGains:
    return c if isinstance(c, ControllerGains) else ControllerGains(kp=float(c))


def controller_z(z: Complex, c: ControllerGains | float, dt: float = DT) -> Complex:
    """C(z) of ``teleop_rt.control.Pid`` (forward-Euler integral, filtered backward difference)."""
    g = _gains(c)
    out = g.kp + 0.0 * z
    if g.ki:
        out = out + g.ki * dt / (z - 1.0)
    if g.kd:
        a = g.derivative_filter_s / (g.derivative_filter_s + dt)
        out = out + g.kd * (1.0 - a) * (1.0 - 1.0 / z) / (dt * (1.0 - a / z))
    return out


def displayed_impedance_parts_z(
    omega: ArrayLike, params: ImpedanceParams, dt: float = DT
) -> DiscreteParts:
    """All factors of the discrete displayed impedance at omega (rad/s), see the module doc."""
    p = params
    w = np.asarray(omega, dtype=float)
    z = np.exp(1j * w * dt)
    s_f = (z - 1.0) / dt
    s_b = -np.expm1(-1j * w * dt) / dt  # (1 - 1/z) / dt without cancellation
    c1, c2 = controller_z(z, p.c1, dt), controller_z(z, p.c2, dt)
    g_tau = c1 * p.z_o / (p.m1 * s_f + c1 * p.z_o)
    g_omega = c2 / (p.m2 * s_f + c2)
    z_e = p.env_mass * s_b + p.env_damping + 0.0 * z
    if p.env_stiffness:
        z_e = z_e + p.env_stiffness / s_b
    z_t = g_omega * z_e
    d = delay_ticks(p.delay_s, dt)
    if d == 0:
        z_c = z_t
    else:
        # t = (1 - R)/(1 + R), R = F^2 z^-2D; 1 - R in closed form (no cancellation at low omega)
        one_minus_e = -np.expm1(-2j * d * w * dt)
        alpha = filter_alpha(p.wave_filter_hz, dt)
        if alpha is None:
            f2, one_minus_f2 = 1.0 + 0.0 * z, 0.0 * z
        else:
            f = alpha / (1.0 - (1.0 - alpha) / z)
            # 1 - F = (1 - alpha)(1 - 1/z) / (1 - (1 - alpha)/z) = (1 - alpha) dt s_b F / alpha
            one_minus_f = (1.0 - alpha) * dt * s_b * f / alpha
            f2, one_minus_f2 = f * f, one_minus_f * (1.0 + f)
        e = 1.0 - one_minus_e
        t = (one_minus_f2 + f2 * one_minus_e) / (1.0 + f2 * e)
        b = p.b
        big = np.abs(z_t) > b
        with np.errstate(all="ignore"):
            y = np.where(big, b / np.where(big, z_t, 1.0), 0.0)
            z_c = np.where(big, b * (1.0 + t * y) / (t + y), b * (z_t + b * t) / (b + z_t * t))
    z_h = g_tau * z_c
    c = np.complex128
    return DiscreteParts(*(np.asarray(x, dtype=c) for x in (g_tau, g_omega, z_e, z_t, z_c, z_h)))


def displayed_impedance_z(omega: ArrayLike, params: ImpedanceParams, dt: float = DT) -> Complex:
    """Z_h(exp(j omega dt)) of the 1 kHz implementation, N m s/rad; omega in rad/s."""
    return displayed_impedance_parts_z(omega, params, dt).z_h


# --- poles ------------------------------------------------------------------------------------
class _Rat(NamedTuple):
    """A rational function of z, numerator and denominator as numpy Polynomials."""

    num: Polynomial
    den: Polynomial

    def __add__(self, other: _Rat) -> _Rat:  # type: ignore[override]
        if self.den == other.den:
            return _Rat(self.num + other.num, self.den)
        return _Rat(self.num * other.den + other.num * self.den, self.den * other.den)

    def __mul__(self, other: _Rat) -> _Rat:  # type: ignore[override]
        return _Rat(self.num * other.num, self.den * other.den)


def _const(x: float) -> _Rat:
    return _Rat(Polynomial([x]), Polynomial([1.0]))


_Z = Polynomial([0.0, 1.0])
_ZM1 = Polynomial([-1.0, 1.0])


def _controller_rat(c: ControllerGains | float, dt: float) -> _Rat:
    g = _gains(c)
    out = _const(g.kp)
    if g.ki:
        out = out + _Rat(Polynomial([g.ki * dt]), _ZM1)
    if g.kd:
        a = g.derivative_filter_s / (g.derivative_filter_s + dt)
        out = out + _Rat(g.kd * (1.0 - a) * _ZM1, dt * Polynomial([-a, 1.0]))
    return out


def characteristic_polynomials(params: ImpedanceParams, dt: float = DT) -> list[Polynomial]:
    """The HSI loop polynomial and the channel-TO polynomial (module doc); modes = their roots."""
    p = params
    c1, c2 = _controller_rat(p.c1, dt), _controller_rat(p.c2, dt)
    hsi = p.m1 * _ZM1 * c1.den + dt * p.z_o * c1.num
    # G_omega = dt n2 / (M2 (z - 1) d2 + dt n2)
    g_num, g_den = dt * c2.num, p.m2 * _ZM1 * c2.den + dt * c2.num
    z_e = _const(p.env_damping)
    if p.env_mass:
        z_e = z_e + _Rat(p.env_mass * _ZM1, dt * _Z)
    if p.env_stiffness:
        z_e = z_e + _Rat(p.env_stiffness * dt * _Z, _ZM1)
    n_t, d_t = g_num * z_e.num, g_den * z_e.den
    d = delay_ticks(p.delay_s, dt)
    if d == 0:
        return [hsi, d_t]
    alpha = filter_alpha(p.wave_filter_hz, dt)
    if alpha is None:
        f_n, f_d = Polynomial([1.0]), Polynomial([1.0])
    else:
        f_n, f_d = Polynomial([0.0, alpha]), Polynomial([alpha - 1.0, 1.0])
    z2d = Polynomial([0.0] * (2 * d) + [1.0])
    channel = (p.b * d_t + n_t) * f_d**2 * z2d + f_n**2 * (p.b * d_t - n_t)
    return [hsi, channel]


@lru_cache(maxsize=64)
def _modes(params: ImpedanceParams, dt: float) -> tuple[complex, ...]:
    roots: list[complex] = []
    for poly in characteristic_polynomials(params, dt):
        coef = poly.coef
        nz = np.flatnonzero(np.abs(coef) > 0)
        if len(nz) and nz[-1] > nz[0]:
            roots.extend(Polynomial(coef[nz[0] : nz[-1] + 1]).roots())  # roots at 0 dropped
    return tuple(complex(z) for z in roots)


def chain_modes(params: ImpedanceParams, dt: float = DT) -> np.ndarray:
    """The open chain's modes: the nonzero roots of ``characteristic_polynomials``."""
    return np.array(_modes(params, dt), dtype=complex)


def spectral_radius(params: ImpedanceParams, dt: float = DT) -> float:
    """Largest |z| of the open chain's modes: > 1 rings up, < 1 settles.

    Exactly 1 (to round-off) is bounded here: a simple root at z = 1 is a joint spring's
    position integrating the imposed velocity (a constant offset), and a lossless channel in
    free space keeps its startup echoes (z^2D = -1); neither disturbs a whole-window lock-in.
    """
    modes = chain_modes(params, dt)
    return float(np.abs(modes).max()) if len(modes) else 0.0


# a root this close to the unit circle is on it (root-finding error is ~1e-11 here)
_ON_CIRCLE = 1e-8


def window_decay(params: ImpedanceParams, window_ticks: int, dt: float = DT) -> float:
    """r = max |z|^N over the modes that leak into a lock-in over whole windows of N ticks.

    Left out: modes on the unit circle that are periodic over the window (z^N = 1: a joint
    spring's offset at z = 1; a lossless channel's echoes, z^2D = -1, when 4D divides N). A
    transient then leaves at most r / (1 - r) times the last window-to-window change in the
    estimate (module doc); r >= 1: a mode that never dies out (marginal or unstable chain).
    """
    z = chain_modes(params, dt)
    radius = np.abs(z)
    on_circle = np.abs(radius - 1.0) <= _ON_CIRCLE
    turns = np.angle(z) * window_ticks / (2.0 * np.pi)  # per window
    periodic = on_circle & (np.abs(turns - np.round(turns)) <= _ON_CIRCLE * window_ticks)
    radius = np.where(on_circle, 1.0, radius)[~periodic]
    return float(radius.max() ** window_ticks) if len(radius) else 0.0
