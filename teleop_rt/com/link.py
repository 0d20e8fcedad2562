"""Links: what carries packets (``teleop_rt.com.port.Packet``) between the two sites' ports.

A link takes one packet per tick from each site (``send``) and gives each site, at its tick,
the packet to use then (``receive``): the peer's packet of some earlier tick, or a zero packet
(``valid = 0``) when nothing is due. Whatever happens to packets on the way (late, early, twice,
out of order, never) is the link's business; a port only ever sees one packet per tick, and a
zero one is passive.

``InProcessLink`` is the paper's eq 10 with a constant delay of D whole ticks, as two delay
lines (zeros until filled, like Drake's DiscreteTimeDelay). D = 0 hands each site the peer's
packet of the same tick: the sites must both have sent before either receives (the one-process
session steps them in lock-step, sense then update). It is also a compiled block, so that the
lock-step session runs the exchange inside its tick kernel (``link_deliver``, ``link_push``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from teleop_rt.com.port import HSI, N_PACKET_VECTORS, P_WAVE, Packet
from teleop_rt.flat import Block, Int, jit, jit_inline

N_PACKET_SCALARS, N_PACKET_INTS = len(Packet.SCALARS), len(Packet.INTS)


@jit_inline
def packet_floats(n: int) -> int:
    return N_PACKET_VECTORS * n + N_PACKET_SCALARS


@jit_inline
def entry_size(n: int) -> int:
    """Floats per packet held in a delay line: its floats, then its ints (exact as float64)."""
    return N_PACKET_VECTORS * n + N_PACKET_SCALARS + N_PACKET_INTS


class Link(ABC):
    """Carries packets between the HSI's port (side 0) and the TO's (side 1).

    Per tick and site: ``send`` the site's packet once its port input is set (a link with no
    delay hands it to the peer in the same tick), ``receive`` the packet due, and ``end_tick``
    once the packet is complete (its wave and energy written): only then may it travel."""

    @abstractmethod
    def send(self, side: int, packet: Packet) -> None:
        """Site ``side``'s packet of this tick (read by the link until ``end_tick``)."""

    @abstractmethod
    def receive(self, side: int, into: Packet) -> None:
        """The packet site ``side`` uses this tick into ``into`` (zeros if none is due)."""

    @abstractmethod
    def end_tick(self, side: int) -> None:
        """Site ``side``'s packet of this tick is complete."""


class InProcessLink(Block, Link):
    """A constant delay of ``delay_ticks`` whole ticks each way (forward line: HSI to TO)."""

    delay_ticks = Int("D, ticks", param=True)
    slot = Int("this tick's slot of both lines")

    def __init__(self, n: int, delay_ticks: int) -> None:
        if delay_ticks < 0:
            raise ValueError("delay_ticks must be >= 0")
        super().__init__(n, tail=2 * delay_ticks * entry_size(n))
        self.delay_ticks = delay_ticks
        self._sent: list[Packet | None] = [None, None]  # this tick's packets
        self._ended = [False, False]

    def stored_wave_energy(self, dt: float) -> float:
        """Wave energy held in the lines: dt/2 times the sum of squares of the waves in flight."""
        e, n = entry_size(self.n), self.n
        lines = self.f[self.tail_start :].reshape(-1, e)
        waves = lines[:, P_WAVE * n : (P_WAVE + 1) * n]
        return 0.5 * dt * float(np.sum(waves * waves))

    # --- the Link interface, for sites stepped from Python (a session's lock-step tick runs
    # the same exchange compiled: link_deliver, link_push) ------------------------------------
    def send(self, side: int, packet: Packet) -> None:
        self._sent[side] = packet

    def receive(self, side: int, into: Packet) -> None:
        if self.delay_ticks:
            line_load(self.f, self.i, self.n, 1 - side, into.f, into.i)
            return
        sent = self._sent[1 - side]
        if sent is None:
            raise RuntimeError("with no delay both sites must send before either receives")
        into.f[:], into.i[:] = sent.f, sent.i

    def end_tick(self, side: int) -> None:
        self._ended[side] = True
        if not all(self._ended):
            return  # the lines move once both sites have used this tick's slot
        if self.delay_ticks:
            for sender, packet in enumerate(self._sent):
                assert packet is not None
                line_store(self.f, self.i, self.n, sender, packet.f, packet.i)
            advance_slot(self.i)
        self._sent, self._ended = [None, None], [False, False]


SLOT, DELAY = InProcessLink.slot.k, InProcessLink.delay_ticks.k


@jit
def _line_start(i: np.ndarray, n: int, sender: int) -> int:
    """Float index of this tick's slot in the line of packets from ``sender`` (the block has
    no vectors or scalars: the lines are its whole float buffer, forward then backward)."""
    d = i[DELAY]
    return (sender * d + i[SLOT]) * entry_size(n)


@jit
def line_store(
    f: np.ndarray, i: np.ndarray, n: int, sender: int, pf: np.ndarray, pi: np.ndarray
) -> None:
    """Put the packet (pf, pi) from ``sender`` into this tick's slot of its line."""
    s, m = _line_start(i, n, sender), packet_floats(n)
    for k in range(m):
        f[s + k] = pf[k]
    for k in range(N_PACKET_INTS):
        f[s + m + k] = pi[k]


@jit
def line_load(
    f: np.ndarray, i: np.ndarray, n: int, sender: int, pf: np.ndarray, pi: np.ndarray
) -> None:
    """The packet from ``sender`` held in this tick's slot (pushed D ticks ago; zeros before)."""
    s, m = _line_start(i, n, sender), packet_floats(n)
    for k in range(m):
        pf[k] = f[s + k]
    for k in range(N_PACKET_INTS):
        pi[k] = np.int64(f[s + m + k])


@jit
def advance_slot(i: np.ndarray) -> None:
    slot = i[SLOT] + 1
    i[SLOT] = 0 if slot == i[DELAY] else slot


@jit
def link_deliver(
    lf: np.ndarray, li: np.ndarray, n: int,
    tx_h: np.ndarray, txi_h: np.ndarray, rx_h: np.ndarray, rxi_h: np.ndarray,
    tx_t: np.ndarray, txi_t: np.ndarray, rx_t: np.ndarray, rxi_t: np.ndarray,
) -> None:  # fmt: skip
    """Each site's packet of this tick: the peer's of this tick (D = 0), else of D ticks ago."""
    if li[DELAY] == 0:
        m = packet_floats(n)
        for k in range(m):
            rx_t[k] = tx_h[k]
            rx_h[k] = tx_t[k]
        for k in range(N_PACKET_INTS):
            rxi_t[k] = txi_h[k]
            rxi_h[k] = txi_t[k]
    else:
        line_load(lf, li, n, HSI, rx_t, rxi_t)
        line_load(lf, li, n, 1 - HSI, rx_h, rxi_h)


@jit
def link_push(
    lf: np.ndarray, li: np.ndarray, n: int,
    tx_h: np.ndarray, txi_h: np.ndarray, tx_t: np.ndarray, txi_t: np.ndarray,
) -> None:  # fmt: skip
    """This tick's packets into the lines (after both ports have written their waves)."""
    if li[DELAY]:
        line_store(lf, li, n, HSI, tx_h, txi_h)
        line_store(lf, li, n, 1 - HSI, tx_t, txi_t)
        advance_slot(li)
