"""A delay line counted in whole ticks (like Drake's DiscreteTimeDelay): zeros until filled."""

from __future__ import annotations


class DelayLine:
    """Ring buffer delaying a per-joint signal (a list of floats) by ``ticks`` >= 1 ticks.

    Call ``pop()`` then ``push(x)`` once per tick: ``pop`` at tick k returns what was pushed at
    tick k - ticks (zeros for k < ticks); both use the same preallocated slot. Plain lists, not
    numpy: for a handful of joints numpy's per-call cost dominates (see docs, Performance).
    """

    def __init__(self, ticks: int, width: int) -> None:
        if ticks < 1:
            raise ValueError("a DelayLine needs ticks >= 1; a zero delay couples directly")
        self.ticks = ticks
        self.buffer = [[0.0] * width for _ in range(ticks)]
        self._slot = 0

    def pop(self) -> list[float]:
        """The sample pushed ``ticks`` ticks ago (the slot itself: read it before push)."""
        return self.buffer[self._slot]

    def push(self, x: list[float]) -> None:
        self.buffer[self._slot][:] = x
        self._slot += 1
        if self._slot == self.ticks:
            self._slot = 0

    def sum_of_squares(self) -> float:
        """Sum over all buffered samples and components of x^2 (wave energy bookkeeping)."""
        return sum(x * x for row in self.buffer for x in row)
