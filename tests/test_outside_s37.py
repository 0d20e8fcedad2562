"""Found from outside (sessions 36-37): what a site says about its run (an incomplete log, a
silent peer) reaches the user of ``run --link zenoh``, whose children's stderr is not passed
through."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import CONFIGS
from tests.test_zenoh_sites import endpoints, free_port

pytest.importorskip("zenoh")


def test_a_sites_incomplete_log_is_its_own_line_under_run_link_zenoh(tmp_path: Path) -> None:
    """Both site logs on a 1 MB tmpfs: each fills it, the site stops (exit 4) and, as a site
    started by hand would, the pair's command says so in one line per log with what the file
    holds (it said only "INCOMPLETE" in its table)."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)],
                             capture_output=True, text=True)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a 1 MB tmpfs here: {mounted.stderr.strip()}")
    try:
        sets = ["recording.ring_s=2", "channel.delay_ms=20", "link.peer_timeout_ms=1000"]
        cmd = [sys.executable, "-m", "teleop_rt", "run", str(CONFIGS / "paper_experiment.yaml"),
               "--link", "zenoh", "--realtime", "--duration", "8", "--json",
               "--log", str(mnt / "pair.mcap"), *(x for s in sets for x in ("--set", s)),
               *endpoints(free_port())]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=240, cwd=tmp_path)
        assert out.returncode == 4, out.stderr[-3000:]
        lines = out.stderr.splitlines()
        for site in ("hsi", "to"):
            said = [x for x in lines if x.startswith(f"teleop-rt: log {mnt}/pair.{site}.mcap is "
                                                      "incomplete: cannot write")]  # fmt: skip
            assert len(said) == 1 and "No space left on device" in said[0], out.stderr
            assert "; the file holds " in said[0], said
            assert json.loads(out.stdout)["sites"][site]["recording"]["complete"] is False
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def test_a_silent_peer_is_each_sites_own_line_under_run_link_zenoh(tmp_path: Path) -> None:
    """70 % of the packets lost each way (the impairment stage, seeded): each site used under
    half of its peer's packets due, which a site run by hand says in one error line, exit 5.
    The pair's command says it too, once per site, naming the site (a review's finding)."""
    sets = [
        "channel.delay_ms=20",
        "link.peer_timeout_ms=1000",
        "link.impairment={loss_percent: 70}",
    ]
    cmd = [sys.executable, "-m", "teleop_rt", "run", str(CONFIGS / "paper_experiment.yaml"),
           "--link", "zenoh", "--realtime", "--duration", "3", "--no-log", "--json",
           *(x for s in sets for x in ("--set", s)), *endpoints(free_port())]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert out.returncode == 5, out.stderr[-3000:]
    for site, peer in (("hsi", "to"), ("to", "hsi")):
        said = [
            x
            for x in out.stderr.splitlines()
            if x.startswith(f"teleop-rt: error: {site} site: link: the {peer} site was silent")
        ]
        assert len(said) == 1, out.stderr
        assert json.loads(out.stdout)["sites"][site]["peer_silent"] in said[0]
