"""Transparency measures of eq 18 over whole series (a log's, two sites' tick records): the
live accumulator (``teleop_rt.transparency_tick``) fed row after row by one compiled call, so a
log gives the live figures because it is summed by the live arithmetic itself.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.flat import jit
from teleop_rt.transparency_tick import TransparencyAccumulator, accumulate

# eq 18's terms per coordinate of the channel, with their units: a joint channel compares joint
# angles and torques, a plane channel the tools' x-y positions and forces (teleop_rt.mapping)
_TERMS = {
    "joint": ("joint", "rad^2 s", "N^2 m^2 s"), "plane": ("axis", "m^2 s", "N^2 s"),
    "position": ("axis", "m^2 s", "N^2 s"),
    "pose": ("axis", "m^2 s x 3, rad^2 s x 3", "N^2 s x 3, N^2 m^2 s x 3"),
}  # fmt: skip


def transparency_labels(space: str) -> tuple[str, str]:
    """The row names of T_p and T_tau per coordinate for a channel in ``space``."""
    what, p_unit, tau_unit = _TERMS.get(space, _TERMS["joint"])
    return f"T_p per {what} ({p_unit})", f"T_tau per {what} ({tau_unit})"


def add_series(
    acc: TransparencyAccumulator,
    q_h: np.ndarray,
    q_t: np.ndarray,
    tau_h: np.ndarray,
    tau_e: np.ndarray,
) -> None:
    """Add whole (ticks, joints) series to ``acc``, tick by tick (``accumulate`` per row,
    compiled)."""
    rows = (np.ascontiguousarray(x, dtype=np.float64) for x in (q_h, q_t, tau_h, tau_e))
    accumulate_series(acc.f, acc.i, acc.n, *rows)


@jit
def accumulate_series(
    f: np.ndarray, i: np.ndarray, n: int,
    q_h: np.ndarray, q_t: np.ndarray, tau_h: np.ndarray, tau_e: np.ndarray,
) -> None:  # fmt: skip
    """``accumulate`` over the rows of (ticks, joints) series, one tick after the other: a log
    gives the live figures because it is summed by the live arithmetic itself."""
    for k in range(q_h.shape[0]):
        accumulate(f, i, n, q_h[k], q_t[k], tau_h[k], tau_e[k])
