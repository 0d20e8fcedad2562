"""Output files of the command line (issue 19, rough edges): paths are checked before any work,
an existing file is refused unless --force (plot, bode, replay alike), the format comes from
the extension, and replay --no-log --plot still writes its plot."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from log_fixtures import write_synthetic_log

import teleop_rt.analysis.bode as bode
import teleop_rt.recording.replay as replay
from teleop_rt.cli import main
from teleop_rt.recording.plot import default_title
from teleop_rt.recording.reader import read_log
from tests.conftest import CONFIGS

PNG, PDF = b"\x89PNG\r\n\x1a\n", b"%PDF"
FREE = str(CONFIGS / "free_space.yaml")
BODE = ["bode", FREE, "--omegas", "5", "--max-seconds", "5", "--env-stiffness", "20"]


def one_error(capsys, *named: str) -> str:
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("teleop-rt: error: "), err
    for text in named:
        assert text in lines[0], (text, lines[0])
    return lines[0]


@pytest.fixture
def no_work(monkeypatch):
    """Any sweep or replay started fails the test: the paths must be refused before."""

    def fail(*_a, **_k):
        raise AssertionError("the work started before the output path was checked")

    monkeypatch.setattr(bode, "measure_displayed_impedance", fail)
    monkeypatch.setattr(replay, "build_replay", fail)


# --- bode -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("option", "path", "named"),
    [
        ("--json", "/nonexistent/d/o.json", "does not exist"),
        ("--plot", "/nonexistent/x.png", "does not exist"),
        ("--plot", "{tmp}", "no extension"),
        ("--plot", "{tmp}/dir.png", "is a folder"),
        ("--json", "{tmp}/dir.png", "is a folder"),
        ("--plot", "{tmp}/x.xyz", "unknown image format '.xyz'"),
        ("--plot", "{tmp}/old.png", "exists; pass --force"),
        ("--json", "{tmp}/old.png", "exists; pass --force"),
    ],
)
def test_bode_refuses_bad_outputs_before_the_sweep(
    tmp_path, capsys, no_work, option, path, named
) -> None:
    (tmp_path / "dir.png").mkdir()
    (tmp_path / "old.png").write_bytes(b"keep")
    path = path.format(tmp=tmp_path)
    assert main([*BODE, option, path]) == 2
    one_error(capsys, option, path, named)
    assert (tmp_path / "old.png").read_bytes() == b"keep"


def test_bode_json_and_plot_on_one_file(tmp_path, capsys, no_work) -> None:
    same = str(tmp_path / "x.png")
    assert main([*BODE, "--json", same, "--plot", same]) == 2
    one_error(capsys, "--plot", "--json writes the same file")


def test_bode_force_overwrites_and_the_extension_picks_the_format(tmp_path, capsys) -> None:
    plot, out = tmp_path / "z.pdf", tmp_path / "z.json"
    plot.write_bytes(b"old")
    out.write_text("old")
    assert main([*BODE, "--plot", str(plot), "--json", str(out), "--force"]) == 0
    assert plot.read_bytes()[:4] == PDF
    doc = json.loads(out.read_text())
    assert doc["measured"]["reason"] == ["settled"]


# --- plot -------------------------------------------------------------------------------------
@pytest.fixture
def log(tmp_path) -> Path:
    return write_synthetic_log(tmp_path / "run.mcap", 600).path


@pytest.mark.parametrize(("suffix", "magic"), [(".png", PNG), (".pdf", PDF), (".svg", b"<?xml")])
def test_plot_format_by_extension(tmp_path, log, capsys, suffix, magic) -> None:
    out = tmp_path / f"x{suffix}"
    assert main(["plot", str(log), "-o", str(out)]) == 0
    assert out.read_bytes()[: len(magic)] == magic


@pytest.mark.parametrize("name", ["x.xyz", "x", "x.mcap"])
def test_plot_refuses_unknown_formats(tmp_path, log, capsys, name) -> None:
    assert main(["plot", str(log), "-o", str(tmp_path / name)]) == 2
    one_error(capsys, "-o", "(use .png, .pdf, .svg")
    assert not (tmp_path / name).exists()


def test_plot_existing_file_needs_force(tmp_path, log, capsys) -> None:
    out = tmp_path / "run.png"  # the default output, LOG.png
    out.write_bytes(b"keep")
    assert main(["plot", str(log)]) == 2
    one_error(capsys, "exists; pass --force")
    assert out.read_bytes() == b"keep"
    assert main(["plot", str(log), "--force"]) == 0
    assert out.read_bytes()[:8] == PNG


def test_plot_never_overwrites_its_input(tmp_path, capsys) -> None:
    log = write_synthetic_log(tmp_path / "odd.png", 300).path  # a log with an image's name
    before = log.read_bytes()
    assert main(["plot", str(log), "-o", str(log), "--force"]) == 2
    one_error(capsys, "that is the input file")
    assert log.read_bytes() == before


def test_plot_window(tmp_path, log, capsys) -> None:
    out = tmp_path / "w.png"
    assert main(["plot", str(log), "-o", str(out), "--from", "0.2", "--to", "0.3"]) == 0
    assert out.read_bytes()[:8] == PNG
    assert main(["plot", str(log), "-o", str(tmp_path / "e.png"), "--from", "5"]) == 2
    one_error(capsys, "the window 5 s to the end holds no ticks (the log's ticks run from 0 to")
    assert main(["plot", str(log), "--from", "0.3", "--to", "0.2"]) == 2
    one_error(capsys, "the window is empty")


# --- replay -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def real_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("outputs") / "wall.mcap"
    argv = ["run", str(CONFIGS / "stiff_wall.yaml"), "--duration", "0.3", "--log", str(path)]
    assert main(argv) == 0
    return path


def test_replay_checks_its_plot_before_replaying(tmp_path, real_log, capsys, no_work) -> None:
    existing = tmp_path / "r.png"
    existing.write_bytes(b"keep")
    assert main(["replay", str(real_log), "--plot", str(existing)]) == 2
    one_error(capsys, "--plot", "exists; pass --force")
    assert main(["replay", str(real_log), "--plot", str(tmp_path / "r.bmpx")]) == 2
    one_error(capsys, "unknown image format")
    assert existing.read_bytes() == b"keep"


def test_replay_no_log_still_plots(tmp_path, real_log, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "r.svg"
    argv = ["replay", str(real_log), "--no-log", "--plot", str(out), "--json"]
    assert main([*argv, "--set", "channel.delay_ms=20"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["log"] is None and doc["plot"] == str(out)
    assert out.read_bytes()[:5] == b"<?xml"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.svg"]  # no log left anywhere


def test_replay_plot_says_it_is_a_replay(tmp_path, real_log, capsys) -> None:
    log, out = tmp_path / "again.mcap", tmp_path / "again.png"
    argv = ["replay", str(real_log), "--log", str(log), "--plot", str(out)]
    assert main([*argv, "--set", "channel.delay_ms=20"]) == 0
    assert f"plot: {out}" in capsys.readouterr().out
    title = default_title(read_log(log))
    assert f"replay of {real_log}" in title and "--set channel.delay_ms=20" in title
    assert "delay 20 ms" in title
    out.write_bytes(b"keep")  # the same rule as plot and bode: --force overwrites
    assert main([*argv[:2], "--no-log", "--plot", str(out), "--force"]) == 0
    assert out.read_bytes()[:8] == PNG


def test_replaying_a_can_log_says_it_runs_on_sim(tmp_path, capsys) -> None:
    can_log = tmp_path / "can.mcap"
    argv = ["run", str(CONFIGS / "can_emulated.yaml"), "--set", "can.emulate=true"]
    assert main([*argv, "--duration", "0.2", "--log", str(can_log)]) == 0
    capsys.readouterr()
    assert main(["replay", str(can_log), "--log", str(tmp_path / "r.mcap")]) == 0
    out = capsys.readouterr().out
    assert "recorded on the can backend; the replay runs on the simulated backend (sim)" in out
    assert "recorded on can, replayed on sim" in default_title(read_log(tmp_path / "r.mcap"))
    assert main(["replay", str(can_log), "--no-log", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["backend"] == "sim" and doc["recorded_backend"] == "can"
