"""Every build of a tick runs the stages of ``teleop_rt.tick_stages`` in the order derived
there: a site alone, the lock-step session, the fused simulated pair, two sites over a link
stepped from Python, and the standalone two-port. Each build runs with every stage's calls
traced (tests/tick_trace.py, kernels as Python under NUMBA_DISABLE_JIT=1), so a stage moved,
dropped or doubled in any build (or in the list) fails here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from teleop_rt import tick_stages as ts
from teleop_rt.site_tick import SITE_ORDER

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def traces() -> dict:
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "tick_trace.py")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)


def steps(trace: dict) -> list[tuple[str, str]]:
    return [tuple(s) for s in trace["steps"]]  # type: ignore[misc]


def meets(trace: dict) -> dict[str, set[str]]:
    return {site: set(c) for site, c in trace["meets"].items()}


def test_each_site_alone_runs_the_list_in_order(traces: dict) -> None:
    trace = traces["alone"]
    got, has = steps(trace), meets(trace)
    assert has == {"hsi": {"workspace_box", "task_space"}, "to": {"workspace_box", "task_space"}}
    for site in ("hsi", "to"):
        assert [s for s in got if s[1] == site] == ts.present(ts.alone(site), has)
    # the sites' sense phases, then their update phases (the link's contract)
    assert got == [s for s in ts.present(ts.phased(), has) if s[1] != ts.PAIR_NAME]


def test_the_lockstep_session_runs_the_list_in_order(traces: dict) -> None:
    trace = traces["lockstep"]
    assert not trace["fused"]
    assert steps(trace) == ts.present(ts.lockstep(packed=True), meets(trace))


def test_the_fused_simulated_pair_runs_the_list_in_order(traces: dict) -> None:
    trace = traces["fused"]
    assert trace["fused"], "the joint-space config must fuse its two simulated plants"
    assert steps(trace) == ts.present(ts.lockstep(packed=True), meets(trace))
    assert meets(trace) == {"hsi": {"workspace_box"}, "to": {"workspace_box"}}


def test_a_python_stepped_pair_runs_the_list_in_phases(traces: dict) -> None:
    trace = traces["phased"]
    assert steps(trace) == ts.present(ts.phased(), meets(trace))


def test_the_two_port_runs_the_port_stages_of_the_list(traces: dict) -> None:
    assert steps(traces["two_port"]) == ts.two_port()
    assert [name for name, _ in ts.two_port()] == [
        "port_input", "port_input", "deliver", "port", "port", "push", "monitor",
    ]  # fmt: skip


def test_the_list_names_real_blocks_and_keeps_each_kernel_whole() -> None:
    known = {*SITE_ORDER, *ts.PAIR_BLOCKS, ts.RNEA}
    for stage in ts.SITE_STAGES:
        assert set(stage.reads) | set(stage.writes) <= known, stage.name
        assert stage.runs in (ts.HOST, ts.SITE, ts.LINK, ts.PAIR)
        assert not stage.when or stage.when in ts.CONDITIONS
    kernels = [s.part for s in ts.SITE_STAGES if s.runs == ts.SITE]
    runs = [k for j, k in enumerate(kernels) if j == 0 or kernels[j - 1] != k]
    assert runs == ["site_sense", "site_before_models", "site_after_models"]
    # what a stage reads from this tick is written by an earlier stage of it
    order = [s.name for s in ts.SITE_STAGES]
    for value, writer, reader in ((ts.RNEA, "rnea", "torque"), ("rx", "deliver", "port"),
                                  ("tx", "port_input", "send"),
                                  ("computed_torque", "prepare", "rnea")):  # fmt: skip
        assert value in ts.STAGES[writer].writes and value in ts.STAGES[reader].reads
        assert order.index(writer) < order.index(reader)
    assert ts.SENSE_PHASE == ("read", "check", "port_input", "send")
