"""A one-process session: the two sites (``teleop_rt.site``) joined by an in-process link,
stepped in lock-step, in fast mode or in real time.

One tick k is the stages of ``teleop_rt.tick_stages`` (read, check, port input, the link's
delivery, port, C1 / C2, M_v^-1 a_ref, the link's push, the monitor, RNEA, workspace, computed
torque, guard, T_p / T_tau, write), run in lock-step: ``tick_stages.lockstep()`` is the order
``step`` runs, ``tick_stages.phased()`` the order over a link stepped from Python
(tests/test_tick_stages.py traces both). In real-time mode the loop waits for the deadline first.

All but the backend, Pinocchio and workspace calls are compiled (``teleop_rt.lockstep``
around each site's kernels, ``teleop_rt.site_tick``) and run on the blocks' state, packed into
two flat buffers when the session is built (``teleop_rt.flat``). Backends that can (two
simulated plants) run inside those kernels instead of through ``read`` / ``write``
(``teleop_rt.lockstep_fused``): bit for bit the same.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

from teleop_rt.com import codec
from teleop_rt.com.channel import ChannelMonitor
from teleop_rt.com.link import InProcessLink, Link
from teleop_rt.com.port import WAVE
from teleop_rt.config import SessionConfig
from teleop_rt.declarations import OVERRUN_DEFAULT, PORT_LOG, SITES
from teleop_rt.errors import ConfigError, SafetyStop
from teleop_rt.flat import Block, Packed, compiled_for
from teleop_rt.lockstep import (
    SESSION_BLOCKS,
    PairState,
    link_at,
    lockstep_after,
    lockstep_before,
    pair_account,
    pair_monitor,
)
from teleop_rt.loop import TickClock
from teleop_rt.mapping import dls_figures
from teleop_rt.runner import LoopHooks, LoopOptions, LoopOutcome, run_loop
from teleop_rt.site import HsiSite, Site, ToSite, bring_to_rest, channel_figures
from teleop_rt.task_limits import tool_limits_figures
from teleop_rt.transparency_tick import TransparencyAccumulator

if TYPE_CHECKING:
    from teleop_rt.lockstep_fused import FusedPlants
    from teleop_rt.recording.recorder import Recorder
    from teleop_rt.world import Load


class ChannelView:
    """The two-port's signals under the paper's names, from the two sites' ports and the
    session's monitor (what the log's /channel topic holds)."""

    SOURCES = {  # name -> (owner, field): the ports' variables under their symbols (PORT_LOG)
        **{x.log_name(site): (site, x.source) for site in SITES for x in PORT_LOG if x.symbols},
        "power": ("monitor", "power"), "energy": ("monitor", "energy"),
        "total_energy": ("monitor", "total_energy"),
        "min_total_energy": ("monitor", "min_total_energy"),
        "balance_hsi": ("hsi", "balance"), "balance_to": ("to", "balance"),
        "removed_hsi": ("hsi", "limited"), "removed_to": ("to", "limited"),
    }  # fmt: skip

    def __init__(self, session: Session) -> None:
        self._owners = {"hsi": session.hsi.port, "to": session.to.port,
                        "monitor": session.monitor}  # fmt: skip
        self.link = session.link
        self._hsi_port = session.hsi.port
        self.dt = session.dt

    def source(self, name: str) -> tuple[Block, str]:
        """The block and field that hold signal ``name``."""
        owner, attr = self.SOURCES[name]
        return self._owners[owner], attr

    def __getattr__(self, name: str):
        if name.startswith("_") or name not in self.SOURCES:
            raise AttributeError(name)
        block, attr = self.source(name)
        return getattr(block, attr)

    def stored_energy(self) -> float:
        """Wave energy in flight on the link (0 for a channel of no waves)."""
        if self._hsi_port.mode != WAVE:
            return 0.0
        if not isinstance(self.link, InProcessLink):  # an impaired link's packets in flight
            raise NotImplementedError("stored wave energy: only the in-process link's lines")
        return self.link.stored_wave_energy(self.dt)


@dataclass
class Summary:
    """End-of-session figures (all SI; timing in microseconds)."""

    name: str
    ticks: int
    simulated_time_s: float
    delay_ticks: int
    t_p: list[float]
    t_tau: list[float]
    channel_energy_j: float
    min_channel_energy_j: float
    timing: dict
    realtime: bool
    notes: list[str] = field(default_factory=list)
    stopped_early: str | None = None
    stop_signal: int | None = None  # the signal that ended the run (SIGINT, SIGTERM), if any
    safety_stop: bool = False  # the safety layer ended the run (stopped_early says why)
    saturated_ticks: int = 0  # ticks in which a commanded torque hit its effort limit
    link: dict | None = None  # what an impaired link did (sent, lost, late, ...; per site)
    channel: dict | None = None  # the channel kind and its protection's activity per port
    tool_limits: dict | None = None  # what the TO's task-space limits did (safety.tool)
    dls: dict | None = None  # task space: what each site's damped least squares did
    space: str = "joint"  # what the channel couples (channel.space): T_p / T_tau's coordinates

    @property
    def t_p_total(self) -> float:
        return float(sum(self.t_p))

    @property
    def t_tau_total(self) -> float:
        return float(sum(self.t_tau))

    def to_dict(self) -> dict:
        d = self.__dict__.copy()
        d["t_p_total"] = self.t_p_total
        d["t_tau_total"] = self.t_tau_total
        return d


class Session:
    """Two sites and an in-process link, preallocated at construction."""

    fused = False  # True while two backends run inside the tick (set False to force read/write)

    def __init__(
        self,
        cfg: SessionConfig,
        operator: Load | None = None,
        fuse: bool = True,
        backends: dict[str, str] | None = None,
    ) -> None:
        """``operator`` replaces the config's operator model (replay drives it from a log);
        ``backends`` the config's backend per robot (``{"hsi": "can"}``); ``fuse=False``
        keeps the backends on the plain ``read`` / ``write`` path and their own buffers."""
        self.cfg = cfg
        self.dt = cfg.dt
        backends = backends or {}
        self.hsi = HsiSite(cfg, backends.get("hsi"), operator)
        self.to = ToSite(cfg, backends.get("to"))
        n = self.hsi.m  # the channel's size: the joints, or the task's dimension
        if self.to.m != n:
            raise ConfigError(
                f"to.robot: the TO has {self.to.n} joints but the HSI has {self.hsi.n}; "
                "the channel couples joint to joint (channel.space: plane couples the tools)"
            )
        self.n = n
        impairment = cfg.link.impairment
        if impairment is None:
            self.link: Link = InProcessLink(n, cfg.delay_ticks)
        else:  # the network emulated between the sites: stepped from Python, seeded
            from teleop_rt.com.impaired_link import ImpairedLink

            if cfg.delay_ticks < 1:
                raise ConfigError(
                    "link.impairment: an impaired link needs channel.delay_ms of at least one "
                    "tick (the playout delay)"
                )
            self.link = ImpairedLink(n, cfg.delay_ticks, self.dt, impairment,
                                     playout=cfg.link.playout,
                                     codec=cfg.channel.codec != "none")  # fmt: skip
        self.monitor = ChannelMonitor(n, self.dt)
        self.metrics = TransparencyAccumulator(n, self.dt)
        self.pair = PairState(n)
        self.channel = ChannelView(self)
        self.tick = 0
        compiled_link = isinstance(self.link, InProcessLink)
        # the fused plants take one joint count (a pair of other robots runs read / write)
        same = self.hsi.n == self.to.n
        pair = None
        if fuse and compiled_link and same:  # (imported here: a CAN pair needs no plant kernels)
            from teleop_rt.lockstep_fused import fuse_plants

            pair = fuse_plants(self.hsi.backend, self.to.backend)
        if compiled_link and cfg.channel.codec != "none":
            # the in-process link hands each packet over at once and plays it D ticks later:
            # the receivers look D - 1 ticks ahead, the senders count on part of it
            for site in self.sites:
                codec.look_ahead(site.port, codec.ahead_ticks(cfg.delay_ticks))
        self._pack(pair)
        self.compiled_link = compiled_link
        self._boxed = [s for s in self.sites if s.guard.workspace is not None and s.guard.enabled]

    @property
    def sites(self) -> tuple[Site, Site]:
        return self.hsi, self.to

    def _pack(self, pair: FusedPlants | None) -> None:
        """All blocks into one pair of buffers, for the compiled lock-step tick; backends that
        fuse follow, so that the same compiled calls reach their state."""
        hsi, to = self.hsi, self.to
        link_block = self.link if isinstance(self.link, InProcessLink) else InProcessLink(self.n, 0)
        own = [*hsi.blocks, *to.blocks, link_block, self.monitor, self.metrics, self.pair]
        assert len(own) == SESSION_BLOCKS
        blocks = own + (pair.blocks if pair else [])
        self.packed = p = Packed(blocks)
        hsi.bind(p, 0)
        to.bind(p, len(hsi.blocks))
        # each task-space site's map, bound to these buffers (``Site.map_kinematics``'s call)
        self._maps = [site._kin for site in (hsi, to) if site._kin is not None]
        self._buffers = (p.f, p.i, p.offsets, self.n)
        self._at = at = link_at(p.offsets)
        self._pin = (hsi._pin, to._pin)
        # where each controller model's RNEA lands (Pinocchio's data.tau, viewed once): the
        # second kernel reads it there, not from the copy pin.rnea returns
        rnea = (hsi.model.data.tau, to.model.data.tau)
        # load (or, on a fresh install, compile) the kernels now, on scratch copies of the
        # state, not at the first deadline; then bound to the buffers (``compiled_for``)
        f, i, o, n = self._buffers
        lockstep_before(f.copy(), i.copy(), o, at, n)
        lockstep_after(f.copy(), i.copy(), o, n, *rnea)
        args: tuple[Any, ...] = (f, i, o, at, n)
        self._before = partial(compiled_for(lockstep_before, *args), *args)
        args = (f, i, o, n, *rnea)
        self._after = partial(compiled_for(lockstep_after, *args), *args)
        self._pair_plants = pair
        if pair is not None:
            pair.bind(p.f, p.i, p.offsets, rnea, self.n)
            self.fused = True
            # the maps in the plants' last compiled call of the tick, where the pair takes them
            self._maps_fused = [] if pair.take_maps(self._maps) else self._maps

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        """The state of every block (not the parameters), one copy per buffer."""
        fs, is_ = self._state_index()
        return self.packed.f[fs], self.packed.i[is_]

    def restore(self, snapshot: tuple[np.ndarray, np.ndarray]) -> None:
        """Put a ``snapshot`` back (the backends' hardware, if any, is not rewound)."""
        fs, is_ = self._state_index()
        self.packed.f[fs], self.packed.i[is_] = snapshot

    def _state_index(self) -> tuple[np.ndarray, np.ndarray]:
        if not hasattr(self, "_state_idx"):
            self._state_idx = self.packed.state_index()
        return self._state_idx

    @property
    def tau_h(self) -> np.ndarray:
        """The operator's torque on the HSI, as measured this tick."""
        return self.hsi.tau_h

    @property
    def tau_e(self) -> np.ndarray:
        """The TO's torque on the environment this tick (-tau_ext of the TO)."""
        return self.to.tau_e

    @property
    def saturated_ticks(self) -> int:
        return self.pair.saturated_ticks

    def step(self) -> None:
        """One control tick of both sites: read, link, ports, controllers, computed torque,
        safety, write. With ``fused`` the reads and writes are the backends' own compiled
        pieces inside the lock-step kernels (``teleop_rt.lockstep_fused``). The kernels are
        bound to the session's buffers once (``_pack``); RNEA leaves its torque in each
        controller model's ``data.tau``, where the second kernel reads it."""
        if not self.compiled_link:
            self._step_over(self.link)
            return
        pair = self._pair_plants if self.fused else None  # (fused: the pair is there)
        if pair is not None:
            code = pair.before()
        else:
            hsi, to = self.hsi, self.to
            try:
                hsi.backend.read()  # into hsi.feedback
            except SafetyStop as exc:
                raise self._read_to_after(exc) from None
            to.backend.read()
            code = self._before()
        if code:
            raise self._stop_for(code)
        pin_h, pin_t = self._pin
        pin.rnea(*pin_h)  # (into data.tau: the result pin.rnea returns is a copy of it)
        pin.rnea(*pin_t)
        for site in self._boxed:  # (forward kinematics: only sites with a workspace box)
            site.tick = self.tick
            site.check_workspace()
        # only without a finding do the plants take the torques
        code = self._after() if pair is None else pair.after()
        if code:
            raise self._stop_for(code)
        maps = self._maps
        if pair is not None:
            pair.advance()  # (and the maps, where it took them)
            maps = self._maps_fused
        else:
            hsi.backend.write(hsi.computed_torque.tau)
            to.backend.write(to.computed_torque.tau)
        for jacobian, args, mapped in maps:  # (the next tick's: task-space maps only)
            mapped(jacobian(*args))
        self.tick += 1

    def _step_over(self, link: Link) -> None:
        """One tick of both sites through a link stepped from Python (an impaired one): each
        site's own entry points, then the pair's stages on the session's buffers
        (``tick_stages.phased``)."""
        hsi, to = self.hsi, self.to
        try:
            hsi.sense(link)
        except SafetyStop as exc:
            raise self._read_to_after(exc) from None
        to.sense(link)
        hsi.update(link)
        to.update(link)
        f, i, o, n = self._buffers  # the pair's stages: the same kernels as the lock-step's
        pair_monitor(f, o, n)
        pair_account(f, i, o, n)
        self.tick += 1

    def _read_to_after(self, exc: SafetyStop) -> SafetyStop:
        """The HSI's read (or its checks) stopped the tick: the TO's backend reads all the
        same, so its bus gets this period's SYNC (a CAN drive watches it by the wall clock);
        a fault that read finds joins the HSI's."""
        try:
            self.to.backend.read()
        except SafetyStop as other:
            return SafetyStop(f"{exc}; {other}")
        return exc

    def link_stats(self) -> dict | None:
        """What an impaired link did, per receiving site (None for the plain in-process one)."""
        if self.compiled_link:
            return None
        from teleop_rt.com.impaired_link import ImpairedLink

        assert isinstance(self.link, ImpairedLink)  # the one link that is not compiled
        return {"hsi": self.link.stats(0), "to": self.link.stats(1)}

    def _stop_for(self, code: int) -> SafetyStop:
        site = self.to if self.pair.finding_site else self.hsi
        site.tick = self.tick
        return site.stop_for(code)

    def run(
        self,
        ticks: int | None = None,
        realtime: bool = False,
        overrun: str = OVERRUN_DEFAULT,
        progress: Callable[[int, int], None] | None = None,
        observer: Callable[[Session], None] | None = None,
        recorder: Recorder | None = None,
        max_missed: int | None = None,
    ) -> Summary:
        """Run ``ticks`` ticks (default: the config's duration) and return the summary.

        ``observer(session)`` is called after every tick (tests); ``recorder`` records every
        tick and is closed (the log finalized, with the summary) however the run ends.
        ``progress(done, total)`` is called about 20 times a second of wall time. ``max_missed``:
        more missed deadlines than this stop the run (``TickClock``). SIGINT and
        SIGTERM end the run at the next tick boundary; an exception ends it at once, and the
        log still holds every completed tick.
        """
        total = self.cfg.n_ticks if ticks is None else ticks
        hooks = _SessionRun(self, progress, observer)
        options = LoopOptions(realtime=realtime, overrun=overrun, max_missed=max_missed)
        backends = [self.hsi.backend, self.to.backend]
        run_loop(hooks, total, self.dt, backends, options, recorder)
        assert hooks.summary is not None  # (finish runs however the loop ends)
        return hooks.summary

    def _bring_to_rest(self, clock: TickClock) -> str:
        """The reaction to a safety stop: each site brings its robot to rest until the TO is
        (``teleop_rt.site.bring_to_rest``, paced by the clock in real time); then zero torque."""
        return bring_to_rest(
            [self.hsi, self.to], self.to, clock.wait, self.cfg.safety.stop_max_ticks
        )

    def _summary(self, outcome: LoopOutcome) -> Summary:
        return Summary(
            name=self.cfg.name,
            space=self.cfg.channel.space,
            ticks=outcome.stats.count,
            simulated_time_s=outcome.stats.count * self.dt,
            delay_ticks=self.cfg.delay_ticks,
            t_p=self.metrics.t_p.tolist(),
            t_tau=self.metrics.t_tau.tolist(),
            channel_energy_j=self.monitor.total_energy,
            min_channel_energy_j=self.monitor.min_total_energy,
            timing=outcome.timing(),
            realtime=outcome.realtime,
            notes=outcome.notes,
            stopped_early=outcome.stopped_early,
            stop_signal=outcome.stop.signum,
            safety_stop=outcome.safety_stop,
            saturated_ticks=self.saturated_ticks,
            link=self.link_stats(),
            channel=channel_figures(self.cfg, {"hsi": self.hsi.port, "to": self.to.port}),
            tool_limits=tool_limits_figures(self.to.mapping),
            dls=None if self.cfg.channel.space == "joint" else {
                s.name: dls_figures(s.mapping) for s in self.sites},
        )  # fmt: skip


class _SessionRun(LoopHooks):
    """A session's run in the loop: its ticks (and a test's observer after each), its staged
    stop, its summary."""

    def __init__(
        self,
        session: Session,
        progress: Callable[[int, int], None] | None,
        observer: Callable[[Session], None] | None,
    ) -> None:
        self.session, self._progress, self._observer = session, progress, observer
        self.summary: Summary | None = None

    def step(self) -> None:
        self.session.step()
        if self._observer is not None:
            self._observer(self.session)

    def tick(self) -> Callable[[], None]:
        # without an observer the loop calls the session's step itself: one call less a tick
        return self.session.step if self._observer is None else self.step

    def bring_to_rest(self, clock: TickClock) -> str:
        return self.session._bring_to_rest(clock)

    def progress(self, done: int, total: int) -> None:
        if self._progress is not None:
            self._progress(done, total)

    def finish(self, outcome: LoopOutcome) -> dict:
        self.summary = self.session._summary(outcome)
        return self.summary.to_dict()
