"""Chordal initialization (Martinec & Pajdla 2007; Carlone et al., ICRA 2015).

A better start than dead reckoning for graphs with large rotation noise
(docs/mathematics.md#lm-damping names it as
the lever for reaching the global optimum).  Two linear least-squares problems:

1. rotations: minimize sum_c kappa_c ||R_b - R_a Z_c||_F^2 over free 3x3 matrices with the
   gauge pose's rotation fixed, then project every matrix onto SO(3) (SVD);
2. translations: with those rotations fixed, minimize
   sum_c ||t_b - t_a - R_a t_c||^2_{W_c} (+ GPS terms) over the positions.

Both are sparse and solved with one factorization each (:func:`hybridpgo.linalg.solve_spd`: a
fill-reducing ordering of the pose graph, then CHOLMOD; the three rows of the rotations share
one factorization).  ``kappa_c`` is the mean of the
rotation block's diagonal of the information; ``W_c`` is ``R_a Omega_tt R_a^T``.
"""

from __future__ import annotations

import enum
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .errors import GraphError, SolverError
from .graph import FloatArray, PoseGraph
from .tree import LINK_EDGE, LINK_GPS, PoseTree, locals_from_globals

ComplexArray = npt.NDArray[np.complex128]


def _project_to_so3(m: FloatArray) -> FloatArray:
    u, _, vt = np.linalg.svd(m)
    det = np.linalg.det(u @ vt)
    u[:, :, 2] *= det[:, None]
    out: FloatArray = u @ vt
    return out


def _project_to_so2(m: FloatArray) -> FloatArray:
    """The nearest planar rotations (N, 3, 3) of (N, 2, 2) matrices: the angle maximizing
    ``tr(R^T M)``, ``atan2(m10 - m01, m00 + m11)`` (the identity where M has no rotation
    part)."""
    c = m[:, 0, 0] + m[:, 1, 1]
    s = m[:, 1, 0] - m[:, 0, 1]
    h = np.hypot(c, s)
    none = ~(h > 0.0)
    c = np.where(none, 1.0, c / np.where(none, 1.0, h))
    s = np.where(none, 0.0, s / np.where(none, 1.0, h))
    out = np.zeros((m.shape[0], 3, 3))
    out[:, 0, 0] = out[:, 1, 1] = c
    out[:, 1, 0] = s
    out[:, 0, 1] = -s
    out[:, 2, 2] = 1.0
    return out


