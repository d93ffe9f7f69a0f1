"""A resident heap for the frames' compiled kernels (glibc).

The Numba kernels of a frame allocate their temporaries with ``malloc`` (a junction group's
batch: its Jacobian blocks, its union's 6x6 blocks, a workspace per path, several megabytes for
a loop of 2 000 nodes).  By default glibc serves a block of 128 KiB or more by a fresh
anonymous memory map, or from heap pages it has returned to the system since, so every such
block costs one page fault per 4 KiB the first time each page is written: valencia, 5 ms
frames, one batch of 1 742 entries took 888 faults and 6.4 ms against 2.6 ms predicted, and
paris2's frames took some 100 faults in a relaxation loop, every few hundred frames.  The cost
model cannot predict them.

:func:`keep_resident` makes such blocks come from the heap (``M_MMAP_THRESHOLD`` 32 MiB), keeps
the top of the heap mapped when blocks are freed (``M_TOP_PAD`` and ``M_TRIM_THRESHOLD``), and
writes a reserve of heap pages once, so that the kernels' temporaries land on pages that are
already there.  These are settings of the whole process (every thread's ``malloc``), made once
by the first :class:`~.solver.OnlineSolver` that asks (``OnlineConfig.heap_reserve_mb``; 0
leaves ``malloc`` as it is); the reserve stays resident for the life of the process.  Other
C libraries than glibc are left alone.
"""

from __future__ import annotations

import ctypes
import platform

#: ``mallopt`` parameters (glibc's ``malloc.h``).
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
#: Blocks below this come from the heap (glibc's largest default threshold on 64-bit systems).
MMAP_THRESHOLD = 32 << 20
#: The reserve is written in blocks of this size (each below ``MMAP_THRESHOLD``).
_BLOCK = 4 << 20

#: The largest reserve a configuration may ask for (MiB; a saved state's too).  Twice it, and
#: the threshold, stay below 2^31 bytes: ``mallopt`` takes an ``int``.
MAX_RESERVE_MB = 512
#: Bytes of heap kept resident so far in this process (0: none; the settings not made).
_kept = [0]


def keep_resident(reserve_mb: int) -> bool:
    """Keep ``reserve_mb`` MiB of the calling thread's heap resident and ``malloc``'s blocks
    below :data:`MMAP_THRESHOLD` on the heap (module docstring).  Done once per process; a
    later call with a larger reserve makes the settings and writes the heap again for it.
    False where the C library is not glibc or does not take the settings (nothing is then
    changed) or ``reserve_mb`` is 0."""
    want = int(reserve_mb) << 20
    if want == 0:
        return False
    if want <= _kept[0]:
        return _kept[0] > 0
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt, malloc, free = libc.mallopt, libc.malloc, libc.free
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    malloc.argtypes, malloc.restype = [ctypes.c_size_t], ctypes.c_void_p
    free.argtypes, free.restype = [ctypes.c_void_p], None
    # the top of the heap is trimmed only past twice the reserve, and then down to the reserve
    if not (mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) and mallopt(_M_TOP_PAD, want)
            and mallopt(_M_TRIM_THRESHOLD, 2 * want + MMAP_THRESHOLD)):
        return False
    blocks = []
    try:
        for _ in range(-(-want // _BLOCK)):
            p = malloc(_BLOCK)
            if not p:
                break
            ctypes.memset(p, 0, _BLOCK)
            blocks.append(p)
    finally:
        for p in reversed(blocks):  # they merge into the heap's top, which is kept
            free(p)
    _kept[0] = want
    return True
