"""The command line, called in-process (``main(argv) -> int``) and once through the installed
entry point: bad input is one ``teleop-rt: error:`` line on stderr and exit code 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from teleop_rt.cli import main

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SHIPPED = sorted(CONFIGS.glob("*.yaml"))


def assert_one_error_line(err: str, *named: str) -> None:
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {err!r}"
    assert lines[0].startswith("teleop-rt: error: ")
    assert "Traceback" not in err
    for text in named:
        assert text in lines[0], f"{text!r} not in {lines[0]!r}"


def bad_config(tmp_path: Path, old: str, new: str) -> Path:
    """A copy of the free-space config with one line changed (URDFs pointed back to robots/)."""
    text = (CONFIGS / "free_space.yaml").read_text()
    assert old in text
    text = text.replace(old, new, 1).replace("../robots", str(ROOT / "robots"))
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


# --- check ------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_check_accepts_every_shipped_config(path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(path)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"{path}: ok (2 joints")
    assert err == ""


def test_check_reports_overrides(capsys: pytest.CaptureFixture[str]) -> None:
    path = str(CONFIGS / "stiff_wall.yaml")
    assert main(["check", path, "--set", "channel.delay_ms=50", "--set", "duration_s=2"]) == 0
    out, _ = capsys.readouterr()
    assert "2000 ticks" in out and "delay 50 ticks" in out


# --- run --------------------------------------------------------------------------------------
def test_run_json_summary(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(CONFIGS / "free_space.yaml"), "--duration", "0.2", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    summary = json.loads(out)
    assert summary["ticks"] == 200
    assert summary["simulated_time_s"] == pytest.approx(0.2)
    assert summary["realtime"] is False and summary["stopped_early"] is None
    for key in ("t_p", "t_tau"):
        values = summary[key]
        assert isinstance(values, list) and len(values) == 2
        assert all(isinstance(v, float) for v in values)
    timing = summary["timing"]
    assert timing["ticks"] == 200
    assert isinstance(timing["compute_us"]["p50"], float)
    assert timing["compute_us"]["p50"] <= timing["compute_us"]["max"]
    assert "Traceback" not in err


def test_run_duration_and_overrides_combine(capsys: pytest.CaptureFixture[str]) -> None:
    path = str(CONFIGS / "stiff_wall.yaml")
    argv = ["run", path, "--duration", "0.05", "--set", "channel.delay_ms=10", "--json"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["ticks"] == 50 and summary["delay_ticks"] == 10


# --- bad input: one line, exit code 2 ---------------------------------------------------------
@pytest.mark.parametrize("command", ["check", "run"])
def test_bad_config_is_one_line_naming_the_key(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = bad_config(tmp_path, "virtual_mass: 0.1", "virtual_mass: -0.1")
    assert main([command, str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert_one_error_line(err)
    assert err.startswith("teleop-rt: error: hsi.virtual_mass: ")


def test_bad_yaml_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = bad_config(tmp_path, "rate_hz: 1000", "rate_hz: [1000")
    assert main(["check", str(path)]) == 2
    assert_one_error_line(capsys.readouterr().err, str(path), "not valid YAML")


def test_session_build_error_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = bad_config(tmp_path, "virtual_mass: 0.1", "virtual_mass: [0.1, 0.1, 0.1]")
    assert main(["run", str(path), "--duration", "0.01"]) == 2
    assert_one_error_line(capsys.readouterr().err, "hsi.virtual_mass")


@pytest.mark.parametrize("command", ["check", "run"])
def test_nonexistent_config_file(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "nope.yaml"
    assert main([command, str(missing)]) == 2
    assert_one_error_line(capsys.readouterr().err, str(missing))


@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("channel.dealy_ms=5", "channel.dealy_ms"),  # unknown key
        ("colour=red", "colour"),  # unknown top-level key
        ("channel.delay_ms", "channel.delay_ms"),  # no '='
        ("environment.0.stiffness_n_per_m=1", "environment.0"),  # free space has no item 0
        ("environment.\u00b2.x=1", "environment"),  # a digit that int() refuses
        ("name=" + "[" * 600, "name"),  # nested too deeply for the YAML parser
    ],
)
def test_bad_set(override: str, named: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(CONFIGS / "free_space.yaml"), "--set", override]) == 2
    assert_one_error_line(capsys.readouterr().err, named)


@pytest.mark.parametrize("duration", ["1e12", "1e308"])
def test_absurd_duration_is_a_config_error(
    duration: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # passes argparse (positive, finite) but must not overflow or try to allocate petabytes
    assert main(["run", str(CONFIGS / "free_space.yaml"), "--duration", duration]) == 2
    assert_one_error_line(capsys.readouterr().err, "duration_s")


def test_unknown_backend_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["run", str(CONFIGS / "free_space.yaml"), "--duration", "0.01", "--backend", "nope"]
    assert main(argv) == 2
    assert_one_error_line(capsys.readouterr().err, "backend", "nope")


@pytest.mark.parametrize("duration", ["-1", "0", "abc", "inf", "nan"])
def test_bad_duration_is_an_argparse_error(
    duration: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        main(["run", str(CONFIGS / "free_space.yaml"), "--duration", duration])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--duration" in err and "Traceback" not in err


@pytest.mark.parametrize("argv", [[], ["fly"], ["run"], ["run", "x.yaml", "--overrun", "panic"]])
def test_bad_arguments_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert "usage: teleop-rt" in capsys.readouterr().err


# --- the installed entry point ----------------------------------------------------------------
def entry_point() -> list[str]:
    """The console script installed next to this interpreter, else ``python -m teleop_rt.cli``."""
    script = Path(sys.executable).parent / "teleop-rt"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "teleop_rt.cli"]


def test_console_script_check(tmp_path: Path) -> None:
    proc = subprocess.run(
        [*entry_point(), "check", "configs/foam.yaml"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("configs/foam.yaml: ok (2 joints")

    missing = tmp_path / "missing.yaml"
    proc = subprocess.run(
        [*entry_point(), "check", str(missing)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2  # main()'s return value becomes the exit status
    assert_one_error_line(proc.stderr, str(missing))
