"""Flat state for the compiled tick: every block of the loop keeps its signals and state in two
flat buffers, one float64 and one int64, and exposes them as named numpy views.

Why: a call from Python into a compiled (numba) function costs about 200 ns plus 60 ns per
array argument on this project's machine. With each block's state in its own buffers, one
session packs all blocks into one float64 and one int64 buffer (``pack``), and the tick's kernels
reach everything through three arguments instead of dozens.

Layout convention, shared by a block's Python views and its compiled functions: the float
buffer holds ``len(VECTORS)`` vectors of ``n`` entries (vector k at ``k * n``), then the
``SCALARS`` (scalar k at ``len(VECTORS) * n + k``), then any variable-sized tail the block
declares (delay lines). The int buffer holds the block's ``INTS``. The compiled functions take
the indices from the block's own namespace, ``MyBlock.idx`` (``Block``), derived from the same
declaration.
"""

from __future__ import annotations

import hashlib
from abc import ABCMeta
from collections import namedtuple
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, ClassVar, cast, overload

import numba
import numpy as np
from numba.core.imputils import lower_constant
from numba.core.typing.templates import AttributeTemplate
from numba.extending import infer_getattr, lower_getattr, models, register_model, typeof_impl

from teleop_rt.kernel_lock import CompileLock, locked


def _source_hash() -> str:
    """A hash of every source file of the package: the compiled kernels' cache key."""
    digest = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _kernel_cache_dir() -> Path:
    """Where compiled kernels are cached: a folder per version of the package's sources.

    numba's own cache checks a kernel's file but not the files of the kernels it calls, so an
    edit to a callee (or a revert) could leave stale machine code; keyed by a hash of all the
    sources, any edit starts a fresh folder. ``NUMBA_CACHE_DIR`` moves the root; to debug a
    kernel as Python, run with ``NUMBA_DISABLE_JIT=1``."""
    # (numba.config makes its options at import time, out of mypy's sight: attr-defined)
    configured = numba.config.CACHE_DIR  # type: ignore[attr-defined]
    root = Path(configured or Path.home() / ".cache" / "teleop_rt" / "numba")
    return root / _source_hash()


# compiled once per version of the sources and cached (the first run pays some seconds); the
# decorators below pick the folder up when they are applied
numba.config.CACHE_DIR = str(_kernel_cache_dir())  # type: ignore[attr-defined]
# processes that start together compile one at a time (numba's cache is not safe otherwise)
COMPILE_LOCK = CompileLock(Path(numba.config.CACHE_DIR))  # type: ignore[attr-defined]
# (a folder that cannot be written: not cached at all, rather than in numba's fallback folders,
# which the hash does not key; COMPILE_LOCK says so at the first compilation)
_njit = numba.njit(cache=COMPILE_LOCK.caches, nogil=True)
# for the small helpers that slice the buffers: inlined where they are called, which saves the
# call (about a third of a slice's cost here); the view itself still costs tens of ns for its
# reference counting, which is why the plant's kernels index by offset instead
_njit_inline = numba.njit(cache=COMPILE_LOCK.caches, nogil=True, inline="always")


def jit(func: Callable[..., Any]) -> Any:
    """A compiled, cached kernel (``numba.njit``) that compiles under ``COMPILE_LOCK``."""
    return locked(_njit(func), COMPILE_LOCK)


def jit_inline(func: Callable[..., Any]) -> Any:
    """``jit``, inlined where it is called."""
    return locked(_njit_inline(func), COMPILE_LOCK)


def bound_kernel(kernel: Any, args: tuple[Any, ...], *rest: Any) -> Callable[..., Any]:
    """``kernel``'s compiled entry point (``compiled_for``) with ``args`` bound in front
    (``partial``: passed in C, no list built per call), for arguments ``rest`` like these
    examples. With ``NUMBA_DISABLE_JIT=1`` the kernel itself, bound alike (a stage called
    inside it is still looked up, and traced, at call time: tests/tick_trace.py)."""
    return partial(compiled_for(kernel, *args, *rest), *args)


