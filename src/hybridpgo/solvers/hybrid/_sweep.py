"""Sweeps over the constraints (paper Algorithm 1, III-H).

Constraints are relaxed in the given order (increasing root depth for a full sweep); GPS
readings are buffered and relaxed together in batches of ``gps_batch_size`` (III-G), the buffer
being flushed when full and before every relative constraint.  A sweep can stop at a deadline
on the CPU's cycle counter (the online mode's time budget).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..._numba import cycle_counter, kernel
from ._batch import batch_relax, batch_relax_exact
from ._interpolate import relax_interpolated
from ._step import RELAX
from .problem import (
    BATCH_REJECTED,
    NUM_COUNTS,
    Count,
    Problem,
    State,
    StepKind,
    Update,
    domain,
    is_gps,
    new_workspace,
)


@kernel
def max_domain(prob: Problem) -> int:
    """The largest domain size (at least 1): the workspace capacity single updates need."""
    dmax = 1
    for c in range(prob.path_ptr.shape[0] - 1):
        d = domain(prob, c)[1]
        if d > dmax:
            dmax = d
    return dmax


@kernel
def _count_batch(nu: int, t0: np.uint64, buf: np.ndarray, nbuf: int, cycles: np.ndarray,
                 batch_cycles: np.ndarray, counts: np.ndarray) -> bool:
    """Book a GPS batch started at cycle ``t0`` that returned ``nu``; True when rejected."""
    dc = cycle_counter() - t0
    if dc > counts[Count.MAX_CYCLES]:
        counts[Count.MAX_CYCLES] = dc
    counts[Count.BATCHES] += 1
    for q in range(nbuf):
        cycles[buf[q]] = dc // nbuf
    batch_cycles[buf[0]] = dc
    if nu == BATCH_REJECTED:
        counts[Count.REJECTED] += nbuf
        return True
    return False


@kernel
def _flush(prob: Problem, state: State, buf: np.ndarray, nbuf: int, tau: float, mu: float,
           slot: np.ndarray, xb: np.ndarray, nodes: np.ndarray, cycles: np.ndarray,
           batch_cycles: np.ndarray, counts: np.ndarray, d_max: int = 0) -> bool:
    """Relax the buffered GPS readings as one batch (interpolated when ``d_max`` > 0 is below
    the union's size, III-G); True when the batch was rejected."""
    t0 = cycle_counter()
    nu = batch_relax(prob, state, buf, nbuf, tau, mu, slot, xb, nodes, d_max)
    return _count_batch(nu, t0, buf, nbuf, cycles, batch_cycles, counts)


@kernel
def _flush_exact(prob: Problem, state: State, buf: np.ndarray, nbuf: int, tau: float, mu: float,
                 slot: np.ndarray, xb: np.ndarray, nodes: np.ndarray, cycles: np.ndarray,
                 batch_cycles: np.ndarray, counts: np.ndarray) -> bool:
    """:func:`_flush` without interpolated solving (``batch_relax_exact``: compiles less)."""
    t0 = cycle_counter()
    nu = batch_relax_exact(prob, state, buf, nbuf, tau, mu, slot, xb, nodes)
    return _count_batch(nu, t0, buf, nbuf, cycles, batch_cycles, counts)


#: The :data:`~._step.RELAX` variants the sweeps call, as module globals: the sweep kernels'
#: closures hold only booleans.  Numba's cache key of a closure includes the pickle of its
#: cells, and a kernel in a cell pickles differently in every process: the sweep then missed
#: the cache and compiled again in every run.
_RELAX = RELAX[False, int(StepKind.WOODBURY)]
_RELAX_GIVENS = RELAX[False, int(StepKind.GIVENS)]
_RELAX_GPS = RELAX[True, int(StepKind.WOODBURY)]
_RELAX_GPS_GIVENS = RELAX[True, int(StepKind.GIVENS)]


def _make_sweep(with_gps: bool, with_interpolation: bool, givens: bool) -> Any:
    """The sweep kernel of one variant: GPS batches and interpolated solving are compiled in
    only when the flag says so (a constant of the closure: Numba prunes the dead branch before
    typing it, so a plain sweep never compiles the GPS batches (:func:`_flush_exact`,
    ``batch_relax``) or ``relax_interpolated``, about two thirds of the hybrid solver's compile
    time, and a sweep without ``d_max`` never the interpolated batch).  Its single updates are
    the :data:`~._step.RELAX` variant with the GPS linearization only ``with_gps`` and one
    solve, Givens' when ``givens`` (the ``step_kind`` argument must then agree)."""

    def sweep_variant(prob: Problem, state: State, order: np.ndarray, tau: float, mu: float,
                      step_kind: int, gps_batch_size: int, dmax: int, d_max: int,
                      deadline: np.uint64, cycles: np.ndarray, batch_cycles: np.ndarray,
                      counts: np.ndarray, apply: bool) -> int:
        wk = new_workspace(dmax)
        nt = state.rot.shape[0]
        if with_interpolation:
            sub = new_workspace(max(min(d_max, dmax), 1))
            keep = np.empty(max(d_max, 1), np.int64)
        if with_gps:
            slot = np.full(nt, -1, np.int64)
            xb = np.empty((nt, 6))
            nodes = np.empty(nt, np.int64)
            buf = np.empty(max(gps_batch_size, 1), np.int64)
        nbuf = 0
        first_bad = -1
        n_order = order.shape[0]
        for idx in range(n_order + 1):
            c = order[idx] if idx < n_order else -1
            if c >= 0 and idx > 0 and cycle_counter() >= deadline:
                c = -1
            if with_gps:
                gps = c >= 0 and apply and is_gps(prob, c)
                if nbuf > 0 and (not gps or nbuf >= gps_batch_size):
                    if with_interpolation:
                        bad = _flush(prob, state, buf, nbuf, tau, mu, slot, xb, nodes, cycles,
                                     batch_cycles, counts, d_max)
                    else:
                        bad = _flush_exact(prob, state, buf, nbuf, tau, mu, slot, xb, nodes,
                                           cycles, batch_cycles, counts)
                    if bad and first_bad < 0:
                        first_bad = buf[0]
                    nbuf = 0
                if gps:
                    buf[nbuf] = c
                    nbuf += 1
                    continue
            if c < 0:
                counts[Count.DONE] += idx
                break
            t0 = cycle_counter()
            if with_interpolation and apply and 0 < d_max < domain(prob, c)[1]:
                st = relax_interpolated(prob, state, wk, sub, keep, c, tau, mu, step_kind, d_max)
            elif with_gps and givens:
                st = _RELAX_GPS_GIVENS(prob, state, wk, c, tau, mu, step_kind, apply)
            elif with_gps:
                st = _RELAX_GPS(prob, state, wk, c, tau, mu, step_kind, apply)
            elif givens:
                st = _RELAX_GIVENS(prob, state, wk, c, tau, mu, step_kind, apply)
            else:
                st = _RELAX(prob, state, wk, c, tau, mu, step_kind, apply)
            dc = cycle_counter() - t0
            cycles[c] = dc
            if dc > counts[Count.MAX_CYCLES]:
                counts[Count.MAX_CYCLES] = dc
            if st == Update.CAPPED:
                counts[Count.CAPPED] += 1
            elif st == Update.REJECTED:
                counts[Count.REJECTED] += 1
                if first_bad < 0:
                    first_bad = c
        return first_bad

    sweep_variant.__qualname__ = sweep_variant.__name__ = (
        "sweep" + ("_gps" if with_gps else "") + ("_interpolated" if with_interpolation else "")
        + ("_givens" if givens else ""))
    return kernel(sweep_variant)


#: The sweep kernels by ``(with_gps, with_interpolation, givens)``; each is compiled on first
#: use.
SWEEPS = {(g, i, v): _make_sweep(g, i, v) for g in (False, True) for i in (False, True)
          for v in (False, True)}


def sweep_kernel(with_gps: bool, with_interpolation: bool, givens: bool = False) -> Any:
    """The sweep kernel a problem needs: with GPS batches when it has GPS readings, with
    interpolated solving when ``d_max`` > 0, with the Givens solve when asked, Woodbury's
    otherwise (compiling only what is used)."""
    return SWEEPS[bool(with_gps), bool(with_interpolation), bool(givens)]


def sweep(prob: Problem, state: State, order: np.ndarray, tau: float, mu: float,
          step_kind: int, gps_batch_size: int, dmax: int, d_max: int, deadline: np.uint64,
          cycles: np.ndarray, batch_cycles: np.ndarray, counts: np.ndarray) -> int:
    """One pass over the constraints in ``order`` (paper Algorithm 1).

    ``dmax`` is the largest domain (workspace capacity); ``d_max`` > 0 solves single updates of
    longer domains, and GPS batches of larger unions, for about ``d_max`` nodes (interpolated
    solving, III-E, III-G), 0 never.

    ``cycles[c]`` receives the cycle count of constraint c's update (a batch's count is shared
    among its members, and ``batch_cycles[first member]`` gets the whole batch's count);
    ``counts`` accumulates the entries named by :class:`Count`.  When the cycle counter passes
    ``deadline`` no further constraint is started (the GPS buffer is still flushed);
    ``counts[Count.DONE]`` tells how many were processed.  Returns the first rejected
    constraint or -1.

    Runs the variant of :func:`sweep_kernel` the problem needs (GPS batches only when it has GPS
    readings, interpolation only with ``d_max`` > 0).
    """
    return _run(sweep_kernel(prob.gps_pos.shape[0] > 0, d_max > 0, step_kind == StepKind.GIVENS),
                prob, state, order, tau, mu, step_kind, gps_batch_size, dmax, d_max, deadline,
                cycles, batch_cycles, counts, True)


def _run(kern: Any, prob: Problem, state: State, order: np.ndarray, tau: float, mu: float,
         step_kind: int, gps_batch_size: int, dmax: int, d_max: int,
         deadline: int | np.uint64, cycles: np.ndarray, batch_cycles: np.ndarray,
         counts: np.ndarray, apply: bool) -> int:
    """Call a sweep kernel with normalized argument types, so each variant is compiled for one
    signature only: a writable ``order`` (``step``) and the tree's read-only one (``run``), an
    IntEnum step kind or a NumPy integer would each compile the whole sweep again."""
    order = np.ascontiguousarray(order, dtype=np.int32).view()
    order.flags.writeable = False
    return int(kern(prob, state, order, float(tau), float(mu), int(step_kind),
                    int(gps_batch_size), int(dmax), int(d_max), np.uint64(deadline), cycles,
                    batch_cycles, counts, bool(apply)))


def init_blocks(prob: Problem, state: State, dmax: int, with_gps: bool = False,
                with_interpolation: bool = False, givens: bool = False) -> None:
    """𝔅(H) and every constraint's contribution at the current poses (no step).

    Runs the sweep kernel of the given variant (the one the solve uses: nothing more to
    compile) with ``apply=False`` over every constraint: every variant then relaxes each
    constraint, GPS readings one by one, with :func:`relax` (only the blocks are wanted), so
    the blocks are the same whatever the variant.
    """
    state.bdiag[:] = 0.0
    state.contrib[:] = 0.0
    nc = prob.path_ptr.shape[0] - 1
    _run(sweep_kernel(with_gps, with_interpolation, givens), prob, state,
         np.arange(nc, dtype=np.int32), 0.0, 0.0,
         StepKind.GIVENS if givens else StepKind.WOODBURY, 1, dmax, 0, np.iinfo(np.uint64).max,
         np.zeros(nc, np.uint64), np.zeros(nc, np.uint64), np.zeros(NUM_COUNTS, np.int64), False)
