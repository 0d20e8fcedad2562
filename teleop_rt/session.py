"""A bilateral session: builds the blocks of Fig 2 from a config and runs fixed-step ticks.

One tick k (see ../shared/docs/architecture.md), in this order:
1. wait for the deadline (real-time mode);
2. read both backends (q, v, tau_ext);
3. COM: omega_c = v_h and tau_t = -tau_ext_t in, tau_c and omega_t out (eq 9, 10);
4. controllers: a_ref_h = C1(tau_h - tau_c), a_ref_t = C2(omega_t - v_t) (eq 4, 14);
5. computed torque: g = M M_v^-1 a_ref + n - tau_ext (eq 2, 12), one RNEA per robot;
6. write both backends; accumulate T_p, T_tau (eq 18) and timing.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from teleop_rt.analysis.transparency import TransparencyAccumulator
from teleop_rt.com.direct import DirectChannel
from teleop_rt.com.wave import WaveChannel
from teleop_rt.config import SessionConfig, per_joint
from teleop_rt.control import ComputedTorque, Pid
from teleop_rt.errors import ConfigError, SafetyStop
from teleop_rt.hal.base import Backend, create_backend
from teleop_rt.loop import StopSignals, TickClock, TimingStats, acquire_realtime
from teleop_rt.model import RobotModel
from teleop_rt.safety import Supervisor

if TYPE_CHECKING:
    from teleop_rt.recording.recorder import Recorder
    from teleop_rt.world import Load


class Side:
    """One robot of the pair on the controller side: model, backend, controllers, signals."""

    def __init__(
        self, cfg: SessionConfig, name: str, backend_name: str, operator: Load | None = None
    ) -> None:
        spec = getattr(cfg, name)
        self.name = name
        self.model = RobotModel.from_spec(spec.robot, name, cfg.plant.coulomb_smoothing_rad_s)
        n = self.model.nv
        self.virtual_mass = per_joint(spec.virtual_mass, n, f"{name}.virtual_mass")
        self.controller = Pid(spec.controller, n, cfg.dt, f"{name}.controller")
        self.computed_torque = ComputedTorque(
            self.model, self.virtual_mass, spec.compensate_friction
        )
        self.backend: Backend = create_backend(backend_name, cfg, name, self.model, operator)
        self.error = [0.0] * n
        self.a_ref = self.controller.out  # reference acceleration (updated in place)
        self.tau_cmd = self.computed_torque.tau  # motor torque command (updated in place)
        self.feedback = self.backend.feedback


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
    """Everything of one teleoperation session, preallocated at construction."""

    def __init__(self, cfg: SessionConfig, operator: Load | None = None) -> None:
        """``operator`` replaces the config's operator model (replay drives it from a log)."""
        self.cfg = cfg
        backend = cfg.backend
        self.dt = cfg.dt
        self.hsi = Side(cfg, "hsi", backend, operator)
        self.to = Side(cfg, "to", backend)
        n = self.hsi.model.nv
        if self.to.model.nv != n:
            raise ConfigError(
                f"to.robot: the TO has {self.to.model.nv} joints but the HSI has {n}; "
                "the channel couples joint to joint"
            )
        self.n = n
        if cfg.channel.mode == "direct":
            self.channel: WaveChannel | DirectChannel = DirectChannel(n, cfg.delay_ticks, self.dt)
        else:
            b = per_joint(cfg.channel.wave_impedance, n, "channel.wave_impedance")
            self.channel = WaveChannel(b, cfg.delay_ticks, self.dt, cfg.channel.wave_filter_hz)
        # per-tick signals as lists (scalar path); tau_e: torque the TO applies to the
        # environment, = tau_t of the channel
        self.tau_h = [0.0] * n
        self.tau_e = [0.0] * n
        self.tick = 0
        self.metrics = TransparencyAccumulator(n, self.dt)
        self.supervisor = Supervisor(cfg.safety, self.hsi.model, self.to.model, self.dt)

    def step(self) -> None:
        """One control tick: read, channel, controllers, computed torque, write."""
        hsi, to, ch, n = self.hsi, self.to, self.channel, self.n
        fb_h = hsi.backend.read()
        fb_t = to.backend.read()
        v_h, v_t = fb_h.v_list, fb_t.v_list
        tau_h, tau_e = self.tau_h, self.tau_e
        tau_h[:] = fb_h.tau_ext
        tau_ext_t = fb_t.tau_ext
        for j in range(n):
            tau_e[j] = -tau_ext_t[j]
        ch.step(v_h, tau_e)
        err_h, err_t, tau_c, omega_t = hsi.error, to.error, ch.tau_c, ch.omega_t
        for j in range(n):
            err_h[j] = tau_h[j] - tau_c[j]
            err_t[j] = omega_t[j] - v_t[j]
        a_ref_h = hsi.controller.step(err_h)
        a_ref_t = to.controller.step(err_t)
        g_h = hsi.computed_torque.step(fb_h.q, fb_h.v, a_ref_h, tau_h, v_h)
        g_t = to.computed_torque.step(fb_t.q, fb_t.v, a_ref_t, tau_ext_t, v_t)
        # step 7, safety: nothing unchecked reaches a motor (may saturate g_h, g_t in place)
        self.supervisor.step(
            self.tick,
            fb_h, tau_h, g_h, hsi.computed_torque.a_des_list,
            fb_t, tau_ext_t, g_t, to.computed_torque.a_des_list,
        )  # fmt: skip
        hsi.backend.write(g_h)
        to.backend.write(g_t)
        self.metrics.add(fb_h.q_list, fb_t.q_list, tau_h, tau_e)
        self.tick += 1

    def run(
        self,
        ticks: int | None = None,
        realtime: bool = False,
        overrun: str = "catch_up",
        progress: Callable[[int, int], None] | None = None,
        observer: Callable[[Session], None] | None = None,
        recorder: Recorder | None = None,
    ) -> Summary:
        """Run ``ticks`` ticks (default: the config's duration) and return the summary.

        ``observer(session)`` is called after every tick (tests); ``recorder`` records every
        tick and is closed (the log finalized, with the summary) however the run ends.
        ``progress(done, total)`` is called about 20 times a second of wall time. SIGINT and
        SIGTERM end the run at the next tick boundary; an exception ends it at once, and the
        log still holds every completed tick.
        """
        total = self.cfg.n_ticks if ticks is None else ticks
        period_ns = int(round(self.dt * 1e9))
        stats = TimingStats(total, period_ns)
        clock = TickClock(period_ns, realtime, overrun)
        grant = acquire_realtime() if realtime else None
        notes = list(grant.notes) if grant else []
        stop = StopSignals()
        error: str | None = None
        safety_stop = False
        perf = time.perf_counter_ns
        next_report = 0
        wall_start = perf()
        try:
            stop.install()
            self.hsi.backend.start()
            self.to.backend.start()
            clock.start()
            for k in range(total):
                if stop.requested:
                    break
                lateness = clock.wait()
                t0 = perf()
                self.step()
                if observer is not None:
                    observer(self)
                t1 = perf()
                missed = clock.finish(clock.now_ns()) if realtime else False
                stats.add(t1 - t0, lateness, missed)
                if recorder is not None:
                    recorder.record(t1 - t0, lateness, missed)
                if progress is not None and t1 >= next_report:
                    progress(k + 1, total)
                    next_report = t1 + 50_000_000
        except SafetyStop as exc:
            error = f"safety stop: {exc}"
            safety_stop = True
            notes.append(f"after the stop: {self._bring_to_rest()}")
        except BaseException as exc:
            error = f"{type(exc).__name__}: {exc}"
            raise
        finally:
            stop.uninstall()
            self.hsi.backend.stop()
            self.to.backend.stop()
            if grant:
                grant.release()
            notes += self.hsi.backend.notes() + self.to.backend.notes()
            summary = self._summary(
                stats, clock, realtime, notes, wall_start, stop, error, safety_stop
            )
            if recorder is not None:
                recorder.close(summary.to_dict())
        if progress is not None:
            progress(stats.count, total)
        return summary

    def _bring_to_rest(self) -> str:
        """The reaction to a safety stop: the HSI is damped, the TO is brought to zero velocity
        under its own velocity loop; then (in run's finally) both get zero torque. Sensors that
        are not usable end it at once with zero torque."""
        spec = self.cfg.safety
        hsi, to = self.hsi, self.to
        try:
            return self._damp_and_rest(spec, hsi, to)
        except SafetyStop as exc:  # a second fault while stopping: zero torque at once
            return f"a further fault while stopping ({exc}): zero torque"

    def _damp_and_rest(self, spec, hsi: Side, to: Side) -> str:
        zeros = np.zeros(self.n)
        gains = to.controller.kp
        limits = self.supervisor.limits
        for i in range(spec.stop_max_ticks):
            fb_h, fb_t = hsi.backend.read(), to.backend.read()
            values = fb_h.v_list + fb_t.v_list + fb_h.q_list + fb_t.q_list + list(fb_t.tau_ext)
            if fb_h.age_ticks or fb_t.age_ticks or not all(map(math.isfinite, values)):
                return f"sensors unusable after {i} ticks: zero torque"
            gravity = hsi.model.rnea(fb_h.q, zeros, zeros)
            g_h = [
                gravity[j] - spec.stop_damping_nm_s_per_rad * fb_h.v_list[j] for j in range(self.n)
            ]
            a_t = [-gains[j] * fb_t.v_list[j] for j in range(self.n)]
            g_t = to.computed_torque.step(fb_t.q, fb_t.v, a_t, list(fb_t.tau_ext), fb_t.v_list)
            limits["hsi"].clamp_effort(g_h)
            limits["to"].clamp_effort(g_t)
            hsi.backend.write(g_h)
            to.backend.write(g_t)
            if max(abs(x) for x in fb_t.v_list) < 1e-3:
                return f"TO at rest after {i + 1} ticks, then zero torque"
        return f"TO not at rest after {spec.stop_max_ticks} ticks; zero torque"

    def _summary(
        self, stats, clock, realtime, notes, wall_start, stop, error, safety_stop
    ) -> Summary:
        timing = stats.summary()
        timing["wall_s"] = (time.perf_counter_ns() - wall_start) / 1e9
        if realtime and clock.skipped:
            timing["skipped_deadlines"] = clock.skipped
        stopped = stop.reason if stop.requested else error
        return Summary(
            name=self.cfg.name,
            ticks=stats.count,
            simulated_time_s=stats.count * self.dt,
            delay_ticks=self.cfg.delay_ticks,
            t_p=list(self.metrics.t_p),
            t_tau=list(self.metrics.t_tau),
            channel_energy_j=self.channel.total_energy,
            min_channel_energy_j=self.channel.min_total_energy,
            timing=timing,
            realtime=realtime,
            notes=notes,
            stopped_early=stopped,
            stop_signal=stop.signum,
            safety_stop=safety_stop,
            saturated_ticks=self.supervisor.saturated_ticks,
        )
