"""A reader that closes stdout (``teleop-rt run --json | head``, ``| true``) never changes the
exit code a command earned: from outside, with a real pipe whose read end is closed before the
command writes, a safety stop still exits 3, a complete run 0, a site 0, ``info`` and
``metrics`` 0; stderr says it in one line; the log is finished all the same."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import CONFIGS

PAPER = CONFIGS / "paper_experiment.yaml"
FAULT = "plant.faults=[{kind: nan, robot: to, joint: 1, start_s: 0.5, magnitude: 1.0}]"
CLOSED = "stdout was closed by its reader"


def closed_stdout(*argv: str, cwd: Path | None = None) -> tuple[int, str]:
    """``teleop-rt ARGV`` with a stdout whose reader is gone: its exit code and stderr."""
    read, write = os.pipe()
    os.close(read)  # the reader left before the first write: every write meets EPIPE
    try:
        proc = subprocess.Popen([sys.executable, "-m", "teleop_rt", *argv], stdout=write,
                                stderr=subprocess.PIPE, text=True, cwd=cwd)  # fmt: skip
    finally:
        os.close(write)
    _, err = proc.communicate(timeout=240)
    return proc.returncode, err


def assert_one_closed_line(err: str) -> None:
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert len([x for x in err.splitlines() if CLOSED in x]) == 1, err


def info(log: Path) -> dict:
    out = subprocess.run([sys.executable, "-m", "teleop_rt", "info", str(log), "--json"],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.mark.parametrize("as_json", [True, False])
def test_a_safety_stop_stays_exit_3(tmp_path: Path, as_json: bool) -> None:
    log = tmp_path / "stop.mcap"
    code, err = closed_stdout("run", str(PAPER), "--duration", "1", "--set", FAULT,
                              "--log", str(log), *(["--json"] if as_json else []))  # fmt: skip
    assert code == 3, err
    assert_one_closed_line(err)
    held = info(log)
    assert held["status"] == "complete" and held["summary"]["safety_stop"], held


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("closed") / "run.mcap"
    code, err = closed_stdout("run", str(PAPER), "--duration", "0.5", "--json", "--log", str(path))
    assert code == 0, err  # a complete run stays 0
    assert_one_closed_line(err)
    return path


@pytest.mark.parametrize("command", [["info"], ["info", "--json"], ["metrics"],
                                     ["metrics", "--json"]])  # fmt: skip
def test_info_and_metrics_exit_0(log: Path, command: list[str]) -> None:
    code, err = closed_stdout(command[0], str(log), *command[1:])
    assert code == 0, err
    assert_one_closed_line(err)


def test_a_site_keeps_its_exit_code(tmp_path: Path) -> None:
    """Two sites for a second; the HSI's stdout is closed: it exits 0 like its peer."""
    pytest.importorskip("zenoh")
    from tests.test_zenoh_sites import PATIENT, endpoints, free_port

    port = free_port()
    common = ["--duration", "1", "--json", "--set", "channel.delay_ms=20", *PATIENT,
              *endpoints(port)]  # fmt: skip
    to = subprocess.Popen([sys.executable, "-m", "teleop_rt", "site", "to", str(PAPER), *common,
                           "--log", str(tmp_path / "s.to.mcap")], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        code, err = closed_stdout("site", "hsi", str(PAPER), *common, "--log",
                                  str(tmp_path / "s.hsi.mcap"))  # fmt: skip
        to_out, to_err = to.communicate(timeout=120)
    finally:
        if to.poll() is None:
            to.kill()
    assert to.returncode == 0 and json.loads(to_out)["ticks"] == 1000, to_err
    assert code == 0, err
    assert_one_closed_line(err)
    assert info(tmp_path / "s.hsi.mcap")["status"] == "complete"
