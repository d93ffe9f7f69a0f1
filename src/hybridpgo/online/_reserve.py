"""Zero-filled arrays whose capacity is reserved, not allocated.

The online mode's arrays grow with the map.  Doubling an array copies it (at 10^4 poses the
path pool alone is tens of megabytes: a frame that doubles misses its budget), so on Linux the
arrays are views of an anonymous memory map of their whole capacity made with
``MAP_NORESERVE``: the capacity costs address space only, a page is allocated the first time it
is written, and an array never moves.  Where such a map cannot be made (another system, a
strict overcommit policy, an address-space limit) the arrays are ordinary ``numpy.zeros``
(whose pages are also allocated on first touch) and grow by doubling.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._memory import map_only, mapped_zeros


def reserved_zeros(shape: tuple[int, ...], dtype: Any = np.float64) -> tuple[np.ndarray, bool]:
    """``(array, reserved)``: a zero array of ``shape``; ``reserved`` is True when it is a view
    of a memory map that costs address space only until written
    (:func:`hybridpgo._memory.mapped_zeros` with ``overcommit=True``)."""
    return mapped_zeros(shape, dtype, overcommit=True)


def reserved_only(shape: tuple[int, ...], dtype: Any = np.float64) -> np.ndarray | None:
    """A zero array of ``shape`` reserved as address space only (as :func:`reserved_zeros`),
    or None where that cannot be done (then nothing is allocated)."""
    return map_only(shape, dtype, overcommit=True)


def grown(arr: np.ndarray, size: int, fill: float = 0) -> np.ndarray:
    """A copy of ``arr`` with capacity ``size`` along axis 0 (the new tail set to ``fill``)."""
    out, _ = reserved_zeros((size, *arr.shape[1:]), arr.dtype)
    out[: arr.shape[0]] = arr
    if fill != 0:
        out[arr.shape[0]:] = fill
    return out


def capacity(need: int, cap: int) -> int:
    """``cap`` doubled until it holds ``need``."""
    cap = max(cap, 1)
    while cap < need:
        cap *= 2
    return cap
