"""Aggregated-gradient sweeps: the hybrid step with a SAGA-style right-hand side.

The paper's update of constraint c solves ``H_c x = g_c`` with ``g_c = J_c^T r_c`` (eq. 25).  At
the optimum the gradient ``G = sum_c g_c`` vanishes but the single ``g_c`` do not, so every
update keeps moving and only the decaying temperature damps the oscillation: the optimum is not
a fixed point of the sweeps.

Here every constraint c keeps a memory ``m_c`` of its contribution (per domain node, 6 numbers,
like its blocks of 𝔅(H)) and every node i the sum ``M_i`` of the memories of the ``n_i``
constraints through it.  Relaxing c solves the same hybrid system with the right-hand side

    b_i = g_c,i - m_c,i + M_i / n_i,          i in D_c,

then moves the memory towards the fresh contribution, ``m_c += rate (g_c - m_c)``.  The term
``m_c,i - M_i / n_i`` is the force c is expected to keep at the optimum (the memories' share that
is not balanced at node i removed: these estimates sum to zero at every node, as the forces at a
stationary point do), and the step only corrects what differs from it.  With ``rate = 1`` this is
SAGA (Defazio et al. 2014) per node; smaller rates average the memory over several visits (an
ADMM-like dual update), which keeps the sweeps stable where ``rate = 1`` diverges on M3500.  With a
memory that has settled at a stationary point (``m_c = g_c``, ``M = G = 0``) the step is exactly
zero: the optimum is a fixed point.  The memory starts at zero, so the first visits are the
paper's steps.  The cost per update stays O(d) (Woodbury with a general right-hand side,
:func:`woodbury_solve_rhs`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..._numba import cycle_counter, kernel
from ._dense import chol_inplace, chol_solve_cols, solve_lt
from ._linearize import linearize
from ._step import accumulate_blocks, cap_and_apply
from ._sweep import _flush_exact
from .problem import (
    Count,
    FloatArray,
    Problem,
    State,
    Update,
    Workspace,
    domain,
    is_gps,
    new_workspace,
)


class Memory(NamedTuple):
    """The remembered gradient contributions of the aggregated sweeps."""

    grad: FloatArray
    """(nnz, 6) ``g_c,k = J_c^kT r_c`` of every constraint at its last relaxation (path order)."""
    gsum: FloatArray
    """(T, 6) ``G_i = sum over constraints through i of their remembered g_c,i``."""


def new_memory(num_entries: int, num_nodes: int) -> Memory:
    """Zeroed memory (fill it with :func:`init_memory`)."""
    return Memory(np.zeros((num_entries, 6)), np.zeros((num_nodes, 6)))


@kernel
def contribution(d: int, kr: int, jac: np.ndarray, r: np.ndarray, out: np.ndarray) -> None:
    """``out[k] = J_k^T r`` for the d domain nodes (kr rows)."""
    for k in range(d):
        for p in range(6):
            acc = 0.0
            for t in range(kr):
                acc += jac[k, t, p] * r[t]
            out[k, p] = acc


@kernel
def init_memory(prob: Problem, state: State, mem: Memory, dmax: int) -> None:
    """Every constraint's contribution ``g_c`` at the current poses, and their sums ``G``."""
    wk = new_workspace(dmax)
    g = np.empty((dmax, 6))
    mem.gsum[:] = 0.0
    for c in range(prob.path_ptr.shape[0] - 1):
        s, d = domain(prob, c)
        if d == 0:
            continue
        kr, _na = linearize(prob, c, state.rot, state.trans, wk, wk.jac)
        contribution(d, kr, wk.jac, wk.r, g)
        for k in range(d):
            i = prob.path_node[s + k]
            for p in range(6):
                mem.grad[s + k, p] = g[k, p]
                mem.gsum[i, p] += g[k, p]


