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
There is one delay line: the ``Link`` methods, for sites stepped from Python, run the same
kernels (``line_put``, ``line_get``) on the link's own buffers.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from teleop_rt.com.port import HSI, Packet
from teleop_rt.declarations import require_delay_ticks
from teleop_rt.flat import Block, Int, jit, jit_inline


@jit_inline
def packet_floats(n: int) -> int:
    Pk = Packet.idx
    return Pk.N_VECTORS * n + Pk.N_SCALARS


@jit_inline
def entry_size(n: int) -> int:
    """Floats per packet held in a delay line: its floats, then its ints (exact as float64)."""
    Pk = Packet.idx
    return Pk.N_VECTORS * n + Pk.N_SCALARS + Pk.N_INTS


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
        super().__init__(n, tail=2 * require_delay_ticks(delay_ticks) * entry_size(n))
        self.delay_ticks = delay_ticks
        self._sent: list[Packet | None] = [None, None]  # this tick's packets
        self._ended = [False, False]

    def stored_wave_energy(self, dt: float) -> float:
        """Wave energy held in the lines: dt/2 times the sum of squares of the waves in flight."""
        Pk = Packet.idx
        e, n = entry_size(self.n), self.n
        lines = self.f[self.tail_start :].reshape(-1, e)
        waves = lines[:, Pk.WAVE * n : Pk.WAVE * n + n]
        return 0.5 * dt * float(np.sum(waves * waves))

    # --- the Link interface, for sites stepped from Python (a session's lock-step tick runs
    # the same exchange compiled: link_deliver, link_push) ------------------------------------
    def send(self, side: int, packet: Packet) -> None:
        self._sent[side] = packet

    def _slot(self, sender: int) -> np.ndarray:
        d, e = self.delay_ticks, entry_size(self.n)
        start = (sender * d + self.slot) * e
        return self.f[start : start + e]

    def receive(self, side: int, into: Packet) -> None:
        if self.delay_ticks:
            start = line_start(self.i, 0, 0, self.n, 1 - side)
            line_get(self.f, start, self.n, into.f, 0, into.i, 0)
            return
        sent = self._sent[1 - side]
        if sent is None:
            raise RuntimeError("with no delay both sites must send before either receives")
        into.f[:], into.i[:] = sent.f, sent.i

    def end_tick(self, side: int) -> None:
        self._ended[side] = True
        if not all(self._ended):
            return  # the lines move once both sites have used this tick's slot
        if self.delay_ticks:  # the compiled lines' own kernels: one delay line, two callers
            for sender, packet in enumerate(self._sent):
                assert packet is not None
                start = line_start(self.i, 0, 0, self.n, sender)
                line_put(self.f, start, self.n, packet.f, 0, packet.i, 0)
            next_slot(self.i, 0)
        self._sent, self._ended = [None, None], [False, False]


# The kernels below work on one pair of buffers (f, i) holding the link's block and the four
# packets, reached by offsets: ``at`` = (link float, link int, then float and int start of the
# HSI's tx, the HSI's rx, the TO's tx, the TO's rx); a slice per block would cost numba tens of
# ns each, more than the copies themselves.
LF, LI, TXH, RXH, TXT, RXT = 0, 1, 2, 4, 6, 8


@jit
def line_start(li: np.ndarray, link_i: int, link_f: int, n: int, sender: int) -> int:
    """Float index of this tick's slot in the line of packets from ``sender``; ``link_i``,
    ``link_f``: where the link's ints and floats start in ``li`` and its float buffer (the
    block has no vectors or scalars: the lines are its whole float buffer, forward then
    backward)."""
    Ln = InProcessLink.idx
    d = li[link_i + Ln.DELAY_TICKS]
    return link_f + (sender * d + li[link_i + Ln.SLOT]) * entry_size(n)


@jit
def line_put(
    lines: np.ndarray, s: int, n: int, pf: np.ndarray, pf0: int, pi: np.ndarray, pi0: int
) -> None:  # fmt: skip
    """The packet at ``pf[pf0:]``, ``pi[pi0:]`` into the slot at ``lines[s:]`` (one the codec
    did not send, as a zero packet: nothing travels)."""
    Pk = Packet.idx
    m = packet_floats(n)
    sent = pi[pi0 + Pk.UNSENT] == 0
    for k in range(m):
        lines[s + k] = pf[pf0 + k] if sent else 0.0
    for k in range(Pk.N_INTS):
        lines[s + m + k] = pi[pi0 + k] if sent else 0


@jit
def line_get(
    lines: np.ndarray, s: int, n: int, pf: np.ndarray, pf0: int, pi: np.ndarray, pi0: int
) -> None:  # fmt: skip
    """The packet in the slot at ``lines[s:]`` (pushed D ticks ago; zeros before) into the
    packet at ``pf[pf0:]``, ``pi[pi0:]``."""
    Pk = Packet.idx
    m = packet_floats(n)
    for k in range(m):
        pf[pf0 + k] = lines[s + k]
    for k in range(Pk.N_INTS):
        pi[pi0 + k] = np.int64(lines[s + m + k])


@jit
def next_slot(li: np.ndarray, link_i: int) -> None:
    """Both lines on by one slot (after this tick's packets are in)."""
    Ln = InProcessLink.idx
    slot = li[link_i + Ln.SLOT] + 1
    li[link_i + Ln.SLOT] = 0 if slot == li[link_i + Ln.DELAY_TICKS] else slot


@jit
def link_deliver(f: np.ndarray, i: np.ndarray, at: np.ndarray, n: int) -> None:
    """Each site's packet of this tick: the peer's of this tick (D = 0), else of D ticks ago."""
    Pk, Ln = Packet.idx, InProcessLink.idx
    if i[at[LI] + Ln.DELAY_TICKS] == 0:
        m = packet_floats(n)
        for k in range(m):
            f[at[RXT] + k] = f[at[TXH] + k]
            f[at[RXH] + k] = f[at[TXT] + k]
        for k in range(Pk.N_INTS):
            i[at[RXT + 1] + k] = i[at[TXH + 1] + k]
            i[at[RXH + 1] + k] = i[at[TXT + 1] + k]
    else:
        line_get(f, line_start(i, at[LI], at[LF], n, HSI), n, f, at[RXT], i, at[RXT + 1])
        line_get(f, line_start(i, at[LI], at[LF], n, 1 - HSI), n, f, at[RXH], i, at[RXH + 1])


@jit
def link_push(f: np.ndarray, i: np.ndarray, at: np.ndarray, n: int) -> None:
    """This tick's packets into the lines (after both ports have written their waves)."""
    Ln = InProcessLink.idx
    if i[at[LI] + Ln.DELAY_TICKS]:
        line_put(f, line_start(i, at[LI], at[LF], n, HSI), n, f, at[TXH], i, at[TXH + 1])
        line_put(f, line_start(i, at[LI], at[LF], n, 1 - HSI), n, f, at[TXT], i, at[TXT + 1])
        next_slot(i, at[LI])


def link_offsets(offsets: np.ndarray, link: int, tx_h: int, rx_h: int, tx_t: int, rx_t: int):
    """``at`` for the kernels: the blocks' float and int starts, from packed offsets."""
    at = np.zeros(10, dtype=np.int64)
    for k, block in enumerate((link, tx_h, rx_h, tx_t, rx_t)):
        at[2 * k], at[2 * k + 1] = offsets[2 * block], offsets[2 * block + 1]
    return at
