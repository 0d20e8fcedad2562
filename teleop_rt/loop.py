"""Fixed-step clock with absolute deadlines, timing statistics and the overrun policy.

Real-time mode: deadlines are absolute, ``next_ns += period_ns`` (never ``sleep(dt)``, which
drifts); the clock sleeps until ``spin_ns`` before the deadline, then spins on the monotonic
clock. With ``adaptive`` it sleeps until ``spin_ns`` plus its estimate of how late a sleep
returns (the running median of the overshoot, a sign-step quantile tracker after Robbins and
Monro, 1951), so that a short spin is enough where the OS's sleeps overshoot by tens of us.
Fast mode runs ticks back to back (simulation time only).

Overrun policy, applied when a tick's work ends after the next deadline (a missed deadline):
* ``catch_up``: keep the schedule; the following ticks start late until they have caught up;
* ``skip``: drop the missed deadlines and continue on the next future one (time base kept);
* ``stop``: raise ``OverrunStop``.
``max_missed`` N raises ``OverrunStop`` at the (N + 1)th missed deadline whatever the policy.
The late tick itself has run and is counted (``TimingStats``, the log) like any other: the stop
is raised when the next tick waits for its deadline, so the summary's missed deadlines
include the one that stopped the run.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import FrameType
from typing import Any, BinaryIO, ClassVar

import numpy as np

from teleop_rt.declarations import OVERRUN_DEFAULT, OVERRUN_POLICIES
from teleop_rt.errors import SafetyStop
from teleop_rt.exit_signals import unanswered

MCL_CURRENT, MCL_FUTURE = 1, 2  # <sys/mman.h>
CPU_DMA_LATENCY = "/dev/cpu_dma_latency"  # the kernel's PM QoS request for wake-up latency
OVERSLEEP_STEP_NS = 1_000  # the adaptive clock's median tracker moves by this per sleep


class OverrunStop(SafetyStop):
    """A tick ended after the next deadline and the policy is 'stop'."""


class TickClock:
    """Paces ticks to absolute deadlines (real-time) or not at all (fast mode)."""

    def __init__(
        self,
        period_ns: int,
        realtime: bool,
        overrun: str = OVERRUN_DEFAULT,
        spin_ns: int = 200_000,
        now_ns=time.monotonic_ns,
        sleep=time.sleep,
        max_missed: int | None = None,
        adaptive: bool = False,
    ) -> None:
        if overrun not in OVERRUN_POLICIES:
            raise ValueError(f"overrun policy must be one of {OVERRUN_POLICIES}, got {overrun!r}")
        self.max_missed = max_missed
        self.missed = 0
        self.stop_reason: str | None = None  # raised as OverrunStop at the next wait()
        self.period_ns = period_ns
        self.realtime = realtime
        self.overrun = overrun
        self.spin_ns = spin_ns
        self.now_ns = now_ns
        self.sleep = sleep
        self.deadline_ns = 0
        self.skipped = 0
        self.spun_ns = 0  # time spent spinning before deadlines (CPU the loop burns by design)
        self.adaptive = adaptive
        self.oversleep_ns = 0  # (adaptive) the estimated median of how late a sleep returns

    def start(self) -> None:
        self.deadline_ns = self.now_ns()

    def wait(self) -> int:
        """Wait for the current tick's deadline; return the lateness in ns (0 in fast mode).
        Raise ``OverrunStop`` if the last tick's miss ends the run."""
        if self.stop_reason is not None:
            raise OverrunStop(self.stop_reason)
        if not self.realtime:
            return 0
        now = self.now_ns()
        lead = self.spin_ns + self.oversleep_ns
        remaining = self.deadline_ns - now
        if remaining > lead:
            self.sleep((remaining - lead) * 1e-9)
            asleep_at = now
            now = self.now_ns()
            if self.adaptive:  # one step towards the median of the overshoot
                late = now - asleep_at - (remaining - lead)  # past the sleep asked for
                step = OVERSLEEP_STEP_NS if late > self.oversleep_ns else -OVERSLEEP_STEP_NS
                self.oversleep_ns = min(max(self.oversleep_ns + step, 0), self.period_ns // 2)
        spin_from = now
        while now < self.deadline_ns:
            now = self.now_ns()
        self.spun_ns += now - spin_from
        return now - self.deadline_ns

    def finish(self, end_ns: int) -> bool:
        """Close the tick that ended at end_ns; advance the deadline. Return True if missed."""
        if not self.realtime:
            return False
        next_deadline = self.deadline_ns + self.period_ns
        missed = end_ns > next_deadline
        if missed:
            self.missed += 1
            if self.overrun == "stop" and self.stop_reason is None:
                self.stop_reason = (
                    f"tick overran its deadline by {(end_ns - next_deadline) / 1e3:.0f} us "
                    "(overrun policy: stop)"
                )
            if self.max_missed is not None and self.missed > self.max_missed:
                self.stop_reason = self.stop_reason or (
                    f"{self.missed} deadlines missed, more than the {self.max_missed} allowed "
                    "(--max-missed)"
                )
            if self.overrun == "skip":
                # deadlines before end_ns are dropped; one at end_ns is still on time
                behind = -(-(end_ns - next_deadline) // self.period_ns)
                self.skipped += behind
                next_deadline += behind * self.period_ns
        self.deadline_ns = next_deadline
        return missed


class TimingStats:
    """Per-tick compute time and lateness in preallocated arrays; summary in microseconds.

    ``period_ns`` (when known) lets the summary count ticks that started later than a whole
    period (the deadline of the following tick had already passed)."""

    def __init__(self, capacity: int, period_ns: int | None = None) -> None:
        self.compute_ns = np.zeros(capacity, dtype=np.int64)
        self.lateness_ns = np.zeros(capacity, dtype=np.int64)
        self.period_ns = period_ns
        self.count = 0
        self.missed = 0

    def add(self, compute_ns: int, lateness_ns: int, missed: bool) -> None:
        i = self.count
        self.compute_ns[i] = compute_ns
        self.lateness_ns[i] = lateness_ns
        self.count = i + 1
        if missed:
            self.missed += 1

    def summary(self) -> dict:
        n = self.count
        late = self.lateness_ns[:n]
        out: dict = {"ticks": n, "missed_deadlines": self.missed}
        if self.period_ns is not None:
            out["late_over_period"] = int(np.count_nonzero(late > self.period_ns))
        for name, arr in (("compute_us", self.compute_ns[:n]), ("lateness_us", late)):
            if n:
                p50, p99, p999 = np.percentile(arr, [50, 99, 99.9])
                out[name] = {
                    "p50": float(p50) / 1e3,
                    "p99": float(p99) / 1e3,
                    "p99.9": float(p999) / 1e3,
                    "max": float(arr.max()) / 1e3,
                }
            else:
                out[name] = {"p50": 0.0, "p99": 0.0, "p99.9": 0.0, "max": 0.0}
        return out


def format_percentiles(stat: dict) -> str:
    """One line of a summary's percentiles (microseconds), as the summary and metrics print."""
    return "  ".join(f"{key} {stat[key]:.1f}" for key in ("p50", "p99", "p99.9", "max"))


@dataclass
class RealtimeGrant:
    """What the OS granted for real-time mode, and how to undo it."""

    notes: list[str]
    gc_was_enabled: bool
    old_policy: tuple[int, int] | None = None
    old_affinity: set[int] | None = None
    memory_locked: bool = False
    wakeup_latency: BinaryIO | None = None  # /dev/cpu_dma_latency, held open for the loop

    def release(self) -> None:
        if self.wakeup_latency is not None:
            self.wakeup_latency.close()  # the kernel drops the request with the last close
            self.wakeup_latency = None
        if self.gc_was_enabled:
            gc.enable()
        if self.old_policy is not None:
            policy, prio = self.old_policy
            try:
                os.sched_setscheduler(0, policy, os.sched_param(prio))
            except OSError:
                pass
        if self.old_affinity is not None:
            try:
                os.sched_setaffinity(0, self.old_affinity)
            except OSError:
                pass
        if self.memory_locked:
            _libc().munlockall()


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def acquire_realtime(priority: int = 80, cpu: int | None = -1) -> RealtimeGrant:
    """Ask the OS for what a 1 kHz loop needs and report what worked: SCHED_FIFO, one CPU of
    its own (``cpu``: an index into the allowed CPUs, -1 the last one, so the log writer and the
    OS keep the others; None leaves the affinity alone), memory locked against page faults
    (mlockall), no deep CPU idle states (/dev/cpu_dma_latency), and the garbage collector
    frozen for the loop."""
    notes: list[str] = []
    old = None
    if hasattr(os, "sched_setscheduler"):
        try:
            old = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            notes.append(f"SCHED_FIFO priority {priority} granted")
        except (OSError, PermissionError) as err:
            old = None
            notes.append(
                f"SCHED_FIFO not granted ({err.strerror or err}); running under the default "
                "scheduler, expect larger lateness (grant CAP_SYS_NICE or an rtprio limit)"
            )
    else:  # pragma: no cover - non-Linux
        notes.append("SCHED_FIFO is not available on this OS; default scheduler")
    old_affinity = _pin_cpu(cpu, notes)
    locked = _lock_memory(notes)
    wakeup = hold_wakeup_latency(notes)
    gc_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    notes.append("garbage collector frozen for the loop")
    return RealtimeGrant(notes, gc_enabled, old, old_affinity, locked, wakeup)


def _pin_cpu(cpu: int | None, notes: list[str]) -> set[int] | None:
    if cpu is None or not hasattr(os, "sched_setaffinity"):
        return None
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) < 2:
        notes.append(f"CPU affinity left as is (only CPU {allowed} allowed)")
        return None
    target = allowed[cpu % len(allowed)]
    try:
        os.sched_setaffinity(0, {target})
    except OSError as err:
        notes.append(f"CPU affinity not granted ({err.strerror or err})")
        return None
    notes.append(f"pinned to CPU {target} of {allowed}")
    return set(allowed)


def hold_wakeup_latency(notes: list[str], path: str = CPU_DMA_LATENCY) -> BinaryIO | None:
    """Ask the kernel's PM QoS for a 0 us CPU wake-up latency (no deep idle states, whose exit
    adds tens to hundreds of us to a wake-up) for as long as the returned file stays open, as
    cyclictest does; None, with a note, if not granted."""
    handle = None
    try:
        handle = open(path, "wb", buffering=0)  # noqa: SIM115 - held open for the loop
        handle.write(struct.pack("i", 0))
    except OSError as err:
        if handle is not None:
            handle.close()
        notes.append(
            f"CPU wake-up latency not held ({path}: {err.strerror}); deep idle states may "
            "add latency"
        )
        return None
    notes.append(f"CPU wake-up latency held at 0 us ({path})")
    return handle


def _lock_memory(notes: list[str]) -> bool:
    if not sys.platform.startswith("linux"):  # pragma: no cover - non-Linux
        return False
    if _libc().mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        notes.append(
            f"memory not locked (mlockall: {os.strerror(err)}; raise RLIMIT_MEMLOCK): page "
            "faults may add latency"
        )
        return False
    notes.append("memory locked (mlockall)")
    return True


class StopSignals:
    """Turns SIGINT, SIGTERM and SIGHUP into a flag the loop checks at each tick boundary, so a run
    stops between ticks (never halfway through one) and the log matches the summary.

    Only the main thread can install signal handlers; elsewhere it is a no-op flag."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    installed: ClassVar[list[StopSignals]] = []  # lets a wait elsewhere (the log) see a stop

    @classmethod
    def pending(cls) -> bool:
        """Whether an installed instance has been asked to stop."""
        return any(s.requested for s in cls.installed)

    def __init__(self) -> None:
        self.requested = False
        self.signum: int | None = None
        # what signal.signal returned: a handler, SIG_DFL / SIG_IGN, or None
        self._previous: dict[int, Callable[[int, FrameType | None], Any] | int | None] = {}

    @property
    def reason(self) -> str:
        name = signal.Signals(self.signum).name if self.signum else "stop"
        return f"stopped by {name}"

    def _handle(self, signum: int, frame: object) -> None:
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt  # a second Ctrl-C: the user insists
        self.requested = True
        self.signum = signum

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in self.SIGNALS:
            self._previous[sig] = signal.signal(sig, self._handle)
        StopSignals.installed.append(self)
        signum = unanswered()  # a signal before the loop whose exception Python dropped
        if signum is not None:
            self.requested, self.signum = True, signum

    def uninstall(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()
        if self in StopSignals.installed:
            StopSignals.installed.remove(self)
