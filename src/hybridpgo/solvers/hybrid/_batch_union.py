"""The union of a batch's domains: its numbering, its entries, its segments (paper III-F).

A batch C of constraints works on the union U of their domains.  :func:`union_nodes` numbers U;
the *entries* of the batch are its (constraint, domain position) pairs (:class:`BatchArrays`);
:func:`entries_by_node` lists each union node's entries; :func:`segments` groups union nodes
into chains whose nodes lie on the same constraints, which the segmented Woodbury solve
(:mod:`._batch_solve`) and the interpolated batch (:mod:`._batch_reduced`) share.
"""

from __future__ import annotations

import numpy as np

from ..._numba import kernel
from ._linearize import num_a_side
from .problem import Problem, domain


class BatchArrays:
    """Documentation of the batch arrays (Numba passes them one by one).

    ``e`` indexes *entries*: the (constraint, domain position) pairs of the batch, constraint q's
    entries being ``e_off[q] .. e_off[q+1]-1``; ``u`` indexes union nodes (``nodes_out[u]``);
    ``e_slot[e]`` / ``e_q[e]``: the union node and the batch position of entry e;
    ``cnt`` / ``by_slot``: CSR of the entries of each union node; ``jb[e]``: whitened Jacobian
    block; rows ``r_off[q] .. r_off[q+1]-1`` of the stacked residual ``rbuf`` belong to q.
    """


@kernel
def union_nodes(prob: Problem, cs: np.ndarray, nb: int, slot: np.ndarray,
                nodes_out: np.ndarray, e_off: np.ndarray, e_slot: np.ndarray,
                e_q: np.ndarray) -> int:
    """Number the union of the domains (``slot[node]``, ``nodes_out[u]``); returns its size."""
    nu = 0
    for q in range(nb):
        s, d = domain(prob, cs[q])
        for k in range(d):
            i = prob.path_node[s + k]
            if slot[i] < 0:
                slot[i] = nu
                nodes_out[nu] = i
                nu += 1
            e_slot[e_off[q] + k] = slot[i]
            e_q[e_off[q] + k] = q
    return nu


@kernel
def entries_by_node(e_slot: np.ndarray, nu: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR ``(cnt, by_slot)`` of the entries of every union node."""
    ne = e_slot.shape[0]
    cnt = np.zeros(nu + 1, np.int64)
    for e in range(ne):
        cnt[e_slot[e] + 1] += 1
    for u in range(nu):
        cnt[u + 1] += cnt[u]
    fill = cnt[:nu].copy()
    by_slot = np.empty(ne, np.int64)
    for e in range(ne):
        by_slot[fill[e_slot[e]]] = e
        fill[e_slot[e]] += 1
    return cnt, by_slot


@kernel
def entry_sign(prob: Problem, cs: np.ndarray, e_off: np.ndarray, e_q: np.ndarray,
               e: int) -> float:
    """The sign ``s_{c,u}`` of entry e on its constraint's path."""
    q = e_q[e]
    return float(prob.path_sign[prob.path_ptr[cs[q]] + e - e_off[q]])


@kernel
def segments(prob: Problem, cs: np.ndarray, nb: int, e_off: np.ndarray, e_slot: np.ndarray,
             cnt: np.ndarray, slot: np.ndarray, nodes_out: np.ndarray,
             seg: np.ndarray, seg_rep: np.ndarray) -> int:
    """Group union nodes into segments: chains whose nodes lie on the same constraints.

    Each constraint side is walked top-down; a node starts a new segment when a constraint
    side tops out at it, its parent is outside the union, or the counts differ.  Returns the
    number of segments; ``seg[u]`` is u's segment and ``seg_rep[s]`` a representative node.
    """
    nu = seg.shape[0]
    tops = np.zeros(nu, np.bool_)
    for q in range(nb):
        d = domain(prob, cs[q])[1]
        na = num_a_side(prob, cs[q])
        if na > 0:
            tops[e_slot[e_off[q] + na - 1]] = True
        if na < d:
            tops[e_slot[e_off[q] + d - 1]] = True
    seg[:] = -1
    nseg = 0
    for q in range(nb):
        d = domain(prob, cs[q])[1]
        na = num_a_side(prob, cs[q])
        for side in range(2):
            lo = 0 if side == 0 else na
            hi = na if side == 0 else d
            for k in range(hi - 1, lo - 1, -1):
                u = e_slot[e_off[q] + k]
                if seg[u] >= 0:
                    continue
                p = prob.parent[nodes_out[u]]
                pu = slot[p] if p >= 0 else -1
                if tops[u] or pu < 0 or (cnt[u + 1] - cnt[u]) != (cnt[pu + 1] - cnt[pu]):
                    seg[u] = nseg
                    seg_rep[nseg] = u
                    nseg += 1
                else:
                    seg[u] = seg[pu]
    return nseg

