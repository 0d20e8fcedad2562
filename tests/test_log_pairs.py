"""Logs of heterogeneous pairs (issue 26): each robot with its own joint count, the channel with
its size, and what T_p and T_tau compare at mapped sites (``LogLayout.mapped``), so that a log of
SCARA -> Panda, SCARA -> UR5 or UR5 -> SCARA in the plane reads back as the session had it,
its metrics are the live figures bit for bit, and info, plot and replay take it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.cli import main
from teleop_rt.recording.metrics import agrees_with_live, log_metrics
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.recording.replay import build_replay
from teleop_rt.recording.schema import LogLayout
from teleop_rt.session import Session
from tests.conftest import CONFIGS

# (config, HSI joints, TO joints); 1.2 s: the hand reaches the wall at about 0.95 s
PAIRS = [("scara_panda_plane", 2, 7), ("ur5_scara_plane", 6, 2), ("scara_ur5_plane", 2, 6)]
SHORT = ["duration_s=1.2"]


def recorded(name: str, path: Path, *overrides: str):
    """Run the pair with a log; the session (its final state) and its summary."""
    cfg = config.load(CONFIGS / "task_space" / f"{name}.yaml", [*SHORT, *overrides])
    session = Session(cfg)
    rows: list[np.ndarray] = []

    def observe(s: Session) -> None:
        rows.append(np.concatenate([s.hsi.mapping.q_mapped, s.to.mapping.q_mapped]))

    summary = session.run(recorder=Recorder(session, path), observer=observe)
    return session, summary, np.array(rows)


@pytest.mark.parametrize("delay_ms", [0, 50])
@pytest.mark.parametrize("name, n_hsi, n_to", PAIRS, ids=[p[0] for p in PAIRS])
def test_a_pair_records_each_robot_with_its_joints(tmp_path, name, n_hsi, n_to, delay_ms):
    """Each robot's q has its own length and ends where the session's robot ended (exactly);
    the mapped positions are the session's tick by tick; T_p and T_tau from the log alone
    equal the live summary's bit for bit (in the plane: m^2 s and N^2 s)."""
    path = tmp_path / f"{name}.mcap"
    session, summary, mapped = recorded(name, path, f"channel.delay_ms={delay_ms}")
    data = read_log(path)
    assert data.layout == LogLayout(2, 1, "", n_hsi, n_to, True)
    assert (data.meta["joints"], data.meta["joints_hsi"], data.meta["joints_to"]) == (
        "2", str(n_hsi), str(n_to))  # fmt: skip
    hsi, to, channel = (data.topics[t] for t in ("/hsi", "/to", "/channel"))
    assert hsi["q"].shape == (summary.ticks, n_hsi) and to["q"].shape == (summary.ticks, n_to)
    assert channel["omega_c"].shape == (summary.ticks, 2)
    assert np.array_equal(hsi["q"][-1], session.hsi.feedback.q)
    assert np.array_equal(to["q"][-1], session.to.feedback.q)
    assert np.array_equal(to["tau_cmd"][-1], session.to.computed_torque.tau)
    assert np.array_equal(hsi["q_mapped"], mapped[:, :2])
    assert np.array_equal(to["q_mapped"], mapped[:, 2:])
    m = log_metrics(data)
    assert m["t_p"] == summary.t_p and m["t_tau"] == summary.t_tau
    assert min(summary.t_tau) > 0  # pressing the wall: a figure that is not trivially 0
    assert agrees_with_live(m, data.summary) is True


def test_a_scaled_joint_session_logs_what_its_metrics_compare(tmp_path) -> None:
    """Joint to joint with alpha = 0.2, beta = 5: the log's metrics are the live scaled figures
    (before, the log's raw q_h and tau_e gave other ones)."""
    cfg = config.load(CONFIGS / "free_space.yaml", ["duration_s=1", "mapping.motion_scale=0.2",
                                                    "mapping.force_scale=5"])  # fmt: skip
    session = Session(cfg)
    summary = session.run(recorder=Recorder(session, tmp_path / "scaled.mcap"))
    data = read_log(tmp_path / "scaled.mcap")
    assert data.layout == LogLayout(2, len(cfg.environment), "", 2, 2, True)
    m = log_metrics(data)
    assert m["t_p"] == summary.t_p and m["t_tau"] == summary.t_tau
    assert sum(m["t_p"]) > 0


def test_a_joint_space_log_keeps_its_layout(tmp_path) -> None:
    """The joint-space configs' logs are as before: no new metadata keys, no new fields."""
    cfg = config.load(CONFIGS / "stiff_wall.yaml", ["duration_s=0.05"])
    session = Session(cfg)
    session.run(recorder=Recorder(session, tmp_path / "wall.mcap"))
    data = read_log(tmp_path / "wall.mcap")
    assert data.layout == LogLayout(2, len(cfg.environment)) and data.layout.plain
    assert data.channel_space() == "joint"
    assert not {"joints_hsi", "joints_to", "mapped"} & set(data.meta)
    assert [f.name for f in data.layout.topics[0].fields] == [
        "tick", "t", "q", "v", "tau_ext", "tau_cmd", "a_ref", "operator_reference_m",
        "operator_reference_velocity_m_s", "operator_force_n",
    ]  # fmt: skip


def test_metrics_info_plot_and_replay_of_a_pair_log(tmp_path, capsys) -> None:
    """The CLI on a Panda pair's log: run records it (no refusal), metrics agree with the live
    summary, info and plot read it, and a replay reproduces every logged field bit for bit."""
    log, again = tmp_path / "panda.mcap", tmp_path / "again.mcap"
    cfg = str(CONFIGS / "task_space" / "scara_panda_plane.yaml")
    assert main(["run", cfg, "--set", SHORT[0], "--log", str(log)]) == 0
    live = capsys.readouterr().out
    assert "T_p per axis (m^2 s)" in live and "T_tau per axis (N^2 s)" in live
    assert main(["metrics", str(log)]) == 0
    out = capsys.readouterr().out
    assert "agrees exactly" in out  # the plane's figures are named in its units (tool x-y)
    assert "T_p per axis (m^2 s)" in out and "T_tau per axis (N^2 s)" in out
    assert "per joint" not in out
    assert main(["info", str(log)]) == 0
    assert "complete" in capsys.readouterr().out
    assert main(["plot", str(log), "-o", str(tmp_path / "panda.png")]) == 0
    assert (tmp_path / "panda.png").stat().st_size > 0
    data = read_log(log)
    session, ticks = build_replay(data, [])
    session.run(ticks=ticks, recorder=Recorder(session, again))
    replayed = read_log(again)
    for topic in data.layout.topics[:3]:
        for field in topic.fields:
            a, b = data.topics[topic.name][field.name], replayed.topics[topic.name][field.name]
            assert np.array_equal(a, b), f"{topic.name}.{field.name} differs"
