"""The README and docs/*.md keep their promises (issue 25): every command in a ``bash`` block of
any of them is run here (or, where it needs real time, two processes or minutes, parsed by the
real parser, its config checked, and the test that runs such a command named); the README's
set-up and test commands are what .ci/run runs; relative links point at files that exist; no
prose line is over 100 characters (the generated reports excepted)."""

from __future__ import annotations

import argparse
import ast
import importlib.util
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from teleop_rt.cli import _build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
# written by tools/reproduce_paper.py, network_study.py (--codec: codec_study.py, --acceptance:
# transparency_study.py): one line per paragraph
GENERATED = {
    "paper_reproduction.md",
    "network_study.md",
    "codec_study.md",
    "transparency_under_loss.md",
}
# pages a sibling branch adds (issue 25's index links them ahead of the merge); once a page
# exists its links are checked like any other
PENDING = {"codec.md", "performance.md", "transparency_under_loss.md", "task_space.md"}

# commands not run here, with the test that runs their kind (they are still parsed and their
# config checked below)
RUN_ELSEWHERE = {
    "--link zenoh": "tests/test_zenoh_sites.py (two site processes over Zenoh)",
    "site hsi": "tests/test_zenoh_sites.py",
    "site to": "tests/test_zenoh_sites.py",
    "drive_emulator.py": "tests/test_can_tools.py (the emulator in a process of its own)",
    "can.feedback_window_us": "tests/test_can_tools.py",
    "reproduce_paper.py": "tests/test_reproduce_paper.py (the quick run)",
}


def bash_commands(path: Path) -> list[str]:
    """Every command line of the ``bash`` blocks of one page (comments and ``&`` dropped)."""
    commands: list[str] = []
    block = None
    for line in path.read_text().replace("\\\n", " ").split("\n"):
        s = line.strip()
        if s.startswith("```"):
            block = s[3:] if block is None else None
            continue
        if block == "bash" and s and not s.startswith("#"):
            commands.append(re.sub(r"\s+#.*$", "", s).rstrip(" &"))
    return commands


ALL = [(p.relative_to(ROOT).as_posix(), c) for p in DOCS for c in bash_commands(p)]


def ci_lines() -> list[str]:
    return [ln for ln in (ROOT / ".ci" / "run").read_text().split("\n") if ln and ln[0] != "#"]


def test_the_readme_set_up_and_test_commands_are_what_ci_runs() -> None:
    readme = bash_commands(ROOT / "README.md")
    assert readme[0] == 'python3 -m venv .venv && .venv/bin/pip install -q -e ".[test]"'
    assert readme[0] in ci_lines()
    assert ".venv/bin/python -m pytest" in readme and ".venv/bin/python -m pytest" in ci_lines()


def teleop_commands() -> list[tuple[str, str]]:
    return [(d, c) for d, c in ALL if shlex.split(c)[0].endswith("teleop-rt")]


def tool_commands() -> list[tuple[str, str]]:
    return [(d, c) for d, c in ALL if re.match(r"(\.venv/bin/)?python3? tools/", c)]


def test_every_command_is_of_a_kind_this_file_covers() -> None:
    kinds = set(teleop_commands()) | set(tool_commands())
    other = [(d, c) for d, c in ALL if (d, c) not in kinds]
    # the set-up and the pytest commands: test_the_readme_set_up_..., test_the_fast_subset_...
    assert all(c.startswith(("python3 -m venv", ".venv/bin/python -m pytest")) for _, c in other)
    assert len(ALL) >= 15


def _args(command: str) -> list[str]:
    return shlex.split(command)[1:]


def _flag(args: list[str], flag: str) -> list[str]:
    """Each ``flag VALUE`` pair of args, kept in order."""
    return [w for i in range(len(args) - 1) if args[i] == flag for w in (flag, args[i + 1])]


def _elsewhere(command: str) -> str | None:
    return next((t for k, t in RUN_ELSEWHERE.items() if k in command), None)


