"""A global correction between sweeps: a truncated Gauss-Newton step by preconditioned CG.

The single updates of a sweep are local: each one moves only its constraint's domain, and at the
optimum the single forces ``J_c^T r_c`` do not vanish, so the sweeps hover around it.
After each sweep :func:`correct` takes one *global* step: a few iterations of conjugate
gradients on the exact Gauss-Newton system of the tree parametrization (paper eq. 11, the step
the batch of every constraint would take, III-F)

    H x = J^T r,        H = sum_c J_c^T J_c,

preconditioned by 𝔅(H), the block diagonal of H the hybrid Hessians are built from (eq. 23).  In
the tree parametrization every tree edge has a one-node domain, so 𝔅(H) contains the whole
Hessian of the spanning tree: this is at least the spanning-tree ("subgraph") preconditioner of
the global parametrization.  The step is applied with the pi/8 cap of III-H and accepted only if
the energy falls (halved up to ``BACKTRACKS`` times, else not taken).  At a stationary point
``J^T r = 0`` and the correction is zero.

Products with J and J^T cost O(N + M) whatever the path lengths.  Constraint c's Jacobian block
on domain node u factors as ``J_{c,u} = s_{c,u} A_c Ad(Y_u)`` (``Y_u`` the global pose of u,
``A_c = L^T Jr^-1(e_c) Ad(Y_b)^-1`` for a relative constraint, ``L^T [I | -[p_n]x]`` for GPS;
the factorization :mod:`._batch` uses), and the signed domain of c is the tree path from a up to
the constraint's root and down to b.  Hence, with ``w_u = Ad(Y_u) v_u`` and ``S_i`` the sum of
w over i and its ancestors,

    (J v)_c = A_c (S_b - S_a),

and ``J^T y`` deposits ``+A_c^T y_c`` at b and ``-A_c^T y_c`` at a; the sum of the deposits over
u's subtree, times ``Ad(Y_u)^T``, is ``(J^T y)_u`` (a constraint's two deposits cancel at and
above its root).  𝔅(H) is built the same way from ``A_c^T A_c`` deposited at a and b and
``-2 A_c^T A_c`` at the constraint's root.  (A GPS reading is a constraint between the earth,
the root, and its pose.)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from ..._cost import (
    ROBUST_NONE,
    SCRATCH,
    gps_residual,
    jr_inv_matrix,
    residual_and_jr_inv,
    retract_into,
    robust_whitening,
    whiten_residual,
    whiten_rows,
)
from ..._numba import kernel
from ..._tree_kernels import globals_from_locals
from ...geometry._kernels import adjoint_into
from ...graph import FloatArray, PoseGraph
from ...tree import PoseTree
from ._dense import MAX_DAMPING_ESCALATIONS, regularized_factor, solve_lt
from ._linearize import gps_factor_into, relative_factor_into
from ._step import step_temperature
from .problem import Problem, State, Update

#: Halvings of a correction step whose energy is not below the start's before it is dropped.
BACKTRACKS = 4
#: CG stops early when the preconditioned residual norm falls below this fraction of its start.
CG_TOLERANCE = 1e-10

I64 = npt.NDArray[np.int64]


class Topology(NamedTuple):
    """The tree arrays a correction needs (int64)."""

    order: I64
    """(T,) tree nodes, every parent before its children."""
    parent: I64
    """(T,) parent, -1 for the root."""
    ends: I64
    """(C, 2) tree nodes (a, b) of every constraint; a GPS reading is (root = earth, n)."""
    croot: I64
    """(C,) every constraint's root (the lowest common ancestor of a and b)."""


def topology(graph: PoseGraph, tree: PoseTree) -> Topology:
    """The :class:`Topology` of ``tree`` over ``graph`` (tree node i is pose i, the earth N)."""
    ends = np.empty((tree.num_constraints, 2), np.int64)
    ends[: graph.num_edges] = graph.edge_nodes
    ends[graph.num_edges:, 0] = tree.root
    ends[graph.num_edges:, 1] = graph.gps_nodes
    return Topology(tree.order.astype(np.int64), tree.parent.astype(np.int64), ends,
                    tree.constraint_root.astype(np.int64))


class Report(NamedTuple):
    """What one :func:`correct` did."""

    iterations: int
    """CG iterations run."""
    scale: float
    """The factor the CG step was applied with (0: not taken)."""
    energy_before: float
    energy_after: float


