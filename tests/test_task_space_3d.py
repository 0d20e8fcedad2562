"""Task space in 3-D and in the pose (issue 26, docs/task_space.md): channel.space position and
pose, a UR5 HSI driving a Franka Panda (configs/task_space/ur5_panda_*.yaml), each site through
its own tool Jacobian (world-aligned, at the tool: power = twist . wrench).

Closed forms checked:
* Power across the map, per tick: (J v) . F = v . (J^T F) at the HSI and
  omega . (r beta J#^T tau_e) = (beta / alpha) (r alpha J# omega) . tau_e at the TO, to 1e-12.
* The displayed mass in 3-D: F_h = (Lambda + b T I) x_dd, Lambda = (J (M1 / c1)^-1 J^T)^-1 the
  UR5 HSI's operational-space inertia of its virtual mass (Khatib 1987; as
  tests/test_heterogeneous_pairs.py does it in the plane), within 5 %.
* The TO's orientation correction: about a fixed axis the error obeys
  T2 e'' + e' + K e = 0 (the correction's first order rate K behind C2's velocity loop, lag
  T2 = M2 / c2), so it decays at the dominant root of T2 s^2 + s + K.
* The DLS's report against an SVD of the tool Jacobian at every tick.
"""

from __future__ import annotations

import json
from pathlib import Path

import example_robot_data
import numpy as np
import pinocchio as pin
import pytest

from teleop_rt import config
from teleop_rt.analysis.discrete import filter_group_delay_s
from teleop_rt.com.port import HSI, TO
from teleop_rt.errors import ConfigError
from teleop_rt.mapping import (
    DLS_ACTIVE_SINGULAR,
    POSE,
    POSITION,
    Mapping,
    hsi_plane_input,
    hsi_plane_render,
    map_kinematics,
    map_orientation,
    start_orientation,
    to_map_gain,
    to_plane_input,
    to_plane_output,
)
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_heterogeneous_pairs import IMPAIRMENTS, assert_passive_under
from tests.test_mapping import ALPHA, BETA, Trace

PASSIVE_J = -1e-9
TASK_SPACE = CONFIGS / "task_space"
PAIRS = [("ur5_panda_position", 3), ("ur5_panda_pose", 6)]
HELD = slice(3500, 4400)  # ticks the operator holds the Panda's hand on the table
UR5_Q0 = [0.0, -1.2, 1.6, -1.97, -1.57, 0.0]
PANDA_Q0 = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.02, 0.02]


def pair(name: str, *overrides: str) -> config.SessionConfig:
    return config.load(TASK_SPACE / f"{name}.yaml", list(overrides))


# --- power across the map: the kernels on the robots' own Jacobians ---------------------------
class Arm:
    """A model of example-robot-data and its tool frame."""

    def __init__(self, name: str, frame: str) -> None:
        self.model = example_robot_data.load(name).model
        self.data = self.model.createData()
        self.frame = self.model.getFrameId(frame)

    def map_at(self, mapping: Mapping, q: np.ndarray) -> None:
        """``mapping``'s kinematics at q, as the site computes them."""
        jac = pin.computeFrameJacobian(
            self.model, self.data, q, self.frame, pin.LOCAL_WORLD_ALIGNED
        )
        placement = self.data.oMf[self.frame]
        map_kinematics(mapping.f, mapping.i, jac, placement.translation)
        if mapping.space == POSE:
            map_orientation(mapping.f, mapping.i, placement.rotation)


def mapped(arm: Arm, q0: list[float], side: int, space: int, m: int, **kw: float) -> Mapping:
    """A site's map alone (its own buffers), at q0 and then at a pose nearby."""
    nv = arm.model.nv
    mapping = Mapping(m, side, 1e-3, space=space, joints=nv, **kw)  # type: ignore[arg-type]
    arm.map_at(mapping, np.array(q0))
    if space == POSE:
        start_orientation(mapping.f, mapping.i)
    arm.map_at(mapping, np.array(q0) + RNG.uniform(-0.3, 0.3, nv))
    mapping.gain = 0.7  # (r: mid ramp)
    return mapping


RNG = np.random.default_rng(11)


