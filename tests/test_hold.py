"""The hold in front of a transport (teleop_rt.com.hold): packets come out in the order of
their due instants whatever the order they went in, a full pool refuses and counts, and
holding a packet keeps no allocation."""

from __future__ import annotations

import random

import pytest

from teleop_rt.com.hold import NEVER, HeldPackets
from tests.test_no_allocation import net_blocks


def test_packets_come_out_in_due_order() -> None:
    hold = HeldPackets(4, 16)
    rng = random.Random(3)
    dues = [rng.randrange(1_000_000) for _ in range(16)]
    for k, due in enumerate(dues):
        assert hold.put(due, bytes([k, 0, 0, k]))
    out = []
    while True:
        slot, due = hold.next_due()
        if due == NEVER:
            break
        out.append((due, hold.pop(slot)[0]))
    assert out == sorted((due, k) for k, due in enumerate(dues))
    assert hold.held == 16 and len(hold) == 0


def test_a_full_hold_refuses_and_counts() -> None:
    hold = HeldPackets(2, 3)
    assert all(hold.put(t, b"ab") for t in (5, 6, 7))
    assert not hold.put(1, b"cd")
    assert hold.overflow == 1 and hold.held == 3
    slot, due = hold.next_due()
    assert (due, hold.pop(slot)) == (5, b"ab")
    assert hold.put(1, b"cd") and hold.next_due()[1] == 1 and len(hold) == 3


def test_holding_keeps_no_allocation() -> None:
    hold = HeldPackets(128, 64)
    data = bytearray(range(128))
    t = [0]

    def tick() -> None:  # one in, one out (the sender's pop makes its bytes: off the tick)
        t[0] += 1
        hold.put(t[0] + 10, data)
        if len(hold) > 20:
            hold.pop(hold.next_due()[0])

    for _ in range(100):
        tick()
    assert net_blocks(tick, 10_000) < 50


def test_a_hold_needs_room() -> None:
    with pytest.raises(ValueError, match="at least one byte"):
        HeldPackets(0, 4)
