"""Chordal initialization (Martinec & Pajdla 2007; Carlone et al., ICRA 2015).

A better start than dead reckoning for graphs with large rotation noise
(docs/mathematics.md#lm-damping names it as
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

import enum

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .errors import GraphError, SolverError
from .graph import FloatArray, PoseGraph
from .tree import LINK_EDGE, LINK_GPS, PoseTree, locals_from_globals


def _project_to_so3(m: FloatArray) -> FloatArray:
    u, _, vt = np.linalg.svd(m)
    det = np.linalg.det(u @ vt)
    u[:, :, 2] *= det[:, None]
    out: FloatArray = u @ vt
    return out


def _solve_blocks(n: int, diag: FloatArray, ea: npt.NDArray[np.int64],
                  eb: npt.NDArray[np.int64], off: FloatArray, rhs: FloatArray,
                  fixed: int | None, x_fixed: FloatArray | None) -> FloatArray:
    """Solve the SPD normal equations of 3-vectors per pose, given by blocks.

    ``diag`` (n, 3, 3): diagonal blocks; ``off`` (m, 3, 3): the block (row ea, column eb) of
    each edge (the (eb, ea) one is its transpose; parallel edges add up); ``rhs`` (n, 3, k).
    With ``fixed``, that pose is held at ``x_fixed`` (3, k): its blocks move to the right-hand
    side.  Only the lower triangle is built, straight in a fill-reducing (AMD, pose graph)
    order, and factored once for the k right-hand sides (CHOLMOD, else SuperLU).
    """
    from .linalg import CscPattern, fill_reducing_order, make_factorizer

    k = rhs.shape[2]
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
    pairs = np.unique(lo * max(nf, 1) + hi)
    new = fill_reducing_order(nf, pairs % max(nf, 1), pairs // max(nf, 1))
    del pairs, lo, hi
    pa, pb = new[va], new[vb]
    q3 = np.arange(3)
    # off-diagonal: block (pa, pb) = off; keep the one below the diagonal of the new order
    swap = pa < pb
    blk = np.where(swap[:, None, None], np.swapaxes(off, 1, 2), off)
    row_b = np.maximum(pa, pb)
    col_b = np.minimum(pa, pb)
    rows = [(3 * row_b[:, None, None] + q3[None, :, None]).repeat(3, 2).ravel()]
    cols = [(3 * col_b[:, None, None] + q3[None, None, :]).repeat(3, 1).ravel()]
    vals = [blk.ravel()]
    pi = new[var[keep]]
    il, jl = np.tril_indices(3)
    rows.append((3 * pi[:, None] + il[None, :]).ravel())
    cols.append((3 * pi[:, None] + jl[None, :]).ravel())
    vals.append(diag[keep][:, il, jl].ravel())
    dim = 3 * nf
    low = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(dim, dim))
    del rows, cols, vals, blk
    low.sum_duplicates()
    low.sort_indices()
    b = np.empty((dim, k))
    b.reshape(nf, 3, k)[new[var[keep]]] = rhs[keep]
    try:
        x = make_factorizer(CscPattern(low), "auto").solve(
            np.asarray(low.data, np.float64), b, check=True)
    except SolverError as exc:
        raise RuntimeError(str(exc)) from exc
    out = np.empty((n, 3, k))
    out[keep] = np.asarray(x).reshape(nf, 3, k)[new[var[keep]]]
    if fixed is not None:
        assert x_fixed is not None
        out[fixed] = x_fixed
    return out


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
    n = graph.num_nodes
    if gauge is None:
        gauge = int(graph.fixed_nodes[0]) if graph.fixed_nodes.size else 0
    r_gauge = graph.rotations[gauge] if graph.has_estimates else np.eye(3)
    t_gauge = graph.translations[gauge] if graph.has_estimates else np.zeros(3)
    a = graph.edge_nodes[:, 0].astype(np.int64)
    b = graph.edge_nodes[:, 1].astype(np.int64)
    zr = graph.edge_rotations
    kappa = np.mean(np.diagonal(graph.edge_information[:, 3:, 3:], axis1=1, axis2=2), axis=1)

    # --- rotations: row k of R_b = (row k of R_a) Z, i.e. residual sqrt(kappa) (r_b - Z^T r_a)
    # for each row k (unknowns: the rows r of every R_i).  Normal equations by blocks:
    # (a, a) and (b, b) += kappa I (Z Z^T = I), (a, b) += -kappa Z; three right-hand sides k.
    eye = np.eye(3)
    deg = np.bincount(a, kappa, n) + np.bincount(b, kappa, n)
    diag = deg[:, None, None] * eye[None]
    off = -kappa[:, None, None] * zr
    try:
        x = _solve_blocks(n, diag, a, b, off, np.zeros((n, 3, 3)), gauge, r_gauge.T)
    except RuntimeError as exc:  # singular: a part of the graph has no path to the gauge
        raise GraphError(
            "chordal initialization failed: the rotation system is singular "
            "(is the graph connected?)"
        ) from exc
    rot = _project_to_so3(np.swapaxes(x, 1, 2))  # x[i, :, k] is row k of R_i
    del x, diag, off

    # --- translations: residual L^T R_a^T (t_b - t_a) - L^T t_c with Omega_tt = L L^T, i.e.
    # weight S = R_a Omega_tt R_a^T: (a, a), (b, b) += S, (a, b) += -S; rhs_b += S R_a t_c.
    info_t = graph.edge_information[:, :3, :3]
    ra = rot[a]
    smat = np.einsum("eij,ejk,elk->eil", ra, info_t, ra)
    d = np.einsum("eij,ej->ei", smat, np.einsum("eij,ej->ei", ra, graph.edge_translations))
    diag = np.zeros((n, 3, 3))
    rhs = np.zeros((n, 3))
    for p in range(3):
        rhs[:, p] = np.bincount(b, d[:, p], n) - np.bincount(a, d[:, p], n)
        for q in range(3):
            diag[:, p, q] = np.bincount(a, smat[:, p, q], n) + np.bincount(b, smat[:, p, q], n)
    if graph.num_gps:
        gn = graph.gps_nodes.astype(np.int64)
        og = graph.gps_information
        gd = np.einsum("gij,gj->gi", og, graph.gps_positions)
        for p in range(3):
            rhs[:, p] += np.bincount(gn, gd[:, p], n)
            for q in range(3):
                diag[:, p, q] += np.bincount(gn, og[:, p, q], n)
    del ra, d
    try:
        t = _solve_blocks(n, diag, a, b, -smat, rhs[:, :, None],
                          None if graph.num_gps else gauge,
                          None if graph.num_gps else t_gauge[:, None])
    except RuntimeError as exc:
        raise GraphError(
            "chordal initialization failed: the translation system is singular "
            "(a part of the graph without a gauge?)"
        ) from exc
    return rot, np.ascontiguousarray(t[:, :, 0])


# --------------------------------------------------------------------------- planar relaxation
ComplexArray = npt.NDArray[np.complex128]


class PlanarRelaxation:
    """The planar pose-graph problem in SE-Sync's form (Rosen et al. 2019; complex numbers as in
    CPL-SLAM, Fan et al. 2020), for a rank-restricted (Burer-Monteiro) relaxation.

    With rotations ``z_i`` (unit complex numbers) and positions ``t_i`` (complex), the chordal
    cost of a 2D graph is ``sum_c kappa_c |z_b - z_a r_c|^2 + tau_c |t_b - t_a - z_a t_c|^2``
    (``r_c``, ``t_c``: the measurement; ``kappa_c`` the yaw information, ``tau_c`` the mean of
    the x and y information: an isotropic model of the translation term).  The positions enter
    linearly: eliminating them (pose 0's held at 0) leaves ``z^H Q z`` with the Schur complement
    ``Q = A - B D^-1 B^H`` (D: the weighted position Laplacian, factored once; Q stays implicit,
    one sparse solve per product).  The relaxation replaces each unit ``z_i`` by a unit row of
    ``Y`` (n, p) and minimizes ``tr(Y^H Q Y)`` (:meth:`minimize`); :meth:`round` projects back.
    It is the chordal cost, not the energy E (``Log``-based): an initializer, not a certificate
    of E's optimum.
    """

    def __init__(self, graph: PoseGraph) -> None:
        from .linalg import CscPattern, fill_reducing_order, make_factorizer

        n = graph.num_nodes
        self.n = n
        a = graph.edge_nodes[:, 0].astype(np.int64)
        b = graph.edge_nodes[:, 1].astype(np.int64)
        rz = graph.edge_rotations[:, 0, 0] + 1j * graph.edge_rotations[:, 1, 0]
        rz = rz / np.abs(rz)
        tz = graph.edge_translations[:, 0] + 1j * graph.edge_translations[:, 1]
        info = graph.edge_information
        kappa = info[:, 5, 5]
        tau = 0.5 * (info[:, 0, 0] + info[:, 1, 1])
        one = np.ones(a.size, np.complex128)
        # each term w |sum_k c_k x_k|^2 adds w conj(c_p) c_q at (p, q); z: 0..n-1, t: n..2n-1
        rows: list[npt.NDArray[np.int64]] = []
        cols: list[npt.NDArray[np.int64]] = []
        vals: list[ComplexArray] = []
        for idx, coef, w in (((b, a), (one, -rz), kappa),
                             ((n + b, n + a, a), (one, -one, -tz), tau)):
            for p, cp in zip(idx, coef, strict=True):
                for q, cq in zip(idx, coef, strict=True):
                    rows.append(p)
                    cols.append(q)
                    vals.append(w * np.conj(cp) * cq)
        m = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(2 * n, 2 * n))
        del rows, cols, vals
        keep = np.arange(n + 1, 2 * n)  # t_0 = 0: the translation gauge
        self._a = sp.csr_matrix(m[:n][:, :n])
        self._b = sp.csr_matrix(m[:n][:, keep])
        self._bh = sp.csr_matrix(self._b.conj().T)
        d = sp.csc_matrix(m[keep][:, keep].real)
        # D in a fill-reducing order, lower triangle, for the package's factorizer
        coo = sp.triu(d, k=1).tocoo()
        self._order = fill_reducing_order(n - 1, coo.row.astype(np.int64),
                                           coo.col.astype(np.int64))
        inv = np.empty(n - 1, np.int64)
        inv[self._order] = np.arange(n - 1)
        perm = sp.csc_matrix(d[inv][:, inv])  # (P D P^T)[i, j] = D[inv[i], inv[j]]
        low = sp.csc_matrix(sp.tril(perm))
        low.sort_indices()
        self._inv = inv
        self._solver = make_factorizer(CscPattern(low), "auto")
        self._solver.factor(np.asarray(low.data, np.float64))

    def _dsolve(self, rhs: ComplexArray) -> ComplexArray:
        """``D^-1 rhs`` for a complex (n-1, k) right-hand side (one real solve, 2k columns)."""
        k = rhs.shape[1]
        stacked = np.concatenate([rhs.real, rhs.imag], axis=1)[self._inv]
        x = np.empty_like(stacked)
        x[self._inv] = np.asarray(self._solver.solve_factored(stacked)).reshape(stacked.shape)
        out: ComplexArray = x[:, :k] + 1j * x[:, k:]
        return out

    def q(self, y: ComplexArray) -> ComplexArray:
        """``Q y`` for y (n, k)."""
        out: ComplexArray = self._a @ y - self._b @ self._dsolve(self._bh @ y)
        return out

    def cost(self, y: ComplexArray) -> float:
        """``tr(Y^H Q Y)`` (the chordal cost at unit ``z``, optimal positions)."""
        return float(np.real(np.vdot(y, self.q(y))))

    def positions(self, z: ComplexArray) -> ComplexArray:
        """The optimal positions for rotations z (pose 0 at 0)."""
        t = np.zeros(self.n, np.complex128)
        t[1:] = -self._dsolve(self._bh @ z[:, None])[:, 0]
        return t

    def minimize(self, y: ComplexArray, max_iterations: int,
                 gradient_tolerance: float = 1e-6, stall: float = 1e-6
                 ) -> tuple[ComplexArray, float, int]:
        """Riemannian conjugate gradients (Polak-Ribiere+, the tangent projection as
        transport) on the unit rows of Y, from ``y``; each step minimizes the quadratic model
        along the direction, then normalizes the rows (Armijo backtracking).  Stops when the
        Riemannian gradient falls below ``gradient_tolerance`` of its first norm, or the cost
        fell by less than ``stall`` (relative) over 20 iterations.  Returns ``(Y, cost, its)``."""
        def unit(v: ComplexArray) -> ComplexArray:
            out: ComplexArray = v / np.linalg.norm(v, axis=1, keepdims=True)
            return out

        def tangent(at: ComplexArray, v: ComplexArray) -> ComplexArray:
            out: ComplexArray = v - np.real(np.sum(np.conj(at) * v, axis=1,
                                                   keepdims=True)) * at
            return out

        qy = self.q(y)
        f = float(np.real(np.vdot(y, qy)))
        grad = tangent(y, 2.0 * qy)
        g0 = float(np.linalg.norm(grad))
        direction = -grad
        past = [f]
        it = 0
        while it < max_iterations and g0 > 0.0:
            it += 1
            slope = float(np.real(np.vdot(grad, direction)))
            if slope >= 0.0:
                direction = -grad
                slope = -float(np.real(np.vdot(grad, grad)))
            curv = 2.0 * float(np.real(np.vdot(direction, self.q(direction))))
            step = -slope / curv if curv > 0.0 else 1.0
            while True:
                y_new = unit(y + step * direction)
                qy_new = self.q(y_new)
                f_new = float(np.real(np.vdot(y_new, qy_new)))
                if f_new <= f + 1e-4 * step * slope or step < 1e-14:
                    break
                step *= 0.5
            if not f_new <= f:
                break
            grad_new = tangent(y_new, 2.0 * qy_new)
            moved = tangent(y_new, grad)
            beta = max(0.0, float(np.real(np.vdot(grad_new, grad_new - moved)))
                       / float(np.real(np.vdot(grad, grad))))
            direction = tangent(y_new, direction)
            direction = -grad_new + beta * direction
            y, grad, f = y_new, grad_new, f_new
            past.append(f)
            if float(np.linalg.norm(grad)) <= gradient_tolerance * g0:
                break
            if len(past) > 20 and past[-21] - f <= stall * abs(past[-21]):
                break
        return y, f, it

    @staticmethod
    def round(y: ComplexArray) -> ComplexArray:
        """Unit complex rotations from Y: its leading left singular vector, entries normalized
        (the rank-1 projection of ``Y Y^H``; global phase arbitrary)."""
        u, s, _ = np.linalg.svd(y, full_matrices=False)
        z = u[:, 0] * s[0]
        mag = np.abs(z)
        out: ComplexArray = np.where(mag > 0, z / np.where(mag > 0, mag, 1.0), 1.0 + 0j)
        return out


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
    rel = PlanarRelaxation(graph)
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
    t = rel.positions(z)
    g = int(graph.fixed_nodes[0]) if graph.fixed_nodes.size else 0
    turn = z0[g] * np.conj(z[g])
    z = z * turn
    t0 = translations[g, 0] + 1j * translations[g, 1]
    t = (t - t[g]) * turn + t0
    angle = np.abs(np.angle(z * np.conj(z0)))
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0] = rot[:, 1, 1] = z.real
    rot[:, 1, 0] = z.imag
    rot[:, 0, 1] = -z.imag
    rot[:, 2, 2] = 1.0
    trans = np.zeros((n, 3))
    trans[:, 0], trans[:, 1] = t.real, t.imag
    info = {"value": value, "rounded_value": rel.cost(z[:, None]), "start_value": start_value,
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