@pytest.mark.parametrize("space, m", [(POSITION, 3), (POSE, 6)], ids=["position", "pose"])
def test_the_power_is_the_same_on_either_side_of_the_map(space: int, m: int) -> None:
    """HSI: the port's power omega_c . F_c equals the robot's v_h . (rendered torque); TO: the
    port's omega_t . tau_t equals (beta / alpha) v_ref . tau_e (orientation gain 0: the
    correction is the TO's own), at random poses, velocities and forces, to 1e-12."""
    hsi = mapped(Arm("ur5", "tool0"), UR5_Q0, HSI, space, m)
    to = mapped(Arm("panda", "panda_hand"), PANDA_Q0, TO, space, m, motion_scale=ALPHA,
                force_scale=BETA)  # fmt: skip
    for _ in range(50):
        v, tau_h, force = RNG.normal(size=6), RNG.normal(size=6), RNG.normal(size=m)
        hsi_plane_input(hsi.f, hsi.i, m, v, tau_h)
        error = np.zeros(6)
        hsi_plane_render(hsi.f, hsi.i, m, tau_h, force, error)
        port, robot = hsi.x @ force, v @ (tau_h - error)
        assert port == pytest.approx(robot, rel=1e-12, abs=1e-12)
        assert abs(port) > 1e-3
        v_t, tau_e, omega = RNG.normal(size=9), RNG.normal(size=9), RNG.normal(size=m)
        to_plane_input(to.f, to.i, m, tau_e)
        to_map_gain(to.f, m)
        error = np.zeros(9)
        to_plane_output(to.f, to.i, m, omega, v_t, error)
        port, robot = omega @ to.x, BETA / ALPHA * (error + v_t) @ tau_e
        assert port == pytest.approx(robot, rel=1e-12, abs=1e-12)
        assert abs(port) > 1e-3


# --- the pairs ---------------------------------------------------------------------------------
def run_pair(session: Session) -> tuple[object, np.ndarray]:
    """Per tick: tau_mapped of the HSI, of the TO, then q_mapped of each (m columns each)."""
    rows: list[np.ndarray] = []
    summary = session.run(observer=lambda s: rows.append(np.concatenate([
        s.hsi.mapping.tau_mapped, s.to.mapping.tau_mapped,
        s.hsi.mapping.q_mapped, s.to.mapping.q_mapped])))  # fmt: skip
    return summary, np.array(rows)


@pytest.mark.parametrize("delay_ms", [0, 50])
@pytest.mark.parametrize("name, m", PAIRS, ids=[p[0] for p in PAIRS])
def test_the_panda_follows_the_ur5_and_the_operator_feels_the_table(
    name: str, m: int, delay_ms: int
) -> None:  # fmt: skip
    """The Panda's hand follows the UR5's tool in x, y, z (1 mm at 0 ms, 8 mm at 50 ms: the
    stroke's 8 cm in z at 50 ms) and in the pose also turns as it does (2 mrad at 0 ms, 8 mrad
    at 50 ms, of a 0.14 rad turn); held on the table the operator's force at the tool equals
    the Panda's on it within 5 % (z); the channel's energy >= -1e-9 J."""
    session = Session(pair(name, f"channel.delay_ms={delay_ms}"))
    assert (session.hsi.n, session.to.n, session.n) == (6, 7, m) and not session.fused
    summary, a = run_pair(session)
    q_h, q_t = a[:, 2 * m : 3 * m], a[:, 3 * m :]
    off = np.abs((q_h - q_h[0]) - (q_t - q_t[0])).max(axis=0)
    assert off[:3].max() < (1e-3 if delay_ms == 0 else 8e-3)
    if m == 6:
        assert np.abs(q_h - q_h[0])[:, 3:].max() > 0.05  # the tool did turn
        assert off[3:].max() < (2e-3 if delay_ms == 0 else 8e-3)
    held = a[HELD].mean(axis=0)
    assert held[m + 2] < -3.0  # pressing the table (N)
    assert held[2] == pytest.approx(held[m + 2], rel=0.05)
    assert summary.min_channel_energy_j >= PASSIVE_J and summary.stopped_early is None
    assert summary.dls["to"]["active_ticks"] == 0  # (no singular pose on the way)


