"""The posture task of a redundant TO in task space (issue 26, ``teleop_rt.mapping.to_posture``,
docs/task_space.md): v_ref += (I - J# J) k_p (q_posture - q), J# the damped least squares'.

Closed forms. The kernel's term is P z with P = I - J^T A^-1 J (A = J J^T + l^2 I): exact on
J's null space, and its task velocity, the leak, is J P z = l^2 A^-1 J z (J J# = I - l^2 A^-1),
so |J P z| <= l^2 / (sigma_min^2 + l^2) |J z| and <= l / 2 |z| at any sigma. In a session, with
the HSI still (the paper's damper operator: nothing drives it) and the TO started on the
self-motion manifold of its posture's tool pose, 0.1 rad from the posture, the offset obeys
T2 e'' + e' + k_p e = 0 (T2 = M2 / c2 = 5 ms on every joint): exp(-k_p t) within k_p T2 (0.5 %)
plus the manifold's curvature, O(|e0|); the test's bound is 1 % of e0. The tool moves by what
the velocity loop's lag and the one-tick stale J leave of the null-space motion, to first
order |J(q(t)) - J(q(t - T2 - dt))| |v| per unit time: |dx| <= B = integral of
(T2 + dt) |D_u J| |v|^2 dt (u = v / |v|, from the logged motion; the leak adds l^2 / sigma^2 of
that, far below), against the e0 sigma (centimetres) a posture term without the projector
moves it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from teleop_rt import config
from teleop_rt.com.port import HSI, TO
from teleop_rt.errors import ConfigError
from teleop_rt.mapping import (
    DLS_DAMPING_M,
    JOINT,
    PLANE,
    POSE,
    POSITION,
    Mapping,
    map_kinematics,
    to_posture,
)
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_bad_input import assert_refused
from tests.test_heterogeneous_pairs import IMPAIRMENTS, assert_passive_under
from tests.test_no_allocation import net_blocks

TASK_SPACE = CONFIGS / "task_space"
LWA = pin.LOCAL_WORLD_ALIGNED
L2 = DLS_DAMPING_M**2
KP = 1.0  # k_p, 1/s (mapping.posture_gain_per_s; off by default)
T2 = 0.005  # the TO's M2 / c2 in the task-space configs
RNG = np.random.default_rng(26)


def posture_map(m: int, nj: int, jac: np.ndarray, posture: np.ndarray | None) -> Mapping:
    """A TO's map alone (its own buffers) with the posture task, its kinematics at ``jac``."""
    space = {2: PLANE, 3: POSITION, 6: POSE}[m]
    mapping = Mapping(m, TO, 1e-3, space=space, joints=nj, posture_gain=KP, posture=posture)
    full = np.zeros((6, nj))
    full[:m] = jac
    map_kinematics(mapping.f, mapping.i, full, np.zeros(3))
    return mapping


def dls(jac: np.ndarray) -> np.ndarray:
    return jac.T @ np.linalg.inv(jac @ jac.T + L2 * np.eye(len(jac)))


