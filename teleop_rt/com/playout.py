"""The receiver's playout rule: which of the peer's packets a site uses at its tick.

At its tick k a site uses the packet the peer sent at tick k - D - offset, if it has arrived by
then, else a zero packet (``valid = 0``: a zero wave is passive, holding the last one is not).
D is the playout delay in ticks (the channel's nominal one-way delay, >= 1 over a network), and
``offset`` how far the receiver's tick count runs ahead of the sender's (0 in one process;
``retarget`` moves it by whole ticks when the clocks have drifted: over a network
``teleop_rt.com.drift`` decides when, from the floor of the arrivals' lateness).
So jitter up to D becomes the constant delay D (Kosuge et al., 1996): the ``fixed`` policy.
The ``newest`` policy uses instead the newest packet sent by k - D - offset that has arrived
and is newer than the last one used (zeros if there is none): less latency when the network is
faster than D, and the delay the channel sees varies with the network's (a delay that drops
skips packets; one that grows leaves ticks with none); the ports keep the channel passive
(``teleop_rt.com.port``). An arrival is:

- on time (stored, used at its tick; ``reordered`` too if a later-sent packet came first);
- ``late``: after its playout tick (``fixed``), or not newer than the packet last used (also a
  copy of a packet already used): dropped;
- ``duplicated``: a second copy before its playout tick: dropped;
- ``early``: more than ``early_ticks`` ticks before its playout tick: dropped (bounds memory
  and what a peer with a wrong clock can queue).

``lost`` counts playout ticks whose packet was not there (never arrived, or late; ``newest``:
ticks with no packet newer than the last used), ``skipped`` sender ticks passed over unused.
With the codec (``Receiver(codec=True)``) a sender is silent on most ticks, and a tick with no
packet is no loss: the receiver cannot tell a silence from a loss by the tick. Each packet then
carries its number (how many its sender had sent before it: ``teleop_rt.com.wire``), and a
packet used whose number jumped past the one used before counts the packets between as
``lost`` (never arrived, or late) or, those that had arrived and were passed over for a newer
one, ``skipped``; the per-tick count is ``silent_ticks`` (the peer's silences, and the losses
among them). A jump counts at most as many packets as the sender's tick moved (a sender sends
at most one a tick): a forged number costs no more than the per-tick rule would. Every
arrival's one-way delay in ticks, k - s - offset, goes into a preallocated histogram (p50, p99;
delays beyond it count in its last bin, the max is exact). Packets sit in a ring indexed by
sender tick (``early_ticks + 1`` slots): nothing is allocated per packet.

``Receiver`` puts the wire decoder in front: a packet the decoder drops is counted
``rejected`` by reason, except a stale one (its sequence number not newer than the newest used),
which is a late arrival; using a packet tells the decoder its sequence number. The decoder
rejects (``ahead``) a packet whose sequence number or tick is beyond the early horizon, before
it can move anything. ``Receiver.fresh`` says whether the last arrival passed every check and
was new to the playout (stored, or late for its tick): only such an arrival may tell the drift
follower and the peer timeout that the peer is there (a replayed, duplicated or early copy
never does).
"""

from __future__ import annotations

from functools import partial

import numpy as np

from teleop_rt.com.port import Packet
from teleop_rt.com.wire import (
    NUMBER,
    OK,
    REASONS,
    SEEN_TICK,
    SENDER_TIME,
    SIZE,
    STALE,
    Decoder,
    WireBounds,
    _as_i64,
    _decode,
)  # fmt: skip
from teleop_rt.declarations import PLAYOUT_DEFAULT
from teleop_rt.flat import compiled_for, jit

EARLY_SLACK_TICKS = 50  # default early horizon beyond D: room for the clocks' offset
NONE = -(1 << 62)  # an empty slot's sender tick

# the state's entries: parameters and the last used packet's number and sender tick, then
# counters (COUNTERS, in order; then the packets' own, PACKET_COUNTERS)
(DELAY, EARLY_TICKS, SLOTS, OFFSET, NEWEST, LAST_TAKEN, MAX_DELAY, POLICY, USED_NUMBER,
 USED_TICK) = range(10)  # fmt: skip
