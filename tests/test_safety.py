"""The safety layer: nothing non-finite or out of limits reaches a motor; a violation ends the
session with the tick, robot, joint and reason, and the log keeps every tick up to it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.cli import main
from teleop_rt.errors import ConfigError, SafetyStop
from teleop_rt.hal.signals import Feedback
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.safety import RobotGuard, check_all
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PAPER = CONFIGS / "paper_experiment.yaml"


class Guards:
    """Both sites' guards for a safety spec."""

    def __init__(self, **spec) -> None:
        session = Session(config.load(PAPER, ["duration_s=0.01"]))
        cfg = config.SafetySpec(**spec)
        self.guards = {s.name: RobotGuard(cfg, s.model, s.name, session.dt) for s in session.sites}


def supervisor(**spec) -> Guards:
    return Guards(**spec)


def feedback(q: list[float], v: list[float], age_ticks: int = 0) -> Feedback:
    fb = Feedback(len(q))
    fb.q[:], fb.v[:], fb.age_ticks = q, v, age_ticks
    return fb


def test_non_finite_measurement_is_a_stop_naming_robot_and_joint() -> None:
    guards = supervisor().guards
    with pytest.raises(SafetyStop, match=r"^tick 7: to joint 1 \(elbow\): measured torque is nan"):
        guards["to"].check_measured(7, [0.0, 1.0], [0.0, 0.0], [0.0, float("nan")])
    with pytest.raises(
        SafetyStop, match=r"^tick 8: hsi joint 0 \(shoulder\): commanded torque is nan"
    ):
        guards["hsi"].check(8, feedback([0.0, 1.0], [0.0, 0.0]), [float("nan"), 0.0], [0.0] * 2)


def test_limits_from_the_urdf() -> None:
    guard = supervisor().guards["hsi"]
    zero = [0.0, 0.0]
    # scara_2dof.urdf: +-2.6 rad, 6 / 8 rad/s, 20 / 10 N m
    with pytest.raises(SafetyStop, match=r"hsi joint 0 \(shoulder\): angle 2.7 rad outside"):
        guard.check(0, feedback([2.7, 0.0], zero), [0.0, 0.0], zero)
    with pytest.raises(SafetyStop, match=r"joint 1 \(elbow\): speed -8.5 rad/s above 8"):
        guard.check(0, feedback(zero, [0.0, -8.5]), [0.0, 0.0], zero)
    cmd = [25.0, -12.0]
    assert guard.check(0, feedback(zero, zero), cmd, zero) is True
    assert cmd == [20.0, -10.0]  # saturated to the effort limits


def test_tracking_error_stops_after_its_tick_count_and_resets_on_a_good_tick() -> None:
    guard = supervisor(tracking_error_rad_s2=20.0, tracking_error_ticks=3).guards["to"]
    zero = [0.0, 0.0]
    guard.check(0, feedback(zero, zero), [0.0, 0.0], [100.0, 0.0])  # commands 100 rad/s^2
    # the joint does not accelerate: 100 rad/s^2 off, twice, then one good tick resets the run
    guard.check(1, feedback(zero, zero), [0.0, 0.0], [100.0, 0.0])
    guard.check(2, feedback(zero, zero), [0.0, 0.0], [100.0, 0.0])
    guard.check(3, feedback(zero, [0.1, 0.0]), [0.0, 0.0], [100.0, 0.0])  # (0.1 / 1 ms = 100)
    assert guard.run.tolist() == [0, 0]
    guard.check(4, feedback(zero, [0.1, 0.0]), [0.0, 0.0], [100.0, 0.0])
    guard.check(5, feedback(zero, [0.1, 0.0]), [0.0, 0.0], [100.0, 0.0])
    with pytest.raises(SafetyStop, match=r"^tick 6: to joint 0 .*does not follow"):
        guard.check(6, feedback(zero, [0.1, 0.0]), [0.0, 0.0], [100.0, 0.0])


def test_stale_feedback_is_a_stop_at_stale_ticks() -> None:
    guard = supervisor(stale_ticks=3).guards["hsi"]
    zero = [0.0, 0.0]
    guard.check(0, feedback(zero, zero, age_ticks=2), [0.0, 0.0], zero)
    with pytest.raises(SafetyStop, match=r"^tick 1: hsi feedback stale for 3 ticks"):
        guard.check(1, feedback(zero, zero, age_ticks=3), [0.0, 0.0], zero)


