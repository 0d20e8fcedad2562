"""The COM two-port as a whole: the passivity monitor of eq 7-8 over both ports, and a
standalone two-port (both ports and an in-process link in one object) for the analysis and
tests.

In a session each site holds its own port (``teleop_rt.com.port``) and a link carries packets
between them (``teleop_rt.com.link``). Where both ports are in one process, the
``ChannelMonitor`` sees both: the power entering the two-port, ``omega_c tau_c - omega_t tau_t``
per joint, integrated every tick (eq 7), and its running minimum. With the received-wave filter
off, the energy that entered equals the wave energy held in the link's lines every tick.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.exchange import link_exchange, port_stage
from teleop_rt.com.link import InProcessLink, link_offsets, link_push
from teleop_rt.com.port import HSI, TO, Packet, Port, port_input
from teleop_rt.declarations import (
    DEFAULT_RECONSTRUCTION,
    DIRECT,
    MODES,
    RECONSTRUCTIONS,
    WAVE,
    WAVE_DRIFT_TIME_S,
    WAVE_SKIP_TIME_S,
    ChannelMode,
    Reconstruction,
)
from teleop_rt.flat import Block, Packed, Scalar, Vector, as_floats, floats_of, ints_of, jit

__all__ = ["DIRECT", "WAVE", "ChannelMonitor", "TwoPort", "monitor_step", "two_port_step"]


class ChannelMonitor(Block):
    """Power and energy entering the two-port (eq 7, 8), from both ports' variables."""

    power = Vector("omega_c tau_c - omega_t tau_t per joint, W")
    energy = Vector("its integral per joint, J")
    total_energy = Scalar("sum over joints, J")
    min_total_energy = Scalar("its running minimum, J (NaN counts as a new minimum)")
    dt = Scalar(param=True)

    def __init__(self, n: int, dt: float) -> None:
        super().__init__(n)
        self.dt = dt


@jit
def monitor_step(f: np.ndarray, n: int, port_h: np.ndarray, port_t: np.ndarray) -> None:
    """Update power, energy (per joint), total_energy and its running minimum (a diverged
    channel, NaN, never looks passive). Indexed by offset: it runs every tick."""
    Pt, Cm = Port.idx, ChannelMonitor.idx
    s = Cm.N_VECTORS * n
    dt = f[s + Cm.DT]
    total = 0.0
    for j in range(n):
        p = (
            port_h[Pt.FLOW * n + j] * port_h[Pt.EFFORT * n + j]
            - port_t[Pt.FLOW * n + j] * port_t[Pt.EFFORT * n + j]
        )
        f[Cm.POWER * n + j] = p
        f[Cm.ENERGY * n + j] += p * dt
        total += f[Cm.ENERGY * n + j]
    f[s + Cm.TOTAL_ENERGY] = total
    if not total >= f[s + Cm.MIN_TOTAL_ENERGY]:
        f[s + Cm.MIN_TOTAL_ENERGY] = total


# the standalone two-port's blocks, in its packed buffers
TP_PORT_H, TP_PORT_T, TP_TX_H, TP_RX_H, TP_TX_T, TP_RX_T, TP_LINK, TP_MONITOR = range(8)


class TwoPort:
    """Both ports, an in-process link and the monitor, stepped as one two-port (the paper's
    COM block): ``step(omega_c, tau_t)`` gives ``tau_c`` and ``omega_t``. The same compiled
    pieces as a session's sites and link, on buffers of its own."""

    def __init__(self, n: int, port_h: Port, port_t: Port, delay_ticks: int, dt: float) -> None:
        self.n, self.dt, self.delay_ticks = n, dt, delay_ticks
        self.port_h, self.port_t = port_h, port_t
        self.tx_h, self.rx_h, self.tx_t, self.rx_t = (Packet(n) for _ in range(4))
        self.link = InProcessLink(n, delay_ticks)
        self.monitor = ChannelMonitor(n, dt)
        blocks = [port_h, port_t, self.tx_h, self.rx_h, self.tx_t, self.rx_t, self.link]
        self.packed = Packed([*blocks, self.monitor])
        self._at = link_offsets(self.packed.offsets, TP_LINK, TP_TX_H, TP_RX_H, TP_TX_T, TP_RX_T)

    # the signals under the paper's names
    omega_c = property(lambda self: self.port_h.flow)
    tau_c = property(lambda self: self.port_h.effort)
    omega_t = property(lambda self: self.port_t.flow)
    tau_t = property(lambda self: self.port_t.effort)
    u_l = property(lambda self: self.port_h.wave_out)
    v_l = property(lambda self: self.port_h.wave_in)
    u_r = property(lambda self: self.port_t.wave_in)
    v_r = property(lambda self: self.port_t.wave_out)
    power = property(lambda self: self.monitor.power)
    energy = property(lambda self: self.monitor.energy)
    total_energy = property(lambda self: self.monitor.total_energy)
    min_total_energy = property(lambda self: self.monitor.min_total_energy)
    b = property(lambda self: self.port_h.b)

    def stored_energy(self) -> float:
        """Wave energy held in the link's lines (0 for a channel of no waves)."""
        if self.port_h.mode != WAVE:
            return 0.0
        return self.link.stored_wave_energy(self.dt)

    def step(self, omega_c: list[float] | np.ndarray, tau_t: list[float] | np.ndarray) -> None:
        """One tick: take the HSI velocity and the TO torque, produce tau_c and omega_t."""
        p = self.packed
        two_port_step(p.f, p.i, p.offsets, self._at, self.n, as_floats(omega_c), as_floats(tau_t))


