"""The workspace mapping (issue 26, teleop_rt.mapping): motion and force scaling, the clutch
and the operator's presence, each kept passive.

Passive is checked as in tests/test_passive_channels.py, to -1e-9 J: the two-port's energy
(eq 7, 8, from the ports' variables), and here also the scaled two-port's, from the robots'
own variables: ``integral of v_h (r tau_c) - (beta / alpha) v_ref tau_e`` (rendered torque
r tau_c = tau_h - the HSI controller's error; velocity reference v_ref = the TO controller's
error + v_t), which the mapping's rule says is the channel's energy plus what the decoupled
TO's matched termination absorbed, tick for tick.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from teleop_rt import config
from teleop_rt.errors import ConfigError
from teleop_rt.session import Session, Summary
from tests.conftest import CONFIGS

PASSIVE_J = -1e-9
ALPHA, BETA = 0.2, 5.0
STROKES = 20
# the hand back and forth, a stroke a second; the clutch pressed for the middle of the
# return stroke 10 times, then of the forward stroke 10 times: the operator ratchets the TO
# out and back (indexing), re-engaging 20 times at speed
SWEEP = [
    {"t_s": 0.5 + k, "position_m": [0.29, -0.005] if k % 2 == 0 else [0.38, 0.035]}
    for k in range(2 * STROKES + 1)
]
CLUTCH = [
    {
        "start_s": (1.6 if k < STROKES // 2 else 0.6) + 2 * k,
        "end_s": (2.3 if k < STROKES // 2 else 1.3) + 2 * k,
    }
    for k in range(STROKES)
]
WINDOW = 400  # ticks after a re-engage that count as its transient
# the most tau_h may change in a tick while the coupling comes back: twice the rendered
# torque's ramp limit engage_step_nm (the rest: the hand's own motion)
ENGAGE_STEP_NM = 0.005
TAU_STEP_BOUND_NM = 2 * ENGAGE_STEP_NM


def load(name: str, *overrides: str) -> config.SessionConfig:
    return config.load(CONFIGS / f"{name}.yaml", list(overrides))


class Trace:
    """Per-tick signals of a session, and the scaled two-port's energy from robot variables."""

    def __init__(self, session: Session) -> None:
        self.s = session
        m = session.to.mapping
        self.power_scale = m.force_scale / m.motion_scale
        self.b = session.to.port.b.copy()
        self.rows: list[np.ndarray] = []
        self.scaled = self.absorbed = 0.0
        self.min_scaled = np.inf

    def __call__(self, s: Session) -> None:
        hsi, to, dt = s.hsi, s.to, s.dt
        rendered = hsi.signals.tau - hsi.signals.error
        v_ref = to.signals.error + to.feedback.v
        p_h = float(hsi.feedback.v @ rendered)
        p_t = float(v_ref @ to.signals.tau)
        self.scaled += (p_h - self.power_scale * p_t) * dt
        self.min_scaled = min(self.min_scaled, self.scaled)
        if to.port.terminated:  # the matched damper tau_t = b omega_t
            self.absorbed += float(self.b @ to.port.flow**2) * dt
        self.rows.append(np.concatenate([
            hsi.signals.tau, to.feedback.v, [hsi.mapping.gain, s.monitor.total_energy],
            hsi.feedback.q, to.feedback.q, to.signals.tau, [s.channel.stored_energy()],
        ]))  # fmt: skip

    def array(self) -> np.ndarray:
        return np.array(self.rows)


def run(cfg: config.SessionConfig) -> tuple[Session, Trace, object]:
    session = Session(cfg)
    trace = Trace(session)
    summary = session.run(observer=trace)
    return session, trace, summary


def re_engaged(gain: np.ndarray) -> np.ndarray:
    """Ticks at which the HSI's coupling gain leaves 0."""
    return np.flatnonzero((gain[1:] > 0) & (gain[:-1] == 0)) + 1