def _solve_blocks(n: int, diag: FloatArray, ea: npt.NDArray[np.int64],
                  eb: npt.NDArray[np.int64], off: FloatArray, rhs: FloatArray,
                  fixed: int | None, x_fixed: FloatArray | None,
                  analysis: dict[str, Any] | None = None) -> FloatArray:
    """Solve the SPD normal equations of s-vectors per pose, given by blocks.

    ``diag`` (n, s, s): diagonal blocks; ``off`` (m, s, s): the block (row ea, column eb) of
    each edge (the (eb, ea) one is its transpose; parallel edges add up); ``rhs`` (n, s, k).
    With ``fixed``, that pose is held at ``x_fixed`` (s, k): its blocks move to the right-hand
    side.  Only the lower triangle is built, straight in a fill-reducing (AMD, pose graph)
    order, and factored once for the k right-hand sides (CHOLMOD, else SuperLU).

    ``analysis`` (a dict, filled by the first call): a later call on the same edges, block size
    and ``fixed`` reuses its order and symbolic factorization (the chordal start's two
    systems), once its pattern is checked to be the same.
    """
    from .linalg import CscPattern, fill_reducing_order, make_factorizer

    k = rhs.shape[2]
    bs = diag.shape[1]
    rhs = rhs.copy()
    keep = np.ones(n, bool)
    if fixed is not None:
        assert x_fixed is not None
        keep[fixed] = False
        at_a = (ea == fixed) & (eb != fixed)
        at_b = (eb == fixed) & (ea != fixed)
        # row eb of H holds off^T at column ea (= fixed): rhs_eb -= off^T x_fixed, and so on
        np.add.at(rhs, eb[at_a], -np.einsum("eqp,qk->epk", off[at_a], x_fixed))
        np.add.at(rhs, ea[at_b], -np.einsum("epq,qk->epk", off[at_b], x_fixed))
    var = np.full(n, -1, np.int64)
    nf = int(keep.sum())
    var[keep] = np.arange(nf)
    va, vb = var[ea], var[eb]
    both = (va >= 0) & (vb >= 0) & (va != vb)
    va, vb, off = va[both], vb[both], off[both]
    lo, hi = np.minimum(va, vb), np.maximum(va, vb)
    same = analysis is not None and analysis.get("key") == (n, bs, fixed, ea.size)
    if same:
        assert analysis is not None
        new = analysis["new"]
    else:
        pairs = np.unique(lo * max(nf, 1) + hi)
        new = fill_reducing_order(nf, pairs % max(nf, 1), pairs // max(nf, 1))
        del pairs
    del lo, hi
    pa, pb = new[va], new[vb]
    qs = np.arange(bs)
    # off-diagonal: block (pa, pb) = off; keep the one below the diagonal of the new order
    swap = pa < pb
    blk = np.where(swap[:, None, None], np.swapaxes(off, 1, 2), off)
    row_b = np.maximum(pa, pb)
    col_b = np.minimum(pa, pb)
    rows = [(bs * row_b[:, None, None] + qs[None, :, None]).repeat(bs, 2).ravel()]
    cols = [(bs * col_b[:, None, None] + qs[None, None, :]).repeat(bs, 1).ravel()]
    vals = [blk.ravel()]
    pi = new[var[keep]]
    il, jl = np.tril_indices(bs)
    rows.append((bs * pi[:, None] + il[None, :]).ravel())
    cols.append((bs * pi[:, None] + jl[None, :]).ravel())
    vals.append(diag[keep][:, il, jl].ravel())
    dim = bs * nf
    low = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(dim, dim))
    del rows, cols, vals, blk
    low.sum_duplicates()
    low.sort_indices()
    b = np.empty((dim, k))
    b.reshape(nf, bs, k)[new[var[keep]]] = rhs[keep]
    pattern = CscPattern(low)
    if same and analysis is not None and np.array_equal(analysis["indptr"], pattern.indptr) \
            and np.array_equal(analysis["indices"], pattern.indices):
        factorizer = analysis["factorizer"]
    else:
        factorizer = make_factorizer(pattern, "auto")
        if analysis is not None:
            analysis.update(key=(n, bs, fixed, ea.size), new=new, indptr=pattern.indptr,
                            indices=pattern.indices, factorizer=factorizer)
    try:
        x = factorizer.solve(np.asarray(low.data, np.float64), b, check=True)
    except SolverError as exc:
        raise RuntimeError(str(exc)) from exc
    out = np.empty((n, bs, k))
    out[keep] = np.asarray(x).reshape(nf, bs, k)[new[var[keep]]]
    if fixed is not None:
        assert x_fixed is not None
        out[fixed] = x_fixed
    return out


