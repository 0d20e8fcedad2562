"""A seeded, deterministic network impairment stage, after Linux netem (tc-netem(8)).

Per packet, given the tick it was sent at, ``Impairment.decide`` says what the network does
with it: lost (no arrival), or delivered at one arrival tick, or at two (a duplicate). The
same seed gives the same decisions, packet for packet. What each option does:

- ``delay_ms``: the network's one-way delay (the receiver's playout delay, ``channel.delay_ms``,
  is separate: a packet is on time if its delay is at most the playout delay).
- ``jitter_ms`` with a ``distribution``: the delay varies around ``delay_ms``: ``normal`` with
  standard deviation jitter; ``uniform`` over delay +- jitter (netem's default shape);
  ``pareto`` a Pareto tail of shape 3 shifted and scaled to mean delay and standard deviation
  jitter (it reaches down to delay - 0.577 jitter). ``correlation_percent`` rho: the draws
  follow a Gaussian AR(1) chain z_k = rho z_(k-1) + sqrt(1 - rho^2) e_k mapped onto the
  distribution (through the normal CDF for uniform and pareto), so the distribution stays the
  one named while successive delays correlate; netem's own blend of uniform draws narrows the
  distribution as the correlation grows, which its manual calls an approximation. Delays are
  independent per packet, so jitter reorders packets as netem does (no rate stage).
- ``loss_percent``: independent loss. ``gilbert_elliott``: bursty loss from a two-state chain
  (netem's ``gemodel p r 1-h 1-k``): each packet is lost with the loss probability of the state
  it finds (1-h in bad, 1-k in good), then the chain moves good -> bad with p, bad -> good
  with r. Loss rate (p (1-h) + r (1-k)) / (p + r); with 1-h = 100 %, 1-k = 0 the mean burst is
  1 / r packets.
- ``duplicate_percent``: a delivered packet arrives a second time, its copy with a delay of its
  own (netem re-queues the copy, which draws its own delay).
- ``reorder_percent`` and ``reorder_gap``: as netem's ``reorder P gap G``: after G - 1 packets
  sent with the delay, each further one goes with no delay at all with probability P (then the
  count restarts), so it overtakes the packets still in flight; needs a delay.
- ``delay_step``: from ``at_s`` on, the base delay is ``delay_ms`` of the step (a sudden step
  down, typically: later packets overtake earlier ones).
- ``trace``: replay a recorded per-packet trace instead (CSV of ``send_tick,delay_ms`` with
  ``lost`` for a lost packet; a tick listed twice is a duplicate); ticks count from the trace's
  first row and must follow each other; the trace repeats when the run outlasts it.

Delays are clamped to [0, ``max_delay_ms``] (a Pareto tail is unbounded; the link holds a packet
at most that long). A packet sent at tick s with delay d ms arrives at tick s + ceil(d / dt):
the first tick of the receiver at or after its arrival (with d = D dt exactly: tick s + D, the
tick an in-process link of D ticks hands it over).

Random numbers are drawn in blocks into preallocated arrays (``Generator.random(out=)``), a
fixed number per packet whatever happens to it, so one option's outcome never shifts another's
draws, and ``decide`` allocates nothing. The config's models of these options are in
``teleop_rt.com.impairment_spec`` (the config imports them without loading this stage).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import get_args

import numpy as np

from teleop_rt.com.impairment_spec import (
    DelayStepSpec,
    Distribution,
    GilbertElliottSpec,
    ImpairmentSpec,
)
from teleop_rt.errors import ConfigError
from teleop_rt.flat import float_view
from teleop_rt.inputs import read_bounded, shown

__all__ = ["DelayStepSpec", "GilbertElliottSpec", "Impairment", "ImpairmentSpec", "load_trace"]

MAX_ARRIVALS = 2  # an original and a duplicate
# about 1.5 million packets (25 min at 1 kHz; a trace repeats): read whole into lists
MAX_TRACE_BYTES = 20_000_000
SQRT2 = math.sqrt(2.0)
PARETO_SHAPE = 3.0
_PARETO_MEAN = PARETO_SHAPE / (PARETO_SHAPE - 1.0)
_PARETO_STD = math.sqrt(PARETO_SHAPE / ((PARETO_SHAPE - 1.0) ** 2 * (PARETO_SHAPE - 2.0)))


def load_trace(path: Path, max_delay_ms: float) -> tuple[list[int], list[float]]:
    """A trace CSV as arrivals per tick (0, 1 or 2) and their delays, ms (``MAX_ARRIVALS`` per
    tick, flat); a malformed file is a ``ConfigError`` naming the file and the line."""
    raw = read_bounded(path, MAX_TRACE_BYTES, "impairment trace ")
    try:
        lines = raw.decode().splitlines()
    except UnicodeDecodeError as exc:
        raise ConfigError(f"impairment trace {shown(path)}: cannot be read ({exc})") from None
    counts: list[int] = []
    delays: list[float] = []
    first: int | None = None
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        fields = [x.strip() for x in text.split(",")]
        if not text or (first is None and fields == ["send_tick", "delay_ms"]):
            continue  # blank, a comment, the header
        where = f"impairment trace {path}, line {number}"
        if len(fields) != 2:
            raise ConfigError(f"{where}: expected 'send_tick,delay_ms' or 'send_tick,lost'")
        try:
            tick = int(fields[0])
        except ValueError:
            raise ConfigError(f"{where}: send_tick {fields[0]!r} is not a whole number") from None
        lost = fields[1].lower() == "lost"
        delay = 0.0
        if not lost:
            try:
                delay = float(fields[1])
            except ValueError:
                raise ConfigError(
                    f"{where}: delay_ms {fields[1]!r} is neither a number nor 'lost'"
                ) from None
            if not 0 <= delay <= max_delay_ms:
                raise ConfigError(
                    f"{where}: delay_ms {fields[1]} is outside [0, max_delay_ms = {max_delay_ms:g}]"
                )
        if first is None:
            first = tick
        index = tick - first
        if index == len(counts):  # the next tick
            counts.append(0 if lost else 1)
            delays += [delay, 0.0]
        elif index == len(counts) - 1 and not lost and counts[index] == 1:  # a duplicate
            counts[index] = 2
            delays[MAX_ARRIVALS * index + 1] = delay
        elif index == len(counts) - 1:
            raise ConfigError(f"{where}: send_tick {tick} again, but it was lost or is lost")
        else:
            expected = first + len(counts)
            raise ConfigError(
                f"{where}: send_tick {tick} where {expected} comes next (ticks follow each other)"
            )
    if not counts:
        raise ConfigError(f"impairment trace {path}: no packets in it")
    return counts, delays


# columns of the uniform draws of one packet
U_LOSS, U_STATE, U_DUP, U_REORDER, U_REORDER_COPY = range(5)
Z_DELAY, Z_COPY = range(2)
BLOCK = 256  # packets per refill of the draws


class Impairment:
    """One direction's impairment stage: ``decide(send_tick)`` returns how many times the packet
    arrives (0: lost); the arrival ticks are then in ``arrivals[:count]`` and the delays that
    gave them, ms, in ``delays_ms[:count]``. Counters: ``decided``, ``lost``, ``duplicated``,
    ``reordered`` (sent with no delay by the reorder option)."""

    def __init__(self, spec: ImpairmentSpec, dt: float, stream: int = 0) -> None:
        """``stream`` tells the directions apart: each draws its own numbers from the seed."""
        self.spec, self.dt_ms = spec, 1000.0 * dt
        self.arrivals = [0] * MAX_ARRIVALS
        self.delays_ms = [0.0] * MAX_ARRIVALS
        self.decided = self.lost = self.duplicated = self.reordered = 0
        self._max_ms = spec.max_delay_ms
        self.max_delay_ticks = self._ticks(self._max_ms)
        self._trace: tuple[list[int], list[float]] | None = None
        if spec.trace is not None:
            self._trace = load_trace(spec.trace, spec.max_delay_ms)
            return
        self._rng = np.random.Generator(
            np.random.PCG64(np.random.SeedSequence([spec.seed, stream]))
        )
        self._u = np.zeros((BLOCK, 5))
        self._z = np.zeros((BLOCK, 2))
        self._u_mv, self._z_mv = float_view(self._u), float_view(self._z)
        self._row = BLOCK  # draws used up: refill on the first packet
        rho = spec.correlation_percent / 100.0
        self._rho, self._rho_c = rho, math.sqrt(1.0 - rho * rho)
        self._z_state = 0.0
        ge = spec.gilbert_elliott
        self._ge = ge is not None
        self._bad = False
        if ge is not None:
            self._p, self._r = ge.p_percent / 100.0, ge.r
            self._loss_bad = ge.loss_bad_percent / 100.0
            self._loss_good = ge.loss_good_percent / 100.0
        self._loss = spec.loss_percent / 100.0
        self._dup = spec.duplicate_percent / 100.0
        self._reorder, self._gap = spec.reorder_percent / 100.0, spec.reorder_gap
        self._since_reorder = 0  # packets sent with the delay since the last reordered one
        self._jitter = spec.jitter_ms
        self._shape = get_args(Distribution).index(spec.distribution)
        step = spec.delay_step
        self._delay_ms = spec.delay_ms
        self._step_tick = round(step.at_s / dt) if step else -1
        self._step_ms = step.delay_ms if step else spec.delay_ms
        self._random = bool(self._jitter or self._ge or self._loss or self._dup or self._reorder)

    def _ticks(self, delay_ms: float) -> int:
        """Whole ticks from sending to the first receiver tick at or after arrival."""
        return max(0, math.ceil(delay_ms / self.dt_ms - 1e-9))

    def decide(self, send_tick: int) -> int:
        """The fate of the packet sent at ``send_tick`` (ticks in increasing order)."""
        self.decided += 1
        if self._trace is not None:
            return self._replay(send_tick)
        base = self._step_ms if 0 <= self._step_tick <= send_tick else self._delay_ms
        if not self._random:  # a constant delay (and its step): no draws
            self.delays_ms[0] = base
            self.arrivals[0] = send_tick + self._ticks(base)
            return 1
        row = self._row
        if row == BLOCK:
            self._rng.random(out=self._u)
            self._rng.standard_normal(out=self._z)
            row = 0
        self._row = row + 1
        u, z = self._u_mv, self._z_mv
        # the delay chain moves with every packet, lost or not
        zs = self._z_state = self._rho * self._z_state + self._rho_c * z[row, Z_DELAY]
        if self._ge:
            bad = self._bad
            lost = u[row, U_LOSS] < (self._loss_bad if bad else self._loss_good)
            self._bad = u[row, U_STATE] >= self._r if bad else u[row, U_STATE] < self._p
        else:
            lost = u[row, U_LOSS] < self._loss
        if lost:
            self.lost += 1
            return 0
        self._arrive(0, send_tick, base, zs, u[row, U_REORDER])
        if u[row, U_DUP] >= self._dup:
            return 1
        self.duplicated += 1
        z_copy = self._rho * zs + self._rho_c * z[row, Z_COPY]  # not advancing the chain
        self._arrive(1, send_tick, base, z_copy, u[row, U_REORDER_COPY])
        return 2

    def _arrive(self, k: int, send_tick: int, base_ms: float, z: float, u_reorder: float) -> None:
        if self._reorder and self._since_reorder >= self._gap - 1 and u_reorder < self._reorder:
            self._since_reorder = 0
            self.reordered += 1
            delay = 0.0  # sent at once: overtakes what is in flight
        else:
            self._since_reorder += 1
            delay = base_ms + self._jitter_of(z) if self._jitter else base_ms
            delay = min(max(delay, 0.0), self._max_ms)
        self.delays_ms[k] = delay
        self.arrivals[k] = send_tick + self._ticks(delay)

    def _jitter_of(self, z: float) -> float:
        """The delay's deviation for the standard normal draw z."""
        if self._shape == 0:
            return self._jitter * z
        if self._shape == 1:  # 2 Phi(z) - 1: uniform on (-1, 1)
            return self._jitter * math.erf(z / SQRT2)
        tail = 0.5 * math.erfc(z / SQRT2)  # 1 - Phi(z): uniform on (0, 1), exact in the tail
        pareto = tail ** (-1.0 / PARETO_SHAPE) if tail > 0.0 else math.inf
        return self._jitter * (pareto - _PARETO_MEAN) / _PARETO_STD

    def _replay(self, send_tick: int) -> int:
        counts, delays = self._trace  # type: ignore[misc]
        index = send_tick % len(counts)
        count = counts[index]
        if count == 0:
            self.lost += 1
        elif count == 2:
            self.duplicated += 1
        for k in range(count):
            delay = delays[MAX_ARRIVALS * index + k]
            self.delays_ms[k] = delay
            self.arrivals[k] = send_tick + self._ticks(delay)
        return count
