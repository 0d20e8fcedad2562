"""Operator and environment models: forces against closed forms, and the J^T F mapping."""

from __future__ import annotations

import numpy as np
import pytest

from teleop_rt.config import HandOperatorSpec, MassSpec, RobotSpec, SpringSpec, WallSpec
from teleop_rt.hal.sim import SimBackend
from teleop_rt.model import RobotModel
from teleop_rt.world import HalfPlaneContact, HandTrajectory, PushedMass, ScriptedHand
from tests.conftest import SCARA_URDF


def wall(**kw) -> HalfPlaneContact:
    spec = dict(
        kind="wall",
        point_m=[0.4, 0.0],
        normal=[-2, 0],
        stiffness_n_per_m=1000.0,
        damping_n_s_per_m=10.0,
    )
    return HalfPlaneContact(WallSpec(**(spec | kw)))


def test_wall_force_is_spring_damper_along_the_normal_inside_only() -> None:
    w = wall()
    # 1 cm inside, moving further in at 0.1 m/s: f = 1000 * 0.01 + 10 * 0.1 = 11 N along -x
    assert w.force(0.0, [0.41, 0.2, 0.1], [0.1, 0.5, 0.0]) == pytest.approx((-11.0, 0.0, 0.0))
    assert w.in_contact
    assert w.force(0.0, [0.39, 0.0, 0.0], [1.0, 0.0, 0.0]) == (0.0, 0.0, 0.0)
    assert not w.in_contact
    # inside but leaving fast: the unilateral wall never pulls
    assert w.force(0.0, [0.401, 0.0, 0.0], [-1.0, 0.0, 0.0]) == (0.0, 0.0, 0.0)


def test_spring_environment_is_bilateral() -> None:
    s = HalfPlaneContact(
        SpringSpec(kind="spring", point_m=[0, 0.1], normal=[0, 1], stiffness_n_per_m=200.0)
    )
    assert s.force(0.0, [0.0, 0.12, 0.0], [0.0, 0.0, 0.0]) == pytest.approx((0.0, -4.0, 0.0))
    assert s.force(0.0, [0.0, 0.08, 0.0], [0.0, 0.0, 0.0]) == pytest.approx((0.0, 4.0, 0.0))


def test_minimum_jerk_hand_reference_hits_waypoints_with_zero_velocity() -> None:
    traj = HandTrajectory([0.0, 0.0, 0.1], [1.0, 3.0], [[0.1, 0.0, 0.1], [0.1, 0.2, 0.1]])
    for t, pos in (
        (0.0, [0, 0, 0.1]),
        (1.0, [0.1, 0, 0.1]),
        (3.0, [0.1, 0.2, 0.1]),
        (9.0, [0.1, 0.2, 0.1]),
    ):
        traj.evaluate(t)
        np.testing.assert_allclose(traj.pos, pos, atol=1e-15)
        np.testing.assert_allclose(traj.vel, 0.0, atol=1e-15)
    traj.evaluate(0.5)  # midpoint of a minimum-jerk segment: half way, peak speed 1.875 d / T
    np.testing.assert_allclose(traj.pos, [0.05, 0.0, 0.1], atol=1e-15)
    np.testing.assert_allclose(traj.vel, [1.875 * 0.1, 0.0, 0.0], rtol=1e-12)


def test_hand_waypoints_with_two_numbers_keep_the_start_height() -> None:
    spec = HandOperatorSpec(kind="hand", waypoints=[{"t_s": 1.0, "position_m": [0.3, 0.1]}])
    hand = ScriptedHand.from_spec(spec, [0.35, 0.0, 0.12])
    assert hand.trajectory.points[-1] == [0.3, 0.1, 0.12]
    # at rest at the start the hand pulls with K (x_ref - x)
    f = hand.force(0.0, [0.34, 0.0, 0.12], [0.0, 0.0, 0.0])
    assert f == pytest.approx((300.0 * 0.01, 0.0, 0.0))


def test_contact_torque_is_j_transpose_f_by_virtual_power() -> None:
    """Power balance: the joint torque the plant reports times v equals F . xdot."""
    model = RobotModel.from_spec(RobotSpec(urdf=SCARA_URDF, ee_frame="tool"), "to")
    w = wall(point_m=[0.30, 0.0])  # the tool at q0 is 4.4 cm inside this wall
    plant = SimBackend(model, [w], np.array([-0.8, 1.8]), 1e-3)
    plant.state.v[:] = [0.3, -0.5]
    plant._evaluate_loads()
    assert w.in_contact
    joint_power = float(np.dot(plant.state.tau_load, plant.state.v))
    model.update_ee(plant.state.q, plant.state.v.tolist())  # the tool velocity, independently
    cart_power = float(np.dot(w.last_force, model.ee_vel))
    assert joint_power == pytest.approx(cart_power, rel=1e-12)
    assert abs(joint_power) > 1e-3


def test_pushed_mass_feels_like_m_s_when_pushed_steadily() -> None:
    """Push the mass with a constant end-effector acceleration a: after the contact settles, the
    contact force is m a (Z_e = m s along the normal)."""
    m = PushedMass(
        MassSpec(
            kind="mass",
            point_m=[0.0, 0.0],
            normal=[-1, 0],
            mass_kg=0.5,
            contact_damping_n_s_per_m=100.0,
        )
    )
    dt, a = 1e-4, 2.0
    x = xd = 0.0
    for _ in range(20000):  # 2 s
        f = m.force(0.0, [x, 0.0, 0.0], [xd, 0.0, 0.0])
        m.advance(dt)
        xd += a * dt
        x += xd * dt
    assert -f[0] == pytest.approx(0.5 * a, rel=1e-3)


