"""``hybridpgo warmup``: compile every Numba kernel now (or load it from the cache).

The first run of a solver compiles the kernels it uses (the hybrid sweeps with the GPS batches
or interpolated solving only when the graph and options need them) and caches them on disk
(Numba's ``__pycache__`` beside the sources, or ``NUMBA_CACHE_DIR``); later runs load them in
about a second.  ``warmup`` does that compilation up front, e.g. in a Docker image
build or after ``pip install``, with the same "compiling kernels" display as the first solve.
"""

from __future__ import annotations

import argparse
import time

from ._common import log

#: What each --solver value compiles (``all``: every one of them).
TARGETS = ("hybrid", "exact", "toro")


def _compile(target: str) -> float:
    if target == "hybrid":  # every sweep variant: with and without GPS, with interpolation,
        from ..solvers.hybrid.solver import ensure_compiled  # Woodbury and Givens

        return sum(ensure_compiled(gps, interp, givens) for gps in (False, True)
                   for interp in (False, True) for givens in (False, True))
    if target == "exact":
        from ..solvers.gauss_newton import ensure_compiled as ensure_exact

        return ensure_exact()
    from ..solvers.toro import ensure_compiled as ensure_toro

    return ensure_toro()


def run(args: argparse.Namespace) -> int:
    from .._numba import compile_status
    from ._progress import phase

    targets = TARGETS if args.solver == "all" else (args.solver,)
    if "hybrid" in targets:  # a second core compiles the other targets meanwhile
        from .._precompile import start

        others = [t for t in targets if t != "hybrid"]
        start(["finish", *others, "starts", *(["exact-solve"] if "exact" in others else [])])
    before = compile_status()
    t0 = time.perf_counter()
    for target in targets:
        with phase(f"compiling kernels (first run only): {target}", enabled=not args.quiet):
            _compile(target)
    elapsed = time.perf_counter() - t0
    compiled = compile_status().compiled - before.compiled
    if not args.quiet:
        how = (f"compiled {compiled} kernels" if compiled
               else "all kernels were already compiled (loaded from the cache)")
        log(f"hybridpgo warmup: {', '.join(targets)}: {how} in {elapsed:.1f} s")
    return 0
