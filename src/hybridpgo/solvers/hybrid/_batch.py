"""Batch updates: several constraints relaxed together (paper III-F, III-G; DESIGN.md §5).

For a set C of constraints, ``H_C = sum_{c in C} J_c^T J_c + B_C`` over the union U of their
domains, with ``B_C = 𝔅(H) - sum_{c in C} 𝔅(J_c^T J_c)`` (eq. 35-37).  GPS readings are relaxed
this way in batches (III-G); the batch of every constraint is the exact Gauss-Newton step
(eq. 37 reduces to eq. 14).

Stages (:func:`batch_relax`): the union of the domains, one linearization per constraint, the
blocks of B_C with 𝔅(H) updated (eq. 36, 24), the solve, and :func:`~._step.cap_and_apply`.
The solve is the Woodbury form over *segments* (:func:`woodbury_segments`) when every block of
B_C is non-zero, else (B_C vanishes on a node only the batch touches) the dense normal
equations over U.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..._cost import retract_into, whiten_rows
from ..._numba import kernel
from ..._tree_kernels import global_pose, mul_pose_into
from ._dense import TINY, chol_inplace, chol_solve_cols, regularized_factor, solve_lt
from ._interpolate import distribute_chain, merged_block
from ._linearize import endpoints, linearize, num_a_side
from ._step import cap_and_apply, step_temperature
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

#: Largest union (nodes) solved by the dense normal equations when B_C has a zero block.
MAX_DENSE_NODES = 4096 // 6
#: An undamped dense batch system whose Cholesky pivot^2 falls below this fraction of its
#: diagonal entry is singular to rounding; it is solved again with the damping of DESIGN §4.
SINGULAR_PIVOT = 1e-12


# --------------------------------------------------------------------------- helpers
@kernel
def adjoint_into(r: np.ndarray, t: np.ndarray, out: np.ndarray) -> None:
    """Ad(T) = [[R, [t]x R], [0, R]]."""
    for i in range(3):
        for j in range(3):
            out[i, j] = r[i, j]
            out[3 + i, 3 + j] = r[i, j]
            out[3 + i, j] = 0.0
    for j in range(3):
        out[0, 3 + j] = t[1] * r[2, j] - t[2] * r[1, j]
        out[1, 3 + j] = t[2] * r[0, j] - t[0] * r[2, j]
        out[2, 3 + j] = t[0] * r[1, j] - t[1] * r[0, j]


class _Batch:
    """Documentation of the batch arrays (Numba passes them one by one).

    ``e`` indexes *entries*: the (constraint, domain position) pairs of the batch, constraint q's
    entries being ``e_off[q] .. e_off[q+1]-1``; ``u`` indexes union nodes (``nodes_out[u]``);
    ``e_slot[e]`` / ``e_q[e]``: the union node and the batch position of entry e;
    ``cnt`` / ``by_slot``: CSR of the entries of each union node; ``jb[e]``: whitened Jacobian
    block; rows ``r_off[q] .. r_off[q+1]-1`` of the stacked residual ``rbuf`` belong to q.
    """


# --------------------------------------------------------------------------- 1. union
@kernel
def _union(prob: Problem, cs: np.ndarray, nb: int, slot: np.ndarray, nodes_out: np.ndarray,
           e_off: np.ndarray, e_slot: np.ndarray, e_q: np.ndarray) -> int:
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
def _entries_by_node(e_slot: np.ndarray, nu: int) -> tuple[np.ndarray, np.ndarray]:
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


# --------------------------------------------------------------------------- 2. linearize
@kernel
def _linearize_batch(prob: Problem, state: State, cs: np.ndarray, nb: int, wk: Workspace,
                     e_off: np.ndarray, e_slot: np.ndarray, jb: np.ndarray, r_off: np.ndarray,
                     krs: np.ndarray, rbuf: np.ndarray, amat: np.ndarray, yr: np.ndarray,
                     yt: np.ndarray) -> None:
    """Linearize every constraint once: blocks ``jb``, residuals ``rbuf``, and the factors
    ``J_{c,u} = s_{c,u} A_c Ad(Y_u)`` the segmented Woodbury solve uses: ``A_c`` (``amat[q]``)
    and the global pose ``Y_u`` of every union node (``yr``, ``yt``).

    ``A_c`` is ``L^T Jr^-1(e) Ad(Y_b)^-1`` for a relative constraint and ``L^T [I | -[p_n]x]``
    for GPS (the earth is the root).
    """
    nu = yr.shape[0]
    have = np.zeros(nu, np.bool_)
    gr = np.empty((3, 3))
    gt = np.empty(3)
    tr_ = np.empty((3, 3))
    tt_ = np.empty(3)
    adb = np.empty((6, 6))
    blk = np.zeros((3, 6))
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
            # Ad(Y_b)^-1 = Ad(Y_b^-1), Y_b = G_root P_b
            mul_pose_into(gr, gt, rb, tb, tr_, tt_)
            rinv = tr_.T.copy()
            tinv = -(rinv @ tt_)
            adjoint_into(rinv, tinv, adb)
            amat[q] = wk.a @ adb
        else:
            pn = pt[0]  # p_n in the earth frame (G = I)
            for i in range(3):
                blk[i, i] = 1.0
            blk[0, 4] = pn[2]  # -[p_n]x
            blk[0, 5] = -pn[1]
            blk[1, 3] = -pn[2]
            blk[1, 5] = pn[0]
            blk[2, 3] = pn[1]
            blk[2, 4] = -pn[0]
            whiten_rows(prob.gps_lt[c - prob.num_edges], blk, 3, amat[q])


# --------------------------------------------------------------------------- 3. blocks of B_C
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


# --------------------------------------------------------------------------- 4a. dense solve
@kernel
def _dense_solve(nb: int, jb: np.ndarray, e_off: np.ndarray, e_slot: np.ndarray,
                 r_off: np.ndarray, krs: np.ndarray, rbuf: np.ndarray, bc: np.ndarray,
                 scale: np.ndarray, mu: float, damped: bool, x_out: np.ndarray) -> bool:
    """``(sum_c J_c^T J_c + B_C) x = sum_c J_c^T r_c`` densely over the union (6|U| unknowns).

    An entry whose ``e_slot`` is negative is left out (interpolated batches).
    ``damped``: every block of B_C gets the damping of DESIGN §4 (``mu tr(B)/6 + TINY scale``),
    which keeps the system SPD where the batch alone leaves a direction free (e.g. the rotation
    of a subtree about a single GPS reading).
    """
    nu = bc.shape[0]
    n6 = 6 * nu
    amat = np.zeros((n6, n6))
    g = np.zeros(n6)
    for u in range(nu):
        damp = 0.0
        if damped:
            tr = max(bc[u, 0, 0] + bc[u, 1, 1] + bc[u, 2, 2] + bc[u, 3, 3] + bc[u, 4, 4]
                     + bc[u, 5, 5], 0.0)
            damp = mu * tr / 6.0 + TINY * scale[u]
        for p in range(6):
            for q2 in range(6):
                amat[6 * u + p, 6 * u + q2] = bc[u, p, q2]
            amat[6 * u + p, 6 * u + p] += damp
    for q in range(nb):
        kr = krs[q]
        for e in range(e_off[q], e_off[q + 1]):
            ue = e_slot[e]
            if ue < 0:  # a node omitted by interpolated solving
                continue
            for p in range(6):
                acc = 0.0
                for w in range(kr):
                    acc += jb[e, w, p] * rbuf[r_off[q] + w]
                g[6 * ue + p] += acc
            for f in range(e_off[q], e_off[q + 1]):
                uf = e_slot[f]
                if uf < 0:
                    continue
                for p in range(6):
                    for q2 in range(6):
                        acc = 0.0
                        for w in range(kr):
                            acc += jb[e, w, p] * jb[f, w, q2]
                        amat[6 * ue + p, 6 * uf + q2] += acc
    sym = 0.5 * (amat + amat.T)
    diag = np.diag(sym).copy()
    if not chol_inplace(sym, n6):
        return False
    if not damped:  # singular to rounding: a direction the batch leaves free
        for k in range(n6):
            if not (sym[k, k] * sym[k, k] > SINGULAR_PIVOT * diag[k]):
                return False
    gg = g.reshape((n6, 1)).copy()
    chol_solve_cols(sym, n6, gg, 1)
    for u in range(nu):
        for p in range(6):
            x_out[u, p] = gg[6 * u + p, 0]
    return True


# --------------------------------------------------------------------------- 4b. Woodbury
@kernel
def _entry_sign(prob: Problem, cs: np.ndarray, e_off: np.ndarray, e_q: np.ndarray,
                e: int) -> float:
    q = e_q[e]
    return float(prob.path_sign[prob.path_ptr[cs[q]] + e - e_off[q]])


@kernel
def _segments(prob: Problem, cs: np.ndarray, nb: int, e_off: np.ndarray, e_slot: np.ndarray,
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


@kernel
def _segment_moments(jb: np.ndarray, krs: np.ndarray, e_q: np.ndarray, cnt: np.ndarray,
                     by_slot: np.ndarray, bc: np.ndarray, mu: float, yr: np.ndarray,
                     yt: np.ndarray, seg: np.ndarray, nseg: int, lf: np.ndarray,
                     vv: np.ndarray) -> np.ndarray:
    """Per node: factor of damped B_u, ``V_u = L_u^-1 Ad(Y_u)^T``; per segment the moment
    ``M_seg = sum_u V_u^T V_u`` (returned, (nseg, 6, 6))."""
    nu = bc.shape[0]
    mseg = np.zeros((nseg, 6, 6))
    ad = np.empty((6, 6))
    for u in range(nu):
        sc = 0.0
        for t in range(cnt[u], cnt[u + 1]):
            e = by_slot[t]
            for p in range(6):
                for w in range(krs[e_q[e]]):
                    sc += jb[e, w, p] * jb[e, w, p]
        regularized_factor(bc[u], sc, mu, lf[u])
        adjoint_into(yr[u], yt[u], ad)
        lk = lf[u]
        for col in range(6):  # column col of Ad^T = row col of Ad
            for i in range(6):
                acc = ad[col, i]
                for m in range(i):
                    acc -= lk[i, m] * vv[u, m, col]
                vv[u, i, col] = acc / lk[i, i]
        sg = seg[u]
        for i in range(6):
            for j in range(i, 6):
                acc = 0.0
                for m in range(6):
                    acc += vv[u, m, i] * vv[u, m, j]
                mseg[sg, i, j] += acc
    for sg in range(nseg):
        for i in range(6):
            for j in range(i):
                mseg[sg, i, j] = mseg[sg, j, i]
    return mseg


@kernel
def _capacitance(prob: Problem, cs: np.ndarray, e_off: np.ndarray, e_q: np.ndarray,
                 r_off: np.ndarray, krs: np.ndarray, cnt: np.ndarray, by_slot: np.ndarray,
                 amat: np.ndarray, mseg: np.ndarray, seg_rep: np.ndarray,
                 k_rows: int) -> np.ndarray:
    """``S = I + sum_seg sum_{c,d in seg} s_c s_d A_c M_seg A_d^T`` (k_rows x k_rows)."""
    smat = np.zeros((k_rows, k_rows))
    for i in range(k_rows):
        smat[i, i] = 1.0
    tm = np.empty((6, 6))
    for sg in range(mseg.shape[0]):
        u = seg_rep[sg]
        for t1 in range(cnt[u], cnt[u + 1]):
            e = by_slot[t1]
            qe = e_q[e]
            se = _entry_sign(prob, cs, e_off, e_q, e)
            kre = krs[qe]
            for a in range(kre):
                for j in range(6):
                    acc = 0.0
                    for m in range(6):
                        acc += amat[qe, a, m] * mseg[sg, m, j]
                    tm[a, j] = se * acc
            for t2 in range(cnt[u], cnt[u + 1]):
                f = by_slot[t2]
                qf = e_q[f]
                sf = _entry_sign(prob, cs, e_off, e_q, f)
                for a in range(kre):
                    for b in range(krs[qf]):
                        acc = 0.0
                        for m in range(6):
                            acc += tm[a, m] * amat[qf, b, m]
                        smat[r_off[qe] + a, r_off[qf] + b] += sf * acc
    return smat


@kernel
def _back_substitute(prob: Problem, cs: np.ndarray, e_off: np.ndarray, e_q: np.ndarray,
                     r_off: np.ndarray, krs: np.ndarray, cnt: np.ndarray, by_slot: np.ndarray,
                     amat: np.ndarray, zz: np.ndarray, seg: np.ndarray, seg_rep: np.ndarray,
                     nseg: int, lf: np.ndarray, vv: np.ndarray, x_out: np.ndarray) -> None:
    """``v_seg = sum_c s_c A_c^T z_c``, then ``x_u = L_u^-T (V_u v_seg)``."""
    vseg = np.zeros((nseg, 6))
    for sg in range(nseg):
        u = seg_rep[sg]
        for t1 in range(cnt[u], cnt[u + 1]):
            e = by_slot[t1]
            qe = e_q[e]
            se = _entry_sign(prob, cs, e_off, e_q, e)
            for j in range(6):
                acc = 0.0
                for a in range(krs[qe]):
                    acc += amat[qe, a, j] * zz[r_off[qe] + a, 0]
                vseg[sg, j] += se * acc
    v = np.empty(6)
    for u in range(lf.shape[0]):
        sg = seg[u]
        for i in range(6):
            acc = 0.0
            for m in range(6):
                acc += vv[u, i, m] * vseg[sg, m]
            v[i] = acc
        solve_lt(lf[u], v, x_out[u])


@kernel
def woodbury_segments(prob: Problem, cs: np.ndarray, nb: int, mu: float, jb: np.ndarray,
                      e_off: np.ndarray, r_off: np.ndarray, krs: np.ndarray, rbuf: np.ndarray,
                      e_slot: np.ndarray, e_q: np.ndarray, cnt: np.ndarray,
                      by_slot: np.ndarray, bc: np.ndarray, slot: np.ndarray,
                      nodes_out: np.ndarray, amat: np.ndarray, yr: np.ndarray, yt: np.ndarray,
                      x_out: np.ndarray) -> bool:
    """Woodbury solve of a batch in O(entries + sum over segments of |sig|^2) (DESIGN §5).

    Every Jacobian block factors as ``J_{c,u} = s_{c,u} A_c Ad(Y_u)``.  Union nodes whose
    constraint sets agree (chains between branch points, "segments") share one moment
    ``M_seg = sum_u Ad(Y_u) B_u^-1 Ad(Y_u)^T``, so the capacitance matrix
    ``S = I + sum_seg sum_{c,d} s_c s_d A_c M_seg A_d^T`` costs O(|sig|^2) per segment instead
    of per node: a batch of GPS readings sharing a long trunk stays cheap.
    """
    nu = bc.shape[0]
    seg = np.empty(nu, np.int64)
    seg_rep = np.empty(nu, np.int64)
    nseg = _segments(prob, cs, nb, e_off, e_slot, cnt, slot, nodes_out, seg, seg_rep)
    lf = np.empty((nu, 6, 6))
    vv = np.empty((nu, 6, 6))
    mseg = _segment_moments(jb, krs, e_q, cnt, by_slot, bc, mu, yr, yt, seg, nseg, lf, vv)
    k_rows = r_off[nb]
    smat = _capacitance(prob, cs, e_off, e_q, r_off, krs, cnt, by_slot, amat, mseg[:nseg],
                        seg_rep, k_rows)
    sym = 0.5 * (smat + smat.T)
    if not chol_inplace(sym, k_rows):
        return False
    zz = rbuf[:k_rows].reshape((k_rows, 1)).copy()
    chol_solve_cols(sym, k_rows, zz, 1)
    _back_substitute(prob, cs, e_off, e_q, r_off, krs, cnt, by_slot, amat, zz, seg, seg_rep,
                     nseg, lf, vv, x_out)
    return True


# --------------------------------------------------------------------------- 5. interpolated
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
def _reduced_batch(prob: Problem, state: State, cs: np.ndarray, nb: int, tau: float, mu: float,
                   d_max: int, wk: Workspace, jb: np.ndarray, e_off: np.ndarray,
                   e_slot: np.ndarray, e_q: np.ndarray, r_off: np.ndarray, krs: np.ndarray,
                   rbuf: np.ndarray, cnt: np.ndarray, by_slot: np.ndarray, bc: np.ndarray,
                   scale: np.ndarray, slot: np.ndarray, nodes_out: np.ndarray,
                   amat: np.ndarray, yr: np.ndarray, yt: np.ndarray,
                   x_out: np.ndarray) -> int:
    """Interpolated batch update (paper III-E with III-G): solve the batch for the kept union
    nodes only (:func:`kept_union_nodes`), chains between them merged (eq. 31-33, the same
    kernels as single updates), then distribute each kept node's change over its chain.

    Runs after :func:`_batch_blocks` (𝔅(H) is updated over the whole union).  On return the
    slots are cleared, ``nodes_out[:nk]`` / ``x_out[:nk]`` hold the kept nodes and their steps;
    returns nk or ``BATCH_REJECTED``.
    """
    nu = bc.shape[0]
    seg = np.empty(nu, np.int64)
    seg_rep = np.empty(nu, np.int64)
    nseg = _segments(prob, cs, nb, e_off, e_slot, cnt, slot, nodes_out, seg, seg_rep)
    kept = np.empty(nu, np.bool_)
    nk = kept_union_nodes(prob, nu, d_max, seg, nseg, slot, nodes_out, kept)
    kidx = np.full(nu, -1, np.int64)
    ku = np.empty(nk, np.int64)
    j = 0
    for u in range(nu):
        if kept[u]:
            kidx[u] = j
            ku[j] = u
            j += 1
    # reduced blocks, poses, segments and entry lists; the merged chains (eq. 31)
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
    by_slotk = np.empty(cntk[nk], np.int64)
    for j in range(nk):
        u = ku[j]
        for t in range(cnt[u + 1] - cnt[u]):
            by_slotk[cntk[j] + t] = by_slot[cnt[u] + t]
    xk = np.empty((nk, 6))
    if zero_block and nk <= MAX_DENSE_NODES:
        e_slotk = np.empty(e_slot.shape[0], np.int64)
        for e in range(e_slot.shape[0]):
            e_slotk[e] = kidx[e_slot[e]]
        ok = _dense_solve(nb, jb, e_off, e_slotk, r_off, krs, rbuf, bck, scalek, mu, False, xk)
        if not ok:
            ok = _dense_solve(nb, jb, e_off, e_slotk, r_off, krs, rbuf, bck, scalek, mu, True,
                              xk)
    else:
        lf = np.empty((nk, 6, 6))
        vv = np.empty((nk, 6, 6))
        mseg = _segment_moments(jb, krs, e_q, cntk, by_slotk, bck, mu, yrk, ytk, segk, nseg,
                                lf, vv)
        k_rows = r_off[nb]
        smat = _capacitance(prob, cs, e_off, e_q, r_off, krs, cnt, by_slot, amat, mseg,
                            seg_rep, k_rows)
        sym = 0.5 * (smat + smat.T)
        ok = chol_inplace(sym, k_rows)
        if ok:
            zz = rbuf[:k_rows].reshape((k_rows, 1)).copy()
            chol_solve_cols(sym, k_rows, zz, 1)
            _back_substitute(prob, cs, e_off, e_q, r_off, krs, cnt, by_slot, amat, zz, segk,
                             seg_rep, nseg, lf, vv, xk)
    for u in range(nu):
        slot[nodes_out[u]] = -1
    for j in range(nk):
        nodes_out[j] = chain_nodes[chain_start[j]]
        x_out[j] = xk[j]
    if not ok:
        return BATCH_REJECTED
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


# --------------------------------------------------------------------------- the batch update
def _make_batch_relax(with_interpolation: bool) -> Callable[..., int]:
    """:func:`batch_relax`, or without ``with_interpolation`` :data:`batch_relax_exact`, which
    ignores ``d_max`` and never compiles the interpolated batch (:func:`_reduced_batch` and its
    callees, about a third of the GPS batches' compile time; the closure's constant is pruned
    before typing)."""

    def batch_relax(prob: Problem, state: State, cs: np.ndarray, nb: int, tau: float, mu: float,
                    slot: np.ndarray, x_out: np.ndarray, nodes_out: np.ndarray,
                    d_max: int = 0, dense: bool = True) -> int:
        """Relax the constraints ``cs[:nb]`` together (paper eq. 35-37, DESIGN §5).

        ``slot`` (T,) must be -1 on entry and is -1 again on exit.  The step of union node
        ``nodes_out[u]`` is written to ``x_out[u]``.  Returns the number of union nodes, or
        ``BATCH_REJECTED`` when the step was not finite (nothing applied).

        With ``0 < d_max <`` the union's size the batch is solved by interpolation
        (:func:`_reduced_batch`, paper III-E/III-G): ``nodes_out`` / ``x_out`` then hold the kept
        nodes and the return value is their number.

        ``dense=False`` keeps the segmented Woodbury solve even when a block of B_C vanishes (a
        node all of whose constraints are in the batch): such a block is then damped like every
        other (DESIGN §4) and the cost stays O(entries + (6|C|)^3) instead of the dense
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
        nu = _union(prob, cs, nb, slot, nodes_out, e_off, e_slot, e_q)
        cnt, by_slot = _entries_by_node(e_slot, nu)
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
            return _reduced_batch(prob, state, cs, nb, tau, mu, d_max, wk, jb, e_off, e_slot,
                                  e_q, r_off, krs, rbuf, cnt, by_slot, bc, scale, slot,
                                  nodes_out, amat, yr, yt, x_out)
        if dense and zero_block and nu <= MAX_DENSE_NODES:
            # the exact step (eq. 37; the GN step when C is every constraint) when it is defined;
            # damped when the batch alone leaves a direction free (DESIGN §4)
            ok = _dense_solve(nb, jb, e_off, e_slot, r_off, krs, rbuf, bc, scale, mu, False,
                              x_out)
            if not ok:
                ok = _dense_solve(nb, jb, e_off, e_slot, r_off, krs, rbuf, bc, scale, mu, True,
                                  x_out)
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