FIXED, NEWEST_POLICY = 0, 1
POLICIES = {"fixed": FIXED, "newest": NEWEST_POLICY}
COUNTERS = ("received", "used", "lost", "late", "duplicated", "reordered", "early", "skipped",
            "repeated")  # fmt: skip
RECEIVED, USED, LOST, LATE, DUPLICATED, REORDERED, EARLY, SKIPPED, REPEATED = range(
    10, 10 + len(COUNTERS)
)
# by the packets' numbers: sent, not used and never there in time, or passed over for a newer
PACKET_COUNTERS = ("lost_packets", "skipped_packets")
LOST_PACKETS, SKIPPED_PACKETS = range(10 + len(COUNTERS), 10 + len(COUNTERS) + 2)
HISTOGRAM = 10 + len(COUNTERS) + len(PACKET_COUNTERS)  # the delay histogram's first bin
# what arrive() did with a packet
STORED, DROPPED_LATE, DROPPED_DUPLICATE, DROPPED_EARLY = range(4)


class Playout:
    """The playout buffer of one direction, for packets of ``n`` joints."""

    def __init__(
        self,
        n: int,
        delay_ticks: int,
        early_ticks: int | None = None,
        histogram_ticks: int | None = None,
        policy: str = PLAYOUT_DEFAULT,
    ) -> None:
        if policy not in POLICIES:
            raise ValueError(f"playout policy {policy!r}: one of {', '.join(POLICIES)}")
        if delay_ticks < 1:
            raise ValueError("a playout delay needs at least one tick")
        early = delay_ticks + EARLY_SLACK_TICKS if early_ticks is None else early_ticks
        if early < delay_ticks:
            raise ValueError("early_ticks must be >= the playout delay (a packet with no delay)")
        self.n = n
        slots = early + 1
        bins = max(1024, 4 * (early + 1)) if histogram_ticks is None else histogram_ticks
        # one int array for the state, the counters and the delay histogram, one float and one
        # int array for the ring (fewer arrays: each costs a compiled call ~80 ns)
        self.st = np.zeros(HISTOGRAM + bins, dtype=np.int64)
        self.st[[DELAY, EARLY_TICKS, SLOTS]] = delay_ticks, early, slots
        self.st[[NEWEST, LAST_TAKEN]] = NONE
        self.st[[USED_NUMBER, USED_TICK]] = -1  # (as if packet -1 of tick -1 was used)
        self.st[POLICY] = POLICIES[policy]
        self.histogram = self.st[HISTOGRAM:]
        probe = Packet(n)
        self.ring_f = np.zeros((slots, probe.f.size))
        # per slot: the packet's ints, then the slot's sender tick, whether it was used and
        # the packet's number
        self.ring_i = np.zeros((slots, probe.i.size + 3), dtype=np.int64)
        self.ring_i[:, probe.i.size] = NONE
        # ``take``'s compiled entry point, once a tick (``compiled_for``: no dispatcher typing
        # five arrays; a Packet's buffers are float64 and int64 vectors, as the probe's)
        self._take = compiled_for(_take, self.st, self.ring_f, self.ring_i, 0, probe.f, probe.i)

    @property
    def delay_ticks(self) -> int:
        return int(self.st[DELAY])

    @property
    def offset_ticks(self) -> int:
        return int(self.st[OFFSET])

    def retarget(self, offset_ticks: int) -> None:
        """From now on tick k plays the sender's tick k - D - ``offset_ticks``: a larger offset
        replays no new tick for a while (zero packets, counted ``repeated``), a smaller one
        jumps over sender ticks (``skipped``)."""
        self.st[OFFSET] = offset_ticks

    def arrive(self, k: int, packet: Packet, number: int | None = None) -> int:
        """A packet (valid, decoded) arriving at receiver tick ``k``: STORED or why dropped.
        ``number``: the packet's (None: its tick, as from a sender that sends every tick)."""
        number = packet.tick if number is None else number
        return _arrive(self.st, self.ring_f, self.ring_i, k, packet.f, packet.i, number)

    def late(self, k: int, sender_tick: int) -> None:
        """A late arrival that was dropped before reaching the buffer (the decoder's stale)."""
        _count_late(self.st, k, sender_tick)

    def take(self, k: int, into: Packet) -> int:
        """The packet to use at tick ``k`` into ``into``; 1 if one arrived, 0 (zeros) if not."""
        return self._take(self.st, self.ring_f, self.ring_i, k, into.f, into.i)

    def counters(self) -> dict[str, int]:
        return {name: int(self.st[RECEIVED + k]) for k, name in enumerate(COUNTERS)}

    def packet_counters(self) -> dict[str, int]:
        """Packets lost and skipped by the jumps of their numbers (``PACKET_COUNTERS``)."""
        return {name: int(self.st[LOST_PACKETS + k]) for k, name in enumerate(PACKET_COUNTERS)}

    def delay_percentiles(self) -> dict[str, int | None]:
        """One-way delay of the arrivals, ticks: p50, p99 (upper bins) and the exact max."""
        total = int(self.histogram.sum())
        if total == 0:
            return {"p50": None, "p99": None, "max": None}
        cumulative = np.cumsum(self.histogram)
        p50, p99 = (int(np.searchsorted(cumulative, q * total)) for q in (0.5, 0.99))
        return {"p50": p50, "p99": p99, "max": int(self.st[MAX_DELAY])}


