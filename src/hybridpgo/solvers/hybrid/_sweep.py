"""The relaxation loop over a list of constraints (paper Algorithm 1, III-H).

Constraints are relaxed in the given order (increasing root depth for a full sweep); GPS
readings are buffered and relaxed together in batches of ``gps_batch_size`` (III-G), the buffer
being flushed when full and before every relative constraint.  The loop stops at a deadline on
the CPU's cycle counter.

One loop serves the whole-graph solver and the online mode.  Under the *admission policy*
(:class:`._admission.Admission`, the online mode's frames) an update starts only when its
predicted cost fits before the deadline, the constraints of a junction group are relaxed
together as one batch, and every constraint's χ² before its update is recorded.  Each variant
is compiled separately (:func:`loop_kernel`) so the whole-graph sweeps carry none of it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from ..._numba import cycle_counter, kernel
from . import _admission as adm
from ._admission import Admission
from ._batch import batch_relax, batch_relax_exact
from ._interpolate import relax_interpolated
from ._step import BY_ARGUMENT, RELAX
from .problem import (
    BATCH_REJECTED,
    NUM_COUNTS,
    Count,
    Problem,
    State,
    StepKind,
    Update,
    Workspace,
    domain,
    is_gps,
    new_workspace,
)


class Scratch(NamedTuple):
    """Buffers of a relaxation loop, owned by its caller and reused from call to call."""

    wk: Workspace
    """Single updates of domains up to the workspace's capacity."""
    sub: Workspace
    """Interpolated solving's reduced updates."""
    keep: np.ndarray
    """(d_max,) the kept nodes of an interpolated update."""
    slot: np.ndarray
    """(T,) -1 everywhere between batches (the batches' union numbering)."""
    xb: np.ndarray
    """(T, 6) a batch's steps."""
    nodes: np.ndarray
    """(T,) a batch's union nodes."""
    buf: np.ndarray
    """(gps_batch_size,) the GPS buffer."""
    cycles: np.ndarray
    """(C,) cycles of each constraint's last update (a batch's shared among its members)."""
    batch_cycles: np.ndarray
    """(C,) cycles of a whole batch, at its first member."""


def new_scratch(num_tree_nodes: int, num_constraints: int, dmax: int, d_max: int = 0,
                gps_batch_size: int = 1) -> Scratch:
    """Scratch for a problem of these sizes (``dmax``: the largest domain)."""
    return Scratch(new_workspace(max(dmax, 1)), new_workspace(max(min(d_max, dmax), 1)),
                   np.empty(max(d_max, 1), np.int64), np.full(num_tree_nodes, -1, np.int64),
                   np.empty((num_tree_nodes, 6)), np.empty(num_tree_nodes, np.int64),
                   np.empty(max(gps_batch_size, 1), np.int64),
                   np.zeros(num_constraints, np.uint64), np.zeros(num_constraints, np.uint64))


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
def _book_batch(nu: int, t0: np.uint64, buf: np.ndarray, nbuf: int, cycles: np.ndarray,
                batch_cycles: np.ndarray, counts: np.ndarray) -> bool:
    """Book a batch started at cycle ``t0`` that returned ``nu``; True when rejected."""
    dc = cycle_counter() - t0
    if dc > counts[Count.MAX_CYCLES]:
        counts[Count.MAX_CYCLES] = dc
    counts[Count.BATCHES] += 1
    for q in range(nbuf):
        cycles[buf[q]] = dc // nbuf
    batch_cycles[buf[0]] = dc
    if nu == BATCH_REJECTED:
        counts[Count.REJECTED] += nbuf
        if counts[Count.FIRST_REJECTED] == 0:
            counts[Count.FIRST_REJECTED] = buf[0] + 1
        return True
    return False


@kernel
def _flush(prob: Problem, state: State, sc: Scratch, nbuf: int, tau: float, mu: float,
           counts: np.ndarray, d_max: int) -> float:
    """Relax the buffered GPS readings as one batch (interpolated when ``d_max`` > 0 is below
    the union's size, III-G); returns its cycles."""
    t0 = cycle_counter()
    nu = batch_relax(prob, state, sc.buf, nbuf, tau, mu, sc.slot, sc.xb, sc.nodes, d_max)
    _book_batch(nu, t0, sc.buf, nbuf, sc.cycles, sc.batch_cycles, counts)
    return float(cycle_counter() - t0)


