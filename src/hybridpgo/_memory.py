"""Large zero arrays on demand-zero pages of an anonymous memory map (Linux).

NumPy asks the kernel for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on every array of
4 MiB or more.  Where the kernel compacts memory to serve such a request (``defrag`` set to
``madvise``, the default of many distributions), the first write to a large fresh array can
stall: the hybrid solver's set-up on a 1M-pose city, which writes 1.8 GB of fresh blocks, took
7.3 s that way and 2.9-3.0 s with the blocks here, its sweep as fast either way
(``benchmarks/results/2026-11-30-scale-b`` against ``-scale-c`` and ``-scale-d``).  The arrays
here come from an anonymous map instead: each page is allocated, zeroed, the first time it is
written, in the kernel's base page size (or in huge pages only where the system gives them to
every map, ``enabled=always``).

``overcommit=False`` (the default) commits the memory up front like any allocation, so a
machine short of memory refuses it with :class:`MemoryError`; ``overcommit=True``
(``MAP_NORESERVE``) costs address space only until written, for capacities that may never be
used.  Elsewhere than on Linux, or where no map can be made, the arrays are ``numpy.zeros``.
"""

from __future__ import annotations

import mmap
import sys
from typing import Any

import numpy as np

#: Linux's ``MAP_NORESERVE``: no swap is reserved for the map (pages come on first write);
#: Python's value where its mmap module has one, else 0x4000 (x86 and ARM Linux).
_MAP_NORESERVE = getattr(mmap, "MAP_NORESERVE", 0x4000)


def mapped_zeros(shape: tuple[int, ...], dtype: Any = np.float64,
                 overcommit: bool = False) -> tuple[np.ndarray, bool]:
    """``(array, mapped)``: a zero array of ``shape``; ``mapped`` is True when it is a view of
    an anonymous memory map (module docstring), False when it is ``numpy.zeros``."""
    arr = map_only(shape, dtype, overcommit)
    if arr is not None:
        return arr, True
    return np.zeros(shape, np.dtype(dtype)), False


def map_only(shape: tuple[int, ...], dtype: Any = np.float64,
             overcommit: bool = False) -> np.ndarray | None:
    """A zero array of ``shape`` on an anonymous memory map (as :func:`mapped_zeros`), or
    None where no map can be made (then nothing is allocated)."""
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    if sys.platform.startswith("linux") and nbytes >= mmap.PAGESIZE:
        flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | (_MAP_NORESERVE if overcommit else 0)
        try:
            m = mmap.mmap(-1, nbytes, flags=flags)
        except (OSError, ValueError, OverflowError):
            return None
        return np.frombuffer(m, dtype=dt).reshape(shape)
    return None
