"""Interpolated solving (paper III-E, eq. 31-34; docs/mathematics.md#interpolated-solving).

A constraint whose domain has more than ``D_max`` nodes is solved for a subset ``S_c`` of at most
``D_max`` nodes, kept uniformly along each side of its path (the endpoints always kept).  For a
kept node b whose parent is omitted, the chain of tree links between b and its closest kept
ancestor a (or the constraint's root) is merged into one constraint β (eq. 31-33,
:mod:`._merge`).  The reduced system (eq. 34) is solved like a full update (Woodbury or Givens).
Each kept node's pose change is then spread over its chain the way TORO does
(:mod:`._distribute`).  𝔅(H) itself is still updated over the whole domain (eq. 24), which
needs the O(d) linearization; only the solve is reduced.

Cost: besides the linearization and the 𝔅(H) update, the merged constraints cost O(1) scalar
work per omitted node, the distribution a rotation interpolation and a translation per node;
nothing allocates (the scratch lives in the :class:`~.problem.Workspace`).  Batches (III-G) use
the same kernels through :mod:`._batch_reduced`.
"""

from __future__ import annotations

import numpy as np

from ..._cost import retract_into
from ..._numba import kernel
from ._dense import regularized_factor
from ._distribute import distribute_chains
from ._linearize import linearize, relative_setup
from ._merge import merged_blocks
from ._step import accumulate_path, linearize_accumulate, solve_single, step_temperature
from .problem import Problem, State, Update, Workspace, domain, is_gps


