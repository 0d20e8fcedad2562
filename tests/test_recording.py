"""Recording: every tick reaches the MCAP file, decodable by an independent ros2msg decoder
from the schema stored in the file, and the file is finished however the session ends."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from teleop_rt import config
from teleop_rt.recording.recorder import LogPathError, Recorder
from teleop_rt.session import Session
from tests.conftest import CONFIGS, START_LIMIT_S


def decoded(path: Path, topic: str) -> list:
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [msg for _, _, _, msg in reader.iter_decoded_messages(topics=[topic])]


def summary_of(path: Path) -> dict | None:
    with open(path, "rb") as f:
        for record in make_reader(f).iter_metadata():
            if record.name == "teleop_rt.summary":
                return json.loads(record.metadata["json"])
    return None


def test_every_tick_is_recorded_and_decodes_independently(tmp_path: Path) -> None:
    cfg = config.load(CONFIGS / "foam.yaml", ["duration_s=1.5"])
    session = Session(cfg)
    seen = []
    session_summary = session.run(
        observer=lambda s: seen.append(
            (list(s.hsi.feedback.q), list(s.to.feedback.tau_ext), list(s.channel.tau_c))
        ),
        recorder=Recorder(session, tmp_path / "foam.mcap"),
    )
    hsi = decoded(tmp_path / "foam.mcap", "/hsi")
    to = decoded(tmp_path / "foam.mcap", "/to")
    channel = decoded(tmp_path / "foam.mcap", "/channel")
    timing = decoded(tmp_path / "foam.mcap", "/timing")
    assert len(hsi) == len(to) == len(channel) == len(timing) == 1500 == session_summary.ticks
    assert [m.tick for m in hsi] == list(range(1500))
    for k in (0, 700, 1499):  # bit-exact: float64 in, float64 out
        q_h, tau_t, tau_c = seen[k]
        assert list(hsi[k].q) == q_h
        assert list(to[k].tau_ext) == tau_t
        assert list(channel[k].tau_c) == tau_c
    assert any(m.in_contact[0] for m in to)  # the foam was pressed
    stored = summary_of(tmp_path / "foam.mcap")
    assert stored["ticks"] == 1500 and stored["t_tau"] == session_summary.t_tau


def test_the_log_describes_itself(tmp_path: Path) -> None:
    cfg = config.load(CONFIGS / "free_space.yaml", ["duration_s=0.05"])
    session = Session(cfg)
    session.run(recorder=Recorder(session, tmp_path / "a.mcap"))
    with open(tmp_path / "a.mcap", "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = {a.name: a.data for a in reader.iter_attachments()}
    assert meta["teleop_rt"]["joints"] == "2" and meta["teleop_rt"]["operator"] == "hand"
    stored = config.from_dict(__import__("yaml").safe_load(attachments["config.yaml"]))
    assert stored == cfg
    assert attachments["urdf/hsi.urdf"].startswith(b"<?xml")


def test_an_existing_file_is_never_overwritten(tmp_path: Path) -> None:
    target = tmp_path / "keep.mcap"
    target.write_bytes(b"precious")
    session = Session(config.load(CONFIGS / "free_space.yaml", ["duration_s=0.01"]))
    with pytest.raises(LogPathError, match="exists"):
        Recorder(session, target)
    assert target.read_bytes() == b"precious"


def test_an_exception_inside_the_session_still_finishes_the_log(tmp_path: Path) -> None:
    session = Session(config.load(CONFIGS / "free_space.yaml", ["duration_s=2"]))

    def boom(s: Session) -> None:
        if s.tick == 321:
            raise RuntimeError("sensor exploded")

    with pytest.raises(RuntimeError):
        session.run(observer=boom, recorder=Recorder(session, tmp_path / "b.mcap"))
    stored = summary_of(tmp_path / "b.mcap")
    # tick 321's step ran but the tick did not complete: 320 complete ticks, all recorded
    assert stored["ticks"] == 320 and "sensor exploded" in stored["stopped_early"]
    assert len(decoded(tmp_path / "b.mcap", "/hsi")) == 320


def _start_realtime_run(log: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "teleop_rt.cli", "run", str(CONFIGS / "free_space.yaml"),
           "--realtime", "--duration", "20", "--json", "--log", str(log)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + START_LIMIT_S
    while not log.exists() or log.stat().st_size < 70_000:  # the writer put a few chunks on disk
        assert time.monotonic() < deadline and proc.poll() is None, f"exit {proc.poll()}"
        time.sleep(0.1)
    return proc


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_stops_a_realtime_run_with_a_complete_log(tmp_path: Path, sig, code) -> None:
    log = tmp_path / "rt.mcap"
    proc = _start_realtime_run(log)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    printed = json.loads(out)
    stored = summary_of(log)
    assert stored is not None and stored["ticks"] == printed["ticks"] > 100
    assert len(decoded(log, "/hsi")) == printed["ticks"]
    assert stored["stopped_early"] == f"stopped by {signal.Signals(sig).name}"


def test_a_hard_kill_leaves_a_readable_log(tmp_path: Path) -> None:
    log = tmp_path / "killed.mcap"
    proc = _start_realtime_run(log)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    # the writer process notices its parent is gone, writes what reached the ring, finishes
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            messages = decoded(log, "/hsi")
            break
        except Exception:  # still being finished
            time.sleep(0.2)
    ticks = [m.tick for m in messages]
    assert len(ticks) > 100 and ticks == list(range(len(ticks)))
    assert summary_of(log) is None  # no summary: the log says it was cut short
    assert np.isfinite([m.q[0] for m in messages]).all()


def test_a_signal_before_the_first_tick_leaves_no_writer_behind(monkeypatch, tmp_path) -> None:
    """SIGINT (here: the KeyboardInterrupt it becomes) after the log's writer has started but
    before the loop's own handler: the writer is ended and the file finished, so the process
    does not wait at exit for a child nobody closes."""
    import multiprocessing

    from teleop_rt.cli import main
    from teleop_rt.session import Session

    def interrupted(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(Session, "run", interrupted)
    log = tmp_path / "early.mcap"
    cfg = str(CONFIGS / "free_space.yaml")
    assert main(["run", cfg, "--duration", "0.5", "--log", str(log)]) == 130
    assert not [p for p in multiprocessing.active_children() if p.is_alive()]
    assert log.exists() and log.stat().st_size > 0
