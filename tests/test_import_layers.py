"""The package's layers (issue 25): its module-level imports form no cycle, so every module can
be imported on its own and the HAL's interface imports no implementation. Imports inside a
function (resolved on use, as the backend registry's ``"module:factory"`` names) and under
``TYPE_CHECKING`` do not count: they run after every module has loaded."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "teleop_rt"


def module_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    """Each module of the package and the package modules it imports at module level."""
    files = {}
    for path in root.rglob("*.py"):
        parts = path.relative_to(root.parent).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph: dict[str, set[str]] = {name: set() for name in files}

    def owner(target: str) -> str | None:
        while target not in files and "." in target:
            target = target.rsplit(".", 1)[0]
        return target if target in files else None

    for name, path in files.items():
        for node in ast.parse(path.read_text()).body:  # module level (not under an `if`)
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            graph[name] |= {t for t in map(owner, targets) if t and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, 1972)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_package_imports_form_no_cycle() -> None:
    graph = module_graph()
    assert len(graph) > 80 and graph["teleop_rt.config"]  # the walk saw the package
    assert cycles(graph) == []


def test_a_cycle_is_found() -> None:
    """The check itself: one import back (declarations -> config, which imports it) closes a
    cycle."""
    graph = module_graph()
    assert "teleop_rt.declarations" in graph["teleop_rt.config"]
    graph["teleop_rt.declarations"].add("teleop_rt.config")
    assert any({"teleop_rt.config", "teleop_rt.declarations"} <= set(c) for c in cycles(graph))


def test_the_hal_interface_imports_no_implementation() -> None:
    """hal/base.py and hal/signals.py (what kernels and backends share) reach neither the
    simulated nor the CAN backend, nor the session, through any chain of imports."""
    graph = module_graph()

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for w in graph[todo.pop()] - seen:
                seen.add(w)
                todo.append(w)
        return seen

    for interface in ("teleop_rt.hal.base", "teleop_rt.hal.signals"):
        bad = {m for m in reach(interface)
               if m.startswith(("teleop_rt.hal.can", "teleop_rt.hal.sim")) or m in (
                   "teleop_rt.session", "teleop_rt.site", "teleop_rt.lockstep")}  # fmt: skip
        assert not bad, (interface, sorted(bad))
