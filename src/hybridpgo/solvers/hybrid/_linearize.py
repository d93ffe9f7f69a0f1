"""Linearization in the tree parametrization (paper III-B; docs/mathematics.md#jacobians).

Perturbing every local transform on the right, ``T_i <- T_i Exp(delta_i)``, constraint c's
whitened Jacobian block for domain node i is

* relative: ``s_i L^T Jr^-1(e0) Ad(X_b^-1 X_i)`` (s_i = +1 on the b side, -1 on the a side);
* GPS on n: ``L^T R_i [I | -[t_{i->n}]x]``.

Both come from products of local transforms along the path only (no global pose is needed),
so one linearization costs O(d).  The error, ``Jr^-1`` and the whitening come from the cost
layer (:mod:`hybridpgo._cost`).  With a robust kernel a relative constraint is whitened with
``sqrt(w) L^T`` in place of ``L^T``, ``w = rho'(s)`` (docs/conventions.md#robust-kernels), so its
``J_c``, ``r_c`` and its
contribution to 𝔅(H) all carry the weight.
"""

from __future__ import annotations

import numpy as np

from ..._cost import (
    ROBUST_NONE,
    gps_residual,
    jr_inv_matrix,
    residual_and_jr_inv,
    robust_whitening,
    whiten_residual,
    whiten_rows,
)
from ..._numba import kernel
from ..._tree_kernels import mul_pose_into as mul_pose_into
from ...geometry._kernels import adjoint_into
from .problem import EYE, ZERO, Problem, Workspace, domain, is_gps


@kernel
def num_a_side(prob: Problem, c: int) -> int:
    """How many of c's domain nodes are on the a side (they come first in the path)."""
    s, d = domain(prob, c)
    na = 0
    while na < d and prob.path_sign[s + na] < 0:
        na += 1
    return na


@kernel
def chain_products(path_node: np.ndarray, s: int, lo: int, hi: int, rot: np.ndarray,
                   trans: np.ndarray, pr: np.ndarray, pt: np.ndarray) -> None:
    """``P_k = P_{k+1} X_{path[k]}`` for ``k = hi-1 .. lo`` (``P_{hi-1}`` its local transform).

    Scalar indexing only (a view or an array argument per node costs a reference-count pair,
    an atomic operation, more than the 3x3 product itself); ``P_{k+1}`` is carried in scalar
    locals (``v..``, ``w.``) rather than read back from ``pr``/``pt`` after a store.
    """
    if hi <= lo:
        return
    i = path_node[s + hi - 1]
    v00, v01, v02 = rot[i, 0, 0], rot[i, 0, 1], rot[i, 0, 2]
    v10, v11, v12 = rot[i, 1, 0], rot[i, 1, 1], rot[i, 1, 2]
    v20, v21, v22 = rot[i, 2, 0], rot[i, 2, 1], rot[i, 2, 2]
    w0, w1, w2 = trans[i, 0], trans[i, 1], trans[i, 2]
    k = hi - 1
    pr[k, 0, 0], pr[k, 0, 1], pr[k, 0, 2] = v00, v01, v02
    pr[k, 1, 0], pr[k, 1, 1], pr[k, 1, 2] = v10, v11, v12
    pr[k, 2, 0], pr[k, 2, 1], pr[k, 2, 2] = v20, v21, v22
    pt[k, 0], pt[k, 1], pt[k, 2] = w0, w1, w2
    for k in range(hi - 2, lo - 1, -1):
        i = path_node[s + k]
        q00 = v00 * rot[i, 0, 0] + v01 * rot[i, 1, 0] + v02 * rot[i, 2, 0]
        q01 = v00 * rot[i, 0, 1] + v01 * rot[i, 1, 1] + v02 * rot[i, 2, 1]
        q02 = v00 * rot[i, 0, 2] + v01 * rot[i, 1, 2] + v02 * rot[i, 2, 2]
        q10 = v10 * rot[i, 0, 0] + v11 * rot[i, 1, 0] + v12 * rot[i, 2, 0]
        q11 = v10 * rot[i, 0, 1] + v11 * rot[i, 1, 1] + v12 * rot[i, 2, 1]
        q12 = v10 * rot[i, 0, 2] + v11 * rot[i, 1, 2] + v12 * rot[i, 2, 2]
        q20 = v20 * rot[i, 0, 0] + v21 * rot[i, 1, 0] + v22 * rot[i, 2, 0]
        q21 = v20 * rot[i, 0, 1] + v21 * rot[i, 1, 1] + v22 * rot[i, 2, 1]
        q22 = v20 * rot[i, 0, 2] + v21 * rot[i, 1, 2] + v22 * rot[i, 2, 2]
        u0 = v00 * trans[i, 0] + v01 * trans[i, 1] + v02 * trans[i, 2] + w0
        u1 = v10 * trans[i, 0] + v11 * trans[i, 1] + v12 * trans[i, 2] + w1
        u2 = v20 * trans[i, 0] + v21 * trans[i, 1] + v22 * trans[i, 2] + w2
        pr[k, 0, 0], pr[k, 0, 1], pr[k, 0, 2] = q00, q01, q02
        pr[k, 1, 0], pr[k, 1, 1], pr[k, 1, 2] = q10, q11, q12
        pr[k, 2, 0], pr[k, 2, 1], pr[k, 2, 2] = q20, q21, q22
        pt[k, 0], pt[k, 1], pt[k, 2] = u0, u1, u2
        v00, v01, v02 = q00, q01, q02
        v10, v11, v12 = q10, q11, q12
        v20, v21, v22 = q20, q21, q22
        w0, w1, w2 = u0, u1, u2