@pytest.mark.parametrize("m, nj", [(2, 6), (2, 7), (3, 7), (6, 7)])
def test_the_kernel_is_the_dls_projection_of_the_posture(m: int, nj: int) -> None:
    """At random J (sigma_min swept from 1 down to l): the term is (I - J# J) z to rounding
    (1e-15 cond(A)); on
    J's null space it is z's own component (exact); its task velocity J P z is l^2 A^-1 J z,
    below l^2 / (sigma_min^2 + l^2) |J z| and l / 2 |z|, and is what the block reports."""
    for sigma_min in (1.0, 0.3, 0.05, 10 * DLS_DAMPING_M, DLS_DAMPING_M):
        u, _ = np.linalg.qr(RNG.normal(size=(m, m)))
        w, _ = np.linalg.qr(RNG.normal(size=(nj, nj)))
        sv = np.linspace(1.0, sigma_min, m)
        jac = u @ np.diag(sv) @ w[:, :m].T
        q, q_p = RNG.uniform(-1, 1, nj), RNG.uniform(-1, 1, nj)
        mapping = posture_map(m, nj, jac, q_p)
        error = np.zeros(nj)
        to_posture(mapping.f, mapping.i, m, q, error)
        z = KP * (q_p - q)
        a = jac @ jac.T + L2 * np.eye(m)
        rounding = 1e-15 * np.linalg.cond(a)  # (1e-15 at sigma_min = 1, 5e-10 at l)
        assert np.allclose(error, (np.eye(nj) - dls(jac) @ jac) @ z, rtol=0, atol=rounding)
        null = w[:, m:]  # J's null space: the term's component there is z's, exactly
        assert np.allclose(null.T @ error, null.T @ z, rtol=0, atol=rounding)
        leak = jac @ error
        assert np.allclose(leak, L2 * np.linalg.solve(a, jac @ z), rtol=1e-6, atol=1e-15)
        bound = L2 / (sigma_min**2 + L2) * np.linalg.norm(jac @ z)
        assert np.linalg.norm(leak) <= bound * (1 + 1e-9) + 1e-15
        assert np.linalg.norm(leak) <= DLS_DAMPING_M / 2 * np.linalg.norm(z) * (1 + 1e-9)
        assert np.linalg.norm(error) > 0.1 * np.linalg.norm(null.T @ z) > 0
        assert mapping.peak_posture_leak == pytest.approx(np.abs(leak).max(), rel=1e-9)


def test_the_posture_defaults_to_the_first_ticks_configuration() -> None:
    """No posture given: the first tick's q becomes it (the term is 0 then), and a later q
    is pulled back toward it; a map without redundancy or at the HSI has none."""
    jac = RNG.normal(size=(2, 6))
    mapping = posture_map(2, 6, jac, None)
    q0, error = RNG.uniform(-1, 1, 6), np.zeros(6)
    to_posture(mapping.f, mapping.i, 2, q0, error)
    assert mapping.posture_held == 1 and not error.any()
    q1 = q0 + RNG.normal(scale=0.1, size=6)
    to_posture(mapping.f, mapping.i, 2, q1, error)
    assert np.allclose(error, (np.eye(6) - dls(jac) @ jac) @ (KP * (q0 - q1)), atol=1e-12)
    for side, joints in ((HSI, 6), (TO, 2)):  # (the HSI; a TO with no joint to spare)
        assert Mapping(2, side, 1e-3, space=PLANE, joints=joints, posture_gain=KP).posture_gain == 0
    assert Mapping(6, TO, 1e-3, space=JOINT, posture_gain=KP).posture_gain == 0


def test_off_by_default_and_in_a_session_the_posture_is_the_start() -> None:
    """The default config has no posture task (the kernel is not called: the runs are those
    of before it); with a gain and no posture_rad, a session's posture is the TO's start."""
    path = TASK_SPACE / "scara_ur5_plane.yaml"
    assert Session(config.load(path, [])).to.mapping.posture_gain == 0
    session = Session(config.load(path, ["mapping.posture_gain_per_s=1", "duration_s=0.005"]))
    session.run()
    to = session.to.mapping
    assert to.posture_gain == 1 and to.posture_held == 1
    at = to.posture_at
    assert to.f[at : at + 6].tolist() == session.cfg.to.robot.q0_rad
    assert session.hsi.mapping.posture_gain == 0


def tool_pose(model: pin.Model, data: pin.Data, frame: int, q: np.ndarray, m: int) -> np.ndarray:
    pin.framesForwardKinematics(model, data, q)
    return data.oMf[frame].translation[: min(m, 3)].copy()


