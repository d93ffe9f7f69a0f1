"""Numba kernels of the exact solver (docs/mathematics.md#exact-solver).

Global parametrization, right perturbation ``X_i <- X_i Exp(delta_i)``, tangent order (rho, phi):

* relative constraint: ``e = Log(Z^-1 X_a^-1 X_b)``, ``de/d delta_b = Jr^-1(e)``,
  ``de/d delta_a = -Jr^-1(e) Ad(X_b^-1 X_a)``;
* position constraint: ``e = p_n - g``, ``de/d delta_n = [R_n | 0]``.

The normal equations ``H = J^T Omega J``, ``g = J^T Omega e`` (with a robust kernel
``H = sum_c w_c J_c^T Omega_c J_c``, ``g = sum_c w_c J_c^T Omega_c e_c`` over the relative and
the GPS constraints, docs/conventions.md#robust-kernels) are
written straight into the value array of the *lower triangle* of H in CSC form, whose pattern
was computed once (the "analyze" step in :mod:`hybridpgo.solvers.gauss_newton`): the layout
CHOLMOD factors, so no copy or transpose of H is ever made.  Scalar column ``6 j + q`` of block
column ``j`` holds the diagonal block's rows ``q..5`` first, then the 6 rows of each lower
off-diagonal block (block rows ``> j``, increasing).  So, with ``indptr`` the scalar column
pointers, entry ``(p, q)``, ``p >= q``, of diagonal block ``j`` lives at
``data[indptr[6 j + q] + p - q]`` and entry ``(p, q)`` of the ``k``-th lower block of block
column ``j`` at ``data[indptr[6 j + q] + 6 - q + 6 k + p]``.  A relative constraint between
variables ``va, vb`` touches the diagonal blocks of both and one lower block, in block column
``min(va, vb)`` at position ``edge_off[c]`` (computed once).  The planar system (the x, y,
yaw rows and columns) has the same layout with 3 in place of 6, and the same assembly writes
it directly (its ``dofs`` argument).

The error, its Jacobians (``Jr^-1``), χ², energy and retraction come from the cost layer
(:mod:`hybridpgo._cost`), shared with the hybrid solver and :mod:`hybridpgo.energy`; they are
allocation-free (docs/contributing.md#kernels).  The drivers allocate their few (6, 6) buffers
once per call.
``tests/test_gauss_newton.py`` checks them against ``tests/ref_kernels.py`` to float64 rounding.
"""

from __future__ import annotations

import math

import numpy as np

from .._cost import (
    ROBUST_NONE,
    chi2,
    edge_linearization9,
    gps_chi2,
    planar_jacobians,
    planar_residual,
    retract_into,
    robust_cost,
)
from .._numba import kernel


# --------------------------------------------------------------------------- inner kernels
@kernel
def _rows(d: int) -> int:
    """Rows of a Jacobian's column d that can be non-zero: both the SE(3) Jacobians
    (:func:`hybridpgo._cost.edge_linearization9`) and the planar ones
    (:func:`hybridpgo._cost.planar_jacobians`) are 0 in rows 3-5 of columns 0-2 (their
    lower-left block), so the products here sum column d over rows ``< _rows(d)`` only.  The
    terms left out are exact zeros times finite numbers, so each sum is the full sum to the
    bit (adding +-0 to a sum that started at +0 never changes it; where a product overflows,
    H is not finite either way)."""
    return 3 if d < 3 else 6


@kernel
def _matmul_cols(a: np.ndarray, b: np.ndarray, dofs: tuple[int, ...], out: np.ndarray) -> None:
    """``out[:, q] = a @ b[:, dofs[q]]`` for (6, 6) a and a Jacobian b: the columns of
    ``a @ b`` kept."""
    for i in range(6):
        for q in range(len(dofs)):
            dq = dofs[q]
            s = 0.0
            for k in range(_rows(dq)):
                s += a[i, k] * b[k, dq]
            out[i, q] = s


@kernel
def _add_diag_atb(a: np.ndarray, b: np.ndarray, dofs: tuple[int, ...], data: np.ndarray,
                  indptr: np.ndarray, v: int) -> None:
    """Lower triangle of diagonal block v += lower triangle of ``a[:, dofs]^T @ b`` (a (6, 6)
    Jacobian, (6, nd) b: its columns already the kept ones)."""
    nd = len(dofs)
    for q in range(nd):
        col = indptr[nd * v + q] - q
        for p in range(q, nd):
            dp = dofs[p]
            s = 0.0
            for k in range(_rows(dp)):
                s += a[k, dp] * b[k, q]
            data[col + p] += s


@kernel
def _add_lower_atb(a: np.ndarray, b: np.ndarray, dofs: tuple[int, ...], data: np.ndarray,
                   indptr: np.ndarray, v: int, k: int) -> None:
    """The k-th lower block of block column v += ``a[:, dofs]^T @ b`` (a (6, 6) Jacobian,
    (6, nd) b)."""
    nd = len(dofs)
    for q in range(nd):
        col = indptr[nd * v + q] + nd - q + nd * k
        for p in range(nd):
            dp = dofs[p]
            s = 0.0
            for i in range(_rows(dp)):
                s += a[i, dp] * b[i, q]
            data[col + p] += s


