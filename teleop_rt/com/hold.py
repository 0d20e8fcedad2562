"""Packets held until an instant: the real-time half of the impairment stage in front of a
transport (``teleop_rt.com.zenoh_transport``).

The tick ``put``s a copy of its encoded packet with the instant it is due on the network
(CLOCK_MONOTONIC ns: the send instant plus the delay the impairment drew); the sender thread
asks for ``next_due`` and ``pop``s what is due, in due order, to publish it. Everything is
preallocated: a pool of wire-sized slots and an array of their due instants (an empty slot is
due ``NEVER``), so ``put`` copies bytes and allocates nothing it keeps.

Why not the in-process link's timing wheel (``teleop_rt.com.impaired_link.InFlight``): it
releases packets by whole receiver ticks, stepped in lock-step with the sites; here a thread
publishes each packet at its own instant, between ticks, so it needs the earliest instant
of what is held (an argmin over the due array: a few microseconds for a thousand slots, on
the sender thread, never on the tick).

The caller serialises ``put`` and ``pop`` (one lock: the tick and the sender thread).
"""

from __future__ import annotations

import numpy as np

NEVER = np.iinfo(np.int64).max  # an empty slot's due instant


class HeldPackets:
    """Up to ``slots`` packets of ``size`` bytes, each held until its due instant (ns)."""

    def __init__(self, size: int, slots: int) -> None:
        if size < 1 or slots < 1:
            raise ValueError("a hold needs slots of at least one byte")
        self.size, self.slots = size, slots
        self._pool = bytearray(size * slots)
        whole = memoryview(self._pool)
        self._views = [whole[k * size : (k + 1) * size] for k in range(slots)]
        self.due = np.full(slots, NEVER, dtype=np.int64)
        self._free = list(range(slots - 1, -1, -1))
        self.held = 0  # packets put on hold
        self.overflow = 0  # packets refused: every slot busy (the sender thread starved)

    def __len__(self) -> int:
        return self.slots - len(self._free)

    def put(self, due_ns: int, data: bytes | bytearray | memoryview) -> bool:
        """Hold ``data`` (``size`` bytes) until ``due_ns``; False (counted) if the pool is
        full: the packet is lost, as a network with a full queue loses it."""
        if not self._free:
            self.overflow += 1
            return False
        slot = self._free.pop()
        self._views[slot][:] = data
        self.due[slot] = due_ns
        self.held += 1
        return True

    def next_due(self) -> tuple[int, int]:
        """The slot that is due first and its instant (``NEVER`` if nothing is held)."""
        slot = int(self.due.argmin())
        return slot, int(self.due[slot])

    def pop(self, slot: int) -> bytes:
        """The packet of ``slot`` (a copy) and the slot freed."""
        data = bytes(self._views[slot])
        self.due[slot] = NEVER
        self._free.append(slot)
        return data
