"""Flat state for the compiled tick: every block of the loop keeps its signals and state in two
flat buffers, one float64 and one int64, and exposes them as named numpy views.

Why: a call from Python into a compiled (numba) function costs about 200 ns plus 60 ns per
array argument on this project's machine. With each block's state in its own buffers, one
session packs all blocks into one float64 and one int64 buffer (``pack``), and the tick's kernels
reach everything through three arguments instead of dozens.

Layout convention, shared by a block's Python views and its compiled functions: the float
buffer holds ``len(VECTORS)`` vectors of ``n`` entries (vector k at ``k * n``), then the
``SCALARS`` (scalar k at ``len(VECTORS) * n + k``), then any variable-sized tail the block
declares (delay lines). The int buffer holds the block's ``INTS``. The compiled functions use
module constants with the same indices, listed next to the names.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

# compiled once per machine and cached beside the sources (the first run pays a few seconds)
jit = numba.njit(cache=True, nogil=True)
# for the small helpers that slice the buffers: inlined where they are called, which saves the
# call (about a third of a slice's cost here); the view itself still costs tens of ns for its
# reference counting, which is why the plant's kernels index by offset instead
jit_inline = numba.njit(cache=True, nogil=True, inline="always")


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


class Block:
    """One block's state: float buffer ``f`` and int buffer ``i`` with named views.

    Subclasses set ``VECTORS`` (names of n-vectors), ``SCALARS`` (names of floats) and ``INTS``
    (names of ints); scalars and ints are read and written through properties of their names.
    ``tail`` extra floats follow the scalars (see ``tail_view``)."""

    VECTORS: tuple[str, ...] = ()
    SCALARS: tuple[str, ...] = ()
    INTS: tuple[str, ...] = ()

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
        self._f_mv, self._i_mv = memoryview(self.f), memoryview(self.i)
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

    def __init_subclass__(cls) -> None:
        super().__init_subclass__()
        taken = {"f", "i", "n", "tail"} & {*cls.VECTORS, *cls.SCALARS, *cls.INTS}
        if taken:
            raise TypeError(f"{cls.__name__}: {sorted(taken)} name the block's own attributes")
        base = len(cls.VECTORS)
        for k, name in enumerate(cls.SCALARS):
            setattr(cls, name, _scalar_property(base, k))
        for k, name in enumerate(cls.INTS):
            setattr(cls, name, _int_property(k))


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

    def index_of(self, block: Block, name: str) -> int:
        """Position in the packed float buffer of a block's scalar, or of the first entry of
        any of its named views (vectors and tail views alike)."""
        if name in block.SCALARS:
            start = int(self.offsets[2 * self.blocks.index(block)])
            return start + block.scalar_index(name, block.n)
        view = getattr(block, name)
        if not np.shares_memory(view, self.f):
            raise ValueError(f"{name} of {type(block).__name__} is not in these buffers")
        return (view.ctypes.data - self.f.ctypes.data) // self.f.itemsize


def as_floats(x: Sequence[float] | np.ndarray) -> np.ndarray:
    """A float64 array of x (no copy if it is one): the standalone entry points' inputs."""
    return np.asarray(x, dtype=np.float64)
