"""Compiled kernels of the hybrid Hessian solver (paper III-B..III-D, III-H; DESIGN.md §3, §4).

State (struct-of-arrays, all preallocated by the driver in ``hybrid.py``):

* ``rot (T,3,3), trans (T,3)``: local transforms ``T_i = X_parent^-1 X_i`` of the tree nodes;
* ``bdiag (T,6,6)``: the block diagonal 𝔅(H) of ``H = sum_c J_c^T J_c``;
* ``contrib (nnz,6,6)``: for every constraint and every node of its path, the block
  ``J_c^iT J_c^i`` it last contributed to ``bdiag`` (so eq. 24 is an O(d) update).

Constraints are indexed ``0..M-1`` (relative edges) then ``M..M+G-1`` (GPS).  For a relative
constraint the whitened Jacobian block of path node i is ``s_i L^T Jr^-1(e0) Ad(X_b^-1 X_i)``;
for GPS ``L^T R_i [I | -[t_{i->n}]x]`` (DESIGN §3).  Both are computed from products of local
transforms along the path only (no global pose is needed), so one update costs O(d).

Status codes returned by the kernels: ``STATUS_OK`` or ``STATUS_NONFINITE`` (a step was
non-finite and rejected; the poses were not touched).
"""

from __future__ import annotations

import math

import numpy as np

from .._numba import cycle_counter, kernel
from ..geometry._kernels import (
    orthonormalize,
    relative_error,
    se3_exp,
    se3_right_jacobian_inv,
    skew,
)

STEP_WOODBURY = 0
STEP_GIVENS = 1

#: A block of B_c is damped by ``mu * trace(B)/6 + TINY * scale`` (DESIGN §4); ``scale`` is the
#: trace of the constraint's own block, so a node that only constraint c touches still gets a
#: finite, well-scaled step.
TINY = 1e-9
#: Largest rotation (rad) any node may turn in one step (paper III-H).
MAX_ROTATION = math.pi / 8.0


# --------------------------------------------------------------------------- small dense helpers
@kernel
def _chol_inplace(a: np.ndarray, n: int) -> bool:
    """Lower Cholesky factor of the leading n x n block of ``a``, in place. False if not SPD."""
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if not (s > 0.0):
            return False
        d = math.sqrt(s)
        a[j, j] = d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s / d
        for i in range(j):
            a[i, j] = 0.0
    return True


@kernel
def _chol_solve_cols(lo: np.ndarray, n: int, b: np.ndarray, ncols: int) -> None:
    """Solve (L L^T) X = B in place for the first ``ncols`` columns of ``b`` (n rows)."""
    for c in range(ncols):
        for i in range(n):
            s = b[i, c]
            for k in range(i):
                s -= lo[i, k] * b[k, c]
            b[i, c] = s / lo[i, i]
        for i in range(n - 1, -1, -1):
            s = b[i, c]
            for k in range(i + 1, n):
                s -= lo[k, i] * b[k, c]
            b[i, c] = s / lo[i, i]


@kernel
def _regularized_factor(bc: np.ndarray, scale: float, mu: float, out: np.ndarray) -> None:
    """``out`` = lower Cholesky factor of sym(bc) + (mu tr(bc)/6 + TINY scale) I (DESIGN §4).

    Rounding in ``bdiag - old`` can leave ``bc`` slightly indefinite; the damping is raised
    tenfold until the factorization succeeds.
    """
    tr = 0.0
    for i in range(6):
        tr += bc[i, i]
    if tr < 0.0:
        tr = 0.0
    damp = mu * tr / 6.0 + TINY * scale
    if not (damp > 0.0):
        damp = 1e-300
    for _ in range(60):
        for i in range(6):
            for j in range(6):
                out[i, j] = 0.5 * (bc[i, j] + bc[j, i])
            out[i, i] += damp
        if _chol_inplace(out, 6):
            return
        damp *= 10.0
        if damp < 1e-12 * (tr + scale):
            damp = 1e-12 * (tr + scale)


# --------------------------------------------------------------------------- linearization
@kernel
def _path_products(c: int, ptr: np.ndarray, pnode: np.ndarray, psign: np.ndarray,
                   rot: np.ndarray, trans: np.ndarray, pr: np.ndarray, pt: np.ndarray) -> int:
    """P_k = X_root^-1 X_{path[k]} for every path node k (into ``pr``, ``pt``); returns n_a.

    The a-side nodes are stored from a upward, so products are accumulated from the top down.
    """
    s = ptr[c]
    d = ptr[c + 1] - s
    na = 0
    while na < d and psign[s + na] < 0:
        na += 1
    # a side: indices 0..na-1, top is na-1
    for k in range(na - 1, -1, -1):
        i = pnode[s + k]
        if k == na - 1:
            pr[k] = rot[i]
            pt[k] = trans[i]
        else:
            pr[k] = pr[k + 1] @ rot[i]
            pt[k] = pr[k + 1] @ trans[i] + pt[k + 1]
    for k in range(d - 1, na - 1, -1):
        i = pnode[s + k]
        if k == d - 1:
            pr[k] = rot[i]
            pt[k] = trans[i]
        else:
            pr[k] = pr[k + 1] @ rot[i]
            pt[k] = pr[k + 1] @ trans[i] + pt[k + 1]
    return na