@kernel
def _flush_exact(prob: Problem, state: State, sc: Scratch, nbuf: int, tau: float, mu: float,
                 counts: np.ndarray) -> float:
    """:func:`_flush` without interpolated solving (``batch_relax_exact``: compiles less)."""
    t0 = cycle_counter()
    nu = batch_relax_exact(prob, state, sc.buf, nbuf, tau, mu, sc.slot, sc.xb, sc.nodes)
    _book_batch(nu, t0, sc.buf, nbuf, sc.cycles, sc.batch_cycles, counts)
    return float(cycle_counter() - t0)


@kernel
def group_work(prob: Problem, pol: Admission, grp: int) -> int:
    """The work of a junction group's batch, in domain-node units."""
    d = 0
    for j in range(pol.group_ptr[grp], pol.group_ptr[grp + 1]):
        d += adm.batch_work(prob, pol.depth, pol.group_members[j])
    return d


@kernel
def group_cost(prob: Problem, pol: Admission, grp: int) -> float:
    """The predicted cycles of a junction group's batch: its work under the cost model, and
    the solve of its members' capacitance system."""
    nb = pol.group_ptr[grp + 1] - pol.group_ptr[grp]
    return adm.predict(pol.model, group_work(prob, pol, grp), True) + adm.capacitance_cost(nb)


@kernel
def _relax_group(prob: Problem, state: State, sc: Scratch, pol: Admission, grp: int,
                 stamp: int, tau: float, mu: float, counts: np.ndarray) -> None:
    """Relax a junction group's members together as one batch (their χ² recorded first); the
    group is marked with ``stamp`` (relaxed once per call of the loop)."""
    lo = pol.group_ptr[grp]
    nb = pol.group_ptr[grp + 1] - lo
    pol.group_stamp[grp] = stamp
    members = pol.group_members[lo: lo + nb]
    ro = np.empty((3, 3))
    to = np.empty(3)
    for j in range(nb):
        cj = members[j]
        pol.chi2[cj] = adm.chi2_of(prob, state, cj, sc.wk, ro, to)
    t0 = cycle_counter()
    nu = batch_relax_exact(prob, state, members, nb, tau, mu, sc.slot, sc.xb, sc.nodes, 0,
                           False)
    adm.learn(pol.model, max(group_work(prob, pol, grp), 1), float(cycle_counter() - t0), True)
    _book_batch(nu, t0, members, nb, sc.cycles, sc.batch_cycles, counts)


#: The :data:`~._step.RELAX` variants the loops call, as module globals: the loop kernels'
#: closures hold only booleans.  Numba keys a closure's cache entry on the pickle of its cells,
#: and a kernel in a cell pickles differently in every process (the loop would miss the cache
#: and compile again in every run).
_RELAX = RELAX[False, int(StepKind.WOODBURY)]
_RELAX_GIVENS = RELAX[False, int(StepKind.GIVENS)]
_RELAX_GPS = RELAX[True, int(StepKind.WOODBURY)]
_RELAX_GPS_GIVENS = RELAX[True, int(StepKind.GIVENS)]
_RELAX_ANY = RELAX[False, BY_ARGUMENT]
_RELAX_GPS_ANY = RELAX[True, BY_ARGUMENT]


