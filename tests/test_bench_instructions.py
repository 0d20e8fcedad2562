"""tools/bench_instructions.py: the callgrind output parser (valgrind itself is not run here:
a run takes minutes; the tool's figures are in docs/benchmarks.md)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import bench_instructions  # noqa: E402

# Two objects with compressed names, a call whose inclusive cost must not count as self
# cost, a subposition line and a reused "(id)"; self costs: python 100 + 7 + 5, pinocchio 40.
CALLGRIND = """# callgrind format
version: 1
positions: line
events: Ir
summary: 152

ob=(1) /usr/lib/libpython3.11.so.1.0
fl=(1) ceval.c
fn=(1) _PyEval_EvalFrameDefault
10 100
cob=(2) /site-packages/pinocchio/pinocchio_pywrap_default.so
cfl=(2) rnea.cpp
cfn=(2) rnea
calls=3 20
11 40
+1 7
ob=(2)
fl=(2)
fn=(2)
20 40
ob=(1)
fl=(1)
fn=(1)
* 5
"""


def test_self_cost_per_object_skips_inclusive_call_costs(tmp_path) -> None:
    out = tmp_path / "callgrind.out"
    out.write_text(CALLGRIND)
    by_object = bench_instructions.instructions_by_object(out)
    assert by_object == {
        "/usr/lib/libpython3.11.so.1.0": 112,
        "/site-packages/pinocchio/pinocchio_pywrap_default.so": 40,
    }
    assert sum(by_object.values()) == 152  # the file's own summary line
    assert bench_instructions.categorise(by_object) == {
        "interpreter": 112,
        "Pinocchio + bindings": 40,
    }


def test_unknown_objects_are_counted_as_other() -> None:
    got = bench_instructions.categorise({"/lib/x86_64-linux-gnu/libc.so.6": 3, "/x/_foo.so": 2})
    assert got == {"C library": 3, bench_instructions.OTHER: 2}


def test_bad_arguments_are_one_line_and_exit_2(tmp_path) -> None:
    tool = str(ROOT / "tools" / "bench_instructions.py")
    for args in (["--ticks", "5"], [str(tmp_path / "missing.yaml")]):
        done = subprocess.run([sys.executable, tool, *args], capture_output=True, text=True)
        assert done.returncode == 2
        assert len(done.stderr.strip().splitlines()) == 1, done.stderr
        assert done.stderr.startswith("bench_instructions: error:")