@kernel
def _linearize(c: int, m_edges: int, ptr: np.ndarray, pnode: np.ndarray, psign: np.ndarray,
               rot: np.ndarray, trans: np.ndarray, edge_rot: np.ndarray, edge_trans: np.ndarray,
               edge_lt: np.ndarray, gps_pos: np.ndarray, gps_lt: np.ndarray, pr: np.ndarray,
               pt: np.ndarray, jac: np.ndarray, r: np.ndarray) -> int:
    """Whitened Jacobian blocks ``jac[k, :kr, :]`` and residual ``r[:kr]`` (= -L^T e0).

    Returns kr, the number of rows (6 relative, 3 GPS).
    """
    s = ptr[c]
    d = ptr[c + 1] - s
    na = _path_products(c, ptr, pnode, psign, rot, trans, pr, pt)
    if c < m_edges:
        ra = np.eye(3)
        ta = np.zeros(3)
        if na > 0:
            ra = pr[0]
            ta = pt[0]
        rb = np.eye(3)
        tb = np.zeros(3)
        if na < d:
            rb = pr[na]
            tb = pt[na]
        rab = ra.T @ rb
        tab = ra.T @ (tb - ta)
        e0 = relative_error(edge_rot[c], edge_trans[c], rab, tab)
        a = edge_lt[c] @ se3_right_jacobian_inv(e0)
        r[:6] = -(edge_lt[c] @ e0)
        adj = np.zeros((6, 6))
        for k in range(d):
            rm = rb.T @ pr[k]
            tm = rb.T @ (pt[k] - tb)
            adj[0:3, 0:3] = rm
            adj[3:6, 3:6] = rm
            adj[0:3, 3:6] = skew(tm) @ rm
            jac[k] = psign[s + k] * (a @ adj)
        return 6
    g = c - m_edges
    tn = pt[0]  # path[0] is n itself; the earth is the identity
    e0 = tn - gps_pos[g]
    lt = gps_lt[g]
    r[:3] = -(lt @ e0)
    blk = np.zeros((3, 6))
    for k in range(d):
        rk = pr[k]
        t_kn = rk.T @ (tn - pt[k])
        blk[:, 0:3] = rk
        blk[:, 3:6] = -(rk @ skew(t_kn))
        jac[k, 0:3, :] = lt @ blk
        jac[k, 3:6, :] = 0.0
    return 3


# --------------------------------------------------------------------------- the two solves
@kernel
def _woodbury_solve(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray,
                    y: np.ndarray, x: np.ndarray) -> None:
    """x = B^-1 J^T (I + J B^-1 J^T)^-1 r with B = blockdiag(lfac lfac^T): O(d) (DESIGN §4)."""
    smat = np.zeros((kr, kr))
    for i in range(kr):
        smat[i, i] = 1.0
    for k in range(d):
        for i in range(6):
            for q in range(kr):
                y[k, i, q] = jac[k, q, i]
        _chol_solve_cols(lfac[k], 6, y[k], kr)
        for p in range(kr):
            for q in range(kr):
                acc = 0.0
                for i in range(6):
                    acc += jac[k, p, i] * y[k, i, q]
                smat[p, q] += acc
    z = np.empty(kr)
    for i in range(kr):
        z[i] = r[i]
    sl = np.zeros((6, 6))
    for p in range(kr):
        for q in range(kr):
            sl[p, q] = 0.5 * (smat[p, q] + smat[q, p])
    ok = _chol_inplace(sl, kr)
    if not ok:
        for k in range(d):
            x[k, :] = np.nan
        return
    zz = np.empty((kr, 1))
    for i in range(kr):
        zz[i, 0] = z[i]
    _chol_solve_cols(sl, kr, zz, 1)
    for k in range(d):
        for i in range(6):
            acc = 0.0
            for q in range(kr):
                acc += y[k, i, q] * zz[q, 0]
            x[k, i] = acc