def compiled_for(kernel: Any, *args: Any) -> Callable[..., Any]:
    """``kernel``'s compiled code for the types of ``args`` (loaded or compiled now), to call
    per tick in place of ``kernel``: a numba dispatcher works out each argument's type on
    every call (about 0.9k instructions per array here, twice what the call itself costs),
    the compiled entry point takes the arguments as typed here. Call it only with arguments
    of these types (the bound buffers, Pinocchio's float64 results): it does not check them.
    With ``NUMBA_DISABLE_JIT=1``, ``kernel`` itself."""
    if not hasattr(kernel, "overloads"):
        return cast(Callable[..., Any], kernel)
    return cast(Callable[..., Any], kernel.compile(tuple(kernel.typeof_pyval(a) for a in args)))


# an index a kernel computes, unsigned: numba checks a signed index for a negative value at
# every access (Python's wraparound) and takes an unsigned one as it is. The same arithmetic,
# bit for bit, in fewer instructions (task_math.dls_inverse: 10.0k -> 5.9k per call at m = n =
# 6). Keep such an index unsigned throughout, its constants too: numba makes a float of an
# int64 variable + a uint64, and a signed index again of a literal + a uint64.
Index = np.uint64


@jit_inline
def vec(f: np.ndarray, k: int, n: int) -> np.ndarray:
    """Vector k of a block's float buffer (a view; compiled code only)."""
    return f[k * n : (k + 1) * n]


@jit_inline
def floats_of(f: np.ndarray, offsets: np.ndarray, block: int) -> np.ndarray:
    """Block ``block``'s float buffer within packed buffers (compiled code only)."""
    return f[offsets[2 * block] :]


@jit_inline
def ints_of(i: np.ndarray, offsets: np.ndarray, block: int) -> np.ndarray:
    """Block ``block``'s int buffer within packed buffers (compiled code only)."""
    return i[offsets[2 * block + 1] :]


def float_view(a: np.ndarray) -> memoryview[float]:
    """A memoryview of a float64 array, for element reads and writes from Python (a fraction of
    numpy's per-element cost), typed as floats: numpy's stubs give ``ndarray.__buffer__`` only
    on Python 3.12+, and a memoryview's items are ints unless said otherwise."""
    return cast("memoryview[float]", memoryview(a))  # type: ignore[arg-type]


def int_view(a: np.ndarray) -> memoryview[int]:
    """A memoryview of an integer array (see ``float_view``)."""
    return memoryview(a)  # type: ignore[arg-type]


class _Declared:
    """What a field declaration holds: its doc, whether it is a parameter, its name (from the
    class attribute) and its index ``k`` among the block's fields of its kind."""

    def __init__(self, doc: str = "", *, param: bool = False) -> None:
        self.doc, self.param = doc, param
        self.name, self.k, self.base = "", -1, 0

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name


class Vector(_Declared):
    """A block's n-vector field (declared once, as a class attribute): its index ``k`` among the
    block's vectors is derived from the declaration order (the compiled kernels read it as
    ``MyBlock.idx.NAME``); instances see a float64 view."""

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> Vector: ...
    @overload
    def __get__(self, obj: Block, owner: type | None = None) -> np.ndarray: ...
    def __get__(self, obj: Block | None, owner: type | None = None) -> Vector | np.ndarray:
        if obj is None:
            return self
        return obj.f[self.k * obj.n : (self.k + 1) * obj.n]  # (normally shadowed by _bind)


class Scalar(_Declared):
    """A block's float field; read and written from Python through a memoryview (a fraction
    of numpy's per-element cost). ``k``: its index among the scalars."""

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> Scalar: ...
    @overload
    def __get__(self, obj: Block, owner: type | None = None) -> float: ...
    def __get__(self, obj: Block | None, owner: type | None = None) -> Scalar | float:
        if obj is None:
            return self
        return obj._f_mv[self.base * obj.n + self.k]

    def __set__(self, obj: Block, value: float) -> None:
        obj._f_mv[self.base * obj.n + self.k] = value


class Int(_Declared):
    """A block's int64 field (flags, counters, codes). ``k``: its index in the int buffer."""

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> Int: ...
    @overload
    def __get__(self, obj: Block, owner: type | None = None) -> int: ...
    def __get__(self, obj: Block | None, owner: type | None = None) -> Int | int:
        if obj is None:
            return self
        return obj._i_mv[self.k]

    def __set__(self, obj: Block, value: int) -> None:
        obj._i_mv[self.k] = value