def on_the_self_motion_manifold(
    model: pin.Model, frame: int, q_p: np.ndarray, m: int, arc: float
) -> np.ndarray:  # fmt: skip
    """A configuration ``arc`` rad along J's null space from q_p with the tool where it is at
    q_p (in the task's directions): small steps along the null space, each corrected back to
    the tool's place (the pose: its rotation too, to second order in the step)."""
    data = model.createData()

    def jac(q: np.ndarray) -> np.ndarray:
        return pin.computeFrameJacobian(model, data, q, frame, LWA)[:m]

    q, d = q_p.copy(), np.linalg.svd(jac(q_p))[2][m]
    pin.framesForwardKinematics(model, data, q_p)
    goal = data.oMf[frame].copy() if m == 6 else data.oMf[frame].translation[:m].copy()
    steps = 200
    for _ in range(steps):
        null = np.linalg.svd(jac(q))[2][m:].T
        d = null @ (null.T @ d)
        q = q + arc / steps * d / np.linalg.norm(d)
        for _ in range(2):  # back onto the tool's pose
            pin.framesForwardKinematics(model, data, q)
            if m == 6:
                miss = pin.log6(goal.inverse() * data.oMf[frame]).vector
                miss = np.concatenate([data.oMf[frame].rotation @ miss[:3],
                                       data.oMf[frame].rotation @ miss[3:]])  # fmt: skip
            else:
                miss = data.oMf[frame].translation[:m] - goal
            q = q - np.linalg.pinv(jac(q)) @ miss
    return q


NULL_CASES = [("scara_ur5_plane", 2), ("ur5_panda_position", 3), ("ur5_panda_pose", 6)]


@pytest.mark.parametrize("name, m", NULL_CASES, ids=[c[0] for c in NULL_CASES])
def test_a_null_space_offset_decays_as_exp_minus_kp_t_and_the_tool_stays(name: str, m: int) -> None:
    """The TO started 0.1 rad from its posture on the posture tool pose's self-motion manifold,
    the HSI still: |q - q_p| follows e0 exp(-k_p t) within 1 % of e0 (and the closed form of
    T2 s^2 + s + k_p within 0.5 %) over 4 s; the tool moves less than the lag's bound B (the
    module's docstring; tens of um), far below the e0 sigma_min a posture term without the
    projector moves it; the channel's energy >= -1e-9 J."""
    path = TASK_SPACE / f"{name}.yaml"
    base = config.load(path, [])
    q_p = np.array(base.to.robot.q0_rad)
    probe = Session(config.load(path, ["environment=[]"]))
    model, frame = probe.to.model.model, probe.to.model.ee_frame_id
    q0 = on_the_self_motion_manifold(model, frame, q_p, m, 0.1)
    e0 = float(np.linalg.norm(q0 - q_p))
    assert e0 == pytest.approx(0.1, rel=0.01)
    session = Session(config.load(path, [
        "environment=[]", "duration_s=4", "operator={kind: damper, damping_nm_s_per_rad: 1.0}",
        "to.robot.q0_rad=" + json.dumps(q0.tolist()),
        "mapping.posture_rad=" + json.dumps(q_p.tolist()), f"mapping.posture_gain_per_s={KP}",
    ]))  # fmt: skip
    rows: list[np.ndarray] = []
    summary = session.run(observer=lambda s: rows.append(
        np.concatenate([s.to.feedback.q, s.to.feedback.v])))  # fmt: skip
    assert summary.min_channel_energy_j >= -1e-9 and summary.stopped_early is None
    a = np.array(rows)
    nj, dt = len(q_p), session.dt
    q, v = a[:, :nj], a[:, nj:]
    t = (np.arange(len(a)) + 1) * dt
    e = np.linalg.norm(q - q_p, axis=1)
    assert np.abs(e - e0 * np.exp(-KP * t)).max() < 0.01 * e0
    root = np.sqrt(1 - 4 * T2 * KP)
    s1, s2 = (-1 + root) / (2 * T2), (-1 - root) / (2 * T2)
    closed = (s2 * np.exp(s1 * t) - s1 * np.exp(s2 * t)) / (s2 - s1)
    assert np.abs(e - e0 * closed).max() < 0.005 * e0
    data = model.createData()
    x = np.array([tool_pose(model, data, frame, qk, m) for qk in q])
    moved = np.linalg.norm(x - tool_pose(model, data, frame, q0, m), axis=1).max()
    bound, h = 0.0, 1e-6
    for qk, vk in zip(q, v, strict=True):
        speed = np.linalg.norm(vk)
        if speed > 0:
            du = (pin.computeFrameJacobian(model, data, qk + h * vk / speed, frame, LWA)
                  - pin.computeFrameJacobian(model, data, qk, frame, LWA))[: min(m, 3)] / h
            bound += (T2 + dt) * np.linalg.norm(du, 2) * speed**2 * dt
    sigma_min = np.linalg.svd(pin.computeFrameJacobian(model, data, q_p, frame, LWA)[:m])[1][-1]
    assert moved < bound < 1e-3 * e0 * sigma_min
    assert session.to.mapping.peak_posture_leak < 1e-6  # m/s (rad/s in the pose's rows)


