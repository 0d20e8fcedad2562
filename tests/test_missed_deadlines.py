"""Missed deadlines, from outside: the real-time loop is frozen for 100 ms (SIGSTOP, SIGCONT),
as a loaded host would freeze it, and the summary, the log and the exit code agree on what the
deadline guards (``--overrun stop``, ``--max-missed N``) did (issue 18)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from teleop_rt.recording.metrics import log_metrics
from teleop_rt.recording.reader import read_log
from tests.conftest import CONFIGS, START_LIMIT_S

PAPER = CONFIGS / "paper_experiment.yaml"


def frozen_run(log: Path, *args: str) -> tuple[subprocess.Popen, dict]:
    """A 6 s real-time run frozen for 100 ms once it records; its exit and JSON summary."""
    cmd = [sys.executable, "-m", "teleop_rt.cli", "run", str(PAPER), "--realtime", "--json",
           "--duration", "6", "--log", str(log), *args]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + START_LIMIT_S
    # (a run that ends first, stopped by a loaded host's own overrun, is judged as it is)
    while proc.poll() is None:
        assert time.monotonic() < deadline, "the run never reached its loop"
        if log.exists() and log.stat().st_size > 70_000:  # the loop is running
            proc.send_signal(signal.SIGSTOP)
            time.sleep(0.1)
            proc.send_signal(signal.SIGCONT)
            break
        time.sleep(0.02)
    out, err = proc.communicate(timeout=60)
    assert "Traceback" not in err, err
    return proc, json.loads(out)


def test_an_overrun_stop_counts_the_deadline_it_stopped_for(tmp_path: Path) -> None:
    log = tmp_path / "overrun.mcap"
    proc, summary = frozen_run(log, "--overrun", "stop")
    assert proc.returncode == 3 and summary["safety_stop"]
    assert "overran its deadline by" in summary["stopped_early"]
    # the stop and the figures agree: one missed deadline, the late tick counted and logged
    assert summary["timing"]["missed_deadlines"] == 1
    data = read_log(log)
    assert data.ticks == summary["ticks"] and log_metrics(data)["timing"]["missed_deadlines"] == 1


def test_max_missed_stops_at_one_more_than_allowed(tmp_path: Path) -> None:
    log = tmp_path / "missed.mcap"
    proc, summary = frozen_run(log, "--max-missed", "5")  # 100 ms frozen: ~100 ticks late
    assert proc.returncode == 3 and summary["safety_stop"]
    assert "6 deadlines missed, more than the 5 allowed" in summary["stopped_early"]
    assert summary["timing"]["missed_deadlines"] == 6
    assert log_metrics(read_log(log))["timing"]["missed_deadlines"] == 6


def test_max_missed_within_the_limit_is_a_complete_run(tmp_path: Path) -> None:
    proc, summary = frozen_run(tmp_path / "ok.mcap", "--max-missed", "100000")
    assert proc.returncode == 0 and summary["stopped_early"] is None
    assert summary["ticks"] == 6000 and 0 < summary["timing"]["missed_deadlines"] <= 100000


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--max-missed", "3"], "needs --realtime"),
        (["--realtime", "--max-missed", "-1"], "whole number >= 0"),
        (["--realtime", "--max-missed", "x"], "whole number >= 0"),
    ],
)
def test_max_missed_arguments(args: list[str], named: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "teleop_rt.cli", "run", str(PAPER), "--no-log", *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2 and named in done.stderr and "Traceback" not in done.stderr