@kernel
def woodbury_solve_rhs(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, b: np.ndarray,
                       w: np.ndarray, x: np.ndarray) -> None:
    """``x = (J^T J + B)^-1 b`` for a general right-hand side b, O(d) (DESIGN §4's Woodbury form).

    ``B = blockdiag(L_k L_k^T)``; with ``W_k = L_k^-1 J_k^T``, ``y_k = L_k^-1 b_k``,
    ``S = I + sum_k W_k^T W_k`` and ``z = S^-1 sum_k W_k^T y_k``:  ``x_k = L_k^-T (y_k - W_k z)``.
    ``w`` receives the W_k; ``x`` holds the y_k in between.
    """
    smat = np.zeros((6, 6))
    for i in range(kr):
        smat[i, i] = 1.0
    zz = np.zeros((6, 1))
    for k in range(d):
        lk = lfac[k]
        for i in range(6):
            inv = 1.0 / lk[i, i]
            for q in range(kr):
                acc = jac[k, q, i]
                for m in range(i):
                    acc -= lk[i, m] * w[k, m, q]
                w[k, i, q] = acc * inv
            acc = b[k, i]
            for m in range(i):
                acc -= lk[i, m] * x[k, m]
            x[k, i] = acc * inv
        for p in range(kr):
            acc = 0.0
            for i in range(6):
                acc += w[k, i, p] * x[k, i]
            zz[p, 0] += acc
            for q in range(p, kr):
                acc = 0.0
                for i in range(6):
                    acc += w[k, i, p] * w[k, i, q]
                smat[p, q] += acc
    for p in range(kr):
        for q in range(p):
            smat[p, q] = smat[q, p]
    if not chol_inplace(smat, kr):
        for k in range(d):
            x[k, :] = np.nan
        return
    chol_solve_cols(smat, kr, zz, 1)
    v = np.empty(6)
    for k in range(d):
        for i in range(6):
            acc = x[k, i]
            for q in range(kr):
                acc -= w[k, i, q] * zz[q, 0]
            v[i] = acc
        solve_lt(lfac[k], v, x[k])


@kernel
def aggregated_rhs(prob: Problem, mem: Memory, c: int, g: np.ndarray, rate: float,
                   b: np.ndarray) -> None:
    """``b_k = g_k - m_k + M_i / n_i`` over c's domain (module docstring), then the memory moves
    towards ``g``: ``m_k += rate (g_k - m_k)``, ``M_i`` by the same amount."""
    s, d = domain(prob, c)
    for k in range(d):
        i = prob.path_node[s + k]
        inv_n = 1.0 / prob.path_count[i]
        for p in range(6):
            old = mem.grad[s + k, p]
            b[k, p] = g[k, p] - old + mem.gsum[i, p] * inv_n
            dg = rate * (g[k, p] - old)
            mem.gsum[i, p] += dg
            mem.grad[s + k, p] = old + dg


@kernel
def relax_aggregated(prob: Problem, state: State, mem: Memory, wk: Workspace, g: np.ndarray,
                     b: np.ndarray, c: int, tau: float, mu: float, rate: float) -> int:
    """Relax constraint c with the aggregated right-hand side (module docstring).

    Linearize, update 𝔅(H) (eq. 24), form ``b``, solve ``H_c x = b`` and apply ``tau x``
    (capped at pi/8).  ``g``, ``b``: (>= d, 6) scratch.  Returns an ``Update``.
    """
    s, d = domain(prob, c)
    if d == 0:
        return Update.APPLIED
    kr, _na = linearize(prob, c, state.rot, state.trans, wk, wk.jac)
    accumulate_blocks(prob, state, c, kr, wk.jac, mu, wk.lfac, wk.bc)
    contribution(d, kr, wk.jac, wk.r, g)
    aggregated_rhs(prob, mem, c, g, rate, b)
    woodbury_solve_rhs(d, kr, wk.jac, wk.lfac, b, wk.w, wk.x)
    return cap_and_apply(prob.path_node, s, d, wk.x, tau, state, wk.ws)


@kernel
def sweep_aggregated(prob: Problem, state: State, mem: Memory, rate: float, order: np.ndarray,
                     tau: float, mu: float, gps_batch_size: int, dmax: int,
                     deadline: np.uint64, cycles: np.ndarray, batch_cycles: np.ndarray,
                     counts: np.ndarray) -> int:
    """:func:`._sweep.sweep` with :func:`relax_aggregated` for the relative constraints.

    GPS readings are still buffered and relaxed in the paper's batches (III-G), without memory.
    Same arguments and counters as :func:`._sweep.sweep` (no interpolated solving).
    """
    wk = new_workspace(dmax)
    g = np.empty((dmax, 6))
    b = np.empty((dmax, 6))
    nt = state.rot.shape[0]
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
        gps = c >= 0 and is_gps(prob, c)
        if nbuf > 0 and (not gps or nbuf >= gps_batch_size):
            if _flush_exact(prob, state, buf, nbuf, tau, mu, slot, xb, nodes, cycles,
                            batch_cycles, counts) and first_bad < 0:
                first_bad = buf[0]
            nbuf = 0
        if c < 0:
            counts[Count.DONE] += idx
            break
        if gps:
            buf[nbuf] = c
            nbuf += 1
            continue
        t0 = cycle_counter()
        st = relax_aggregated(prob, state, mem, wk, g, b, c, tau, mu, rate)
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