@kernel
def path_products(prob: Problem, c: int, rot: np.ndarray, trans: np.ndarray,
                  pr: np.ndarray, pt: np.ndarray) -> int:
    """P_k = X_root^-1 X_{path[k]} for every domain node k (into ``pr``, ``pt``); returns n_a.

    The a-side nodes are stored from a upward, so products are accumulated from the top down.
    """
    s, d = domain(prob, c)
    na = num_a_side(prob, c)
    chain_products(prob.path_node, s, 0, na, rot, trans, pr, pt)  # the a side (top at na-1)
    chain_products(prob.path_node, s, na, d, rot, trans, pr, pt)  # the b side (top at d-1)
    return na


@kernel
def endpoints(
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
def relative_blocks(path_sign: np.ndarray, s: int, d: int, rb: np.ndarray, tb: np.ndarray,
                    pr: np.ndarray, pt: np.ndarray, a: np.ndarray, sc: np.ndarray,
                    jac: np.ndarray) -> None:
    """``jac[k] = s_k A Ad(M_k)`` with ``A = L^T Jr^-1(e0)``, ``M_k = X_b^-1 X_k = P_b^-1 P_k``
    (``rb, tb``: X_b in the constraint root's frame; ``sc`` (>= 3, 3, 3) scratch).  Scalar
    indexing only (no view per node)."""
    for k in range(d):
        # Ad(M_k) = [[R, [t]x R], [0, R]]: R -> sc[0], [t]x R -> sc[1], t -> sc[2, 0]
        for i in range(3):
            sc[2, 0, i] = (
                rb[0, i] * (pt[k, 0] - tb[0])
                + rb[1, i] * (pt[k, 1] - tb[1])
                + rb[2, i] * (pt[k, 2] - tb[2])
            )
            for j in range(3):
                sc[0, i, j] = (rb[0, i] * pr[k, 0, j] + rb[1, i] * pr[k, 1, j]
                               + rb[2, i] * pr[k, 2, j])
        for j in range(3):  # [tm]x rm
            sc[1, 0, j] = sc[2, 0, 1] * sc[0, 2, j] - sc[2, 0, 2] * sc[0, 1, j]
            sc[1, 1, j] = sc[2, 0, 2] * sc[0, 0, j] - sc[2, 0, 0] * sc[0, 2, j]
            sc[1, 2, j] = sc[2, 0, 0] * sc[0, 1, j] - sc[2, 0, 1] * sc[0, 0, j]
        sg = float(path_sign[s + k])
        for p in range(6):
            for j in range(3):
                v0 = a[p, 0] * sc[0, 0, j] + a[p, 1] * sc[0, 1, j] + a[p, 2] * sc[0, 2, j]
                v1 = (
                    a[p, 0] * sc[1, 0, j]
                    + a[p, 1] * sc[1, 1, j]
                    + a[p, 2] * sc[1, 2, j]
                    + a[p, 3] * sc[0, 0, j]
                    + a[p, 4] * sc[0, 1, j]
                    + a[p, 5] * sc[0, 2, j]
                )
                jac[k, p, j] = sg * v0
                jac[k, p, 3 + j] = sg * v1


@kernel
def _gps_blocks(prob: Problem, c: int, wk: Workspace, jac: np.ndarray) -> None:
    """``jac[k] = L^T R_k [I | -[t_{k->n}]x]`` (rows 3..5 zero); path[0] is n itself."""
    _s, d = domain(prob, c)
    pr = wk.path_rot
    pt = wk.path_trans
    lt = prob.gps_lt[c - prob.num_edges]
    tn = pt[0]
    blk = wk.a  # (3, 6) used
    t_kn = wk.ws[0][0]
    for k in range(d):
        for i in range(3):
            t_kn[i] = (
                pr[k, 0, i] * (tn[0] - pt[k, 0])
                + pr[k, 1, i] * (tn[1] - pt[k, 1])
                + pr[k, 2, i] * (tn[2] - pt[k, 2])
            )
        for i in range(3):  # R_k [I | -[t]x], [t]x's columns (0,t2,-t1), (-t2,0,t0), (t1,-t0,0)
            blk[i, 0] = pr[k, i, 0]
            blk[i, 1] = pr[k, i, 1]
            blk[i, 2] = pr[k, i, 2]
            blk[i, 3] = -(pr[k, i, 1] * t_kn[2] - pr[k, i, 2] * t_kn[1])
            blk[i, 4] = -(-pr[k, i, 0] * t_kn[2] + pr[k, i, 2] * t_kn[0])
            blk[i, 5] = -(pr[k, i, 0] * t_kn[1] - pr[k, i, 1] * t_kn[0])
        whiten_rows(lt, blk, 3, jac[k])
        for p in range(3, 6):
            for j in range(6):
                jac[k, p, j] = 0.0


@kernel
def relative_setup(path_node: np.ndarray, path_sign: np.ndarray, s: int, d: int,
                   zr: np.ndarray, zt: np.ndarray, lt: np.ndarray, robust_kind: int,
                   robust_scale: float, rot: np.ndarray, trans: np.ndarray, pr: np.ndarray,
                   pt: np.ndarray, iws: np.ndarray, ws: np.ndarray, e: np.ndarray,
                   r: np.ndarray, jri: np.ndarray, a: np.ndarray) -> int:
    """:func:`relative_linearization` up to the Jacobian blocks: the path products, ``e0``,
    ``r``, ``Jr^-1(e0)`` and ``a = L^T Jr^-1(e0)``; returns n_a.  The update kernels then run
    :func:`~._step.linearize_accumulate` (the blocks and 𝔅(H) in one pass)."""
    na = 0
    while na < d and path_sign[s + na] < 0:
        na += 1
    chain_products(path_node, s, 0, na, rot, trans, pr, pt)  # the a side (top at na-1)
    chain_products(path_node, s, na, d, rot, trans, pr, pt)  # the b side (top at d-1)
    # endpoints in the root's frame: an empty side is the root itself (the identity)
    ra = iws[EYE]
    ta = iws[ZERO][0]
    if na > 0:
        ra = pr[0]
        ta = pt[0]
    rb = iws[EYE]
    tb = iws[ZERO][0]
    if na < d:
        rb = pr[na]
        tb = pt[na]
    residual_and_jr_inv(zr, zt, ra, ta, rb, tb, e, ws)
    jr_inv_matrix(ws, jri)
    whiten_residual(lt, e, 6, r)
    whiten_rows(lt, jri, 6, a)
    if robust_kind != ROBUST_NONE:  # whiten with sqrt(w) L^T (docs/conventions.md#robust-kernels)
        sw = robust_whitening(robust_kind, robust_scale, r, 6)
        for p in range(6):
            r[p] *= sw
            for j in range(6):
                a[p, j] *= sw
    return na


@kernel
def relative_linearization(path_node: np.ndarray, path_sign: np.ndarray, s: int, d: int,
                           zr: np.ndarray, zt: np.ndarray, lt: np.ndarray, robust_kind: int,
                           robust_scale: float, rot: np.ndarray, trans: np.ndarray,
                           pr: np.ndarray, pt: np.ndarray, iws: np.ndarray, ws: np.ndarray,
                           e: np.ndarray, r: np.ndarray, jri: np.ndarray, a: np.ndarray,
                           jac: np.ndarray) -> int:
    """:func:`linearize` of a relative constraint (measurement ``zr, zt``, whitening ``lt``)
    whose domain is ``path_node[s:s + d]``, with a :class:`~.problem.Workspace`'s fields
    passed one by one (``iws[EYE]``, ``iws[ZERO][0]``: the identity); returns n_a.

    Every array a Numba call receives (each field of a NamedTuple included) costs an atomic
    reference-count pair, so callers pass only the arrays needed.
    """
    na = relative_setup(path_node, path_sign, s, d, zr, zt, lt, robust_kind, robust_scale, rot,
                        trans, pr, pt, iws, ws, e, r, jri, a)
    rb = iws[EYE]
    tb = iws[ZERO][0]
    if na < d:
        rb = pr[na]
        tb = pt[na]
    relative_blocks(path_sign, s, d, rb, tb, pr, pt, a, ws, jac)
    return na


@kernel
def linearize(prob: Problem, c: int, rot: np.ndarray, trans: np.ndarray, wk: Workspace,
              jac: np.ndarray) -> tuple[int, int]:
    """Whitened Jacobian blocks ``jac[k, :kr, :]`` and residual ``wk.r[:kr]`` (= -L^T e0).

    Returns ``(kr, na)``: the number of rows (6 relative, 3 GPS) and of a-side domain nodes.
    Leaves the path products in ``wk.path_rot/path_trans``; for a relative constraint also
    ``e0`` in ``wk.e``, ``Jr^-1(e0)`` in ``wk.jri`` and ``L^T Jr^-1(e0)`` in ``wk.a``.
    """
    s, d = domain(prob, c)
    if not is_gps(prob, c):
        na = relative_linearization(prob.path_node, prob.path_sign, s, d, prob.edge_rot[c],
                                    prob.edge_trans[c], prob.edge_lt[c], prob.robust_kind,
                                    prob.robust_scale, rot, trans, wk.path_rot,
                                    wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a, jac)
        return 6, na
    na = path_products(prob, c, rot, trans, wk.path_rot, wk.path_trans)
    g = c - prob.num_edges
    gps_residual(wk.path_trans[0], prob.gps_pos[g], wk.e)  # the earth is the identity
    whiten_residual(prob.gps_lt[g], wk.e, 3, wk.r)
    _gps_blocks(prob, c, wk, jac)
    return 3, na


# --------------------------------------------------------------------------- J = s A_c Ad(Y)
@kernel
def relative_factor_into(a: np.ndarray, rb: np.ndarray, tb: np.ndarray, adb: np.ndarray,
                         out: np.ndarray) -> None:
    """``A_c = a Ad(Y_b)^-1`` of a relative constraint (``a = L^T Jr^-1(e)``, ``(rb, tb)`` the
    global pose ``Y_b``), so that ``J_{c,u} = s_{c,u} A_c Ad(Y_u)`` (the batch solve and the
    global correction use this factorization); ``adb`` (6, 6) scratch."""
    rinv = rb.T.copy()  # Ad(Y_b)^-1 = Ad(Y_b^-1)
    tinv = -(rinv @ tb)
    adjoint_into(rinv, tinv, adb)
    out[:] = a @ adb


@kernel
def gps_factor_into(lt: np.ndarray, pn: np.ndarray, blk: np.ndarray, out: np.ndarray) -> None:
    """``A_c = L^T [I | -[p_n]x]`` of a GPS reading on a node at ``pn`` (the earth is the root)
    into rows 0..2 of ``out``, as :func:`relative_factor_into`; ``blk`` (3, 6) scratch."""
    for i in range(3):
        for j in range(6):
            blk[i, j] = 0.0
        blk[i, i] = 1.0
    blk[0, 4] = pn[2]  # -[p_n]x
    blk[0, 5] = -pn[1]
    blk[1, 3] = -pn[2]
    blk[1, 5] = pn[0]
    blk[2, 3] = pn[1]
    blk[2, 4] = -pn[0]
    whiten_rows(lt, blk, 3, out)
