"""CI's static checks (issue 25): ruff with the project's rules on the package, the tests and
the tools, and mypy on the package (its settings in pyproject.toml's [tool.mypy]), from the
README's test command; a finding fails its test and lists itself."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str:
    """The venv's own copy of a tool (next to this Python), else the one on PATH."""
    beside = Path(sys.executable).parent / name
    return str(beside) if beside.exists() else shutil.which(name) or name


def test_ruff_finds_nothing() -> None:
    done = subprocess.run(
        [_tool("ruff"), "check", "teleop_rt", "tests", "tools"], cwd=ROOT, capture_output=True,
        text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr


def test_mypy_finds_nothing() -> None:
    # the files come from [tool.mypy]; no cache so that a stale one cannot hide a finding
    done = subprocess.run(
        [_tool("mypy"), "--no-incremental", "--cache-dir", "/dev/null"], cwd=ROOT,
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr


def test_mypy_sees_block_fields(tmp_path: Path) -> None:
    # docs/architecture.md: "editors and mypy see the fields" of a flat block
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from teleop_rt.com.port import Port\n"
        "def f(p: Port) -> None:\n"
        "    reveal_type(p.flow)\n"
        "    reveal_type(p.total_energy)\n"
        "    reveal_type(Port.flow.k)\n"
        "    p.flwo\n"
    )
    done = subprocess.run(
        [_tool("mypy"), "--no-incremental", "--cache-dir", "/dev/null", "--follow-imports",
         "silent", str(probe)], cwd=ROOT, capture_output=True, text=True,
        env={**os.environ, "MYPYPATH": str(ROOT)},
    )  # fmt: skip
    lines = done.stdout.splitlines()
    assert len(lines) >= 4, done.stdout + done.stderr
    assert 'Revealed type is "numpy.ndarray' in lines[0], done.stdout
    assert re.search(r'Revealed type is "(builtins\.)?float"$', lines[1]), done.stdout
    assert re.search(r'Revealed type is "(builtins\.)?int"$', lines[2]), done.stdout
    assert '"Port" has no attribute "flwo"' in lines[3], done.stdout