@kernel
def _givens_solve(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray,
                  x: np.ndarray) -> None:
    """The paper's solve (eq. 29-30): Givens-triangularize [J; Gamma] x = [r; 0], O(d^2).

    Gamma is block diagonal with upper-triangular blocks Gamma_k = L_k^T (Gamma^T Gamma = B).
    Each J row is rotated into the Gamma rows column by column; the Gamma rows fill in to the
    right, giving a dense upper-triangular R, then R x = b is back-substituted.
    """
    n = 6 * d
    rr = np.zeros((n, n))
    rhs = np.zeros(n)
    for k in range(d):
        for i in range(6):
            for j in range(i, 6):
                rr[6 * k + i, 6 * k + j] = lfac[k, j, i]
    w = np.zeros((kr, n))
    wr = np.zeros(kr)
    for q in range(kr):
        wr[q] = r[q]
        for k in range(d):
            for i in range(6):
                w[q, 6 * k + i] = jac[k, q, i]
    for col in range(n):
        for q in range(kr):
            b = w[q, col]
            if b == 0.0:
                continue
            a = rr[col, col]
            h = math.hypot(a, b)
            cs = a / h
            sn = b / h
            for j in range(col, n):
                u = rr[col, j]
                v = w[q, j]
                rr[col, j] = cs * u + sn * v
                w[q, j] = -sn * u + cs * v
            u = rhs[col]
            v = wr[q]
            rhs[col] = cs * u + sn * v
            wr[q] = -sn * u + cs * v
    for i in range(n - 1, -1, -1):
        acc = rhs[i]
        for j in range(i + 1, n):
            acc -= rr[i, j] * rhs[j]
        rhs[i] = acc / rr[i, i]
    for k in range(d):
        for i in range(6):
            x[k, i] = rhs[6 * k + i]


# --------------------------------------------------------------------------- one update
@kernel
def _accumulate_blocks(c: int, d: int, kr: int, ptr: np.ndarray, pnode: np.ndarray,
                       jac: np.ndarray, bdiag: np.ndarray, contrib: np.ndarray,
                       mu: float, lfac: np.ndarray) -> None:
    """Eq. 23/24: B_c = 𝔅(H) - 𝔅(J_c^T J_c)_old; 𝔅(H) += new - old; factor damped B_c."""
    s = ptr[c]
    newb = np.empty((6, 6))
    bc = np.empty((6, 6))
    for k in range(d):
        i = pnode[s + k]
        scale = 0.0
        for p in range(6):
            for q in range(6):
                acc = 0.0
                for t in range(kr):
                    acc += jac[k, t, p] * jac[k, t, q]
                newb[p, q] = acc
            scale += newb[p, p]
        for p in range(6):
            for q in range(6):
                old = contrib[s + k, p, q]
                bc[p, q] = bdiag[i, p, q] - old
                bdiag[i, p, q] += newb[p, q] - old
                contrib[s + k, p, q] = newb[p, q]
        _regularized_factor(bc, scale, mu, lfac[k])


@kernel
def _relax(c: int, tau: float, mu: float, step_kind: int, m_edges: int, ptr: np.ndarray,
           pnode: np.ndarray, psign: np.ndarray, rot: np.ndarray, trans: np.ndarray,
           edge_rot: np.ndarray, edge_trans: np.ndarray, edge_lt: np.ndarray,
           gps_pos: np.ndarray, gps_lt: np.ndarray, bdiag: np.ndarray, contrib: np.ndarray,
           pr: np.ndarray, pt: np.ndarray, jac: np.ndarray, lfac: np.ndarray, y: np.ndarray,
           x: np.ndarray, r: np.ndarray, apply: bool) -> int:
    """Relax constraint c (paper eq. 25): linearize, update 𝔅(H), solve, apply ``tau x``.

    Returns 0 (applied), 1 (capped by the pi/8 rule, applied), 2 (non-finite, rejected).
    """
    s = ptr[c]
    d = ptr[c + 1] - s
    if d == 0:
        return 0
    kr = _linearize(c, m_edges, ptr, pnode, psign, rot, trans, edge_rot, edge_trans, edge_lt,
                    gps_pos, gps_lt, pr, pt, jac, r)
    _accumulate_blocks(c, d, kr, ptr, pnode, jac, bdiag, contrib, mu, lfac)
    if not apply:
        return 0
    if step_kind == STEP_GIVENS:
        _givens_solve(d, kr, jac, lfac, r, x)
    else:
        _woodbury_solve(d, kr, jac, lfac, r, y, x)
    biggest = 0.0
    for k in range(d):
        for i in range(6):
            if not math.isfinite(x[k, i]):
                return 2
        ang = math.sqrt(x[k, 3] ** 2 + x[k, 4] ** 2 + x[k, 5] ** 2)
        if ang > biggest:
            biggest = ang
    status = 0
    t = tau
    if t * biggest > MAX_ROTATION:  # paper III-H
        t = MAX_ROTATION / biggest
        status = 1
    for k in range(d):
        i = pnode[s + k]
        dr, dt = se3_exp(t * x[k])
        trans[i] = rot[i] @ dt + trans[i]
        rot[i] = orthonormalize(rot[i] @ dr)
    return status