def test_the_posture_does_no_work_on_the_wall() -> None:
    """SCARA -> UR5 pressing the wall, the UR5 started 0.1 rad from its posture on the
    self-motion manifold (k_p 0.5 /s: the posture still acts while held). The posture term's
    power on the measured environment torque, tau_e . P z (P, z as the kernel formed them:
    checked against its own J P z), is F . J P z with tau_e = J^T F at the tool: at each tick
    within |F| (|J_stale P z| + |J - J_stale| |P z|) (the leak, and the one-tick stale J's),
    below 1e-5 of the port's peak power, and its energy below 1e-5 J (measured 4e-6 and
    1.8e-6 J); the full z (no projector) would do 0.5 J on the wall. The channel's energy
    >= -1e-9 J."""
    path = TASK_SPACE / "scara_ur5_plane.yaml"
    q_p = np.array(config.load(path, []).to.robot.q0_rad)
    probe = Session(config.load(path, []))
    model, frame = probe.to.model.model, probe.to.model.ee_frame_id
    q0 = on_the_self_motion_manifold(model, frame, q_p, 2, 0.1)
    gain = 0.5
    session = Session(config.load(path, [
        "to.robot.q0_rad=" + json.dumps(q0.tolist()), f"mapping.posture_gain_per_s={gain}",
        "mapping.posture_rad=" + json.dumps(q_p.tolist()),
    ]))  # fmt: skip
    to = session.to
    kin, nj = to.mapping.kin_at, to.n
    rows: list[tuple[float, float, float, float]] = []
    stale = [to.mapping.f[kin : kin + 4 * nj].copy()]  # J, J# (2 x nj each) the tick uses

    def observe(s: Session) -> None:
        jac, inv = stale[0][: 2 * nj].reshape(2, nj), stale[0][2 * nj :].reshape(nj, 2)
        z = gain * (q_p - s.to.feedback.q)
        pz = z - inv @ (jac @ z)
        at = s.to.mapping.posture_at + nj + 2  # (the kernel's own J P z: the same P z)
        assert np.allclose(s.to.mapping.f[at : at + 2], jac @ pz, rtol=1e-9, atol=1e-15)
        stale[0] = s.to.mapping.f[kin : kin + 4 * nj].copy()  # (J at this tick's q)
        now = stale[0][: 2 * nj].reshape(2, nj)
        tau_e = s.to.signals.tau
        force = np.linalg.lstsq(now.T, tau_e, rcond=None)[0]
        rest = np.linalg.norm(tau_e - now.T @ force)  # (0 but for rounding: a tool contact)
        bound = (np.linalg.norm(force) * (np.linalg.norm(jac @ pz)
                 + np.linalg.norm(now - jac, 2) * np.linalg.norm(pz))
                 + rest * np.linalg.norm(pz))  # fmt: skip
        port = float(s.to.port.flow @ s.to.port.effort)
        rows.append((float(tau_e @ pz), bound, float(tau_e @ z), port))

    summary = session.run(observer=observe)
    assert summary.min_channel_energy_j >= -1e-9 and summary.stopped_early is None
    power, bound, unprojected, port = np.array(rows).T
    assert np.abs(port).max() > 0.05  # W: the wall was pressed
    assert np.all(np.abs(power) <= bound * (1 + 1e-9) + 1e-15)
    assert np.abs(power).max() < 1e-5 * np.abs(port).max()
    assert abs(power.sum() * session.dt) < 1e-5
    assert abs(unprojected.sum() * session.dt) > 0.1  # J: what the term does without P


