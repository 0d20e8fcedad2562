"""Fault injection on the simulated plant: every fault ends in the right safe stop, soon after
it starts, naming the robot and joint; the log keeps every tick up to the stop."""

from __future__ import annotations

import re

import pytest

from teleop_rt import config
from teleop_rt.session import Session
from tests.conftest import CONFIGS

START_S = 4.5  # the operator is pressing the TO into the foam
START_TICK = 4500

# (fault, magnitude, expected stop reason, ticks allowed from the fault's start to the stop)
CASES = [
    ("nan", 1.0, r"{robot} joint 1 \(elbow\): measured torque is nan", 1),
    ("dropout", 1.0, r"{robot} feedback stale for 3 ticks", 3),
    ("noise_burst", 3.0, r"{robot} joint 1 \(elbow\): does not follow", 60),
    ("bias", 0.5, r"{robot} joint 1 \(elbow\): does not follow", 21),
    ("saturation", 0.05, r"{robot} joint 1 \(elbow\): does not follow", 60),
]


def faulty_run(kind: str, robot: str, magnitude: float, **extra: str):
    fault = (
        f"{{kind: {kind}, robot: {robot}, joint: 1, start_s: {START_S}, magnitude: {magnitude}}}"
    )
    overrides = [f"plant.faults=[{fault}]", *[f"{k}={v}" for k, v in extra.items()]]
    session = Session(config.load(CONFIGS / "paper_experiment.yaml", overrides))
    return session.run()


@pytest.mark.parametrize("robot", ["hsi", "to"])
@pytest.mark.parametrize("kind,magnitude,reason,within", CASES)
def test_each_fault_ends_in_the_right_safe_stop(kind, magnitude, reason, within, robot) -> None:
    summary = faulty_run(kind, robot, magnitude)
    assert summary.safety_stop, f"{kind} on {robot} did not stop the session"
    assert re.search(reason.format(robot=robot), summary.stopped_early), summary.stopped_early
    stop_tick = int(re.search(r"tick (\d+)", summary.stopped_early).group(1))
    assert START_TICK <= stop_tick <= START_TICK + within
    assert summary.ticks == stop_tick  # every tick before the stop completed (and is logged)


def test_a_stuck_joint_is_found_once_the_operator_moves_it() -> None:
    # the TO elbow blocked while the operator drives the arm: the joint cannot follow
    summary = faulty_run("stuck", "to", 1.0)
    assert summary.safety_stop and "to joint 1 (elbow): does not follow" in summary.stopped_early


def test_after_a_stop_the_to_is_brought_to_rest() -> None:
    summary = faulty_run("bias", "hsi", 0.5)
    (note,) = [n for n in summary.notes if n.startswith("after the stop")]
    assert re.search(r"TO at rest after \d+ ticks", note)


def test_a_fault_on_a_joint_the_robot_does_not_have_is_a_config_error() -> None:
    from teleop_rt.errors import ConfigError

    cfg = config.load(
        CONFIGS / "paper_experiment.yaml", ["plant.faults=[{kind: nan, robot: to, joint: 5}]"]
    )
    with pytest.raises(ConfigError, match=r"^plant\.faults\.0\.joint"):
        Session(cfg)
