"""Helpers of the scalar tick path.

For a handful of joints, numpy's per-call cost (about 1 us for ``arr[:] = list`` on this
project's machine) exceeds the arithmetic; per-element writes cost a fraction of that.
"""

from __future__ import annotations

from collections.abc import MutableSequence, Sequence


def assign(dst: MutableSequence[float], src: Sequence[float]) -> None:
    """dst[j] = src[j] for every j, element by element (no temporary, no numpy call)."""
    for j, x in enumerate(src):
        dst[j] = x