@pytest.mark.parametrize("name", [p[0] for p in PAIRS])
def test_the_scaled_two_port_s_energy_is_the_channel_s(name: str) -> None:
    """alpha = 0.2, beta = 5 and a clutch, the table where the scaled Panda reaches it: the
    channel's energy >= -1e-9 J, and the two-port from the robots' own variables
    (tests/test_mapping.py's Trace: v_h . rendered - (beta / alpha) v_ref . tau_e) is that
    energy plus what the matched termination took, tick for tick (the orientation's
    correction off: it is the TO's own motion, not the channel's)."""
    cfg = pair(name, "channel.delay_ms=20", f"mapping.motion_scale={ALPHA}",
               f"mapping.force_scale={BETA}", "mapping.orientation_gain_per_s=0",
               "environment.0.point_m=[0.0, 0.0, 0.585]",
               "operator.clutch=[{start_s: 1.2, end_s: 1.4},"
               " {start_s: 3.0, end_s: 3.3}]")  # fmt: skip
    session = Session(cfg)
    trace = Trace(session)
    summary = session.run(observer=trace)
    assert summary.min_channel_energy_j >= PASSIVE_J and trace.min_scaled >= PASSIVE_J
    n = session.to.n  # (Trace's columns before tau_e: 6 + n + 2 + 6 + n)
    tau_e = np.array(trace.rows)[:, 14 + 2 * n : 14 + 3 * n]
    assert np.abs(tau_e).max() > 0.5  # the Panda in contact
    expected = session.monitor.total_energy + trace.absorbed
    assert trace.scaled == pytest.approx(expected, abs=1e-9, rel=1e-6)
    assert session.hsi.mapping.engagements == session.to.mapping.engagements == 2


@pytest.mark.parametrize("impairment", IMPAIRMENTS)
@pytest.mark.parametrize("name", [p[0] for p in PAIRS])
def test_a_3d_pair_stays_passive_under_every_impairment(
    name: str, impairment: str, tmp_path: Path
) -> None:  # fmt: skip
    """The study's impairment classes and traces (tests/test_passive_channels.py) on each pair's
    own script, bounded wave channel: both ports' balances and the channel's energy >= -1e-9 J,
    motion bounded, no stop. (bounded named: with the default, reflected, the pose pair ends
    under jitter and reordering in a safety stop, the UR5 HSI's wrist_1 at 3.22 rad/s against
    its 3.2: docs/task_space.md, left to do.)"""
    assert_passive_under(TASK_SPACE / f"{name}.yaml", impairment, tmp_path, 6.5,
                         ("channel.wave_reconstruction=bounded",))  # fmt: skip


# --- the displayed mass in 3-D -----------------------------------------------------------------
M1_OVER_C1 = np.array([0.5, 0.5, 0.25, 0.05, 0.05, 0.025]) / 2.0  # the UR5 HSI's M1 / kp
B = 50.0  # N s/m
START = [0.610, 0.109, 0.250]  # the UR5's tool
STROKE = ("environment=[]", "duration_s=7", "operator.waypoints=" + json.dumps([
    {"t_s": 0.5, "position_m": START},
    {"t_s": 3.0, "position_m": [0.630, 0.129, 0.230]},
    {"t_s": 4.0, "position_m": [0.630, 0.129, 0.230]},
    {"t_s": 6.5, "position_m": START},
]))  # fmt: skip  (2 cm along each of x, y and -z, out and back, in free space)


