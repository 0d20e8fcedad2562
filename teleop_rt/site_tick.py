"""The compiled parts of one site's tick (one robot's loop), around the Pinocchio call (each
kernel a run of consecutive stages of ``teleop_rt.tick_stages``):

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
(``teleop_rt.lockstep``); within a block, by the block's own index namespace (``Port.idx``).
The HSI and the TO differ only in the port's side and in the controller's error: ``tau_h -
tau_c`` on the HSI, ``omega_t - v_t`` on the TO.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.exchange import port_stage
from teleop_rt.com.port import HSI, Packet, Port, port_input
from teleop_rt.control import ComputedTorque, Pid, ct_finish, ct_prepare, pid_step
from teleop_rt.flat import Block, Int, Vector, floats_of, ints_of, jit, vec
from teleop_rt.hal.signals import Feedback
from teleop_rt.mapping import (
    JOINT,
    Mapping,
    hsi_map_input,
    hsi_plane_input,
    hsi_plane_render,
    mapping_engage,
    to_frame_force,
    to_map_gain,
    to_map_input,
    to_map_output,
    to_plane_input,
    to_plane_output,
    to_posture,
)
from teleop_rt.safety import guard_site, measured_fault
from teleop_rt.task_limits import to_speed_ceiling, to_speed_limit, to_tool_sense

SITE_ORDER = ("feedback", "signals", "port", "tx", "rx", "controller", "computed_torque",
              "guard", "world", "mapping")  # fmt: skip
FB, SIG, PORT, TX, RX, PID, CT, GUARD, WORLD, MAP = range(len(SITE_ORDER))
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


@jit
def site_sense(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> int:
    """From the fresh feedback to the outgoing packet's port input; a non-finite measurement
    is a finding (returned) before anything is computed or sent from it. ``n``: the port's
    size (the robot's joints, or the task's dimension: the mapping's ``joints`` says)."""
    Fb, Ss, Pt, Pk, Mp = Feedback.idx, SiteSignals.idx, Port.idx, Packet.idx, Mapping.idx
    nj = i[o[2 * MAP + 1] + Mp.JOINTS]
    fb = floats_of(f, o, FB)
    q, v, tau_ext = vec(fb, Fb.Q, nj), vec(fb, Fb.V, nj), vec(fb, Fb.TAU_EXT, nj)
    code = measured_fault(floats_of(f, o, GUARD), ints_of(i, o, GUARD), nj, q, v, tau_ext)
    if code:
        return code
    sig, si = floats_of(f, o, SIG), o[2 * SIG + 1]  # (ints by offset: a slice costs more)
    port, port_i, tx = floats_of(f, o, PORT), ints_of(i, o, PORT), floats_of(f, o, TX)
    tau = vec(sig, Ss.TAU, nj)
    mapped = i[o[2 * MAP + 1] + Mp.ACTIVE] != 0  # (the identity: the ports take v_h, tau_e)
    mf, mi = floats_of(f, o, MAP), ints_of(i, o, MAP)
    if i[si + Ss.SIDE] == HSI:  # tau_h = tau_ext; the port's flow omega_c = v_h
        for j in range(nj):
            tau[j] = tau_ext[j]
        if mapped:  # omega_c = r v_h (teleop_rt.mapping)
            code = mapping_engage(
                mf, mi, n, i[si + Ss.TICK], vec(port, Pt.EFFORT, n), i[o[2 * FB + 1] + Fb.INPUTS]
            )
            if code:
                return code
            if mi[Mp.SPACE] != JOINT:  # (task space: the plane, position or pose)
                hsi_plane_input(mf, mi, n, v, tau)
            else:
                hsi_map_input(mf, n, q, v)
            port_input(port, port_i, n, vec(mf, Mp.X, n), tx)
        else:
            port_input(port, port_i, n, v, tx)
    else:  # tau_e = -tau_ext; the port's effort tau_t = tau_e
        for j in range(nj):
            tau[j] = -tau_ext[j]
        if mapped:  # tau_t = r beta tau_e
            limited = mi[Mp.LIMITS] != 0  # (the tool's limits in the plane: task_limits)
            if mi[Mp.SPACE] != JOINT:
                to_plane_input(mf, mi, n, tau)
                if limited:
                    code = to_tool_sense(mf, mi, n, v)
                    if code:
                        return code
                to_frame_force(mf, mi, n)  # (framed: R^T, into the HSI's frame)
            else:
                to_map_input(mf, n, tau)
            mapping_engage(mf, mi, n, i[si + Ss.TICK], vec(mf, Mp.TAU_MAPPED, n), 0)
            if limited:
                to_speed_ceiling(mf, n)
            to_map_gain(mf, n)
            port_i[Pt.TERMINATED] = mf[Mp.N_VECTORS * n + Mp.GAIN] == 0.0
            port_input(port, port_i, n, vec(mf, Mp.X, n), tx)
        else:
            port_input(port, port_i, n, tau, tx)
    ti = o[2 * TX + 1]
    i[ti + Pk.TICK] = i[si + Ss.TICK]
    i[ti + Pk.SEQ] = i[si + Ss.TICK]
    i[ti + Pk.VALID] = 1
    i[ti + Pk.ENGAGED] = i[o[2 * MAP + 1] + Mp.COUPLED] if mapped else 1  # (the peer follows it)
    return 0


@jit
def site_before_models(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> None:
    """From the received packet to the acceleration the model is evaluated at."""
    Fb, Ss, Pt, Pk, Pd, Mp = (
        Feedback.idx, SiteSignals.idx, Port.idx, Packet.idx, Pid.idx, Mapping.idx
    )  # fmt: skip
    port, port_i = floats_of(f, o, PORT), ints_of(i, o, PORT)
    rx, rx_i, tx = floats_of(f, o, RX), ints_of(i, o, RX), floats_of(f, o, TX)
    mi = o[2 * MAP + 1]
    if i[mi + Mp.FOLLOW] and rx_i[Pk.VALID] and rx_i[Pk.SEQ] > port_i[Pt.LAST_SEQ]:
        # the HSI's coupling state, from a packet that arrived (not the codec's hold): the
        # next tick's map decouples on it
        i[mi + Mp.PEER_ENGAGED] = rx_i[Pk.ENGAGED]
    port_stage(port, port_i, n, rx, rx_i, tx, ints_of(i, o, TX))
    nj = i[o[2 * MAP + 1] + Mp.JOINTS]  # (n: the port's size)
    sig = floats_of(f, o, SIG)
    error, tau = vec(sig, Ss.ERROR, nj), vec(sig, Ss.TAU, nj)
    mapped = i[o[2 * MAP + 1] + Mp.ACTIVE] != 0
    ms = Mp.N_VECTORS * n
    if i[o[2 * SIG + 1] + Ss.SIDE] == HSI:  # M1 a_h = C1(tau_h - tau_c)
        tau_c = vec(port, Pt.EFFORT, n)
        if mapped and ints_of(i, o, MAP)[Mp.SPACE] != JOINT:  # r J^T F_c
            hsi_plane_render(floats_of(f, o, MAP), ints_of(i, o, MAP), n, tau, tau_c, error)
        elif mapped:  # the rendered torque r tau_c
            r = floats_of(f, o, MAP)[ms + Mp.GAIN]
            for j in range(n):
                error[j] = tau[j] - r * tau_c[j]
        else:
            for j in range(n):
                error[j] = tau[j] - tau_c[j]
    else:  # M2 a_t = C2(omega_t - v_t)
        omega_t, v = vec(port, Pt.FLOW, n), vec(floats_of(f, o, FB), Fb.V, nj)
        if mapped and ints_of(i, o, MAP)[Mp.SPACE] != JOINT:  # r alpha J# omega_t
            mf, mi = floats_of(f, o, MAP), ints_of(i, o, MAP)
            to_plane_output(mf, mi, n, omega_t, v, error)
            if mf[ms + Mp.POSTURE_GAIN] > 0.0:  # a redundant TO's posture, in J's null space
                to_posture(mf, mi, n, vec(floats_of(f, o, FB), Fb.Q, nj), error)
            if mi[Mp.LIMITS]:
                to_speed_limit(mf, mi, n, omega_t, v)
        elif mapped:  # the velocity reference r alpha omega_t
            mf = floats_of(f, o, MAP)
            g = mf[ms + Mp.GAIN] * mf[ms + Mp.MOTION_SCALE]
            for j in range(n):
                error[j] = g * omega_t[j] - v[j]
            to_map_output(mf, n, vec(floats_of(f, o, FB), Fb.Q, n), omega_t)
        else:
            for j in range(n):
                error[j] = omega_t[j] - v[j]
    pid = floats_of(f, o, PID)
    pid_step(pid, ints_of(i, o, PID), nj, error)
    ct_prepare(floats_of(f, o, CT), nj, vec(pid, Pd.OUT, nj))


@jit
def site_after_models(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, rnea: np.ndarray) -> int:
    """From the model's RNEA to the checked motor torque; the safety finding (0: none)."""
    Fb, Ss, Ct, Mp = Feedback.idx, SiteSignals.idx, ComputedTorque.idx, Mapping.idx
    n = i[o[2 * MAP + 1] + Mp.JOINTS]  # (all joint-sized here)
    fb, ct = floats_of(f, o, FB), floats_of(f, o, CT)
    q, v, tau_ext = vec(fb, Fb.Q, n), vec(fb, Fb.V, n), vec(fb, Fb.TAU_EXT, n)
    ct_finish(ct, ints_of(i, o, CT), n, rnea, tau_ext, v)
    i[o[2 * SIG + 1] + Ss.TICK] += 1
    # nothing unchecked reaches a motor (may saturate the torque in place)
    return guard_site(
        floats_of(f, o, GUARD), ints_of(i, o, GUARD), n, q, v, i[o[2 * FB + 1] + Fb.AGE_TICKS],
        vec(ct, Ct.TAU, n), vec(ct, Ct.A_DES, n),
    )  # fmt: skip


@jit
def site_position(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> np.ndarray:
    """The position this site adds to T_p: q, or the mapped, indexed one (the HSI's
    alpha (q_h - offset), the TO's q_t + offset: ``teleop_rt.mapping``)."""
    Fb, Mp = Feedback.idx, Mapping.idx
    if i[o[2 * MAP + 1] + Mp.ACTIVE]:
        return vec(floats_of(f, o, MAP), Mp.Q_MAPPED, n)
    return vec(floats_of(f, o, FB), Fb.Q, n)


@jit
def site_torque(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> np.ndarray:
    """The torque this site adds to T_tau: tau_h or tau_e, or the mapped one (the TO's
    beta tau_e; in task space the tools' forces)."""
    Ss, Mp = SiteSignals.idx, Mapping.idx
    mi = o[2 * MAP + 1]
    if i[mi + Mp.ACTIVE] and (i[o[2 * SIG + 1] + Ss.SIDE] != HSI or i[mi + Mp.SPACE] != JOINT):
        return vec(floats_of(f, o, MAP), Mp.TAU_MAPPED, n)
    return vec(floats_of(f, o, SIG), Ss.TAU, n)
