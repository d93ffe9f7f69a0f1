"""The solve of a batch update (paper III-F, eq. 37): dense, or Woodbury over segments.

:func:`woodbury_segments` solves ``(sum_c J_c^T J_c + B_C) x = sum_c J_c^T r_c`` when every block
of B_C is non-zero, in O(entries + sum over segments of |sig|^2) (the segments of
:func:`._batch_union.segments`); :func:`exact_or_damped` solves it densely over the union when
B_C vanishes on a node only the batch touches.  The batch arrays are those of
:class:`._batch_union.BatchArrays`.
"""

from __future__ import annotations

import numpy as np

from ..._numba import kernel
from ...geometry._kernels import adjoint_into
from ._batch_union import entry_sign, segments
from ._dense import TINY, chol_inplace, chol_solve_cols, regularized_factor, solve_lt
from .problem import Problem

#: Largest union (nodes) solved by the dense normal equations when B_C has a zero block (larger:
#: the block is damped and the segments solve it).  The dense solve is O((6 |U|)^3): on a
#: 3 500-pose grid whose 35 GPS readings form one batch (the tree's root has only them through
#: it: a zero block), 2.4 s per sweep with unions up to 682 nodes, 0.04 s with the segments.
MAX_DENSE_NODES = 64
#: An undamped dense batch system whose Cholesky pivot^2 falls below this fraction of its
#: diagonal entry is singular to rounding; it is solved again with the damping of
#: docs/mathematics.md#hybrid-step.
SINGULAR_PIVOT = 1e-12


# --------------------------------------------------------------------------- dense
@kernel
def dense_solve(nb: int, jb: np.ndarray, e_off: np.ndarray, e_slot: np.ndarray,
                r_off: np.ndarray, krs: np.ndarray, rbuf: np.ndarray, bc: np.ndarray,
                scale: np.ndarray, mu: float, damped: bool, x_out: np.ndarray) -> bool:
    """``(sum_c J_c^T J_c + B_C) x = sum_c J_c^T r_c`` densely over the union (6|U| unknowns).

    An entry whose ``e_slot`` is negative is left out (interpolated batches).
    ``damped``: every block of B_C gets the damping of docs/mathematics.md#hybrid-step (``mu
    tr(B)/6 + TINY scale``),
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

@kernel
def exact_or_damped(nb: int, jb: np.ndarray, e_off: np.ndarray, e_slot: np.ndarray,
                    r_off: np.ndarray, krs: np.ndarray, rbuf: np.ndarray, bc: np.ndarray,
                    scale: np.ndarray, mu: float, x_out: np.ndarray) -> bool:
    """The exact step (eq. 37; the GN step when C is every constraint) when it is defined;
    damped when the batch alone leaves a direction free (:func:`dense_solve`)."""
    if dense_solve(nb, jb, e_off, e_slot, r_off, krs, rbuf, bc, scale, mu, False, x_out):
        return True
    return dense_solve(nb, jb, e_off, e_slot, r_off, krs, rbuf, bc, scale, mu, True, x_out)


# --------------------------------------------------------------------------- Woodbury
@kernel
def segment_moments(jb: np.ndarray, krs: np.ndarray, e_q: np.ndarray, cnt: np.ndarray,
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
def capacitance(prob: Problem, cs: np.ndarray, e_off: np.ndarray, e_q: np.ndarray,
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
            se = entry_sign(prob, cs, e_off, e_q, e)
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
                sf = entry_sign(prob, cs, e_off, e_q, f)
                for a in range(kre):
                    for b in range(krs[qf]):
                        acc = 0.0
                        for m in range(6):
                            acc += tm[a, m] * amat[qf, b, m]
                        smat[r_off[qe] + a, r_off[qf] + b] += sf * acc
    return smat


@kernel
def back_substitute(prob: Problem, cs: np.ndarray, e_off: np.ndarray, e_q: np.ndarray,
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
            se = entry_sign(prob, cs, e_off, e_q, e)
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
def solve_segmented(prob: Problem, cs: np.ndarray, nb: int, mu: float, jb: np.ndarray,
                    e_off: np.ndarray, e_q: np.ndarray, r_off: np.ndarray, krs: np.ndarray,
                    rbuf: np.ndarray, cnt: np.ndarray, by_slot: np.ndarray, amat: np.ndarray,
                    seg_rep: np.ndarray, nseg: int, node_cnt: np.ndarray,
                    node_by_slot: np.ndarray, bc: np.ndarray, yr: np.ndarray, yt: np.ndarray,
                    seg: np.ndarray, x_out: np.ndarray) -> bool:
    """The Woodbury solve of :func:`woodbury_segments` for the nodes ``bc``, ``yr``, ``yt``,
    ``seg`` describe (their entries ``node_cnt``, ``node_by_slot``): the union's, or the kept
    nodes of an interpolated batch.  ``cnt``, ``by_slot`` and ``seg_rep`` (a representative
    union node per segment) are the union's.  Returns False when S is not positive definite.
    """
    nu = bc.shape[0]
    lf = np.empty((nu, 6, 6))
    vv = np.empty((nu, 6, 6))
    mseg = segment_moments(jb, krs, e_q, node_cnt, node_by_slot, bc, mu, yr, yt, seg, nseg,
                           lf, vv)
    k_rows = r_off[nb]
    smat = capacitance(prob, cs, e_off, e_q, r_off, krs, cnt, by_slot, amat, mseg, seg_rep,
                       k_rows)
    sym = 0.5 * (smat + smat.T)
    if not chol_inplace(sym, k_rows):
        return False
    zz = rbuf[:k_rows].reshape((k_rows, 1)).copy()
    chol_solve_cols(sym, k_rows, zz, 1)
    back_substitute(prob, cs, e_off, e_q, r_off, krs, cnt, by_slot, amat, zz, seg, seg_rep,
                    nseg, lf, vv, x_out)
    return True


@kernel
def woodbury_segments(prob: Problem, cs: np.ndarray, nb: int, mu: float, jb: np.ndarray,
                      e_off: np.ndarray, r_off: np.ndarray, krs: np.ndarray, rbuf: np.ndarray,
                      e_slot: np.ndarray, e_q: np.ndarray, cnt: np.ndarray,
                      by_slot: np.ndarray, bc: np.ndarray, slot: np.ndarray,
                      nodes_out: np.ndarray, amat: np.ndarray, yr: np.ndarray, yt: np.ndarray,
                      x_out: np.ndarray) -> bool:
    """Woodbury solve of a batch in O(entries + sum over segments of |sig|^2)
    (docs/mathematics.md#batches).

    Every Jacobian block factors as ``J_{c,u} = s_{c,u} A_c Ad(Y_u)``.  Union nodes whose
    constraint sets agree (chains between branch points, "segments") share one moment
    ``M_seg = sum_u Ad(Y_u) B_u^-1 Ad(Y_u)^T``, so the capacitance matrix
    ``S = I + sum_seg sum_{c,d} s_c s_d A_c M_seg A_d^T`` costs O(|sig|^2) per segment instead
    of per node: a batch of GPS readings sharing a long trunk stays cheap.
    """
    nu = bc.shape[0]
    seg = np.empty(nu, np.int64)
    seg_rep = np.empty(nu, np.int64)
    nseg = segments(prob, cs, nb, e_off, e_slot, cnt, slot, nodes_out, seg, seg_rep)
    return solve_segmented(prob, cs, nb, mu, jb, e_off, e_q, r_off, krs, rbuf, cnt, by_slot,
                           amat, seg_rep, nseg, cnt, by_slot, bc, yr, yt, seg, x_out)
