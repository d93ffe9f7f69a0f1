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

The read-only problem arrays travel as one tuple ``prob = (m_edges, path_ptr, path_node,
path_sign, edge_rot, edge_trans, edge_lt, gps_pos, gps_lt, path_count, parent)`` and the mutable
arrays as ``state = (rot, trans, bdiag, contrib)`` (built by ``HybridState.problem`` /
``HybridState.arrays``).

A single update returns 0 (applied), 1 (applied with the pi/8 cap) or 2 (non-finite step,
rejected: the poses were not touched); a batch returns its number of nodes, or -1 when rejected.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._numba import cycle_counter, kernel
from ..geometry._fast import edge_error_into, jr_inv_blocks, skew_into
from ..geometry._kernels import SMALL_ANGLE

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
        inv_d = 1.0 / d  # one division per column (divisions dominate 6x6 factorizations)
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s * inv_d
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
            for j in range(i + 1):  # the factorization reads the lower triangle only
                out[i, j] = 0.5 * (bc[i, j] + bc[j, i])
            out[i, i] += damp
        if _chol_inplace(out, 6):
            return
        damp *= 10.0
        if damp < 1e-12 * (tr + scale):
            damp = 1e-12 * (tr + scale)


# --------------------------------------------------------------------------- linearization
@kernel
def _mul_pose_into(
    ra: np.ndarray, ta: np.ndarray, rb: np.ndarray, tb: np.ndarray, ro: np.ndarray, to: np.ndarray
) -> None:
    """(ro, to) = (ra, ta) * (rb, tb) without allocating (outputs must not alias inputs)."""
    for i in range(3):
        for j in range(3):
            ro[i, j] = ra[i, 0] * rb[0, j] + ra[i, 1] * rb[1, j] + ra[i, 2] * rb[2, j]
        to[i] = ra[i, 0] * tb[0] + ra[i, 1] * tb[1] + ra[i, 2] * tb[2] + ta[i]


@kernel
def _path_products(
    c: int,
    ptr: np.ndarray,
    pnode: np.ndarray,
    psign: np.ndarray,
    rot: np.ndarray,
    trans: np.ndarray,
    pr: np.ndarray,
    pt: np.ndarray,
) -> int:
    """P_k = X_root^-1 X_{path[k]} for every path node k (into ``pr``, ``pt``); returns n_a.

    The a-side nodes are stored from a upward, so products are accumulated from the top down.
    """
    s = ptr[c]
    d = ptr[c + 1] - s
    na = 0
    while na < d and psign[s + na] < 0:
        na += 1
    for k in range(na - 1, -1, -1):  # a side: indices 0..na-1, top is na-1
        i = pnode[s + k]
        if k == na - 1:
            pr[k] = rot[i]
            pt[k] = trans[i]
        else:
            _mul_pose_into(pr[k + 1], pt[k + 1], rot[i], trans[i], pr[k], pt[k])
    for k in range(d - 1, na - 1, -1):
        i = pnode[s + k]
        if k == d - 1:
            pr[k] = rot[i]
            pt[k] = trans[i]
        else:
            _mul_pose_into(pr[k + 1], pt[k + 1], rot[i], trans[i], pr[k], pt[k])
    return na


@kernel
def _error_and_jr_inv(
    zr: np.ndarray,
    zt: np.ndarray,
    ra: np.ndarray,
    ta: np.ndarray,
    rb: np.ndarray,
    tb: np.ndarray,
    e: np.ndarray,
    jri: np.ndarray,
    ws: np.ndarray,
) -> None:
    """e = Log(Z^-1 X_a^-1 X_b) and Jr^-1(e) (6, 6), allocation-free (ws: (12, 3, 3) scratch)."""
    edge_error_into(ra, ta, rb, tb, zr, zt, ws[10], ws[11][0], ws[0], e)
    jr_inv_blocks(e, ws)
    jm = ws[8]
    km = ws[9]
    for i in range(3):
        for j in range(3):
            jri[i, j] = jm[i, j]
            jri[i, 3 + j] = km[i, j]
            jri[3 + i, j] = 0.0
            jri[3 + i, 3 + j] = jm[i, j]


