"""The fixed-step loop around a tick, shared by a one-process session and a site that runs
alone: the deadline clock, timing statistics, the real-time grant, signals at tick boundaries,
recording, the staged stop after a safety finding, and stopping every backend together.
"""

from __future__ import annotations

import time
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


def run_loop(
    step: Callable[[], None],
    total: int,
    dt: float,
    backends: Sequence[Backend],
    bring_to_rest: Callable[[TickClock], str],
    realtime: bool = False,
    overrun: str = OVERRUN_DEFAULT,
    max_missed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    after_tick: Callable[[], None] | None = None,
    recorder: Recorder | None = None,
    before_start: Callable[[], None] | None = None,
    at_start: Callable[[], None] | None = None,
    finish: Callable[[LoopOutcome], dict] | None = None,
    spin_ns: int | None = None,
    cpu: int | None = -1,
) -> LoopOutcome:
    """Run ``step`` ``total`` times, one per period ``dt`` in real time (else back to back).

    ``before_start`` runs once the signals are caught and before the backends start (a site's
    handshake with its peer: no motor is enabled before it), ``at_start`` just before the first
    tick (a site waits there for the instant both sites start at); ``after_tick`` after each tick
    (tests' observers); ``bring_to_rest(clock)`` after a safety finding (the staged stop, paced
    by the clock in real time). Whatever ends the run, every backend is stopped together and
    ``recorder`` is closed with the summary ``finish(outcome)`` gives. ``spin_ns``: how long
    before each deadline the clock stops sleeping and spins (None: ``TickClock``'s default);
    ``cpu``: the real-time loop's CPU, an index into the CPUs it may use (-1 the last; None
    leaves the affinity alone)."""
    period_ns = int(round(dt * 1e9))
    stats = TimingStats(total, period_ns)
    spin = {} if spin_ns is None else {"spin_ns": spin_ns}
    clock = TickClock(period_ns, realtime, overrun, max_missed=max_missed, **spin)
    grant = acquire_realtime(cpu=cpu) if realtime else None
    perf = time.perf_counter_ns
    out = LoopOutcome(stats, clock, realtime, perf(), StopSignals())
    out.notes += grant.notes if grant else []
    stop = out.stop
    next_report = 0
    try:
        stop.install()
        if before_start is not None:
            before_start()
        for backend in backends:
            backend.start()
        if at_start is not None:
            at_start()
        clock.start()
        for k in range(total):
            if stop.requested:
                break
            lateness = clock.wait()
            t0 = perf()
            step()
            if after_tick is not None:
                after_tick()
            t1 = perf()
            missed = clock.finish(clock.now_ns()) if realtime else False
            stats.add(t1 - t0, lateness, missed)
            if recorder is not None:
                recorder.record(t1 - t0, lateness, missed)
            if progress is not None and t1 >= next_report:
                progress(k + 1, total)
                next_report = t1 + 50_000_000
    except SafetyStop as exc:
        out.error = f"safety stop: {exc}"
        out.safety_stop = True
        out.notes.append(f"after the stop: {bring_to_rest(clock)}")
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
        summary = finish(out) if finish is not None else None
        if recorder is not None:
            recorder.close(summary)
    if progress is not None:
        progress(stats.count, total)
    return out