# --- scaling -------------------------------------------------------------------------------
def test_the_identity_is_inactive_and_the_mapped_path_at_one_computes_the_same() -> None:
    """Without mapping the sites skip the map (the reference figures hold it bit for bit);
    the map at alpha = beta = 1 with a clutch that never comes computes the same figures."""
    cfg = load("stiff_wall", "channel.delay_ms=20", "duration_s=3")
    plain = Session(cfg)
    assert not plain.hsi.mapping.active and not plain.to.mapping.active
    a = plain.run()
    later = load("stiff_wall", "channel.delay_ms=20", "duration_s=3",
                 "operator.clutch=[{start_s: 5.0, end_s: 6.0}]")  # fmt: skip
    mapped = Session(later)
    assert mapped.hsi.mapping.active and mapped.to.mapping.active
    b = mapped.run()
    assert (a.t_p, a.t_tau, a.channel_energy_j) == (b.t_p, b.t_tau, b.channel_energy_j)


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_the_to_moves_alpha_times_the_hsi_in_free_space(delay_ms: int) -> None:
    """Free space: tau_t = beta tau_e = 0, so the HSI sees the channel it saw unscaled and the
    TO, linearised by computed torque, moves alpha times as far: T_p is alpha^2 times the
    unscaled session's and T_tau the same (to rounding)."""
    delay = f"channel.delay_ms={delay_ms}"
    session, _, summary = run(
        load("free_space", delay, f"mapping.motion_scale={ALPHA}", f"mapping.force_scale={BETA}")
    )
    plain = Session(load("free_space", delay))
    unscaled = plain.run()
    moved_h = session.hsi.feedback.q - np.array([-0.8, 1.8])
    moved_t = session.to.feedback.q - np.array([-0.8, 1.8])
    np.testing.assert_allclose(moved_h, plain.hsi.feedback.q - np.array([-0.8, 1.8]), rtol=1e-9)
    np.testing.assert_allclose(moved_t, ALPHA * (plain.to.feedback.q - np.array([-0.8, 1.8])),
                               rtol=1e-6)  # fmt: skip
    np.testing.assert_allclose(summary.t_p, np.array(unscaled.t_p) * ALPHA**2, rtol=1e-6)
    np.testing.assert_allclose(summary.t_tau, unscaled.t_tau, rtol=1e-9)


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_the_operator_feels_beta_times_the_wall(delay_ms: int) -> None:
    """Held against the wall (the 5000 N/m wall moved to where the scaled TO reaches it):
    tau_h = beta tau_e at rest, within 5 %; the channel stays passive."""
    cfg = load("stiff_wall", f"channel.delay_ms={delay_ms}", f"mapping.motion_scale={ALPHA}",
               f"mapping.force_scale={BETA}", "environment.0.point_m=[0.0, -0.015]")  # fmt: skip
    session, trace, summary = run(cfg)
    rows = trace.array()
    hold = slice(3500, 3900)  # 3.5-3.9 s: the hand held beyond the wall
    tau_h, tau_e = rows[hold, :2].mean(axis=0), rows[hold, 10:12].mean(axis=0)
    assert np.abs(tau_e).max() > 0.05  # in contact
    np.testing.assert_allclose(tau_h, BETA * tau_e, rtol=0.05, atol=0.005)
    assert summary.min_channel_energy_j >= PASSIVE_J


@settings(max_examples=16, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    delay_ms=st.sampled_from([0, 1, 7, 20, 50]),
    mode=st.sampled_from(
        ["channel.mode=wave", "channel.mode=tdpa", "channel.wave_reconstruction=zero"]
    ),  # fmt: skip
    stiffness=st.sampled_from([500.0, 5000.0]),
    clutch=st.booleans(),
    b=st.sampled_from([0.5, 2.0, 8.0]),
    space=st.sampled_from(["joint", "plane"]),
)
def test_scaled_channel_is_passive(delay_ms, mode, stiffness, clutch, b, space) -> None:
    """alpha = 0.2, beta = 5 against a wall within the scaled TO's reach, with and without a
    clutch, joint to joint or in the plane (b in N s/m there: 25 times, the SCARA's ~0.2 m
    lever squared): the channel's energy >= -1e-9 J, and the scaled two-port's (robot
    variables, the TO's power times beta / alpha) is that energy plus what the matched
    termination took."""
    b_space = b * (25 if space == "plane" else 1)
    overrides = [
        f"channel.delay_ms={delay_ms}", mode, f"channel.wave_impedance={b_space}",
        f"channel.space={space}", "duration_s=3",
        f"mapping.motion_scale={ALPHA}", f"mapping.force_scale={BETA}",
        "environment.0.point_m=[0.0, -0.015]", f"environment.0.stiffness_n_per_m={stiffness}",
    ]  # fmt: skip
    if clutch:
        overrides.append("operator.clutch=[{start_s: 1.2, end_s: 1.7}, {start_s: 2.2, end_s: 2.4}]")
    session, trace, summary = run(load("stiff_wall", *overrides))
    assert summary.min_channel_energy_j >= PASSIVE_J
    assert trace.min_scaled >= PASSIVE_J
    expected = session.monitor.total_energy + trace.absorbed
    assert trace.scaled == pytest.approx(expected, abs=1e-9, rel=1e-6)
    assert trace.absorbed >= 0.0 and (clutch or trace.absorbed == 0.0)


