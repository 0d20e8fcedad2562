"""Transparency measures of eq 18, per joint, accumulated tick by tick (a per-tick kernel
module: the lock-step session's and a Python-stepped session's tick call ``accumulate``; the
offline sums over a log's series are ``teleop_rt.analysis.transparency``'s):

    T_p   = integral (alpha_h - alpha_e)^2 dt      alpha = joint angle moved since the start
    T_tau = integral (tau_h - tau_e)^2 dt          tau_h: operator on HSI, tau_e: TO on environment

Integrals are rectangle sums over ticks (dt each), the same for the live session and for logs.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.flat import Block, Int, Scalar, Vector, as_floats, jit, vec


class TransparencyAccumulator(Block):
    """Accumulates T_p and T_tau tick by tick (compiled ``accumulate``; nothing allocated)."""

    t_p = Vector("T_p per joint, rad^2 s")
    t_tau = Vector("T_tau per joint, N^2 m^2 s")
    offset = Vector("q_h - q_t at the first tick, rad")
    dt = Scalar(param=True)
    has_offset = Int()

    def __init__(self, n: int, dt: float, offset: list[float] | None = None) -> None:
        super().__init__(n)
        self.dt = dt
        # alpha = angle moved since the first tick: unless given, the offset q_h - q_t is taken
        # there (a log holds that tick too, so metrics from the log use the very same offset)
        if offset is not None:
            self.offset[:] = offset
            self.has_offset = 1

    def add(self, q_h, q_t, tau_h, tau_e) -> None:
        accumulate(
            self.f, self.i, self.n,
            as_floats(q_h), as_floats(q_t), as_floats(tau_h), as_floats(tau_e),
        )  # fmt: skip


@jit
def accumulate(
    f: np.ndarray,
    i: np.ndarray,
    n: int,
    q_h: np.ndarray,
    q_t: np.ndarray,
    tau_h: np.ndarray,
    tau_e: np.ndarray,
) -> None:
    """Add one tick's rectangle to T_p and T_tau (eq 18)."""
    Ta = TransparencyAccumulator.idx
    t_p, t_tau, offset = vec(f, Ta.T_P, n), vec(f, Ta.T_TAU, n), vec(f, Ta.OFFSET, n)
    dt = f[Ta.N_VECTORS * n + Ta.DT]
    if not i[Ta.HAS_OFFSET]:
        for j in range(n):
            offset[j] = q_h[j] - q_t[j]
        i[Ta.HAS_OFFSET] = 1
    for j in range(n):
        e = q_h[j] - q_t[j] - offset[j]
        t_p[j] += e * e * dt
        e = tau_h[j] - tau_e[j]
        t_tau[j] += e * e * dt