@kernel
def _endpoints(
    pr: np.ndarray, pt: np.ndarray, na: int, d: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Poses of a and b relative to the constraint's root, from the path products.

    An empty side means that endpoint is the root itself (the identity).
    """
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
    return ra, ta, rb, tb


@kernel
def _linearize(
    c: int,
    prob: tuple[Any, ...],
    rot: np.ndarray,
    trans: np.ndarray,
    pr: np.ndarray,
    pt: np.ndarray,
    jac: np.ndarray,
    r: np.ndarray,
) -> int:
    """Whitened Jacobian blocks ``jac[k, :kr, :]`` and residual ``r[:kr]`` (= -L^T e0).

    Returns kr, the number of rows (6 relative, 3 GPS).
    """
    # fmt: off
    (m_edges, ptr, pnode, psign, edge_rot, edge_trans, edge_lt, gps_pos, gps_lt, _path_count,
     _parent) = prob
    # fmt: on
    s = ptr[c]
    d = ptr[c + 1] - s
    na = _path_products(c, ptr, pnode, psign, rot, trans, pr, pt)
    if c < m_edges:
        ra, ta, rb, tb = _endpoints(pr, pt, na, d)
        e0 = np.empty(6)
        jri = np.empty((6, 6))
        ws = np.empty((12, 3, 3))
        _error_and_jr_inv(edge_rot[c], edge_trans[c], ra, ta, rb, tb, e0, jri, ws)
        lt = edge_lt[c]
        a = np.empty((6, 6))
        for p in range(6):
            acc = 0.0
            for q in range(6):
                acc += lt[p, q] * e0[q]
            r[p] = -acc
            for j in range(6):
                acc = 0.0
                for q in range(p, 6):  # L^T is upper triangular
                    acc += lt[p, q] * jri[q, j]
                a[p, j] = acc
        rm = np.empty((3, 3))
        tm = np.empty(3)
        tx = np.empty((3, 3))
        for k in range(d):
            # M_k = X_b^-1 X_k = P_b^-1 P_k; J_k = s_k A Ad(M_k), Ad = [[R, [t]x R], [0, R]]
            for i in range(3):
                tm[i] = (
                    rb[0, i] * (pt[k, 0] - tb[0])
                    + rb[1, i] * (pt[k, 1] - tb[1])
                    + rb[2, i] * (pt[k, 2] - tb[2])
                )
                for j in range(3):
                    rm[i, j] = (
                        rb[0, i] * pr[k, 0, j] + rb[1, i] * pr[k, 1, j] + rb[2, i] * pr[k, 2, j]
                    )
            for j in range(3):  # tx = [tm]x rm
                tx[0, j] = tm[1] * rm[2, j] - tm[2] * rm[1, j]
                tx[1, j] = tm[2] * rm[0, j] - tm[0] * rm[2, j]
                tx[2, j] = tm[0] * rm[1, j] - tm[1] * rm[0, j]
            sg = float(psign[s + k])
            for p in range(6):
                for j in range(3):
                    v0 = a[p, 0] * rm[0, j] + a[p, 1] * rm[1, j] + a[p, 2] * rm[2, j]
                    v1 = (
                        a[p, 0] * tx[0, j]
                        + a[p, 1] * tx[1, j]
                        + a[p, 2] * tx[2, j]
                        + a[p, 3] * rm[0, j]
                        + a[p, 4] * rm[1, j]
                        + a[p, 5] * rm[2, j]
                    )
                    jac[k, p, j] = sg * v0
                    jac[k, p, 3 + j] = sg * v1
        return 6
    g = c - m_edges
    tn = pt[0]  # path[0] is n itself; the earth is the identity
    e0 = tn - gps_pos[g]
    lt = gps_lt[g]
    r[:3] = -(lt @ e0)
    blk = np.empty((3, 6))
    t_kn = np.empty(3)
    for k in range(d):
        for i in range(3):
            t_kn[i] = (
                pr[k, 0, i] * (tn[0] - pt[k, 0])
                + pr[k, 1, i] * (tn[1] - pt[k, 1])
                + pr[k, 2, i] * (tn[2] - pt[k, 2])
            )
        for i in range(
            3
        ):  # R_k [I | -[t]x], with [t]x's columns (0,t2,-t1), (-t2,0,t0), (t1,-t0,0)
            blk[i, 0] = pr[k, i, 0]
            blk[i, 1] = pr[k, i, 1]
            blk[i, 2] = pr[k, i, 2]
            blk[i, 3] = -(pr[k, i, 1] * t_kn[2] - pr[k, i, 2] * t_kn[1])
            blk[i, 4] = -(-pr[k, i, 0] * t_kn[2] + pr[k, i, 2] * t_kn[0])
            blk[i, 5] = -(pr[k, i, 0] * t_kn[1] - pr[k, i, 1] * t_kn[0])
        for p in range(3):
            for j in range(6):
                jac[k, p, j] = lt[p, 0] * blk[0, j] + lt[p, 1] * blk[1, j] + lt[p, 2] * blk[2, j]
        for p in range(3, 6):
            for j in range(6):
                jac[k, p, j] = 0.0
    return 3


# --------------------------------------------------------------------------- the two solves
@kernel
def _woodbury_solve(
    d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray, y: np.ndarray, x: np.ndarray
) -> None:
    """x = B^-1 J^T (I + J B^-1 J^T)^-1 r with B = blockdiag(L_k L_k^T): O(d) (DESIGN §4).

    With W_k = L_k^-1 J_k^T (forward substitution), S = I + sum_k W_k^T W_k and
    x_k = L_k^-T W_k S^-1 r.  ``y`` holds the W_k.
    """
    smat = np.zeros((6, 6))
    for i in range(kr):
        smat[i, i] = 1.0
    for k in range(d):
        lk = lfac[k]
        for i in range(6):
            inv = 1.0 / lk[i, i]
            for q in range(kr):
                acc = jac[k, q, i]
                for m in range(i):
                    acc -= lk[i, m] * y[k, m, q]
                y[k, i, q] = acc * inv
        for p in range(kr):
            for q in range(p, kr):
                acc = 0.0
                for i in range(6):
                    acc += y[k, i, p] * y[k, i, q]
                smat[p, q] += acc
    for p in range(kr):
        for q in range(p):
            smat[p, q] = smat[q, p]
    if not _chol_inplace(smat, kr):
        for k in range(d):
            x[k, :] = np.nan
        return
    zz = np.empty((6, 1))
    for i in range(kr):
        zz[i, 0] = r[i]
    _chol_solve_cols(smat, kr, zz, 1)
    v = np.empty(6)
    for k in range(d):
        lk = lfac[k]
        for i in range(6):
            acc = 0.0
            for q in range(kr):
                acc += y[k, i, q] * zz[q, 0]
            v[i] = acc
        for i in range(5, -1, -1):
            acc = v[i]
            for m in range(i + 1, 6):
                acc -= lk[m, i] * x[k, m]
            x[k, i] = acc / lk[i, i]


@kernel
def _givens_solve(
    d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray, x: np.ndarray
) -> None:
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


@kernel
def _apply_step(
    rot_i: np.ndarray,
    trans_i: np.ndarray,
    xi: np.ndarray,
    t: float,
    er: np.ndarray,
    tmp: np.ndarray,
) -> None:
    """T_i <- T_i Exp(t xi) in place, then re-orthonormalize R_i (no allocation)."""
    rx, ry, rz = t * xi[0], t * xi[1], t * xi[2]
    px, py, pz = t * xi[3], t * xi[4], t * xi[5]
    th2 = px * px + py * py + pz * pz
    th = math.sqrt(th2)
    if th < SMALL_ANGLE:
        sa = 1.0 - th2 / 6.0  # sin(th)/th
        sb = 0.5 - th2 / 24.0  # (1 - cos th)/th^2
        sc = 1.0 / 6.0 - th2 / 120.0  # (th - sin th)/th^3
    else:
        sn = math.sin(th)
        sh = math.sin(0.5 * th)
        sa = sn / th
        sb = 2.0 * sh * sh / th2
        sc = (th - sn) / (th2 * th)
    # K = [phi]x, K^2 = phi phi^T - th^2 I
    k = tmp
    skew_into(px, py, pz, k)
    ph = (px, py, pz)
    for i in range(3):
        for j in range(3):
            k2 = ph[i] * ph[j] - (th2 if i == j else 0.0)
            idn = 1.0 if i == j else 0.0
            er[i, j] = idn + sa * k[i, j] + sb * k2
    # t_exp = V rho, V = I + sb K + sc K^2
    rho = (rx, ry, rz)
    dt0 = rx
    dt1 = ry
    dt2 = rz
    for j in range(3):
        v0 = sb * k[0, j] + sc * (ph[0] * ph[j] - (th2 if j == 0 else 0.0))
        v1 = sb * k[1, j] + sc * (ph[1] * ph[j] - (th2 if j == 1 else 0.0))
        v2 = sb * k[2, j] + sc * (ph[2] * ph[j] - (th2 if j == 2 else 0.0))
        dt0 += v0 * rho[j]
        dt1 += v1 * rho[j]
        dt2 += v2 * rho[j]
    for i in range(3):
        trans_i[i] += rot_i[i, 0] * dt0 + rot_i[i, 1] * dt1 + rot_i[i, 2] * dt2
    for i in range(3):
        for j in range(3):
            tmp[i, j] = rot_i[i, 0] * er[0, j] + rot_i[i, 1] * er[1, j] + rot_i[i, 2] * er[2, j]
    # one Newton step towards the polar factor: R <- R (3I - R^T R) / 2
    for i in range(3):
        for j in range(3):
            er[i, j] = -(tmp[0, i] * tmp[0, j] + tmp[1, i] * tmp[1, j] + tmp[2, i] * tmp[2, j])
        er[i, i] += 3.0
    for i in range(3):
        for j in range(3):
            rot_i[i, j] = 0.5 * (tmp[i, 0] * er[0, j] + tmp[i, 1] * er[1, j] + tmp[i, 2] * er[2, j])


# --------------------------------------------------------------------------- one update
@kernel
def _accumulate_blocks(
    c: int,
    d: int,
    kr: int,
    ptr: np.ndarray,
    pnode: np.ndarray,
    jac: np.ndarray,
    bdiag: np.ndarray,
    contrib: np.ndarray,
    mu: float,
    lfac: np.ndarray,
) -> None:
    """Eq. 23/24: B_c = 𝔅(H) - 𝔅(J_c^T J_c)_old; 𝔅(H) += new - old; factor damped B_c."""
    s = ptr[c]
    bc = np.empty((6, 6))
    for k in range(d):
        i = pnode[s + k]
        scale = 0.0
        e = s + k
        # J^T J is symmetric: compute the upper triangle, mirror every store (the blocks stay
        # exactly symmetric, so B_c needs no symmetrization before its factorization)
        for p in range(6):
            for q in range(p, 6):
                acc = 0.0
                for t in range(kr):
                    acc += jac[k, t, p] * jac[k, t, q]
                old = contrib[e, p, q]
                b_old = bdiag[i, p, q]
                v = b_old + (acc - old)
                bdiag[i, p, q] = v
                bdiag[i, q, p] = v
                contrib[e, p, q] = acc
                contrib[e, q, p] = acc
                bc[p, q] = b_old - old
                bc[q, p] = b_old - old
            scale += contrib[e, p, p]
        _regularized_factor(bc, scale, mu, lfac[k])


@kernel
def _relax(
    c: int,
    tau: float,
    mu: float,
    step_kind: int,
    prob: tuple[Any, ...],
    state: tuple[Any, ...],
    pr: np.ndarray,
    pt: np.ndarray,
    jac: np.ndarray,
    lfac: np.ndarray,
    y: np.ndarray,
    x: np.ndarray,
    r: np.ndarray,
    apply: bool,
) -> int:
    """Relax constraint c (paper eq. 25): linearize, update 𝔅(H), solve, apply ``tau x``.

    Returns 0 (applied), 1 (capped by the pi/8 rule, applied), 2 (non-finite, rejected).
    """
    # fmt: off
    (_m_edges, ptr, pnode, _psign, _edge_rot, _edge_trans, _edge_lt, _gps_pos, _gps_lt,
     _path_count, _parent) = prob
    # fmt: on
    rot, trans, bdiag, contrib = state
    s = ptr[c]
    d = ptr[c + 1] - s
    if d == 0:
        return 0
    kr = _linearize(c, prob, rot, trans, pr, pt, jac, r)
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
    er = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for k in range(d):
        _apply_step(rot[pnode[s + k]], trans[pnode[s + k]], x[k], t, er, tmp)
    return status


@kernel
def _workspace(
    dmax: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Scratch buffers of single updates for paths of up to ``dmax`` poses:
    (path products R, t; Jacobian blocks; factors of B_c; W blocks; steps; residual)."""
    return (
        np.empty((dmax, 3, 3)),
        np.empty((dmax, 3)),
        np.zeros((dmax, 6, 6)),
        np.empty((dmax, 6, 6)),
        np.empty((dmax, 6, 6)),
        np.empty((dmax, 6)),
        np.empty(6),
    )


@kernel
def init_blocks(prob: tuple[Any, ...], state: tuple[Any, ...], dmax: int) -> None:
    """𝔅(H) and every constraint's contribution at the current poses (no step)."""
    # fmt: off
    (_m_edges, ptr, _pnode, _psign, _edge_rot, _edge_trans, _edge_lt, _gps_pos, _gps_lt,
     _path_count, _parent) = prob
    # fmt: on
    _rot, _trans, bdiag, contrib = state
    pr, pt, jac, lfac, y, x, r = _workspace(dmax)
    bdiag[:] = 0.0
    contrib[:] = 0.0
    for c in range(ptr.shape[0] - 1):
        _relax(c, 0.0, 0.0, STEP_WOODBURY, prob, state, pr, pt, jac, lfac, y, x, r, False)


# --------------------------------------------------------------------------- batch updates
@kernel
def _global_pose(
    i: int, parent: np.ndarray, rot: np.ndarray, trans: np.ndarray, ro: np.ndarray, to: np.ndarray
) -> None:
    """Pose of tree node i in the root's frame (product of locals up the tree), O(depth)."""
    tmp_r = np.empty((3, 3))
    tmp_t = np.empty(3)
    if i < 0:
        for a in range(3):
            for b in range(3):
                ro[a, b] = 1.0 if a == b else 0.0
            to[a] = 0.0
        return
    ro[:] = rot[i]
    to[:] = trans[i]
    v = parent[i]
    while v >= 0:
        _mul_pose_into(rot[v], trans[v], ro, to, tmp_r, tmp_t)
        ro[:] = tmp_r
        to[:] = tmp_t
        v = parent[v]


@kernel
def _adjoint_into(r: np.ndarray, t: np.ndarray, out: np.ndarray) -> None:
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


@kernel
def _woodbury_segments(
    cs: np.ndarray,
    nb: int,
    prob: tuple[Any, ...],
    rot: np.ndarray,
    trans: np.ndarray,
    mu: float,
    jb: np.ndarray,
    e_off: np.ndarray,
    r_off: np.ndarray,
    krs: np.ndarray,
    rbuf: np.ndarray,
    e_slot: np.ndarray,
    e_q: np.ndarray,
    cnt: np.ndarray,
    by_slot: np.ndarray,
    bc: np.ndarray,
    slot: np.ndarray,
    nodes_out: np.ndarray,
    nu: int,
    x_out: np.ndarray,
) -> bool:
    """Woodbury solve of a batch in O(entries + sum over segments of |sig|^2) (DESIGN §5).

    Every Jacobian block factors as ``J_{c,u} = s_{c,u} A_c Ad(Y_u)`` with ``Y_u`` the pose of
    node u in the tree root's frame and ``A_c`` a per-constraint matrix (relative:
    ``L^T Jr^-1(e) Ad(Y_b)^-1``; GPS: ``L^T [I | -[p_n]x]``).  Union nodes whose constraint sets
    agree (chains between branch points, "segments") share one moment
    ``M_seg = sum_u Ad(Y_u) B_u^-1 Ad(Y_u)^T``, so
    ``S = I + sum_seg sum_{c,d} s_c s_d A_c M_seg A_d^T`` costs O(|sig|^2) per segment instead
    of O(|sig|^2) per node: a batch of GPS readings sharing a long trunk stays cheap.
    """
    # fmt: off
    (m_edges, ptr, pnode, psign, edge_rot, edge_trans, edge_lt, _gps_pos, gps_lt,
     _path_count, parent) = prob
    # fmt: on
    k_rows = r_off[nb]
    # per-constraint A_c (kr x 6) and global poses of the union nodes
    amat = np.zeros((nb, 6, 6))
    yr = np.empty((nu, 3, 3))
    yt = np.empty((nu, 3))
    have = np.zeros(nu, np.bool_)
    gr = np.empty((3, 3))
    gt = np.empty(3)
    tr_ = np.empty((3, 3))
    tt_ = np.empty(3)
    dmax = 1
    for q in range(nb):
        dq = ptr[cs[q] + 1] - ptr[cs[q]]
        if dq > dmax:
            dmax = dq
    pr = np.empty((dmax, 3, 3))
    pt = np.empty((dmax, 3))
    adb = np.empty((6, 6))
    ws = np.empty((12, 3, 3))
    e0 = np.empty(6)
    jri = np.empty((6, 6))
    for q in range(nb):
        c = cs[q]
        s0 = ptr[c]
        d = ptr[c + 1] - s0
        na = _path_products(c, ptr, pnode, psign, rot, trans, pr, pt)
        # the constraint's root: parent of the top node of a non-empty side
        top = pnode[s0 + na - 1] if na > 0 else pnode[s0 + d - 1]
        _global_pose(parent[top], parent, rot, trans, gr, gt)
        for k in range(d):
            u = e_slot[e_off[q] + k]
            if not have[u]:
                _mul_pose_into(gr, gt, pr[k], pt[k], yr[u], yt[u])
                have[u] = True
        if c < m_edges:
            ra, ta, rb, tb = _endpoints(pr, pt, na, d)
            _error_and_jr_inv(edge_rot[c], edge_trans[c], ra, ta, rb, tb, e0, jri, ws)
            a6 = edge_lt[c] @ jri
            # Ad(Y_b)^-1 = Ad(Y_b^-1), Y_b = G_root P_b
            _mul_pose_into(gr, gt, rb, tb, tr_, tt_)
            rinv = tr_.T.copy()
            tinv = -(rinv @ tt_)
            _adjoint_into(rinv, tinv, adb)
            amat[q] = a6 @ adb
        else:
            g = c - m_edges
            # p_n in the root (earth) frame: the earth is the root, G = I
            pn = pt[0]
            lt = gps_lt[g]
            blk = np.zeros((3, 6))
            for i in range(3):
                blk[i, i] = 1.0
            # -[p_n]x
            blk[0, 4] = pn[2]
            blk[0, 5] = -pn[1]
            blk[1, 3] = -pn[2]
            blk[1, 5] = pn[0]
            blk[2, 3] = pn[1]
            blk[2, 4] = -pn[0]
            amat[q, 0:3, :] = lt @ blk
    # segments: process each constraint side top-down; a node starts a new segment when a
    # constraint side tops out at it, its parent is outside the union, or the counts differ
    tops = np.zeros(nu, np.bool_)
    for q in range(nb):
        c = cs[q]
        s0 = ptr[c]
        d = ptr[c + 1] - s0
        na = 0
        while na < d and psign[s0 + na] < 0:
            na += 1
        if na > 0:
            tops[e_slot[e_off[q] + na - 1]] = True
        if na < d:
            tops[e_slot[e_off[q] + d - 1]] = True
    seg = np.full(nu, -1, np.int64)
    seg_rep = np.empty(nu, np.int64)
    nseg = 0
    for q in range(nb):
        c = cs[q]
        s0 = ptr[c]
        d = ptr[c + 1] - s0
        na = 0
        while na < d and psign[s0 + na] < 0:
            na += 1
        for side in range(2):
            lo = 0 if side == 0 else na
            hi = na if side == 0 else d
            for k in range(hi - 1, lo - 1, -1):
                u = e_slot[e_off[q] + k]
                if seg[u] >= 0:
                    continue
                p = parent[nodes_out[u]]
                pu = slot[p] if p >= 0 else -1
                if tops[u] or pu < 0 or (cnt[u + 1] - cnt[u]) != (cnt[pu + 1] - cnt[pu]):
                    seg[u] = nseg
                    seg_rep[nseg] = u
                    nseg += 1
                else:
                    seg[u] = seg[pu]
    # per node: factor B_u, V_u = L^-1 Ad(Y_u)^T, moments M_seg += V^T V
    lf = np.empty((nu, 6, 6))
    vv = np.empty((nu, 6, 6))
    mseg = np.zeros((nseg, 6, 6))
    ad = np.empty((6, 6))
    for u in range(nu):
        sc = 0.0
        for t in range(cnt[u], cnt[u + 1]):
            e = by_slot[t]
            for p in range(6):
                for w in range(krs[e_q[e]]):
                    sc += jb[e, w, p] * jb[e, w, p]
        _regularized_factor(bc[u], sc, mu, lf[u])
        _adjoint_into(yr[u], yt[u], ad)
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
    # S = I + sum_seg sum_{c,d in sig} s_c s_d A_c M A_d^T
    smat = np.zeros((k_rows, k_rows))
    for i in range(k_rows):
        smat[i, i] = 1.0
    tm = np.empty((6, 6))
    for sg in range(nseg):
        u = seg_rep[sg]
        for t1 in range(cnt[u], cnt[u + 1]):
            e = by_slot[t1]
            qe = e_q[e]
            se = float(psign[ptr[cs[qe]] + e - e_off[qe]])
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
                sf = float(psign[ptr[cs[qf]] + f - e_off[qf]])
                for a in range(kre):
                    for b in range(krs[qf]):
                        acc = 0.0
                        for m in range(6):
                            acc += tm[a, m] * amat[qf, b, m]
                        smat[r_off[qe] + a, r_off[qf] + b] += sf * acc
    sym = 0.5 * (smat + smat.T)
    if not _chol_inplace(sym, k_rows):
        return False
    zz = rbuf[:k_rows].reshape((k_rows, 1)).copy()
    _chol_solve_cols(sym, k_rows, zz, 1)
    # v_seg = sum_c s_c A_c^T z_c ; x_u = L^-T (V_u v_seg)
    vseg = np.zeros((nseg, 6))
    for sg in range(nseg):
        u = seg_rep[sg]
        for t1 in range(cnt[u], cnt[u + 1]):
            e = by_slot[t1]
            qe = e_q[e]
            se = float(psign[ptr[cs[qe]] + e - e_off[qe]])
            for j in range(6):
                acc = 0.0
                for a in range(krs[qe]):
                    acc += amat[qe, a, j] * zz[r_off[qe] + a, 0]
                vseg[sg, j] += se * acc
    v = np.empty(6)
    for u in range(nu):
        sg = seg[u]
        for i in range(6):
            acc = 0.0
            for m in range(6):
                acc += vv[u, i, m] * vseg[sg, m]
            v[i] = acc
        lk = lf[u]
        for i in range(5, -1, -1):
            acc = v[i]
            for m in range(i + 1, 6):
                acc -= lk[m, i] * x_out[u, m]
            x_out[u, i] = acc / lk[i, i]
    return True


@kernel
def _batch_relax(
    cs: np.ndarray,
    nb: int,
    tau: float,
    mu: float,
    prob: tuple[Any, ...],
    state: tuple[Any, ...],
    slot: np.ndarray,
    x_out: np.ndarray,
    nodes_out: np.ndarray,
    apply: bool,
) -> int:
    """Relax the constraints ``cs[:nb]`` together (paper eq. 35-37, DESIGN §5).

    ``H_C = sum_{c in C} J_c^T J_c + B_C`` over the union U of their domains, with
    ``B_C = 𝔅(H) - sum_{c in C} 𝔅(J_c^T J_c)``.  Solved in Woodbury form (a K x K system, K the
    stacked rows) when every block of B_C is non-zero, else (B_C vanishes on a node that only
    the batch touches, e.g. when C is every constraint) by the dense normal equations over U,
    which then equal the Gauss-Newton step (eq. 37 reduces to eq. 14).

    ``slot`` (T,) must be -1 on entry and is -1 again on exit.  The step of union node
    ``nodes_out[u]`` is written to ``x_out[u]``.  Returns the number of union nodes, or -1 when
    the step was non-finite (nothing applied).
    """
    # fmt: off
    (_m_edges, ptr, pnode, _psign, _edge_rot, _edge_trans, _edge_lt, _gps_pos, _gps_lt,
     path_count, _parent) = prob
    # fmt: on
    rot, trans, bdiag, contrib = state
    # 1. linearize every constraint of the batch
    ne = 0
    for q in range(nb):
        ne += ptr[cs[q] + 1] - ptr[cs[q]]
    dmax = 1
    for q in range(nb):
        dq = ptr[cs[q] + 1] - ptr[cs[q]]
        if dq > dmax:
            dmax = dq
    pr = np.empty((dmax, 3, 3))
    pt = np.empty((dmax, 3))
    jb = np.empty((ne, 6, 6))
    e_off = np.empty(nb + 1, np.int64)
    r_off = np.empty(nb + 1, np.int64)
    krs = np.empty(nb, np.int64)
    rbuf = np.empty(6 * nb)
    rq = np.empty(6)
    e_off[0] = 0
    r_off[0] = 0
    for q in range(nb):
        c = cs[q]
        d = ptr[c + 1] - ptr[c]
        kr = _linearize(c, prob, rot, trans, pr, pt, jb[e_off[q] : e_off[q] + d], rq)
        krs[q] = kr
        for i in range(kr):
            rbuf[r_off[q] + i] = rq[i]
        e_off[q + 1] = e_off[q] + d
        r_off[q + 1] = r_off[q] + kr
    # 2. the union of the domains: slot of each node, entries (path positions) per slot
    e_slot = np.empty(ne, np.int64)
    e_q = np.empty(ne, np.int64)
    nu = 0
    for q in range(nb):
        c = cs[q]
        for k in range(ptr[c + 1] - ptr[c]):
            i = pnode[ptr[c] + k]
            if slot[i] < 0:
                slot[i] = nu
                nodes_out[nu] = i
                nu += 1
            e_slot[e_off[q] + k] = slot[i]
            e_q[e_off[q] + k] = q
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
    # 3. eq. 36 and eq. 24: B_C per union node, and 𝔅(H) updated with the new contributions
    bc = np.zeros((nu, 6, 6))
    zero_block = False
    for u in range(nu):
        i = nodes_out[u]
        for p in range(6):
            for q2 in range(6):
                bc[u, p, q2] = bdiag[i, p, q2]
        for t in range(cnt[u], cnt[u + 1]):
            e = by_slot[t]
            q = e_q[e]
            k = e - e_off[q]
            pe = ptr[cs[q]] + k
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
        if cnt[u + 1] - cnt[u] == path_count[i]:  # every constraint on node i is in C
            for p in range(6):
                for q2 in range(6):
                    bc[u, p, q2] = 0.0
            zero_block = True
    if not apply:
        for u in range(nu):
            slot[nodes_out[u]] = -1
        return nu
    # 4. solve
    if zero_block and 6 * nu <= 4096:
        n6 = 6 * nu
        amat = np.zeros((n6, n6))
        g = np.zeros(n6)
        for u in range(nu):
            for p in range(6):
                for q2 in range(6):
                    amat[6 * u + p, 6 * u + q2] = bc[u, p, q2]
        for q in range(nb):
            kr = krs[q]
            for e in range(e_off[q], e_off[q + 1]):
                ue = e_slot[e]
                for p in range(6):
                    acc = 0.0
                    for w in range(kr):
                        acc += jb[e, w, p] * rbuf[r_off[q] + w]
                    g[6 * ue + p] += acc
                for f in range(e_off[q], e_off[q + 1]):
                    uf = e_slot[f]
                    for p in range(6):
                        for q2 in range(6):
                            acc = 0.0
                            for w in range(kr):
                                acc += jb[e, w, p] * jb[f, w, q2]
                            amat[6 * ue + p, 6 * uf + q2] += acc
        sym = 0.5 * (amat + amat.T)
        ok = _chol_inplace(sym, n6)
        if not ok:
            for u in range(nu):
                slot[nodes_out[u]] = -1
            return -1
        gg = g.reshape((n6, 1)).copy()
        _chol_solve_cols(sym, n6, gg, 1)
        for u in range(nu):
            for p in range(6):
                x_out[u, p] = gg[6 * u + p, 0]
    else:
        ok = _woodbury_segments(
            cs,
            nb,
            prob,
            rot,
            trans,
            mu,
            jb,
            e_off,
            r_off,
            krs,
            rbuf,
            e_slot,
            e_q,
            cnt,
            by_slot,
            bc,
            slot,
            nodes_out,
            nu,
            x_out,
        )
        if not ok:
            for u in range(nu):
                slot[nodes_out[u]] = -1
            return -1
    for u in range(nu):
        slot[nodes_out[u]] = -1
    # 5. temperature and the pi/8 cap, then apply
    biggest = 0.0
    for u in range(nu):
        for p in range(6):
            if not math.isfinite(x_out[u, p]):
                return -1
        ang = math.sqrt(x_out[u, 3] ** 2 + x_out[u, 4] ** 2 + x_out[u, 5] ** 2)
        if ang > biggest:
            biggest = ang
    t_step = tau
    if t_step * biggest > MAX_ROTATION:
        t_step = MAX_ROTATION / biggest
    er = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for u in range(nu):
        _apply_step(rot[nodes_out[u]], trans[nodes_out[u]], x_out[u], t_step, er, tmp)
    return nu


@kernel
def sweep(
    order: np.ndarray,
    tau: float,
    mu: float,
    step_kind: int,
    gps_batch: int,
    prob: tuple[Any, ...],
    state: tuple[Any, ...],
    dmax: int,
    cycles: np.ndarray,
    batch_cycles: np.ndarray,
    counts: np.ndarray,
) -> int:
    """One pass over the constraints in ``order`` (paper Algorithm 1).

    GPS constraints (index >= m_edges) are buffered and relaxed together in batches of
    ``gps_batch`` (flushed when full and before every relative constraint).
    ``cycles[c]`` receives the cycle count of constraint c's update (a batch's count is shared
    among its members, and ``batch_cycles[first member]`` gets the whole batch's count);
    ``counts`` accumulates [capped steps, rejected steps, max cycles of one
    update, batches].  Returns the first rejected constraint or -1.
    """
    # fmt: off
    (m_edges, _ptr, _pnode, _psign, _edge_rot, _edge_trans, _edge_lt, _gps_pos, _gps_lt,
     _path_count, _parent) = prob
    # fmt: on
    rot, _trans, _bdiag, _contrib = state
    pr, pt, jac, lfac, y, x, r = _workspace(dmax)
    nt = rot.shape[0]
    slot = np.full(nt, -1, np.int64)
    xb = np.empty((nt, 6))
    nodes = np.empty(nt, np.int64)
    buf = np.empty(max(gps_batch, 1), np.int64)
    nbuf = 0
    first_bad = -1
    n_order = order.shape[0]
    for idx in range(n_order + 1):
        c = order[idx] if idx < n_order else -1
        is_gps = c >= m_edges
        if nbuf > 0 and (not is_gps or nbuf >= gps_batch):
            t0 = cycle_counter()
            nu = _batch_relax(buf, nbuf, tau, mu, prob, state, slot, xb, nodes, True)
            dc = cycle_counter() - t0
            if dc > counts[2]:
                counts[2] = dc
            counts[3] += 1
            for q in range(nbuf):
                cycles[buf[q]] = dc // nbuf
            batch_cycles[buf[0]] = dc
            if nu < 0:
                counts[1] += nbuf
                if first_bad < 0:
                    first_bad = buf[0]
            nbuf = 0
        if c < 0:
            break
        if is_gps:
            buf[nbuf] = c
            nbuf += 1
            continue
        t0 = cycle_counter()
        st = _relax(c, tau, mu, step_kind, prob, state, pr, pt, jac, lfac, y, x, r, True)
        dc = cycle_counter() - t0
        cycles[c] = dc
        if dc > counts[2]:
            counts[2] = dc
        if st == 1:
            counts[0] += 1
        elif st == 2:
            counts[1] += 1
            if first_bad < 0:
                first_bad = c
    return first_bad


@kernel
def batch_step(
    cs: np.ndarray,
    mu: float,
    prob: tuple[Any, ...],
    state: tuple[Any, ...],
    tau: float,
    x_out: np.ndarray,
    nodes_out: np.ndarray,
) -> int:
    """Relax the batch ``cs`` once with temperature ``tau`` (0: compute the step only)."""
    # fmt: off
    (_m_edges, _ptr, _pnode, _psign, _edge_rot, _edge_trans, _edge_lt, _gps_pos, _gps_lt,
     _path_count, _parent) = prob
    # fmt: on
    rot, trans, bdiag, contrib = state
    slot = np.full(rot.shape[0], -1, np.int64)
    work_rot = rot if tau > 0.0 else rot.copy()
    work_trans = trans if tau > 0.0 else trans.copy()
    return _batch_relax(
        cs,
        cs.shape[0],
        max(tau, 1e-300),
        mu,
        prob,
        (work_rot, work_trans, bdiag, contrib),
        slot,
        x_out,
        nodes_out,
        True,
    )


@kernel
def constraint_step(
    c: int,
    mu: float,
    step_kind: int,
    prob: tuple[Any, ...],
    state: tuple[Any, ...],
    jac_out: np.ndarray,
    r_out: np.ndarray,
    x_out: np.ndarray,
) -> int:
    """Testing hook: linearize c, update blocks as a sweep would, return its step (not applied).

    Writes J blocks (d,6,6), r (6,) and x (d,6); returns kr.
    """
    # fmt: off
    (_m_edges, ptr, pnode, _psign, _edge_rot, _edge_trans, _edge_lt, _gps_pos, _gps_lt,
     _path_count, _parent) = prob
    # fmt: on
    rot, trans, bdiag, contrib = state
    d = ptr[c + 1] - ptr[c]
    pr = np.empty((d, 3, 3))
    pt = np.empty((d, 3))
    lfac = np.empty((d, 6, 6))
    y = np.empty((d, 6, 6))
    kr = _linearize(c, prob, rot, trans, pr, pt, jac_out, r_out)
    _accumulate_blocks(c, d, kr, ptr, pnode, jac_out, bdiag, contrib, mu, lfac)
    if step_kind == STEP_GIVENS:
        _givens_solve(d, kr, jac_out, lfac, r_out, x_out)
    else:
        _woodbury_solve(d, kr, jac_out, lfac, r_out, y, x_out)
    return kr