Field = Vector | Scalar | Int


class BlockMeta(ABCMeta):
    """The type of every block class: what numba recognises a block class by (``BlockClass``).
    (An ``ABCMeta``, so that a block can also implement an abstract interface: ``Link``.)"""


class Block(metaclass=BlockMeta):
    """One block's state: float buffer ``f`` and int buffer ``i`` with named views.

    Fields are declared once, as class attributes: ``Vector()`` (n-vectors), ``Scalar()``
    (floats) and ``Int()`` (ints), each optionally ``param=True`` (set at construction and
    never written by a tick: gains, impedances, limits; the rest is state). Their order in the
    class gives the layout and the indices (``MyBlock.name.k``, ``MyBlock.idx``); the names are
    also listed in ``VECTORS``, ``SCALARS`` and ``INTS`` (derived; older blocks may still
    declare these tuples directly). ``tail`` extra floats follow the scalars (``tail_view``).

    Layout, shared by a block's Python views and its compiled functions: the float buffer
    holds the vectors (vector k at ``k * n``), then the scalars (scalar k at
    ``len(VECTORS) * n + k``), then the tail; the int buffer holds the ints.

    ``idx``: the block's index namespace for the compiled kernels, derived from the same
    declaration: each field's index under its upper-case name (``PlantState.idx.TAU``: vector
    ``tau``'s k) and the counts ``N_VECTORS``, ``N_SCALARS``, ``N_INTS`` (a scalar sits at
    ``idx.N_VECTORS * n + idx.NAME``). It is a named tuple of a type of the block's own
    (``MyBlock.Idx``), which numba lowers into a kernel as a compile-time constant (as it does
    a module's int: no cost). ``BlockClass`` lets a kernel reach it through the block's class,
    so that each index names its block where it is used: ``f[s + PlantState.idx.TAU * n]``, or
    ``Ps = PlantState.idx`` at the top of a kernel of many."""

    VECTORS: tuple[str, ...] = ()
    SCALARS: tuple[str, ...] = ()
    INTS: tuple[str, ...] = ()
    # (generated per block: typed Any, as mypy cannot see generated names; test_index_namespaces
    # checks every use against the declaration)
    idx: ClassVar[Any]
    Idx: ClassVar[type]
    PARAMS: frozenset[str] = frozenset()  # fields that are parameters, not state
    TAIL_IS_STATE = True  # a tail (delay lines, contacts) is state unless a block says not

    def __init__(self, n: int, tail: int = 0) -> None:
        self.n = n
        self.tail = tail
        self.f = np.zeros(self.float_size)
        self.i = np.zeros(max(len(self.INTS), 1), dtype=np.int64)
        self._bind()

    @property
    def float_size(self) -> int:
        return len(self.VECTORS) * self.n + len(self.SCALARS) + self.tail

    @property
    def tail_start(self) -> int:
        return len(self.VECTORS) * self.n + len(self.SCALARS)

    def _bind(self) -> None:
        """(Re)create the named vector views on the current buffers."""
        n = self.n
        for k, name in enumerate(self.VECTORS):
            setattr(self, name, self.f[k * n : (k + 1) * n])
        # scalars and ints are read and written one at a time from Python: through memoryviews,
        # a fraction of numpy's per-element cost
        self._f_mv, self._i_mv = float_view(self.f), int_view(self.i)
        self._bind_tail()

    def _bind_tail(self) -> None:
        """Views into the tail (blocks with one override this)."""

    def adopt(self, f: np.ndarray, i: np.ndarray) -> None:
        """Move the state into the given buffers (slices of a session's packed buffers)."""
        f[:] = self.f
        i[:] = self.i
        self.f, self.i = f, i
        self._bind()

    @classmethod
    def scalar_index(cls, name: str, n: int) -> int:
        """Where scalar ``name`` sits in the float buffer of a block of vectors of n."""
        return len(cls.VECTORS) * n + cls.SCALARS.index(name)

    def state_positions(self) -> tuple[list[int], list[int]]:
        """Positions of the block's state (not its parameters) in its float and int buffers."""
        n = self.n
        fs: list[int] = []
        is_: list[int] = []
        for k, name in enumerate(self.VECTORS):
            if name not in self.PARAMS:
                fs += range(k * n, (k + 1) * n)
        base = len(self.VECTORS) * n
        fs += [base + k for k, name in enumerate(self.SCALARS) if name not in self.PARAMS]
        if self.TAIL_IS_STATE:
            fs += range(self.tail_start, self.tail_start + self.tail)
        is_ += [k for k, name in enumerate(self.INTS) if name not in self.PARAMS]
        return fs, is_

    def __init_subclass__(cls) -> None:
        super().__init_subclass__()
        declared: list[Field] = []
        for klass in reversed(cls.__mro__):
            declared += [x for x in vars(klass).values() if isinstance(x, Vector | Scalar | Int)]
        if declared:  # the tuples follow from the declarations
            seen: dict[str, Field] = {}
            for x in declared:
                seen.pop(x.name, None)
                seen[x.name] = x  # a redeclared name keeps the subclass's, in its place
            fields = list(seen.values())
            cls.VECTORS = tuple(x.name for x in fields if isinstance(x, Vector))
            cls.SCALARS = tuple(x.name for x in fields if isinstance(x, Scalar))
            cls.INTS = tuple(x.name for x in fields if isinstance(x, Int))
            cls.PARAMS = frozenset(x.name for x in fields if x.param)
        taken = {"f", "i", "n", "tail"} & {*cls.VECTORS, *cls.SCALARS, *cls.INTS}
        if taken:
            raise TypeError(f"{cls.__name__}: {sorted(taken)} name the block's own attributes")
        base = len(cls.VECTORS)
        for k, name in enumerate(cls.VECTORS):
            existing = vars(cls).get(name)
            if isinstance(existing, Vector):
                existing.k = k
        for k, name in enumerate(cls.SCALARS):
            existing = vars(cls).get(name)
            if isinstance(existing, Scalar):
                existing.k, existing.base = k, base
            else:
                setattr(cls, name, _scalar_property(base, k))
        for k, name in enumerate(cls.INTS):
            existing = vars(cls).get(name)
            if isinstance(existing, Int):
                existing.k = k
            else:
                setattr(cls, name, _int_property(k))
        cls.Idx, cls.idx = _index_namespace(cls)