def posture_case(*overrides: str) -> list[str]:
    return ["check", str(TASK_SPACE / "scara_ur5_plane.yaml"), "--set",
            "mapping.posture_gain_per_s=1", *(x for o in overrides for x in ("--set", o))]


def test_a_bad_posture_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    """Wrong length, outside a joint's limits, in joint space, without a gain, or a TO with no
    joint to spare: one line naming mapping.posture_rad, exit 2."""
    assert_refused(posture_case("mapping.posture_rad=[0, 0]"), capsys,
                   "mapping.posture_rad: has 2 entries but the TO has 6 joints")  # fmt: skip
    assert_refused(posture_case("mapping.posture_rad=[0, -1.2, 7.0, -1.97, -1.57, 0]"), capsys,
                   "mapping.posture_rad: 7 rad for joint 2", "outside its limits")  # fmt: skip
    assert_refused(posture_case("channel.space=joint", "mapping.posture_rad=[0, 0]"), capsys,
                   "mapping.posture_rad", "channel.space: plane, position or pose")  # fmt: skip
    assert_refused(["check", str(TASK_SPACE / "scara_ur5_plane.yaml"), "--set",
                    "mapping.posture_rad=[0, -1.2, 1.6, -1.97, -1.57, 0]"], capsys,
                   "mapping.posture_rad", "mapping.posture_gain_per_s > 0")  # fmt: skip
    with pytest.raises(ConfigError) as err:
        Session(config.load(TASK_SPACE / "ur5_scara_plane.yaml",
                            ["mapping.posture_gain_per_s=1", "mapping.posture_rad=[0, 1]"]))
    said = str(err.value)
    assert "\n" not in said and said.startswith("mapping.posture_rad: the TO's 2 joints have none")


def test_a_tick_with_the_posture_keeps_no_allocation() -> None:
    """The posture's tick path allocates nothing it keeps (tests/test_no_allocation.py's
    measurement): the SCARA -> UR5 pair with the posture on, after warm-up."""
    session = Session(config.load(TASK_SPACE / "scara_ur5_plane.yaml",
                                  ["mapping.posture_gain_per_s=1"]))  # fmt: skip
    for _ in range(500):
        session.step()
    ticks = 4000
    assert net_blocks(session.step, ticks) < ticks // 100
    assert session.to.mapping.posture_held == 1


@pytest.mark.parametrize("impairment", IMPAIRMENTS)
@pytest.mark.parametrize("name", ["scara_ur5_plane", "scara_panda_plane"])
def test_a_pair_with_the_posture_stays_passive_under_every_impairment(
    name: str, impairment: str, tmp_path: Path
) -> None:  # fmt: skip
    """The plane pairs with a redundant TO, the posture on (k_p 1 /s), under the study's
    impairment classes and traces on the default channel: both ports' balances and the
    channel's energy >= -1e-9 J, motion bounded, no stop (slow)."""
    assert_passive_under(TASK_SPACE / f"{name}.yaml", impairment, tmp_path, 6.0,
                         ("mapping.posture_gain_per_s=1",))  # fmt: skip
