"""The compiled parts of one site's tick (one robot's loop), around the Pinocchio call:

    site_sense:          measured values finite; tau_h or tau_e; the port's input, into the
                         outgoing packet
    (the link)           the packet this site uses this tick, into its rx block
    site_before_models:  the port (eq 9, 10) on rx, between the codec's receive and send
                         stages (teleop_rt.com.codec; idle without one); the error; C1
                         or C2 (eq 4, 14); M_v^-1 a_ref
    (Python)             RNEA at M_v^-1 a_ref
    site_after_models:   computed torque (eq 2, 12); the site's safety checks and saturation

All take the site's blocks (``SITE_ORDER``) in packed buffers through their offsets ``o``: the
site's own buffers when it runs alone, or its part of a one-process session's
(``teleop_rt.lockstep``). The HSI and the TO differ only in the port's side and in the
controller's error: ``tau_h - tau_c`` on the HSI, ``omega_t - v_t`` on the TO.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.codec import codec_receive, codec_send
from teleop_rt.com.port import EFFORT, FLOW, HSI, P_SEQ, P_TICK, P_VALID, port_input, port_step
from teleop_rt.control import A_DES, OUT, TAU, ct_finish, ct_prepare, pid_step
from teleop_rt.flat import Block, Int, Vector, floats_of, ints_of, jit, vec
from teleop_rt.hal.base import FB_AGE_TICKS, FB_Q, FB_TAU_EXT, FB_V
from teleop_rt.safety import guard_site, measured_fault

SITE_ORDER = ("feedback", "signals", "port", "tx", "rx", "controller", "computed_torque",
              "guard", "world")  # fmt: skip
FB, SIG, PORT, TX, RX, PID, CT, GUARD, WORLD = range(len(SITE_ORDER))
SITE_BLOCKS = len(SITE_ORDER)


class SiteSignals(Block):
    """A site's own per-tick signals."""

    tau = Vector("tau_h (operator on the HSI, measured) or tau_e (TO on the environment)")
    error = Vector("the controller's input: tau_h - tau_c (HSI) or omega_t - v_t (TO)")
    tick = Int("the site's tick")
    side = Int("HSI or TO", param=True)

    def __init__(self, n: int, side: int) -> None:
        super().__init__(n)
        self.side = side


S_TAU, S_ERROR, S_TICK, S_SIDE = (
    SiteSignals.tau.k, SiteSignals.error.k, SiteSignals.tick.k, SiteSignals.side.k
)  # fmt: skip


@jit
def site_sense(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> int:
    """From the fresh feedback to the outgoing packet's port input; a non-finite measurement
    is a finding (returned) before anything is computed or sent from it."""
    fb = floats_of(f, o, FB)
    q, v, tau_ext = vec(fb, FB_Q, n), vec(fb, FB_V, n), vec(fb, FB_TAU_EXT, n)
    code = measured_fault(floats_of(f, o, GUARD), ints_of(i, o, GUARD), n, q, v, tau_ext)
    if code:
        return code
    sig, si = floats_of(f, o, SIG), o[2 * SIG + 1]  # (ints by offset: a slice costs more)
    port, port_i, tx = floats_of(f, o, PORT), ints_of(i, o, PORT), floats_of(f, o, TX)
    tau = vec(sig, S_TAU, n)
    if i[si + S_SIDE] == HSI:  # tau_h = tau_ext; the port's flow omega_c = v_h
        for j in range(n):
            tau[j] = tau_ext[j]
        port_input(port, port_i, n, v, tx)
    else:  # tau_e = -tau_ext; the port's effort tau_t = tau_e
        for j in range(n):
            tau[j] = -tau_ext[j]
        port_input(port, port_i, n, tau, tx)
    ti = o[2 * TX + 1]
    i[ti + P_TICK] = i[si + S_TICK]
    i[ti + P_SEQ] = i[si + S_TICK]
    i[ti + P_VALID] = 1
    return 0


@jit
def site_before_models(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> None:
    """From the received packet to the acceleration the model is evaluated at."""
    port, port_i = floats_of(f, o, PORT), ints_of(i, o, PORT)
    rx, rx_i, tx = floats_of(f, o, RX), ints_of(i, o, RX), floats_of(f, o, TX)
    codec_receive(port, port_i, n, rx, rx_i)
    port_step(port, port_i, n, rx, rx_i, tx)
    codec_send(port, port_i, n, tx, ints_of(i, o, TX))
    sig = floats_of(f, o, SIG)
    error, tau = vec(sig, S_ERROR, n), vec(sig, S_TAU, n)
    if i[o[2 * SIG + 1] + S_SIDE] == HSI:  # M1 a_h = C1(tau_h - tau_c)
        tau_c = vec(port, EFFORT, n)
        for j in range(n):
            error[j] = tau[j] - tau_c[j]
    else:  # M2 a_t = C2(omega_t - v_t)
        omega_t, v = vec(port, FLOW, n), vec(floats_of(f, o, FB), FB_V, n)
        for j in range(n):
            error[j] = omega_t[j] - v[j]
    pid = floats_of(f, o, PID)
    pid_step(pid, ints_of(i, o, PID), n, error)
    ct_prepare(floats_of(f, o, CT), n, vec(pid, OUT, n))


@jit
def site_after_models(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, rnea: np.ndarray) -> int:
    """From the model's RNEA to the checked motor torque; the safety finding (0: none)."""
    fb, ct = floats_of(f, o, FB), floats_of(f, o, CT)
    q, v, tau_ext = vec(fb, FB_Q, n), vec(fb, FB_V, n), vec(fb, FB_TAU_EXT, n)
    ct_finish(ct, ints_of(i, o, CT), n, rnea, tau_ext, v)
    i[o[2 * SIG + 1] + S_TICK] += 1
    # nothing unchecked reaches a motor (may saturate the torque in place)
    return guard_site(
        floats_of(f, o, GUARD), ints_of(i, o, GUARD), n, q, v, i[o[2 * FB + 1] + FB_AGE_TICKS],
        vec(ct, TAU, n), vec(ct, A_DES, n),
    )  # fmt: skip