def _held_mass_velocity(integrator: str, substeps: int, ticks: int = 200) -> np.ndarray:
    """The TO tool holding a 0.3 kg mass (attached, soft coupling), driven by a smooth torque."""
    spec = MassSpec(kind="mass", point_m=[0.40, 0.0], normal=[-1, 0], mass_kg=0.3, attached=True,
                    contact_stiffness_n_per_m=2000.0, contact_damping_n_s_per_m=5.0)  # fmt: skip
    model = RobotModel.from_spec(RobotSpec(urdf=SCARA_URDF, ee_frame="tool"), "to")
    model.has_coulomb = False  # the smoothed Coulomb kink at v = 0 would cap any method's order
    plant = SimBackend(model, [PushedMass(spec)], np.array([-0.8, 1.8]), 1e-3,
                       substeps=substeps, integrator=integrator)  # fmt: skip
    for k in range(ticks):
        plant.write([0.3 * np.sin(0.02 * k), -0.1])
    return plant.state.v.copy()


def test_rk4_is_fourth_order_with_a_stateful_load() -> None:
    reference = _held_mass_velocity("rk4", 64)
    errors = [np.abs(_held_mass_velocity("rk4", m) - reference).max() for m in (2, 4, 8)]
    # halving the step divides the error by 2^4 = 16 for a 4th-order method
    assert errors[0] / errors[1] > 12 and errors[1] / errors[2] > 12, errors


def test_the_plants_compiled_write_equals_its_general_loop_exactly() -> None:
    """The common write (three compiled calls around ABA and the Jacobian) and the general
    loop (used for faults, sub-steps, RK4) run the same pieces: with a fault that never fires
    the plant takes the general loop, and every tick's feedback and world snapshot agree
    bit for bit, through the foam and into the wall with a pushed mass behind it."""
    from teleop_rt.config import FaultSpec

    def plant(faults):
        model = RobotModel.from_spec(RobotSpec(urdf=SCARA_URDF, ee_frame="tool"), "to")
        loads = [wall(point_m=[0.36, 0.0]), PushedMass(MassSpec(
            kind="mass", point_m=[0.0, -0.008], normal=[0, 1], mass_kg=0.2))]  # fmt: skip
        return SimBackend(model, loads, np.array([-0.8, 1.8]), 1e-3, faults=faults)

    def loads_moved(p):
        return p.loads[1].s > 1e-4

    common = plant([])
    general = plant([FaultSpec(kind="stuck", robot="to", start_s=100.0)])
    assert common._one_euler_step and not general._one_euler_step
    contacts = np.zeros(2)
    for k in range(1500):
        a, b = common.read(), general.read()
        for x, y in (
            (a.q, b.q),
            (a.v, b.v),
            (a.tau_ext, b.tau_ext),
            (common.world.f, general.world.f),
        ):
            assert np.array_equal(x, y), k
        contacts += common.world.contacts
        tau = [0.4 * np.sin(0.004 * k), -0.3 * np.cos(0.003 * k)]
        common.write(tau)
        general.write(tau)
    assert contacts[0] > 50 and contacts[1] > 0, f"both loads must have been touched: {contacts}"
    assert loads_moved(common), "the mass must have been pushed"


def test_a_one_joint_robot_feels_a_tool_load_through_its_jacobian() -> None:
    """Pinocchio hands a 1-DoF Jacobian over flat: the plant still maps F to tau = J^T F.
    A rotary joint with the tool at r = 0.3 m, q = 0.2 rad, a bilateral spring along y about
    y = 0: tau = x F_y = r cos q (-k r sin q)."""
    import pinocchio as pin

    model = pin.Model()
    joint = model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "j1")
    tool = pin.SE3(np.eye(3), np.array([0.3, 0.0, 0.0]))
    model.appendBodyToJoint(joint, pin.Inertia.FromSphere(1.0, 0.1), tool)
    model.addFrame(pin.Frame("tool", joint, 0, tool, pin.FrameType.OP_FRAME))
    spring = HalfPlaneContact(
        SpringSpec(kind="spring", point_m=[0, 0], normal=[0, 1], stiffness_n_per_m=200.0)
    )
    plant = SimBackend(RobotModel(model, "tool"), [spring], np.array([0.2]), 1e-3)
    expected = 0.3 * np.cos(0.2) * (-200.0 * 0.3 * np.sin(0.2))
    assert plant.read().tau_ext[0] == pytest.approx(expected, rel=1e-12)


def test_a_new_plant_has_its_kernels_loaded_before_its_first_read_and_write() -> None:
    """Loading a compiled kernel takes milliseconds: a drive emulator whose plant loaded its
    write's kernels at the first write (when the drives enable) missed three SYNC windows and
    the master stopped. In a fresh process, constructing the plant loads them."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(f"""
        import numpy as np
        from teleop_rt.config import RobotSpec, WallSpec
        from teleop_rt.hal import sim
        from teleop_rt.model import RobotModel
        from teleop_rt.world import HalfPlaneContact
        kernels = (sim.sense, sim.command, sim.euler_step, sim.next_tick, sim.total_torque)
        assert not any(k.signatures for k in kernels), "loaded before the test"
        model = RobotModel.from_spec(RobotSpec(urdf={str(SCARA_URDF)!r}, ee_frame="tool"), "to")
        wall = HalfPlaneContact(WallSpec(kind="wall", point_m=[0.4, 0], normal=[-1, 0],
                                         stiffness_n_per_m=1000.0))
        sim.SimBackend(model, [wall], np.array([-0.8, 1.8]), 1e-3)
        print([len(k.signatures) for k in kernels])
    """)
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[1,", "1,", "1,", "1,", "1]"]