@pytest.mark.parametrize(("doc", "command"), teleop_commands())
def test_every_teleop_rt_command_parses_and_its_config_checks(doc: str, command: str) -> None:
    args = _args(command)
    _build_parser().parse_args(args)  # an unknown option or a bad value exits 2 here
    configs = [a for a in args if a.startswith("configs/")]
    for config in configs:
        sets = _flag(args, "--set") + _flag(args, "--backend")
        assert main(["check", str(ROOT / config), *sets]) == 0, (doc, command)


def _rewrite_logs(args: list[str], tmp: Path) -> list[str]:
    return [str(tmp / a[len("logs/") :]) if a.startswith("logs/") else a for a in args]


def test_every_teleop_rt_command_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The commands run in page order (a log written by one is read by the next); a run is cut
    to 0.3 s of simulated time; logs go to tmp_path."""
    monkeypatch.chdir(ROOT)
    ran = 0
    for doc, command in teleop_commands():
        if _elsewhere(command):
            continue
        args = _rewrite_logs(_args(command), tmp_path)
        if args[0] == "run":
            args += ["--duration", "0.3"]
            if "--log" not in args:
                args.append("--no-log")
        code = main(args)
        assert code == 0, (doc, command, code)
        ran += 1
    assert (tmp_path / "wall.png").stat().st_size > 0  # the README's plot
    assert ran >= 8


@pytest.mark.parametrize(("doc", "command"), tool_commands())
def test_every_tool_command_parses(
    doc: str, command: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A tool's command line is parsed by the tool's own parser; the run itself is the named
    test's (they take minutes, or a second process)."""
    assert _elsewhere(command), f"{command}: name the test that runs it in RUN_ELSEWHERE"
    words = shlex.split(command)
    tool = ROOT / words[1]

    class Parsed(Exception):
        pass

    original = argparse.ArgumentParser.parse_args

    def parse_and_stop(self, args=None, namespace=None):  # type: ignore[no-untyped-def]
        original(self, args, namespace)
        raise Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_and_stop)
    monkeypatch.setattr(sys, "argv", [str(tool), *words[2:]])
    monkeypatch.syspath_prepend(str(ROOT / "tools"))
    monkeypatch.chdir(ROOT)
    spec = importlib.util.spec_from_file_location(f"docs_{tool.stem}", tool)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)
    main_fn = module.main
    with pytest.raises(Parsed):
        try:
            main_fn(words[2:])  # type: ignore[operator]
        except TypeError:  # main() without argv reads sys.argv
            main_fn()  # type: ignore[operator]


def test_the_fast_subset_deselects_exactly_the_marked_tests() -> None:
    """The README's fast subset names registered markers, and collecting it leaves out the
    marked tests and nothing else."""
    readme = bash_commands(ROOT / "README.md")
    subset = next(c for c in readme if "pytest -m " in c)
    expression = shlex.split(subset)[-1]
    markers = set(re.findall(r"not (\w+)", expression))
    assert markers == {"slow", "realtime", "zenoh", "can"}
    text = (ROOT / "pyproject.toml").read_text()
    for m in markers:
        assert re.search(rf'"{m}: ', text), m
    assert "--strict-markers" in text

    def collect(*extra: str) -> set[str]:
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "pytest",
                "--collect-only",
                "-p",
                "no:cacheprovider",
                *extra,
                str(ROOT / "tests"),
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
            check=True,
        ).stdout
        return {ln for ln in out.split("\n") if "::" in ln}

    everything, fast = collect(), collect("-m", expression)
    marked = collect("-m", " or ".join(sorted(markers)))
    assert fast and marked and fast | marked == everything and not fast & marked


# what in a test's (or its fixture's) source needs a marker to stay out of the fast subset
NEEDS = {"realtime": ('"--realtime"',), "zenoh": ('"--link", "zenoh"', "link.kind=zenoh")}