# --- clutch and indexing --------------------------------------------------------------------
def ratchet(delay_ms: int, *extra: str) -> config.SessionConfig:
    return config.from_dict({
        **config.read_yaml(CONFIGS / "free_space.yaml"),
        "duration_s": 2.0 * STROKES + 1.5,
        "channel": {"mode": "wave", "delay_ms": delay_ms, "wave_impedance": 2.0,
                    "wave_filter_hz": 30},
        "operator": {"kind": "hand", "stiffness_n_per_m": 300, "damping_n_s_per_m": 20,
                     "waypoints": SWEEP, "clutch": CLUTCH},
        "mapping": {"engage_step_nm": ENGAGE_STEP_NM,
                    **dict(x.split("=") for x in extra)},  # type: ignore[arg-type]
    }, base_dir=CONFIGS)  # fmt: skip


def test_a_bad_script_is_one_clear_line() -> None:
    for clutch, words in (
        ("[{start_s: 2, end_s: 1}]", "end_s must be after start_s"),
        ("[{start_s: 1, end_s: 3}, {start_s: 2, end_s: 4}]", "must not overlap"),
    ):
        with pytest.raises(ConfigError, match=words) as err:
            load("free_space", f"operator.clutch={clutch}")
        assert "\n" not in str(err.value) and str(err.value).startswith("operator.clutch")


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_twenty_re_engagements_without_a_jump_or_energy_made(delay_ms: int) -> None:
    """The ratchet: 20 clutch releases at full stroke speed. Each site counts 20
    re-engagements; after each, tau_h changes by less than the bound per tick and the TO's
    speed stays within what it reaches while coupled; the channel never makes energy and is
    empty when the coupling comes back; the TO is ratcheted out and back."""
    session, trace, summary = run(ratchet(delay_ms))
    assert session.hsi.mapping.engagements == session.to.mapping.engagements == STROKES
    rows = trace.array()
    tau_h, v_t, gain = rows[:, :2], rows[:, 2:4], rows[:, 4]
    starts = re_engaged(gain)
    assert len(starts) == STROKES
    step = np.abs(np.diff(tau_h, axis=0)).max(axis=1)
    window = np.zeros(len(rows), bool)
    for k in starts:
        window[k : k + WINDOW] = True
    assert step[window[1:]].max() <= TAU_STEP_BOUND_NM
    speed = np.abs(v_t).max(axis=1)
    assert speed[window].max() <= 1.2 * speed[~window].max()
    assert summary.min_channel_energy_j >= PASSIVE_J and trace.min_scaled >= PASSIVE_J
    assert np.ptp(rows[:, 8:10] - rows[:, 6:8], axis=0).max() > 0.5  # ratcheted out and back
    # nothing is replayed: the decoupled TO's matched termination drains the lines, so they
    # are empty when the coupling comes back (a reflecting end would trap the waves)
    stored = rows[:, 12]
    assert stored[starts - 1].max() <= 1e-9 * max(1.0, stored.max())
    assert delay_ms == 0 or stored.max() > 1e-3


def test_without_the_ramp_re_engaging_jumps() -> None:
    """The bound above is the ramp's doing: at 50 ms (free space at 0 ms has no channel
    torque to step; the wall test covers it) re-engaging at once (no ramp, no step limit)
    steps tau_h by more than the bound."""
    _, trace, _ = run(ratchet(50, "engage_ramp_s=0", "engage_step_nm=1e9"))
    rows = trace.array()
    step = np.abs(np.diff(rows[:, :2], axis=0)).max(axis=1)
    starts = re_engaged(rows[:, 4])
    window = np.zeros(len(rows), bool)
    for k in starts:
        window[k : k + WINDOW] = True
    assert step[window[1:]].max() > TAU_STEP_BOUND_NM


