"""The compiled part of one control tick (steps 3-7 of ../shared/docs/architecture.md), around
the two Pinocchio calls that Python makes between its halves:

    before_models:  tau_h, tau_e; channel (eq 9, 10); errors; C1, C2 (eq 4, 14); M_v^-1 a_ref
    (Python)        RNEA of each robot at M_v^-1 a_ref
    after_models:   computed torque (eq 2, 12); safety checks and saturation; T_p, T_tau (eq 18)

Both take the session's packed buffers (``teleop_rt.flat.Packed``) with its blocks in the order
``BLOCK_ORDER``: three array arguments reach every signal of the tick.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.analysis.transparency import accumulate
from teleop_rt.com.channel import OMEGA_T, TAU_C, channel_step
from teleop_rt.control import A_DES, OUT, TAU, ct_finish, ct_prepare, pid_step
from teleop_rt.flat import Block, floats_of, ints_of, jit, vec
from teleop_rt.hal.base import FB_AGE_TICKS, FB_Q, FB_TAU_EXT, FB_V
from teleop_rt.safety import supervise

BLOCK_ORDER = (
    "fb_h", "fb_t", "signals", "channel", "pid_h", "pid_t", "ct_h", "ct_t",
    "supervisor", "guard_h", "guard_t", "metrics", "world_h", "world_t",
)  # fmt: skip
FB_H, FB_T, SIGNALS, CHANNEL, PID_H, PID_T, CT_H, CT_T = range(8)
SUPERVISOR, GUARD_H, GUARD_T, METRICS, WORLD_H, WORLD_T = range(8, 14)
TAU_H, TAU_E, ERROR_H, ERROR_T = range(4)  # TickSignals vectors


class TickSignals(Block):
    """The session's own per-tick signals: tau_h (the operator's torque on the HSI, as
    measured), tau_e (the TO's torque on the environment, -tau_ext_t) and the controllers'
    errors."""

    VECTORS = ("tau_h", "tau_e", "error_h", "error_t")


@jit
def before_models(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> None:
    """From the fresh feedback to the accelerations the models are evaluated at."""
    fb_h, fb_t, sig = floats_of(f, o, FB_H), floats_of(f, o, FB_T), floats_of(f, o, SIGNALS)
    tau_h, tau_e = vec(sig, TAU_H, n), vec(sig, TAU_E, n)
    err_h, err_t = vec(sig, ERROR_H, n), vec(sig, ERROR_T, n)
    tau_ext_h, tau_ext_t, v_h = (
        vec(fb_h, FB_TAU_EXT, n),
        vec(fb_t, FB_TAU_EXT, n),
        vec(fb_h, FB_V, n),
    )
    for j in range(n):
        tau_h[j] = tau_ext_h[j]
        tau_e[j] = -tau_ext_t[j]
    ch = floats_of(f, o, CHANNEL)
    channel_step(ch, ints_of(i, o, CHANNEL), n, v_h, tau_e)
    tau_c, omega_t, v_t = vec(ch, TAU_C, n), vec(ch, OMEGA_T, n), vec(fb_t, FB_V, n)
    for j in range(n):
        err_h[j] = tau_h[j] - tau_c[j]
        err_t[j] = omega_t[j] - v_t[j]
    pid_h, pid_t = floats_of(f, o, PID_H), floats_of(f, o, PID_T)
    pid_step(pid_h, ints_of(i, o, PID_H), n, err_h)
    pid_step(pid_t, ints_of(i, o, PID_T), n, err_t)
    ct_prepare(floats_of(f, o, CT_H), n, vec(pid_h, OUT, n))
    ct_prepare(floats_of(f, o, CT_T), n, vec(pid_t, OUT, n))


@jit
def after_models(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, rnea_h: np.ndarray, rnea_t: np.ndarray
) -> int:
    """From the models' RNEA to checked motor torques; the safety finding (0: none)."""
    fb_h, fb_t, sig = floats_of(f, o, FB_H), floats_of(f, o, FB_T), floats_of(f, o, SIGNALS)
    ct_h, ct_t = floats_of(f, o, CT_H), floats_of(f, o, CT_T)
    q_h, v_h, tau_h = vec(fb_h, FB_Q, n), vec(fb_h, FB_V, n), vec(fb_h, FB_TAU_EXT, n)
    q_t, v_t, tau_ext_t = vec(fb_t, FB_Q, n), vec(fb_t, FB_V, n), vec(fb_t, FB_TAU_EXT, n)
    ct_finish(ct_h, ints_of(i, o, CT_H), n, rnea_h, tau_h, v_h)
    ct_finish(ct_t, ints_of(i, o, CT_T), n, rnea_t, tau_ext_t, v_t)
    age_h, age_t = ints_of(i, o, FB_H)[FB_AGE_TICKS], ints_of(i, o, FB_T)[FB_AGE_TICKS]
    # step 7, safety: nothing unchecked reaches a motor (may saturate the torques in place)
    code = supervise(
        ints_of(i, o, SUPERVISOR), floats_of(f, o, GUARD_H), ints_of(i, o, GUARD_H),
        floats_of(f, o, GUARD_T), ints_of(i, o, GUARD_T), n,
        q_h, v_h, age_h, tau_h, vec(ct_h, TAU, n), vec(ct_h, A_DES, n),
        q_t, v_t, age_t, tau_ext_t, vec(ct_t, TAU, n), vec(ct_t, A_DES, n),
    )  # fmt: skip
    if code:
        return code
    accumulate(
        floats_of(f, o, METRICS), ints_of(i, o, METRICS), n,
        q_h, q_t, vec(sig, TAU_H, n), vec(sig, TAU_E, n),
    )  # fmt: skip
    return 0
