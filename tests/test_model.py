"""The SCARA's Pinocchio model against the closed form of a planar two-link arm."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop_rt.config import RobotSpec
from teleop_rt.model import RobotModel, friction_torque
from tests.conftest import SCARA_URDF

# Parameters written in robots/urdf/scara_2dof.urdf
L1, LC1, M1, I1 = 0.30, 0.15, 1.2, 0.009
LC2, M2, I2 = 0.125, 0.8, 0.0041667
L2 = 0.25


def closed_form_mass_matrix(q2: float) -> np.ndarray:
    c2 = math.cos(q2)
    m11 = I1 + I2 + M1 * LC1**2 + M2 * (L1**2 + LC2**2 + 2 * L1 * LC2 * c2)
    m12 = I2 + M2 * (LC2**2 + L1 * LC2 * c2)
    m22 = I2 + M2 * LC2**2
    return np.array([[m11, m12], [m12, m22]])


def closed_form_coriolis(q2: float, v: np.ndarray) -> np.ndarray:
    h = M2 * L1 * LC2 * math.sin(q2)
    return np.array([-h * (2 * v[0] * v[1] + v[1] ** 2), h * v[0] ** 2])


@pytest.fixture(scope="module")
def scara() -> RobotModel:
    return RobotModel.from_spec(RobotSpec(urdf=SCARA_URDF, ee_frame="tool"), "scara")


@pytest.mark.parametrize("q", [(0.0, 0.0), (0.3, 0.7), (-1.2, 2.4), (2.0, -1.9)])
def test_mass_matrix_matches_planar_two_link_closed_form(scara: RobotModel, q) -> None:
    # 1e-12 relative: the URDF numbers are exact, only floating point separates the two
    np.testing.assert_allclose(
        scara.mass_matrix(np.array(q)), closed_form_mass_matrix(q[1]), rtol=1e-12
    )


@pytest.mark.parametrize("q2", [0.4, 1.8, -2.2])
def test_nonlinear_effects_are_coriolis_only_in_the_horizontal_plane(scara: RobotModel, q2) -> None:
    v = np.array([1.3, -0.7])
    n = scara.nonlinear_effects(np.array([0.5, q2]), v)
    np.testing.assert_allclose(n, closed_form_coriolis(q2, v), rtol=1e-10, atol=1e-14)
    # gravity acts along -z, the joint axes are vertical: no static joint torque
    np.testing.assert_allclose(
        scara.nonlinear_effects(np.array([0.5, q2]), np.zeros(2)), 0.0, atol=1e-14
    )


def test_tool_kinematics_and_jacobian(scara: RobotModel) -> None:
    q = np.array([0.4, 1.1])
    x = scara.ee_position(q)
    np.testing.assert_allclose(
        x[:2],
        [L1 * math.cos(0.4) + L2 * math.cos(1.5), L1 * math.sin(0.4) + L2 * math.sin(1.5)],
        rtol=1e-12,
    )
    v = [0.3, -0.8]
    scara.update_ee(q, v)
    np.testing.assert_allclose(scara.ee_pos, x, rtol=1e-12)
    # velocity by finite difference of the forward kinematics
    eps = 1e-7
    fd = (scara.ee_position(q + eps * np.array(v)) - scara.ee_position(q - eps * np.array(v))) / (
        2 * eps
    )
    np.testing.assert_allclose(scara.ee_vel, fd, rtol=1e-6, atol=1e-9)


def test_friction_from_urdf_dynamics_tags(scara: RobotModel) -> None:
    assert scara.damping == [0.02, 0.01] and scara.coulomb == [0.01, 0.005]

    def friction(v: list[float]) -> list[float]:
        return [friction_torque(d, c, scara.inv_v_s, x)
                for d, c, x in zip(scara.damping, scara.coulomb, v, strict=True)]  # fmt: skip

    # far above the smoothing velocity tanh saturates: viscous + Coulomb
    np.testing.assert_allclose(
        friction([2.0, -3.0]), [0.02 * 2 + 0.01, -0.01 * 3 - 0.005], rtol=1e-9
    )
    assert friction([0.0, 0.0]) == [0.0, 0.0]
    # half the Coulomb level at v_s atanh(1/2) (smoothing 0.01 rad/s by default)
    half = 0.01 * np.arctanh(0.5)
    assert friction([half, 0.0])[0] == pytest.approx(0.02 * half + 0.005, rel=1e-12)


def test_example_robot_data_double_pendulum_loads() -> None:
    model = RobotModel.from_spec(RobotSpec(example_robot="double_pendulum"), "pendulum")
    assert model.nv == 2
    # gravity acts in its plane: away from the hanging equilibrium there is a static torque
    assert np.abs(model.nonlinear_effects(np.array([0.5, 0.3]), np.zeros(2))).max() > 1e-3