def _make_loop(with_gps: bool, with_interpolation: bool, givens: bool, admission: bool) -> Any:
    """The loop kernel of one variant: GPS batches, interpolated solving and the admission
    policy are compiled in only when the flag says so (constants of the closure: Numba prunes
    the dead branches before typing them, so a plain sweep never compiles the GPS batches or
    ``relax_interpolated``, about two thirds of the hybrid solver's compile time).  Single
    updates are the :data:`~._step.RELAX` variant with the GPS linearization only
    ``with_gps`` and one solve, Givens' when ``givens`` (``step_kind`` must then agree); under
    the policy the solve is chosen by ``step_kind`` at run time.  Under the policy an entry
    starts only when its predicted cost fits before the deadline, except the first of a call
    with ``force_first``; when that one's junction group does not fit, it is relaxed alone
    (a single update costs O(its path), the group's batch O(every member's path and the
    depth of its roots) and more per entry), and so is every member of a group whose batch
    is predicted to take longer than the call's whole budget (``pol.span``)."""

    def loop_variant(prob: Problem, state: State, sc: Scratch, order: np.ndarray, tau: float,
                     mu: float, step_kind: int, gps_batch_size: int, d_max: int,
                     deadline: np.uint64, counts: np.ndarray, apply: bool, pol: Admission,
                     stamp: int, max_updates: int, force_first: bool, skip: bool) -> int:
        wk = sc.wk
        nbuf = 0
        buf_cost = 0.0
        started = 0
        n_order = order.shape[0]
        stop_at = n_order
        ro = np.empty((3, 3))
        to = np.empty(3)
        for idx in range(n_order + 1):
            c = order[idx] if idx < n_order else -1
            grp = -1
            if admission and c >= 0:
                gps = is_gps(prob, c)
                grp = pol.group_of[c]
                if grp >= 0 and pol.group_stamp[grp] == stamp:
                    continue  # relaxed with its group in this call
                if started >= max_updates:
                    c = -1
                    stop_at = idx
                else:
                    pred = 0.0
                    if grp >= 0:
                        pred = group_cost(prob, pol, grp)
                        if pred > pol.span[0]:  # no frame holds the batch: member by member
                            grp = -1
                    if grp < 0:
                        if gps:
                            pred = adm.predict(pol.model, domain(prob, c)[1], True) + buf_cost
                        else:
                            pred = adm.predict(pol.model, domain(prob, c)[1], False)
                    now = float(cycle_counter())
                    late = now + pred > float(deadline)
                    if late and not (force_first and started == 0):
                        if skip and now < float(deadline):
                            counts[Count.SKIPPED] += 1
                            continue  # a shorter one may still fit
                        # (with skip: past the deadline none fits, the rest are skipped too)
                        counts[Count.SKIPPED] += n_order - idx if skip else 1
                        c = -1
                        stop_at = idx
                    elif late and grp >= 0:
                        # started whatever its cost, but a junction group's batch would
                        # overrun: this member alone, by a single update (its group stays,
                        # and each member comes first in a later frame likewise)
                        grp = -1
            elif c >= 0 and idx > 0 and cycle_counter() >= deadline:
                c = -1
                stop_at = idx
            if with_gps:
                gps = c >= 0 and apply and is_gps(prob, c) and grp < 0
                if nbuf > 0 and (not gps or nbuf >= gps_batch_size):
                    if with_interpolation:
                        dc = _flush(prob, state, sc, nbuf, tau, mu, counts, d_max)
                    else:
                        dc = _flush_exact(prob, state, sc, nbuf, tau, mu, counts)
                    if admission:
                        ne = 0
                        for q in range(nbuf):
                            ne += domain(prob, sc.buf[q])[1]
                        adm.learn(pol.model, max(ne, 1), dc, True)
                    nbuf = 0
                    buf_cost = 0.0
                if gps:
                    if admission:
                        started += 1
                        pol.chi2[c] = adm.gps_chi2(prob, state, c, ro, to)
                        buf_cost += adm.predict(pol.model, domain(prob, c)[1], True)
                    sc.buf[nbuf] = c
                    nbuf += 1
                    continue
            if c < 0:
                break
            if admission:
                started += 1
                if grp >= 0:
                    _relax_group(prob, state, sc, pol, grp, stamp, tau, mu, counts)
                    continue
            t0 = cycle_counter()
            if with_interpolation and apply and 0 < d_max < domain(prob, c)[1]:
                st = relax_interpolated(prob, state, wk, sc.sub, sc.keep, c, tau, mu,
                                        step_kind, d_max)
            elif admission:
                if with_gps:
                    st = _RELAX_GPS_ANY(prob, state, wk, c, tau, mu, step_kind, apply)
                else:
                    st = _RELAX_ANY(prob, state, wk, c, tau, mu, step_kind, apply)
            elif with_gps:
                if givens:
                    st = _RELAX_GPS_GIVENS(prob, state, wk, c, tau, mu, step_kind, apply)
                else:
                    st = _RELAX_GPS(prob, state, wk, c, tau, mu, step_kind, apply)
            elif givens:
                st = _RELAX_GIVENS(prob, state, wk, c, tau, mu, step_kind, apply)
            else:
                st = _RELAX(prob, state, wk, c, tau, mu, step_kind, apply)
            dc = cycle_counter() - t0
            sc.cycles[c] = dc
            if dc > counts[Count.MAX_CYCLES]:
                counts[Count.MAX_CYCLES] = dc
            if admission:
                s = 0.0
                for i in range(6):
                    s += wk.r[i] * wk.r[i]
                pol.chi2[c] = s
                adm.learn(pol.model, domain(prob, c)[1], float(dc), False)
            if st == Update.CAPPED:
                counts[Count.CAPPED] += 1
            elif st == Update.REJECTED:
                counts[Count.REJECTED] += 1
                if counts[Count.FIRST_REJECTED] == 0:
                    counts[Count.FIRST_REJECTED] = c + 1
        counts[Count.DONE] += started if admission else stop_at
        return int(stop_at)

    loop_variant.__qualname__ = loop_variant.__name__ = (
        "relax_loop" + ("_gps" if with_gps else "")
        + ("_interpolated" if with_interpolation else "") + ("_givens" if givens else "")
        + ("_admission" if admission else ""))
    return kernel(loop_variant)


