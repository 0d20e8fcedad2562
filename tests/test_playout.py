"""The playout rule: at tick k the packet sent at k - D - offset if it has arrived, else zeros;
late, duplicated, early packets dropped and counted, reordered ones used and counted; against
a plain-Python model of the rule on random schedules, and with the wire decoder in front."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt.com.playout import (
    DROPPED_DUPLICATE,
    DROPPED_EARLY,
    DROPPED_LATE,
    STORED,
    Playout,
    Receiver,
)
from teleop_rt.com.port import Packet
from teleop_rt.com.wire import WireBounds, WireBuffer, encode_into
from tests.test_no_allocation import net_blocks

N = 2


def sent(s: int) -> Packet:
    """The peer's packet of tick s: values that name it."""
    p = Packet(N)
    p.f[:] = s + np.arange(p.f.size) / 10.0
    p.tick = p.seq = s
    p.valid = 1
    return p


def taken(playout: Playout, k: int) -> int | None:
    """The sender tick of the packet used at k (None: a zero packet), checked whole."""
    into = Packet(N)
    into.f[:], into.i[:] = 9.0, 9
    if not playout.take(k, into):
        assert not into.f.any() and not into.i.any()
        return None
    s = int(into.tick)
    assert np.array_equal(into.f, sent(s).f) and np.array_equal(into.i, sent(s).i)
    return s


def test_in_time_packets_play_exactly_d_ticks_after_sending() -> None:
    d = 5
    playout = Playout(N, d, policy="fixed")
    used = []
    for k in range(30):
        if k >= 1:
            assert playout.arrive(k, sent(k - 1)) == STORED  # one tick on the way
        used.append(taken(playout, k))
    assert used == [None] * d + list(range(30 - d))
    c = playout.counters()
    assert (c["used"], c["lost"], c["received"], c["late"]) == (25, 0, 29, 0)
    assert playout.delay_percentiles() == {"p50": 1, "p99": 1, "max": 1}


def test_newest_plays_the_newest_arrival_and_skips_what_it_overtook() -> None:
    """The newest policy: the newest packet sent by k - D that arrived, each used once; a
    network slower than the ring is long (80 ticks here, the ring holds D + 51) still plays;
    when the delay drops the packets it overtook are skipped; with none new, zeros."""
    d, delay = 2, 80
    playout = Playout(N, d, policy="newest")
    used = []
    for k in range(200):
        if delay <= k < 100 + delay:  # sender ticks 0..99 take 80 ticks
            playout.arrive(k, sent(k - delay))
        if k >= 110:  # from sender tick 100 on: 10 ticks
            playout.arrive(k, sent(k - 10))
        used.append(taken(playout, k))
    assert used[:delay] == [None] * delay
    assert used[delay:110] == list(range(30))  # each arrival played at once
    assert used[110] == 100  # the overtaken ticks 30..99 are skipped
    assert used[190:] == list(range(180, 190))
    c = playout.counters()
    assert c["skipped"] == 70 and c["used"] == len([u for u in used if u is not None])
    assert c["late"] > 0  # the overtaken ones that still arrived, after 70 was played


def test_late_duplicate_early_and_reordered() -> None:
    d = 4
    playout = Playout(N, d, early_ticks=6, policy="fixed")
    assert playout.arrive(0, sent(1)) == STORED  # 5 ticks early: within 6
    assert playout.arrive(0, sent(0)) == STORED  # after a later one: reordered, in time
    assert playout.arrive(0, sent(1)) == DROPPED_DUPLICATE
    assert playout.arrive(0, sent(3)) == DROPPED_EARLY  # plays at 7: 7 ticks early
    for k in range(4):
        assert taken(playout, k) is None
    assert taken(playout, 4) == 0
    assert playout.arrive(5, sent(0)) == DROPPED_LATE  # a copy after its tick
    assert taken(playout, 5) == 1
    assert taken(playout, 6) is None  # sender tick 2 has not come: lost
    assert playout.arrive(7, sent(2)) == DROPPED_LATE  # it comes after its tick
    c = playout.counters()
    assert c == {"received": 6, "used": 2, "lost": 1, "late": 2, "duplicated": 1,
                 "reordered": 1, "early": 1, "skipped": 0, "repeated": 0}  # fmt: skip


def test_an_arrival_after_its_ticks_take_is_late() -> None:
    """A transport's thread may deliver during tick k after the site took tick k's packet."""
    playout = Playout(N, 2, policy="fixed")
    assert taken(playout, 2) is None  # sender tick 0 not there yet
    assert playout.arrive(2, sent(0)) == DROPPED_LATE
    assert playout.arrive(2, sent(1)) == STORED
    assert taken(playout, 3) == 1
    c = playout.counters()
    assert (c["late"], c["lost"], c["used"]) == (1, 1, 1)


