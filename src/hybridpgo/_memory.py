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
used.  Such a map is made only where the kernel honours ``MAP_NORESERVE`` and the address
space is not limited (:func:`can_overcommit`): under a strict overcommit policy every byte of
it would be committed, and under an address-space limit it would use up the room of every
other allocation.  Elsewhere than on Linux, or where no map can be made, the arrays are
``numpy.zeros``.
"""

from __future__ import annotations

import functools
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


@functools.cache
def can_overcommit() -> bool:
    """True where a ``MAP_NORESERVE`` map costs address space only: 64-bit Linux with an
    overcommit policy other than 2 (strict: every map is committed in full) and no limit on
    the process's address space or data (``RLIMIT_AS``, ``RLIMIT_DATA``: a private map counts
    against both).  False where any of these cannot be read.  Read once per process."""
    if not (sys.platform.startswith("linux") and sys.maxsize > 2**32):
        return False
    try:
        import resource

        with open("/proc/sys/vm/overcommit_memory", encoding="ascii") as fh:
            strict = fh.read().strip() == "2"
        limited = any(resource.getrlimit(what)[0] != resource.RLIM_INFINITY
                      for what in (resource.RLIMIT_AS, resource.RLIMIT_DATA))
    except (OSError, ValueError, ImportError):
        return False
    return not (strict or limited)


def map_only(shape: tuple[int, ...], dtype: Any = np.float64,
             overcommit: bool = False) -> np.ndarray | None:
    """A zero array of ``shape`` on an anonymous memory map (as :func:`mapped_zeros`), or
    None where no map can be made, or with ``overcommit`` where it would not cost address
    space only (:func:`can_overcommit`); then nothing is allocated."""
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    if overcommit and not can_overcommit():
        return None
    if sys.platform.startswith("linux") and nbytes >= mmap.PAGESIZE:
        flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | (_MAP_NORESERVE if overcommit else 0)
        try:
            m = mmap.mmap(-1, nbytes, flags=flags)
        except (OSError, ValueError, OverflowError):
            return None
        return np.frombuffer(m, dtype=dt).reshape(shape)
    return None