def chordal_initialization(
    graph: PoseGraph, gauge: int | None = None
) -> tuple[FloatArray, FloatArray]:
    """Global poses ``(R (N,3,3), t (N,3))`` from the chordal relaxation.

    A planar graph (``is_2d``) is solved in the plane: its z rows and columns decouple (zero
    right-hand side), so both systems keep the in-plane components only, and each rotation is
    the nearest planar one.

    Parameters
    ----------
    graph : PoseGraph
    gauge : int, optional
        Dense index of the pose whose rotation (and, without GPS, translation) is held at its
        file value (identity when the file has none).  Default: the first FIX node or pose 0.
    """
    n = graph.num_nodes
    if gauge is None:
        gauge = int(graph.fixed_nodes[0]) if graph.fixed_nodes.size else 0
    r_gauge = graph.rotations[gauge] if graph.has_estimates else np.eye(3)
    t_gauge = graph.translations[gauge] if graph.has_estimates else np.zeros(3)
    a = graph.edge_nodes[:, 0].astype(np.int64)
    b = graph.edge_nodes[:, 1].astype(np.int64)
    # the in-plane components only on a planar graph (see the docstring)
    s = 2 if graph.is_2d else 3
    analysis: dict[str, Any] = {}  # the rotations' order and analysis, for the translations
    zr = graph.edge_rotations[:, :s, :s]
    kappa = np.mean(np.diagonal(graph.edge_information[:, 3:, 3:], axis1=1, axis2=2), axis=1)

    # --- rotations: row k of R_b = (row k of R_a) Z, i.e. residual sqrt(kappa) (r_b - Z^T r_a)
    # for each row k (unknowns: the rows r of every R_i).  Normal equations by blocks:
    # (a, a) and (b, b) += kappa I (Z Z^T = I), (a, b) += -kappa Z; three right-hand sides k.
    eye = np.eye(s)
    deg = np.bincount(a, kappa, n) + np.bincount(b, kappa, n)
    diag = deg[:, None, None] * eye[None]
    off = -kappa[:, None, None] * zr
    try:
        x = _solve_blocks(n, diag, a, b, off, np.zeros((n, s, s)), gauge, r_gauge.T[:s, :s],
                          analysis)
    except RuntimeError as exc:  # singular: a part of the graph has no path to the gauge
        raise GraphError(
            "chordal initialization failed: the rotation system is singular "
            "(is the graph connected?)"
        ) from exc
    # x[i, :, k] is row k of R_i
    rot = (_project_to_so2 if s == 2 else _project_to_so3)(np.swapaxes(x, 1, 2))
    del x, diag, off

    # --- translations: residual L^T R_a^T (t_b - t_a) - L^T t_c with Omega_tt = L L^T, i.e.
    # weight S = R_a Omega_tt R_a^T: (a, a), (b, b) += S, (a, b) += -S; rhs_b += S R_a t_c.
    info_t = graph.edge_information[:, :s, :s]
    ra = rot[a][:, :s, :s]
    smat = np.einsum("eij,ejk,elk->eil", ra, info_t, ra)
    d = np.einsum("eij,ej->ei", smat,
                  np.einsum("eij,ej->ei", ra, graph.edge_translations[:, :s]))
    diag = np.zeros((n, s, s))
    rhs = np.zeros((n, s))
    for p in range(s):
        rhs[:, p] = np.bincount(b, d[:, p], n) - np.bincount(a, d[:, p], n)
        for q in range(s):
            diag[:, p, q] = np.bincount(a, smat[:, p, q], n) + np.bincount(b, smat[:, p, q], n)
    if graph.num_gps:
        gn = graph.gps_nodes.astype(np.int64)
        og = graph.gps_information[:, :s, :s]
        gd = np.einsum("gij,gj->gi", og, graph.gps_positions[:, :s])
        for p in range(s):
            rhs[:, p] += np.bincount(gn, gd[:, p], n)
            for q in range(s):
                diag[:, p, q] += np.bincount(gn, og[:, p, q], n)
    del ra, d
    try:
        t = _solve_blocks(n, diag, a, b, -smat, rhs[:, :, None],
                          None if graph.num_gps else gauge,
                          None if graph.num_gps else t_gauge[:s, None], analysis)
    except RuntimeError as exc:
        raise GraphError(
            "chordal initialization failed: the translation system is singular "
            "(a part of the graph without a gauge?)"
        ) from exc
    trans = np.zeros((n, 3))
    trans[:, :s] = t[:, :, 0]
    return rot, trans


def planar_relaxation_start(graph: PoseGraph, rotations: FloatArray, translations: FloatArray,
                            *, max_iterations: int = 300, rank: int = 2, seed: int = 0
                            ) -> tuple[FloatArray, FloatArray, dict[str, float]]:
    """Poses from the rank-``rank`` relaxation of a planar graph, started at given poses.

    The given rotations fill the first column of Y, the others are small random (``seed``):
    from a local minimum of the chordal cost, the extra rank opens a descent path (Burer-
    Monteiro).  The rounded rotations and their optimal positions are expressed in the frame
    of the given poses at the gauge pose (the first FIX node, else pose 0).  Returns
    ``(R, t, info)`` with ``info``: ``value`` (cost of the relaxation), ``rounded_value``,
    ``start_value`` (chordal cost of the given rotations), ``iterations``, ``max_angle`` (the
    largest rotation difference from the given poses, rad), ``second_singular_value``
    (relative to the first: 0 when the relaxation is rank 1).
    """
    if not graph.is_2d or graph.num_gps:
        raise ValueError("the planar relaxation needs a 2D graph without GPS constraints")
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            return _planar_relaxation(graph, rotations, translations, max_iterations, rank,
                                      seed)
    except FloatingPointError as exc:  # measurements of ~1e154: the quadratic overflows
        raise ValueError(f"the planar relaxation overflows float64 ({exc})") from exc