@kernel
def _edge_linearization(rot: np.ndarray, trans: np.ndarray, edge_rot: np.ndarray,
                        edge_trans: np.ndarray, a: int, b: int, c: int, e: np.ndarray,
                        ja: np.ndarray, jb: np.ndarray) -> None:
    """:func:`edge_linearization9` into the arrays e (6,), ja and jb (6, 6)."""
    ev, jm, km, jr, jt = edge_linearization9(rot, trans, edge_rot, edge_trans, a, b, c)
    for i in range(6):
        e[i] = ev[i]
    for i in range(3):
        for j in range(3):
            n = 3 * i + j
            ja[i, j] = -jr[n]
            ja[i, j + 3] = -jt[n]
            ja[i + 3, j] = 0.0
            ja[i + 3, j + 3] = -jr[n]
            jb[i, j] = jm[n]
            jb[i, j + 3] = km[n]
            jb[i + 3, j] = 0.0
            jb[i + 3, j + 3] = jm[n]


@kernel
def _add_gradient(j: np.ndarray, oe: np.ndarray, dofs: tuple[int, ...], grad: np.ndarray,
                  v: int) -> None:
    """grad[6v + dofs] += J[:, dofs]^T (Omega e) for one (6, 6) Jacobian block."""
    for p in range(len(dofs)):
        dp = dofs[p]
        s = 0.0
        for k in range(_rows(dp)):
            s += j[k, dp] * oe[k]
        grad[6 * v + dp] += s


# --------------------------------------------------------------------------- drivers
@kernel
def edge_jacobians(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                   edge_rot: np.ndarray, edge_trans: np.ndarray, out_err: np.ndarray,
                   out_ja: np.ndarray, out_jb: np.ndarray) -> None:
    """Errors (M, 6) and Jacobians (M, 6, 6) w.r.t. delta_a and delta_b of every relative edge."""
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        _edge_linearization(rot, trans, edge_rot, edge_trans, a, b, c, out_err[c], out_ja[c],
                            out_jb[c])


