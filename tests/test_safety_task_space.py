"""The TO's limits in task space (issue 26, teleop_rt.task_limits, ``safety.tool``): a virtual
wall's force against its closed form, the tool's speed limit holding while the map stays
lossless, the tool's force limit as a stop; all off for joint-space configs.

The heterogeneous pair (configs/task_space/scara_ur5_plane.yaml: a SCARA HSI, a UR5 TO) is
the plant; the tool's speed and place are computed here from Pinocchio at the measured q, v,
not taken from the kernels' own figures.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from teleop_rt import config
from teleop_rt.com.port import TO
from teleop_rt.errors import ConfigError
from teleop_rt.mapping import PLANE, TASK, Mapping, map_kinematics
from teleop_rt.report import tool_limits_text
from teleop_rt.session import Session
from teleop_rt.task_limits import to_tool_sense
from tests.conftest import CONFIGS

PASSIVE_J = -1e-9
UR5 = CONFIGS / "task_space" / "scara_ur5_plane.yaml"
# the config's real wall (y = 0.054 m, normal +y), as a virtual one on a TO in free space
K_WALL, D_WALL, Y_WALL = 5000.0, 20.0, 0.054
VIRTUAL_WALL = (
    "environment=[]",
    f"safety.tool.walls=[{{point_m: [0.0, {Y_WALL}], normal: [0, 1], "
    f"stiffness_n_per_m: {K_WALL}, damping_n_s_per_m: {D_WALL}}}]",
)
HELD = slice(3500, 3900)  # ticks the operator holds the tool against the wall


def ur5(*overrides: str) -> config.SessionConfig:
    return config.load(UR5, list(overrides))


class ToolTrace:
    """Per tick: the TO tool's x, y velocity and place (Pinocchio at the measured q, v), the
    HSI's and the TO's task-space forces (tau_mapped), the TO's port power, its robot-side
    power (beta / alpha) v_ref . tau_e, and its coupling gain."""

    def __init__(self, session: Session) -> None:
        self.model = session.to.model
        m = session.to.mapping
        self.power_scale = m.force_scale / m.motion_scale
        self.rows: list[np.ndarray] = []

    def __call__(self, s: Session) -> None:
        m, to = self.model, s.to
        q, v = to.feedback.q, to.feedback.v
        jac = pin.computeFrameJacobian(m.model, m.data, q, m.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
        v_ref = to.signals.error + v
        self.rows.append(np.concatenate([
            jac[:2] @ v, m.tool_position(q)[:2], s.hsi.mapping.tau_mapped,
            to.mapping.tau_mapped,
            [to.port.flow @ to.port.effort, self.power_scale * (v_ref @ to.signals.tau),
             to.mapping.gain],
        ]))  # fmt: skip

    def array(self) -> np.ndarray:
        return np.array(self.rows)


def traced(cfg: config.SessionConfig):
    session = Session(cfg)
    trace = ToolTrace(session)
    summary = session.run(observer=trace)
    return session, trace.array(), summary


# --- virtual walls ---------------------------------------------------------------------------
def test_a_virtual_wall_pushes_k_times_its_penetration_plus_d_times_its_rate() -> None:
    """The kernel against F_w = max(0, k p + d dp/dt) n, p the depth beyond the wall along
    its unit normal: added to the TO's task-space force as -beta F_w (the TO pushes the wall);
    nothing outside the wall, nothing while the clamp holds (leaving faster than k p / d)."""
    Mi = Mapping.idx
    k, d, beta = 2000.0, 30.0, 5.0
    normal = np.array([3.0, 4.0]) / 5.0  # (given as 3, 4: the kernel normalises it)
    m = Mapping(TASK, TO, 1e-3, force_scale=beta, space=PLANE, joints=2,
                walls=[(0.1, 0.2, 3.0, 4.0, k, d)])  # fmt: skip
    jac = np.zeros((6, 2))
    jac[:2] = [[0.3, -0.1], [0.2, 0.4]]
    v = np.array([0.05, -0.02])
    rate = -(jac[:2] @ v) @ normal  # dp/dt
    for depth, expected in ((0.004, k * 0.004 + d * rate), (-0.004, 0.0), (1e-5, 0.0)):
        x = np.array([0.1, 0.2, 0.0]) - depth * np.append(normal, 0.0)
        map_kinematics(m.f, m.i, jac, x)
        before = np.array([1.5, -2.0])
        m.f[Mi.TAU_MAPPED * TASK : Mi.TAU_MAPPED * TASK + 2] = before
        assert to_tool_sense(m.f, m.i, TASK, v) == 0
        if depth == 1e-5:
            assert k * depth + d * rate < 0  # the case: the clamp holds
        np.testing.assert_allclose(m.tau_mapped, before - beta * expected * normal, rtol=1e-12)
    assert m.wall_ticks == 1 and m.max_penetration == pytest.approx(0.004, rel=1e-12)


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_a_virtual_wall_holds_the_tool_as_a_spring(delay_ms: int) -> None:
    """Free space with the config's wall made virtual: held, the operator's force at the HSI's
    tool (y) is k p, p the TO tool's depth beyond the wall (Pinocchio), within 5 %; the held
    force equals the real wall's run within 1 %; passive; the summary says the wall acted."""
    _, a, summary = traced(ur5(f"channel.delay_ms={delay_ms}", *VIRTUAL_WALL))
    held = a[HELD].mean(axis=0)
    depth = Y_WALL - held[3]
    assert depth > 5e-4  # pressing it (~1.1 mm)
    assert -held[5] == pytest.approx(K_WALL * depth, rel=0.05)  # F_h(y) = -k p
    _, real, _ = traced(ur5(f"channel.delay_ms={delay_ms}"))
    assert held[5] == pytest.approx(real[HELD].mean(axis=0)[5], rel=0.01)
    assert summary.min_channel_energy_j >= PASSIVE_J and summary.stopped_early is None
    tool = summary.tool_limits
    assert tool["wall_ticks"] > 1000 and tool["max_penetration_m"] >= depth
    assert "virtual wall pushed" in tool_limits_text(tool)


