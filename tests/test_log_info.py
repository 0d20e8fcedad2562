"""``teleop-rt info LOG [--json]`` (issue 19): start, duration, ticks, topics with message
counts, config name and overrides, backends, complete / cut short / incomplete, the summary's
headline figures; a file that is not a readable log is one line and exit code 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from log_fixtures import START_NS, write_synthetic_log

from teleop_rt.cli import main
from tests.conftest import CONFIGS, ROOT


def info_json(path: Path, capsys) -> dict:
    capsys.readouterr()
    assert main(["info", str(path), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_run_log(tmp_path: Path, capsys) -> None:
    log = tmp_path / "run.mcap"
    argv = ["run", str(CONFIGS / "stiff_wall.yaml"), "--duration", "0.25", "--json"]
    assert main([*argv, "--set", "channel.delay_ms=10", "--log", str(log)]) == 0
    summary = json.loads(capsys.readouterr().out)
    info = info_json(log, capsys)
    assert info["status"] == "complete" and info["cut_reason"] is None
    assert info["ticks"] == 250 and info["duration_s"] == pytest.approx(0.25)
    assert info["start_time_utc"].endswith("Z") and info["start_time_ns"] > 1.7e18
    assert info["delay_ms"] == 10.0 and info["name"] == "stiff_wall"
    assert info["config"] == str(CONFIGS / "stiff_wall.yaml")
    assert info["overrides"] == ["channel.delay_ms=10", "duration_s=0.25"]
    assert info["backends"] == {"hsi": "sim", "to": "sim"}
    assert info["environment"] == ["wall"] and info["profile"] == "ros2"
    assert [(t["topic"], t["messages"]) for t in info["topics"]] == [
        ("/hsi", 250),
        ("/to", 250),
        ("/channel", 250),
        ("/timing", 250),
        # the 3D scene (teleop_rt.recording.scene), in the order first written: the URDF and
        # the fixed transforms once, the moving ones and the hand at 50 Hz, the environment at
        # the start (the tool does not reach the wall within 0.25 s)
        ("/robot_description", 1),
        ("/tf", 1 + 13),
        ("/environment", 1),
        ("/hand_target", 13),
    ]
    headline = info["summary"]
    assert headline["t_p_total"] == summary["t_p_total"]
    assert headline["missed_deadlines"] == summary["timing"]["missed_deadlines"]
    assert main(["info", str(log)]) == 0
    text = capsys.readouterr().out
    for line in ("status", "complete", "--set channel.delay_ms=10", "/timing", "250 msgs"):
        assert line in text, line
    assert "start" in text and info["start_time_utc"] in text


def test_cut_short_and_incomplete(tmp_path: Path, capsys) -> None:
    whole = write_synthetic_log(tmp_path / "whole.mcap", 3000, chunk_size=4096)
    cut = write_synthetic_log(
        tmp_path / "cut.mcap", 3000, chunk_size=4096, finish=False, truncate_bytes=60_000
    )
    info = info_json(cut.path, capsys)
    assert info["status"] == "cut short" and "file ends at byte 60000" in info["cut_reason"]
    assert info["summary"] is None and 0 < info["ticks"] < 3000
    counts = {t["topic"]: t["messages"] for t in info["topics"]}
    assert min(counts.values()) >= info["ticks"]  # what the file holds, before trimming
    # finished by its writer, but no summary: the session never handed it over
    unfinished = write_synthetic_log(tmp_path / "nosummary.mcap", 500, with_summary=False)
    assert info_json(unfinished.path, capsys)["status"] == "incomplete"
    info = info_json(whole.path, capsys)
    assert info["status"] == "complete" and info["start_time_ns"] == START_NS
    assert info["start_time_utc"] == "2026-01-01T00:00:00.123456Z"


def test_a_can_log_names_its_buses(tmp_path: Path, capsys) -> None:
    log = write_synthetic_log(tmp_path / "can.mcap", 100, meta={"backend": "can"})
    info = info_json(log.path, capsys)
    # the fixture's config has no can section: the backend, without bus details
    assert info["backends"] == {"hsi": "can", "to": "can"}


@pytest.mark.parametrize("content", [b"", b"hello, not a log\n", b"\x89MCAP0\r\n\x07garbage"])
def test_a_file_that_is_not_a_log_is_one_line_exit_2(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-m", "teleop_rt", "info", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"teleop-rt: error: {path}: ")


def test_a_missing_file(tmp_path: Path, capsys) -> None:
    assert main(["info", str(tmp_path / "nope.mcap")]) == 2
    assert capsys.readouterr().err.strip().endswith("no such file")
