"""One site as a process of its own: ``teleop-rt site hsi|to CONFIG``.

The site builds its robot's loop (``teleop_rt.site``) and its end of the network link
(``teleop_rt.com.zenoh_link``), shakes hands with its peer before its backend starts, and runs
its own real-time loop (``teleop_rt.runner``) with its own clock, signals, staged stop and
summary, and its own log (``teleop_rt.recording.site_log``: the same recorder and writer as a
session's). It keeps every tick's joint angles and measured torque (``TickRecord``,
preallocated) so that a parent that ran both sites can compute T_p and T_tau of the pair (eq
18) with or without logs, aligned by tick: both sites start their tick clocks at the instant
the handshake agreed on (``teleop_rt.recording.pair`` does the same from the two logs).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from teleop_rt.com.zenoh_link import HandshakeError, ZenohLink, wait_until_ns
from teleop_rt.config import SessionConfig
from teleop_rt.declarations import OVERRUN_DEFAULT
from teleop_rt.errors import ConfigError
from teleop_rt.exit_signals import Terminated
from teleop_rt.keys import key_reader
from teleop_rt.loop import TickClock
from teleop_rt.runner import LoopHooks, LoopOptions, LoopOutcome, run_loop
from teleop_rt.site import HsiSite, Site, ToSite, bring_to_rest, channel_figures

if TYPE_CHECKING:
    from teleop_rt.recording.live import LiveAddress
    from teleop_rt.recording.recorder import Recorder

SENDER_PRIORITY = 81  # the link's sender thread (with an impairment): above the loop's 80
ZENOH_PRIORITY = 70  # Zenoh's threads: below the loop's SCHED_FIFO 80, above normal processes
# A site's loop sleeps until 5 us plus its sleeps' measured overshoot before each deadline
# (loop.TickClock's adaptive clock), then spins: on this VM a sleep returns 35-60 us late, and
# a fixed 50 us spin cost 4-17 us per tick (3-7 % of a site's CPU) and still started ticks
# late where the overshoot passed 50 us; adaptive: 6-7 us a tick, ticks on time at p50, p99
# as before (docs/benchmarks.md). The one-process loop keeps its fixed 200 us.
SITE_SPIN_NS = 5_000
SITE_ADAPTIVE_SPIN = True
# Each role's CPU by default, as an index into the CPUs the process may use: two sites started
# by hand on one host spin on different CPUs (the HSI on the last, the TO on the one before).
SITE_CPU_INDEX = {"hsi": -1, "to": -2}


def site_cpu_index(name: str, cpu: int | None) -> int:
    """The index (into this process's allowed CPUs) that site ``name``'s loop pins to: CPU
    ``cpu`` if given (one of those allowed, else a ConfigError), else its role's default."""
    if cpu is None:
        return SITE_CPU_INDEX[name]
    allowed = sorted(os.sched_getaffinity(0))
    if cpu not in allowed:
        raise ConfigError(f"--cpu {cpu}: this process may run on CPUs {allowed} only")
    return allowed.index(cpu)


@dataclass
class SiteSummary:
    """End-of-run figures of one site (SI; timing in microseconds)."""

    name: str
    site: str
    ticks: int
    simulated_time_s: float
    delay_ticks: int
    port_energy_j: float  # energy that entered the channel at this site's port (eq 7, 8)
    channel: dict  # the channel kind and its protection's activity at this port
    timing: dict
    realtime: bool
    link: dict
    cpu_s: float  # this process's CPU time over the run (the loop, the link's threads)
    spin_s: float = 0.0  # of which the loop spun before its deadlines (loop.TickClock)
    notes: list[str] = field(default_factory=list)
    stopped_early: str | None = None
    stop_signal: int | None = None
    safety_stop: bool = False
    saturated_ticks: int = 0
    log: str | None = None  # this site's log, and whether it holds every tick (``status()``)
    recording: dict | None = None
    peer_silent: str | None = None  # the peer's packets mostly never came (ZenohLink.silence)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class TickRecord:
    """Every tick's q and tau (tau_h at the HSI, tau_e at the TO), preallocated."""

    def __init__(self, ticks: int, n: int) -> None:
        self.q = np.zeros((ticks, n))
        self.tau = np.zeros((ticks, n))
        self.count = 0

    def add(self, site: Site) -> None:
        k = self.count
        self.q[k] = site.feedback.q
        self.tau[k] = site.signals.tau
        self.count = k + 1

    def save(self, path: Path) -> None:
        np.savez(path, q=self.q[: self.count], tau=self.tau[: self.count])


def run_site(
    cfg: SessionConfig,
    name: str,
    backend: str | None = None,
    realtime: bool = True,
    overrun: str = OVERRUN_DEFAULT,
    max_missed: int | None = None,
    record: Path | None = None,
    on_peer: Callable[[str], None] | None = None,
    log: Path | None = None,
    live: LiveAddress | None = None,
    metadata: dict[str, str] | None = None,
    on_live: Callable[[LiveAddress], None] | None = None,
    on_wait: Callable[[], None] | None = None,
    cpu: int | None = None,
) -> SiteSummary:
    """Run site ``name`` ('hsi' or 'to') of ``cfg`` against its peer over the config's link;
    ``log``: record it there (``live``: and serve it, from the log's writer); ``metadata``:
    further ``teleop_rt`` metadata of the log (the command line's config path and overrides);
    ``on_wait()`` when the site starts waiting for its peer (signals now end the wait);
    ``cpu``: the CPU its loop pins to (None: its role's, ``SITE_CPU_INDEX``)."""
    cpu_index = site_cpu_index(name, cpu)
    site: Site = (HsiSite if name == "hsi" else ToSite)(cfg, backend)
    # the kernels load (or compile, after any other process compiling into the same cache:
    # teleop_rt.kernel_lock) here and in the link's constructor, before the loop: no tick waits
    site.warm_up()
    ZenohLink.check(cfg, name)
    # the log's writer is forked before Zenoh starts its threads
    from teleop_rt.recording.site_log import site_recorder

    recorder = site_recorder(site, log, metadata=metadata, live=live) if log is not None else None
    try:
        link = ZenohLink(cfg, site.side, site.n, lambda: site.tick)
    except BaseException:
        if recorder is not None:
            recorder.discard()
        raise
    if recorder is not None:
        link.arrival = recorder.session.arrival
        if recorder.live is not None and on_live is not None:
            on_live(recorder.live)
    run = _SiteRun(cfg, name, site, link, recorder, realtime, on_wait, on_peer)
    options = LoopOptions(
        realtime=realtime, overrun=overrun, max_missed=max_missed, spin_ns=SITE_SPIN_NS,
        adaptive_spin=SITE_ADAPTIVE_SPIN,
        cpu=cpu_index,
    )  # fmt: skip
    try:
        with key_reader(site):  # (mapping.keys: the HSI's operator inputs from the terminal)
            # the site's own clock: off by clock_ppm in a drift test
            period_s = link.period_ns / 1e9
            run_loop(run, cfg.n_ticks, period_s, [site.backend], options, recorder)
    except (HandshakeError, KeyboardInterrupt, Terminated):
        if recorder is not None and not run.shaken:  # no session: no log of one
            recorder.discard()
        raise
    finally:
        link.close()
        if record is not None:
            run.ticks.save(record)
    summary = run.summary
    assert summary is not None  # (finish runs however the loop ends)
    if recorder is not None:
        summary.recording = recorder.status()
    return summary


class _SiteRun(LoopHooks):
    """A site's run in the loop, and its state: the handshake's agreed start instant, the CPU
    time at the first tick, the notes on Zenoh's threads, the summary."""

    def __init__(
        self, cfg: SessionConfig, name: str, site: Site, link: ZenohLink,
        recorder: Recorder | None, realtime: bool, on_wait: Callable[[], None] | None,
        on_peer: Callable[[str], None] | None,
    ) -> None:  # fmt: skip
        self.cfg, self.name, self.site, self.link, self.recorder = cfg, name, site, link, recorder
        self.realtime, self.on_wait, self.on_peer = realtime, on_wait, on_peer
        self.ticks = TickRecord(cfg.n_ticks, site.n)
        self.start_ns = 0
        self.shaken = False  # the peer answered: a session exists (and its log)
        self.cpu0 = 0.0
        self.zenoh_note: list[str] = []
        self.summary: SiteSummary | None = None

    def before_start(self) -> None:
        if self.on_wait is not None:
            self.on_wait()
        link, recorder = self.link, self.recorder
        self.start_ns = link.handshake()
        self.shaken = True
        if recorder is not None:  # log times count from the agreed instant, on both sites
            recorder.describe({"session_id": f"{link.session_id:x}"}, start_ns=self.start_ns)
        if self.on_peer is not None:
            self.on_peer(f"the {link.peer} site answered (session {link.session_id:x}); starting")

    def at_start(self) -> None:  # both sites start their clocks at the agreed instant
        link = self.link
        if self.realtime:
            link.transport.raise_priority(SENDER_PRIORITY)
            raised = link.transport.raise_zenoh_threads(ZENOH_PRIORITY)
            self.zenoh_note = [
                f"Zenoh's threads at SCHED_FIFO {ZENOH_PRIORITY}: {', '.join(raised)}"
                if raised
                else "Zenoh's threads left at normal priority (not granted)"
            ]
        # a stop signal ends the wait at once (the loop then runs no tick: exit 130 / 143)
        wait_until_ns(self.start_ns)
        link.start()
        self.cpu0 = time.process_time()

    def step(self) -> None:
        site, link = self.site, self.link
        site.sense(link)
        site.update(link)
        self.ticks.add(site)

    def bring_to_rest(self, clock: TickClock) -> str:
        return bring_to_rest([self.site], self.site, clock.wait, self.cfg.safety.stop_max_ticks)

    def finish(self, out: LoopOutcome) -> dict:
        cfg, name, site, link, recorder = self.cfg, self.name, self.site, self.link, self.recorder
        ppm = getattr(cfg.link.zenoh, name).clock_ppm
        clock_note = [f"this site's clock ran {ppm:+g} ppm off (link.zenoh.{name}.clock_ppm)"]
        self.summary = SiteSummary(
            name=cfg.name,
            site=name,
            ticks=out.stats.count,
            simulated_time_s=out.stats.count * cfg.dt,
            delay_ticks=cfg.delay_ticks,
            port_energy_j=site.port.total_energy,
            channel=channel_figures(cfg, {site.name: site.port}),
            timing=out.timing(),
            realtime=self.realtime,
            link=link.stats(),
            cpu_s=time.process_time() - self.cpu0,
            spin_s=out.clock.spun_ns / 1e9,
            notes=out.notes + self.zenoh_note + (clock_note if ppm else []),
            stopped_early=out.stopped_early,
            stop_signal=out.stop.signum,
            safety_stop=out.safety_stop,
            saturated_ticks=site.guard.saturated_ticks,
            log=None if recorder is None else str(recorder.path),
            peer_silent=link.silence(out.stats.count),
        )  # fmt: skip
        return self.summary.to_dict()


def pair_transparency(hsi: Path, to: Path, dt: float) -> tuple[list[float], list[float], int]:
    """T_p and T_tau (eq 18) per joint of two sites' tick records, aligned by tick (both sites
    count ticks from the instant they agreed to start); the ticks both ran."""
    from teleop_rt.recording.metrics import transparency_sums

    a, b = np.load(hsi), np.load(to)
    k = min(len(a["q"]), len(b["q"]))
    t_p, t_tau = transparency_sums(a["q"][:k], b["q"][:k], a["tau"][:k], b["tau"][:k], dt)
    return t_p, t_tau, k