@jit
def _record_delay(st: np.ndarray, k: int, sender_tick: int) -> None:
    st[RECEIVED] += 1
    delay = k - sender_tick - st[OFFSET]
    if delay > st[MAX_DELAY]:
        st[MAX_DELAY] = delay
    last = st.size - 1
    st[min(HISTOGRAM + max(delay, 0), last)] += 1


@jit
def _count_late(st: np.ndarray, k: int, sender_tick: int) -> None:
    _record_delay(st, k, sender_tick)
    st[LATE] += 1


@jit
def _arrive(
    st: np.ndarray, ring_f: np.ndarray, ring_i: np.ndarray, k: int, pf: np.ndarray,
    pi: np.ndarray, number: int,
) -> int:  # fmt: skip
    Pk = Packet.idx
    r_tick, r_used = Pk.N_INTS, Pk.N_INTS + 1  # a slot's sender tick and used flag
    s = pi[Pk.TICK]
    _record_delay(st, k, s)
    target = s + st[DELAY] + st[OFFSET]  # the tick this packet plays at
    # late: its tick has passed (fixed), or it is not newer than the packet last played (an
    # arrival after this tick's take, as from a transport's own thread)
    if (target < k and st[POLICY] == FIXED) or (st[LAST_TAKEN] != NONE and s <= st[LAST_TAKEN]):
        st[LATE] += 1
        return DROPPED_LATE
    slot = s % st[SLOTS]
    if ring_i[slot, r_tick] == s:
        st[DUPLICATED] += 1
        return DROPPED_DUPLICATE
    if target > k + st[EARLY_TICKS]:
        st[EARLY] += 1
        return DROPPED_EARLY
    # the slot's previous tick is at least SLOTS older: played (or missed) already
    for j in range(pf.size):
        ring_f[slot, j] = pf[j]
    for j in range(Pk.N_INTS):
        ring_i[slot, j] = pi[j]
    ring_i[slot, r_tick] = s
    ring_i[slot, r_used] = 0
    ring_i[slot, Pk.N_INTS + 2] = number
    if s < st[NEWEST]:
        st[REORDERED] += 1
    else:
        st[NEWEST] = s
    return STORED


