"""Recording never holds the robot, and a lost log is never reported as success (issue 18).

From outside, as an operating system would: the CLI runs as a subprocess; its log writer (the
child named ``teleop-rt-log``) is stopped (SIGSTOP), killed, or given no room to write (a 2 MB
tmpfs, RLIMIT_FSIZE). The loop keeps its ticks (a run with a stopped writer still runs every
tick of its duration), rows it could not hand over are counted and their ticks named, the log
says where its gap is, and the exit code is 4. In-process tests pin the counts exactly.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from teleop_rt import config
from teleop_rt.recording import recorder as recorder_module
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.recording.writer import PROCESS_NAME
from teleop_rt.session import Session
from tests.conftest import CONFIGS, START_LIMIT_S

PAPER = CONFIGS / "paper_experiment.yaml"
EXIT_LOG_INCOMPLETE = 4


def children_named(parent: int, name: str) -> list[int]:
    """Pids of the processes whose parent is ``parent`` and whose /proc comm is ``name``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            comm = (entry / "comm").read_text().strip()
        except OSError:  # gone meanwhile
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == parent and comm == name:
            found.append(int(entry.name))
    return found


def start_run(
    log: Path, *args: str, realtime: bool = True, on_disk: int = 70_000
) -> tuple[subprocess.Popen, int]:
    """``teleop-rt run`` with --json, once its writer has put ``on_disk`` bytes on disk; and
    the writer's pid."""
    cmd = [sys.executable, "-m", "teleop_rt.cli", "run", str(PAPER), "--json", "--log", str(log),
           *(["--realtime"] if realtime else []), *args]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + START_LIMIT_S
    writers: list[int] = []
    while time.monotonic() < deadline and proc.poll() is None:
        writers = writers or children_named(proc.pid, PROCESS_NAME)
        if writers and log.exists() and log.stat().st_size > on_disk:
            return proc, writers[0]
        time.sleep(0.02)
    proc.kill()
    raise AssertionError(f"no writer at work: {proc.communicate()}")


def finish(proc: subprocess.Popen, writer: int | None = None) -> tuple[dict, str]:
    try:
        out, err = proc.communicate(timeout=90)  # a hang detector, not a timing assertion
    except subprocess.TimeoutExpired:
        for pid in (proc.pid, writer):  # leave no hung run nor stopped writer behind
            with contextlib.suppress(ProcessLookupError, TypeError):
                os.kill(pid, signal.SIGKILL)
        proc.communicate()
        raise
    assert "Traceback" not in err, err
    return json.loads(out), err


def assert_says_incomplete(err: str, log: Path, *why: str) -> None:
    lines = [line for line in err.splitlines() if "incomplete" in line]
    assert len(lines) == 1 and str(log) in lines[0], err
    for text in why:
        assert text in lines[0], lines[0]


# --- a stalled writer ---------------------------------------------------------------------------
def test_a_writer_stopped_for_good_does_not_stop_the_loop(tmp_path: Path) -> None:
    log = tmp_path / "stopped.mcap"
    continue_ = ("--set", "recording.on_loss=continue")
    proc, writer = start_run(log, "--duration", "8", "--set", "recording.ring_s=0.5", *continue_)
    os.kill(writer, signal.SIGSTOP)  # and never resumed: a loop that waits would never end
    summary, err = finish(proc, writer)
    assert proc.returncode == EXIT_LOG_INCOMPLETE, err
    assert summary["ticks"] == 8000 and summary["stopped_early"] is None
    status = summary["recording"]
    (first, last), dropped = status["gaps"][0], status["dropped_rows"]
    assert len(status["gaps"]) == 1 and last == 7999 and dropped == 8000 - first > 1000
    assert "ring was full" in status["failure"] and "killed" in status["failure"]
    assert_says_incomplete(err, log, "ring was full", f"ticks dropped: {dropped}")


