"""The only place Numba options live (STYLE.md §3).

``kernel`` is the decorator every hot loop uses.  ``fastmath`` stays off: it breaks NaN checks
and bit-reproducibility.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Any, TypeVar

import numba

F = TypeVar("F", bound=Callable[..., Any])

_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


def kernel(fn: F) -> F:
    """Compile ``fn`` with the project's Numba options (typed once here for mypy)."""
    return numba.njit(**_OPTIONS)(fn)  # type: ignore[no-any-return]


def _make_cycle_counter() -> Any:
    """``cycle_counter()`` -> uint64: the CPU's cycle counter (``llvm.readcyclecounter``).

    Used to time single constraint updates inside compiled sweeps without leaving compiled code
    (~20 ns per read).  Counts are converted to seconds by calibrating against
    ``time.perf_counter`` around each sweep.
    """
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    @intrinsic
    def cycle_counter(typingctx: Any) -> Any:
        sig = types.uint64()

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            fnty = ir.FunctionType(ir.IntType(64), [])
            fn = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
                builder.module, fnty, "llvm.readcyclecounter"
            )
            return builder.call(fn, [])

        return sig, codegen

    return cycle_counter


cycle_counter = _make_cycle_counter()


@kernel
def read_cycles() -> int:
    """The cycle counter, read from Python."""
    return cycle_counter()  # type: ignore[no-any-return]


@functools.cache
def cycles_per_second() -> float:
    """Frequency of the cycle counter, calibrated once against ``time.perf_counter``."""
    read_cycles()
    c0, t0 = read_cycles(), time.perf_counter()
    time.sleep(0.05)
    c1, t1 = read_cycles(), time.perf_counter()
    return float(c1 - c0) / (t1 - t0)