COUNTS = ("N_VECTORS", "N_SCALARS", "N_INTS")  # the counts in every block's ``idx``


def _index_namespace(cls: type[Block]) -> tuple[type, Any]:
    """A block's ``Idx`` type and ``idx`` namespace (``Block``): its fields' indices by their
    upper-case names, then ``COUNTS``."""
    indices = {
        **{name.upper(): k for k, name in enumerate(cls.VECTORS)},
        **{name.upper(): k for k, name in enumerate(cls.SCALARS)},
        **{name.upper(): k for k, name in enumerate(cls.INTS)},
    }
    fields = len(cls.VECTORS) + len(cls.SCALARS) + len(cls.INTS)
    clash = set(indices) & set(COUNTS)
    if len(indices) != fields or clash:
        raise TypeError(f"{cls.__name__}: field names that differ only in case, or {COUNTS}")
    counts = (len(cls.VECTORS), len(cls.SCALARS), len(cls.INTS))
    # (a type made at run time, which mypy's namedtuple support cannot follow)
    make: Callable[..., Any] = namedtuple
    idx_type = make(f"{cls.__name__}Idx", [*indices, *COUNTS], module=cls.__module__)
    # (pickled by reference, as numba's cache may: ``module.Block.Idx``)
    idx_type.__qualname__ = f"{cls.__qualname__}.Idx"
    return idx_type, idx_type(*indices.values(), *counts)


def _scalar_property(base: int, k: int) -> property:
    def get(self: Block) -> float:
        return self._f_mv[base * self.n + k]

    def put(self: Block, value: float) -> None:
        self._f_mv[base * self.n + k] = value

    return property(get, put)


def _int_property(k: int) -> property:
    def get(self: Block) -> int:
        return self._i_mv[k]

    def put(self: Block, value: int) -> None:
        self._i_mv[k] = value

    return property(get, put)