@jit
def two_port_step(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, at: np.ndarray, n: int, omega_c: np.ndarray,
    tau_t: np.ndarray,
) -> None:  # fmt: skip
    """A tick of both ports, the link and the monitor: the port stages of a lock-step pair
    (``teleop_rt.tick_stages.TWO_PORT``), the port inputs given instead of sensed."""
    Pk = Packet.idx
    ph, pih = floats_of(f, o, TP_PORT_H), ints_of(i, o, TP_PORT_H)
    pt, pit = floats_of(f, o, TP_PORT_T), ints_of(i, o, TP_PORT_T)
    tx_h, rx_h = floats_of(f, o, TP_TX_H), floats_of(f, o, TP_RX_H)
    tx_t, rx_t = floats_of(f, o, TP_TX_T), floats_of(f, o, TP_RX_T)
    port_input(ph, pih, n, omega_c, tx_h)
    port_input(pt, pit, n, tau_t, tx_t)
    for tx in (TP_TX_H, TP_TX_T):  # tick and sequence number count from 0, as a site's do
        ints_of(i, o, tx)[Pk.VALID] = 1
        ints_of(i, o, tx)[Pk.ENGAGED] = 1  # (no operator map: always coupled)
    link_exchange(f, i, at, n, ph, pih, pt, pit)
    port_stage(ph, pih, n, rx_h, ints_of(i, o, TP_RX_H), tx_h, ints_of(i, o, TP_TX_H))
    port_stage(pt, pit, n, rx_t, ints_of(i, o, TP_RX_T), tx_t, ints_of(i, o, TP_TX_T))
    link_push(f, i, at, n)
    for tx in (TP_TX_H, TP_TX_T):
        tx_i = ints_of(i, o, tx)
        tx_i[Pk.TICK] += 1
        tx_i[Pk.SEQ] += 1
    monitor_step(floats_of(f, o, TP_MONITOR), n, ph, pt)


def make_port(
    side: int, mode: ChannelMode, wave_impedance: list[float], delay_ticks: int, dt: float,
    filter_hz: float | None, reconstruction: Reconstruction = DEFAULT_RECONSTRUCTION,
    drift_time_s: float | None = None, wave_drift_time_s: float = WAVE_DRIFT_TIME_S,
    wave_skip_time_s: float | None = WAVE_SKIP_TIME_S, wave_impedance_schedule: bool = False,
) -> Port:  # fmt: skip
    """Site ``side``'s port of a channel of ``mode`` ('wave', 'tdpa' or 'direct'; a wave
    channel's ``reconstruction`` of missing waves: 'bounded', 'corrected', 'reflected', 'zero',
    'hold' or 'integral'; TDPA's drift compensation time constant, None: off; the wave
    integral's pay-back time constant of 'corrected' and 'reflected', and that of the part a
    change of the delay brought under the newest playout; the wave impedance scheduled by
    the delay, ``teleop_rt.com.port.schedule_b``)."""
    return Port(side, wave_impedance, delay_ticks, dt, MODES[mode], filter_hz,
                RECONSTRUCTIONS[reconstruction], drift_time_s, wave_drift_time_s,
                wave_skip_time_s, wave_impedance_schedule)  # fmt: skip


def make_ports(
    mode: ChannelMode, wave_impedance: list[float], delay_ticks: int, dt: float,
    filter_hz: float | None, reconstruction: Reconstruction = DEFAULT_RECONSTRUCTION,
    drift_time_s: float | None = None, wave_drift_time_s: float = WAVE_DRIFT_TIME_S,
    wave_skip_time_s: float | None = WAVE_SKIP_TIME_S, wave_impedance_schedule: bool = False,
) -> tuple[Port, Port]:  # fmt: skip
    """The HSI's and the TO's port of a channel of ``mode`` (a two-port in one object)."""
    args = (mode, wave_impedance, delay_ticks, dt, filter_hz, reconstruction, drift_time_s,
            wave_drift_time_s, wave_skip_time_s, wave_impedance_schedule)  # fmt: skip
    return make_port(HSI, *args), make_port(TO, *args)
