"""A bilateral session: builds the blocks of Fig 2 from a config and runs fixed-step ticks.

One tick k (see ../shared/docs/architecture.md), in this order:
1. wait for the deadline (real-time mode);
2. read both backends (q, v, tau_ext);
3. COM: omega_c = v_h and tau_t = -tau_ext_t in, tau_c and omega_t out (eq 9, 10);
4. controllers: a_ref_h = C1(tau_h - tau_c), a_ref_t = C2(omega_t - v_t) (eq 4, 14);
5. computed torque: g = M M_v^-1 a_ref + n - tau_ext (eq 2, 12), one RNEA per robot;
6. safety checks, then write both backends; accumulate T_p, T_tau (eq 18) and timing.

Steps 3-6 but the RNEA calls are compiled (``teleop_rt.tick``) and run on the blocks' state,
packed into two flat buffers when the session is built (``teleop_rt.flat``). Two simulated
plants are packed along; in their common case the session runs steps 2-6 and both plants'
periods as four compiled calls around the six Pinocchio calls (``teleop_rt.sim_tick``), bit for
bit what ``read`` and ``write`` compute.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from teleop_rt.analysis.transparency import TransparencyAccumulator
from teleop_rt.com.direct import DirectChannel
from teleop_rt.com.wave import WaveChannel
from teleop_rt.config import SessionConfig, per_joint
from teleop_rt.control import ComputedTorque, Pid
from teleop_rt.errors import ConfigError, SafetyStop
from teleop_rt.flat import Packed
from teleop_rt.hal.base import Backend, create_backend
from teleop_rt.hal.sim import SimBackend
from teleop_rt.hal.stopping import stop_all
from teleop_rt.loop import StopSignals, TickClock, TimingStats, acquire_realtime
from teleop_rt.model import RobotModel
from teleop_rt.safety import Supervisor
from teleop_rt.sim_tick import (
    PLANT_H,
    finish_and_command,
    integrate,
    next_ticks,
    sense_and_prepare,
    warm_up_simulated_tick,
)
from teleop_rt.tick import BLOCK_ORDER, TickSignals, after_models, before_models

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
        self.feedback = self.backend.feedback

    @property
    def a_ref(self) -> np.ndarray:
        """Reference acceleration times the virtual mass (the controller's output)."""
        return self.controller.out

    @property
    def tau_cmd(self) -> np.ndarray:
        """Motor torque command (after the safety layer's saturation)."""
        return self.computed_torque.tau


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
        self.signals = TickSignals(n)
        self.tick = 0
        self.metrics = TransparencyAccumulator(n, self.dt)
        self.supervisor = Supervisor(cfg.safety, self.hsi.model, self.to.model, self.dt)
        self._pack()

    def _pack(self) -> None:
        """All blocks into one pair of buffers, for the compiled halves of the tick."""
        hsi, to, sup = self.hsi, self.to, self.supervisor
        blocks = {
            "fb_h": hsi.feedback, "fb_t": to.feedback, "signals": self.signals,
            "channel": self.channel, "pid_h": hsi.controller, "pid_t": to.controller,
            "ct_h": hsi.computed_torque, "ct_t": to.computed_torque, "supervisor": sup,
            "guard_h": sup.guards["hsi"], "guard_t": sup.guards["to"], "metrics": self.metrics,
            "world_h": hsi.backend.world, "world_t": to.backend.world,
        }  # fmt: skip
        ordered = [blocks[name] for name in BLOCK_ORDER]
        # two simulated plants' blocks follow, so that one compiled call reaches both the
        # controller's and the plants' state (teleop_rt.sim_tick)
        plants = [s.backend for s in (hsi, to) if isinstance(s.backend, SimBackend)]
        if len(plants) < 2:
            plants = []
        ranges = []
        for plant in plants:
            ranges.append((len(ordered), len(ordered) + len(plant.blocks)))
            ordered += plant.blocks
        self.packed = p = Packed(ordered)
        for plant, (first, end) in zip(plants, ranges, strict=True):
            plant.rebind(p.f, p.i, p.offsets[2 * first : 2 * end])
        # what the tick passes on each call, looked up once
        self._buffers = (p.f, p.i, p.offsets, self.n)
        self._pin = [
            (side.model.model, side.model.data, side.feedback.q, side.feedback.v,
             side.computed_torque.a_des)
            for side in (hsi, to)
        ]  # fmt: skip
        # load (or, on a fresh install, compile) the kernels now, on scratch copies of the
        # state, not at the first deadline
        f, i, o, n = self._buffers
        before_models(f.copy(), i.copy(), o, n)
        after_models(f.copy(), i.copy(), o, n, np.zeros(n), np.zeros(n))
        # the fused tick: the same arithmetic as read / write, in fewer calls
        self.fused = bool(plants) and all(plant.compiled_common_case for plant in plants)
        if self.fused:
            # the layout the fused kernels assume: the HSI's plant right after the session's
            # blocks, the TO's from ``split`` to the end
            assert ranges[0][0] == PLANT_H and ranges[1][1] == len(ordered)
            self._split = ranges[1][0]
            self._plants = plants
            warm_up_simulated_tick(f.copy(), i.copy(), o, n, self._split)

    @property
    def tau_h(self) -> np.ndarray:
        """The operator's torque on the HSI, as measured this tick."""
        return self.signals.tau_h

    @property
    def tau_e(self) -> np.ndarray:
        """The TO's torque on the environment this tick (-tau_ext of the TO)."""
        return self.signals.tau_e

    def step(self) -> None:
        """One control tick: read, channel, controllers, computed torque, safety, write.

        With ``fused`` (two simulated plants in their common case) the reads and writes are the
        plants' compiled pieces inside the tick's own kernels (teleop_rt.sim_tick): the same
        arithmetic in four compiled calls, using the plants' cached Pinocchio arguments and
        Jacobian as their ``write`` would."""
        hsi, to = self.hsi, self.to
        f, i, o, n = self._buffers
        fused = self.fused
        if fused:
            sense_and_prepare(f, i, o, n, self._split)
        else:
            hsi.backend.read()  # into hsi.feedback
            to.backend.read()
            before_models(f, i, o, n)
        (model_h, data_h, q_h, v_h, a_h), (model_t, data_t, q_t, v_t, a_t) = self._pin
        rnea_h = pin.rnea(model_h, data_h, q_h, v_h, a_h)
        rnea_t = pin.rnea(model_t, data_t, q_t, v_t, a_t)
        supervisor = self.supervisor
        if supervisor.workspaces:
            supervisor.check_workspaces(self.tick, hsi.feedback, to.feedback)
        if fused:  # only without a finding do the plants take the torques
            code = finish_and_command(f, i, o, n, self._split, rnea_h, rnea_t)
        else:
            code = after_models(f, i, o, n, rnea_h, rnea_t)
        if code:
            supervisor.raise_for(code, self.tick, hsi.feedback, to.feedback)
        if fused:
            plant_h, plant_t = self._plants
            integrate(f, i, o, n, self._split, pin.aba(*plant_h._pin), pin.aba(*plant_t._pin))
            next_ticks(
                f, i, o, n, self._split,
                plant_h._jacobian(), plant_h._x, plant_t._jacobian(), plant_t._x,
            )  # fmt: skip
        else:
            hsi.backend.write(hsi.computed_torque.tau)
            to.backend.write(to.computed_torque.tau)
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
            stop_all([self.hsi.backend, self.to.backend], self.dt)
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
            values = (fb_h.v, fb_t.v, fb_h.q, fb_t.q, fb_t.tau_ext)
            if fb_h.age_ticks or fb_t.age_ticks or not all(np.isfinite(x).all() for x in values):
                return f"sensors unusable after {i} ticks: zero torque"
            gravity = hsi.model.rnea(fb_h.q, zeros, zeros)
            g_h = gravity - spec.stop_damping_nm_s_per_rad * fb_h.v
            g_t = to.computed_torque.step(fb_t.q, fb_t.v, -gains * fb_t.v, fb_t.tau_ext)
            limits["hsi"].clamp_effort(g_h)
            limits["to"].clamp_effort(g_t)
            hsi.backend.write(g_h)
            to.backend.write(g_t)
            if np.abs(fb_t.v).max() < 1e-3:
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
            t_p=self.metrics.t_p.tolist(),
            t_tau=self.metrics.t_tau.tolist(),
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