def test_the_lost_count_starts_at_the_senders_first_tick() -> None:
    playout = Playout(N, 3, policy="fixed")
    for k in range(10):
        taken(playout, k)
    assert playout.counters()["lost"] == 7  # ticks 3..9 missed sender ticks 0..6


def test_retarget_shifts_the_played_tick_by_whole_ticks() -> None:
    d = 2
    playout = Playout(N, d, policy="fixed")
    for s in range(40):
        playout.arrive(0, sent(s))
    used = [taken(playout, k) for k in range(2, 8)]
    assert used == [0, 1, 2, 3, 4, 5]
    playout.retarget(1)  # the receiver's ticks run one ahead: tick 8 plays sender tick 5 again
    assert taken(playout, 8) is None and taken(playout, 9) == 6
    playout.retarget(-1)  # two back: tick 10 plays sender tick 9 (7 and 8 skipped)
    assert taken(playout, 10) == 9 and taken(playout, 11) == 10
    c = playout.counters()
    assert (c["repeated"], c["skipped"], c["lost"]) == (1, 2, 0)
    assert playout.offset_ticks == -1


def test_delay_percentiles_from_the_histogram() -> None:
    playout = Playout(N, 50, histogram_ticks=64, policy="fixed")
    delays = [1] * 60 + [7] * 39 + [30, 200]  # 200 beyond the histogram: its last bin
    for s, delay in enumerate(delays):
        playout.arrive(s + delay, sent(s))
    assert playout.delay_percentiles() == {"p50": 1, "p99": 30, "max": 200}


def test_parameters_that_cannot_work_are_refused() -> None:
    with pytest.raises(ValueError, match="at least one tick"):
        Playout(N, 0, policy="fixed")
    with pytest.raises(ValueError, match="early_ticks"):
        Playout(N, 10, early_ticks=9, policy="fixed")


class Model:
    """The rule in plain Python, with unbounded memory (what the ring must equal)."""

    def __init__(self, d: int, early: int) -> None:
        self.d, self.early, self.offset = d, early, 0
        self.stored: set[int] = set()
        self.used: set[int] = set()
        self.newest, self.last = None, None
        self.c = dict.fromkeys(("received", "used", "lost", "late", "duplicated", "reordered",
                                "early", "skipped", "repeated"), 0)  # fmt: skip

    def arrive(self, k: int, s: int) -> None:
        self.c["received"] += 1
        target = s + self.d + self.offset
        if target < k or (self.last is not None and s <= self.last):
            self.c["late"] += 1
        elif s in self.stored:
            self.c["duplicated"] += 1
        elif target > k + self.early:
            self.c["early"] += 1
        else:
            self.stored.add(s)
            if self.newest is not None and s < self.newest:
                self.c["reordered"] += 1
            else:
                self.newest = s

    def take(self, k: int) -> int | None:
        s = k - self.d - self.offset
        if self.last is not None and s <= self.last:
            self.c["repeated"] += 1
            return None
        if self.last is not None:
            self.c["skipped"] += s - self.last - 1
        self.last = s
        if s in self.stored and s not in self.used:
            self.used.add(s)
            self.c["used"] += 1
            return s
        if s >= 0:
            self.c["lost"] += 1
        return None


@settings(max_examples=150, deadline=None)
@given(
    d=st.integers(1, 6),
    slack=st.integers(0, 4),
    data=st.data(),
)
def test_the_ring_equals_the_rule_on_random_schedules(d, slack, data) -> None:
    """Random delays (some beyond D, some copies, any order within a tick) and occasional
    retargets: the preallocated ring decides every tick as the unbounded model does."""
    early = d + slack
    ticks = 60
    delay = st.integers(0, d + 4)
    copies = data.draw(st.lists(st.lists(delay, max_size=3), min_size=ticks, max_size=ticks))
    arrivals: dict[int, list[int]] = {}
    for s, delays in enumerate(copies):
        for x in delays:
            arrivals.setdefault(s + x, []).append(s)
    for k in arrivals:
        arrivals[k] = data.draw(st.permutations(arrivals[k]))
    retargets = data.draw(
        st.dictionaries(st.integers(0, ticks + d), st.integers(-2, 2), max_size=3)
    )
    playout, model = Playout(N, d, early_ticks=early, policy="fixed"), Model(d, early)
    for k in range(ticks + d + 6):
        if k in retargets:
            playout.retarget(retargets[k])
            model.offset = retargets[k]
        for s in arrivals.get(k, []):
            playout.arrive(k, sent(s))
            model.arrive(k, s)
        assert taken(playout, k) == model.take(k), k
    assert playout.counters() == model.c


