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
    PLANE,
    POSE,
    POSITION,
    TASK,
    TO,
    Mapping,
    frame_rotation,
    map_kinematics,
    map_orientation,
    start_orientation,
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
        Mi = Mapping.idx
        m = Mapping(TASK, TO, 1e-3, ALPHA, BETA, space=PLANE, joints=3, frame=frame)
        m.f[Mi.N_VECTORS * TASK + Mi.GAIN] = 0.75
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
        (["mapping.rotation_rpy_deg=[0, 0, 10]"], "channel.space: plane, position or pose"),
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


# --- in 3-D and in the pose: x_t = R (alpha x_h) + offset, R_t = R R_h (R0 fixed) ------------
POSE_DIM = 6


@pytest.mark.parametrize("m", [3, POSE_DIM], ids=["position", "pose"])
def test_the_3d_kernel_turns_each_half_of_the_twist_by_r_and_of_the_wrench_by_r_transposed(
    m: int,
) -> None:
    """The TO's map alone in 3-D (m = 3) and in the pose (m = 6, the twist's linear and angular
    halves each turned by the same R), against its closed form: v_ref = r alpha J# (R omega),
    x = r beta R^T J#^T tau_e, q_mapped = R^T (x_t - offset) (the pose's orientation
    coordinates R^T log(R_t R_t0^T)) + index offset, the orientation's reference
    R_ref <- exp(r alpha dt R omega_ang) R_ref (R_t = R R_h), power in = power out; the
    identity frame computes what the unframed map does, bit for bit."""
    import pinocchio as pin

    rng = np.random.default_rng(5)
    nj = 7
    jac = rng.normal(size=(6, nj))
    tool = np.array([0.5, 0.1, 0.6])
    r3 = frame_rotation((25.0, -40.0, 90.0))
    offset = np.array([0.2, -0.3, 0.15])
    r_start = pin.exp3(np.array([0.3, -0.2, 0.1]))
    r_now = pin.exp3(np.array([0.05, 0.1, -0.07])) @ r_start
    tau_e, omega_t = rng.normal(size=nj), rng.normal(size=m)
    space, gain, dt = (POSITION, 0.75, 1e-3) if m == 3 else (POSE, 0.75, 1e-3)

    def mapped(frame: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, ...]:
        Mi = Mapping.idx
        mp = Mapping(m, TO, dt, ALPHA, BETA, space=space, joints=nj, frame=frame)
        mp.f[Mi.N_VECTORS * m + Mi.GAIN] = gain
        map_kinematics(mp.f, mp.i, jac, tool)
        if space == POSE:
            map_orientation(mp.f, mp.i, r_start)
            start_orientation(mp.f, mp.i)
            map_orientation(mp.f, mp.i, r_now)
        to_plane_input(mp.f, mp.i, m, tau_e)
        to_frame_force(mp.f, mp.i, m)
        to_map_gain(mp.f, m)
        error = np.zeros(nj)
        to_plane_output(mp.f, mp.i, m, omega_t, np.zeros(nj), error)
        at = mp.rot_at + 18
        r_ref = mp.f[at : at + 9].reshape(3, 3).copy() if space == POSE else np.eye(3)
        return mp.x.copy(), error, mp.q_mapped.copy(), mp.index_offset.copy(), r_ref

    j = jac[:m]
    pinv = j.T @ np.linalg.inv(j @ j.T + 1e-6 * np.eye(m))  # (DLS, l = 1 mm)
    turn = np.kron(np.eye(m // 3), r3)  # R on each 3-vector
    x, v_ref, q_mapped, index_offset, r_ref = mapped((r3, offset))
    np.testing.assert_allclose(x, gain * BETA * turn.T @ (pinv.T @ tau_e), rtol=1e-12)
    np.testing.assert_allclose(v_ref, gain * ALPHA * pinv @ (turn @ omega_t), rtol=1e-12)
    np.testing.assert_allclose(index_offset, (1 - gain) * ALPHA * omega_t * dt, rtol=1e-12)
    pos = np.concatenate([tool - offset, pin.log3(r_now @ r_start.T)])[:m]
    np.testing.assert_allclose(q_mapped, turn.T @ pos + index_offset, rtol=1e-12, atol=1e-15)
    if m == POSE_DIM:
        step = pin.exp3(gain * ALPHA * dt * r3 @ omega_t[3:])
        np.testing.assert_allclose(r_ref, step @ r_start, rtol=0, atol=1e-14)
    assert float(omega_t @ x) == pytest.approx(BETA / ALPHA * float(v_ref @ tau_e), abs=1e-14)
    plain, identity = mapped(None), mapped((np.eye(3), np.zeros(3)))
    for a, b in zip(plain, identity, strict=True):
        assert np.array_equal(a, b)


TASK_SPACE = CONFIGS / "task_space"
TILTED = (0.0, 20.0, 90.0)  # rpy, degrees: a quarter turn about z, then tilted 20 degrees


def frame_args(rpy: tuple[float, float, float], offset: np.ndarray) -> list[str]:
    return [f"mapping.rotation_rpy_deg={list(rpy)}", f"mapping.offset_m={offset.tolist()}",
            f"mapping.motion_scale={ALPHA}", f"mapping.force_scale={BETA}"]  # fmt: skip


def start_offset(name: str, rpy: tuple[float, float, float]) -> np.ndarray:
    """The offset of the starting poses: x_t(0) - R alpha x_h(0)."""
    cfg = config.load(TASK_SPACE / f"{name}.yaml", [])
    start = Session(cfg)
    x_h0, x_t0 = (site.model.ee_position(np.array(spec.robot.q0_rad))
                  for site, spec in ((start.hsi, cfg.hsi), (start.to, cfg.to)))  # fmt: skip
    return x_t0 - frame_rotation(rpy) @ (ALPHA * x_h0)


def traced_3d(name: str, *overrides: str) -> tuple[Session, dict[str, np.ndarray]]:
    """Run a 3-D pair; per tick: each tool's position and rotation (Pinocchio at the measured
    q), q_mapped and tau_mapped of each site, the TO's port power and its robot-side power
    (beta / alpha) v_ref . tau_e, the TO's measured velocity."""
    session = Session(config.load(TASK_SPACE / f"{name}.yaml", list(overrides)))
    m = session.to.mapping
    scale = m.force_scale / m.motion_scale
    rows: dict[str, list[np.ndarray]] = {k: [] for k in (
        "x_h", "x_t", "rot_h", "rot_t", "q_h", "q_t", "f_h", "f_t", "power", "v_t")}  # fmt: skip

    def observe(s: Session) -> None:
        for site, x, rot in ((s.hsi, "x_h", "rot_h"), (s.to, "x_t", "rot_t")):
            rows[x].append(site.model.ee_position(site.feedback.q))
            rows[rot].append(site.model.data.oMf[site.model.ee_frame_id].rotation.copy())
        rows["q_h"].append(s.hsi.mapping.q_mapped.copy())
        rows["q_t"].append(s.to.mapping.q_mapped.copy())
        rows["f_h"].append(s.hsi.mapping.tau_mapped.copy())
        rows["f_t"].append(s.to.mapping.tau_mapped.copy())
        v_ref = s.to.signals.error + s.to.feedback.v
        rows["power"].append(np.array([s.to.port.flow @ s.to.port.effort,
                                       scale * (v_ref @ s.to.signals.tau)]))  # fmt: skip
        rows["v_t"].append(s.to.feedback.v.copy())

    session.summary = session.run(observer=observe)
    return session, {k: np.array(v) for k, v in rows.items()}


def angle(rot: np.ndarray) -> float:
    import pinocchio as pin

    return float(np.linalg.norm(pin.log3(rot)))


def scaled(rot: np.ndarray) -> np.ndarray:
    """exp(alpha log(rot)): the rotation alpha times as far about its axis (the TO's turn for
    the HSI's, the motion scale applying to the twist's angular half too)."""
    import pinocchio as pin

    return np.asarray(pin.exp3(ALPHA * pin.log3(rot)))


@pytest.mark.parametrize("name", ["ur5_panda_position", "ur5_panda_pose"])
def test_a_turned_offset_tool_tracks_r_x_h_plus_the_offset(name: str) -> None:
    """Free space, 0 ms, alpha = 0.5, R a quarter turn about z tilted 20 degrees, the offset of
    the starting poses: the Panda's hand is at R (alpha x_h) + offset within 1 mm at every
    tick (unturned it would be more than 10 mm off); in the pose it also turns as R R_h does,
    R_t R_t0^T = R exp(alpha log(R_h R_h0^T)) R^T within 4 mrad; the sites' q_mapped (both
    in the HSI's frame) agree within 1 mm (1 mm / 4 mrad); passive."""
    r = frame_rotation(TILTED)
    offset = start_offset(name, TILTED)
    session, a = traced_3d(name, "environment=[]", *frame_args(TILTED, offset))
    x_h, x_t = a["x_h"], a["x_t"]
    assert np.abs(x_h - x_h[0]).max() > 0.07  # (the stroke: 8 cm in z at the HSI)
    target = ALPHA * x_h @ r.T + offset
    off = np.abs(x_t - target).max()
    assert off < 1e-3, off
    assert np.abs(x_t - (ALPHA * x_h + x_t[0] - ALPHA * x_h[0])).max() > 0.01
    q_off = np.abs(a["q_h"] - a["q_t"]).max(axis=0)
    assert q_off[:3].max() < 1e-3, q_off
    if name.endswith("pose"):
        turned = [angle(rt @ a["rot_t"][0].T @ (r @ scaled(rh @ a["rot_h"][0].T) @ r.T).T)
                  for rh, rt in zip(a["rot_h"], a["rot_t"], strict=True)]  # fmt: skip
        assert max(angle(rh @ a["rot_h"][0].T) for rh in a["rot_h"]) > 0.05  # (it turned)
        assert max(turned) < 4e-3, max(turned)
        assert q_off[3:].max() < 4e-3, q_off
    assert session.summary.min_channel_energy_j >= PASSIVE_J
    assert session.summary.stopped_early is None


def test_an_offset_the_start_does_not_meet_moves_no_robot() -> None:
    """No jump at the start: the offset is a frame, not a command (the channel carries motion),
    so with an offset 10 cm away from the starting poses' the two robots move exactly as with
    the starting poses' offset, bit for bit, and only the TO's q_mapped moves, by
    R^T (the difference) to 1e-12: the TO starts where it stands and the offset is taken up
    as a constant."""
    name = "ur5_panda_position"
    offset = start_offset(name, TILTED)
    moved = offset + np.array([0.06, -0.05, 0.06])
    runs = [traced_3d(name, "duration_s=1.5", *frame_args(TILTED, o))[1] for o in (offset, moved)]
    for key in ("x_h", "x_t", "f_h", "q_h", "v_t"):
        assert np.array_equal(runs[0][key], runs[1][key]), key
    shift = frame_rotation(TILTED).T @ (moved - offset)
    np.testing.assert_allclose(runs[0]["q_t"] - runs[1]["q_t"], np.tile(shift, (1500, 1)),
                               rtol=0, atol=1e-12)  # fmt: skip
    assert np.abs(runs[0]["x_t"] - runs[0]["x_t"][0]).max() > 1e-3  # (the TO did move)


TABLE_WITHIN_REACH = "environment.0.point_m=[0.0, 0.0, 0.57]"  # (the scaled stroke: 3.8 cm)
HELD_3D = slice(3500, 4400)  # ticks the operator holds the Panda's hand on the table


@pytest.mark.parametrize("delay_ms", [0, 50])
@pytest.mark.parametrize("name", ["ur5_panda_position", "ur5_panda_pose"])
def test_through_a_turned_3d_frame_the_power_is_unchanged_and_the_operator_feels_r_t_f(
    name: str, delay_ms: int
) -> None:  # fmt: skip
    """On the table (moved to where the turned, scaled stroke reaches it), the orientation's
    correction off (it is the TO's own motion, not the channel's): the TO's port power equals
    (beta / alpha) v_ref . tau_e at every tick to 1e-12 W (R on each half of the twist, R^T on
    each half of the wrench: R^T R = I), and held there the operator's force at the tool
    equals R^T beta F_e in the HSI's frame within 5 % of its size, where beta F_e in the TO's
    frame is off by the turn; the channel's energy >= -1e-9 J."""
    offset = start_offset(name, TILTED)
    session, a = traced_3d(name, f"channel.delay_ms={delay_ms}", TABLE_WITHIN_REACH,
                           "mapping.orientation_gain_per_s=0", *frame_args(TILTED, offset))
    power = a["power"]
    assert np.abs(power[:, 0]).max() > 0.02  # (power flows: the Panda presses the table)
    np.testing.assert_allclose(power[:, 0], power[:, 1], rtol=0.0, atol=1e-12)
    f_h, f_t = a["f_h"][HELD_3D].mean(axis=0)[:3], a["f_t"][HELD_3D].mean(axis=0)[:3]
    size = np.linalg.norm(f_h)
    assert size > 2.0
    assert np.linalg.norm(f_h - f_t) < 0.05 * size, (f_h, f_t)
    assert np.linalg.norm(frame_rotation(TILTED) @ f_t - f_h) > 0.25 * size  # (20 degrees)
    assert session.summary.min_channel_energy_j >= PASSIVE_J
    assert session.summary.stopped_early is None


@pytest.mark.parametrize("impairment", IMPAIRMENTS)
@pytest.mark.parametrize("name", ["ur5_panda_position", "ur5_panda_pose"])
def test_a_turned_offset_3d_pair_stays_passive_under_every_impairment(
    name: str, impairment: str, tmp_path: Path
) -> None:  # fmt: skip
    """The study's impairment classes and traces on the 3-D pairs turned (a quarter turn about
    z tilted 20 degrees), offset and scaled, the bounded wave channel (as the unturned 3-D
    pairs: tests/test_task_space_3d.py): both ports' balances and the channel's energy
    >= -1e-9 J, motion bounded, no stop; the network did reach the ports. (With the default,
    reflected, 6 of the 16 runs end in a safety stop, the UR5 HSI's wrist_1 at up to 3.25 rad/s
    against its 3.2: docs/task_space.md, left to do.)"""
    spec = CLASSES.get(impairment) or {"trace": str(write_traces(tmp_path)[impairment])}
    frame = frame_args(TILTED, np.array([0.1, -0.2, 0.05]))
    session = run(TASK_SPACE / f"{name}.yaml", spec,
                  [*frame, TABLE_WITHIN_REACH, "channel.wave_reconstruction=bounded"],
                  seconds=6.5, sweep=False)  # fmt: skip
    assert session.to.mapping.framed
    assert_passive_and_bounded(session)
    link = session.summary.link["to"]
    assert link["lost"] + link["skipped"] > 0
