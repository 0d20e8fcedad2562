"""The tools' command lines (issue 19, rough edges): reproduce_paper checks --out before the
work and --quick never writes over the committed docs/; every tool option has help text;
bench_instructions shows progress; .gitignore ignores nothing that is tracked."""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"


def load_tool(name: str):
    sys.path.insert(0, str(TOOLS))  # tools import each other (bench_instructions -> bench)
    spec = importlib.util.spec_from_file_location(f"tool_{name}", TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


# --- reproduce_paper --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rp():
    return load_tool("reproduce_paper")


def test_quick_without_out_writes_into_a_new_temporary_folder(rp) -> None:
    args = rp.parse_args(["--quick"])
    try:
        assert args.out.is_dir() and not any(args.out.iterdir())
        assert not args.out.resolve().is_relative_to(ROOT)  # never docs/ or the checkout
        assert rp.parse_args([]).out == ROOT / "docs"  # the full run regenerates docs/
    finally:
        shutil.rmtree(args.out)


def test_out_is_checked_before_the_work(rp, tmp_path, monkeypatch, capsys) -> None:
    def fail(*_a, **_k):
        raise AssertionError("reproduce() started")

    monkeypatch.setattr(rp, "reproduce", fail)
    afile = tmp_path / "report.md"
    afile.write_text("x")
    assert rp.main(["--quick", "--out", str(afile)]) == 2
    err = capsys.readouterr().err
    assert err == f"reproduce_paper: error: --out {afile}: is a file, not a folder\n"
    assert rp.main(["--quick", "--out", str(afile / "sub")]) == 2
    assert "cannot create" in capsys.readouterr().err


# --- help texts -------------------------------------------------------------------------------
class _Parsed(Exception):
    pass


def parser_of(tool: str, monkeypatch) -> argparse.ArgumentParser:
    """The tool's parser, caught as its main() parses (nothing else of the tool runs)."""
    module = load_tool(tool)

    def capture(self, *_a, **_k):
        raise _Parsed(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    monkeypatch.setattr(sys, "argv", [tool])
    with pytest.raises(_Parsed) as caught:
        main = module.main
        main() if main.__code__.co_argcount == 0 else main([])
    return caught.value.args[0]


@pytest.mark.parametrize(
    "tool",
    [
        "bench",
        "bench_can",
        "bench_instructions",
        "drive_emulator",
        "network_study",
        "reproduce_paper",
    ],
)
def test_every_tool_option_has_help(tool: str, monkeypatch) -> None:
    parser = parser_of(tool, monkeypatch)
    for action in parser._actions:
        if action.help == argparse.SUPPRESS:
            continue  # internal (bench_instructions' child mode)
        assert action.help, (tool, action.option_strings or action.dest)


def test_the_fault_syntax_is_in_the_emulators_help(monkeypatch) -> None:
    parser = parser_of("drive_emulator", monkeypatch)
    fault = next(a for a in parser._actions if "--fault" in a.option_strings)
    assert fault.metavar == "[SIDE:]KIND:NODE@TICK[+TICKS]"
    for kind in ("drop_tpdo", "emcy", "stop_heartbeat", "status_fault", "error_frame"):
        assert kind in fault.help


# --- bench_instructions progress --------------------------------------------------------------
FAKE_VALGRIND = textwrap.dedent(
    """\
    #!{python}
    # stands in for valgrind: writes a callgrind file whose cost grows with --ticks
    import os, sys
    out = next(a for a in sys.argv if a.startswith("--callgrind-out-file="))
    path = out.split("=", 1)[1].replace("%p", str(os.getpid()))
    ticks = int(sys.argv[sys.argv.index("--ticks") + 1])
    with open(path, "w") as f:
        f.write("events: Ir\\nob=(1) /usr/lib/libpython3.so\\nfn=(1) f\\n")
        f.write(f"1 {{1000 + 300 * ticks}}\\n")
    """
)


def test_bench_instructions_shows_progress(tmp_path: Path) -> None:
    fake = tmp_path / "bin" / "valgrind"
    fake.parent.mkdir()
    fake.write_text(FAKE_VALGRIND.format(python=sys.executable))
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{fake.parent}{os.pathsep}{os.environ['PATH']}"}
    proc = subprocess.run(
        [sys.executable, str(TOOLS / "bench_instructions.py"), "--ticks", "100"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr
    err = proc.stderr.splitlines()
    for i, label in enumerate(("full tick", "full tick, recording on", "controller side"), 1):
        assert any(line.startswith(f"[{i}/3] {label}") and line.endswith(" ...") for line in err)
        assert any(line.startswith(f"[{i}/3] {label}") and "done in" in line for line in err)
    assert "300 instructions per tick" in proc.stdout  # the fake's 300 per tick, counted


# --- .gitignore -------------------------------------------------------------------------------
def test_gitignore_ignores_nothing_tracked() -> None:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    proc = subprocess.run(
        ["git", "-C", str(ROOT), "ls-files", "--cached", "--ignored", "--exclude-standard"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert proc.stdout == "", f"tracked but ignored: {proc.stdout.split()}"
    assert (ROOT / "docs" / "paper_reproduction.md").exists()