def test_a_stalled_writer_leaves_a_marked_gap(tmp_path: Path) -> None:
    log = tmp_path / "stalled.mcap"
    continue_ = ("--set", "recording.on_loss=continue")
    proc, writer = start_run(log, "--duration", "8", "--set", "recording.ring_s=0.5", *continue_)
    os.kill(writer, signal.SIGSTOP)
    time.sleep(2.5)  # five times the ring: rows are being dropped
    os.kill(writer, signal.SIGCONT)
    summary, err = finish(proc, writer)
    assert proc.returncode == EXIT_LOG_INCOMPLETE, err
    assert summary["ticks"] == 8000 and summary["stopped_early"] is None
    status = summary["recording"]
    assert not status["complete"] and status["dropped_rows"] > 500
    assert status["failure"].startswith("the log writer fell 500 rows behind")
    assert_says_incomplete(err, log, "ring was full", f"ticks dropped: {status['dropped_rows']}")
    # the writer resumed: the log holds the ticks before and after the gap, and knows the gap
    data = read_log(log)
    assert not data.truncated and data.summary["recording"]["gaps"] == status["gaps"]
    assert [list(g) for g in data.gaps] == status["gaps"]
    assert data.ticks + data.missing_ticks == 8000 == data.ticks + status["dropped_rows"]
    first, last = status["gaps"][0]
    assert 0 < first and last < 7999  # recording went on after the gap
    metrics = subprocess.run(
        [sys.executable, "-m", "teleop_rt.cli", "metrics", str(log), "--json"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert metrics.returncode == 0 and "ticks missing" in metrics.stderr
    figures = json.loads(metrics.stdout)
    assert figures["gaps"] == status["gaps"] and figures["live_summary_agrees"] is None
    replay = subprocess.run(
        [sys.executable, "-m", "teleop_rt.cli", "replay", str(log), "--no-log", "--json"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert replay.returncode == 0, replay.stderr
    assert f"replayed its first {first} ticks" in replay.stderr
    assert json.loads(replay.stdout)["replay"]["ticks"] == first


def test_by_default_a_stalled_writer_stops_the_session(tmp_path: Path) -> None:
    log = tmp_path / "stop.mcap"
    proc, writer = start_run(log, "--duration", "8", "--set", "recording.ring_s=0.5")
    os.kill(writer, signal.SIGSTOP)
    summary, err = finish(proc, writer)
    assert proc.returncode == EXIT_LOG_INCOMPLETE, err
    assert summary["stopped_early"].startswith("recording failed: the log writer fell 500 rows")
    status = summary["recording"]
    # the first row that found no room stopped the run at that tick's end
    assert status["dropped_rows"] == 1 and status["gaps"] == [[summary["ticks"] - 1] * 2]
    assert summary["ticks"] < 8000
    assert "killed" in status["failure"]  # it never resumed: ended after the bounded wait
    assert_says_incomplete(err, log, "ring was full")
    assert read_log(log).truncated  # what reached the disk is readable


@pytest.mark.parametrize("twice", [False, True], ids=["ctrl-c", "ctrl-c-twice"])
def test_ctrl_c_with_a_stalled_writer_ends_the_run(tmp_path: Path, twice: bool) -> None:
    log = tmp_path / "int.mcap"
    proc, writer = start_run(log, "--duration", "60")
    os.kill(writer, signal.SIGSTOP)  # the default ring (64 s) does not fill
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    if twice:  # the second while the first waits for the writer to finish the log
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
    summary, err = finish(proc, writer)
    assert proc.returncode == EXIT_LOG_INCOMPLETE, err
    assert summary["stopped_early"] == "stopped by SIGINT" and summary["ticks"] < 60_000
    why = "a second interrupt" if twice else "no progress for 3 s while finishing"
    assert why in summary["recording"]["failure"]
    assert summary["recording"]["dropped_rows"] == 0
    assert_says_incomplete(err, log, why)
    assert not Path(f"/proc/{writer}").exists()  # killed and reaped, not left behind


# --- a dead writer ------------------------------------------------------------------------------
@pytest.mark.parametrize("realtime", [True, False], ids=["realtime", "fast"])
def test_a_killed_writer_is_a_recording_failure(tmp_path: Path, realtime: bool) -> None:
    log = tmp_path / "killed.mcap"
    # a few finished chunks on disk (a chunk is about 80 kB)
    duration = "20" if realtime else "600"
    proc, writer = start_run(log, "--duration", duration, realtime=realtime, on_disk=300_000)
    os.kill(writer, signal.SIGKILL)
    summary, err = finish(proc)  # a summary, not exit 1 without one
    assert proc.returncode == EXIT_LOG_INCOMPLETE, err
    assert summary["stopped_early"].startswith("recording failed: the log writer was killed by")
    assert "SIGKILL" in summary["recording"]["failure"]
    assert_says_incomplete(err, log, "SIGKILL")
    data = read_log(log)
    assert data.truncated and 0 < data.ticks < summary["ticks"]


# --- no room on disk ----------------------------------------------------------------------------
def _no_room_run(log: Path, *args: str, **popen) -> tuple[subprocess.Popen, dict, str]:
    """A fast 60 s run: about 20 MB of log."""
    cmd = [sys.executable, "-m", "teleop_rt.cli", "run", str(PAPER), "--json", "--log", str(log),
           "--duration", "60", *args]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)
    summary, err = finish(proc)
    return proc, summary, err


def _assert_write_failure(log: Path, proc, summary: dict, err: str, strerror: str) -> None:
    assert proc.returncode == EXIT_LOG_INCOMPLETE, err
    assert len(err.splitlines()) == 1, err[:2000]  # one line, not one per message
    assert_says_incomplete(err, log, f"cannot write {log} ({strerror})")
    assert summary["stopped_early"].startswith(f"recording failed: cannot write {log}")
    assert summary["ticks"] < 60_000
    data = read_log(log)  # every chunk written before the error
    assert data.truncated and data.ticks > 1000
    # the rows the writer had taken but not put on disk are not in dropped_rows: the line
    # says what the file holds, read back
    assert_says_incomplete(err, log, f"; the file holds {data.ticks} ticks)")


def test_a_full_disk_is_one_line_and_a_recording_failure(tmp_path: Path) -> None:
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a 2 MB tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        log = mnt / "full.mcap"
        proc, summary, err = _no_room_run(log)
        _assert_write_failure(log, proc, summary, err, "No space left on device")
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def test_a_file_size_limit_is_a_recording_failure(tmp_path: Path) -> None:
    """The same fault without root: RLIMIT_FSIZE makes writes past 2 MB fail (EFBIG)."""

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a failed write, not a killed process
        resource.setrlimit(resource.RLIMIT_FSIZE, (2_000_000, resource.RLIM_INFINITY))

    log = tmp_path / "limited.mcap"
    # the ring is a file in /dev/shm too: the default (64 s, 31 MB) does not fit, in one line
    big = subprocess.run(
        [sys.executable, "-m", "teleop_rt.cli", "run", str(PAPER), "--log", str(log)],
        capture_output=True, text=True, timeout=120, preexec_fn=limit,
    )  # fmt: skip
    assert big.returncode == 1 and len(big.stderr.splitlines()) == 1, big.stderr
    assert "recording.ring_s" in big.stderr and not log.exists()
    proc, summary, err = _no_room_run(log, "--set", "recording.ring_s=2", preexec_fn=limit)
    _assert_write_failure(log, proc, summary, err, "File too large")


# --- the counts, in process ---------------------------------------------------------------------
def stopped_writer_session(tmp_path: Path, on_loss: str) -> tuple[Session, Recorder]:
    cfg = config.load(PAPER, ["duration_s=1", f"recording.on_loss={on_loss}"])
    session = Session(cfg)
    recorder = Recorder(session, tmp_path / "a.mcap", capacity=64)
    os.kill(recorder.process.pid, signal.SIGSTOP)  # before any row is published
    return session, recorder


def test_rows_that_find_the_ring_full_are_dropped_and_counted(tmp_path: Path) -> None:
    session, recorder = stopped_writer_session(tmp_path, "continue")
    try:
        summary = session.run(
            observer=lambda s: s.tick == 500 and _resume(recorder), recorder=recorder
        )
    finally:
        _resume(recorder)
    status = recorder.status()
    assert summary.ticks == 1000 and summary.stopped_early is None
    # the ring took ticks 0-63; 64 until the writer ran again were dropped; then it caught up
    first, last = status["gaps"][0]
    assert first == 64 and status["dropped_rows"] == sum(b - a + 1 for a, b in status["gaps"])
    assert last >= 499 and not status["complete"]
    data = read_log(tmp_path / "a.mcap")
    assert [list(g) for g in data.gaps] == status["gaps"]
    assert data.ticks == 1000 - status["dropped_rows"]


def test_the_first_dropped_row_stops_the_session_by_default(tmp_path: Path) -> None:
    session, recorder = stopped_writer_session(tmp_path, "stop")
    close = recorder.close
    recorder.close = lambda summary: _resume(recorder) or close(summary)  # let it finish
    try:
        summary = session.run(recorder=recorder)
    finally:
        _resume(recorder)
    status = recorder.status()
    assert summary.ticks == 65 and summary.stopped_early.startswith("recording failed")
    assert status["dropped_rows"] == 1 and status["gaps"] == [[64, 64]]
    assert read_log(tmp_path / "a.mcap").ticks == 64


def test_closing_a_stalled_writer_is_bounded(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(recorder_module, "CLOSE_STALL_S", 0.3)
    session, recorder = stopped_writer_session(tmp_path, "stop")
    session.run(ticks=10, recorder=recorder)  # returns: the writer is killed, not waited for
    status = recorder.status()
    assert recorder.process.exitcode == -signal.SIGKILL
    assert "no progress for 0.3 s while finishing" in status["failure"]
    assert not status["complete"] and status["dropped_rows"] == 0


def _resume(recorder: Recorder) -> None:
    if recorder.process.exitcode is None:
        os.kill(recorder.process.pid, signal.SIGCONT)