@kernel
def assemble_normal_equations(
    rot: np.ndarray, trans: np.ndarray,
    edge_nodes: np.ndarray, edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
    edge_off: np.ndarray,
    gps_nodes: np.ndarray, gps_pos: np.ndarray, gps_info: np.ndarray,
    var_of_node: np.ndarray, indptr: np.ndarray, data: np.ndarray, grad: np.ndarray,
    robust_kind: int, robust_delta: float, dofs: tuple[int, ...],
) -> tuple[int, float, float]:
    """Fill ``data`` (lower-triangle CSC values of H, module docstring) and ``grad``
    (g = J^T Omega e) in one pass; return the energy.

    ``dofs``: the tangent entries of each pose kept in the system, increasing (all six, or
    the planar system's x, y, yaw), as a tuple (its length is then a constant of each
    compiled variant): ``data`` then holds the rows and columns of those only,
    in the layout of the module docstring with ``len(dofs)`` in place of 6 (``indptr`` the
    system's), and ``grad`` (6 N) only their entries (the others are 0).  The planar system
    (poses and data planar) linearizes each constraint with SE(2)'s formulas
    (:func:`hybridpgo._cost.planar_jacobians`): the whole system's x, y, yaw rows and
    columns, to rounding, at a fraction of SE(3)'s cost.

    With a robust kernel (``robust_kind``, ``robust_delta``: :func:`hybridpgo._cost.robust_cost`)
    every constraint's terms (relative and GPS) are multiplied by its weight ``w = rho'(s)``.

    ``edge_off`` (M,): position of the constraint's lower off-diagonal block in block column
    ``min(va, vb)`` (-1 when a node is fixed).  ``var_of_node`` (N,): variable index of each
    node, -1 when fixed.  ``indptr``: the scalar column pointers of the lower triangle.

    Returns ``(status, robust energy, plain energy)``: status -1 when every quantity is
    finite, else the index of the first offending constraint (relative edges 0..M-1, then
    M + GPS index).
    """
    data[:] = 0.0
    grad[:] = 0.0
    m = edge_nodes.shape[0]
    e = np.empty(6)
    oe = np.empty(6)
    ja = np.empty((6, 6))
    jb = np.empty((6, 6))
    nd = len(dofs)
    wa = np.empty((6, nd))
    wb = np.empty((6, nd))
    energy = 0.0
    plain = 0.0
    for c in range(m):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        if nd == 3:  # the planar system: SE(2)'s error and Jacobians (planar_jacobians)
            rel = planar_residual(edge_rot[c], edge_trans[c], rot[a], trans[a], rot[b],
                                  trans[b], e)
            planar_jacobians(e, rel, ja, jb)
        else:
            _edge_linearization(rot, trans, edge_rot, edge_trans, a, b, c, e, ja, jb)
        om = edge_info[c]
        ec = chi2(om, e, 6, oe)
        ok = math.isfinite(ec)
        for i in range(6):
            for j in range(6):
                if not (math.isfinite(ja[i, j]) and math.isfinite(jb[i, j])):
                    ok = False
        if not ok:
            return c, energy, plain
        plain += ec
        _matmul_cols(om, ja, dofs, wa)
        _matmul_cols(om, jb, dofs, wb)
        if robust_kind != ROBUST_NONE:  # IRLS: H += w J^T Omega J, g += w J^T Omega e
            rho, wc = robust_cost(robust_kind, robust_delta, ec)
            ec = rho
            for i in range(6):
                oe[i] *= wc
                for j in range(nd):
                    wa[i, j] *= wc
                    wb[i, j] *= wc
        energy += ec
        va = var_of_node[a]
        vb = var_of_node[b]
        if va >= 0:
            _add_diag_atb(ja, wa, dofs, data, indptr, va)
            _add_gradient(ja, oe, dofs, grad, va)
        if vb >= 0:
            _add_diag_atb(jb, wb, dofs, data, indptr, vb)
            _add_gradient(jb, oe, dofs, grad, vb)
        if va >= 0 and vb >= 0:
            if va > vb:  # block (row a, col b) = Ja^T W Jb is the lower one
                _add_lower_atb(ja, wb, dofs, data, indptr, vb, edge_off[c])
            elif vb > va:  # block (row b, col a) = Jb^T W Ja
                _add_lower_atb(jb, wa, dofs, data, indptr, va, edge_off[c])
            else:  # one variable for both ends: both cross terms land on the diagonal
                _add_diag_atb(ja, wb, dofs, data, indptr, va)
                _add_diag_atb(jb, wa, dofs, data, indptr, va)
    for c in range(gps_nodes.shape[0]):
        n = gps_nodes[c]
        om = gps_info[c]
        r = rot[n]
        ec = gps_chi2(trans[n], gps_pos[c], om, e, oe)
        if not math.isfinite(ec):
            return m + c, energy, plain
        plain += ec
        wc = 1.0
        if robust_kind != ROBUST_NONE:  # IRLS, as for a relative constraint
            ec, wc = robust_cost(robust_kind, robust_delta, ec)
        energy += ec
        vn = var_of_node[n]
        if vn < 0:
            continue
        # J = [R | 0]: H_nn = w [[R^T Omega R, 0], [0, 0]], g_n = w (R^T Omega e, 0).
        for q in range(nd):
            dq = dofs[q]
            if dq >= 3:
                continue
            col = indptr[nd * vn + q] - q
            for p in range(q, nd):
                dp = dofs[p]
                if dp >= 3:
                    continue
                s = 0.0
                for k in range(3):
                    for l in range(3):
                        s += r[k, dp] * om[k, l] * r[l, dq]
                data[col + p] += wc * s
        for p in range(nd):
            dp = dofs[p]
            if dp < 3:
                grad[6 * vn + dp] += wc * (r[0, dp] * oe[0] + r[1, dp] * oe[1]
                                           + r[2, dp] * oe[2])
    return -1, energy, plain


@kernel
def lower_pattern_indices(block_ptr: np.ndarray, block_row: np.ndarray, indptr: np.ndarray,
                          indices: np.ndarray) -> None:
    """Row indices of the scalar lower-triangle pattern (module docstring) from the block one.

    ``block_ptr`` (nv+1,), ``block_row``: the lower off-diagonal blocks of each block column
    (rows increasing); ``indptr`` (nd nv + 1,): the scalar column pointers of (nd, nd) blocks
    (6, or 3 for the planar system); fills ``indices``.
    """
    nv = block_ptr.shape[0] - 1
    nd = (indptr.shape[0] - 1) // max(nv, 1)
    for j in range(nv):
        for q in range(nd):
            pos = indptr[nd * j + q]
            for p in range(q, nd):
                indices[pos] = nd * j + p
                pos += 1
            for k in range(block_ptr[j], block_ptr[j + 1]):
                r = nd * block_row[k]
                for p in range(nd):
                    indices[pos] = r + p
                    pos += 1


@kernel
def retract(rot: np.ndarray, trans: np.ndarray, step: np.ndarray, var_of_node: np.ndarray,
            scale: float, out_rot: np.ndarray, out_trans: np.ndarray) -> None:
    """``X_i <- X_i Exp(scale * delta_i)`` for free nodes (the cost layer's retraction); copy
    fixed ones.  ``step`` is the solution vector (6 * num_vars,) indexed by ``var_of_node``.
    """
    er = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for i in range(rot.shape[0]):
        v = var_of_node[i]
        if v < 0:
            out_rot[i] = rot[i]
            out_trans[i] = trans[i]
            continue
        retract_into(rot[i], trans[i], step[6 * v: 6 * v + 6], scale, out_rot[i], out_trans[i],
                     er, tmp)