# --------------------------------------------------------------------------- S_c
@kernel
def kept_positions(d: int, na: int, d_max: int, keep: np.ndarray) -> int:
    """Domain positions kept when solving for at most ``d_max`` of the d nodes.

    Each side (a side: positions ``0..na-1``, b side: ``na..d-1``, both listed from the
    endpoint upwards) gets a share of ``d_max`` proportional to its length (at least one node
    when it is not empty); within a side the kept nodes are spread uniformly from the endpoint
    to the top.  Returns the number kept, written in increasing position order.
    """
    nb = d - na
    ka = 0
    if na > 0:
        ka = max(1, min(na, (d_max * na + d // 2) // d))
        if nb > 0:
            ka = min(ka, d_max - 1)
    kb = min(nb, d_max - ka)
    n = 0
    for lo, length, k in ((0, na, ka), (na, nb, kb)):
        if k <= 0:
            continue
        if k == 1:
            keep[n] = lo
            n += 1
            continue
        prev = -1
        for j in range(k):
            p = lo + (j * (length - 1) + (k - 1) // 2) // (k - 1)
            if p > prev:
                keep[n] = p
                n += 1
                prev = p
    return n


@kernel
def chain_end(d: int, na: int, keep: np.ndarray, nk: int, j: int) -> int:
    """One past the last position of kept node j's chain: the next kept position on the same
    side (its closest kept ancestor), or the end of the side (the chain reaches the root)."""
    side_end = na if keep[j] < na else d
    if j + 1 < nk and keep[j + 1] < side_end:
        return int(keep[j + 1])
    return side_end


# --------------------------------------------------------------------------- B̃ (eq. 31)
@kernel
def reduced_factors(prob: Problem, state: State, c: int, d: int, na: int, kr: int,
                    wk: Workspace, keep: np.ndarray, nk: int, mu: float,
                    sub: Workspace) -> None:
    """B̃ (eq. 31) on the kept nodes, damped and factored into ``sub.lfac``; ``sub.jac`` gets
    the kept nodes' Jacobian blocks.  Must run right after ``accumulate_blocks`` (which updated
    𝔅(H) and c's contributions): ``B_c = 𝔅(H) - contribution of c`` at each kept node.
    ``sub.w`` holds B̃ until the solve overwrites it."""
    s = prob.path_ptr[c]
    jac = wk.jac
    pr = wk.path_rot
    pt = wk.path_trans
    bc = sub.w
    sjac = sub.jac
    bdiag = state.bdiag
    contrib = state.contrib
    path_node = prob.path_node
    chains = np.empty((nk, 5), np.int64)
    nch = 0
    for j in range(nk):
        p = keep[j]
        i = path_node[s + p]
        for q1 in range(6):
            for q2 in range(6):
                bc[j, q1, q2] = bdiag[i, q1, q2] - contrib[s + p, q1, q2]
                sjac[j, q1, q2] = jac[p, q1, q2]
        end = chain_end(d, na, keep, nk, j)
        if end - p > 1:  # b's parent is omitted: β replaces α
            chains[nch, 0] = s + p
            chains[nch, 1] = end - p
            chains[nch, 2] = end if end < (na if p < na else d) else -1  # a: kept, or the root
            chains[nch, 3] = p
            chains[nch, 4] = j
            nch += 1
    merged_blocks(prob.link_constraint, prob.link_forward, prob.edge_rot, prob.edge_trans,
                  prob.edge_lt, prob.gps_pos, prob.gps_lt, prob.num_edges, state.rot, contrib,
                  prob.path_ptr, path_node, chains, nch, pr, pt, pr, pt, bc, wk.iws, wk.iws6,
                  wk.ws)
    for j in range(nk):
        scale = 0.0
        for q in range(6):
            acc = 0.0
            for t in range(kr):
                acc += jac[keep[j], t, q] * jac[keep[j], t, q]
            scale += acc
        regularized_factor(bc[j], scale, mu, sub.lfac[j])


@kernel
def distribute(prob: Problem, state: State, c: int, d: int, na: int, keep: np.ndarray,
               nk: int, x: np.ndarray, t: float, wk: Workspace) -> None:
    """Apply the reduced step ``t x`` (kept node j: ``x[j]``) by distributing each kept node's
    desired pose change over its chain (path products ``wk.path_rot/trans`` from before the
    step; the chains are disjoint, so they are moved one after the other)."""
    s = prob.path_ptr[c]
    pr = wk.path_rot
    pt = wk.path_trans
    iws = wk.iws
    er = iws[9]
    tmp = iws[10]
    path_node = prob.path_node
    rot = state.rot
    trans = state.trans
    chains = np.empty((nk, 4), np.int64)
    bnr = np.empty((nk, 3, 3))
    bnt = np.empty((nk, 3))
    nch = 0
    for j in range(nk):
        p = keep[j]
        end = chain_end(d, na, keep, nk, j)
        k = end - p
        if k == 1:  # nothing omitted: the plain update of b's local transform
            i = path_node[s + p]
            retract_into(rot[i], trans[i], x[j], t, rot[i], trans[i], er, tmp)
            continue
        # b's desired pose (root frame): P_b Exp(t x_b), as a full update would move it
        retract_into(pr[p], pt[p], x[j], t, bnr[nch], bnt[nch], er, tmp)
        chains[nch, 0] = s + p
        chains[nch, 1] = k
        chains[nch, 2] = end if end < (na if p < na else d) else -1  # a: kept, or the root
        chains[nch, 3] = nch
        nch += 1
    distribute_chains(rot, trans, state.bdiag, path_node, chains, nch, pr, pt, bnr, bnt,
                      wk.chain_rot, wk.chain_w, iws, wk.iws6)


# --------------------------------------------------------------------------- the update
@kernel
def relax_interpolated(prob: Problem, state: State, wk: Workspace, sub: Workspace,
                       keep: np.ndarray, c: int, tau: float, mu: float, step_kind: int,
                       d_max: int) -> int:
    """Relax constraint c solving for at most ``d_max`` of its domain nodes (paper III-E).

    ``wk`` must hold the whole domain, ``sub`` and ``keep`` ``d_max`` nodes.  Returns an
    ``Update`` like :func:`~._step.relax`.  Allocation-free apart from the solve's 6x6 scratch.
    """
    s, d = domain(prob, c)
    if is_gps(prob, c):
        kr, na = linearize(prob, c, state.rot, state.trans, wk, wk.jac)
        accumulate_path(prob.path_node, s, d, kr, wk.jac, state.bdiag, state.contrib, mu,
                        wk.lfac, wk.bc, False)
    else:
        kr = 6
        na = relative_setup(prob.path_node, prob.path_sign, s, d, prob.edge_rot[c],
                            prob.edge_trans[c], prob.edge_lt[c], prob.robust_kind,
                            prob.robust_scale, state.rot, state.trans, wk.path_rot,
                            wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a)
        nk = kept_positions(d, na, d_max, keep)  # only the kept nodes' blocks are stored
        linearize_accumulate(prob.path_node, prob.path_sign, s, d, na, wk.path_rot,
                             wk.path_trans, wk.a, wk.jac, False, keep, nk, state.bdiag,
                             state.contrib, mu, wk.lfac, wk.bc, False)
    nk = kept_positions(d, na, d_max, keep)
    reduced_factors(prob, state, c, d, na, kr, wk, keep, nk, mu, sub)
    for i in range(6):
        sub.r[i] = wk.r[i]
    solve_single(nk, kr, step_kind, sub)
    t, status = step_temperature(sub.x, nk, tau)
    if status == Update.REJECTED:
        return status
    distribute(prob, state, c, d, na, keep, nk, sub.x, t, wk)
    return status
