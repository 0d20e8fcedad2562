"""``teleop-rt run --can-log PATH``: every frame of every CAN bus, written by python-can's own
writers and read back by python-can's reader, on the emulated CAN backend."""

from __future__ import annotations

import json
import subprocess
import sys

import can
import pytest
from can.util import channel2int
from conftest import ROOT

from teleop_rt.cli import main
from teleop_rt.hal.can import codec
from teleop_rt.hal.can.canlog import CanLog

CONFIG = "configs/paper_experiment.yaml"
EMULATED = ["--backend", "can", "--set", "can.emulate=true"]
NODES = (1, 2)  # the default drives of each robot (can.hsi / can.to)


def frames(path) -> list[can.Message]:
    return list(can.LogReader(str(path)))


def check_session_frames(read: list[can.Message], ticks: int) -> None:
    """SYNC and RPDOs sent and TPDOs received on both buses."""
    for channel in (0, 1):  # HSI, TO
        mine = [m for m in read if channel2int(m.channel) == channel]  # .log says 'can0'
        sync = [m for m in mine if m.arbitration_id == codec.COB_ID_SYNC and not m.is_rx]
        assert len(sync) >= ticks  # one per tick, more during start-up and stop
        for node in NODES:
            rpdo = [m for m in mine if m.arbitration_id == codec.rpdo1_cob_id(node)]
            tpdo = [m for m in mine if m.arbitration_id == codec.tpdo1_cob_id(node)]
            assert len(rpdo) >= ticks and not any(m.is_rx for m in rpdo)
            assert len(tpdo) >= ticks and all(m.is_rx for m in tpdo)
            assert all(len(m.data) == 8 for m in tpdo)  # position and velocity


def test_can_log_of_a_session_reads_back_with_python_can(tmp_path):
    log = tmp_path / "bus.asc"
    proc = subprocess.run(
        [sys.executable, "-m", "teleop_rt", "run", CONFIG, *EMULATED, "--duration", "0.2",
         "--no-log", "--json", "--can-log", str(log)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    status = json.loads(proc.stdout)["can_log"]
    assert status == {"path": str(log), "frames": status["frames"], "dropped_frames": 0,
                      "complete": True, "failure": None}  # fmt: skip
    read = frames(log)
    assert len(read) == status["frames"]
    check_session_frames(read, 200)


@pytest.mark.parametrize("suffix", [".blf", ".log"])
def test_other_formats_by_extension(tmp_path, suffix, capsys):
    log = tmp_path / f"bus{suffix}"
    args = ["run", CONFIG, *EMULATED, "--duration", "0.1", "--no-log", "--json"]
    assert main([*args, "--can-log", str(log)]) == 0
    status = json.loads(capsys.readouterr().out)["can_log"]
    read = frames(log)
    assert len(read) == status["frames"] and status["complete"]
    check_session_frames(read, 100)


def test_the_ring_keeps_frame_contents_and_counts_what_it_drops(tmp_path):
    """A stalled writer (stopped with SIGSTOP) and a tiny ring: frames past its room are
    dropped and counted, never waited for; the rest reach the file bit for bit."""
    import os
    import signal

    log = CanLog(tmp_path / "x.asc", capacity=8)
    os.kill(log.process.pid, signal.SIGSTOP)
    tap = log.tap("to")
    sent = [
        can.Message(arbitration_id=0x181 + k, data=bytes([k, 2 * k, 255]), is_extended_id=False)
        for k in range(12)
    ]
    for k, msg in enumerate(sent):
        tap(msg, k % 2 == 1, 1000.0 + k)
    os.kill(log.process.pid, signal.SIGCONT)
    status = log.close()
    assert status["frames"] == 8 and status["dropped_frames"] == 4 and not status["complete"]
    read = frames(log.path)
    assert [(m.arbitration_id, bytes(m.data), m.is_rx, m.channel) for m in read] == [
        (m.arbitration_id, bytes(m.data), k % 2 == 1, 1) for k, m in enumerate(sent[:8])
    ]


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        (["--can-log", "x.mp3"], "--can-log x.mp3"),
        (["--can-log", "/nonexistent/d/x.asc"], "/nonexistent/d"),
    ],
)
def test_bad_can_log_paths_are_one_line(extra, named, capsys):
    assert main(["run", CONFIG, *EMULATED, "--duration", "0.01", "--no-log", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and named in err[0], err


def test_an_existing_can_log_is_never_overwritten(tmp_path, capsys):
    log = tmp_path / "old.asc"
    log.write_text("keep me")
    assert main(["run", CONFIG, *EMULATED, "--duration", "0.01", "--can-log", str(log)]) == 2
    assert log.read_text() == "keep me"
    assert "exists" in capsys.readouterr().err


def test_can_log_without_a_can_backend_says_so(tmp_path, capsys):
    log = tmp_path / "x.asc"
    assert main(["run", CONFIG, "--duration", "0.01", "--no-log", "--can-log", str(log)]) == 2
    assert "no robot runs on the can backend" in capsys.readouterr().err
    assert not log.exists()


def test_a_can_log_that_cannot_be_written_is_incomplete_exit_4(tmp_path):
    """RLIMIT_FSIZE makes the writer's writes past 3 MB fail (EFBIG): the session runs on, the
    CAN log is reported incomplete in one line, exit code 4."""
    import resource
    import signal

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a failed write, not a killed process
        resource.setrlimit(resource.RLIMIT_FSIZE, (3_000_000, resource.RLIM_INFINITY))

    log = tmp_path / "bus.txt"  # python-can's Printer: about 150 bytes a frame
    proc = subprocess.run(
        [sys.executable, "-m", "teleop_rt", "run", CONFIG, *EMULATED, "--duration", "1.5",
         "--no-log", "--json", "--can-log", str(log)],
        cwd=ROOT, capture_output=True, text=True, timeout=300, preexec_fn=limit,
    )  # fmt: skip
    assert proc.returncode == 4, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["ticks"] == 1500
    status = summary["can_log"]
    assert not status["complete"] and "File too large" in status["failure"]
    lines = [x for x in proc.stderr.splitlines() if "CAN log" in x]
    assert lines == [f"teleop-rt: CAN log {log} is incomplete: {status['failure']} "
                     "(frames dropped: 0)"]  # fmt: skip
    assert 2_000_000 < log.stat().st_size <= 3_000_000