class Packed:
    """The blocks of one session in one float64 and one int64 buffer.

    ``offsets`` holds, per block in the given order, the start of its float and of its int
    buffer (``offsets[2 k]``, ``offsets[2 k + 1]``): what a kernel slices them with."""

    def __init__(self, blocks: Sequence[Block]) -> None:
        self.blocks = list(blocks)
        f_size = sum(b.f.size for b in self.blocks)
        i_size = sum(b.i.size for b in self.blocks)
        self.f = np.zeros(f_size)
        self.i = np.zeros(i_size, dtype=np.int64)
        self.offsets = np.zeros(2 * len(self.blocks), dtype=np.int64)
        fo = io = 0
        for k, block in enumerate(self.blocks):
            fs, is_ = block.f.size, block.i.size
            self.offsets[2 * k], self.offsets[2 * k + 1] = fo, io
            block.adopt(self.f[fo : fo + fs], self.i[io : io + is_])
            fo += fs
            io += is_

    def state_index(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions of every block's state (not its parameters) in the packed float and int
        buffers: a snapshot is ``f[fs], i[is_]``, a restore the reverse, one copy each."""
        fs: list[int] = []
        is_: list[int] = []
        for k, block in enumerate(self.blocks):
            bf, bi = block.state_positions()
            fs += [int(self.offsets[2 * k]) + x for x in bf]
            is_ += [int(self.offsets[2 * k + 1]) + x for x in bi]
        return np.array(fs, dtype=np.int64), np.array(is_, dtype=np.int64)

    def index_of(self, block: Block, name: str) -> int:
        """Position in the packed float buffer of a block's scalar, or of the first entry of
        any of its named views (vectors and tail views alike); of an int, ``int_position``'s
        code for its place in the int buffer (< 0: a log row's gather reads ints too)."""
        if name in block.INTS:
            return int_position(int(self.offsets[2 * self.blocks.index(block) + 1])
                                + block.INTS.index(name))  # fmt: skip
        if name in block.SCALARS:
            start = int(self.offsets[2 * self.blocks.index(block)])
            return start + block.scalar_index(name, block.n)
        view = getattr(block, name)
        if not np.shares_memory(view, self.f):
            raise ValueError(f"{name} of {type(block).__name__} is not in these buffers")
        return (view.ctypes.data - self.f.ctypes.data) // self.f.itemsize


class BlockClass(numba.types.Dummy):
    """numba's type of a block class used in a kernel (``PlantState`` in ``PlantState.idx.TAU``):
    nothing at run time, its ``idx`` a constant. numba cannot type a class otherwise; a
    module-level alias of the namespace would compile as well, but would name its block only
    where it is bound."""

    def __init__(self, cls: type[Block]) -> None:
        self.cls = cls
        super().__init__(f"BlockClass({cls.__module__}.{cls.__qualname__})")

    @property
    def key(self) -> type[Block]:
        return self.cls


register_model(BlockClass)(models.OpaqueModel)


@typeof_impl.register(BlockMeta)
def _typeof_block_class(val: type[Block], c: object) -> BlockClass:
    return BlockClass(val)


@lower_constant(BlockClass)
def _lower_block_class(context: Any, builder: Any, ty: BlockClass, pyval: object) -> Any:
    return context.get_dummy_value()


@infer_getattr
class _BlockClassAttributes(AttributeTemplate):
    key = BlockClass

    def resolve_idx(self, ty: BlockClass) -> Any:
        return numba.typeof(ty.cls.idx)


@lower_getattr(BlockClass, "idx")
def _lower_idx(context: Any, builder: Any, ty: BlockClass, val: object) -> Any:
    return context.get_constant_generic(builder, numba.typeof(ty.cls.idx), ty.cls.idx)


def int_position(k: int) -> int:
    """The gather code of entry k of a packed int buffer: -1 - k (a float's is its position,
    >= 0), so one gather array reads both buffers (``teleop_rt.recording.recorder.fill_row``)."""
    return -1 - k


def as_floats(x: Sequence[float] | np.ndarray) -> np.ndarray:
    """A float64 array of x (no copy if it is one): the standalone entry points' inputs."""
    return np.asarray(x, dtype=np.float64)