def displayed_gain(delay_ms: int, channel_mass: bool = True) -> float:
    """The least-squares gain of the operator's force F_h (x, y, z stacked) on the closed
    form's Lambda(q) x_dd + b T x_dd over a free-space stroke of the UR5 driving the Panda in
    3-D (velocity, displacement and offset terms fitted alongside); ``channel_mass`` False
    leaves b T out."""
    session = Session(pair("ur5_panda_position", f"channel.delay_ms={delay_ms}", *STROKE))
    m = session.hsi.model
    rows: list[np.ndarray] = []

    def observe(s: Session) -> None:
        q, v = s.hsi.feedback.q, s.hsi.feedback.v
        world = pin.LOCAL_WORLD_ALIGNED
        jac = pin.computeFrameJacobian(m.model, m.data, q, m.ee_frame_id, world)[:3]
        rows.append(np.concatenate([jac @ v, m.tool_position(q), s.hsi.mapping.tau_mapped,
                                    jac.ravel()]))  # fmt: skip

    summary = session.run(observer=observe)
    assert summary.min_channel_energy_j >= PASSIVE_J
    a = np.array(rows)
    vel, x, force = a[:, 0:3], a[:, 3:6] - a[0, 3:6], a[:, 6:9]
    acc = np.diff(vel, axis=0, prepend=vel[:1]) / session.dt
    jac = a[:, 9:27].reshape(-1, 3, 6)
    lam = np.linalg.inv(np.einsum("kij,j,klj->kil", jac, 1.0 / M1_OVER_C1, jac))
    d = session.cfg.delay_ticks
    t = d * session.dt + (filter_group_delay_s(30.0, session.dt) if d else 0.0)
    closed = np.einsum("kij,kj->ki", lam, acc) + (B * t * acc if channel_mass else 0.0)
    # one gain for all three axes; per axis its own damping, stiffness and offset terms
    k = len(a)
    regressors = [closed.T.ravel()]
    for axis in range(3):
        for column in (vel[:, axis], x[:, axis], np.ones(k)):
            r = np.zeros((3, k))
            r[axis] = column
            regressors.append(r.ravel())
    coef, *_ = np.linalg.lstsq(np.column_stack(regressors), force.T.ravel(), rcond=None)
    return float(coef[0])


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_the_displayed_mass_in_3d_is_lambda_plus_b_t(delay_ms: int) -> None:
    """F_h = (Lambda + b T I) x_dd within 5 % (b T = 2.74 kg at 50 ms); at 50 ms the closed
    form without b T misses by more than a factor 2, so the fit tells the channel's mass
    apart."""
    assert displayed_gain(delay_ms) == pytest.approx(1.0, abs=0.05)
    if delay_ms:
        assert displayed_gain(delay_ms, channel_mass=False) > 2.0


# --- the TO's orientation on SO(3) --------------------------------------------------------------
K = 5.0  # 1/s (mapping.orientation_gain_per_s)
T2 = 0.005  # s: the Panda's M2 / c2 (configs/task_space/ur5_panda_pose.yaml)


def test_the_orientation_converges_to_a_rotated_target_at_the_closed_form_rate() -> None:
    """The HSI held still, the Panda's reference orientation turned 0.1 rad about a fixed
    axis: the error log(R_ref R^T) stays on that axis and decays as T2 e'' + e' + K e = 0 says,
    e(t) = e0 (s2 exp(s1 t) - s1 exp(s2 t)) / (s2 - s1), within 1 % of e0 over 1.5 s; its
    rate is the dominant root s1 (-5.13 /s, the first-order rate K = 5 behind C2's lag)."""
    ur5 = Arm("ur5", "tool0")
    pin.framesForwardKinematics(ur5.model, ur5.data, np.array(UR5_Q0))
    held = ur5.data.oMf[ur5.frame].translation.tolist()  # (the hand holds the tool where it is)
    cfg = pair("ur5_panda_pose", "environment=[]", "duration_s=1.5",
               f"mapping.orientation_gain_per_s={K}",
               "operator.waypoints=" + json.dumps([{"t_s": 0.5, "position_m": held}]))  # fmt: skip
    session = Session(cfg)
    to, mapping = session.to, session.to.mapping
    at = mapping.rot_at
    start = mapping.f[at : at + 9].reshape(3, 3).copy()
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    target = pin.exp3(0.1 * axis) @ start
    mapping.f[at + 18 : at + 27] = target.ravel()
    m = to.model
    errors: list[np.ndarray] = []

    def observe(s: Session) -> None:
        pin.framesForwardKinematics(m.model, m.data, s.to.feedback.q)
        errors.append(pin.log3(target @ m.data.oMf[m.ee_frame_id].rotation.T))

    summary = session.run(observer=observe)
    assert summary.stopped_early is None
    e = np.array(errors)
    along = e @ axis
    assert np.abs(e - np.outer(along, axis)).max() < 1e-3 * 0.1  # on the axis
    s1, s2 = np.roots([T2, 1.0, K])[::-1]  # the dominant root first (the one nearer 0)
    assert s1 == pytest.approx(-5.132, abs=1e-3)
    t = (np.arange(len(e)) + 1) * session.dt
    closed = 0.1 * (s2 * np.exp(s1 * t) - s1 * np.exp(s2 * t)) / (s2 - s1)
    assert np.abs(along - closed).max() < 0.01 * 0.1
    late = slice(300, None)
    rate = np.polyfit(t[late], np.log(along[late]), 1)[0]
    assert rate == pytest.approx(s1, rel=0.01)


