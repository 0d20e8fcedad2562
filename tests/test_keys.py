"""The clutch and presence as keys of the terminal, from the outside (``teleop-rt run --realtime
--keys``, ``teleop_rt.keys``): a real-time run on a pseudo-terminal, the keys typed into it;
the log shows the sites decoupled and re-engaged, and the terminal's mode is restored after a
normal end, SIGINT and SIGTERM. Without a terminal on stdin the keys do nothing."""

from __future__ import annotations

import os
import pty
import select
import signal
import subprocess
import sys
import termios
import time
from pathlib import Path

import numpy as np
import pytest

from teleop_rt.cli import main
from teleop_rt.hal.signals import INPUT_CLUTCH, INPUT_PRESENT
from teleop_rt.keys import AT_START, KeyReader
from teleop_rt.recording.reader import read_log
from tests.conftest import CONFIGS, START_LIMIT_S

FOAM = CONFIGS / "foam.yaml"
STARTED_S = START_LIMIT_S


class OnTerminal:
    """``teleop-rt run ... --keys`` with stdin on a pty (stdout and stderr pipes)."""

    def __init__(self, log: Path, seconds: float, *extra: str) -> None:
        self.master, self.slave = pty.openpty()
        self.before = termios.tcgetattr(self.slave)
        cmd = [sys.executable, "-m", "teleop_rt", "run", str(FOAM), "--realtime", "--keys",
               "--duration", str(seconds), "--log", str(log), "--set",
               "channel.delay_ms=20", *extra]  # fmt: skip
        self.proc = subprocess.Popen(cmd, stdin=self.slave, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE)  # fmt: skip
        self.err = b""

    def wait_for(self, text: bytes, timeout: float = STARTED_S) -> None:
        """Until stderr has said ``text``."""
        end = time.monotonic() + timeout
        assert self.proc.stderr is not None
        fd = self.proc.stderr.fileno()
        while text not in self.err:
            left = end - time.monotonic()
            assert left > 0, self.err.decode(errors="replace")
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                chunk = os.read(fd, 4096)
                assert chunk, self.err.decode(errors="replace")  # it ended without saying it
                self.err += chunk

    def mode(self) -> list:
        return termios.tcgetattr(self.slave)

    def type(self, key: bytes) -> None:
        os.write(self.master, key)

    def finish(self) -> int:
        out, err = self.proc.communicate(timeout=120)
        self.err += err
        return self.proc.returncode

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def terminal(tmp_path):
    made: list[OnTerminal] = []

    def start(seconds: float, *extra: str) -> OnTerminal:
        made.append(OnTerminal(tmp_path / "keys.mcap", seconds, *extra))
        return made[-1]

    yield start
    for t in made:
        t.close()


def test_the_clutch_key_decouples_and_re_engages_in_real_time(terminal, tmp_path) -> None:
    """'c' pressed, then space: the HSI's map read the clutch bit between the two (the log's
    inputs and gain 0 on those ticks, the TO decoupled too), and the coupling came back; the
    terminal was in cbreak mode during the run and is as it was afterwards."""
    run = terminal(6.0)
    run.wait_for(b"keys: space or c")
    during = run.mode()
    time.sleep(1.0)
    run.type(b"c")
    run.wait_for(b"clutch pressed")
    time.sleep(0.8)
    run.type(b" ")
    run.wait_for(b"clutch released")
    assert run.finish() == 0, run.err.decode(errors="replace")
    assert run.mode() == run.before  # restored
    assert not during[3] & termios.ICANON and not during[3] & termios.ECHO  # (cbreak meanwhile)
    data = read_log(tmp_path / "keys.mcap")
    hsi, to = data.topics["/hsi"], data.topics["/to"]
    pressed = np.flatnonzero(hsi["inputs"] & INPUT_CLUTCH)
    assert len(pressed) > 300 and np.all(np.diff(pressed) == 1)  # one press, held ~0.8 s
    assert np.array_equal(np.flatnonzero(hsi["gain"] == 0), pressed)
    assert (hsi["inputs"] & INPUT_PRESENT).all()
    assert (to["gain"] == 0).sum() == len(pressed)  # the TO followed the HSI's packets
    assert hsi["gain"][-1] == 1.0 and to["gain"][-1] == 1.0  # re-engaged


