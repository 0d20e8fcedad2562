"""Locked joints (``robot.locked_joints``, issue 26): a model's joints taken out with Pinocchio's
``buildReducedModel``, e.g. the Panda's fingers, so that neither the tool Jacobian nor the guard
sees them (configs/task_space/*panda*.yaml). Closed forms: the reduced model's kinematics and
mass matrix are the full model's with the locked joints at their neutral position."""

from __future__ import annotations

import example_robot_data
import numpy as np
import pinocchio as pin
import pytest

from teleop_rt import config
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_bad_input import assert_refused

PAIR = CONFIGS / "task_space" / "scara_panda_plane.yaml"
FINGERS = ["panda_finger_joint1", "panda_finger_joint2"]


def test_the_locked_fingers_leave_seven_joints_with_the_full_model_s_kinematics_and_inertia():
    """The Panda TO with its fingers locked: 7 joints in the site, its guard, its tool
    Jacobian and its map; at random arm poses the hand's placement and Jacobian and the mass
    matrix equal the full model's (fingers at 0, the neutral) to 1e-10: the fingers' inertia is
    merged into the hand, not dropped."""
    session = Session(config.load(PAIR, []))
    to = session.to
    assert to.n == 7 and to.mapping.joints == 7 and len(to.guard.vmax) == 7
    assert list(to.model.model.names)[1:] == [f"panda_joint{k}" for k in range(1, 8)]
    np.testing.assert_array_equal(to.guard.vmax, [2.175] * 4 + [2.61] * 3)
    full = example_robot_data.load("panda").model
    data = full.createData()
    hand = full.getFrameId("panda_hand")
    reduced = to.model
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = np.array(session.cfg.to.robot.q0_rad) + rng.uniform(-0.4, 0.4, 7)
        q_full = np.concatenate([q, [0.0, 0.0]])
        jac = pin.computeFrameJacobian(full, data, q_full, hand, pin.LOCAL_WORLD_ALIGNED)
        mine = pin.computeFrameJacobian(reduced.model, reduced.data, q, reduced.ee_frame_id,
                                        pin.LOCAL_WORLD_ALIGNED)  # fmt: skip
        np.testing.assert_allclose(mine, jac[:, :7], atol=1e-10)
        assert np.abs(jac[:, 7:]).max() < 1e-12  # (the fingers never moved the hand)
        np.testing.assert_allclose(reduced.ee_position(q), data.oMf[hand].translation,
                                   atol=1e-10)  # fmt: skip
        m_full = pin.crba(full, data, q_full)
        m_full = np.triu(m_full) + np.triu(m_full, 1).T
        np.testing.assert_allclose(reduced.mass_matrix(q), m_full[:7, :7], atol=1e-10)


@pytest.mark.parametrize(
    "locked, named",
    [
        ("[panda_finger_joint3]", "to.robot.locked_joints: no joint 'panda_finger_joint3' in the "
                                  "model (its joints: panda_joint1,"),
        ("[panda_finger_joint1, panda_finger_joint1]", "more than once: panda_finger_joint1"),
        ("[" + ", ".join([f"panda_joint{k}" for k in range(1, 8)] + FINGERS) + "]",
         "locks every joint"),
    ],
    ids=["unknown", "twice", "all"],
)
def test_a_bad_locked_joint_is_one_line(locked: str, named: str, capsys) -> None:
    assert_refused(["check", str(PAIR), "--set", f"to.robot.locked_joints={locked}"], capsys,
                   named)  # fmt: skip