def test_saturation_that_lasts_is_a_stop() -> None:
    guard = supervisor(saturation_stop_ticks=5).guards["hsi"]
    zero = [0.0, 0.0]

    def tick(k: int, saturate: bool) -> None:  # 25 N m: above the HSI shoulder's 20 N m
        g_h = np.array([25.0 if saturate else 0.0, 0.0])
        check_all(guard, k, feedback(zero, zero), zero, g_h, zero)

    for k in range(4):
        tick(k, True)
    tick(4, False)  # a break resets the run
    for k in range(5, 9):
        tick(k, True)
    with pytest.raises(SafetyStop, match="tick 9: .*5 ticks in a row"):
        tick(9, True)
    assert guard.saturated_ticks == 9


def test_an_unstable_session_ends_in_a_safety_stop_with_its_log(tmp_path: Path) -> None:
    cfg = config.load(PAPER, ["duration_s=3", "hsi.controller.kp=1e6"])  # a wildly unstable HSI
    session = Session(cfg)
    summary = session.run(recorder=Recorder(session, tmp_path / "unstable.mcap"))
    assert summary.safety_stop and summary.stopped_early.startswith("safety stop: tick ")
    assert summary.ticks < 3000
    log = read_log(tmp_path / "unstable.mcap")
    assert log.ticks == summary.ticks and log.summary["safety_stop"] is True
    # zero torque after the stop: the backends were stopped
    assert session.hsi.backend.tau_motor.tolist() == [0.0, 0.0]


def test_cli_exit_code_3_on_a_safety_stop(capsys) -> None:
    code = main(["run", str(PAPER), "--no-log", "--duration", "3", "--set",
                 "hsi.controller.kp=1e6", "--json"])  # fmt: skip
    assert code == 3


# --- end-effector workspace ---------------------------------------------------------------------
def planar_tool(q1: float, q2: float) -> tuple[float, float]:
    """scara_2dof.urdf's tool in the plane: links of 0.30 m and 0.25 m (closed form)."""
    return (
        0.30 * math.cos(q1) + 0.25 * math.cos(q1 + q2),
        0.30 * math.sin(q1) + 0.25 * math.sin(q1 + q2),
    )


def test_workspace_box_stops_the_tool_outside_it_and_names_axis_and_bound() -> None:
    box = {"to": {"lower_m": [0.1, -0.05], "upper_m": [0.6, 0.4]}}
    guard = supervisor(workspace=box).guards["to"]
    zero = [0.0, 0.0]
    inside = [0.3, 0.7]  # tool at (0.4217, 0.2990)
    assert planar_tool(*inside)[1] == pytest.approx(0.2990, abs=1e-4)
    guard.check(0, feedback(inside, zero), [0.0, 0.0], zero)
    outside = [-0.8, 0.9]  # tool at y = 0.30 sin(-0.8) + 0.25 sin(0.1) = -0.190
    y = planar_tool(*outside)[1]
    with pytest.raises(SafetyStop) as info:
        guard.check(5, feedback(outside, zero), [0.0, 0.0], zero)
    msg = str(info.value)
    assert msg.startswith("tick 5: to tool frame 'tool' at y = ")
    assert float(msg.split("y = ")[1].split(" m")[0]) == pytest.approx(y, abs=1e-4)
    assert "outside its workspace [-0.05, 0.4] m" in msg
    # the HSI has no box: the same pose passes
    supervisor(workspace=box).guards["hsi"].check(0, feedback(outside, zero), [0.0, 0.0], zero)


def test_workspace_stop_in_a_session_keeps_the_log(tmp_path) -> None:
    # the paper experiment presses the TO against the wall at y = -0.06: a box ending at
    # y = -0.05 is left on the way there
    cfg = config.load(PAPER, ["safety.workspace.to={lower_m: [0.0, -0.05], upper_m: [0.6, 0.6]}"])
    session = Session(cfg)
    summary = session.run(recorder=Recorder(session, tmp_path / "ws.mcap"))
    assert summary.safety_stop
    assert "to tool frame 'tool' at y = -0.05" in summary.stopped_early
    assert 7000 < summary.ticks < 10_000  # on the way to the wall (7.5 s to 9 s)
    assert read_log(tmp_path / "ws.mcap").ticks == summary.ticks


@pytest.mark.parametrize(
    "box",
    [
        "{lower_m: [0.5, 0.0], upper_m: [0.1, 0.4]}",  # lower above upper
        "{lower_m: [0.0], upper_m: [0.4]}",  # one axis
        "{lower_m: [0.0, 0.0], upper_m: [0.4, 0.4, 0.4]}",  # axes differ
    ],
)
def test_a_contradictory_workspace_box_is_a_config_error(box: str) -> None:
    with pytest.raises(ConfigError, match=r"safety\.workspace\.to"):
        config.load(PAPER, [f"safety.workspace.to={box}"])


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "teleop_rt.cli", *args], capture_output=True, text=True,
        timeout=600, cwd=cwd,
    )  # fmt: skip