@jit
def _take(
    st: np.ndarray, ring_f: np.ndarray, ring_i: np.ndarray, k: int, pf: np.ndarray,
    pi: np.ndarray,
) -> int:  # fmt: skip
    Pk = Packet.idx
    r_tick, r_used = Pk.N_INTS, Pk.N_INTS + 1  # a slot's sender tick and used flag
    s = k - st[DELAY] - st[OFFSET]
    last = st[LAST_TAKEN]
    if last == NONE or s > last:
        found = s
        if st[POLICY] == NEWEST_POLICY:  # the newest stored since the last used, if any
            # from the newest arrival down (a network slower than the ring is long still
            # plays: the ring holds the newest SLOTS sender ticks that arrived)
            top = min(s, st[NEWEST])
            oldest = top - st[SLOTS] + 1 if last == NONE else max(last + 1, top - st[SLOTS] + 1)
            found = NONE
            for t in range(top, oldest - 1, -1):
                slot = t % st[SLOTS]
                if ring_i[slot, r_tick] == t and ring_i[slot, r_used] == 0:
                    found = t
                    break
        if found != NONE:
            slot = found % st[SLOTS]
            if ring_i[slot, r_tick] == found and ring_i[slot, r_used] == 0:
                if last != NONE:
                    st[SKIPPED] += found - last - 1
                _count_jump(st, ring_i, found, ring_i[slot, Pk.N_INTS + 2])
                st[LAST_TAKEN] = found
                for j in range(pf.size):
                    pf[j] = ring_f[slot, j]
                for j in range(Pk.N_INTS):
                    pi[j] = ring_i[slot, j]
                ring_i[slot, r_used] = 1
                st[USED] += 1
                return 1
        if st[POLICY] == FIXED:  # the tick's packet is missing: it is passed over for good
            if last != NONE:
                st[SKIPPED] += s - last - 1
            st[LAST_TAKEN] = s
        if s >= 0:  # before the sender's first tick nothing is missing
            st[LOST] += 1
    else:
        st[REPEATED] += 1
    pf[:] = 0.0
    pi[:] = 0
    return 0


@jit
def _count_jump(st: np.ndarray, ring_i: np.ndarray, s: int, number: int) -> None:
    """The packet of sender tick ``s`` and number ``number`` is used: the packets its sender
    sent since the last one used, by the jump of their numbers (at most the jump of the
    ticks: a sender sends at most one a tick, so a forged number counts no more than the
    per-tick rule), each lost or, if it is still in the ring unused, skipped."""
    Pk = Packet.idx
    r_tick, r_used = Pk.N_INTS, Pk.N_INTS + 1
    jump = min(number - st[USED_NUMBER], s - st[USED_TICK]) - 1
    if jump > 0:
        passed = 0  # arrived in time, passed over for a newer one (newest; a retarget)
        for t in range(max(st[USED_TICK] + 1, s - st[SLOTS] + 1), s):
            slot = t % st[SLOTS]
            if ring_i[slot, r_tick] == t and ring_i[slot, r_used] == 0:
                passed += 1
        passed = min(passed, jump)
        st[SKIPPED_PACKETS] += passed
        st[LOST_PACKETS] += jump - passed
    st[USED_NUMBER] = number
    st[USED_TICK] = s


# what ``_receive`` notes per arrival: a table by sender tick (modulo its rows) of the first
# copy's sender tick, receiver tick and one-way delay (ns), and every fresh arrival's delay
NOTE_TICK, NOTE_ARRIVAL, NOTE_DELAY = range(3)
FRESH = 1 << 8  # ``_receive``'s result: the decoder's status, or-ed with this if fresh


@jit
def _receive(
    words: np.ndarray, n: int, session: int, sender: int, bounds: np.ndarray,
    dstate: np.ndarray, st: np.ndarray, ring_f: np.ndarray, ring_i: np.ndarray,
    pf: np.ndarray, pi: np.ndarray, arrived: np.ndarray, delays: np.ndarray, count: np.ndarray,
    k: int, now_ns: int,
) -> int:  # fmt: skip
    """One arrival's whole receive path in one compiled call (one call per packet on the
    transport's thread, nothing allocated): decode ``words`` (the packet's bytes, copied in)
    into the scratch packet, hand it to the playout (or count a stale one late), note the
    first copy of each sender tick in ``arrived`` and a fresh arrival's delay in ``delays``
    (``count[0]`` of them). Returns the status, or-ed with ``FRESH``. The arrival's tick and
    instant come last, so the buffers bind once in front (``functools.partial``)."""
    newest = k + st[EARLY_TICKS] - st[DELAY] - st[OFFSET]  # the newest tick playable by k
    status = _decode(words, n, session, sender, newest, bounds, dstate, pf, pi)
    fresh = False
    if status == OK:
        stored = _arrive(st, ring_f, ring_i, k, pf, pi, dstate[NUMBER])
        fresh = stored == STORED or stored == DROPPED_LATE
        s = dstate[SEEN_TICK]
        delay = now_ns - dstate[SENDER_TIME]
        row = s % arrived.shape[0]
        if arrived[row, NOTE_TICK] != s:  # the first copy's
            arrived[row, NOTE_TICK] = s
            arrived[row, NOTE_ARRIVAL] = k
            arrived[row, NOTE_DELAY] = delay
        if fresh and count[0] < delays.size:
            delays[count[0]] = delay
            count[0] += 1
    elif status == STALE:
        _count_late(st, k, dstate[SEEN_TICK])
    return status | FRESH if fresh else status


