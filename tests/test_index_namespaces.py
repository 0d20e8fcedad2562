"""Each block's index namespace (``Block.idx``, teleop_rt/flat.py) is derived from its one
declaration of fields, and the kernels take every index from the namespace of the block they
index (issue 25): the namespace agrees with the Python views of every block; a compiled kernel
sees the same numbers as constants; and a static check of the kernel modules finds no index
constant of their own, no name a block does not declare, no index of one kind used as another
(a vector's without its ``* n``, a scalar's with one) and no index arithmetic that mixes two
blocks."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import pkgutil
from pathlib import Path
from types import ModuleType

import numba
import numpy as np
import pytest

import teleop_rt
from teleop_rt.flat import COUNTS, Block, jit, vec

ROOT = Path(__file__).resolve().parents[1]
# the kernel modules whose indices all come from blocks' namespaces (mapping.py and
# task_math.py still use their own constants: ``Block.field.k``)
KERNEL_MODULES = (
    "teleop_rt/hal/sim.py", "teleop_rt/hal/signals.py", "teleop_rt/control.py",
    "teleop_rt/safety.py", "teleop_rt/lockstep.py", "teleop_rt/lockstep_fused.py",
    "teleop_rt/site_tick.py", "teleop_rt/transparency_tick.py", "teleop_rt/world.py",
    "teleop_rt/com/port.py", "teleop_rt/com/codec.py", "teleop_rt/com/channel.py",
    "teleop_rt/com/wire.py", "teleop_rt/com/link.py", "teleop_rt/com/playout.py",
    "teleop_rt/mapping.py", "teleop_rt/task_limits.py",
)  # fmt: skip


def _all_blocks() -> list[type[Block]]:
    for info in pkgutil.walk_packages(teleop_rt.__path__, "teleop_rt."):
        if ".can" not in info.name and "zenoh" not in info.name:  # (optional dependencies)
            importlib.import_module(info.name)
    found, todo = [], list(Block.__subclasses__())
    while todo:
        cls = todo.pop()
        found.append(cls)
        todo += cls.__subclasses__()
    return found


BLOCKS = _all_blocks()


def _bare(cls: type[Block]) -> Block:
    """A block of n = 3 with buffers and views but none of its own construction."""
    block = cls.__new__(cls)
    Block.__init__(block, 3)
    return block


def test_every_block_has_a_namespace_of_its_own_that_matches_its_declaration() -> None:
    assert len(BLOCKS) >= 25  # (every block of the package: 28 when this was written)
    types = {type(cls.idx) for cls in BLOCKS}
    assert len(types) == len(BLOCKS)  # a type per block: PlantState.idx is not Port.idx
    for cls in BLOCKS:
        idx, name = cls.idx, cls.__name__
        kinds = (cls.VECTORS, cls.SCALARS, cls.INTS)
        assert idx._fields == (*(x.upper() for kind in kinds for x in kind), *COUNTS), name
        assert (idx.N_VECTORS, idx.N_SCALARS, idx.N_INTS) == tuple(len(x) for x in kinds)
        block = _bare(cls)
        n = block.n
        for k, field in enumerate(cls.VECTORS):  # a vector at idx * n, where its view is
            view = getattr(block, field)
            view[:] = [0.5 + k, 1.5 + k, 2.5 + k]
            at = getattr(idx, field.upper()) * n
            assert block.f[at : at + n].tolist() == view.tolist(), (name, field)
        for k, field in enumerate(cls.SCALARS):  # a scalar at N_VECTORS n + idx
            setattr(block, field, 0.25 + k)
            assert block.f[idx.N_VECTORS * n + getattr(idx, field.upper())] == 0.25 + k
        for k, field in enumerate(cls.INTS):  # an int at idx
            setattr(block, field, 7 + k)
            assert block.i[getattr(idx, field.upper())] == 7 + k, (name, field)


def test_a_field_whose_name_collides_in_the_namespace_is_refused() -> None:
    from teleop_rt.flat import Scalar, Vector

    with pytest.raises(TypeError, match="differ only in case"):
        type("Clash", (Block,), {"dt": Scalar(), "DT": Vector()})
    with pytest.raises(TypeError, match="differ only in case"):
        type("Counted", (Block,), {"n_vectors": Scalar()})


def test_a_kernel_sees_the_namespace_as_the_same_constants() -> None:
    from teleop_rt.control import Pid
    from teleop_rt.hal.sim import PlantState

    @jit
    def indices(f: np.ndarray, n: int) -> tuple[int, int, int, float]:
        Ps = PlantState.idx
        return Ps.TAU, Pid.idx.DT, Pid.idx.N_VECTORS, vec(f, PlantState.idx.TAU, n)[1]

    f = np.arange(40.0)
    assert indices(f, 2) == (
        PlantState.idx.TAU, Pid.idx.DT, len(Pid.VECTORS), f[PlantState.idx.TAU * 2 + 1]
    )  # fmt: skip

    @jit
    def undeclared() -> int:
        return PlantState.idx.NO_SUCH_FIELD  # type: ignore[no-any-return]

    with pytest.raises(numba.core.errors.TypingError):
        undeclared()


# --- the static check of the kernel modules ------------------------------------------------
def _idx_block(
    node: ast.AST, aliases: dict[str, type[Block]], blocks: dict[str, type[Block]]
) -> type[Block] | None:
    """The block whose namespace ``node`` is: ``Block.idx`` or a local bound to one."""
    if isinstance(node, ast.Name):
        return aliases.get(node.id)
    if (
        isinstance(node, ast.Attribute) and node.attr == "idx"
        and isinstance(node.value, ast.Name) and node.value.id in blocks
    ):  # fmt: skip
        return blocks[node.value.id]
    return None


def _kind(cls: type[Block], name: str) -> str:
    lower = name.lower()
    if name == "N_VECTORS" or lower in cls.VECTORS:
        return "per n"  # multiplied by the block's n
    return "offset"  # a scalar, an int, N_SCALARS or N_INTS: added as it is


def _refs(node: ast.AST, aliases: dict, blocks: dict) -> set[type[Block]]:
    """The blocks whose namespaces one piece of index arithmetic (``+ - *``) reads."""
    if isinstance(node, ast.BinOp):
        return _refs(node.left, aliases, blocks) | _refs(node.right, aliases, blocks)
    if isinstance(node, ast.UnaryOp):
        return _refs(node.operand, aliases, blocks)
    if isinstance(node, ast.Attribute):
        cls = _idx_block(node.value, aliases, blocks)
        return set() if cls is None else {cls}
    return set()


def _findings(path: Path, module: ModuleType) -> list[str]:
    tree = ast.parse(path.read_text())
    blocks = {
        k: v for k, v in vars(module).items() if isinstance(v, type) and issubclass(v, Block)
    }
    found: list[str] = []
    where = path.name
    for node in tree.body:  # no index constants of the module's own
        if isinstance(node, ast.Assign):
            for sub in ast.walk(node.value):
                derived = isinstance(sub, ast.Attribute) and (
                    sub.attr in ("idx", "VECTORS", "SCALARS", "INTS")
                    or (sub.attr == "k" and isinstance(sub.value, ast.Attribute))
                )
                if derived:
                    found.append(f"{where}:{node.lineno}: an index constant of the module's own")
                    break
    for func in ast.walk(tree):
        if not isinstance(func, ast.FunctionDef):
            continue
        aliases: dict[str, type[Block]] = {}
        for node in ast.walk(func):  # Ps = PlantState.idx; Ps, Fb = PlantState.idx, Feedback.idx
            if isinstance(node, ast.Assign) and len(node.targets) == 1:
                target, value = node.targets[0], node.value
                pairs = (
                    zip(target.elts, value.elts, strict=False)
                    if isinstance(target, ast.Tuple) and isinstance(value, ast.Tuple)
                    else [(target, value)]
                )
                for t, v in pairs:
                    cls = _idx_block(v, {}, blocks)
                    if cls is not None and isinstance(t, ast.Name):
                        if aliases.get(t.id, cls) is not cls:
                            found.append(f"{where}:{node.lineno}: {t.id} names two blocks")
                        aliases[t.id] = cls
        parents = {c: p for p in ast.walk(func) for c in ast.iter_child_nodes(p)}
        for node in ast.walk(func):
            if not isinstance(node, ast.Attribute):
                continue
            cls = _idx_block(node.value, aliases, blocks)
            if cls is None:
                continue
            line = f"{where}:{node.lineno}: {cls.__name__}.idx.{node.attr}"
            if node.attr not in cls.idx._fields:
                found.append(f"{line}: not a field of {cls.__name__}")
                continue
            parent = parents[node]
            kind = _kind(cls, node.attr)
            if isinstance(parent, ast.Call) and getattr(parent.func, "id", "") == "vec":
                if node.attr.lower() not in cls.VECTORS:
                    found.append(f"{line}: vec() of a field that is not a vector")
            elif isinstance(parent, ast.BinOp) and isinstance(parent.op, ast.Mult):
                if kind != "per n":
                    found.append(f"{line}: multiplied by n, but it is not a vector")
            elif isinstance(parent, ast.BinOp | ast.Subscript) and kind != "offset":
                found.append(f"{line}: a vector's index used without its * n")
        for node in ast.walk(func):  # one block per piece of index arithmetic
            outer = parents.get(node)
            if isinstance(node, ast.BinOp) and not isinstance(outer, ast.BinOp | ast.UnaryOp):
                named = _refs(node, aliases, blocks)
                if len(named) > 1:
                    names = sorted(c.__name__ for c in named)
                    found.append(f"{where}:{node.lineno}: one index from {names}")
    return found


@pytest.mark.parametrize("path", KERNEL_MODULES)
def test_each_kernel_indexes_a_block_by_that_blocks_namespace(path: str) -> None:
    module = importlib.import_module(path.removesuffix(".py").replace("/", "."))
    findings = _findings(ROOT / path, module)
    assert not findings, "\n".join(findings)


def _probe(path: Path, source: str) -> list[str]:
    """The check's findings in a module of the given source (imported from path)."""
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("index_probe", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return _findings(path, module)


def test_the_static_check_catches_an_index_taken_from_the_wrong_place(tmp_path: Path) -> None:
    """The check above, on kernels that each break one rule (and on one that breaks none)."""
    cases = {
        "good": "f[Ps.N_VECTORS * n + Ps.DT] + f[Ps.TAU * n + j] + vec(f, Ct.TAU, n)[0]",
        "undeclared": "f[Ps.NO_SUCH * n]",
        "vector without n": "f[Ps.TAU + j]",
        "scalar times n": "f[Ps.DT * n]",
        "vec of a scalar": "vec(f, Ct.INV_V_S, n)[0]",
        "two blocks": "f[Ps.N_VECTORS * n + Ct.INV_V_S]",
    }
    expected = {
        "undeclared": "not a field", "vector without n": "without its * n",
        "scalar times n": "not a vector", "vec of a scalar": "vec() of a field",
        "two blocks": "one index from ['ComputedTorque', 'PlantState']",
    }  # fmt: skip
    probe = tmp_path / "probe.py"
    header = (
        "from teleop_rt.control import ComputedTorque\n"
        "from teleop_rt.flat import vec\n"
        "from teleop_rt.hal.sim import PlantState\n\n\n"
        "def kernel(f, n, j):\n"
        "    Ps, Ct = PlantState.idx, ComputedTorque.idx\n"
    )
    for case, expression in cases.items():
        findings = _probe(probe, f"{header}    return {expression}\n")
        if case == "good":
            assert findings == [], findings
        else:
            assert len(findings) == 1 and expected[case] in findings[0], (case, findings)
    findings = _probe(probe, "from teleop_rt.hal.sim import PlantState\n\nTAU = PlantState.tau.k\n")
    assert len(findings) == 1 and "an index constant of the module's own" in findings[0]
    findings = _probe(probe, f"{header}    Ps = ComputedTorque.idx\n    return f[Ps.DT]\n")
    assert any("Ps names two blocks" in x for x in findings), findings