# --------------------------------------------------------------------------- small algebra
@kernel
def ad_mul(r: np.ndarray, t: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """``out = Ad(T) v = (R rho + t x (R phi), R phi)``."""
    for i in range(3):
        out[3 + i] = r[i, 0] * v[3] + r[i, 1] * v[4] + r[i, 2] * v[5]
        out[i] = r[i, 0] * v[0] + r[i, 1] * v[1] + r[i, 2] * v[2]
    out[0] += t[1] * out[5] - t[2] * out[4]
    out[1] += t[2] * out[3] - t[0] * out[5]
    out[2] += t[0] * out[4] - t[1] * out[3]


@kernel
def ad_t_mul(r: np.ndarray, t: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
    """``out = Ad(T)^T z = (R^T z_t, R^T (z_r - t x z_t))``."""
    c0 = z[3] - (t[1] * z[2] - t[2] * z[1])
    c1 = z[4] - (t[2] * z[0] - t[0] * z[2])
    c2 = z[5] - (t[0] * z[1] - t[1] * z[0])
    for i in range(3):
        out[i] = r[0, i] * z[0] + r[1, i] * z[1] + r[2, i] * z[2]
        out[3 + i] = r[0, i] * c0 + r[1, i] * c1 + r[2, i] * c2


@kernel
def _solve_l(lo: np.ndarray, v: np.ndarray, x: np.ndarray) -> None:
    """Solve ``L x = v`` for a (6, 6) lower factor L (forward substitution)."""
    for i in range(6):
        acc = v[i]
        for m in range(i):
            acc -= lo[i, m] * x[m]
        x[i] = acc / lo[i, i]


# --------------------------------------------------------------------------- linearization
@kernel
def linearize_all(prob: Problem, ends: np.ndarray, yr: np.ndarray, yt: np.ndarray,
                  amat: np.ndarray, res: np.ndarray) -> None:
    """``A_c`` (``amat[c, :kr]``) and the whitened residual ``r_c`` (``res[c, :kr]``) of every
    constraint at the global poses ``(yr, yt)`` (rows beyond kr are zero); the IRLS weight of a
    robust kernel is folded in as in :func:`._linearize.linearize`."""
    ws = np.empty((SCRATCH, 3, 3))
    e = np.empty(6)
    jri = np.empty((6, 6))
    a0 = np.empty((6, 6))
    adb = np.empty((6, 6))
    blk = np.zeros((3, 6))
    for c in range(ends.shape[0]):
        a = ends[c, 0]
        b = ends[c, 1]
        amat[c] = 0.0
        res[c] = 0.0
        if c < prob.num_edges:
            residual_and_jr_inv(prob.edge_rot[c], prob.edge_trans[c], yr[a], yt[a], yr[b],
                                yt[b], e, ws)
            jr_inv_matrix(ws, jri)
            lt = prob.edge_lt[c]
            whiten_residual(lt, e, 6, res[c])
            whiten_rows(lt, jri, 6, a0)
            if prob.robust_kind != ROBUST_NONE:  # whiten with sqrt(w) L^T
            # (docs/conventions.md#robust-kernels)
                sw = robust_whitening(prob.robust_kind, prob.robust_scale, res[c], 6)
                for p in range(6):
                    res[c, p] *= sw
                    for j in range(6):
                        a0[p, j] *= sw
            relative_factor_into(a0, yr[b], yt[b], adb, amat[c])
        else:
            g = c - prob.num_edges
            pn = yt[b]  # the earth is the identity
            gps_residual(pn, prob.gps_pos[g], e)
            whiten_residual(prob.gps_lt[g], e, 3, res[c])
            gps_factor_into(prob.gps_lt[g], pn, blk, amat[c])


# --------------------------------------------------------------------------- products
@kernel
def subtree_transpose(order: np.ndarray, parent: np.ndarray, yr: np.ndarray, yt: np.ndarray,
                      dep: np.ndarray) -> None:
    """In place: world-frame deposits -> ``Ad(Y_u)^T`` (sum over u's subtree); the root gets 0."""
    for k in range(order.shape[0] - 1, -1, -1):
        i = order[k]
        p = parent[i]
        if p >= 0:
            for q in range(6):
                dep[p, q] += dep[i, q]
    tmp = np.empty(6)
    for k in range(order.shape[0]):
        i = order[k]
        if parent[i] < 0:
            dep[i] = 0.0
            continue
        ad_t_mul(yr[i], yt[i], dep[i], tmp)
        dep[i] = tmp


@kernel
def jacobian_product(topo: Topology, num_edges: int, yr: np.ndarray, yt: np.ndarray,
                     amat: np.ndarray, v: np.ndarray, sbuf: np.ndarray, jv: np.ndarray) -> None:
    """``jv[c, :kr] = (J v)_c`` for a step v (T, 6) (the root's entry is ignored)."""
    order = topo.order
    parent = topo.parent
    tmp = np.empty(6)
    for k in range(order.shape[0]):
        i = order[k]
        p = parent[i]
        if p < 0:
            sbuf[i] = 0.0
            continue
        ad_mul(yr[i], yt[i], v[i], tmp)
        for q in range(6):
            sbuf[i, q] = sbuf[p, q] + tmp[q]
    for c in range(topo.ends.shape[0]):
        a = topo.ends[c, 0]
        b = topo.ends[c, 1]
        kr = 6 if c < num_edges else 3
        for q in range(6):
            tmp[q] = sbuf[b, q] - sbuf[a, q]
        for w in range(6):
            acc = 0.0
            if w < kr:
                for q in range(6):
                    acc += amat[c, w, q] * tmp[q]
            jv[c, w] = acc


@kernel
def transpose_product(topo: Topology, num_edges: int, yr: np.ndarray, yt: np.ndarray,
                      amat: np.ndarray, y: np.ndarray, out: np.ndarray) -> None:
    """``out = J^T y`` (T, 6) for per-constraint rows ``y[c, :kr]`` (the root's entry is 0)."""
    out[:] = 0.0
    for c in range(topo.ends.shape[0]):
        a = topo.ends[c, 0]
        b = topo.ends[c, 1]
        kr = 6 if c < num_edges else 3
        for q in range(6):
            acc = 0.0
            for w in range(kr):
                acc += amat[c, w, q] * y[c, w]
            out[b, q] += acc
            out[a, q] -= acc
    subtree_transpose(topo.order, topo.parent, yr, yt, out)


@kernel
def block_diagonal(topo: Topology, num_edges: int, yr: np.ndarray, yt: np.ndarray,
                   amat: np.ndarray, out: np.ndarray) -> None:
    """𝔅(H): ``out[u] = sum over constraints c whose domain holds u of J_{c,u}^T J_{c,u}``."""
    order = topo.order
    parent = topo.parent
    nt = order.shape[0]
    kk = np.zeros((nt, 6, 6))
    for c in range(topo.ends.shape[0]):
        a = topo.ends[c, 0]
        b = topo.ends[c, 1]
        rt = topo.croot[c]
        kr = 6 if c < num_edges else 3
        for p in range(6):
            for q in range(6):
                acc = 0.0
                for w in range(kr):
                    acc += amat[c, w, p] * amat[c, w, q]
                kk[a, p, q] += acc
                kk[b, p, q] += acc
                kk[rt, p, q] -= 2.0 * acc
    for k in range(nt - 1, -1, -1):
        i = order[k]
        p = parent[i]
        if p >= 0:
            kk[p] += kk[i]
    ad = np.empty((6, 6))
    for i in range(nt):
        if parent[i] < 0:
            out[i] = 0.0
            continue
        adjoint_into(yr[i], yt[i], ad)
        out[i] = ad.T @ kk[i] @ ad


# --------------------------------------------------------------------------- the step
@kernel
def _precondition(lf: np.ndarray, parent: np.ndarray, r: np.ndarray, z: np.ndarray,
                  tmp: np.ndarray) -> float:
    """``z = 𝔅(H)^-1 r`` blockwise (the root's entry 0); returns ``r . z``."""
    rz = 0.0
    for i in range(parent.shape[0]):
        if parent[i] < 0:
            z[i] = 0.0
            continue
        _solve_l(lf[i], r[i], tmp)
        solve_lt(lf[i], tmp, z[i])
        for q in range(6):
            rz += r[i, q] * z[i, q]
    return rz


@kernel
def pcg_step(topo: Topology, num_edges: int, yr: np.ndarray, yt: np.ndarray,
             amat: np.ndarray, res: np.ndarray, mu: float, iterations: int,
             x: np.ndarray) -> int:
    """At most ``iterations`` of CG on ``H x = J^T r`` from ``x = 0``, preconditioned by 𝔅(H)
    (each block damped as the hybrid step's, docs/mathematics.md#hybrid-step).  Returns the
    iterations run."""
    parent = topo.parent
    nt = parent.shape[0]
    nc = topo.ends.shape[0]
    lf = np.empty((nt, 6, 6))
    blocks = np.empty((nt, 6, 6))
    block_diagonal(topo, num_edges, yr, yt, amat, blocks)
    for i in range(nt):
        tr = 0.0
        for q in range(6):
            tr += blocks[i, q, q]
        if parent[i] < 0 or (regularized_factor(blocks[i], tr, mu, lf[i])
                             >= MAX_DAMPING_ESCALATIONS):
            lf[i] = 0.0
            for q in range(6):
                lf[i, q, q] = 1.0
    r = np.empty((nt, 6))
    transpose_product(topo, num_edges, yr, yt, amat, res, r)
    x[:] = 0.0
    z = np.empty((nt, 6))
    tmp = np.empty(6)
    rz = _precondition(lf, parent, r, z, tmp)
    if not rz > 0.0:
        return 0
    stop = rz * CG_TOLERANCE * CG_TOLERANCE
    p = z.copy()
    sbuf = np.empty((nt, 6))
    jv = np.empty((nc, 6))
    ap = np.empty((nt, 6))
    done = 0
    for _ in range(iterations):
        jacobian_product(topo, num_edges, yr, yt, amat, p, sbuf, jv)
        pap = 0.0
        for c in range(nc):
            for w in range(6):
                pap += jv[c, w] * jv[c, w]
        if not pap > 0.0:
            break
        transpose_product(topo, num_edges, yr, yt, amat, jv, ap)
        alpha = rz / pap
        for i in range(nt):
            for q in range(6):
                x[i, q] += alpha * p[i, q]
                r[i, q] -= alpha * ap[i, q]
        done += 1
        rz_new = _precondition(lf, parent, r, z, tmp)
        if not rz_new > stop:
            break
        beta = rz_new / rz
        for i in range(nt):
            for q in range(6):
                p[i, q] = z[i, q] + beta * p[i, q]
        rz = rz_new
    return done


@kernel
def apply_step(parent: np.ndarray, x: np.ndarray, scale: float, rot: np.ndarray,
               trans: np.ndarray) -> None:
    """``T_i <- T_i Exp(scale x_i)`` for every non-root tree node."""
    er = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for i in range(parent.shape[0]):
        if parent[i] >= 0:
            retract_into(rot[i], trans[i], x[i], scale, rot[i], trans[i], er, tmp)


def gauss_newton_step(prob: Problem, state: State, topo: Topology, iterations: int,
                      mu: float) -> tuple[FloatArray, int]:
    """The (truncated) CG step x (T, 6) of the tree parametrization at the current state, and the
    number of CG iterations.  Enough iterations give the exact Gauss-Newton step."""
    nt = topo.parent.shape[0]
    nc = topo.ends.shape[0]
    yr = np.empty((nt, 3, 3))
    yt = np.empty((nt, 3))
    globals_from_locals(topo.order, topo.parent, state.rot, state.trans, yr, yt)
    amat = np.empty((nc, 6, 6))
    res = np.empty((nc, 6))
    linearize_all(prob, topo.ends, yr, yt, amat, res)
    x = np.zeros((nt, 6))
    done = pcg_step(topo, prob.num_edges, yr, yt, amat, res, mu, iterations, x)
    return x, int(done)


def correct(prob: Problem, state: State, topo: Topology, iterations: int, mu: float,
            energy: Callable[[], float], energy_before: float | None = None) -> Report:
    """One global correction (module docstring): CG step, pi/8 cap, energy test, backtracking.

    ``energy()`` evaluates the objective at ``state``; the state is left at the accepted step
    (or unchanged).
    """
    x, done = gauss_newton_step(prob, state, topo, iterations, mu)
    e0 = energy() if energy_before is None else energy_before
    if done == 0:
        return Report(0, 0.0, e0, e0)
    scale, status = step_temperature(x, x.shape[0], 1.0)
    if status == Update.REJECTED:
        return Report(done, 0.0, e0, e0)
    rot0 = state.rot.copy()
    trans0 = state.trans.copy()
    for _ in range(BACKTRACKS + 1):
        apply_step(topo.parent, x, scale, state.rot, state.trans)
        e1 = energy()
        if e1 <= e0:
            return Report(done, scale, e0, e1)
        state.rot[:] = rot0
        state.trans[:] = trans0
        scale *= 0.5
    return Report(done, 0.0, e0, e0)