def test_the_offset_is_taken_up() -> None:
    """The indexing offset: T_p compares the TO with the HSI's motion the channel carried
    (alpha (q_h - offset) against the TO's q_t + its own offset). With it the ratchet's T_p
    is the channel's own tracking, within a few times the unclutched sweep's; T_p of the
    positions as they are (the offset not taken up) is the ratchet's whole travel."""
    _, trace, summary = run(ratchet(0))
    rows = trace.array()
    moved_h, moved_t = rows[:, 6:8] - rows[0, 6:8], rows[:, 8:10] - rows[0, 8:10]
    raw = float(((moved_h - moved_t) ** 2).sum()) * 1e-3
    unclutched = Session(config.from_dict({
        **config.read_yaml(CONFIGS / "free_space.yaml"), "duration_s": 2.0 * STROKES + 1.5,
        "operator": {"kind": "hand", "stiffness_n_per_m": 300, "damping_n_s_per_m": 20,
                     "waypoints": SWEEP},
    }, base_dir=CONFIGS)).run()  # fmt: skip
    assert sum(summary.t_p) < 3 * sum(unclutched.t_p)
    assert raw > 1000 * sum(summary.t_p)


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_re_engaging_against_the_wall_ramps_the_force_in(delay_ms: int) -> None:
    """Clutched while the TO presses the wall: the TO holds (its speed ~0), the HSI renders
    nothing and the hand pushes it on; on release the wall's torque comes back within the
    bound per tick; without the ramp it steps by ~20 times that."""
    clutch = "operator.clutch=[{start_s: 2.0, end_s: 2.5}, {start_s: 3.0, end_s: 3.3}]"
    for ramp, within in (
        (("mapping.engage_step_nm=0.005",), True),
        (("mapping.engage_ramp_s=0", "mapping.engage_step_nm=1e9"), False),
    ):
        session, trace, summary = run(load("stiff_wall", f"channel.delay_ms={delay_ms}",
                                           clutch, *ramp))  # fmt: skip
        rows = trace.array()
        step = np.abs(np.diff(rows[:, :2], axis=0)).max(axis=1)
        starts = re_engaged(rows[:, 4])
        assert len(starts) == 2
        worst = max(step[k - 1 : k + WINDOW].max() for k in starts)
        assert (worst <= TAU_STEP_BOUND_NM) == within, worst
        held = slice(2000 + delay_ms + 20, 2500 + delay_ms)  # the TO's own decoupled interval
        assert np.abs(rows[held, 2:4]).max() < 1e-3
        assert summary.min_channel_energy_j >= PASSIVE_J


# --- presence -------------------------------------------------------------------------------
def test_presence_lost_briefly_decouples_and_too_long_stops() -> None:
    brief = load("free_space", "operator.absent=[{start_s: 1.0, end_s: 1.4}]",
                 "mapping.presence_timeout_s=0.5")  # fmt: skip
    session, trace, summary = run(brief)
    assert summary.stopped_early is None and session.hsi.mapping.engagements == 1
    gain = trace.array()[:, 4]
    assert (gain[1000:1400] == 0).all() and gain[1400] > 0
    long = load("free_space", "operator.absent=[{start_s: 1.0, end_s: 2.0}]",
                "mapping.presence_timeout_s=0.5")  # fmt: skip
    stopped = Session(long).run()
    assert stopped.safety_stop and "away for more than 0.5 s" in (stopped.stopped_early or "")
    assert stopped.ticks == 1500  # ticks 0-1499 ran; at tick 1500 away for 501 ticks: stop


# --- the plane: each site through its own Jacobian ----------------------------------------------
PLANE = ("channel.space=plane", "channel.wave_impedance=50")  # b in N s/m


def test_in_the_plane_the_to_tool_follows_the_hsi_tool() -> None:
    """Free space, 0 ms: the TO's tool moves as the HSI's does (x, y), and T_p (now of the
    tools' positions, m^2 s) is small against the motion's own square integral."""
    session, trace, summary = run(load("free_space", *PLANE))
    x_h, x_t = session.hsi.mapping.q_mapped, session.to.mapping.q_mapped
    np.testing.assert_allclose(x_h, x_t, atol=1e-3)
    assert session.hsi.model.tool_position(session.hsi.feedback.q)[:2] == pytest.approx(
        session.to.model.tool_position(session.to.feedback.q)[:2], abs=1e-3
    )
    assert sum(summary.t_p) < 1e-5  # (the tool sweeps ~0.09 m for 4 s: ~1e-2 m^2 s)
    assert summary.min_channel_energy_j >= PASSIVE_J


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_in_the_plane_the_operator_feels_beta_times_the_wall_force(delay_ms: int) -> None:
    """Held against the wall, the HSI at rest: tau_h = J_h^T F_c and F_c = beta F_e, so the
    operator's force at the tool (J_h#^T tau_h) is beta times the TO's force on the wall
    (J_t#^T tau_e), within 5 %; with alpha = 0.2 the TO's tool moves 0.2 times as far."""
    cfg = load("stiff_wall", *PLANE, f"channel.delay_ms={delay_ms}",
               f"mapping.motion_scale={ALPHA}", f"mapping.force_scale={BETA}",
               "environment.0.point_m=[0.0, -0.015]")  # fmt: skip
    session = Session(cfg)
    forces: list[np.ndarray] = []
    session.run(observer=lambda s: forces.append(
        np.concatenate([s.hsi.mapping.tau_mapped, s.to.mapping.tau_mapped])))  # fmt: skip
    held = np.array(forces)[3500:3900].mean(axis=0)
    f_h, beta_f_e = held[:2], held[2:]
    assert abs(beta_f_e[1]) > 1.0  # pressing the wall (N, along its normal y)
    np.testing.assert_allclose(f_h, beta_f_e, rtol=0.05, atol=0.05)


