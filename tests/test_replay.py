"""Replay: the logged operator input re-drives the rebuilt session tick-locked; no overrides
reproduce the log bit for bit, a longer delay answers the counterfactual."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.cli import main
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.recording.replay import build_replay, replay_operator
from teleop_rt.session import Session
from tests.conftest import CONFIGS

COMPARED = {
    "/hsi": ("q", "v", "tau_ext", "tau_cmd", "a_ref", "operator_reference_m", "operator_force_n"),
    "/to": ("q", "v", "tau_ext", "tau_cmd", "a_ref", "environment_force_n", "in_contact"),
    "/channel": ("omega_c", "tau_c", "omega_t", "tau_t", "u_l", "v_l", "energy"),
}


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "orig.mcap"
    cfg = config.load(CONFIGS / "paper_experiment.yaml", ["duration_s=6", "channel.delay_ms=20"])
    session = Session(cfg)
    session.run(recorder=Recorder(session, path))
    return path


def _replay(original: Path, out: Path, *overrides: str):
    data = read_log(original)
    session, ticks = build_replay(data, list(overrides))
    summary = session.run(ticks=ticks, recorder=Recorder(session, out))
    return data, read_log(out), summary


def test_replay_without_overrides_is_bit_exact(original: Path, tmp_path: Path) -> None:
    data, again, summary = _replay(original, tmp_path / "same.mcap")
    assert summary.ticks == len(data.topics["/hsi"]) == 6000
    for topic, fields in COMPARED.items():
        for name in fields:
            a, b = data.topics[topic][name], again.topics[topic][name]
            assert np.array_equal(a, b), f"{topic}.{name} differs"
    assert summary.t_p == data.summary["t_p"] and summary.t_tau == data.summary["t_tau"]


def test_replay_with_a_longer_delay_raises_t_p(original: Path, tmp_path: Path) -> None:
    data, delayed, summary = _replay(original, tmp_path / "d100.mcap", "channel.delay_ms=100")
    assert delayed.meta["delay_ticks"] == "100"
    assert summary.t_p_total > 3 * sum(data.summary["t_p"])
    # the operator's input is the same: the logged hand reference is replayed as it was
    ref = data.topics["/hsi"]["operator_reference_m"]
    assert np.array_equal(delayed.topics["/hsi"]["operator_reference_m"], ref)


def test_a_log_without_operator_model_replays_the_hsi_tool_motion(original: Path) -> None:
    data = read_log(original)
    data.meta["operator"] = "none"  # as a log from hardware with a person at the handle
    cfg = config.from_dict(__import__("yaml").safe_load(data.config_yaml))
    hand = replay_operator(cfg, data)
    session = Session(cfg)
    # the reference at tick k is the HSI's logged tool position at tick k
    k = 2500
    hand.trajectory.evaluate(k * cfg.dt)
    tool = session.hsi.model.ee_position(data.topics["/hsi"]["q"][k])
    np.testing.assert_allclose(hand.trajectory.pos, tool, atol=1e-12)


def test_replay_cli_prints_both_and_refuses_to_overwrite(original: Path, tmp_path: Path, capsys):
    out = tmp_path / "cli.mcap"
    assert main(["replay", str(original), "--set", "channel.delay_ms=50", "--log", str(out)]) == 0
    text = capsys.readouterr().out
    assert "original (log)" in text and "replay" in text and out.exists()
    assert main(["replay", str(original), "--log", str(original)]) == 2  # never the input
    assert "exists" in capsys.readouterr().err