@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGTERM])
def test_the_terminal_is_restored_after_a_signal(terminal, how) -> None:
    """Stopped by a signal in the middle of the run (the presence key pressed before): exit
    128 + the signal, the terminal's mode as it was."""
    run = terminal(30.0)
    run.wait_for(b"keys: space or c")
    run.type(b"p")
    run.wait_for(b"operator away")
    assert run.mode() != run.before
    run.proc.send_signal(how)
    assert run.finish() == 128 + how, run.err.decode(errors="replace")
    assert run.mode() == run.before


def test_keys_need_real_time(capsys) -> None:
    assert main(["run", str(FOAM), "--keys", "--no-log"]) == 2
    assert "--keys reads the operator's keys" in capsys.readouterr().err


class _Feedback:
    inputs = 0


def test_without_a_terminal_the_reader_does_nothing(tmp_path) -> None:
    """stdin a file: no thread, no mode to restore, the inputs at their start (present, the
    clutch released); the keys toggle the bits when pressed."""
    fb = _Feedback()
    with open(tmp_path / "stdin", "w+") as stdin, KeyReader(fb, stdin) as reader:  # type: ignore[arg-type]
        assert not reader.active and fb.inputs == AT_START
        reader.press(ord("c"))
        assert fb.inputs == AT_START | INPUT_CLUTCH
        reader.press(ord("p"))
        reader.press(ord("x"))
        assert fb.inputs == INPUT_CLUTCH and reader.presses == 2


def test_two_sites_with_the_keys_replay_the_tos_log_bit_for_bit(tmp_path) -> None:
    """``run --link zenoh --keys``: the HSI site reads the keys (its terminal goes to cbreak
    mode), the TO site follows its packets; the clutch pressed for about a second shows in both
    site logs, and the TO's site log replays bit for bit against the HSI's logged packets (their
    ``engaged`` included). The terminal's mode is restored."""
    pytest.importorskip("zenoh")
    from test_zenoh_sites import PATIENT, endpoints, free_port

    from teleop_rt.recording.site_replay import replay_site

    master, slave = pty.openpty()
    before = termios.tcgetattr(slave)
    base = tmp_path / "pair.mcap"
    cmd = [sys.executable, "-m", "teleop_rt", "run", str(FOAM), "--link", "zenoh", "--realtime",
           "--keys", "--duration", "8", "--log", str(base), "--set", "channel.delay_ms=20",
           *PATIENT, *endpoints(free_port())]  # fmt: skip
    proc = subprocess.Popen(cmd, stdin=slave, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        end = time.monotonic() + STARTED_S
        while termios.tcgetattr(slave)[3] & termios.ICANON:  # until the HSI site reads keys
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()
            time.sleep(0.05)
        time.sleep(2.5)
        os.write(master, b"c")
        time.sleep(1.0)
        os.write(master, b"c")
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err.decode(errors="replace")[-3000:]
        assert termios.tcgetattr(slave) == before
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)
    hsi, to = (read_log(tmp_path / f"pair.{s}.mcap") for s in ("hsi", "to"))
    pressed = np.flatnonzero(hsi.topics["/hsi"]["inputs"] & INPUT_CLUTCH)
    assert len(pressed) > 300, len(pressed)
    assert np.array_equal(np.flatnonzero(hsi.topics["/hsi"]["gain"] == 0), pressed)
    engaged, valid = to.topics["/link"]["engaged"], to.topics["/link"]["valid"] == 1
    assert (valid & (engaged == 0)).sum() > 300  # the HSI's packets said so
    assert (to.topics["/to"]["gain"] == 0).sum() > 300 and to.topics["/to"]["gain"][-1] == 1.0
    done = replay_site(to, [], None, False, str(tmp_path / "pair.to.mcap"))
    assert done.figures["identical"] is True, done.figures
