"""Transparency measures of eq 18, per joint:

    T_p   = integral (alpha_h - alpha_e)^2 dt      alpha = joint angle moved since the start
    T_tau = integral (tau_h - tau_e)^2 dt          tau_h: operator on HSI, tau_e: TO on environment

Integrals are rectangle sums over ticks (dt each), the same for the live session and for logs.
"""

from __future__ import annotations

import numpy as np


class TransparencyAccumulator:
    """Accumulates T_p and T_tau tick by tick (scalar path, nothing allocated but floats)."""

    def __init__(self, n: int, dt: float, offset: list[float] | None = None) -> None:
        # alpha = angle moved since the first tick: unless given, the offset q_h - q_t is taken
        # there (a log holds that tick too, so metrics from the log use the very same offset)
        self.offset = offset
        self.dt = dt
        self.n = n
        self.t_p = [0.0] * n
        self.t_tau = [0.0] * n

    def add(
        self, q_h: list[float], q_t: list[float], tau_h: list[float], tau_e: list[float]
    ) -> None:
        if self.offset is None:
            self.offset = [a - b for a, b in zip(q_h, q_t, strict=True)]
        dt, t_p, t_tau, offset = self.dt, self.t_p, self.t_tau, self.offset
        for j in range(self.n):
            e = q_h[j] - q_t[j] - offset[j]
            t_p[j] += e * e * dt
            e = tau_h[j] - tau_e[j]
            t_tau[j] += e * e * dt


def transparency(
    q_h: np.ndarray, q_t: np.ndarray, tau_h: np.ndarray, tau_e: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """(T_p, T_tau) per joint from whole time series of shape (ticks, joints)."""
    alpha_err = (q_h - q_h[:1]) - (q_t - q_t[:1])
    return (alpha_err**2).sum(axis=0) * dt, ((tau_h - tau_e) ** 2).sum(axis=0) * dt
