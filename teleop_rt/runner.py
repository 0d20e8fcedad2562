"""The fixed-step loop around a tick, shared by a one-process session and a site that runs
alone: the deadline clock, timing statistics, the real-time grant, signals at tick boundaries,
recording, the staged stop after a safety finding, and the backends' lifecycle
(``teleop_rt.hal.base``: configured and activated before the first tick; whatever ends the
run, deactivated together and released, ``teleop_rt.hal.stopping``).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from teleop_rt.declarations import OVERRUN_DEFAULT
from teleop_rt.errors import RecordingFailure, SafetyStop
from teleop_rt.hal.stopping import stop_all
from teleop_rt.loop import StopSignals, TickClock, TimingStats, acquire_realtime

if TYPE_CHECKING:
    from teleop_rt.hal.base import Backend
    from teleop_rt.recording.recorder import Recorder


@dataclass
class LoopOutcome:
    """How a run went: its timing and how it ended."""

    stats: TimingStats
    clock: TickClock
    realtime: bool
    wall_start_ns: int
    stop: StopSignals
    notes: list[str] = field(default_factory=list)
    error: str | None = None
    safety_stop: bool = False

    @property
    def stopped_early(self) -> str | None:
        return self.stop.reason if self.stop.requested else self.error

    def timing(self) -> dict:
        timing = self.stats.summary()
        timing["wall_s"] = (time.perf_counter_ns() - self.wall_start_ns) / 1e9
        if self.realtime and self.clock.skipped:
            timing["skipped_deadlines"] = self.clock.skipped
        return timing


@dataclass(frozen=True)
class LoopOptions:
    """How the loop keeps time. ``realtime``: one tick per period on the deadline clock (else
    back to back); ``overrun`` / ``max_missed``: what a missed deadline does (``TickClock``);
    ``spin_ns``: how long before each deadline the clock stops sleeping and spins (None:
    ``TickClock``'s default); ``cpu``: the real-time loop's CPU, an index into the CPUs it may
    use (-1 the last; None leaves the affinity alone); ``adaptive_spin``: sleep for the spin
    plus the sleeps' measured overshoot (``TickClock``'s ``adaptive``)."""

    realtime: bool = False
    overrun: str = OVERRUN_DEFAULT
    max_missed: int | None = None
    spin_ns: int | None = None
    cpu: int | None = -1
    adaptive_spin: bool = False


class LoopHooks(ABC):
    """What a run does at the loop's points: ``step`` each tick, ``bring_to_rest`` after a
    safety finding; the others do nothing unless overridden. A run's own state (a handshake's
    instant, its summary) lives on its hooks object."""

    @abstractmethod
    def step(self) -> None:
        """One tick (timed: whatever it calls, observers included, counts as the tick)."""

    @abstractmethod
    def bring_to_rest(self, clock: TickClock) -> str:
        """The staged stop after a safety finding (paced by ``clock`` in real time); its note."""

    def tick(self) -> Callable[[], None]:
        """What the loop calls each tick: ``step``, or a callable a run binds to save a Python
        call per tick (a session without an observer hands over its own ``step``)."""
        return self.step

    def before_start(self) -> None:
        """Once the signals are caught, before the backends are activated (a site's handshake
        with its peer: no motor is enabled before it)."""
        return

    def at_start(self) -> None:
        """Just before the first tick (a site waits there for the instant both sites start)."""
        return

    def progress(self, done: int, total: int) -> None:
        """About 20 times a second of wall time, and once at the end."""
        return

    def finish(self, outcome: LoopOutcome) -> dict | None:
        """The summary the recorder is closed with, once the backends are stopped."""
        return None


def run_loop(
    hooks: LoopHooks,
    total: int,
    dt: float,
    backends: Sequence[Backend],
    options: LoopOptions = LoopOptions(),
    recorder: Recorder | None = None,
) -> LoopOutcome:
    """Run ``hooks.tick()`` ``total`` times, one per period ``dt`` in real time (else back to
    back), calling the hooks at their points. Whatever ends the run, every backend is
    deactivated together and released, and ``recorder`` (if any), which records every tick,
    is closed with the summary ``hooks.finish(outcome)`` gives."""
    realtime = options.realtime
    period_ns = int(round(dt * 1e9))
    stats = TimingStats(total, period_ns)
    spin = {} if options.spin_ns is None else {"spin_ns": options.spin_ns}
    clock = TickClock(period_ns, realtime, options.overrun, max_missed=options.max_missed,
                      adaptive=options.adaptive_spin, **spin)  # fmt: skip
    grant = acquire_realtime(cpu=options.cpu) if realtime else None
    perf = time.perf_counter_ns
    out = LoopOutcome(stats, clock, realtime, perf(), StopSignals())
    out.notes += grant.notes if grant else []
    stop = out.stop
    step = hooks.tick()
    next_report = 0
    try:
        stop.install()
        hooks.before_start()
        # one robot configured and activated after the other: a configured CAN robot's drives
        # are NMT operational, and its keepalive (SYNC, heartbeat) starts with activation
        for backend in backends:
            backend.configure()
            backend.activate()
        hooks.at_start()
        clock.start()
        for k in range(total):
            if stop.requested:
                break
            lateness = clock.wait()
            t0 = perf()
            step()
            t1 = perf()
            missed = clock.finish(clock.now_ns()) if realtime else False
            stats.add(t1 - t0, lateness, missed)
            if recorder is not None:
                recorder.record(t1 - t0, lateness, missed)
            if t1 >= next_report:
                hooks.progress(k + 1, total)
                next_report = t1 + 50_000_000
    except SafetyStop as exc:
        out.error = f"safety stop: {exc}"
        out.safety_stop = True
        out.notes.append(f"after the stop: {hooks.bring_to_rest(clock)}")
    except RecordingFailure as exc:  # on_loss: stop; a normal stop, as by Ctrl-C
        out.error = f"recording failed: {exc}"
    except BaseException as exc:
        out.error = f"{type(exc).__name__}: {exc}"
        raise
    finally:
        stop.uninstall()
        stop_all(backends, dt)
        if grant:
            grant.release()
        for backend in backends:
            out.notes += backend.notes()
        summary = hooks.finish(out)
        if recorder is not None:
            recorder.close(summary)
    hooks.progress(stats.count, total)
    return out
