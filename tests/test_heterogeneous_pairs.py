"""Heterogeneous pairs coupled in the plane (issue 26, docs/task_space.md): a SCARA HSI driving
a UR5 or a Panda (example-robot-data), and a UR5 HSI driving the SCARA. Each follows, feels the
wall, stays passive under the study's impairment classes, and displays in task space the mass
the closed form says.

Displayed mass, in task space. The HSI's virtual dynamics are M1 a_h = c1 (tau_h - J^T F_c)
(P control, eq 4), so at the tool the operator's force is F_h = Lambda x_dd + F_c (the
J_dot v term is second order in the stroke's speed), with Lambda = (J (M1 / c1)^-1 J^T)^-1 the
HSI's operational-space inertia (Khatib 1987) of the virtual mass M1 / c1, and in free space
the wave channel displays F_c = b T x_dd (eq 29; T the effective one-way delay: D dt plus the
received-wave filter's DC group delay, ``teleop_rt.analysis.displayed.effective_delay``).
Displayed: Lambda + b T I, the task-space form of the joint case's M1 / c1 + b T.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from teleop_rt import config
from teleop_rt.analysis.discrete import filter_group_delay_s
from teleop_rt.session import Session, Summary
from tests.conftest import CONFIGS
from tests.test_mapping import (
    CLUTCH,
    STROKES,
    TAU_STEP_BOUND_NM,
    WINDOW,
    re_engaged,
    run_in_the_plane,
)  # fmt: skip
from tests.test_passive_channels import CLASSES, assert_passive_and_bounded, run, write_traces

PASSIVE_J = -1e-9
TASK_SPACE = CONFIGS / "task_space"
# (config, HSI joints, TO joints)
PAIRS = [("scara_ur5_plane", 2, 6), ("scara_panda_plane", 2, 7), ("ur5_scara_plane", 6, 2)]
HELD = slice(3500, 3900)  # ticks the operator holds the tool against the wall


def pair(name: str, *overrides: str) -> config.SessionConfig:
    return config.load(TASK_SPACE / f"{name}.yaml", list(overrides))


@pytest.mark.parametrize("delay_ms", [0, 50])
@pytest.mark.parametrize("name, n_hsi, n_to", PAIRS, ids=[p[0] for p in PAIRS])
def test_a_pair_follows_and_feels_the_wall(name: str, n_hsi: int, n_to: int, delay_ms: int) -> None:
    """The TO's tool follows the HSI's in x, y (1 mm at 0 ms, 6 mm at 50 ms: the channel's
    motion in 50 ms); held against the wall the operator's force at the tool equals the TO's
    on the wall within 5 % (y, along the wall's normal); the channel's energy >= -1e-9 J."""
    session = Session(pair(name, f"channel.delay_ms={delay_ms}"))
    assert (session.hsi.n, session.to.n, session.n) == (n_hsi, n_to, 2)
    summary, a, follow = run_in_the_plane(session)
    assert follow < (1e-3 if delay_ms == 0 else 6e-3)
    held = a[HELD].mean(axis=0)
    assert held[3] < -3.0  # pressing the wall (N)
    assert held[1] == pytest.approx(held[3], rel=0.05)
    assert summary.min_channel_energy_j >= PASSIVE_J and summary.stopped_early is None
    assert np.isfinite(summary.t_p_total) and np.isfinite(summary.t_tau_total)


M1_OVER_C1 = 0.1 / 2.0  # the SCARA HSI's virtual_mass / kp (configs/task_space/*.yaml)
B = 50.0  # N s/m
STROKE = ("environment=[]", "duration_s=7", "operator.waypoints=" + json.dumps([
    {"t_s": 0.5, "position_m": [0.344, -0.005]}, {"t_s": 3.0, "position_m": [0.344, -0.035]},
    {"t_s": 4.0, "position_m": [0.344, -0.035]}, {"t_s": 6.5, "position_m": [0.344, -0.005]},
]))  # fmt: skip  (3 cm along y, out and back, in free space)


def displayed_ratio(delay_ms: int, channel_mass: bool = True) -> float:
    """The least-squares gain of the operator's force F_h,y on the closed form's
    (Lambda(q) x_dd + b T y_dd) over a free-space stroke of the SCARA HSI driving the UR5
    (with damping, stiffness and offset terms fitted alongside: near 0 in free space);
    ``channel_mass`` False leaves b T out of the closed form."""
    session = Session(pair("scara_ur5_plane", f"channel.delay_ms={delay_ms}", *STROKE))
    m = session.hsi.model
    rows: list[np.ndarray] = []

    def observe(s: Session) -> None:
        q, v = s.hsi.feedback.q, s.hsi.feedback.v
        jac = pin.computeFrameJacobian(m.model, m.data, q, m.ee_frame_id,
                                       pin.LOCAL_WORLD_ALIGNED)[:2]  # fmt: skip
        rows.append(np.concatenate([jac @ v, m.tool_position(q)[:2], s.hsi.mapping.tau_mapped,
                                    jac.ravel()]))  # fmt: skip

    summary = session.run(observer=observe)
    assert summary.min_channel_energy_j >= PASSIVE_J
    a = np.array(rows)
    vel, y, force = a[:, 0:2], a[:, 3] - a[0, 3], a[:, 5]
    acc = np.diff(vel, axis=0, prepend=vel[:1]) / session.dt
    jac = a[:, 6:10].reshape(-1, 2, 2)
    lam = np.linalg.inv(jac @ jac.transpose(0, 2, 1) / M1_OVER_C1)  # per tick
    d = session.cfg.delay_ticks
    t = d * session.dt + (filter_group_delay_s(30.0, session.dt) if d else 0.0)
    closed = np.einsum("kij,kj->ki", lam, acc)[:, 1] + (B * t * acc[:, 1] if channel_mass else 0)
    regressors = np.column_stack([closed, vel[:, 1], y, np.ones(len(a))])
    coef, *_ = np.linalg.lstsq(regressors, force, rcond=None)
    return float(coef[0])


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_the_displayed_mass_in_task_space_is_lambda_plus_b_t(delay_ms: int) -> None:
    """F_h = (Lambda + b T I) x_dd within 5 % (the module's docstring; Lambda ~ 0.37-0.42 kg
    over the stroke, b T = 2.74 kg at 50 ms); at 50 ms the closed form without b T misses by
    more than a factor 5, so the fit tells the channel's mass apart."""
    assert displayed_ratio(delay_ms) == pytest.approx(1.0, abs=0.05)
    if delay_ms:
        assert displayed_ratio(delay_ms, channel_mass=False) > 5.0


IMPAIRMENTS = [*CLASSES, "trace_ramp", "trace_outages"]


@pytest.mark.parametrize("impairment", IMPAIRMENTS)
@pytest.mark.parametrize("name", [p[0] for p in PAIRS])
def test_a_pair_stays_passive_under_every_impairment(
    name: str, impairment: str, tmp_path: Path
) -> None:
    """The study's impairment classes and traces (tests/test_passive_channels.py) on each pair's
    own script, the default channel (reflected wave): both ports' balances and the channel's
    energy >= -1e-9 J, motion bounded, no stop; the network did reach the ports. (With the
    Panda's fingers in its model, reflected ended SCARA -> Panda under reordering in a safety
    stop, a finger at 0.21 m/s against its 0.2: the config locks them.)"""
    assert_passive_under(TASK_SPACE / f"{name}.yaml", impairment, tmp_path, 6.0)


def assert_passive_under(
    path: Path, impairment: str, tmp_path: Path, seconds: float, channel: tuple[str, ...] = ()
) -> None:  # fmt: skip
    """A task-space pair's own script under one of the study's impairment classes or traces,
    the config's channel (with the overrides ``channel``): passive and bounded
    (tests/test_passive_channels.py), no stop, and the network did reach the ports."""
    spec = CLASSES.get(impairment) or {"trace": str(write_traces(tmp_path)[impairment])}
    session = run(path, spec, list(channel), seconds=seconds, sweep=False)
    assert_passive_and_bounded(session)
    link = session.summary.link["to"]
    assert link["lost"] + link["skipped"] > 0


def test_a_pair_of_one_joint_count_in_the_plane_runs_fused_as_read_write() -> None:
    """Two UR5s coupled in the plane (6 joints each, a port of 2): the fused simulated plants
    (their joint count now apart from the port's) give what the read / write path gives, bit
    for bit."""
    ur5 = config.load(TASK_SPACE / "scara_ur5_plane.yaml").to
    overrides = [
        "duration_s=2", "channel.delay_ms=20",
        "to.robot=" + json.dumps({"example_robot": "ur5", "ee_frame": "tool0",
                                  "q0_rad": ur5.robot.q0_rad}),
        "to.virtual_mass=" + json.dumps(ur5.virtual_mass),
        "to.controller=" + json.dumps({"kind": "p", "kp": ur5.controller.kp}),
        "environment=[{kind: wall, point_m: [0.0, 0.08], normal: [0, 1], "
        "stiffness_n_per_m: 5000, damping_n_s_per_m: 20}]",
    ]  # fmt: skip
    cfg = pair("ur5_scara_plane", *overrides)
    fused, plain = Session(cfg), Session(cfg)
    assert fused.fused and (fused.hsi.n, fused.to.n, fused.n) == (6, 6, 2)
    plain.fused = False
    a, b = fused.run(), plain.run()
    assert (a.t_p, a.t_tau, a.channel_energy_j) == (b.t_p, b.t_tau, b.channel_energy_j)
    assert np.array_equal(fused.to.feedback.q, plain.to.feedback.q)
    assert a.t_tau_total > 0 and a.stopped_early is None


def test_a_pose_pair_maps_inside_the_fused_tick_as_the_session_does() -> None:
    """Two UR5s coupled in the pose (6 joints each, a port of 6), pressing on a table: the
    fused plants run both sites' task-space maps inside their last compiled call of the tick
    (``lockstep_fused.next_ticks_mapped``), the read / write path has the session call them
    after the writes; both give the same run, bit for bit, maps and all."""
    ur5 = config.load(TASK_SPACE / "ur5_panda_pose.yaml").hsi
    overrides = [
        "duration_s=3", "channel.delay_ms=20",
        "to.robot=" + json.dumps({"example_robot": "ur5", "ee_frame": "tool0",
                                  "q0_rad": ur5.robot.q0_rad}),
        "to.virtual_mass=" + json.dumps(ur5.virtual_mass),
        "to.controller=" + json.dumps({"kind": "p", "kp": 50.0}),
        "environment=[{kind: wall, point_m: [0.0, 0.0, 0.2], normal: [0, 0, 1], "
        "stiffness_n_per_m: 5000, damping_n_s_per_m: 20}]",
    ]  # fmt: skip
    cfg = pair("ur5_panda_pose", *overrides)
    fused, plain = Session(cfg), Session(cfg)
    assert fused.fused and (fused.hsi.n, fused.to.n, fused.n) == (6, 6, 6)
    assert fused._maps_fused == [] and len(fused._maps) == 2  # (the pair took both maps)
    plain.fused = False
    a, b = fused.run(), plain.run()
    assert (a.t_p, a.t_tau, a.channel_energy_j) == (b.t_p, b.t_tau, b.channel_energy_j)
    for x, y in ((fused.hsi, plain.hsi), (fused.to, plain.to)):
        assert np.array_equal(x.mapping.f, y.mapping.f)
        assert np.array_equal(x.feedback.q, y.feedback.q)
    assert a.t_tau_total > 0 and a.stopped_early is None


# the ratchet in the plane: the SCARA's tool back and forth (3 cm, 2 cm) a stroke a second,
# the clutch pressed for the middle of the return stroke 10 times, then of the forward stroke
# 10 times (tests/test_mapping.py's CLUTCH): the UR5's tool is indexed ~0.25 m in and back out
# (the joint test's 9 cm strokes would index it out of its reach)
RATCHET_SWEEP = [
    {"t_s": 0.5 + k, "position_m": [0.36, 0.0] if k % 2 == 0 else [0.33, -0.02]}
    for k in range(2 * STROKES + 1)
]


def ratchet_in_the_plane(delay_ms: int, *ramp: str) -> tuple[np.ndarray, Summary]:
    """Per tick of the ratchet (SCARA -> UR5, free space): tau_h (N m), the HSI's gain, the
    stored wave energy, the tools' raw x, y (Pinocchio); and the summary."""
    cfg = pair("scara_ur5_plane", f"channel.delay_ms={delay_ms}", "environment=[]",
               f"duration_s={2.0 * STROKES + 1.5}",
               "operator.waypoints=" + json.dumps(RATCHET_SWEEP),
               "operator.clutch=" + json.dumps(CLUTCH), *ramp)  # fmt: skip
    session = Session(cfg)
    h, t = session.hsi.model, session.to.model
    rows: list[np.ndarray] = []
    summary = session.run(observer=lambda s: rows.append(np.concatenate([
        s.hsi.signals.tau, [s.hsi.mapping.gain, s.channel.stored_energy()],
        h.tool_position(s.hsi.feedback.q)[:2], t.tool_position(s.to.feedback.q)[:2],
    ])))  # fmt: skip
    assert summary.stopped_early is None
    assert session.hsi.mapping.engagements == session.to.mapping.engagements == STROKES
    return np.array(rows), summary


def largest_step_after_re_engaging(rows: np.ndarray) -> float:
    starts = re_engaged(rows[:, 2])
    assert len(starts) == STROKES
    window = np.zeros(len(rows), bool)
    for k in starts:
        window[k : k + WINDOW] = True
    step = np.abs(np.diff(rows[:, :2], axis=0)).max(axis=1)
    return float(step[window[1:]].max())


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_twenty_re_engagements_in_the_plane(delay_ms: int) -> None:
    """The clutch in task space, SCARA driving the UR5: 20 re-engagements, after each tau_h
    changes by at most the bound per tick (without the ramp at 50 ms by more); the channel
    never makes energy and is empty when the coupling comes back; the offset is taken up:
    the summary's indexed T_p is over 1000 times below the raw tools' (m^2 s)."""
    rows, summary = ratchet_in_the_plane(delay_ms)
    assert largest_step_after_re_engaging(rows) <= TAU_STEP_BOUND_NM
    assert summary.min_channel_energy_j >= PASSIVE_J
    stored, starts = rows[:, 3], re_engaged(rows[:, 2])
    assert stored[starts - 1].max() <= 1e-9 * max(1.0, stored.max())
    assert delay_ms == 0 or stored.max() > 1e-3
    moved = (rows[:, 4:6] - rows[0, 4:6]) - (rows[:, 6:8] - rows[0, 6:8])
    raw = float((moved**2).sum()) * 1e-3
    assert raw > 1000 * summary.t_p_total
    if delay_ms:
        jumped, _ = ratchet_in_the_plane(delay_ms, "mapping.engage_ramp_s=0",
                                         "mapping.engage_step_nm=1e9")  # fmt: skip
        assert largest_step_after_re_engaging(jumped) > TAU_STEP_BOUND_NM
