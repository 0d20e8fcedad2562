"""Helpers of the scalar tick path.

For a handful of joints, numpy's per-call cost (about 1 us for ``arr[:] = list`` on this
project's machine) exceeds the arithmetic; per-element writes cost a fraction of that.
"""

from __future__ import annotations

from collections.abc import MutableSequence, Sequence

import numpy as np


def assign(dst: MutableSequence[float], src: Sequence[float]) -> None:
    """dst[j] = src[j] for every j, element by element (no temporary, no numpy call)."""
    for j, x in enumerate(src):
        dst[j] = x


def shared_vector(n: int) -> tuple[np.ndarray, memoryview]:
    """A float64 numpy array (what Pinocchio takes) and a memoryview of the same memory.

    Element writes through the memoryview cost about half of numpy's ``__setitem__``; the
    array sees them at once (no copy)."""
    buf = bytearray(8 * n)
    return np.frombuffer(buf, dtype=np.float64), memoryview(buf).cast("d")