def needing(path: Path, marker: str) -> set[str]:
    """The tests of ``path`` whose body, or a same-module fixture they take, contains what
    ``marker`` stands for (NEEDS)."""
    source = path.read_text()
    tree = ast.parse(source)
    functions = [n for n in tree.body if isinstance(n, ast.FunctionDef)]

    def uses(node: ast.FunctionDef) -> bool:
        text = ast.get_source_segment(source, node) or ""
        return any(s in text for s in NEEDS[marker])

    fixtures = {n.name for n in functions if not n.name.startswith("test_") and uses(n)}
    return {n.name for n in functions if n.name.startswith("test_")
            and (uses(n) or fixtures & {a.arg for a in n.args.args})}  # fmt: skip


def declared_marks(file: str, function: str) -> set[str]:
    """The markers tests/conftest.py gives ``function`` of ``file`` (the suite declares its
    markers there, by file and by test, not in the test files)."""
    from tests.conftest import MARKS_BY_FILE, MARKS_BY_TEST, SLOW_TESTS

    marks = {*MARKS_BY_FILE.get(file, ()), *MARKS_BY_TEST.get(f"{file}::{function}", ())}
    return marks | ({"slow"} if function in SLOW_TESTS.get(file, ()) else set())


@pytest.mark.parametrize("marker", sorted(NEEDS))
def test_a_test_that_runs_in_real_time_or_over_zenoh_carries_its_marker(marker: str) -> None:
    """A test that starts a real-time run or two sites over Zenoh is marked (tests/conftest.py),
    so the README's fast subset does not wait on the wall clock or on two processes."""
    missing = [f"{path.name}::{name}" for path in sorted((ROOT / "tests").glob("test_*.py"))
               for name in sorted(needing(path, marker))
               if marker not in declared_marks(path.name, name)]  # fmt: skip
    assert not missing, f"not marked {marker}: {missing}"


def test_every_marked_test_exists() -> None:
    """A marker declared for a test that is not there (renamed, a typo) marks nothing: refused."""
    from tests.conftest import MARKS_BY_FILE, MARKS_BY_TEST, SLOW_TESTS

    def functions(file: str) -> set[str]:
        path = ROOT / "tests" / file
        tree = ast.parse(path.read_text()) if path.exists() else ast.Module(body=[])
        return {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}

    named = [key.split("::") for key in MARKS_BY_TEST]
    named += [[file, f] for file, fs in SLOW_TESTS.items() for f in fs]
    missing = [f"{file}::{f}" for file, f in named if f not in functions(file)]
    missing += [file for file in MARKS_BY_FILE if not (ROOT / "tests" / file).exists()]
    assert not missing, missing


LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_relative_links_point_at_files_that_exist(page: Path) -> None:
    for target in LINK.findall(page.read_text()):
        if target.startswith(("http://", "https://", "#", "mailto:")):
            continue
        path = (page.parent / target.split("#")[0]).resolve()
        if path.name in PENDING and path.parent == ROOT / "docs":
            continue
        assert path.exists(), f"{page.name}: {target}"


@pytest.mark.parametrize("page", [p for p in DOCS if p.name not in GENERATED], ids=lambda p: p.name)
def test_no_prose_line_is_over_100_characters(page: Path) -> None:
    long, block = [], False
    for number, line in enumerate(page.read_text().split("\n"), 1):
        if line.strip().startswith("```"):
            block = not block
        elif not block and not line.lstrip().startswith("|") and len(line) > 100:
            long.append(number)
    assert not long, f"{page.name}: lines {long}"


def test_the_docs_index_lists_every_page() -> None:
    index = (ROOT / "docs" / "README.md").read_text()
    for page in (ROOT / "docs").glob("*.md"):
        if page.name != "README.md":
            assert f"]({page.name})" in index, page.name
    for page in PENDING:
        assert f"]({page})" in index, page
