"""The two sites in two processes over Eclipse Zenoh on 127.0.0.1 (multicast scouting off,
explicit endpoints): the pair's figures match the one-process session's, a killed site leaves
its peer stopping its robot, and sites of different sessions refuse each other."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from teleop_rt import config
from teleop_rt.session import Session
from tests.conftest import CONFIGS

pytest.importorskip("zenoh")
PAPER = CONFIGS / "paper_experiment.yaml"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoints(port: int) -> list[str]:
    at = f"udp/127.0.0.1:{port}"
    return ["--set", f"link.zenoh.hsi.listen=[{at}]", "--set", f"link.zenoh.to.connect=[{at}]"]


def site(name: str, port: int, *extra: str, stderr: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "teleop_rt", "site", name, str(PAPER), "--json",
           *endpoints(port), *extra]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=stderr.open("w"), text=True)


def test_two_processes_give_the_one_process_figures(tmp_path: Path) -> None:
    """3 s in real time with 20 ms of delay against the same config in one process. The link's
    packets of tick k are used at tick k + 20 on both sides, as the in-process delay lines do,
    so the figures differ only where a packet was lost (replaced by a zero wave; a few of 3000
    on this loaded VM). T_tau moves by under 1 % for that (15 % allowed); T_p far more, since
    the wave channel carries no position and every zero wave shifts the TO for good (the drift
    issue 17 deals with): 4 lost packets moved it by 60 % in one run. So T_p is held within 5 %
    only when no packet was lost, and within a factor of 3 otherwise."""
    overrides = ["channel.delay_ms=20"]
    local = Session(config.load(PAPER, [*overrides, "duration_s=3"])).run()
    cmd = [sys.executable, "-m", "teleop_rt", "run", str(PAPER), "--link", "zenoh", "--realtime",
           "--duration", "3", "--json", "--set", overrides[0], *endpoints(free_port())]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    both = json.loads(out.stdout)
    pair = both["pair"]
    assert pair["ticks"] == 3000 and both["exit_codes"] == {"hsi": 0, "to": 0}
    assert pair["t_tau_total"] == pytest.approx(local.t_tau_total, rel=0.15)
    lost = 0
    for name in ("hsi", "to"):
        link = both["sites"][name]["link"]["from_peer"]
        assert link["received"] > 0.95 * 3000 and link["rejected"] == 0, link
        assert link["used"] + link["lost"] == 3000 - 20  # the first 20 ticks have none due
        lost += link["lost"]
    if lost == 0:
        assert pair["t_p_total"] == pytest.approx(local.t_p_total, rel=0.05)
    else:
        assert local.t_p_total / 3 < pair["t_p_total"] < 3 * local.t_p_total


def wait_for(path: Path, text: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while text not in path.read_text():
        assert time.monotonic() < deadline, f"{text!r} not in {path.read_text()[-2000:]}"
        time.sleep(0.05)


@pytest.mark.parametrize("killed", ["to", "hsi"])
def test_a_killed_site_leaves_its_peer_stopping_safely(killed: str, tmp_path: Path) -> None:
    """SIGKILL one site mid-run: the other notices the silence within its peer timeout, brings
    its robot to rest (the staged stop) and exits 3 with one clear line and its summary."""
    port = free_port()
    errs = {n: tmp_path / f"{n}.err" for n in ("hsi", "to")}
    procs = {n: site(n, port, "--set", "channel.delay_ms=20", "--duration", "30", stderr=errs[n])
             for n in ("hsi", "to")}  # fmt: skip
    survivor = "hsi" if killed == "to" else "to"
    try:
        wait_for(errs[survivor], "answered", 120)
        time.sleep(1.0)  # a second of ticks
        os.kill(procs[killed].pid, signal.SIGKILL)
        out, _ = procs[survivor].communicate(timeout=60)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
    assert procs[survivor].returncode == 3, errs[survivor].read_text()[-2000:]
    summary = json.loads(out)
    assert summary["safety_stop"] and f"nothing from the {killed} site" in summary["stopped_early"]
    assert 500 < summary["ticks"] < 25_000
    assert any("at rest" in n or "zero torque" in n for n in summary["notes"]), summary["notes"]


def test_sites_of_different_sessions_refuse_each_other(tmp_path: Path) -> None:
    port = free_port()
    errs = {n: tmp_path / f"{n}.err" for n in ("hsi", "to")}
    hsi = site("hsi", port, "--set", "channel.delay_ms=20", stderr=errs["hsi"])
    to = site("to", port, "--set", "channel.delay_ms=30", stderr=errs["to"])
    for p in (hsi, to):
        p.communicate(timeout=120)
        assert p.returncode == 5
    for name, err in errs.items():
        lines = [x for x in err.read_text().splitlines() if x.startswith("teleop-rt")]
        assert lines == [lines[0]] and "runs another session: delay_ticks" in lines[0], name
        assert "Traceback" not in err.read_text()


def test_no_delay_over_a_network_is_refused(tmp_path: Path) -> None:
    err = tmp_path / "hsi.err"
    hsi = site("hsi", free_port(), stderr=err)  # the paper experiment: no delay
    hsi.communicate(timeout=120)
    assert hsi.returncode == 2
    assert "needs a delay of at least one tick" in err.read_text()


def test_a_peer_that_never_appears_is_one_line_and_exit_5(tmp_path: Path) -> None:
    err = tmp_path / "to.err"
    to = site("to", free_port(), "--set", "link.handshake_timeout_s=1",
              "--set", "channel.delay_ms=20", stderr=err)  # fmt: skip
    to.communicate(timeout=120)
    assert to.returncode == 5
    text = err.read_text()
    assert "teleop-rt: error: link: the hsi site did not answer within 1 s" in text
    assert "Traceback" not in text
