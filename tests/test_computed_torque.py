"""Computed-torque linearisation (eq 2, 12) on the simulated plant: the joints move as the
virtual masses of eq 3 / 13, decoupled and independent of the configuration q."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop_rt.config import RobotSpec, WallSpec
from teleop_rt.control import ComputedTorque
from teleop_rt.hal.sim import SimBackend
from teleop_rt.model import RobotModel
from teleop_rt.world import HalfPlaneContact
from tests.conftest import SCARA_URDF

DT = 1e-3
VIRTUAL_MASS = [0.5, 0.2]


def a_ref_profile(k: int) -> list[float]:
    t = k * DT
    return [0.8 * math.sin(3.0 * t) + 0.3, -0.5 * math.cos(5.0 * t)]


def run_linearised(spec: RobotSpec, q0, ticks: int, loads=(), a_ref=a_ref_profile, **plant_kw):
    plant = SimBackend(
        RobotModel.from_spec(spec, "plant"), list(loads), np.array(q0), DT, **plant_kw
    )
    ct = ComputedTorque(RobotModel.from_spec(spec, "ctrl"), VIRTUAL_MASS, compensate_friction=True)
    velocities = []
    for k in range(ticks):
        fb = plant.read()
        velocities.append(fb.v.copy())
        plant.write(ct.step(fb.q, fb.v, a_ref(k), fb.tau_ext))
    return np.array(velocities)


def virtual_velocity(ticks: int, a_ref=a_ref_profile) -> np.ndarray:
    """Exact discrete solution of M_v dv/dt = a_ref with a zero-order-held a_ref."""
    v = np.zeros(2)
    out = []
    for k in range(ticks):
        out.append(v.copy())
        v = v + DT * np.array(a_ref(k)) / np.array(VIRTUAL_MASS)
    return np.array(out)


SCARA = RobotSpec(urdf=SCARA_URDF, ee_frame="tool")


@pytest.mark.parametrize("q0", [(0.0, 1.0), (1.5, -2.0), (-0.8, 1.8)])
def test_joint_motion_is_the_virtual_mass_dynamics(q0) -> None:
    # symplectic Euler, one sub-step: the torque is exact for the whole step, so the plant's
    # velocity equals the virtual dynamics to rounding (1e-9 rad/s over 2 s)
    v = run_linearised(SCARA, q0, 2000)
    np.testing.assert_allclose(v, virtual_velocity(2000), atol=1e-9)


def test_decoupled_a_reference_on_one_joint_moves_only_that_joint() -> None:
    v = run_linearised(SCARA, (0.3, 1.2), 1500, a_ref=lambda k: [1.0, 0.0])
    assert np.abs(v[:, 1]).max() < 1e-10  # the elbow would swing without decoupling
    np.testing.assert_allclose(v[-1, 0], 1499 * DT * 1.0 / VIRTUAL_MASS[0], rtol=1e-9)


def test_measured_contact_torque_is_cancelled() -> None:
    # a stiff wall right in the path of the tool: the wall pushes, computed torque cancels it
    wall = HalfPlaneContact(
        WallSpec(kind="wall", point_m=[0.40, 0.0], normal=[-1, 0], stiffness_n_per_m=2000)
    )
    v = run_linearised(SCARA, (-0.8, 1.8), 1500, loads=[wall], a_ref=lambda k: [0.0, -0.3])
    assert wall.in_contact, "the test must actually press into the wall"
    np.testing.assert_allclose(v, virtual_velocity(1500, lambda k: [0.0, -0.3]), atol=1e-9)


@pytest.mark.parametrize("plant_kw", [{"substeps": 4}, {"integrator": "rk4"}])
def test_finer_integrators_stay_close_to_the_virtual_dynamics(plant_kw) -> None:
    # torque is held over the tick while M(q) changes inside it: O(dt) relative deviation;
    # 1 % of the velocity range over 2 s is far above that and far below a coupling error
    v = run_linearised(SCARA, (0.0, 1.0), 2000, **plant_kw)
    ref = virtual_velocity(2000)
    assert np.abs(v - ref).max() < 0.01 * np.abs(ref).max()


def test_gravity_is_compensated_on_the_double_pendulum() -> None:
    pendulum = RobotSpec(example_robot="double_pendulum")
    q0 = (0.5, 0.3)  # not an equilibrium: gravity loads both joints
    held = run_linearised(pendulum, q0, 1000, a_ref=lambda k: [0.0, 0.0])
    assert np.abs(held).max() < 1e-9
    # control experiment: without motor torque the same pendulum falls
    plant = SimBackend(RobotModel.from_spec(pendulum, "plant"), [], np.array(q0), DT)
    for _ in range(300):
        plant.write([0.0, 0.0])
    assert np.abs(plant.read().v).max() > 0.1