def test_safety_off_still_never_sends_a_nan_torque(tmp_path: Path) -> None:
    """safety.enabled: false with a NaN torque sensor: the session stops at the fault's tick
    (zero torque then), and check and run warn that the safety layer is off."""
    nan_fault = "plant.faults=[{kind: nan, robot: to, joint: 1, start_s: 0.5, duration_s: 0.2}]"
    args = [str(PAPER), "--set", "safety.enabled=false", "--set", nan_fault]
    check = run_cli("check", *args, cwd=tmp_path)
    assert check.returncode == 0 and "warning: safety.enabled is false" in check.stderr
    out = run_cli("run", *args, "--duration", "2", "--json", "--no-log", cwd=tmp_path)
    assert out.returncode == 3, out.stderr
    summary = json.loads(out.stdout)
    assert summary["ticks"] == 500 and "measured torque is nan" in summary["stopped_early"]
    assert "warning: safety.enabled is false" in out.stderr


def test_an_implausible_measured_torque_stops_within_the_tick() -> None:
    """A 1e6 N m sensor bias (far beyond 3 x the URDF effort limit) stops the session at the
    first tick that measures it, before any motor is commanded from it."""
    bias = "plant.faults=[{kind: bias, robot: hsi, joint: 0, start_s: 0.3, magnitude: 1.0e6}]"
    session = Session(config.load(PAPER, ["duration_s=1", bias]))
    summary = session.run()
    assert summary.safety_stop and summary.ticks == 300
    assert "hsi joint 0 (shoulder): measured torque 1e+06 N m is implausible (above 60" in (
        summary.stopped_early
    )
    assert np.abs(session.hsi.backend.tau_motor).max() <= 20.0  # never driven from it


def test_the_plausibility_bounds_are_configurable() -> None:
    bias = "plant.faults=[{kind: bias, robot: to, joint: 1, start_s: 0.1, magnitude: 5.0}]"
    untracked = ["duration_s=0.3", bias, "safety.tracking_error_ticks=0"]  # (a bias derails it)
    quiet = Session(config.load(PAPER, untracked)).run()
    assert not quiet.safety_stop, quiet.stopped_early  # 5 N m is plausible for a 10 N m joint
    tight = [*untracked, "safety.measured_torque_limit_nm=[100.0, 4.0]"]
    stopped = Session(config.load(PAPER, tight)).run()
    assert stopped.safety_stop and stopped.ticks == 100
    assert "to joint 1 (elbow): measured torque 5 N m is implausible" in stopped.stopped_early


def test_each_finding_is_declared_once_and_the_kernels_return_its_code() -> None:
    """The finding codes (safety.Finding): distinct, below the sites' own (from 200), the
    kernels' constants (FOUND) the same numbers, and what a compiled check returns is the
    code whose declared wording the stop carries."""
    from teleop_rt.mapping import PRESENCE_LOST
    from teleop_rt.safety import FOUND, Finding, guard_check
    from teleop_rt.task_limits import TOOL_FORCE

    assert FOUND._asdict() == {x.name: int(x) for x in Finding}
    assert all(type(code) is int for code in FOUND)  # (numba folds ints, not enum members)
    assert max(Finding) < min(PRESENCE_LOST, TOOL_FORCE)
    guard = supervisor(torque_limits="stop").guards["hsi"]
    guard.joint, guard.value = 1, 4.0
    for finding in Finding:  # every finding's wording takes only what the guard gives it
        if finding is not Finding.OK:
            text = str(guard.stop_for(3, finding, 2))
            assert text.startswith("tick 3: hsi") and "{" not in text, text
            assert ("hsi joint 1 (elbow): " in text) == finding.joint, text
    n = guard.n
    cases = (  # (q, v, age, tau) -> the finding
        ([0.0, 9.0], [0.0, 0.0], 0, [0.0, 0.0], Finding.ANGLE),
        ([0.0, 0.0], [0.0, 0.0], guard.stale_ticks, [0.0, 0.0], Finding.STALE),
        ([0.0, 0.0], [0.0, 0.0], 0, [0.0, 1e9], Finding.TORQUE_LIMIT),
        ([0.0, 0.0], [0.0, 0.0], 0, [0.0, 0.0], Finding.OK),
    )
    for q, v, age, tau, expected in cases:
        code = guard_check(guard.f, guard.i, n, np.array(q), np.array(v), age, np.array(tau),
                           np.zeros(n))  # fmt: skip
        assert code == expected, (code, expected)
        if expected.joint and expected is not Finding.OK:
            assert guard.joint == 1
            assert expected.name.lower().split("_")[0] in str(guard.stop_for(0, code, age))