# --- the DLS's report ----------------------------------------------------------------------------
def test_the_dls_reports_when_it_acts() -> None:
    """A UR5 TO started 3 mrad from its wrist singularity (q5 = 0) in the pose: the summary's
    DLS figures are what an SVD of its tool Jacobian at each tick's measured q says: the
    smallest singular value (to 1e-9) and the ticks it is below 10 l (with the start pose's),
    and the HSI's is 0 ticks; the printed summary says it in one row per site."""
    from rich.console import Console

    from teleop_rt.report import print_summary

    cfg = pair("ur5_panda_pose", "environment=[]", "duration_s=2",
               "to.robot=" + json.dumps({"example_robot": "ur5", "ee_frame": "tool0",
                                         "q0_rad": [0.0, -1.2, 1.6, -1.97, 0.003, 0.0]}),
               "to.virtual_mass=[2.0, 2.0, 1.0, 0.2, 0.2, 0.1]",
               "to.controller={kind: p, kp: [400.0, 400.0, 200.0, 40.0, 40.0, 20.0]}")  # fmt: skip
    session = Session(cfg)
    m = session.to.model

    def smallest(q: np.ndarray) -> float:
        jac = pin.computeFrameJacobian(m.model, m.data, q, m.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
        return float(np.linalg.svd(jac, compute_uv=False)[-1])

    start = smallest(np.array(cfg.to.robot.q0_rad))
    sigma: list[float] = []
    summary = session.run(observer=lambda s: sigma.append(smallest(s.to.feedback.q)))
    s = np.array([start, *sigma])
    dls = summary.dls
    assert dls["to"]["min_singular_value"] == pytest.approx(s.min(), rel=1e-9)
    assert dls["to"]["active_ticks"] == int((s < DLS_ACTIVE_SINGULAR).sum()) > 100
    assert dls["hsi"]["active_ticks"] == 0 and dls["hsi"]["min_singular_value"] > 0.2
    assert summary.stopped_early is None and summary.min_channel_energy_j >= PASSIVE_J
    console = Console(width=200, record=True)
    print_summary(summary, console)
    row = next(line for line in console.export_text().splitlines() if "DLS at the to " in line)
    assert f"active on {dls['to']['active_ticks']} ticks" in row
    assert f"min singular value {dls['to']['min_singular_value']:.3g}" in row


# --- refused ------------------------------------------------------------------------------------
@pytest.mark.parametrize("space", ["position", "pose"])
def test_a_robot_that_cannot_span_the_task_is_one_clear_line(space: str) -> None:
    """The 2-joint SCARA cannot move its tool in z (nor turn it but about z): position and pose
    refuse it as the HSI (and as the TO), naming the robot, the space and the rank."""
    scara = {"urdf": "../../robots/urdf/scara_2dof.urdf", "ee_frame": "tool",
             "q0_rad": [-0.8, 1.8]}  # fmt: skip
    for side in ("hsi", "to"):
        cfg = pair("ur5_panda_position", f"channel.space={space}",
                   f"{side}.robot=" + json.dumps(scara), f"{side}.virtual_mass=0.1",
                   f"{side}.controller={{kind: p, kp: 2.0}}")  # fmt: skip
        with pytest.raises(ConfigError) as err:
            Session(cfg)
        said = str(err.value)
        assert "\n" not in said and said.startswith(f"channel.space: {space} couples")
        assert f"the {side}'s tool Jacobian (2 joints, frame tool) spans at most 2" in said
