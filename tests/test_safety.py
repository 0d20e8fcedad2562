"""The safety layer: nothing non-finite or out of limits reaches a motor; a violation ends the
session with the tick, robot, joint and reason, and the log keeps every tick up to it."""

from __future__ import annotations

from pathlib import Path

import pytest

from teleop_rt import config
from teleop_rt.cli import main
from teleop_rt.errors import SafetyStop
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.safety import Supervisor
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PAPER = CONFIGS / "paper_experiment.yaml"


def supervisor(**spec) -> Supervisor:
    session = Session(config.load(PAPER, ["duration_s=0.01"]))
    cfg = config.SafetySpec(**spec)
    return Supervisor(cfg, session.hsi.model, session.to.model)


def test_non_finite_measurement_is_a_stop_naming_robot_and_joint() -> None:
    sup = supervisor()
    with pytest.raises(SafetyStop, match=r"^tick 7: to joint 1 \(elbow\): measured torque is nan"):
        sup.check_measured(7, "to", [0.0, 1.0], [0.0, 0.0], [0.0, float("nan")])
    with pytest.raises(
        SafetyStop, match=r"^tick 8: hsi joint 0 \(shoulder\): commanded torque is nan"
    ):
        sup.check(8, "hsi", [0.0, 1.0], [0.0, 0.0], [0.0, 0.0], [float("nan"), 0.0])


def test_limits_from_the_urdf() -> None:
    sup = supervisor()
    # scara_2dof.urdf: +-2.6 rad, 6 / 8 rad/s, 20 / 10 N m
    with pytest.raises(SafetyStop, match=r"hsi joint 0 \(shoulder\): angle 2.7 rad outside"):
        sup.check(0, "hsi", [2.7, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(SafetyStop, match=r"joint 1 \(elbow\): speed -8.5 rad/s above 8"):
        sup.check(0, "hsi", [0.0, 0.0], [0.0, -8.5], [0.0, 0.0], [0.0, 0.0])
    cmd = [25.0, -12.0]
    assert sup.check(0, "hsi", [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], cmd) is True
    assert cmd == [20.0, -10.0]  # saturated to the effort limits


def test_saturation_that_lasts_is_a_stop() -> None:
    sup = supervisor(saturation_stop_ticks=5)
    for k in range(4):
        sup.saturation(k, True)
    sup.saturation(4, False)  # a break resets the run
    for k in range(5, 9):
        sup.saturation(k, True)
    with pytest.raises(SafetyStop, match="tick 9: .*5 ticks in a row"):
        sup.saturation(9, True)
    assert sup.saturated_ticks == 9


def test_an_unstable_session_ends_in_a_safety_stop_with_its_log(tmp_path: Path) -> None:
    cfg = config.load(PAPER, ["duration_s=3", "hsi.controller.kp=1e6"])  # a wildly unstable HSI
    session = Session(cfg)
    summary = session.run(recorder=Recorder(session, tmp_path / "unstable.mcap"))
    assert summary.safety_stop and summary.stopped_early.startswith("safety stop: tick ")
    assert summary.ticks < 3000
    log = read_log(tmp_path / "unstable.mcap")
    assert log.ticks == summary.ticks and log.summary["safety_stop"] is True
    # zero torque after the stop: the backends were stopped
    assert session.hsi.backend.tau_motor == [0.0, 0.0]


def test_cli_exit_code_3_on_a_safety_stop(capsys) -> None:
    code = main(["run", str(PAPER), "--no-log", "--duration", "3", "--set",
                 "hsi.controller.kp=1e6", "--json"])  # fmt: skip
    assert code == 3
