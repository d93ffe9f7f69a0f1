"""Interpolated batch updates (paper III-E with III-G): a batch solved for some union nodes.

:func:`reduced_batch` keeps the nodes :func:`kept_union_nodes` chooses, merges the chain of
omitted nodes above each into one constraint (eq. 31-33, :mod:`._merge`), solves the batch for
the kept nodes (:mod:`._batch_solve`) and spreads each kept node's change over its chain
(:mod:`._distribute`), as a single interpolated update does.
"""

from __future__ import annotations

import numpy as np

from ..._cost import retract_into
from ..._numba import kernel
from ..._tree_kernels import global_pose
from ._batch_solve import MAX_DENSE_NODES, exact_or_damped, solve_segmented
from ._batch_union import segments
from ._distribute import distribute_chain
from ._merge import merged_block
from ._step import step_temperature
from .problem import BATCH_REJECTED, Problem, State, Update, Workspace


@kernel
def kept_union_nodes(prob: Problem, nu: int, d_max: int, seg: np.ndarray, nseg: int,
                     slot: np.ndarray, nodes_out: np.ndarray, kept: np.ndarray) -> int:
    """The union nodes an interpolated batch solves for (``kept[u]``); returns how many.

    Every segment's lowest node is kept (so every constraint endpoint and every branch point),
    and the union parent of every segment's top: a merged chain then never leaves a segment,
    i.e. every constraint of the batch passes through all of a chain or none of it.  The rest
    of the budget ``d_max`` is spread over the segments in proportion to their length, uniformly
    along each (top included).  More than ``d_max`` nodes are kept only when the forced ones
    alone exceed it.
    """
    parent = prob.parent
    pu = np.empty(nu, np.int64)
    same_child = np.zeros(nu, np.bool_)
    for u in range(nu):
        p = parent[nodes_out[u]]
        pu[u] = slot[p] if p >= 0 else -1
        if pu[u] >= 0 and seg[pu[u]] == seg[u]:
            same_child[pu[u]] = True
    seg_len = np.zeros(nseg, np.int64)
    seg_bottom = np.zeros(nseg, np.int64)
    kept[:nu] = False
    for u in range(nu):
        seg_len[seg[u]] += 1
        if not same_child[u]:
            kept[u] = True
            seg_bottom[seg[u]] = u
        if pu[u] >= 0 and seg[pu[u]] != seg[u]:
            kept[pu[u]] = True
    nk = 0
    for u in range(nu):
        if kept[u]:
            nk += 1
    extra = d_max - nk
    total = nu - nseg  # sum over segments of (length - 1)
    if extra > 0 and total > 0:
        for sg in range(nseg):
            n_len = seg_len[sg]
            ks = 1 + (extra * (n_len - 1)) // total
            if ks < 2:
                continue
            u = seg_bottom[sg]
            pos = 0
            j = 1
            while u >= 0 and j < ks:
                if pos == (j * (n_len - 1) + (ks - 1) // 2) // (ks - 1):
                    kept[u] = True
                    j += 1
                    continue
                u = pu[u]
                pos += 1
        nk = 0
        for u in range(nu):
            if kept[u]:
                nk += 1
    return nk

@kernel
def _kept_system(prob: Problem, state: State, wk: Workspace, kept: np.ndarray, nk: int,
                 cnt: np.ndarray, bc: np.ndarray, scale: np.ndarray, slot: np.ndarray,
                 nodes_out: np.ndarray, yr: np.ndarray, yt: np.ndarray, seg: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                            np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                            np.ndarray, np.ndarray, bool]:
    """The kept nodes' system: ``(ku, bck, scalek, yrk, ytk, segk, cntk, chain_nodes,
    chain_start, chain_len, ra, ta, zero_block)``.

    Kept node j is union node ``ku[j]``; its block of B_C (``bck[j]``, with the merged chain
    above it, eq. 31), the trace ``scalek[j]``, its pose, segment and entry count.  Its chain
    ``chain_nodes[chain_start[j]:][:chain_len[j]]`` runs from it up to (excluding) the chain's
    top parent a, whose pose is ``(ra[j], ta[j])``.  ``zero_block``: B_C is 0 on a kept node.
    """
    nu = bc.shape[0]
    ku = np.empty(nk, np.int64)
    j = 0
    for u in range(nu):
        if kept[u]:
            ku[j] = u
            j += 1
    bck = np.empty((nk, 6, 6))
    scalek = np.empty(nk)
    yrk = np.empty((nk, 3, 3))
    ytk = np.empty((nk, 3))
    segk = np.empty(nk, np.int64)
    cntk = np.zeros(nk + 1, np.int64)
    chain_nodes = np.empty(nu, np.int64)
    chain_start = np.empty(nk, np.int64)
    chain_len = np.empty(nk, np.int64)
    ra = np.empty((nk, 3, 3))
    ta = np.empty((nk, 3))
    zero_block = False
    pos = 0
    for j in range(nk):
        u = ku[j]
        bck[j] = bc[u]
        scalek[j] = scale[u]
        yrk[j] = yr[u]
        ytk[j] = yt[u]
        segk[j] = seg[u]
        cntk[j + 1] = cntk[j] + cnt[u + 1] - cnt[u]
        if cnt[u + 1] - cnt[u] == prob.path_count[nodes_out[u]]:
            zero_block = True  # B_C is 0 there (every constraint on the node is in C)
        chain_start[j] = pos
        v = nodes_out[u]
        chain_nodes[pos] = v
        pos += 1
        p = prob.parent[v]
        while p >= 0 and slot[p] >= 0 and not kept[slot[p]]:
            chain_nodes[pos] = p
            pos += 1
            p = prob.parent[p]
        chain_len[j] = pos - chain_start[j]
        if chain_len[j] > 1:  # the chain's top parent a: kept, or outside the union
            if p >= 0 and slot[p] >= 0:
                ra[j] = yr[slot[p]]
                ta[j] = yt[slot[p]]
            else:
                global_pose(p, prob.parent, state.rot, state.trans, ra[j], ta[j])
            merged_block(prob, state, chain_nodes, chain_start[j], chain_len[j], ra[j], ta[j],
                         yr[u], yt[u], bck[j], wk)
    return (ku, bck, scalek, yrk, ytk, segk, cntk, chain_nodes, chain_start, chain_len, ra, ta,
            zero_block)


@kernel
def _apply_kept(state: State, wk: Workspace, nk: int, nodes_out: np.ndarray, xk: np.ndarray,
                tau: float, yrk: np.ndarray, ytk: np.ndarray, chain_nodes: np.ndarray,
                chain_start: np.ndarray, chain_len: np.ndarray, ra: np.ndarray,
                ta: np.ndarray) -> int:
    """Apply the kept nodes' steps ``xk`` (node ``nodes_out[j]``) with the temperature of
    :func:`~._step.step_temperature`: each kept node's change spread over its chain.  Returns
    nk or ``BATCH_REJECTED``."""
    temp, status = step_temperature(xk, nk, tau)
    if status == Update.REJECTED:
        return BATCH_REJECTED
    rb = np.empty((3, 3))
    tb = np.empty(3)
    for j in range(nk):
        i = nodes_out[j]
        if chain_len[j] == 1:  # nothing omitted above: the plain update of the local
            retract_into(state.rot[i], state.trans[i], xk[j], temp, state.rot[i],
                         state.trans[i], wk.ws[0], wk.ws[1])
            continue
        # b's desired global pose Y_b Exp(t x_b), spread over its chain (TORO's way)
        retract_into(yrk[j], ytk[j], xk[j], temp, rb, tb, wk.ws[0], wk.ws[1])
        distribute_chain(state, chain_nodes, chain_start[j], chain_len[j], ra[j], ta[j], rb, tb,
                         wk)
    return nk


@kernel
def reduced_batch(prob: Problem, state: State, cs: np.ndarray, nb: int, tau: float, mu: float,
                  d_max: int, wk: Workspace, jb: np.ndarray, e_off: np.ndarray,
                  e_slot: np.ndarray, e_q: np.ndarray, r_off: np.ndarray, krs: np.ndarray,
                  rbuf: np.ndarray, cnt: np.ndarray, by_slot: np.ndarray, bc: np.ndarray,
                  scale: np.ndarray, slot: np.ndarray, nodes_out: np.ndarray,
                  amat: np.ndarray, yr: np.ndarray, yt: np.ndarray,
                  x_out: np.ndarray) -> int:
    """Interpolated batch update (paper III-E with III-G): solve the batch for the kept union
    nodes only (:func:`kept_union_nodes`), chains between them merged (eq. 31-33, the same
    kernels as single updates), then distribute each kept node's change over its chain.

    Runs after the batch's blocks of B_C are made (𝔅(H) is updated over the whole union).  On
    return the slots are cleared, ``nodes_out[:nk]`` / ``x_out[:nk]`` hold the kept nodes and
    their steps; returns nk or ``BATCH_REJECTED``.
    """
    nu = bc.shape[0]
    seg = np.empty(nu, np.int64)
    seg_rep = np.empty(nu, np.int64)
    nseg = segments(prob, cs, nb, e_off, e_slot, cnt, slot, nodes_out, seg, seg_rep)
    kept = np.empty(nu, np.bool_)
    nk = kept_union_nodes(prob, nu, d_max, seg, nseg, slot, nodes_out, kept)
    (ku, bck, scalek, yrk, ytk, segk, cntk, chain_nodes, chain_start, chain_len, ra, ta,
     zero_block) = _kept_system(prob, state, wk, kept, nk, cnt, bc, scale, slot, nodes_out,
                                yr, yt, seg)
    by_slotk = np.empty(cntk[nk], np.int64)
    for j in range(nk):
        u = ku[j]
        for t in range(cnt[u + 1] - cnt[u]):
            by_slotk[cntk[j] + t] = by_slot[cnt[u] + t]
    xk = np.empty((nk, 6))
    if zero_block and nk <= MAX_DENSE_NODES:
        kidx = np.full(nu, -1, np.int64)
        for j in range(nk):
            kidx[ku[j]] = j
        e_slotk = np.empty(e_slot.shape[0], np.int64)
        for e in range(e_slot.shape[0]):
            e_slotk[e] = kidx[e_slot[e]]
        ok = exact_or_damped(nb, jb, e_off, e_slotk, r_off, krs, rbuf, bck, scalek, mu, xk)
    else:
        ok = solve_segmented(prob, cs, nb, mu, jb, e_off, e_q, r_off, krs, rbuf, cnt, by_slot,
                             amat, seg_rep, nseg, cntk, by_slotk, bck, yrk, ytk, segk, xk)
    for u in range(nu):
        slot[nodes_out[u]] = -1
    for j in range(nk):
        nodes_out[j] = chain_nodes[chain_start[j]]
        x_out[j] = xk[j]
    if not ok:
        return BATCH_REJECTED
    return _apply_kept(state, wk, nk, nodes_out, xk, tau, yrk, ytk, chain_nodes, chain_start,
                       chain_len, ra, ta)