class Receiver:
    """One direction's receiving end: the wire decoder, then the playout."""

    def __init__(
        self,
        n: int,
        delay_ticks: int,
        session_id: int,
        sender: int,
        bounds: WireBounds | None = None,
        early_ticks: int | None = None,
        policy: str = PLAYOUT_DEFAULT,
        arrivals: int = 1,
        delays: int = 0,
        codec: bool = False,
    ) -> None:
        """``sender``: the side whose packets this direction carries (0 HSI, 1 TO);
        ``codec``: the sender's codec is on (its silences are no losses: ``stats`` counts
        lost and skipped packets by their numbers, and the ticks with none as silent);
        ``arrivals``: rows of the table of arrivals by sender tick (``arrived``: sender tick,
        receiver tick, one-way delay ns; -1 empty); ``delays``: how many fresh arrivals'
        one-way delays (ns) to keep (``delays_ns``, in arrival order, ``delay_count`` of
        them)."""
        self.session_id, self.codec = session_id, codec
        self.decoder = Decoder(n, sender, bounds)
        self.playout = Playout(n, delay_ticks, early_ticks, policy=policy)
        self._scratch = Packet(n)
        self.fresh = False  # the last arrival passed every check and was new to the playout
        self.arrived = np.full((max(arrivals, 1), 3), -1, dtype=np.int64)
        self.delays_ns = np.zeros(delays, dtype=np.int64)
        self._count = np.zeros(1, dtype=np.int64)
        d, p = self.decoder, self.playout
        self._load = d.load
        args = (d._rx.words, n, _as_i64(session_id) if session_id >= 1 << 63 else session_id,
                sender, d.bounds, d.state, p.st, p.ring_f, p.ring_i, self._scratch.f,
                self._scratch.i, self.arrived, self.delays_ns, self._count)  # fmt: skip
        # the compiled entry point (``compiled_for``: no type dispatch), bound to the buffers
        # (``partial`` passes them in C: a star call in ``arrive`` built a list per packet)
        self._receive = partial(compiled_for(_receive, *args, 0, 0), *args)

    @property
    def delay_count(self) -> int:
        """How many one-way delays ``delays_ns`` holds."""
        return int(self._count[0])

    def arrive(self, k: int, data: bytes | bytearray | memoryview, now_ns: int = 0) -> int:
        """Bytes from the network at receiver tick ``k`` (``now_ns``: the arrival's instant,
        CLOCK_MONOTONIC, for the notes); returns the decoder's status."""
        if not self._load(data):  # the decoder's size rule (the kernel never sees a wrong size)
            self.fresh = False
            return SIZE
        result = self._receive(k, now_ns)
        self.fresh = result >= FRESH
        return result & (FRESH - 1)

    def take(self, k: int, into: Packet) -> int:
        """The packet to use at tick ``k`` (zeros if none); 1 if one arrived."""
        used = self.playout.take(k, into)
        if used:
            self.decoder.used_seq = into.seq
        return used

    def stats(self, sent: int | None = None) -> dict:
        """What the link did in this direction (``sent``: the sender's count, if known)."""
        counts = self.decoder.counts
        rejected = {REASONS[r]: int(counts[r]) for r in range(len(REASONS)) if r not in (OK, STALE)}
        counters = self.playout.counters()
        if self.codec:  # a tick with no packet is the codec's silence, or a loss among them
            by_number = self.playout.packet_counters()
            counters["silent_ticks"] = counters.pop("lost")
            counters["lost"] = by_number["lost_packets"]
            del counters["skipped"]  # (the ticks passed over: silences too)
            counters["skipped"] = by_number["skipped_packets"]
        return {
            "sent": sent,
            **counters,
            "rejected": sum(rejected.values()),
            "rejected_by_reason": {k: v for k, v in rejected.items() if v},
            "delay_ticks": self.playout.delay_percentiles(),
        }
