"""Issue 19, "Logs that line up": log times are wall-clock (UTC at the session start plus the
tick's time), the start time is in the metadata, the header profile is ros2, the software
version carries the git commit, and every reader (windows, metrics, plot) counts seconds from
the session start. Checked with mcap's own reader, independent of teleop_rt's."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from log_fixtures import START_NS, write_synthetic_log
from mcap.reader import make_reader

from teleop_rt import __version__
from teleop_rt.cli import main
from teleop_rt.recording.reader import read_log
from teleop_rt.version import git_commit, software_version
from tests.conftest import CONFIGS, ROOT


@pytest.fixture(scope="module")
def run_log(tmp_path_factory) -> tuple[Path, int, int]:
    """A 0.3 s run through the CLI, bracketed by the wall clock."""
    path = tmp_path_factory.mktemp("times") / "run.mcap"
    before = time.time_ns()
    argv = ["run", str(CONFIGS / "foam.yaml"), "--duration", "0.3", "--json", "--log", str(path)]
    argv += ["--set", "channel.delay_ms=5"]
    assert main(argv) == 0
    return path, before, time.time_ns()


def test_log_times_are_utc_at_the_start_plus_the_tick_time(run_log, capsys) -> None:
    path, before, after = run_log
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}["teleop_rt"]
        stamps = [(m.log_time, m.publish_time) for _, _, m in reader.iter_messages(["/hsi"])]
        attachments = [a.log_time for a in reader.iter_attachments()]
    assert header.profile == "ros2"
    start = int(meta["start_time_ns"])
    assert before <= start <= after  # a time during the run, not 0 (1970 in Foxglove)
    assert meta["start_time_utc"].endswith("Z") and meta["start_time_utc"][:4] >= "2025"
    period = int(meta["period_ns"])
    assert [s for s, _ in stamps] == [start + k * period for k in range(300)]
    assert attachments and all(t == start for t in attachments)
    # the readers: seconds count from the session start
    data = read_log(path, t_from=0.1, t_to=0.2)
    assert data.start_ns == start
    np.testing.assert_array_equal(data.topics["/hsi"]["tick"], np.arange(100, 200))
    capsys.readouterr()
    assert main(["metrics", str(path), "--from", "0.1", "--to", "0.2", "--json"]) == 0
    assert '"ticks": 100' in capsys.readouterr().out


def test_the_log_names_its_config_overrides_and_commit(run_log) -> None:
    meta = read_log(run_log[0], ["/hsi"]).meta
    assert meta["config"] == str(CONFIGS / "foam.yaml")
    assert meta["overrides"] == '["channel.delay_ms=5", "duration_s=0.3"]'
    assert meta["software_version"] == software_version()
    if shutil.which("git") and (ROOT / ".git").exists():
        head = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        assert meta["software_version"].startswith(f"{__version__}+g{head}")


def test_no_commit_outside_a_checkout_or_inside_another_repository(tmp_path) -> None:
    assert git_commit(tmp_path) is None  # not a git work tree
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "site-packages").mkdir()
    # an installed package somewhere inside a repository is not that repository's commit
    assert git_commit(tmp_path / "site-packages") is None
    assert git_commit(tmp_path) is None  # a repository without commits


@pytest.mark.parametrize("start_ns", [START_NS, 0])
def test_windows_count_from_the_session_start(tmp_path, start_ns) -> None:
    """Wall-clock logs and logs from before (log times from 0) read the same windows."""
    log = write_synthetic_log(tmp_path / "a.mcap", 1000, chunk_size=2048, start_ns=start_ns)
    data = read_log(log.path, t_from=0.25, t_to=0.5)
    assert data.start_ns == start_ns
    for arr in data.topics.values():
        np.testing.assert_array_equal(arr["tick"], np.arange(250, 500))
    np.testing.assert_array_equal(data.topics["/hsi"]["q"], log.field("/hsi", "q")[250:500])


def test_a_bad_start_time_is_one_error(tmp_path, capsys) -> None:
    log = write_synthetic_log(tmp_path / "a.mcap", 50, meta={"start_time_ns": "soon"})
    assert main(["metrics", str(log.path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "start_time_ns = 'soon'" in err
