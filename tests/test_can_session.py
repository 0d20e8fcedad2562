"""Whole sessions on emulated CiA 402 drives (in-process, python-can ``virtual``) against the
same sessions on the simulated backend.

The emulated drives run the same plant as the sim backend; what differs is the transport:
positions, velocities and the sensor's torques go through encoder counts, drive velocity units
and sensor counts, the torques through per-mille of the rated torque (quantisation), and a
synchronous RPDO (CiA 402's CST mode) applies the torque computed from SYNC k's feedback at
SYNC k+1: one tick later than the sim backend, whose ``write`` acts on the state it just read.

* Against the sim backend with that one tick of command delay added, the emulated session
  agrees within 2 % in T_p and T_tau per joint: what remains is quantisation (about 1e-4 rad
  of encoder step at the joint, 1e-3 N m of torque step, 1e-5 N m of sensor step), the
  sensor's zeroing, and the emulated world's clock starting two ticks before the session's
  tick 0 (the joints are released when the drives enable; the master sees it a tick or two
  later, with the statusword every second SYNC).
* Against the plain sim backend, T_p stays within 5 %, but T_tau of the paper experiment grows
  by about 60 % / 30 % (joints 0 / 1): the extra tick sits inside the TO's contact loop while it
  pushes the 5000 N/m wall (up to 8 s, free space and foam, T_tau agrees within about 1 % and
  T_p within 4 %).
* With asynchronous RPDOs (``rpdo_transmission: async``: the drive applies the torque on
  reception) the tick disappears and the emulated session matches the plain sim backend
  within 2 %.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.cli import main
from teleop_rt.hal import sim
from teleop_rt.hal.base import FINALIZED, UNCONFIGURED, Backend, Feedback
from teleop_rt.hal.can.emulator import QSA, SOD, Fault
from teleop_rt.hal.registry import register_backend
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.session import Session

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper_experiment.yaml"
CAN = ROOT / "configs" / "can_emulated.yaml"
FAST = [
    "can.emulate=true",
    "can.hsi.torque_sensor.zero_ticks=50",
    "can.to.torque_sensor.zero_ticks=50",
]


class _OneTickLate(sim.SimBackend):
    """The sim backend with the torque applied one tick later (a synchronous drive's delay)."""

    def write(self, tau) -> None:
        previous = self._previous
        self._previous = list(tau)
        super().write(previous)


@register_backend("test_sim_one_tick_late")
def _one_tick_late(cfg, side, model, operator=None):
    backend = sim.make_sim(cfg, side, model, operator)
    backend.__class__ = _OneTickLate
    backend._previous = [0.0] * backend.n
    return backend


def run(path: Path, *overrides: str):
    return Session(config.load(path, list(overrides))).run()


def rel(a: list[float], b: list[float]) -> list[float]:
    return [abs(x - y) / abs(y) for x, y in zip(a, b, strict=True)]


@pytest.fixture(scope="module")
def sim_runs():
    return run(PAPER), run(PAPER, "backend=test_sim_one_tick_late")


def test_emulated_drives_close_the_same_loop_one_tick_later(sim_runs) -> None:
    plain, late = sim_runs
    can = run(CAN, *FAST)
    assert can.ticks == 12000 and can.stopped_early is None
    assert max(rel(can.t_p, late.t_p)) < 0.02, (can.t_p, late.t_p)
    assert max(rel(can.t_tau, late.t_tau)) < 0.02, (can.t_tau, late.t_tau)
    assert max(rel(can.t_p, plain.t_p)) < 0.05, (can.t_p, plain.t_p)
    # the tick of transport inside the wall contact: T_tau grows, and by the same as 'late'
    assert all(c > p for c, p in zip(can.t_tau, plain.t_tau, strict=True))


def test_asynchronous_rpdos_match_the_sim_backend(sim_runs) -> None:
    plain, _ = sim_runs
    can = run(CAN, *FAST, "can.rpdo_transmission=async")
    assert can.ticks == 12000 and can.stopped_early is None
    assert max(rel(can.t_p, plain.t_p)) < 0.02, (can.t_p, plain.t_p)
    assert max(rel(can.t_tau, plain.t_tau)) < 0.02, (can.t_tau, plain.t_tau)


def test_a_drive_fault_mid_session_stops_it_safely_and_the_log_keeps_every_tick(
    tmp_path: Path,
) -> None:
    cfg = config.load(CAN, [*FAST, "duration_s=2"])
    session = Session(cfg)

    def inject(s: Session) -> None:
        if s.tick == 300:  # after tick 299: the TO's drive 2 sends an EMCY at the next SYNC
            s.to.backend.emulator.inject(Fault("emcy", 2))

    log = tmp_path / "fault.mcap"
    summary = session.run(observer=inject, recorder=Recorder(session, log))
    assert summary.safety_stop and summary.ticks == 300
    assert "to joint 1 (drive node 2): EMCY 0x2310" in summary.stopped_early
    data = read_log(log)
    assert data.ticks == 300 and not data.truncated
    for side in (session.hsi, session.to):  # both robots quick-stopped and disabled
        for drive in side.backend.emulator.drives:
            assert drive.state in (SOD, "FAULT")
            assert drive.commands[-1][1] == 0


def test_cli_runs_the_paper_experiment_on_emulated_drives(capsys) -> None:
    code = main(
        [
            "run",
            str(PAPER),
            "--backend",
            "can",
            "--set",
            "can.emulate=true",
            "--duration",
            "0.3",
            "--no-log",
            "--json",
        ]
    )
    assert code == 0
    assert '"ticks": 300' in capsys.readouterr().out


def test_a_drive_that_never_enables_is_a_safe_stop_at_start() -> None:
    # a drive that ignores its controlwords stays SWITCH ON DISABLED: the enable phase times out
    cfg = config.load(CAN, [*FAST, "duration_s=0.1", "can.enable_timeout_ticks=30"])
    session = Session(cfg)
    original = session.hsi.backend._open_bus

    def open_bus():
        bus = original()
        drive = session.hsi.backend.emulator.drives[0]
        drive._controlword = lambda cw: None  # ignores every controlword
        return bus

    session.hsi.backend._open_bus = open_bus
    summary = session.run()
    assert summary.safety_stop and summary.ticks == 0
    assert "hsi drives did not reach OPERATION ENABLED within 30 ticks" in summary.stopped_early
    assert "node 1: SWITCH ON DISABLED" in summary.stopped_early


def test_both_robots_stop_together_each_bus_cycling_until_its_drives_are_disabled() -> None:
    """The stop is stepped on both buses at once: every period each bus still stopping gets
    its SYNC and one RPDO per drive, until its drives report SWITCH ON DISABLED; then one
    last SYNC and NMT pre-operational. The drives take a few SYNCs to decelerate in QUICK
    STOP ACTIVE (the TO's longer), so the two robots' stops overlap."""
    cfg = config.load(CAN, [*FAST, "duration_s=0.03"])
    session = Session(cfg)
    total = cfg.n_ticks
    events: list[tuple] = []  # (side, frame kind, the drives' states when it arrived)

    def watch(s: Session) -> None:
        if s.tick == 1:
            for name, side, syncs in (("hsi", s.hsi, 4), ("to", s.to, 9)):
                emu = side.backend.emulator
                for d in emu.drives:
                    d.quick_stop_syncs = syncs
                emu.handle = logged(name, emu, emu.handle)
        if s.tick == total:
            events.append(("stop",))  # the loop is over: the stop begins

    def logged(name, emu, handle):
        def log(msg) -> None:
            cob = msg.arbitration_id
            kind = {0x080: "SYNC", 0x000: "NMT"}.get(cob, "RPDO" if 0x201 <= cob <= 0x27F else "")
            if kind:
                events.append((name, kind, tuple(d.state for d in emu.drives)))
            handle(msg)

        return log

    summary = session.run(observer=watch)
    assert summary.ticks == total and summary.stopped_early is None
    stop = events[events.index(("stop",)) + 1 :]
    counts = {}
    for name in ("hsi", "to"):
        frames = [e[1:] for e in stop if e[0] == name]
        kinds = [k for k, _ in frames]
        n = kinds.count("SYNC")
        counts[name] = n
        # every period a SYNC and an RPDO per drive, then the last SYNC and NMT per drive
        assert kinds == ["SYNC", "RPDO", "RPDO"] * (n - 1) + ["SYNC", "NMT", "NMT"], kinds
        last_sync = len(kinds) - 3
        assert frames[last_sync][1] == (SOD, SOD)  # disabled before NMT pre-operational
        decelerating = [states for kind, states in frames if kind == "SYNC" and QSA in states]
        assert len(decelerating) >= {"hsi": 4, "to": 9}[name]  # SYNC all the way through it
    assert counts["to"] > counts["hsi"] + 2  # the TO went on stopping after the HSI was done
    syncs = [e[0] for e in stop if e[1] == "SYNC"]
    both = ["hsi", "to"] * counts["hsi"] + ["to"] * (counts["to"] - counts["hsi"])
    assert syncs == both  # one period: one SYNC on each bus still stopping


def test_stop_all_stops_the_others_when_one_robot_fails_to_stop() -> None:
    from teleop_rt.hal.stopping import stop_all

    class Robot(Backend):
        """A robot whose deactivation takes ``steps`` periods, or raises at the first."""

        def __init__(self, steps: int, fail: bool = False) -> None:
            super().__init__(1)
            self.steps, self.fail, self.calls = steps, fail, 0
            self.configure()
            self.activate()

        def read(self) -> Feedback:
            return self.feedback

        def write(self, tau: np.ndarray) -> None:
            return

        def on_deactivate_step(self) -> bool:
            self.calls += 1
            if self.fail:
                raise RuntimeError("bus gone")
            return self.calls >= self.steps

    broken, slow = Robot(1, fail=True), Robot(5)
    with pytest.raises(RuntimeError, match="bus gone"):
        stop_all([broken, slow], 1e-4)
    assert (broken.calls, slow.calls) == (1, 5)  # the broken one not retried, the other done
    # released: the one that stopped cleaned up (it may run again), the broken one finalized
    assert (broken.lifecycle, slow.lifecycle) == (FINALIZED, UNCONFIGURED)
    stuck, quick = Robot(10**9), Robot(2)
    assert stop_all([stuck, quick], 1e-5, max_steps=20) == [stuck]  # bounded
    assert stuck.calls == 20 and (stuck.lifecycle, quick.lifecycle) == (FINALIZED, UNCONFIGURED)


def test_a_pdo_longer_than_its_mapping_is_read_counted_and_noted() -> None:
    """A drive that pads its 4-byte TPDO2 to 5 bytes from the first SYNC on (CiA 301: the
    consumer uses the mapped leading bytes): the session runs, the summary says so."""
    cfg = config.load(CAN, [*FAST, "duration_s=0.2"])
    session = Session(cfg)
    backend = session.hsi.backend
    original = backend._open_bus

    def open_bus():
        bus = original()
        backend.emulator.inject(Fault("long_tpdo", 1, 0))  # from world tick 0: start-up too
        return bus

    backend._open_bus = open_bus
    summary = session.run()
    assert summary.ticks == 200 and summary.stopped_early is None
    count = backend.stats["long_pdos"]
    assert count > 100  # TPDO2 every second SYNC, start-up included
    assert (
        f"can: hsi joint 0 (drive node 1): {count} PDO(s) 0x281 of 5 bytes, longer than their "
        "mapping (4 bytes): the mapped leading bytes were used (CiA 301)"
    ) in summary.notes
    assert [d.state for d in backend.emulator.drives] == [SOD, SOD]  # stopped as usual


class _PacedStop:
    """``teleop_rt.hal.stopping``'s clock in the SYNC-gap test: a deadline always ahead, so
    each period of ``stop_all`` sleeps once, and the sleep marks the period."""

    def __init__(self, mark) -> None:
        self.sleep = lambda _s: mark()

    @staticmethod
    def perf_counter_ns() -> int:
        return 0


@pytest.mark.parametrize("lost", ["hsi", "to"])
def test_every_bus_gets_its_sync_every_period_through_a_node_loss_on_either(
    lost: str, monkeypatch
) -> None:
    """A drive node on one bus goes silent (no TPDO, no heartbeat: unplugged). Its robot's
    backend stops the session within ``missed_feedback_ticks``; the staged stop, then both
    backends' stops follow. Through all of it, every period (a loop tick, a tick of the staged
    stop, a period of ``stop_all``) each bus gets exactly one SYNC until its NMT
    pre-operational: a drive watches its SYNC by the wall clock, so a period without one is a
    period the drive runs on a stale command, whatever the other bus does. Counted in periods,
    not in wall time (what this test guards is the sequence; in real time each period is
    paced by the same clock)."""
    from teleop_rt import loop
    from teleop_rt.hal import stopping

    cfg = config.load(CAN, [*FAST, "duration_s=1"])
    session = Session(cfg)
    events: list[str] = []  # "|" a period begins; "hsi" / "to": a SYNC; "hsi NMT" / "to NMT"
    mark = lambda: events.append("|")  # noqa: E731
    wait = loop.TickClock.wait
    monkeypatch.setattr(loop.TickClock, "wait", lambda clock: (mark(), wait(clock))[1])
    monkeypatch.setattr(stopping, "time", _PacedStop(mark))

    def logged(name, handle):
        def log(msg) -> None:
            if msg.arbitration_id == 0x080:
                events.append(name)
            elif msg.arbitration_id == 0x000:
                events.append(f"{name} NMT")
            handle(msg)

        return log

    def watch(s: Session) -> None:
        if s.tick == 1:
            for name, site in (("hsi", s.hsi), ("to", s.to)):
                emu = site.backend.emulator
                emu.handle = logged(name, emu.handle)
        if s.tick == 300:  # node 1 of the lost bus unplugged from the next SYNC on
            emu = getattr(s, lost).backend.emulator
            emu.inject(Fault("drop_tpdo", 1))
            emu.inject(Fault("stop_heartbeat", 1))

    summary = session.run(observer=watch)
    assert summary.safety_stop and f"{lost} joint 0 (drive node 1): no feedback" in (
        summary.stopped_early
    ), summary.stopped_early
    assert 300 < summary.ticks <= 300 + cfg.can.missed_feedback_ticks + 1
    periods: list[list[str]] = []
    for e in events[events.index("hsi") :]:  # from the first period whose SYNCs were seen
        if e == "|":
            periods.append([])
        elif periods:
            periods[-1].append(e)
    for name in ("hsi", "to"):
        end = next(k for k, p in enumerate(periods) if f"{name} NMT" in p)
        counts = [p.count(name) for p in periods[: end + 1]]
        gaps = [k for k, c in enumerate(counts) if c != 1]
        assert not gaps, (
            f"{name} bus: periods without exactly one SYNC at {gaps[:10]} of {len(counts)} "
            f"(loop ticks {summary.ticks}; {sum(c == 0 for c in counts)} without SYNC)"
        )
        assert end > summary.ticks  # the periods after the loop (the stops) were counted