#: The loop kernels by ``(with_gps, with_interpolation, givens, admission)``; each is compiled
#: on first use.
LOOPS = {(g, i, v, a): _make_loop(g, i, v, a) for g in (False, True) for i in (False, True)
         for v in (False, True) for a in (False, True)}


def loop_kernel(with_gps: bool, with_interpolation: bool, givens: bool = False,
                admission: bool = False) -> Any:
    """The loop kernel a problem needs: with GPS batches when it has GPS readings, with
    interpolated solving when ``d_max`` > 0, with the Givens solve when asked, Woodbury's
    otherwise, with the admission policy for budgeted frames (compiling only what is used)."""
    return LOOPS[bool(with_gps), bool(with_interpolation), bool(givens), bool(admission)]


#: The admission arrays of a loop without the policy (never read).
NO_ADMISSION = Admission(np.zeros(3), np.zeros(0), np.zeros(0, np.int64), np.zeros(1, np.int64),
                         np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int32),
                         np.full(1, np.inf))


def run_loop(kern: Any, prob: Problem, state: State, sc: Scratch, order: np.ndarray,
             tau: float, mu: float, step_kind: int, gps_batch_size: int, d_max: int,
             deadline: int | np.uint64, counts: np.ndarray, apply: bool = True,
             pol: Admission = NO_ADMISSION, stamp: int = 0, max_updates: int = 1 << 62,
             force_first: bool = False, skip: bool = False) -> int:
    """Call a loop kernel with normalized argument types, so each variant is compiled for one
    signature only (a writable and a read-only ``order``, an IntEnum step kind or a NumPy
    integer would each compile the whole loop again).  Returns how many leading entries of
    ``order`` were processed (all of them unless the deadline or ``max_updates`` stopped the
    loop, or an update did not fit and ``skip`` is False, or with ``skip`` the deadline
    passed)."""
    order = np.ascontiguousarray(order, dtype=np.int32).view()
    order.flags.writeable = False
    return int(kern(prob, state, sc, order, float(tau), float(mu), int(step_kind),
                    int(gps_batch_size), int(d_max), np.uint64(deadline), counts, bool(apply),
                    pol, int(stamp), int(max_updates), bool(force_first), bool(skip)))


def sweep(prob: Problem, state: State, sc: Scratch, order: np.ndarray, tau: float, mu: float,
          step_kind: int, gps_batch_size: int, d_max: int, deadline: np.uint64,
          counts: np.ndarray) -> int:
    """One pass over the constraints in ``order`` (paper Algorithm 1), no admission policy.

    ``d_max`` > 0 solves single updates of longer domains, and GPS batches of larger unions,
    for about ``d_max`` nodes (interpolated solving, III-E, III-G), 0 never.  ``sc.cycles[c]``
    receives the cycle count of constraint c's update (a batch's count is shared among its
    members, and ``sc.batch_cycles[first member]`` gets the whole batch's count); ``counts``
    accumulates the entries named by :class:`Count`.  When the cycle counter passes ``deadline``
    no further constraint is started (the GPS buffer is still flushed).  Returns how many
    entries of ``order`` were processed.
    """
    kern = loop_kernel(prob.gps_pos.shape[0] > 0, d_max > 0, step_kind == StepKind.GIVENS)
    return run_loop(kern, prob, state, sc, order, tau, mu, step_kind, gps_batch_size, d_max,
                    deadline, counts)


def init_blocks(prob: Problem, state: State, sc: Scratch, with_gps: bool = False,
                with_interpolation: bool = False, givens: bool = False) -> None:
    """𝔅(H) and every constraint's contribution at the current poses (no step).

    Runs the loop kernel of the given variant (the one the solve uses: nothing more to compile)
    with ``apply=False`` over every constraint: every variant then relaxes each constraint, GPS
    readings one by one, with the single update (only the blocks are wanted), so the blocks are
    the same whatever the variant.
    """
    state.bdiag[:] = 0.0
    state.contrib[:] = 0.0
    nc = prob.path_ptr.shape[0] - 1
    run_loop(loop_kernel(with_gps, with_interpolation, givens), prob, state, sc,
             np.arange(nc, dtype=np.int32), 0.0, 0.0,
             StepKind.GIVENS if givens else StepKind.WOODBURY, 1, 0, np.iinfo(np.uint64).max,
             np.zeros(NUM_COUNTS, np.int64), False)
