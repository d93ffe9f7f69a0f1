"""Chordal initialization (Martinec & Pajdla 2007; Carlone et al., ICRA 2015).

A better start than dead reckoning for graphs with large rotation noise (DESIGN.md §9 names it as
the lever for reaching the global optimum).  Two linear least-squares problems:

1. rotations: minimize sum_c kappa_c ||R_b - R_a Z_c||_F^2 over free 3x3 matrices with the
   gauge pose's rotation fixed, then project every matrix onto SO(3) (SVD);
2. translations: with those rotations fixed, minimize
   sum_c ||t_b - t_a - R_a t_c||^2_{W_c} (+ GPS terms) over the positions.

Both are sparse and solved with one factorization each (:func:`._linear.solve_spd`: a
fill-reducing ordering of the pose graph, then CHOLMOD; the three rows of the rotations share
one factorization).  ``kappa_c`` is the mean of the
rotation block's diagonal of the information; ``W_c`` is ``R_a Omega_tt R_a^T``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .errors import GraphError, SolverError
from .graph import FloatArray, PoseGraph


def _project_to_so3(m: FloatArray) -> FloatArray:
    u, _, vt = np.linalg.svd(m)
    det = np.linalg.det(u @ vt)
    u[:, :, 2] *= det[:, None]
    out: FloatArray = u @ vt
    return out


def _solve_spd(a: sp.spmatrix, b: FloatArray) -> FloatArray:
    """``a^-1 b`` for the SPD normal matrix of 3-vectors per pose; RuntimeError when singular."""
    from .solvers._linear import solve_spd

    try:
        return solve_spd(a, b, block=3)
    except SolverError as exc:
        raise RuntimeError(str(exc)) from exc


def chordal_initialization(
    graph: PoseGraph, gauge: int | None = None
) -> tuple[FloatArray, FloatArray]:
    """Global poses ``(R (N,3,3), t (N,3))`` from the chordal relaxation.

    Parameters
    ----------
    graph : PoseGraph
    gauge : int, optional
        Dense index of the pose whose rotation (and, without GPS, translation) is held at its
        file value (identity when the file has none).  Default: the first FIX node or pose 0.
    """
    n, m = graph.num_nodes, graph.num_edges
    if gauge is None:
        gauge = int(graph.fixed_nodes[0]) if graph.fixed_nodes.size else 0
    r_gauge = graph.rotations[gauge] if graph.has_estimates else np.eye(3)
    t_gauge = graph.translations[gauge] if graph.has_estimates else np.zeros(3)
    a = graph.edge_nodes[:, 0].astype(np.int64)
    b = graph.edge_nodes[:, 1].astype(np.int64)
    zr = graph.edge_rotations
    kappa = np.mean(np.diagonal(graph.edge_information[:, 3:, 3:], axis1=1, axis2=2), axis=1)

    # --- rotations: row k of R_b = (row k of R_a) Z, i.e. r_b - Z^T r_a = 0 for each row k.
    # Unknowns: x[3i:3i+3] = row k of R_i (the same matrix for the three rows k).
    rows = np.arange(3 * m).reshape(m, 3)
    ii, jj, vv = [], [], []
    w = np.sqrt(kappa)
    for comp in range(3):
        ii.append(rows[:, comp])
        jj.append(3 * b + comp)
        vv.append(w)
    zt = np.swapaxes(zr, 1, 2)  # Z^T
    for p in range(3):
        for q in range(3):
            ii.append(rows[:, p])
            jj.append(3 * a + q)
            vv.append(-w * zt[:, p, q])
    amat = sp.csr_matrix(
        (np.concatenate(vv), (np.concatenate(ii), np.concatenate(jj))), shape=(3 * m, 3 * n)
    )
    free = np.ones(3 * n, bool)
    free[3 * gauge : 3 * gauge + 3] = False
    a_free = amat[:, free]
    a_fix = amat[:, ~free]
    normal = (a_free.T @ a_free).tocsc()
    rot = np.empty((n, 3, 3))
    try:  # the three rows k of the rotations: one matrix, three right-hand sides
        rhs = -(a_fix @ r_gauge.T)  # column k: -(a_fix @ r_gauge[k])
        x = _solve_spd(normal, np.asarray(a_free.T @ rhs))
        for k in range(3):
            full = np.empty(3 * n)
            full[free] = x[:, k]
            full[~free] = r_gauge[k]
            rot[:, k, :] = full.reshape(n, 3)
    except RuntimeError as exc:  # singular: a part of the graph has no path to the gauge
        raise GraphError(
            "chordal initialization failed: the rotation system is singular "
            "(is the graph connected?)"
        ) from exc
    rot = _project_to_so3(rot)

    # --- translations: t_b - t_a = R_a t_c, weighted by R_a Omega_tt R_a^T
    info_t = graph.edge_information[:, :3, :3]
    lw = np.linalg.cholesky(info_t)  # Omega = L L^T; whitened residual L^T R_a^T (...)
    wmat = np.einsum("kji,kjl->kil", lw, np.swapaxes(rot[a], 1, 2))  # L^T R_a^T
    rhs_e = np.einsum("kij,kj->ki", wmat, np.einsum("kij,kj->ki", rot[a], graph.edge_translations))
    ii, jj, vv = [], [], []
    rows = np.arange(3 * m).reshape(m, 3)
    for p in range(3):
        for q in range(3):
            ii += [rows[:, p], rows[:, p]]
            jj += [3 * b + q, 3 * a + q]
            vv += [wmat[:, p, q], -wmat[:, p, q]]
    blocks_rhs = [rhs_e.reshape(-1)]
    n_rows = 3 * m
    if graph.num_gps:
        g = graph.num_gps
        lg = np.linalg.cholesky(graph.gps_information)
        wg = np.swapaxes(lg, 1, 2)
        grow = n_rows + np.arange(3 * g).reshape(g, 3)
        for p in range(3):
            for q in range(3):
                ii.append(grow[:, p])
                jj.append(3 * graph.gps_nodes.astype(np.int64) + q)
                vv.append(wg[:, p, q])
        blocks_rhs.append(np.einsum("kij,kj->ki", wg, graph.gps_positions).reshape(-1))
        n_rows += 3 * g
    tmat = sp.csr_matrix(
        (np.concatenate(vv), (np.concatenate(ii), np.concatenate(jj))), shape=(n_rows, 3 * n)
    )
    rhs = np.concatenate(blocks_rhs)
    free = np.ones(3 * n, bool)
    if not graph.num_gps:
        free[3 * gauge : 3 * gauge + 3] = False
        rhs = rhs - tmat[:, ~free] @ t_gauge
    t_free = tmat[:, free]
    try:
        x = _solve_spd((t_free.T @ t_free).tocsc(), t_free.T @ rhs)
    except RuntimeError as exc:
        raise GraphError(
            "chordal initialization failed: the translation system is singular "
            "(a part of the graph without a gauge?)"
        ) from exc
    trans = np.empty(3 * n)
    trans[free] = x
    if not graph.num_gps:
        trans[~free] = t_gauge
    return rot, trans.reshape(n, 3)
