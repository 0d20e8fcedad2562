"""Displayed parameters from time-domain runs (issue 4, item 4; paper eq 29, 30).

The operator moves (omega_o imposed on the open chain of ``teleop_rt.analysis.bode``) with a
minimum-jerk stroke out and back; a least-squares fit of the measured tau_h on the operator's
acceleration, velocity and angle,

    tau_h[k] ~ m alpha_o[k] + d omega_o[k] + k theta_o[k],

gives the displayed mass, damping and stiffness (alpha_o and theta_o are the backward
difference and the running sum of omega_o, the discrete derivative and integral the chain
itself uses, so the fit is exact in the low-frequency limit). Over a stroke that starts and
ends at rest the regressors are nearly orthogonal and the higher-order terms of Z_h (the HSI's
lag G_tau ~ 1 - T1 s, tanh(T s) ~ T s - (T s)^3 / 3) stay small for slow strokes.

What the channel displays at low frequencies (module ``impedance``, eq 29, 30): Z_c = b t with
t = tanh(T s) ~ T s in free space, and Z_c = b / t at a rigid termination, i.e. a mass b T and a
stiffness b / T; against a spring k_e (G_omega -> 1): 1 / k_d = 1 / k_e + T / b. In the
1 kHz chain T is the effective one-way delay ``effective_delay``: D dt plus, when the
received-wave filter is on, its group delay at DC, (1 - alpha) dt / alpha (4.82 ms at 30 Hz,
half a tick less than the 1/(2 pi f_c) = 5.31 ms of its continuous namesake; a continuous
filter at ``discrete.matched_filter_hz``, 33.0 Hz, has the same). Hence the ratio
mass / stiffness = T^2 for a rigid wall whatever b is (for a spring k_e it is
T^2 (1 + b / (k_e T))).

Without the filter a joint spring behind any delay rings up in this chain (Re Z_t < 0 and a
lossless channel: ``discrete.spectral_radius`` > 1), so stiffness fits need the filter on;
the free-space mass fit works either way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from teleop_rt.analysis.bode import OpenChain, run_bounded
from teleop_rt.analysis.discrete import DT, delay_ticks, filter_group_delay_s
from teleop_rt.analysis.impedance import AnalysisParamError, ImpedanceParams


@dataclass(frozen=True)
class ImpedanceFit:
    """Least-squares tau_h ~ mass alpha_o + damping omega_o + stiffness theta_o (SI units)."""

    mass: float  # kg m^2
    damping: float  # N m s/rad
    stiffness: float  # N m/rad
    residual_rms: float  # N m, what the three terms leave unexplained
    tau_rms: float  # N m, of tau_h itself


@dataclass(frozen=True)
class DisplayedFit:
    """A fitted displayed parameter and what the analysis says it is.

    value: the fitted mass (kg m^2) or stiffness (N m/rad). expected: the low-frequency limit
    with the effective delay (b T, or 1/(1/k_e + T/b)). paper: eq 29 / 30 with T_d alone (b T_d
    or b / T_d). effective_delay_s: T. fit: all three fitted terms.
    """

    value: float
    expected: float
    paper: float
    effective_delay_s: float
    fit: ImpedanceFit

    @property
    def relative_error(self) -> float:
        return self.value / self.expected - 1.0


def effective_delay(params: ImpedanceParams, dt: float = DT) -> float:
    """T of the 1 kHz channel at low frequency: D dt + the filter's DC group delay (s)."""
    d = delay_ticks(params.delay_s, dt)
    return d * dt + (filter_group_delay_s(params.wave_filter_hz, dt) if d > 0 else 0.0)


def min_jerk_stroke(
    angle_rad: float, move_s: float, hold_s: float, rest_s: float, dt: float = DT
) -> np.ndarray:
    """omega_o (rad/s) per tick: rest, a minimum-jerk stroke to angle_rad, hold, back, rest."""
    n_move = round(move_s / dt)
    s = (np.arange(n_move) + 0.5) / n_move  # mid-tick samples: the stroke sums to angle_rad
    out = angle_rad * 30.0 * s**2 * (1.0 - s) ** 2 / move_s
    rest, hold = np.zeros(round(rest_s / dt)), np.zeros(round(hold_s / dt))
    return np.concatenate([rest, out, hold, -out, rest])


def fit_impedance_terms(omega_o: np.ndarray, tau_h: np.ndarray, dt: float = DT) -> ImpedanceFit:
    """Least-squares mass, damping and stiffness of tau_h against omega_o (one joint, SI)."""
    w = np.asarray(omega_o, dtype=float)
    tau = np.asarray(tau_h, dtype=float)
    alpha = np.diff(w, prepend=0.0) / dt  # backward difference (s_b)
    theta = np.cumsum(w) * dt  # running sum (1 / s_b)
    regressors = np.column_stack([alpha, w, theta])
    coef, *_ = np.linalg.lstsq(regressors, tau, rcond=None)
    residual = tau - regressors @ coef
    return ImpedanceFit(
        float(coef[0]),
        float(coef[1]),
        float(coef[2]),
        float(np.sqrt(np.mean(residual**2))),
        float(np.sqrt(np.mean(tau**2))),
    )


def _run_stroke(
    params: ImpedanceParams,
    joint: int,
    dt: float,
    angle_rad: float,
    move_s: float,
    chain_kwargs: dict | None,
) -> ImpedanceFit:
    omega_o = min_jerk_stroke(angle_rad, move_s, hold_s=move_s / 2, rest_s=move_s / 2, dt=dt)
    chain = OpenChain(params, joint, dt, **(chain_kwargs or {}))
    rec = run_bounded(chain, omega_o, 1e6 * (1.0 + params.b + params.env_stiffness))
    if rec is None:
        raise AnalysisParamError("the chain rang up during the stroke: no displayed parameter")
    return fit_impedance_terms(rec.omega_o, rec.tau_h, dt)


def fit_displayed_mass(
    params: ImpedanceParams,
    joint: int = 1,
    dt: float = DT,
    angle_rad: float = 0.1,
    move_s: float = 4.0,
    chain_kwargs: dict | None = None,
) -> DisplayedFit:
    """Displayed mass in free space (the params' environment is set to zero), kg m^2."""
    free = replace(params, env_mass=0.0, env_damping=0.0, env_stiffness=0.0)
    fit = _run_stroke(free, joint, dt, angle_rad, move_s, chain_kwargs)
    t = effective_delay(params, dt)
    return DisplayedFit(fit.mass, params.b * t, params.b * params.delay_s, t, fit)


def fit_displayed_stiffness(
    params: ImpedanceParams,
    joint: int = 1,
    dt: float = DT,
    angle_rad: float = 0.01,
    move_s: float = 2.0,
    chain_kwargs: dict | None = None,
) -> DisplayedFit:
    """Displayed stiffness against the params' joint spring (a wall: env_stiffness > 0), N m/rad.

    expected: 1 / (1/k_e + T/b) (the soft-wall formula; b / T for k_e -> inf); paper: b / T_d.
    """
    k_e = params.env_stiffness
    if not k_e > 0:
        raise AnalysisParamError("a displayed stiffness needs a wall: env_stiffness > 0")
    fit = _run_stroke(params, joint, dt, angle_rad, move_s, chain_kwargs)
    t = effective_delay(params, dt)
    expected = 1.0 / (1.0 / k_e + t / params.b)
    paper = params.b / params.delay_s if params.delay_s > 0 else math.inf
    return DisplayedFit(fit.stiffness, expected, paper, t, fit)
