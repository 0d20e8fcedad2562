"""One site's port of the COM two-port, and the packets the two ports exchange.

The paper's channel (eq 8-10) has a port at each site. The HSI's port takes the flow
``omega_c = v_h`` and gives the effort ``tau_c``; the TO's takes the effort ``tau_t = tau_e``
and gives the flow ``omega_t``. Each port knows only its own variables and what reaches it in
packets from the other (``Packet``: the sender's tick, sequence number, its port input ``x``,
its outgoing wave and the energy that has crossed its port). The wave transform of eq 9, solved
for what each side knows in its tick (derivation in ``teleop_rt.com.wave``):

    HSI:  tau_c = b omega_c - sqrt(2b) v_l          u_l = sqrt(2b) omega_c - v_l
    TO:   omega_t = (sqrt(2b) u_r - tau_t) / b      v_r = u_r - sqrt(2/b) tau_t

where the received wave (v_l at the HSI, u_r at the TO) is the peer's sent wave through the
optional first-order low-pass. With no delay the ports couple directly (tau_c = tau_t,
omega_t = omega_c, from the peer's port input of the same tick); the direct channel mode is
plain delayed force feedback (the peer's port input, delayed). What the link did not deliver is
a zero packet (a zero wave is passive; holding the last one is not).

Each port also integrates the power into the channel at its side (eq 8): ``omega_c tau_c`` at
the HSI, ``-omega_t tau_t`` at the TO; their sum is the channel's energy (eq 7).
"""

from __future__ import annotations

import math

import numpy as np

from teleop_rt.flat import Block, Int, Scalar, Vector, jit, vec

HSI, TO = 0, 1  # a port's side
DIRECT, WAVE = 0, 1  # channel modes


class Packet(Block):
    """What one site sends the other per tick (the link's unit); zeros mean none arrived."""

    x = Vector("the sender's port input: omega_c from the HSI, tau_t from the TO")
    wave = Vector("the sender's outgoing wave: u_l from the HSI, v_r from the TO")
    energy = Scalar("energy that has crossed the sender's port, J (cumulative)")
    tick = Int("the sender's tick")
    seq = Int("sequence number")
    valid = Int("1: a packet; 0: none arrived")


class Port(Block):
    """One side's port: its wave transform and the energy that crossed it."""

    b = Vector("wave impedance per joint, N m s/rad", param=True)
    sqrt_2b = Vector(param=True)
    sqrt_2_over_b = Vector(param=True)
    flow = Vector("omega: the HSI's input (omega_c), the TO's output (omega_t), rad/s")
    effort = Vector("tau: the HSI's output (tau_c), the TO's input (tau_t), N m")
    wave_out = Vector("the wave this port sends: u_l (HSI), v_r (TO)")
    wave_in = Vector("the wave received, after the optional filter: v_l (HSI), u_r (TO)")
    power = Vector("power into the channel at this port, W")
    energy = Vector("its integral per joint, J")
    total_energy = Scalar("sum over joints, J")
    alpha = Scalar("received-wave low-pass coefficient", param=True)
    dt = Scalar(param=True)
    side = Int("HSI or TO", param=True)
    mode = Int("DIRECT or WAVE", param=True)
    delay_ticks = Int("nominal one-way delay; 0 couples directly", param=True)
    filtered = Int("1: received waves are low-passed", param=True)

    def __init__(
        self,
        side: int,
        wave_impedance: list[float],
        delay_ticks: int,
        dt: float,
        mode: int = WAVE,
        filter_hz: float | None = None,
    ) -> None:
        b = [float(x) for x in wave_impedance]
        if mode == WAVE and any(not x > 0 for x in b):
            raise ValueError("wave impedance b must be > 0 on every joint")
        if delay_ticks < 0:
            raise ValueError("delay_ticks must be >= 0")
        super().__init__(len(b))
        self.side, self.mode, self.delay_ticks, self.dt = side, mode, delay_ticks, dt
        if mode == WAVE:
            self.b[:] = b
            self.sqrt_2b[:] = [math.sqrt(2.0 * x) for x in b]
            self.sqrt_2_over_b[:] = [math.sqrt(2.0 / x) for x in b]
        # the filter acts on received waves; with no delay there are none (direct coupling)
        self.filter_hz = filter_hz if delay_ticks > 0 and mode == WAVE else None
        self.filtered = int(self.filter_hz is not None)
        self.alpha = 1.0
        if self.filter_hz:
            self.alpha = 1.0 - math.exp(-2.0 * math.pi * self.filter_hz * dt)


