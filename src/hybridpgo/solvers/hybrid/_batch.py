"""Batch updates: several constraints relaxed together (paper III-F, III-G;
docs/mathematics.md#batches).

For a set C of constraints, ``H_C = sum_{c in C} J_c^T J_c + B_C`` over the union U of their
domains, with ``B_C = 𝔅(H) - sum_{c in C} 𝔅(J_c^T J_c)`` (eq. 35-37).  GPS readings are relaxed
this way in batches (III-G); the batch of every constraint is the exact Gauss-Newton step
(eq. 37 reduces to eq. 14).

Stages (:func:`batch_relax`): the union of the domains (:mod:`._batch_union`), one linearization
per constraint, the blocks of B_C with 𝔅(H) updated (eq. 36, 24), the solve
(:mod:`._batch_solve`), and :func:`~._step.cap_and_apply`.  The solve is the Woodbury form over
*segments* (:func:`~._batch_solve.woodbury_segments`) when every block of B_C is non-zero, else
(B_C vanishes on a node only the batch touches) the dense normal equations over U when U has at
most ``MAX_DENSE_NODES`` nodes (larger: that block damped, the segments).  With a node
budget the batch is solved by interpolation (:mod:`._batch_reduced`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..._cost import ROBUST_NONE, robust_whitening, whiten_residual
from ..._numba import kernel
from ..._tree_kernels import global_pose, mul_pose_into
from ._batch_reduced import reduced_batch
from ._batch_solve import MAX_DENSE_NODES, exact_or_damped, woodbury_segments
from ._batch_union import entries_by_node, union_nodes
from ._linearize import endpoints, gps_factor_into, linearize, relative_factor_into
from ._step import cap_and_apply
from .problem import (
    BATCH_REJECTED,
    Problem,
    State,
    Update,
    Workspace,
    domain,
    is_gps,
    new_workspace,
)


# --------------------------------------------------------------------------- linearization
@kernel
def _linearize_batch(prob: Problem, state: State, cs: np.ndarray, nb: int, wk: Workspace,
                     e_off: np.ndarray, e_slot: np.ndarray, jb: np.ndarray, r_off: np.ndarray,
                     krs: np.ndarray, rbuf: np.ndarray, amat: np.ndarray, yr: np.ndarray,
                     yt: np.ndarray) -> None:
    """Linearize every constraint once: blocks ``jb``, residuals ``rbuf``, and the factors
    ``J_{c,u} = s_{c,u} A_c Ad(Y_u)`` the segmented Woodbury solve uses: ``A_c`` (``amat[q]``)
    and the global pose ``Y_u`` of every union node (``yr``, ``yt``).

    ``A_c`` is ``L^T Jr^-1(e) Ad(Y_b)^-1`` for a relative constraint and ``L^T [I | -[p_n]x]``
    for GPS (the earth is the root); with a robust kernel ``L^T`` is ``sqrt(w) L^T``, as
    :func:`._linearize.linearize` whitens.
    """
    nu = yr.shape[0]
    have = np.zeros(nu, np.bool_)
    gr = np.empty((3, 3))
    gt = np.empty(3)
    tr_ = np.empty((3, 3))
    tt_ = np.empty(3)
    adb = np.empty((6, 6))
    blk = np.zeros((3, 6))
    r0 = np.empty(3)
    r_off[0] = 0
    for q in range(nb):
        c = cs[q]
        s0, d = domain(prob, c)
        kr, na = linearize(prob, c, state.rot, state.trans, wk, jb[e_off[q] : e_off[q] + d])
        krs[q] = kr
        for i in range(kr):
            rbuf[r_off[q] + i] = wk.r[i]
        r_off[q + 1] = r_off[q] + kr
        pr = wk.path_rot
        pt = wk.path_trans
        # the constraint's root: parent of the top node of a non-empty side
        top = prob.path_node[s0 + na - 1] if na > 0 else prob.path_node[s0 + d - 1]
        global_pose(prob.parent[top], prob.parent, state.rot, state.trans, gr, gt)
        for k in range(d):
            u = e_slot[e_off[q] + k]
            if not have[u]:
                mul_pose_into(gr, gt, pr[k], pt[k], yr[u], yt[u])
                have[u] = True
        if not is_gps(prob, c):
            _ra, _ta, rb, tb = endpoints(pr, pt, na, d)
            mul_pose_into(gr, gt, rb, tb, tr_, tt_)  # Y_b = G_root P_b
            relative_factor_into(wk.a, tr_, tt_, adb, amat[q])
        else:  # p_n = pt[0] in the earth frame (G = I)
            lt = prob.gps_lt[c - prob.num_edges]
            gps_factor_into(lt, pt[0], blk, amat[q])
            if prob.robust_kind != ROBUST_NONE:  # the weight linearize folded into jb, rbuf
                whiten_residual(lt, wk.e, 3, r0)
                sw = robust_whitening(prob.robust_kind, prob.robust_scale, r0, 3)
                for i in range(3):
                    for j in range(6):
                        amat[q, i, j] *= sw


# --------------------------------------------------------------------------- blocks of B_C
@kernel
def _batch_blocks(prob: Problem, state: State, cs: np.ndarray, jb: np.ndarray,
                  e_off: np.ndarray, krs: np.ndarray, e_q: np.ndarray, cnt: np.ndarray,
                  by_slot: np.ndarray, nodes_out: np.ndarray, bc: np.ndarray,
                  scale: np.ndarray) -> bool:
    """Eq. 36 and 24: B_C per union node, 𝔅(H) updated with the batch's new contributions;
    ``scale[u]``: the trace of the batch's own blocks on node u (for the damping rule).

    Returns True when some node has every constraint through it in C (its block of B_C is 0).
    """
    nu = bc.shape[0]
    bdiag = state.bdiag
    contrib = state.contrib
    zero_block = False
    for u in range(nu):
        i = nodes_out[u]
        for p in range(6):
            for q2 in range(6):
                bc[u, p, q2] = bdiag[i, p, q2]
        for t in range(cnt[u], cnt[u + 1]):
            e = by_slot[t]
            q = e_q[e]
            pe = prob.path_ptr[cs[q]] + e - e_off[q]
            kr = krs[q]
            for p in range(6):
                for q2 in range(6):
                    acc = 0.0
                    for w in range(kr):
                        acc += jb[e, w, p] * jb[e, w, q2]
                    old = contrib[pe, p, q2]
                    bc[u, p, q2] -= old
                    bdiag[i, p, q2] += acc - old
                    contrib[pe, p, q2] = acc
                scale[u] += contrib[pe, p, p]
        if cnt[u + 1] - cnt[u] == prob.path_count[i]:  # every constraint on node i is in C
            for p in range(6):
                for q2 in range(6):
                    bc[u, p, q2] = 0.0
            zero_block = True
    return zero_block


# --------------------------------------------------------------------------- the batch update
def _make_batch_relax(with_interpolation: bool) -> Callable[..., int]:
    """:func:`batch_relax`, or without ``with_interpolation`` :data:`batch_relax_exact`, which
    ignores ``d_max`` and never compiles the interpolated batch
    (:func:`~._batch_reduced.reduced_batch` and its callees, about a third of the GPS batches'
    compile time; the closure's constant is pruned before typing)."""

    def batch_relax(prob: Problem, state: State, cs: np.ndarray, nb: int, tau: float, mu: float,
                    slot: np.ndarray, x_out: np.ndarray, nodes_out: np.ndarray,
                    d_max: int = 0, dense: bool = True) -> int:
        """Relax the constraints ``cs[:nb]`` together (paper eq. 35-37,
        docs/mathematics.md#batches).

        ``slot`` (T,) must be -1 on entry and is -1 again on exit.  The step of union node
        ``nodes_out[u]`` is written to ``x_out[u]``.  Returns the number of union nodes, or
        ``BATCH_REJECTED`` when the step was not finite (nothing applied).

        With ``0 < d_max <`` the union's size the batch is solved by interpolation
        (:func:`~._batch_reduced.reduced_batch`, paper III-E/III-G): ``nodes_out`` / ``x_out``
        then hold the kept nodes and the return value is their number.

        ``dense=False`` keeps the segmented Woodbury solve even when a block of B_C vanishes (a
        node all of whose constraints are in the batch): such a block is then damped like every
        other (docs/mathematics.md#hybrid-step) and the cost stays O(entries + (6|C|)^3) instead of
        the dense
        O((6|U|)^3) -- what a time budget per frame needs (the online solver).
        """
        e_off = np.empty(nb + 1, np.int64)
        e_off[0] = 0
        dmax = 1
        for q in range(nb):
            d = domain(prob, cs[q])[1]
            e_off[q + 1] = e_off[q] + d
            dmax = max(dmax, d)
        ne = e_off[nb]
        e_slot = np.empty(ne, np.int64)
        e_q = np.empty(ne, np.int64)
        nu = union_nodes(prob, cs, nb, slot, nodes_out, e_off, e_slot, e_q)
        cnt, by_slot = entries_by_node(e_slot, nu)
        wk = new_workspace(dmax)
        jb = np.empty((ne, 6, 6))
        r_off = np.empty(nb + 1, np.int64)
        krs = np.empty(nb, np.int64)
        rbuf = np.empty(6 * nb)
        amat = np.zeros((nb, 6, 6))
        yr = np.empty((nu, 3, 3))
        yt = np.empty((nu, 3))
        _linearize_batch(prob, state, cs, nb, wk, e_off, e_slot, jb, r_off, krs, rbuf, amat, yr,
                         yt)
        bc = np.zeros((nu, 6, 6))
        scale = np.zeros(nu)
        zero_block = _batch_blocks(prob, state, cs, jb, e_off, krs, e_q, cnt, by_slot,
                                   nodes_out, bc, scale)
        if with_interpolation and 0 < d_max < nu:
            return reduced_batch(prob, state, cs, nb, tau, mu, d_max, wk, jb, e_off, e_slot,
                                 e_q, r_off, krs, rbuf, cnt, by_slot, bc, scale, slot,
                                 nodes_out, amat, yr, yt, x_out)
        if dense and zero_block and nu <= MAX_DENSE_NODES:
            ok = exact_or_damped(nb, jb, e_off, e_slot, r_off, krs, rbuf, bc, scale, mu, x_out)
        else:
            ok = woodbury_segments(prob, cs, nb, mu, jb, e_off, r_off, krs, rbuf, e_slot, e_q,
                                   cnt, by_slot, bc, slot, nodes_out, amat, yr, yt, x_out)
        for u in range(nu):
            slot[nodes_out[u]] = -1
        if not ok:
            return BATCH_REJECTED
        if cap_and_apply(nodes_out, 0, nu, x_out, tau, state, wk.ws) == Update.REJECTED:
            return BATCH_REJECTED
        return nu

    batch_relax.__qualname__ = batch_relax.__name__ = (
        "batch_relax" if with_interpolation else "batch_relax_exact")
    return kernel(batch_relax)


batch_relax = _make_batch_relax(True)
#: :func:`batch_relax` without interpolated solving (``d_max`` is ignored): what a sweep
#: without ``d_max`` and the online mode need, at about two thirds of the compile time.
batch_relax_exact = _make_batch_relax(False)