def run_in_the_plane(session: Session) -> tuple[Summary, np.ndarray, float]:
    """Run a plane session: its summary, per tick the mapped forces and positions (tau_mapped
    of the HSI, of the TO, then q_mapped of each: 2 columns each), and how far the TO's tool
    moved otherwise than the HSI's from their start (m, largest)."""
    rows: list[np.ndarray] = []
    summary = session.run(observer=lambda s: rows.append(np.concatenate([
        s.hsi.mapping.tau_mapped, s.to.mapping.tau_mapped,
        s.hsi.mapping.q_mapped, s.to.mapping.q_mapped])))  # fmt: skip
    a = np.array(rows)
    follow = float(np.abs((a[:, 4:6] - a[0, 4:6]) - (a[:, 6:8] - a[0, 6:8])).max())
    return summary, a, follow


@pytest.mark.parametrize("delay_ms", [0, 50])
def test_a_scara_drives_a_ur5_in_the_plane(delay_ms: int) -> None:
    """The heterogeneous pair (configs/task_space/scara_ur5_plane.yaml): the UR5's tool
    follows the SCARA's in x, y (within 1 mm at 0 ms, 6 mm at 50 ms), and held against the
    wall the operator's tool force equals the UR5's on the wall within 5 %; passive."""
    cfg = config.load(CONFIGS / "task_space" / "scara_ur5_plane.yaml",
                      [f"channel.delay_ms={delay_ms}"])  # fmt: skip
    session = Session(cfg)
    assert (session.hsi.n, session.to.n, session.n) == (2, 6, 2) and not session.fused
    summary, a, follow = run_in_the_plane(session)
    assert follow < (1e-3 if delay_ms == 0 else 6e-3)
    held = a[3500:3900].mean(axis=0)
    assert abs(held[3]) > 1.0
    np.testing.assert_allclose(held[:2], held[2:4], rtol=0.05, atol=0.05)
    assert summary.min_channel_energy_j >= PASSIVE_J and summary.stopped_early is None


@pytest.mark.parametrize("space", ["joint", "plane"])
def test_sites_alone_over_a_link_map_as_the_lock_step_session(space: str) -> None:
    """What a site in a process of its own runs (its sense / update over a Link) maps exactly
    as the one-process session's fused kernels do, clutch, scaling and plane included."""
    from tests.test_two_sites import sites_alone

    b = 50 if space == "plane" else 2
    cfg = load("stiff_wall", "duration_s=3", "channel.delay_ms=20", f"channel.space={space}",
               f"channel.wave_impedance={b}", f"mapping.motion_scale={ALPHA}",
               f"mapping.force_scale={BETA}", "environment.0.point_m=[0.0, -0.015]",
               "operator.clutch=[{start_s: 1.2, end_s: 1.7}]")  # fmt: skip
    lockstep = Session(cfg)
    alone, link = sites_alone(cfg)
    for k in range(cfg.n_ticks):
        lockstep.step()
        alone.hsi.sense(link)
        alone.to.sense(link)
        alone.hsi.update(link)
        alone.to.update(link)
        for a, b_ in ((lockstep.hsi, alone.hsi), (lockstep.to, alone.to)):
            assert np.array_equal(a.tau_cmd, b_.tau_cmd), k
            assert np.array_equal(a.mapping.f, b_.mapping.f), k
    assert alone.hsi.mapping.engagements == alone.to.mapping.engagements == 1