# --- the tool's speed ------------------------------------------------------------------------
SPEED_LIMIT = 0.05  # m/s, unscaled; the operator moves the UR5's tool at up to 0.14 m/s
# soft foam from just below the tool's start: the speed limit acts while in contact
FOAM = ("{kind: foam, point_m: [0.0, 0.107], normal: [0, 1], stiffness_n_per_m: 100, "
        "damping_n_s_per_m: 2}")


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_the_tool_speed_limit_holds_and_the_map_stays_lossless(delay_ms: int) -> None:
    """With safety.tool.speed_limit_m_s the TO tool's measured speed |J v| stays within 2 % of
    the limit (the ceiling is one tick stale), where unlimited it reaches over twice the limit;
    the TO's port power equals (beta / alpha) v_ref . tau_e at every tick (the ceiling scales
    the motion and the fed-back force alike: a transformer), and the channel stays passive.
    Scaled (alpha = 0.2, beta = 5: the power scale 25), pressing into soft foam."""
    scaled = (f"channel.delay_ms={delay_ms}", "mapping.motion_scale=0.2",
              "mapping.force_scale=5.0", f"environment=[{FOAM}]")  # fmt: skip
    limit = SPEED_LIMIT * 0.2  # the scaled TO moves 0.2 times as fast
    _, free, _ = traced(ur5(*scaled))
    assert np.hypot(free[:, 0], free[:, 1]).max() > 2 * limit
    _, a, summary = traced(ur5(*scaled, f"safety.tool.speed_limit_m_s={limit}"))
    speed = np.hypot(a[:, 0], a[:, 1])
    assert speed.max() <= 1.02 * limit
    assert speed.max() >= 0.9 * limit  # (it acted: the operator asked for more)
    limited_in_contact = (a[:, 10] < 0.99) & (np.hypot(a[:, 6], a[:, 7]) > 0.5)
    assert limited_in_contact.sum() > 100  # (where a motion-only cap would break the identity)
    np.testing.assert_allclose(a[:, 8], a[:, 9], rtol=1e-9, atol=1e-12)
    assert summary.min_channel_energy_j >= PASSIVE_J and summary.stopped_early is None
    tool = summary.tool_limits
    assert tool["speed_limited_ticks"] > 100 and 0 < tool["min_speed_gain"] < 1
    assert "capped the coupling" in tool_limits_text(tool)


# --- the tool's force ------------------------------------------------------------------------
def test_the_tool_force_limit_is_a_safety_stop() -> None:
    """Held against the wall the UR5 pushes ~5.6 N: a 3 N limit stops the run (staged stop),
    at the first tick the measured |J#^T tau_e| exceeds it, and says so in one line."""
    limit = 3.0
    session, a, summary = traced(ur5(f"safety.tool.force_limit_n={limit}"))
    assert summary.safety_stop and "safety.tool.force_limit_n" in summary.stopped_early
    assert f"above {limit:g} N" in summary.stopped_early
    assert np.hypot(a[:, 6], a[:, 7]).max() <= limit  # every tick before the stop's
    assert session.to.mapping.peak_tool_force > limit


# --- config ----------------------------------------------------------------------------------
def test_tool_limits_are_off_by_default_and_need_the_plane() -> None:
    """Joint-space configs carry no tool limits (the reference figures' runs are untouched);
    tool limits in joint space are one clear line."""
    session = Session(config.load(CONFIGS / "stiff_wall.yaml"))
    assert not session.to.mapping.limits and session.run(ticks=10).tool_limits is None
    with pytest.raises(ConfigError, match=r"safety.tool.*channel.space: plane") as err:
        config.load(CONFIGS / "stiff_wall.yaml", ["safety.tool.speed_limit_m_s=0.1"])
    assert "\n" not in str(err.value)
    assert math.isinf(Session(ur5()).to.mapping.speed_limit)