# indices for the kernels, derived from the declarations above
P_X, P_WAVE = Packet.x.k, Packet.wave.k
P_ENERGY = Packet.energy.k  # scalar, after the vectors
P_TICK, P_SEQ, P_VALID = Packet.tick.k, Packet.seq.k, Packet.valid.k
N_PACKET_VECTORS = len(Packet.VECTORS)
B, SQRT_2B, SQRT_2_OVER_B = Port.b.k, Port.sqrt_2b.k, Port.sqrt_2_over_b.k
FLOW, EFFORT, WAVE_OUT, WAVE_IN = Port.flow.k, Port.effort.k, Port.wave_out.k, Port.wave_in.k
POWER, ENERGY = Port.power.k, Port.energy.k
TOTAL_ENERGY, ALPHA, DT = Port.total_energy.k, Port.alpha.k, Port.dt.k
SIDE, MODE, DELAY, FILTERED = Port.side.k, Port.mode.k, Port.delay_ticks.k, Port.filtered.k
N_PORT_VECTORS = len(Port.VECTORS)


@jit
def port_input(f: np.ndarray, i: np.ndarray, n: int, x: np.ndarray, tx: np.ndarray) -> None:
    """This tick's port input x (omega_c at the HSI, tau_t at the TO) into the port and into
    the outgoing packet (before the exchange: with no delay the peer needs it this tick)."""
    own = vec(f, FLOW, n) if i[SIDE] == HSI else vec(f, EFFORT, n)
    out = vec(tx, P_X, n)
    for j in range(n):
        own[j] = x[j]
        out[j] = x[j]


@jit
def port_step(f: np.ndarray, i: np.ndarray, n: int, rx: np.ndarray, tx: np.ndarray) -> None:
    """The port's output from the received packet rx; the outgoing wave into tx; the power
    and energy that crossed the port."""
    flow, effort = vec(f, FLOW, n), vec(f, EFFORT, n)
    hsi = i[SIDE] == HSI
    peer_x = vec(rx, P_X, n)
    if i[DELAY] == 0 or i[MODE] == DIRECT:
        # direct coupling (no delay) or plain delayed force feedback: the peer's port input
        out = effort if hsi else flow
        for j in range(n):
            out[j] = peer_x[j]
    else:
        s = N_PORT_VECTORS * n
        alpha, filtered = f[s + ALPHA], i[FILTERED] != 0
        b, s2b, s2ob = vec(f, B, n), vec(f, SQRT_2B, n), vec(f, SQRT_2_OVER_B, n)
        w_in, w_out, received = vec(f, WAVE_IN, n), vec(f, WAVE_OUT, n), vec(rx, P_WAVE, n)
        sent = vec(tx, P_WAVE, n)
        for j in range(n):
            if filtered:
                w_in[j] += alpha * (received[j] - w_in[j])
            else:
                w_in[j] = received[j]
            if hsi:  # tau_c = b omega_c - sqrt(2b) v_l ; u_l = sqrt(2b) omega_c - v_l
                effort[j] = b[j] * flow[j] - s2b[j] * w_in[j]
                w_out[j] = s2b[j] * flow[j] - w_in[j]
            else:  # omega_t = (sqrt(2b) u_r - tau_t) / b ; v_r = u_r - sqrt(2/b) tau_t
                flow[j] = (s2b[j] * w_in[j] - effort[j]) / b[j]
                w_out[j] = w_in[j] - s2ob[j] * effort[j]
            sent[j] = w_out[j]
    account_port_power(f, i, n, tx)


@jit
def account_port_power(f: np.ndarray, i: np.ndarray, n: int, tx: np.ndarray) -> None:
    """Power into the channel at this port (omega_c tau_c, or -omega_t tau_t), its integral,
    and the energy in the outgoing packet."""
    flow, effort = vec(f, FLOW, n), vec(f, EFFORT, n)
    power, energy = vec(f, POWER, n), vec(f, ENERGY, n)
    s = N_PORT_VECTORS * n
    dt, sign = f[s + DT], 1.0 if i[SIDE] == HSI else -1.0
    total = 0.0
    for j in range(n):
        p = sign * flow[j] * effort[j]
        power[j] = p
        energy[j] += p * dt
        total += energy[j]
    f[s + TOTAL_ENERGY] = total
    tx[N_PACKET_VECTORS * n + P_ENERGY] = total
