"""Displayed impedance of the teleoperation chain (Kuschel & Buss, Section 3, eq 19-32).

Single joint, linear time-invariant, continuous time. Every function takes ``s`` (complex
frequency, 1/s; usually ``1j * omega`` with omega in rad/s), scalar or array, and returns complex
numpy values of the broadcast shape. Joint space units: torque N m, velocity rad/s, virtual
inertia ("mass") kg m^2, damping and wave impedance N m s/rad, stiffness N m/rad, time s.

Impedance convention: Z(s) = tau(s) / omega(s), where tau is the torque that must be applied to
a port to move it at omega, so a passive load has Re Z(j omega) >= 0. The stack's sign
convention for the running signals is written once, in ``teleop_rt/control.py``; in its terms
the paper's damper operator is tau_h = -Z_o v_h (operator on the HSI) and eq 21 holds for
tau_h / tau_c. Ports of the chain:

* Z_o: operator hand, a damper of Z_o (eq 5 writes its reaction as Z_o omega_h);
* Z_h = tau_h / omega_o (eq 19): what the operator feels, Z_h = G_tau Z_c (eq 20);
* Z_c = tau_c / omega_c: the channel seen from the HSI side;
* Z_t = tau_t / omega_t = G_omega Z_e (eq 23): the velocity-controlled TO with its environment,
  terminating the channel on the remote side;
* Z_e = tau_e / omega_e: the remote environment.

The power entering the channel two-port is omega_c tau_c - omega_t tau_t (eq 8), i.e. tau_t is
what the channel must apply to the TO side, as it is what the terminating Z_t requires.

Caveat: this is the paper's open chain (operator velocity imposed). A velocity-controlled TO
against a spring can have Re Z_t < 0, so |Gamma| > 1 at some frequencies and the time-domain chain
may ring up for some delays; a frequency response here is only meaningful where the time-domain
chain settles. Nothing in this module checks stability.

Terms with a pole at the origin (integral gain, environment stiffness) are infinite at s = 0;
evaluate limits at small nonzero |s|.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from teleop_rt.errors import ConfigError

Complex = NDArray[np.complex128]
DelayModel = Literal["exact", "pade"]
DELAY_MODELS: tuple[str, ...] = ("exact", "pade")


class AnalysisParamError(ConfigError, ValueError):
    """An analysis parameter is impossible (negative mass, unknown delay model, ...)."""


@dataclass(frozen=True)
class ControllerGains:
    """P(ID) gains of C(s) = kp + ki/s + kd s / (1 + derivative_filter_s s).

    Units depend on the loop: for the HSI torque controller C1 (eq 4, torque error -> torque on the
    virtual mass M1) kp is dimensionless, ki in 1/s, kd in s; for the TO velocity controller C2
    (eq 14, velocity error -> torque on M2) kp is in N m s/rad, ki in N m/rad, kd in N m s^2/rad.
    ``derivative_filter_s`` is the derivative filter time constant in s (0 = ideal derivative).
    """

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    derivative_filter_s: float = 0.0

    def __post_init__(self) -> None:
        if self.derivative_filter_s < 0:
            raise AnalysisParamError(
                f"derivative_filter_s must be >= 0 s, got {self.derivative_filter_s}"
            )


@dataclass(frozen=True)
class ImpedanceParams:
    """Parameters of the single-joint chain of eq (20)-(24).

    m1, m2: virtual inertias of HSI and TO (eq 3, 13), kg m^2, > 0.
    c1, c2: HSI torque and TO velocity controllers, ``ControllerGains`` or a float meaning kp.
    z_o: operator damping, N m s/rad, >= 0 (a damper operator, Z_o = const).
    b: wave impedance, N m s/rad, > 0. delay_s: one-way delay T_d, s, >= 0.
    env_mass (kg m^2), env_damping (N m s/rad), env_stiffness (N m/rad): Z_e, each >= 0.
    delay_model: "exact" (e^{-2 T_d s}) or "pade" (eq 28).
    wave_filter_hz: cut-off of the first-order low-pass on each received wave, Hz; None = off.
    """

    m1: float
    m2: float
    c1: ControllerGains | float
    c2: ControllerGains | float
    z_o: float
    b: float
    delay_s: float
    env_mass: float = 0.0
    env_damping: float = 0.0
    env_stiffness: float = 0.0
    delay_model: DelayModel = "exact"
    wave_filter_hz: float | None = None

    def __post_init__(self) -> None:
        for name in ("m1", "m2", "b"):
            value = getattr(self, name)
            if not 0 < value < math.inf:
                raise AnalysisParamError(f"{name} must be > 0 and finite, got {value}")
        for name in ("z_o", "delay_s", "env_mass", "env_damping", "env_stiffness"):
            value = getattr(self, name)
            if not 0 <= value < math.inf:  # (inf made a NaN model: warnings, and exit 0)
                raise AnalysisParamError(f"{name} must be >= 0 and finite, got {value}")
        _check_delay_model(self.delay_model)
        _check_cutoff(self.wave_filter_hz)


class ImpedanceParts(NamedTuple):
    """The factors of Z_h = G_tau * Z_c(Z_t = G_omega * Z_e), each over s."""

    g_tau: Complex
    g_omega: Complex
    z_e: Complex
    z_t: Complex
    z_c: Complex
    z_h: Complex


def _c(x: ArrayLike) -> Complex:
    return np.asarray(x, dtype=np.complex128)


def _check_delay_model(model: str) -> None:
    if model not in DELAY_MODELS:
        raise AnalysisParamError(f"delay_model must be one of {DELAY_MODELS}, got {model!r}")


def _check_cutoff(cutoff_hz: float | None) -> None:
    if cutoff_hz is not None and not cutoff_hz > 0:
        raise AnalysisParamError(f"wave_filter_hz must be > 0 Hz or None, got {cutoff_hz}")


def controller_tf(
    s: ArrayLike, kp: float, ki: float = 0.0, kd: float = 0.0, derivative_filter_s: float = 0.0
) -> Complex:
    """C(s) = kp + ki/s + kd s / (1 + derivative_filter_s s); units as in ``ControllerGains``."""
    s = _c(s)
    c = kp + kd * s / (1.0 + derivative_filter_s * s)
    if ki:
        c = c + ki / s
    return _c(c)


def _controller_values(s: Complex, c: ControllerGains | float) -> Complex:
    if isinstance(c, ControllerGains):
        return controller_tf(s, c.kp, c.ki, c.kd, c.derivative_filter_s)
    return controller_tf(s, float(c))


def environment_impedance(
    s: ArrayLike, mass: float = 0.0, damping: float = 0.0, stiffness: float = 0.0
) -> Complex:
    """Z_e(s) = mass s + damping + stiffness/s (N m s/rad); all zero = free space.

    mass in kg m^2, damping in N m s/rad, stiffness in N m/rad.
    """
    s = _c(s)
    z = mass * s + damping
    if stiffness:
        z = z + stiffness / s
    return _c(z)


def g_tau(s: ArrayLike, m1: float, c1: ArrayLike, z_o: ArrayLike) -> Complex:
    """Torque-controlled HSI with operator, eq (21): G_tau = C1 Z_o / (s M1 + C1 Z_o).

    m1: virtual inertia, kg m^2. c1: values of C1(s) (dimensionless for P control), scalar or
    array over s. z_o: operator impedance Z_o(s), N m s/rad, scalar or array over s.
    """
    s = _c(s)
    cz = _c(c1) * _c(z_o)
    return _c(cz / (s * m1 + cz))


def g_omega(s: ArrayLike, m2: float, c2: ArrayLike) -> Complex:
    """Velocity-controlled TO, eq (24): G_omega = C2 / (s M2 + C2).

    m2: virtual inertia, kg m^2. c2: values of C2(s), N m s/rad, scalar or array over s.
    """
    s = _c(s)
    c2 = _c(c2)
    return _c(c2 / (s * m2 + c2))


def delay_factor(s: ArrayLike, delay_s: float, model: DelayModel = "exact") -> Complex:
    """Round-trip delay factor for the one-way delay T_d = ``delay_s`` (s).

    "exact": e^{-2 T_d s}; "pade": (1 - T_d s) / (1 + T_d s), the paper's eq (28), valid for
    omega < 1 / (3 T_d). T_d = 0 gives 1.
    """
    _check_delay_model(model)
    s = _c(s)
    if model == "exact":
        return _c(np.exp(-2.0 * delay_s * s))
    return _c((1.0 - delay_s * s) / (1.0 + delay_s * s))


def wave_filter_tf(s: ArrayLike, cutoff_hz: float | None = None) -> Complex:
    """First-order low-pass F(s) = 1 / (1 + s / (2 pi f_c)) on each received wave; None = 1.

    cutoff_hz: f_c in Hz. |F(j omega)| <= 1, so the filter cannot make the channel active.
    """
    _check_cutoff(cutoff_hz)
    s = _c(s)
    if cutoff_hz is None:
        return np.ones_like(s)
    return _c(1.0 / (1.0 + s / (2.0 * np.pi * cutoff_hz)))


def round_trip_factor(
    s: ArrayLike,
    delay_s: float,
    delay_model: DelayModel = "exact",
    wave_filter_hz: float | None = None,
) -> Complex:
    """D(s) = F(s)^2 * delay_factor(s): maps Gamma_t to Gamma = D Gamma_t (HSI side)."""
    return _c(wave_filter_tf(s, wave_filter_hz) ** 2 * delay_factor(s, delay_s, delay_model))


def _channel_tanh(
    s: Complex, delay_s: float, delay_model: DelayModel, wave_filter_hz: float | None
) -> Complex:
    """t = (1 - D)/(1 + D), D = F^2 E, with 1 -/+ E and 1 - F^2 in closed form (no cancellation).

    t = tanh(T_d s) for the exact delay and t = T_d s for Pade when there is no filter.
    """
    x = delay_s * s
    one_minus_e: np.ndarray
    one_plus_e: np.ndarray
    if delay_model == "exact":
        one_minus_e, one_plus_e = -np.expm1(-2.0 * x), 1.0 + np.exp(-2.0 * x)
    else:
        one_minus_e, one_plus_e = 2.0 * x / (1.0 + x), 2.0 / (1.0 + x)
    if wave_filter_hz is None:
        return _c(one_minus_e / one_plus_e)
    f = wave_filter_tf(s, wave_filter_hz)
    one_minus_f2 = (s / (2.0 * np.pi * wave_filter_hz)) * f * (1.0 + f)  # 1 - F = x_f F
    return _c((one_minus_f2 + f**2 * one_minus_e) / (one_minus_f2 + f**2 * one_plus_e))


def reflection_coefficient(z_t: ArrayLike, b: float) -> Complex:
    """Gamma_t = (b - Z_t) / (b + Z_t) of a termination Z_t (N m s/rad) on wave impedance b.

    |Gamma_t| <= 1 iff Re Z_t >= 0. Z_t = inf (np.inf or huge) gives -1, Z_t = 0 gives +1.
    """
    z = _c(z_t)
    big = np.abs(z) > b
    with np.errstate(all="ignore"):  # masked branches may divide by 0 / inf
        y = np.where(big, b / np.where(big, z, 1.0), 0.0)  # b / Z_t, 0 for Z_t = inf
        gamma = np.where(big, (y - 1.0) / (y + 1.0), (b - z) / (b + z))
    return _c(gamma)


def channel_impedance(
    s: ArrayLike,
    b: float,
    delay_s: float,
    z_t: ArrayLike,
    delay_model: DelayModel = "exact",
    wave_filter_hz: float | None = None,
) -> Complex:
    """Z_c = tau_c / omega_c of the wave channel terminated by Z_t, eq (22) (+ wave filters).

    b: wave impedance, N m s/rad. delay_s: one-way delay T_d, s. z_t: termination Z_t(s),
    N m s/rad, scalar or array over s; np.inf (or huge) is a rigid termination.

    Definition: Gamma_t = (b - Z_t)/(b + Z_t), Gamma = D Gamma_t with D = F^2 delay_factor,
    Z_c = b (1 - Gamma)/(1 + Gamma). With F = 1 (D = e = delay factor), multiplying
    numerator and denominator by (b + Z_t) gives
    Z_c = b (b + Z_t - e (b - Z_t)) / (b + Z_t + e (b - Z_t)) = b - 2 b e (b - Z_t) /
    (b + Z_t + e (b - Z_t)), which is eq (22). Evaluated in the algebraically identical
    transmission-line form Z_c = b (Z_t + b t) / (b + Z_t t), t = (1 - D)/(1 + D) (t = tanh(T_d s)
    for the exact delay without filter, T_d s for Pade), which does not cancel as Z_t -> 0 or
    Z_t -> inf: Z_t = 0 gives b t, Z_t = inf gives b / t.
    """
    if not b > 0:
        raise AnalysisParamError(f"wave impedance b must be > 0 N m s/rad, got {b}")
    _check_delay_model(delay_model)
    _check_cutoff(wave_filter_hz)
    s = _c(s)
    z, t = np.broadcast_arrays(_c(z_t), _channel_tanh(s, delay_s, delay_model, wave_filter_hz))
    big = np.abs(z) > b
    with np.errstate(all="ignore"):  # masked branches may divide by 0 / inf
        y = np.where(big, b / np.where(big, z, 1.0), 0.0)  # b / Z_t, 0 for Z_t = inf
        zc = np.where(big, b * (1.0 + t * y) / (t + y), b * (z + b * t) / (b + z * t))
    # rigid termination on a channel without delay or filter: rigid (avoid inf + nan j)
    return _c(np.where(big & (t + y == 0), np.inf, zc))


def time_constant_hsi(m1: float, c1: float, z_o: float) -> float:
    """T1 = M1 / (c1 Z_o), s, eq (31): P gain c1 (dimensionless), damper Z_o (N m s/rad)."""
    return m1 / (c1 * z_o)


def time_constant_to(m2: float, c2: float) -> float:
    """T2 = M2 / c2, s, eq (32): P gain c2 (N m s/rad), virtual inertia M2 (kg m^2)."""
    return m2 / c2


def displayed_mass_free_space(b: float, delay_s: float) -> float:
    """Mass b T_d (kg m^2) the channel shows in free space, eq (29) (Pade, Z_t = 0)."""
    return b * delay_s


def displayed_stiffness_wall(b: float, delay_s: float) -> float:
    """Stiffness b / T_d (N m/rad) the channel shows for a rigid wall, eq (30); inf at T_d = 0."""
    return b / delay_s if delay_s > 0 else float("inf")


def displayed_impedance_parts(s: ArrayLike, params: ImpedanceParams) -> ImpedanceParts:
    """All factors of the displayed impedance, eq (20)-(24), over s (see ``ImpedanceParts``)."""
    p = params
    s = _c(s)
    gt = g_tau(s, p.m1, _controller_values(s, p.c1), p.z_o)
    go = g_omega(s, p.m2, _controller_values(s, p.c2))
    z_e = environment_impedance(s, p.env_mass, p.env_damping, p.env_stiffness)
    z_t = _c(go * z_e)
    z_c = channel_impedance(s, p.b, p.delay_s, z_t, p.delay_model, p.wave_filter_hz)
    return ImpedanceParts(gt, go, z_e, z_t, z_c, _c(gt * z_c))


def displayed_impedance(s: ArrayLike, params: ImpedanceParams) -> Complex:
    """Z_h(s) = G_tau Z_c(Z_t = G_omega Z_e), eq (20) and (23), N m s/rad."""
    return displayed_impedance_parts(s, params).z_h