@kernel
def init_blocks(m_edges: int, ptr: np.ndarray, pnode: np.ndarray, psign: np.ndarray,
                rot: np.ndarray, trans: np.ndarray, edge_rot: np.ndarray, edge_trans: np.ndarray,
                edge_lt: np.ndarray, gps_pos: np.ndarray, gps_lt: np.ndarray,
                bdiag: np.ndarray, contrib: np.ndarray, dmax: int) -> None:
    """𝔅(H) and every constraint's contribution at the current poses (no step)."""
    pr = np.empty((dmax, 3, 3))
    pt = np.empty((dmax, 3))
    jac = np.zeros((dmax, 6, 6))
    lfac = np.empty((dmax, 6, 6))
    y = np.empty((dmax, 6, 6))
    x = np.empty((dmax, 6))
    r = np.empty(6)
    bdiag[:] = 0.0
    contrib[:] = 0.0
    for c in range(ptr.shape[0] - 1):
        _relax(c, 0.0, 0.0, STEP_WOODBURY, m_edges, ptr, pnode, psign, rot, trans, edge_rot,
               edge_trans, edge_lt, gps_pos, gps_lt, bdiag, contrib, pr, pt, jac, lfac, y, x, r,
               False)


@kernel
def sweep(order: np.ndarray, tau: float, mu: float, step_kind: int, m_edges: int,
          ptr: np.ndarray, pnode: np.ndarray, psign: np.ndarray, rot: np.ndarray,
          trans: np.ndarray, edge_rot: np.ndarray, edge_trans: np.ndarray, edge_lt: np.ndarray,
          gps_pos: np.ndarray, gps_lt: np.ndarray, bdiag: np.ndarray, contrib: np.ndarray,
          dmax: int, cycles: np.ndarray, counts: np.ndarray) -> int:
    """One pass over the constraints in ``order`` (paper Algorithm 1, relative constraints).

    ``cycles[c]`` receives the cycle count of constraint c's update; ``counts`` accumulates
    [capped steps, rejected (non-finite) steps].  Returns the first rejected constraint or -1.
    """
    pr = np.empty((dmax, 3, 3))
    pt = np.empty((dmax, 3))
    jac = np.zeros((dmax, 6, 6))
    lfac = np.empty((dmax, 6, 6))
    y = np.empty((dmax, 6, 6))
    x = np.empty((dmax, 6))
    r = np.empty(6)
    first_bad = -1
    for idx in range(order.shape[0]):
        c = order[idx]
        t0 = cycle_counter()
        st = _relax(c, tau, mu, step_kind, m_edges, ptr, pnode, psign, rot, trans, edge_rot,
                    edge_trans, edge_lt, gps_pos, gps_lt, bdiag, contrib, pr, pt, jac, lfac, y,
                    x, r, True)
        cycles[c] = cycle_counter() - t0
        if st == 1:
            counts[0] += 1
        elif st == 2:
            counts[1] += 1
            if first_bad < 0:
                first_bad = c
    return first_bad


@kernel
def constraint_step(c: int, mu: float, step_kind: int, m_edges: int, ptr: np.ndarray,
                    pnode: np.ndarray, psign: np.ndarray, rot: np.ndarray, trans: np.ndarray,
                    edge_rot: np.ndarray, edge_trans: np.ndarray, edge_lt: np.ndarray,
                    gps_pos: np.ndarray, gps_lt: np.ndarray, bdiag: np.ndarray,
                    contrib: np.ndarray, jac_out: np.ndarray, r_out: np.ndarray,
                    x_out: np.ndarray) -> int:
    """Testing hook: linearize c, update blocks as a sweep would, return its step (not applied).

    Writes J blocks (d,6,6), r (6,) and x (d,6); returns kr.
    """
    d = ptr[c + 1] - ptr[c]
    pr = np.empty((d, 3, 3))
    pt = np.empty((d, 3))
    lfac = np.empty((d, 6, 6))
    y = np.empty((d, 6, 6))
    kr = _linearize(c, m_edges, ptr, pnode, psign, rot, trans, edge_rot, edge_trans, edge_lt,
                    gps_pos, gps_lt, pr, pt, jac_out, r_out)
    _accumulate_blocks(c, d, kr, ptr, pnode, jac_out, bdiag, contrib, mu, lfac)
    if step_kind == STEP_GIVENS:
        _givens_solve(d, kr, jac_out, lfac, r_out, x_out)
    else:
        _woodbury_solve(d, kr, jac_out, lfac, r_out, y, x_out)
    return kr
