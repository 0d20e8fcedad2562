"""Following a peer whose clock drifts: when to move the playout by a whole tick.

Each site ticks on its own clock, and two hosts' clocks differ in rate by tens of ppm, so the
receiver's tick count slides against the sender's (at 50 ppm by a tick every 20 s). Left
alone, packets arrive later and later against their playout tick until they are late (the
receiver's clock runs fast), or earlier and earlier while the channel's delay grows by a tick
every 20 s (it runs slow).

The rule. At each arrival the receiver measures the packet's lateness in ticks,
x = r - s - offset: r the receiver's time of arrival in its own ticks (continuous, counted
from the instant both sites started), s the packet's sender tick, offset the playout's
(``teleop_rt.com.playout.Playout.retarget``). Queueing and scheduling only ever add to x, so
the minimum of x over a window of arrivals (``window``: a second at 1 kHz) is the path's
floor plus the clocks' slide, immune to jitter. The first window's minimum is the reference.
When a whole window's minimum has moved by ``threshold`` (3/4 tick) or more from it, the
playout moves by one tick to follow: offset + 1 when the minimum grew, - 1 when it shrank,
which brings the minimum back to within 1/4 tick of the reference. So between retargets it
stays within 3/4 tick of the reference, plus the slide of the windows it takes to notice
(two: 0.2 tick at 100 ppm), and after a retarget the opposite one is 1/2 tick away (floor
noise below that never makes it chatter).

Passivity: offset + 1 makes the next tick's sender tick one already played, which the playout
answers with a zero packet (``repeated``), never with the packet again; offset - 1 jumps over
one sender tick (``skipped``), a packet never used. Either is one packet not delivered, which
a wave channel takes passively (a zero wave emits no energy); no packet is used twice.

The rule cannot tell a lasting change of the network's delay from drift and follows either,
but by at most one tick per 1e6 / ``max_ppm`` receiver ticks (5 s at the default 200 ppm,
twice a crystal's tolerance): a step of the delay is followed slowly, never in a jump, and a
drift beyond ``max_ppm`` is followed at that rate, the rest showing as late packets.
``max_ppm`` 0 never retargets (the minimum is still tracked and reported).
"""

from __future__ import annotations

import math

from teleop_rt.com.playout import Playout

WINDOW = 1000  # arrivals per window
THRESHOLD_TICKS = 0.75


class DriftFollower:
    """Moves ``playout`` by a tick when the arrivals' floor has slid (see the module)."""

    def __init__(
        self,
        playout: Playout,
        max_ppm: float = 200.0,
        window: int = WINDOW,
        threshold_ticks: float = THRESHOLD_TICKS,
    ) -> None:
        if window < 1 or not 0.5 < threshold_ticks < 1.0:
            raise ValueError("a drift window needs arrivals and a threshold in (1/2, 1) tick")
        self.playout = playout
        self.window, self.threshold = window, threshold_ticks
        self.follow = max_ppm > 0
        self.min_gap_ticks = 1e6 / max_ppm if self.follow else math.inf
        self.reference = math.nan  # the first window's minimum lateness, ticks
        self._count = 0
        self._min = math.inf
        self._last_retarget = -math.inf
        self.back = 0  # offset + 1: a zero packet played (the receiver's clock ran ahead)
        self.forward = 0  # offset - 1: a sender tick skipped (the sender's clock ran ahead)
        self.windows = 0
        self.moved_min = self.moved_max = 0.0  # windows' minima against the reference, ticks

    def arrival(self, receiver_ticks: float, sender_tick: int) -> None:
        """A packet of ``sender_tick`` arrived at ``receiver_ticks`` (continuous ticks of the
        receiver's clock since the start); may retarget the playout (the caller holds the
        playout's lock)."""
        x = receiver_ticks - sender_tick - self.playout.offset_ticks
        if x < self._min:
            self._min = x
        self._count += 1
        if self._count < self.window:
            return
        floor, self._min, self._count = self._min, math.inf, 0
        self.windows += 1
        if math.isnan(self.reference):
            self.reference = floor
            return
        moved = floor - self.reference
        self.moved_min, self.moved_max = min(self.moved_min, moved), max(self.moved_max, moved)
        if not self.follow or abs(moved) < self.threshold:
            return
        if receiver_ticks - self._last_retarget < self.min_gap_ticks:
            return
        step = 1 if moved > 0 else -1
        self.playout.retarget(self.playout.offset_ticks + step)
        self._last_retarget = receiver_ticks
        if step > 0:
            self.back += 1
        else:
            self.forward += 1

    def stats(self) -> dict:
        """Retargets each way, the offset now, and how far the windows' floor moved."""
        return {"retargets": self.back + self.forward, "back": self.back,
                "forward": self.forward, "offset_ticks": self.playout.offset_ticks,
                "windows": self.windows,
                "floor_moved_ticks": {"min": round(self.moved_min, 3),
                                      "max": round(self.moved_max, 3)}}  # fmt: skip