def _planar_relaxation(graph: PoseGraph, rotations: FloatArray, translations: FloatArray,
                       max_iterations: int, rank: int, seed: int,
                       ) -> tuple[FloatArray, FloatArray, dict[str, float]]:
    from .certificate import SyncProblem

    rel = SyncProblem(graph, weights="planar")
    n = graph.num_nodes
    z0: ComplexArray = np.asarray(rotations[:, 0, 0] + 1j * rotations[:, 1, 0], np.complex128)
    z0 = z0 / np.abs(z0)
    rng = np.random.default_rng(seed)
    y0 = np.empty((n, rank), np.complex128)
    y0[:, 0] = z0
    y0[:, 1:] = 0.01 * (rng.standard_normal((n, rank - 1))
                        + 1j * rng.standard_normal((n, rank - 1)))
    y0 /= np.linalg.norm(y0, axis=1, keepdims=True)
    start_value = rel.cost(z0[:, None])
    y, value, its = rel.minimize(y0, max_iterations)
    s = np.linalg.svd(y, compute_uv=False)
    z = rel.round(y)
    rot, trans = rel.poses(z, (rotations, translations))
    angle = np.abs(np.angle(rel.to_y(rot)[:, 0] * np.conj(z0)))
    info = {"value": value, "rounded_value": rel.cost(z), "start_value": start_value,
            "iterations": float(its), "max_angle": float(angle.max()),
            "second_singular_value": float(s[1] / s[0]) if s.size > 1 and s[0] > 0 else 0.0}
    return rot, trans, info


# --------------------------------------------------------------------------- tree starts
class InitKind(enum.Enum):
    """Where the initial local transforms of the tree parametrization come from."""

    TREE = "tree"
    """Concatenate the tree edges' measurements down from the root (paper III-A)."""
    FILE = "file"
    """The file's vertex estimates, ``T_i = X_parent^-1 X_i``."""
    CHORDAL = "chordal"
    """Chordal relaxation of the rotations, then linear translations (robust to rotation noise)."""


def initial_locals(
    graph: PoseGraph, tree: PoseTree, init: InitKind | str = InitKind.TREE
) -> tuple[FloatArray, FloatArray]:
    """Initial local transforms ``(rot (T,3,3), trans (T,3))`` of every tree node.

    ``init="tree"`` concatenates tree-edge measurements (a GPS link gives the child its measured
    position and its rotation from the file, or the identity when the file has no vertices);
    ``init="file"`` uses the file's vertex estimates; ``init="chordal"`` the chordal relaxation
    (:func:`chordal_initialization`).  The root keeps its file pose (the gauge);
    the earth is the identity.
    """
    init = InitKind(init)
    if init is InitKind.FILE and not graph.has_estimates:
        raise GraphError(
            "init='file' needs vertex estimates, but the file has none "
            "(iSAM files list only constraints): use init='tree'"
        )
    t_nodes = tree.num_tree_nodes
    rot = np.zeros((t_nodes, 3, 3))
    trans = np.zeros((t_nodes, 3))
    rot[:] = np.eye(3)
    n = graph.num_nodes
    if init in (InitKind.FILE, InitKind.CHORDAL):
        if init is InitKind.CHORDAL:
            grot0, gtr0 = chordal_initialization(graph, None if tree.has_earth else tree.root)
        else:
            grot0, gtr0 = graph.rotations, graph.translations
        grot = (
            np.concatenate([grot0, np.eye(3)[None]])
            if tree.has_earth
            else np.ascontiguousarray(grot0)
        )
        gtr = (
            np.concatenate([gtr0, np.zeros((1, 3))])
            if tree.has_earth
            else np.ascontiguousarray(gtr0)
        )
        locals_from_globals(tree.parent, grot, gtr, rot, trans)
        return rot, trans
    kind = tree.link_kind
    idx = tree.link_index
    e = kind == LINK_EDGE
    ei = idx[e]
    fwd = tree.link_forward[e]
    zr = graph.edge_rotations[ei]
    zt = graph.edge_translations[ei]
    # forward link (parent, child): T = Z; reversed (child, parent): T = Z^-1
    rot[e] = np.where(fwd[:, None, None], zr, np.swapaxes(zr, 1, 2))
    inv_t = -np.einsum("kji,kj->ki", zr, zt)
    trans[e] = np.where(fwd[:, None], zt, inv_t)
    gl = kind == LINK_GPS
    trans[gl] = graph.gps_positions[idx[gl]]
    if graph.has_estimates:
        rot[gl] = graph.rotations[np.nonzero(gl)[0]]
    if not tree.has_earth and tree.root < n:
        rot[tree.root] = graph.rotations[tree.root]
        trans[tree.root] = graph.translations[tree.root]
    return rot, trans
