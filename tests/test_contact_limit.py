"""The sampled contact loop's stability limit K_max = b (4 T2 - 2 dt) / dt^2, checked on the
project's own TO blocks (computed torque on the simulated SCARA, P velocity control, channel)."""

from __future__ import annotations

import numpy as np
import pytest

from teleop_rt.analysis.contact import contact_stiffness_limit, joint_space_stiffness
from teleop_rt.com.wave import WaveChannel
from teleop_rt.config import ControllerSpec, RobotSpec
from teleop_rt.control import ComputedTorque, Pid
from teleop_rt.hal.sim import SimBackend
from teleop_rt.model import RobotModel
from teleop_rt.world import JointSpringDamper
from tests.conftest import SCARA_URDF

DT, B, M2, C2 = 1e-3, 2.0, 0.1, 20.0
Q0 = [-0.8, 1.8]


def contact_growth(k_joint: float, ticks: int = 400) -> float:
    """|q - q_rest| at the end over at the start, the TO pressed into a joint-space spring with
    no wave arriving yet (the delay is longer than the run)."""
    spec = RobotSpec(urdf=SCARA_URDF, ee_frame="tool")
    rest = [Q0[0], Q0[1] - 0.01]  # 10 mrad into the spring on the elbow
    plant = SimBackend(
        RobotModel.from_spec(spec, "to"), [JointSpringDamper([0.0, k_joint], [0.0, 0.0], rest)],
        np.array(Q0), DT,
    )  # fmt: skip
    ct = ComputedTorque(RobotModel.from_spec(spec, "c"), [M2, M2], True)
    c2 = Pid(ControllerSpec(kind="p", kp=C2), 2, DT, "c2")
    channel = WaveChannel([B, B], 1000, DT, filter_hz=None)
    for _ in range(ticks):
        fb = plant.read()
        channel.step([0.0, 0.0], [-x for x in fb.tau_ext])
        a = c2.step([channel.omega_t[j] - fb.v[j] for j in range(2)])
        plant.write(ct.step(fb.q, fb.v, a, fb.tau_ext))
    return abs(plant.read().q[1] - rest[1]) / 0.01


def test_limit_formula_for_the_default_to() -> None:
    # T2 = 5 ms, dt = 1 ms, b = 2: K_max = 2 (0.020 - 0.002) / 1e-6 = 36 000 N m/rad
    assert contact_stiffness_limit(B, M2, C2, DT) == pytest.approx(36_000.0)
    assert contact_stiffness_limit(B, M2, 200.0, DT) == 0.0  # T2 = dt / 2: the loop alone fails


@pytest.mark.parametrize("fraction,stable", [(0.9, True), (1.1, False)])
def test_the_running_to_loop_is_stable_exactly_below_the_limit(fraction, stable) -> None:
    growth = contact_growth(fraction * contact_stiffness_limit(B, M2, C2, DT))
    assert (growth < 1.0) == stable, growth


def test_joint_space_stiffness_of_a_wall() -> None:
    # a single link of length L along x pushing a wall with normal y: K = k L^2
    jac = np.array([[0.0], [0.5], [0.0]])
    assert joint_space_stiffness(jac, 1000.0, np.array([0.0, 2.0, 0.0])) == pytest.approx(250.0)


def test_a_wall_stiffer_than_the_loop_can_hold_is_warned_about() -> None:
    from teleop_rt import config
    from teleop_rt.analysis.contact import contact_warnings
    from tests.conftest import CONFIGS

    to = RobotModel.from_spec(RobotSpec(urdf=SCARA_URDF, ee_frame="tool"), "to")
    shipped = config.load(CONFIGS / "stiff_wall.yaml")
    assert contact_warnings(shipped, to) == []  # 5000 N/m is far inside the limit
    harsh = config.load(CONFIGS / "stiff_wall.yaml", ["environment.0.stiffness_n_per_m=5e6"])
    (line,) = contact_warnings(harsh, to)
    assert line.startswith("environment.0 (wall, 5e+06 N/m)") and "limit 36000" in line
