"""An in-process link with a network in between, for fast-mode runs: bit-reproducible from the
impairment's seed.

Each site's packet, once complete (``end_tick``), is encoded on the wire (``teleop_rt.com.wire``),
goes through the impairment stage (``teleop_rt.com.impairment``; one stream of draws per
direction), waits in flight until its arrival tick, and is then decoded and played out by the
receiver's rule (``teleop_rt.com.playout``): the same path as over a real network, bytes and
all. With no impairment every packet arrives at once and plays D ticks after it was sent, so
the sites compute exactly what they compute over an ``InProcessLink`` of D ticks; so they do
under any jitter that stays within D.

Packets in flight sit in a preallocated pool on a timing wheel (one bucket per arrival tick,
FIFO within a tick); the sites must be stepped in lock-step (as a session steps them), each
receiving once per tick.
"""

from __future__ import annotations

from teleop_rt.com.impairment import MAX_ARRIVALS, Impairment, ImpairmentSpec
from teleop_rt.com.link import Link
from teleop_rt.com.playout import Receiver
from teleop_rt.com.port import HSI, TO, Packet
from teleop_rt.com.wire import WireBounds, WireBuffer, encode_into
from teleop_rt.declarations import PLAYOUT_DEFAULT


class InFlight:
    """One direction's packets between sending and arrival: a pool of wire-sized slots and a
    wheel of arrival ticks (FIFO lists through ``_next``)."""

    def __init__(self, size: int, max_delay_ticks: int) -> None:
        self.buckets = max_delay_ticks + 4  # arrival ticks from (drained + 1) to s + max
        slots = MAX_ARRIVALS * (max_delay_ticks + 4)
        self._pool = bytearray(size * slots)
        whole = memoryview(self._pool)
        self._views = [whole[k * size : (k + 1) * size] for k in range(slots)]
        self._next = [-1] * slots
        self._free = list(range(slots - 1, -1, -1))
        self._head = [-1] * self.buckets
        self._tail = [-1] * self.buckets
        self.drained = -1  # the last tick delivered

    def put(self, arrival: int, data: memoryview) -> None:
        if not self._free:
            raise RuntimeError("more packets in flight than the link holds: step both sites")
        slot = self._free.pop()
        self._views[slot][:] = data
        self._next[slot] = -1
        bucket = max(arrival, self.drained + 1) % self.buckets
        tail = self._tail[bucket]
        if tail < 0:
            self._head[bucket] = slot
        else:
            self._next[tail] = slot
        self._tail[bucket] = slot

    def deliver(self, k: int, receiver: Receiver) -> None:
        """Everything due by tick ``k`` into ``receiver``, in arrival order."""
        for t in range(self.drained + 1, k + 1):
            bucket = t % self.buckets
            slot = self._head[bucket]
            while slot >= 0:
                receiver.arrive(k, self._views[slot])
                self._free.append(slot)
                after = self._next[slot]
                self._next[slot] = -1
                slot = after
            self._head[bucket] = self._tail[bucket] = -1
        self.drained = max(self.drained, k)


class ImpairedLink(Link):
    """Two sites' packets through the wire, an impairment each way, and the playout rule."""

    def __init__(
        self,
        n: int,
        delay_ticks: int,
        dt: float,
        impairment: ImpairmentSpec | None = None,
        *,
        session_id: int = 1,
        bounds: WireBounds | None = None,
        early_ticks: int | None = None,
        playout: str = PLAYOUT_DEFAULT,
        codec: bool = False,
    ) -> None:
        """``delay_ticks``: the playout delay D (>= 1); ``impairment``: what the network does
        (None: nothing); ``bounds``: the decoders' (both directions; generous by default);
        ``playout``: the receivers' policy (``teleop_rt.com.playout``); ``codec``: the sites
        run the codec (the receivers count losses by the packets' numbers)."""
        if delay_ticks < 1:
            raise ValueError("an impaired link needs a playout delay of at least one tick")
        spec = impairment or ImpairmentSpec()
        self.n, self.delay_ticks, self.session_id = n, delay_ticks, session_id
        self._period_ns = round(dt * 1e9)
        # per sender side: its wire buffer, its direction's impairment and packets in flight;
        # per receiver side: its receiver (decoder and playout)
        self._wire = [WireBuffer(n), WireBuffer(n)]
        self.impairments = [Impairment(spec, dt, stream=side) for side in (HSI, TO)]
        self._flight = [InFlight(self._wire[0].size, imp.max_delay_ticks)
                        for imp in self.impairments]  # fmt: skip
        self.receivers = [Receiver(n, delay_ticks, session_id, 1 - side, bounds, early_ticks,
                                   playout, codec=codec) for side in (HSI, TO)]  # fmt: skip
        self._sent: list[Packet | None] = [None, None]
        self._ticks = [0, 0]  # ticks each side has ended
        self.sent = [0, 0]

    def send(self, side: int, packet: Packet) -> None:
        self._sent[side] = packet

    def receive(self, side: int, into: Packet) -> None:
        k = self._ticks[side]
        receiver = self.receivers[side]
        self._flight[1 - side].deliver(k, receiver)
        receiver.take(k, into)

    def end_tick(self, side: int) -> None:
        packet = self._sent[side]
        if packet is None:
            raise RuntimeError("end_tick before send")
        tick = self._ticks[side]
        if packet.unsent:  # the codec sends nothing this tick
            self._ticks[side] = tick + 1
            self._sent[side] = None
            return
        # numbered by the packets sent (the receiver counts a loss by a jump of the number)
        data = encode_into(self._wire[side], packet, self.session_id, tick * self._period_ns,
                           side, self.sent[side])  # fmt: skip
        impairment, flight = self.impairments[side], self._flight[side]
        for k in range(impairment.decide(packet.tick)):
            flight.put(impairment.arrivals[k], data)
        self.sent[side] += 1
        self._ticks[side] = tick + 1
        self._sent[side] = None

    def stats(self, side: int) -> dict:
        """What the link did to the packets arriving at ``side``: the receiver's figures and,
        under ``network``, the impairment's own decisions."""
        imp = self.impairments[1 - side]
        out = self.receivers[side].stats(sent=self.sent[1 - side])
        out["network"] = {"lost": imp.lost, "duplicated": imp.duplicated,
                          "reordered": imp.reordered}  # fmt: skip
        return out