# --- with the decoder in front ------------------------------------------------------------
SESSION_ID = 77
SENDER = 1  # the TO's packets, at the HSI


def wire_of(s: int, session: int = SESSION_ID, x: float | None = None) -> bytes:
    p = sent(s)
    if x is not None:
        p.f[0] = x
    return bytes(encode_into(WireBuffer(N), p, session, s * 1_000_000, SENDER))


def test_the_receiver_counts_stale_packets_late_and_foreign_ones_rejected() -> None:
    d = 3
    rx = Receiver(N, d, SESSION_ID, SENDER, WireBounds(x=100.0))
    into = Packet(N)
    for s in range(5):
        rx.arrive(s, wire_of(s))
    rx.arrive(0, wire_of(9, session=SESSION_ID + 1))
    rx.arrive(0, wire_of(5, x=1e3))
    rx.arrive(0, wire_of(6)[:-3])
    for k in range(3, 6):
        assert rx.take(k, into) == 1 and into.tick == k - d
    assert rx.decoder.used_seq == 2
    rx.arrive(6, wire_of(1))  # stale for the decoder (older than the newest used): late
    rx.arrive(6, wire_of(2))  # a copy of the packet used last: late too
    stats = rx.stats(sent=10)
    assert stats["sent"] == 10
    assert (stats["late"], stats["received"], stats["used"]) == (2, 7, 3)
    assert stats["rejected"] == 3
    assert stats["rejected_by_reason"] == {"size": 1, "session": 1, "implausible": 1}
    assert stats["delay_ticks"]["max"] == 5  # the late copy of tick 1, at 6


def test_the_receive_path_allocates_nothing_it_keeps() -> None:
    d = 20
    rx = Receiver(N, d, SESSION_ID, SENDER)
    buffer, p, into = WireBuffer(N), sent(0), Packet(N)
    k = [0]

    def tick() -> None:
        p.tick = p.seq = k[0]
        data = encode_into(buffer, p, SESSION_ID, 0, SENDER)
        rx.arrive(k[0], data)
        rx.arrive(k[0], data)  # and a duplicate
        rx.take(k[0], into)
        k[0] += 1

    for _ in range(100):
        tick()
    assert net_blocks(tick, 10_000) < 100
    c = rx.playout.counters()
    assert c["used"] == 10_100 - d and c["duplicated"] == 10_100


def test_the_receive_path_notes_each_ticks_first_copy_and_every_fresh_delay() -> None:
    """``Receiver.arrive`` (one compiled call per packet) notes, per sender tick, the first
    copy's receiver tick and one-way delay (a duplicate never overwrites it), and the delay
    of every fresh arrival only (not a duplicate's, a stale one's or a rejected one's)."""
    d = 2
    rx = Receiver(N, d, SESSION_ID, SENDER, arrivals=16, delays=8)
    sent_ns = lambda s: s * 1_000_000  # (wire_of's stamps)  # noqa: E731
    for s in range(4):
        rx.arrive(s + 1, wire_of(s), sent_ns(s) + 100 + s)  # 100 + s ns on the way
    rx.arrive(5, wire_of(2), sent_ns(2) + 7_000)  # a second copy, later: duplicated
    rx.arrive(5, wire_of(3)[:-1], sent_ns(3) + 9_000)  # the wrong size: rejected
    for k in range(2, 5):
        rx.take(k, Packet(N))  # ticks 0..2 used
    rx.arrive(6, wire_of(1), sent_ns(1) + 8_000)  # stale: counted late, not fresh
    assert not rx.fresh
    assert rx.delay_count == 4
    assert rx.delays_ns[:4].tolist() == [100, 101, 102, 103]
    for s in range(4):
        assert rx.arrived[s % 16].tolist() == [s, s + 1, 100 + s]
    assert rx.arrived[4].tolist() == [-1, -1, -1]
    c = rx.playout.counters()
    assert (c["received"], c["duplicated"], c["late"]) == (6, 1, 1)


def test_a_full_delay_record_keeps_the_first_ones() -> None:
    rx = Receiver(N, 2, SESSION_ID, SENDER, arrivals=4, delays=3)
    for s in range(6):
        rx.arrive(s + 1, wire_of(s), s * 1_000_000 + 50 + s)
    assert rx.delay_count == 3 and rx.delays_ns.tolist() == [50, 51, 52]
    assert rx.arrived[5 % 4].tolist() == [5, 6, 55]  # the table wraps by sender tick
