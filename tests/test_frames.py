"""The frames between the HSI and the TO (issue 26, teleop_rt.mapping): the TO's tool is to be
at R (alpha x_h) + offset, with R on velocities and R^T on forces so that the power through
the map is the one without it. Closed forms on the SCARA -> UR5 pair in the plane
(configs/task_space/scara_ur5_plane.yaml), the TO's frame turned by a yaw of 30 degrees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.errors import ConfigError
from teleop_rt.mapping import (
    M_GAIN,
    N_MAPPING_VECTORS,
    PLANE,
    TASK,
    TO,
    Mapping,
    frame_rotation,
    map_kinematics,
    to_frame_force,
    to_map_gain,
    to_plane_input,
    to_plane_output,
)
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_passive_channels import CLASSES, assert_passive_and_bounded, run, write_traces

PASSIVE_J = -1e-9
PAIR = CONFIGS / "task_space" / "scara_ur5_plane.yaml"
YAW_DEG = 30.0
ALPHA, BETA = 0.5, 2.0
TURNED = (f"mapping.rotation_rpy_deg=[0, 0, {YAW_DEG}]", f"mapping.motion_scale={ALPHA}",
          f"mapping.force_scale={BETA}")  # fmt: skip
# the config's wall (5.5 cm below the UR5's tool) moved to where the turned, scaled stroke
# (alpha 7.5 cm cos 30 degrees: 3.2 cm down) reaches it
WALL_WITHIN_REACH = "environment.0.point_m=[0.0, 0.09]"
HELD = slice(3500, 3900)  # ticks the operator holds the tool against the wall


def yaw(deg: float) -> np.ndarray:
    t = np.radians(deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def traced(*overrides: str) -> tuple[Session, np.ndarray]:
    """Run the pair; per tick: the HSI's and the TO's tool x, y (Pinocchio at the measured
    q), q_mapped of each, tau_mapped of each, the TO's port power and its robot-side power
    (beta / alpha) v_ref . tau_e (2, 2, 2, 2, 2, 2, 1, 1 columns)."""
    session = Session(config.load(PAIR, list(overrides)))
    m = session.to.mapping
    scale = m.force_scale / m.motion_scale
    rows: list[np.ndarray] = []

    def observe(s: Session) -> None:
        hsi, to = s.hsi, s.to
        v_ref = to.signals.error + to.feedback.v
        rows.append(np.concatenate([
            hsi.model.tool_position(hsi.feedback.q)[:2], to.model.tool_position(to.feedback.q)[:2],
            hsi.mapping.q_mapped, to.mapping.q_mapped, hsi.mapping.tau_mapped,
            to.mapping.tau_mapped,
            [to.port.flow @ to.port.effort, scale * (v_ref @ to.signals.tau)],
        ]))  # fmt: skip

    session.summary = session.run(observer=observe)
    return session, np.array(rows)


def test_a_turned_stroke_of_the_hsi_gives_the_turned_to_stroke() -> None:
    """Free space, 0 ms, alpha = 0.5: the TO's tool moves R alpha times the HSI's tool's motion
    (within 1 mm of a 38 mm stroke, the tracking error of the unturned pair), where the
    unturned motion would be 19 mm off; with offset = x_t(0) - R alpha x_h(0) the positions
    logged (q_mapped, both in the HSI's frame) agree at every tick within the same 1 mm."""
    cfg = config.load(PAIR, [])
    start = Session(cfg)
    x_h0, x_t0 = (np.asarray(site.model.tool_position(np.array(spec.robot.q0_rad))[:2])
                  for site, spec in ((start.hsi, cfg.hsi), (start.to, cfg.to)))  # fmt: skip
    r = yaw(YAW_DEG)
    offset = x_t0 - r @ (ALPHA * x_h0)
    session, a = traced("environment=[]", "duration_s=3", *TURNED,
                        f"mapping.offset_m=[{offset[0]}, {offset[1]}, 0]")  # fmt: skip
    moved_h, moved_t = a[:, 0:2] - a[0, 0:2], a[:, 2:4] - a[0, 2:4]
    assert np.abs(moved_h).max() > 0.07  # (the stroke: 75 mm at the HSI)
    assert np.abs(moved_t - ALPHA * moved_h @ r.T).max() < 1e-3
    assert np.abs(moved_t - ALPHA * moved_h).max() > 0.015
    assert np.abs(a[:, 4:6] - a[:, 6:8]).max() < 1e-3
    assert session.summary.min_channel_energy_j >= PASSIVE_J


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_through_a_turned_frame_the_power_is_unchanged_and_the_operator_feels_r_t_f(
    delay_ms: int,
) -> None:
    """Against the wall (moved to where the turned stroke reaches it): the TO's port power equals
    (beta / alpha) v_ref . tau_e at every tick to 1e-12 W (R on the flow, R^T on the force:
    R^T R = I), and held there the operator's force at the tool equals R^T beta F_e in the
    HSI's frame within 5 %, where F_e in the TO's frame is off by the turn; passive."""
    session, a = traced(f"channel.delay_ms={delay_ms}", *TURNED, WALL_WITHIN_REACH)
    assert np.abs(a[:, 12]).max() > 0.02  # (power flows: the TO is pushing the wall)
    np.testing.assert_allclose(a[:, 12], a[:, 13], rtol=0.0, atol=1e-12)
    held = a[HELD].mean(axis=0)
    f_h, f_t = held[8:10], held[10:12]  # both in the HSI's frame
    assert np.hypot(*f_t) > 1.0
    np.testing.assert_allclose(f_h, f_t, rtol=0.05, atol=0.05)
    turned_back = yaw(YAW_DEG) @ f_t  # beta F_e in the TO's frame: 30 degrees off
    assert np.hypot(*(turned_back - f_h)) > 0.4 * np.hypot(*f_h)
    assert session.summary.min_channel_energy_j >= PASSIVE_J


def test_the_kernel_maps_flow_by_r_and_force_by_r_transposed() -> None:
    """The TO's map alone, against its closed form: v_ref = r alpha J# R omega_t,
    x = r beta R^T J#^T tau_e, q_mapped = R^T (x_t - offset) + index offset; and with the
    identity frame (R = I, no offset) it computes what the unframed map does, bit for bit."""
    jac = np.zeros((6, 3))
    jac[:2] = [[0.3, -0.1, 0.05], [0.2, 0.4, -0.2]]
    tool = np.array([0.5, 0.1, 0.0])
    r3 = frame_rotation((0.0, 0.0, 40.0))
    offset = np.array([0.2, -0.3])
    tau_e, omega_t, v = np.array([0.7, -1.1, 0.4]), np.array([0.03, -0.02]), np.zeros(3)

    def mapped(frame: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, ...]:
        m = Mapping(TASK, TO, 1e-3, ALPHA, BETA, space=PLANE, joints=3, frame=frame)
        m.f[N_MAPPING_VECTORS * TASK + M_GAIN] = 0.75
        map_kinematics(m.f, m.i, jac, tool)
        to_plane_input(m.f, m.i, TASK, tau_e)
        to_frame_force(m.f, m.i, TASK)
        to_map_gain(m.f, TASK)
        error = np.zeros(3)
        to_plane_output(m.f, m.i, TASK, omega_t, v, error)
        return m.x.copy(), error, m.q_mapped.copy(), m.index_offset.copy()

    j2 = jac[:2]
    pinv = j2.T @ np.linalg.inv(j2 @ j2.T + 1e-6 * np.eye(2))  # (DLS, l = 1 mm)
    r = r3[:2, :2]
    x, v_ref, q_mapped, index_offset = mapped((r, offset))
    np.testing.assert_allclose(x, 0.75 * BETA * r.T @ (pinv.T @ tau_e), rtol=1e-12)
    np.testing.assert_allclose(v_ref, 0.75 * ALPHA * pinv @ (r @ omega_t), rtol=1e-12)
    np.testing.assert_allclose(index_offset, 0.25 * ALPHA * omega_t * 1e-3, rtol=1e-12)
    np.testing.assert_allclose(q_mapped, r.T @ (tool[:2] - offset) + index_offset, rtol=1e-12)
    assert float(omega_t @ x) == pytest.approx(BETA / ALPHA * float(v_ref @ tau_e), abs=1e-15)
    plain, identity = mapped(None), mapped((np.eye(2), np.zeros(2)))
    for a, b in zip(plain, identity, strict=True):
        assert np.array_equal(a, b)


IMPAIRMENTS = [*CLASSES, "trace_ramp", "trace_outages"]


@pytest.mark.parametrize("impairment", IMPAIRMENTS)
def test_a_turned_scaled_pair_stays_passive_under_every_impairment(
    impairment: str, tmp_path: Path
) -> None:
    """The study's impairment classes and traces (tests/test_passive_channels.py) on the
    turned, offset and scaled pair, the default channel: both ports' balances and the
    channel's energy >= -1e-9 J, motion bounded, no stop; the network did reach the ports."""
    spec = CLASSES.get(impairment) or {"trace": str(write_traces(tmp_path)[impairment])}
    session = run(PAIR, spec, [*TURNED, "mapping.offset_m=[0.1, -0.2, 0]"], seconds=6.0,
                  sweep=False)  # fmt: skip
    assert session.to.mapping.framed
    assert_passive_and_bounded(session)
    link = session.summary.link["to"]
    assert link["lost"] + link["skipped"] > 0


@pytest.mark.parametrize(
    "overrides, words",
    [
        (["mapping.rotation_rpy_deg=[0, 0, 10]"], "they need channel.space: plane"),
        (["channel.space=plane", "mapping.rotation_rpy_deg=[5, 0, 10]"], "roll and pitch"),
        (["channel.space=plane", "mapping.offset_m=[0, 0, 0.1]"], "offset_m's z"),
        (["channel.space=plane", "mapping.offset_m=[0, 0]"], "mapping.offset_m"),
    ],
)
def test_a_frame_the_space_cannot_take_is_one_line(overrides: list[str], words: str) -> None:
    with pytest.raises(ConfigError) as err:
        config.load(CONFIGS / "free_space.yaml", overrides)
    message = str(err.value)
    assert words in message and "\n" not in message
