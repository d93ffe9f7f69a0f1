"""Interpolated solving (paper III-E, eq. 31-34; DESIGN.md §6).

A constraint whose domain has more than ``D_max`` nodes is solved for a subset ``S_c`` of at most
``D_max`` nodes, kept uniformly along each side of its path (the endpoints always kept).  For a
kept node b whose parent is omitted, the chain of tree links between b and its closest kept
ancestor a (or the constraint's root) is merged into one constraint β: measurement
``p_β = Π p_i`` (eq. 32), stiffness ``S_β = Σ R_{b,i} S_i R_{b,i}^T`` (eq. 33, expressed in b's
frame, where our errors live), and b's block of B is temporarily ``B - J_α^T J_α + J_β^T J_β``
(eq. 31).  The reduced system (eq. 34) is solved like a full update (Woodbury or Givens).  Each
kept node's pose change is then spread over its chain the way TORO does (TORO.md, last section):
the rotation about the single axis of b's rotation change, in the cumulative-weight profile,
first; the translation linearly on the re-bent chain after.  The weights are
``1 / min diag`` of each node's rotational and translational 3x3 block of 𝔅(H).
𝔅(H) itself is still updated over the whole domain (eq. 24), which needs the O(d)
linearization; only the solve is reduced.

Cost: besides the linearization and the 𝔅(H) update, the merged constraints cost O(1) scalar
work per omitted node (a 3x3 product and a rotated 6x6 information, eq. 32-33), the
distribution a rotation interpolation and a translation per node; nothing allocates (the
scratch lives in the :class:`~.problem.Workspace`).  Batches (III-G) use the same kernels
through :mod:`._batch`.
"""

from __future__ import annotations

import math

import numpy as np

from ..._cost import jr_inv_matrix, residual_and_jr_inv, retract_into
from ..._numba import kernel
from ...geometry._kernels import so3_log_into
from ._dense import regularized_factor
from ._linearize import linearize, relative_setup
from ._step import accumulate_path, linearize_accumulate, solve_single, step_temperature
from .problem import EYE, ZERO, Problem, State, Update, Workspace, domain, is_gps


# --------------------------------------------------------------------------- S_c
@kernel
def kept_positions(d: int, na: int, d_max: int, keep: np.ndarray) -> int:
    """Domain positions kept when solving for at most ``d_max`` of the d nodes.

    Each side (a side: positions ``0..na-1``, b side: ``na..d-1``, both listed from the
    endpoint upwards) gets a share of ``d_max`` proportional to its length (at least one node
    when it is not empty); within a side the kept nodes are spread uniformly from the endpoint
    to the top.  Returns the number kept, written in increasing position order.
    """
    nb = d - na
    ka = 0
    if na > 0:
        ka = max(1, min(na, (d_max * na + d // 2) // d))
        if nb > 0:
            ka = min(ka, d_max - 1)
    kb = min(nb, d_max - ka)
    n = 0
    for lo, length, k in ((0, na, ka), (na, nb, kb)):
        if k <= 0:
            continue
        if k == 1:
            keep[n] = lo
            n += 1
            continue
        prev = -1
        for j in range(k):
            p = lo + (j * (length - 1) + (k - 1) // 2) // (k - 1)
            if p > prev:
                keep[n] = p
                n += 1
                prev = p
    return n


@kernel
def chain_end(d: int, na: int, keep: np.ndarray, nk: int, j: int) -> int:
    """One past the last position of kept node j's chain: the next kept position on the same
    side (its closest kept ancestor), or the end of the side (the chain reaches the root)."""
    side_end = na if keep[j] < na else d
    if j + 1 < nk and keep[j + 1] < side_end:
        return int(keep[j + 1])
    return side_end



# --------------------------------------------------------------------------- eq. 31-33
# The kernels below never allocate and take a chain as ``nodes[start + n]``, n = 0 (b) ...
# k-1 (the top, a's child): a slice of a constraint's path (single updates) or nodes collected
# by walking up the tree (batches).
@kernel
def chain_measurement(link_c: np.ndarray, link_fwd: np.ndarray, edge_rot: np.ndarray,
                      edge_trans: np.ndarray, edge_lt: np.ndarray, gps_pos: np.ndarray,
                      gps_lt: np.ndarray, num_edges: int, rot: np.ndarray, nodes: np.ndarray,
                      start: int, k: int, zr: np.ndarray, zt: np.ndarray, s_beta: np.ndarray,
                      ws: np.ndarray, m: np.ndarray) -> None:
    """:func:`merged_constraint` with the problem's arrays passed one by one (``ws``, ``m``:
    unused scratch, kept for the signature).

    Everything per node lives in scalar locals (no store in the loop: the arrays a Numba kernel
    receives may alias, so a scratch array would be reloaded after every store): ``f..`` is
    ``F = R_{b, node}``, ``l..``/``u.`` the link's desired local transform, ``g..`` ``R_{b,
    parent}``, ``a..``/``b..`` the columns of ``M = L^T blockdiag(H, H)^T`` (H: the error
    frame), ``s..`` the upper triangle of ``S_β``.  ``p_β``'s rotation is ``F^T`` at the top
    (``F_n^T = l_n F_{n-1}^T`` is the product ``l_n ... l_1`` term by term, so it is not
    accumulated separately: the same products, summed in the same order).  Each entry of ``M^T
    M`` is summed from 0.0 over the rows of M that are not structurally zero (L^T is upper
    triangular: rows 3..5 vanish in columns 0..2; a GPS link has rows 0..2 only).
    """
    lt = edge_lt
    glt = gps_lt
    f00, f01, f02 = 1.0, 0.0, 0.0
    f10, f11, f12 = 0.0, 1.0, 0.0
    f20, f21, f22 = 0.0, 0.0, 1.0
    z0 = 0.0
    z1 = 0.0
    z2 = 0.0
    s00 = s01 = s02 = s03 = s04 = s05 = s11 = s12 = s13 = s14 = s15 = 0.0
    s22 = s23 = s24 = s25 = s33 = s34 = s35 = s44 = s45 = s55 = 0.0
    for n in range(k):
        node = nodes[start + n]
        c = link_c[node]
        gps = c >= num_edges
        forward = link_fwd[node] and not gps
        g = c - num_edges
        if gps:  # the GPS reading prescribes the position, the rotation stays the current one
            u0, u1, u2 = gps_pos[g, 0], gps_pos[g, 1], gps_pos[g, 2]
            l00, l01, l02 = rot[node, 0, 0], rot[node, 0, 1], rot[node, 0, 2]
            l10, l11, l12 = rot[node, 1, 0], rot[node, 1, 1], rot[node, 1, 2]
            l20, l21, l22 = rot[node, 2, 0], rot[node, 2, 1], rot[node, 2, 2]
        elif forward:
            u0, u1, u2 = edge_trans[c, 0], edge_trans[c, 1], edge_trans[c, 2]
            l00, l01, l02 = edge_rot[c, 0, 0], edge_rot[c, 0, 1], edge_rot[c, 0, 2]
            l10, l11, l12 = edge_rot[c, 1, 0], edge_rot[c, 1, 1], edge_rot[c, 1, 2]
            l20, l21, l22 = edge_rot[c, 2, 0], edge_rot[c, 2, 1], edge_rot[c, 2, 2]
        else:  # the inverse of the measurement
            e0, e1, e2 = edge_trans[c, 0], edge_trans[c, 1], edge_trans[c, 2]
            u0 = -(edge_rot[c, 0, 0] * e0 + edge_rot[c, 1, 0] * e1 + edge_rot[c, 2, 0] * e2)
            u1 = -(edge_rot[c, 0, 1] * e0 + edge_rot[c, 1, 1] * e1 + edge_rot[c, 2, 1] * e2)
            u2 = -(edge_rot[c, 0, 2] * e0 + edge_rot[c, 1, 2] * e1 + edge_rot[c, 2, 2] * e2)
            l00, l01, l02 = edge_rot[c, 0, 0], edge_rot[c, 1, 0], edge_rot[c, 2, 0]
            l10, l11, l12 = edge_rot[c, 0, 1], edge_rot[c, 1, 1], edge_rot[c, 2, 1]
            l20, l21, l22 = edge_rot[c, 0, 2], edge_rot[c, 1, 2], edge_rot[c, 2, 2]
        g00 = f00 * l00 + f01 * l01 + f02 * l02
        g01 = f00 * l10 + f01 * l11 + f02 * l12
        g02 = f00 * l20 + f01 * l21 + f02 * l22
        g10 = f10 * l00 + f11 * l01 + f12 * l02
        g11 = f10 * l10 + f11 * l11 + f12 * l12
        g12 = f10 * l20 + f11 * l21 + f12 * l22
        g20 = f20 * l00 + f21 * l01 + f22 * l02
        g21 = f20 * l10 + f21 * l11 + f22 * l12
        g22 = f20 * l20 + f21 * l21 + f22 * l22
        if forward:
            h00, h01, h02 = f00, f01, f02
            h10, h11, h12 = f10, f11, f12
            h20, h21, h22 = f20, f21, f22
        else:
            h00, h01, h02 = g00, g01, g02
            h10, h11, h12 = g10, g11, g12
            h20, h21, h22 = g20, g21, g22
        if gps:
            a00 = glt[g, 0, 0] * h00 + glt[g, 0, 1] * h01 + glt[g, 0, 2] * h02
            a01 = glt[g, 0, 0] * h10 + glt[g, 0, 1] * h11 + glt[g, 0, 2] * h12
            a02 = glt[g, 0, 0] * h20 + glt[g, 0, 1] * h21 + glt[g, 0, 2] * h22
            a10 = glt[g, 1, 0] * h00 + glt[g, 1, 1] * h01 + glt[g, 1, 2] * h02
            a11 = glt[g, 1, 0] * h10 + glt[g, 1, 1] * h11 + glt[g, 1, 2] * h12
            a12 = glt[g, 1, 0] * h20 + glt[g, 1, 1] * h21 + glt[g, 1, 2] * h22
            a20 = glt[g, 2, 0] * h00 + glt[g, 2, 1] * h01 + glt[g, 2, 2] * h02
            a21 = glt[g, 2, 0] * h10 + glt[g, 2, 1] * h11 + glt[g, 2, 2] * h12
            a22 = glt[g, 2, 0] * h20 + glt[g, 2, 1] * h21 + glt[g, 2, 2] * h22
            b00 = b01 = b02 = b10 = b11 = b12 = b20 = b21 = b22 = 0.0
            b30 = b31 = b32 = b40 = b41 = b42 = b50 = b51 = b52 = 0.0
        else:
            b00 = lt[c, 0, 3] * h00 + lt[c, 0, 4] * h01 + lt[c, 0, 5] * h02
            b01 = lt[c, 0, 3] * h10 + lt[c, 0, 4] * h11 + lt[c, 0, 5] * h12
            b02 = lt[c, 0, 3] * h20 + lt[c, 0, 4] * h21 + lt[c, 0, 5] * h22
            a00 = lt[c, 0, 0] * h00 + lt[c, 0, 1] * h01 + lt[c, 0, 2] * h02
            a01 = lt[c, 0, 0] * h10 + lt[c, 0, 1] * h11 + lt[c, 0, 2] * h12
            a02 = lt[c, 0, 0] * h20 + lt[c, 0, 1] * h21 + lt[c, 0, 2] * h22
            b10 = lt[c, 1, 3] * h00 + lt[c, 1, 4] * h01 + lt[c, 1, 5] * h02
            b11 = lt[c, 1, 3] * h10 + lt[c, 1, 4] * h11 + lt[c, 1, 5] * h12
            b12 = lt[c, 1, 3] * h20 + lt[c, 1, 4] * h21 + lt[c, 1, 5] * h22
            a10 = lt[c, 1, 0] * h00 + lt[c, 1, 1] * h01 + lt[c, 1, 2] * h02
            a11 = lt[c, 1, 0] * h10 + lt[c, 1, 1] * h11 + lt[c, 1, 2] * h12
            a12 = lt[c, 1, 0] * h20 + lt[c, 1, 1] * h21 + lt[c, 1, 2] * h22
            b20 = lt[c, 2, 3] * h00 + lt[c, 2, 4] * h01 + lt[c, 2, 5] * h02
            b21 = lt[c, 2, 3] * h10 + lt[c, 2, 4] * h11 + lt[c, 2, 5] * h12
            b22 = lt[c, 2, 3] * h20 + lt[c, 2, 4] * h21 + lt[c, 2, 5] * h22
            a20 = lt[c, 2, 0] * h00 + lt[c, 2, 1] * h01 + lt[c, 2, 2] * h02
            a21 = lt[c, 2, 0] * h10 + lt[c, 2, 1] * h11 + lt[c, 2, 2] * h12
            a22 = lt[c, 2, 0] * h20 + lt[c, 2, 1] * h21 + lt[c, 2, 2] * h22
            b30 = lt[c, 3, 3] * h00 + lt[c, 3, 4] * h01 + lt[c, 3, 5] * h02
            b31 = lt[c, 3, 3] * h10 + lt[c, 3, 4] * h11 + lt[c, 3, 5] * h12
            b32 = lt[c, 3, 3] * h20 + lt[c, 3, 4] * h21 + lt[c, 3, 5] * h22
            b40 = lt[c, 4, 3] * h00 + lt[c, 4, 4] * h01 + lt[c, 4, 5] * h02
            b41 = lt[c, 4, 3] * h10 + lt[c, 4, 4] * h11 + lt[c, 4, 5] * h12
            b42 = lt[c, 4, 3] * h20 + lt[c, 4, 4] * h21 + lt[c, 4, 5] * h22
            b50 = lt[c, 5, 3] * h00 + lt[c, 5, 4] * h01 + lt[c, 5, 5] * h02
            b51 = lt[c, 5, 3] * h10 + lt[c, 5, 4] * h11 + lt[c, 5, 5] * h12
            b52 = lt[c, 5, 3] * h20 + lt[c, 5, 4] * h21 + lt[c, 5, 5] * h22
        s00 += 0.0 + a00 * a00 + a10 * a10 + a20 * a20
        s01 += 0.0 + a00 * a01 + a10 * a11 + a20 * a21
        s02 += 0.0 + a00 * a02 + a10 * a12 + a20 * a22
        s03 += 0.0 + a00 * b00 + a10 * b10 + a20 * b20
        s04 += 0.0 + a00 * b01 + a10 * b11 + a20 * b21
        s05 += 0.0 + a00 * b02 + a10 * b12 + a20 * b22
        s11 += 0.0 + a01 * a01 + a11 * a11 + a21 * a21
        s12 += 0.0 + a01 * a02 + a11 * a12 + a21 * a22
        s13 += 0.0 + a01 * b00 + a11 * b10 + a21 * b20
        s14 += 0.0 + a01 * b01 + a11 * b11 + a21 * b21
        s15 += 0.0 + a01 * b02 + a11 * b12 + a21 * b22
        s22 += 0.0 + a02 * a02 + a12 * a12 + a22 * a22
        s23 += 0.0 + a02 * b00 + a12 * b10 + a22 * b20
        s24 += 0.0 + a02 * b01 + a12 * b11 + a22 * b21
        s25 += 0.0 + a02 * b02 + a12 * b12 + a22 * b22
        s33 += 0.0 + b00 * b00 + b10 * b10 + b20 * b20 + b30 * b30 + b40 * b40 + b50 * b50
        s34 += 0.0 + b00 * b01 + b10 * b11 + b20 * b21 + b30 * b31 + b40 * b41 + b50 * b51
        s35 += 0.0 + b00 * b02 + b10 * b12 + b20 * b22 + b30 * b32 + b40 * b42 + b50 * b52
        s44 += 0.0 + b01 * b01 + b11 * b11 + b21 * b21 + b31 * b31 + b41 * b41 + b51 * b51
        s45 += 0.0 + b01 * b02 + b11 * b12 + b21 * b22 + b31 * b32 + b41 * b42 + b51 * b52
        s55 += 0.0 + b02 * b02 + b12 * b12 + b22 * b22 + b32 * b32 + b42 * b42 + b52 * b52
        # p_β from b upwards: zt <- l zt + u; F <- G
        t0 = l00 * z0 + l01 * z1 + l02 * z2 + u0
        t1 = l10 * z0 + l11 * z1 + l12 * z2 + u1
        t2 = l20 * z0 + l21 * z1 + l22 * z2 + u2
        z0, z1, z2 = t0, t1, t2
        f00, f01, f02 = g00, g01, g02
        f10, f11, f12 = g10, g11, g12
        f20, f21, f22 = g20, g21, g22
    zt[0], zt[1], zt[2] = z0, z1, z2
    zr[0, 0], zr[0, 1], zr[0, 2] = f00, f10, f20
    zr[1, 0], zr[1, 1], zr[1, 2] = f01, f11, f21
    zr[2, 0], zr[2, 1], zr[2, 2] = f02, f12, f22
    s_beta[0, 0], s_beta[0, 1], s_beta[0, 2] = s00, s01, s02
    s_beta[0, 3], s_beta[0, 4], s_beta[0, 5] = s03, s04, s05
    s_beta[1, 1], s_beta[1, 2], s_beta[1, 3], s_beta[1, 4], s_beta[1, 5] = s11, s12, s13, s14, s15
    s_beta[2, 2], s_beta[2, 3], s_beta[2, 4], s_beta[2, 5] = s22, s23, s24, s25
    s_beta[3, 3], s_beta[3, 4], s_beta[3, 5] = s33, s34, s35
    s_beta[4, 4], s_beta[4, 5] = s44, s45
    s_beta[5, 5] = s55
    for i in range(6):
        for j in range(i):
            s_beta[i, j] = s_beta[j, i]


@kernel
def merged_constraint(prob: Problem, state: State, nodes: np.ndarray, start: int, k: int,
                      zr: np.ndarray, zt: np.ndarray, s_beta: np.ndarray, ws: np.ndarray,
                      m: np.ndarray) -> None:
    """The constraint β replacing the chain ``nodes[start]`` (= b) ... ``nodes[start+k-1]``.

    ``(zr, zt) = p_β``, the product of the links' desired transforms from the chain's top
    parent a down to b (eq. 32; a link is oriented parent -> child; a GPS link, which
    prescribes only a position, with the current local rotation); ``s_beta`` the stiffness
    Σ R_{b,i} S_i R_{b,i}^T in b's frame (eq. 33), ``R_{b,i}`` the desired rotation from link
    i's error frame to b (an error lives in the child's frame for a forward link, in the
    parent's for a reversed or GPS link).  Each term is added as ``M^T M``, ``M = L_i^T
    blockdiag(R, R)^T``.  One pass from b upwards, O(1) scalar work per node; the loop body is
    written out because calls that pass the problem's arrays cost more than the arithmetic.
    ``ws`` (>= 5, 3, 3), ``m`` (6, 6) scratch.
    """
    chain_measurement(prob.link_constraint, prob.link_forward, prob.edge_rot, prob.edge_trans,
                      prob.edge_lt, prob.gps_pos, prob.gps_lt, prob.num_edges, state.rot, nodes,
                      start, k, zr, zt, s_beta, ws, m)


@kernel
def merged_blocks(link_c: np.ndarray, link_fwd: np.ndarray, edge_rot: np.ndarray,
                  edge_trans: np.ndarray, edge_lt: np.ndarray, gps_pos: np.ndarray,
                  gps_lt: np.ndarray, num_edges: int, rot: np.ndarray, contrib: np.ndarray,
                  path_ptr: np.ndarray, nodes: np.ndarray, chains: np.ndarray, nch: int,
                  apr: np.ndarray, apt: np.ndarray, bpr: np.ndarray, bpt: np.ndarray,
                  out: np.ndarray, iws: np.ndarray, iws6: np.ndarray, ws: np.ndarray) -> None:
    """:func:`merged_block` for ``nch`` chains at once, with the arrays passed one by one
    (one call per update: every call costs a reference-count pair per array argument).

    Chain j is ``chains[j] = (start, k, ia, ib, io)``: nodes ``nodes[start:start + k]``, a's
    pose ``(apr[ia], apt[ia])`` (the identity when ``ia < 0``), b's ``(bpr[ib], bpt[ib])``,
    added into ``out[io]``.  ``iws``, ``iws6``, ``ws``: a workspace's fields of those names.
    """
    zr = iws[5]
    zt = iws[6][0]
    s_beta = iws6[0]
    jri = iws6[1]
    tm = iws6[2]
    e = iws6[3][0]
    for j in range(nch):
        start = chains[j, 0]
        k = chains[j, 1]
        ia = chains[j, 2]
        ib = chains[j, 3]
        io = chains[j, 4]
        chain_measurement(link_c, link_fwd, edge_rot, edge_trans, edge_lt, gps_pos, gps_lt,
                          num_edges, rot, nodes, start, k, zr, zt, s_beta, iws, tm)
        ra = iws[EYE] if ia < 0 else apr[ia]
        ta = iws[ZERO][0] if ia < 0 else apt[ia]
        residual_and_jr_inv(zr, zt, ra, ta, bpr[ib], bpt[ib], e, ws)
        jr_inv_matrix(ws, jri)
        for p in range(6):  # tm = S_β Jr^-1 (Jr^-1 is block upper triangular)
            for q in range(6):
                v = 0.0
                for m in range(6):
                    v += s_beta[p, m] * jri[m, q]
                tm[p, q] = v
        b = nodes[start]
        ob = path_ptr[link_c[b]]  # α's domain is {b}: its contribution is contrib[ob]
        for p in range(6):
            for q in range(p, 6):
                v = 0.0
                for m in range(6):
                    v += jri[m, p] * tm[m, q]
                out[io, p, q] += v - contrib[ob, p, q]
                if q != p:
                    out[io, q, p] += v - contrib[ob, q, p]


@kernel
def merged_block(prob: Problem, state: State, nodes: np.ndarray, start: int, k: int,
                 ra: np.ndarray, ta: np.ndarray, rb: np.ndarray, tb: np.ndarray,
                 out: np.ndarray, wk: Workspace) -> None:
    """Eq. 31 for kept node b = ``nodes[start]`` whose chain of k links is merged:
    ``out += J_β^T J_β - J_α^T J_α`` (α: b's tree link, whose last contribution is removed).

    ``(ra, ta)``, ``(rb, tb)``: current poses of the chain's top parent a and of b in a common
    frame.  ``J_β = L_β^T Jr^-1(e_β)``, ``e_β = Log(p_β^-1 T_{a,b})``, so
    ``J_β^T J_β = Jr^-T S_β Jr^-1``.  Scratch: ``wk.iws[0:7]``, ``wk.iws6``, ``wk.ws``.
    """
    chains = np.empty((1, 5), np.int64)
    chains[0, 0] = start
    chains[0, 1] = k
    chains[0, 2:] = 0
    merged_blocks(prob.link_constraint, prob.link_forward, prob.edge_rot, prob.edge_trans,
                  prob.edge_lt, prob.gps_pos, prob.gps_lt, prob.num_edges, state.rot,
                  state.contrib, prob.path_ptr, nodes, chains, 1, ra.reshape((1, 3, 3)),
                  ta.reshape((1, 3)), rb.reshape((1, 3, 3)), tb.reshape((1, 3)),
                  out.reshape((1, 6, 6)), wk.iws, wk.iws6, wk.ws)


@kernel
def reduced_factors(prob: Problem, state: State, c: int, d: int, na: int, kr: int,
                    wk: Workspace, keep: np.ndarray, nk: int, mu: float,
                    sub: Workspace) -> None:
    """B̃ (eq. 31) on the kept nodes, damped and factored into ``sub.lfac``; ``sub.jac`` gets
    the kept nodes' Jacobian blocks.  Must run right after ``accumulate_blocks`` (which updated
    𝔅(H) and c's contributions): ``B_c = 𝔅(H) - contribution of c`` at each kept node.
    ``sub.w`` holds B̃ until the solve overwrites it."""
    s = prob.path_ptr[c]
    jac = wk.jac
    pr = wk.path_rot
    pt = wk.path_trans
    bc = sub.w
    sjac = sub.jac
    bdiag = state.bdiag
    contrib = state.contrib
    path_node = prob.path_node
    chains = np.empty((nk, 5), np.int64)
    nch = 0
    for j in range(nk):
        p = keep[j]
        i = path_node[s + p]
        for q1 in range(6):
            for q2 in range(6):
                bc[j, q1, q2] = bdiag[i, q1, q2] - contrib[s + p, q1, q2]
                sjac[j, q1, q2] = jac[p, q1, q2]
        end = chain_end(d, na, keep, nk, j)
        if end - p > 1:  # b's parent is omitted: β replaces α
            chains[nch, 0] = s + p
            chains[nch, 1] = end - p
            chains[nch, 2] = end if end < (na if p < na else d) else -1  # a: kept, or the root
            chains[nch, 3] = p
            chains[nch, 4] = j
            nch += 1
    merged_blocks(prob.link_constraint, prob.link_forward, prob.edge_rot, prob.edge_trans,
                  prob.edge_lt, prob.gps_pos, prob.gps_lt, prob.num_edges, state.rot, contrib,
                  prob.path_ptr, path_node, chains, nch, pr, pt, pr, pt, bc, wk.iws, wk.iws6,
                  wk.ws)
    for j in range(nk):
        scale = 0.0
        for q in range(6):
            acc = 0.0
            for t in range(kr):
                acc += jac[keep[j], t, q] * jac[keep[j], t, q]
            scale += acc
        regularized_factor(bc[j], scale, mu, sub.lfac[j])


# --------------------------------------------------------------------------- distribution
@kernel
def distribution_weights(bdiag_block: np.ndarray) -> tuple[float, float]:
    """TORO's weights of a node: 1 / the smallest diagonal entry of the rotational and of the
    translational 3x3 block of 𝔅(H) (a tiny floor keeps a free node finite)."""
    wr = min(bdiag_block[3, 3], bdiag_block[4, 4], bdiag_block[5, 5])
    wt = min(bdiag_block[0, 0], bdiag_block[1, 1], bdiag_block[2, 2])
    return 1.0 / max(wr, 1e-300), 1.0 / max(wt, 1e-300)


@kernel
def node_weights(bdiag: np.ndarray, i: int) -> tuple[float, float]:
    """:func:`distribution_weights` of node i's block of 𝔅(H) (no view)."""
    wr = min(bdiag[i, 3, 3], bdiag[i, 4, 4], bdiag[i, 5, 5])
    wt = min(bdiag[i, 0, 0], bdiag[i, 1, 1], bdiag[i, 2, 2])
    return 1.0 / max(wr, 1e-300), 1.0 / max(wt, 1e-300)


@kernel
def distribute_chains(rot: np.ndarray, trans: np.ndarray, bdiag: np.ndarray,
                      nodes: np.ndarray, chains: np.ndarray, nch: int, apr: np.ndarray,
                      apt: np.ndarray, bpr: np.ndarray, bpt: np.ndarray, qr: np.ndarray,
                      cw: np.ndarray, ws: np.ndarray, ws6: np.ndarray) -> None:
    """:func:`distribute_chain` for ``nch`` chains at once (one call per update), the arrays
    passed one by one; no view per node.

    Chain j is ``chains[j] = (start, k, ia, ib)``: nodes ``nodes[start:start + k]``, a's pose
    ``(apr[ia], apt[ia])`` (the identity when ``ia < 0``), b's desired pose
    ``(bpr[ib], bpt[ib])``.  ``qr``, ``cw``, ``ws``, ``ws6``: a workspace's ``chain_rot``,
    ``chain_w``, ``iws``, ``iws6``.  Per node, the 3x3 products live in scalar locals (``v..``:
    the previous ``Q``, ``c..``/``q..`` the current one, ``x..`` the Rodrigues factor, ``m..``/
    ``g..`` the new local and its Gram matrix, symmetric: six entries).
    """
    dr = ws[0]
    dt = ws[1][0]
    mm = ws[5]
    phi6 = ws6[3][0]
    for jc in range(nch):
        start = chains[jc, 0]
        k = chains[jc, 1]
        ia = chains[jc, 2]
        ib = chains[jc, 3]
        ra = ws[EYE] if ia < 0 else apr[ia]
        ta = ws[ZERO][0] if ia < 0 else apt[ia]
        rb_new = bpr[ib]
        tb_new = bpt[ib]
        # 0. current rotations relative to a, Q_j (top down), and the cumulative weights
        for i in range(3):
            for j in range(3):
                qr[0, i, j] = 1.0 if i == j else 0.0
        cw[0, 0] = 0.0
        cw[0, 1] = 0.0
        v00, v01, v02 = 1.0, 0.0, 0.0
        v10, v11, v12 = 0.0, 1.0, 0.0
        v20, v21, v22 = 0.0, 0.0, 1.0
        for j in range(1, k + 1):
            i = nodes[start + k - j]
            q00 = v00 * rot[i, 0, 0] + v01 * rot[i, 1, 0] + v02 * rot[i, 2, 0]
            q01 = v00 * rot[i, 0, 1] + v01 * rot[i, 1, 1] + v02 * rot[i, 2, 1]
            q02 = v00 * rot[i, 0, 2] + v01 * rot[i, 1, 2] + v02 * rot[i, 2, 2]
            q10 = v10 * rot[i, 0, 0] + v11 * rot[i, 1, 0] + v12 * rot[i, 2, 0]
            q11 = v10 * rot[i, 0, 1] + v11 * rot[i, 1, 1] + v12 * rot[i, 2, 1]
            q12 = v10 * rot[i, 0, 2] + v11 * rot[i, 1, 2] + v12 * rot[i, 2, 2]
            q20 = v20 * rot[i, 0, 0] + v21 * rot[i, 1, 0] + v22 * rot[i, 2, 0]
            q21 = v20 * rot[i, 0, 1] + v21 * rot[i, 1, 1] + v22 * rot[i, 2, 1]
            q22 = v20 * rot[i, 0, 2] + v21 * rot[i, 1, 2] + v22 * rot[i, 2, 2]
            qr[j, 0, 0], qr[j, 0, 1], qr[j, 0, 2] = q00, q01, q02
            qr[j, 1, 0], qr[j, 1, 1], qr[j, 1, 2] = q10, q11, q12
            qr[j, 2, 0], qr[j, 2, 1], qr[j, 2, 2] = q20, q21, q22
            v00, v01, v02 = q00, q01, q02
            v10, v11, v12 = q10, q11, q12
            v20, v21, v22 = q20, q21, q22
            wr, wt = node_weights(bdiag, i)
            cw[j, 0] = cw[j - 1, 0] + wr
            cw[j, 1] = cw[j - 1, 1] + wt
        # b's desired pose relative to a
        for p in range(3):
            dt[p] = (ra[0, p] * (tb_new[0] - ta[0]) + ra[1, p] * (tb_new[1] - ta[1])
                     + ra[2, p] * (tb_new[2] - ta[2]))
            for q in range(3):
                dr[p, q] = (ra[0, p] * rb_new[0, q] + ra[1, p] * rb_new[1, q]
                            + ra[2, p] * rb_new[2, q])
        # rotation change of b in a's frame: Exp(phi) = R'_b Q_b^T
        for p in range(3):
            for q in range(3):
                mm[p, q] = dr[p, 0] * qr[k, q, 0] + dr[p, 1] * qr[k, q, 1] + dr[p, 2] * qr[k, q, 2]
        so3_log_into(mm, phi6)
        px, py, pz = phi6[3], phi6[4], phi6[5]
        th = math.sqrt(px * px + py * py + pz * pz)
        kx00, kx01, kx02 = 0.0, -pz, py
        kx10, kx11, kx12 = pz, 0.0, -px
        kx20, kx21, kx22 = -py, px, 0.0
        kk00 = kx00 * kx00 + kx01 * kx10 + kx02 * kx20
        kk01 = kx00 * kx01 + kx01 * kx11 + kx02 * kx21
        kk02 = kx00 * kx02 + kx01 * kx12 + kx02 * kx22
        kk10 = kx10 * kx00 + kx11 * kx10 + kx12 * kx20
        kk11 = kx10 * kx01 + kx11 * kx11 + kx12 * kx21
        kk12 = kx10 * kx02 + kx11 * kx12 + kx12 * kx22
        kk20 = kx20 * kx00 + kx21 * kx10 + kx22 * kx20
        kk21 = kx20 * kx01 + kx21 * kx11 + kx22 * kx21
        kk22 = kx20 * kx02 + kx21 * kx12 + kx22 * kx22
        # 1. rotations first: R''_j = Exp(f_j phi) Q_j (Rodrigues about the one axis); positions
        # re-bent with the old locals: t''_k = sum_j R''_{j-1} t_j
        w_r = cw[k, 0]
        t0 = 0.0
        t1 = 0.0
        t2 = 0.0
        v00, v01, v02 = 1.0, 0.0, 0.0
        v10, v11, v12 = 0.0, 1.0, 0.0
        v20, v21, v22 = 0.0, 0.0, 1.0
        for j in range(1, k + 1):
            i = nodes[start + k - j]
            t0 += v00 * trans[i, 0] + v01 * trans[i, 1] + v02 * trans[i, 2]
            t1 += v10 * trans[i, 0] + v11 * trans[i, 1] + v12 * trans[i, 2]
            t2 += v20 * trans[i, 0] + v21 * trans[i, 1] + v22 * trans[i, 2]
            if j == k:  # the end reaches its desired rotation exactly
                for p in range(3):
                    for q in range(3):
                        qr[k, p, q] = dr[p, q]
                break
            f = cw[j, 0] / w_r
            a_th = f * th
            if a_th < 1e-12:
                ca = f
                cb = 0.5 * f * f
            else:
                sh = math.sin(0.5 * a_th)
                ca = math.sin(a_th) / th
                cb = 2.0 * sh * sh / (th * th)
            x00 = 1.0 + ca * kx00 + cb * kk00
            x01 = 0.0 + ca * kx01 + cb * kk01
            x02 = 0.0 + ca * kx02 + cb * kk02
            x10 = 0.0 + ca * kx10 + cb * kk10
            x11 = 1.0 + ca * kx11 + cb * kk11
            x12 = 0.0 + ca * kx12 + cb * kk12
            x20 = 0.0 + ca * kx20 + cb * kk20
            x21 = 0.0 + ca * kx21 + cb * kk21
            x22 = 1.0 + ca * kx22 + cb * kk22
            c00, c01, c02 = qr[j, 0, 0], qr[j, 0, 1], qr[j, 0, 2]
            c10, c11, c12 = qr[j, 1, 0], qr[j, 1, 1], qr[j, 1, 2]
            c20, c21, c22 = qr[j, 2, 0], qr[j, 2, 1], qr[j, 2, 2]
            v00 = x00 * c00 + x01 * c10 + x02 * c20
            v01 = x00 * c01 + x01 * c11 + x02 * c21
            v02 = x00 * c02 + x01 * c12 + x02 * c22
            v10 = x10 * c00 + x11 * c10 + x12 * c20
            v11 = x10 * c01 + x11 * c11 + x12 * c21
            v12 = x10 * c02 + x11 * c12 + x12 * c22
            v20 = x20 * c00 + x21 * c10 + x22 * c20
            v21 = x20 * c01 + x21 * c11 + x22 * c21
            v22 = x20 * c02 + x21 * c12 + x22 * c22
            qr[j, 0, 0], qr[j, 0, 1], qr[j, 0, 2] = v00, v01, v02
            qr[j, 1, 0], qr[j, 1, 1], qr[j, 1, 2] = v10, v11, v12
            qr[j, 2, 0], qr[j, 2, 1], qr[j, 2, 2] = v20, v21, v22
        # 2. then translations, linearly along the re-bent chain; new locals, with one Newton
        # step towards the polar factor (as the retraction does): products along long chains
        # would otherwise let rounding grow
        e0 = dt[0] - t0
        e1 = dt[1] - t1
        e2 = dt[2] - t2
        w_t = cw[k, 1]
        v00, v01, v02 = 1.0, 0.0, 0.0
        v10, v11, v12 = 0.0, 1.0, 0.0
        v20, v21, v22 = 0.0, 0.0, 1.0
        for j in range(1, k + 1):
            i = nodes[start + k - j]
            g = (cw[j, 1] - cw[j - 1, 1]) / w_t
            c00, c01, c02 = qr[j, 0, 0], qr[j, 0, 1], qr[j, 0, 2]
            c10, c11, c12 = qr[j, 1, 0], qr[j, 1, 1], qr[j, 1, 2]
            c20, c21, c22 = qr[j, 2, 0], qr[j, 2, 1], qr[j, 2, 2]
            trans[i, 0] += g * (v00 * e0 + v10 * e1 + v20 * e2)
            trans[i, 1] += g * (v01 * e0 + v11 * e1 + v21 * e2)
            trans[i, 2] += g * (v02 * e0 + v12 * e1 + v22 * e2)
            m00 = v00 * c00 + v10 * c10 + v20 * c20
            m01 = v00 * c01 + v10 * c11 + v20 * c21
            m02 = v00 * c02 + v10 * c12 + v20 * c22
            m10 = v01 * c00 + v11 * c10 + v21 * c20
            m11 = v01 * c01 + v11 * c11 + v21 * c21
            m12 = v01 * c02 + v11 * c12 + v21 * c22
            m20 = v02 * c00 + v12 * c10 + v22 * c20
            m21 = v02 * c01 + v12 * c11 + v22 * c21
            m22 = v02 * c02 + v12 * c12 + v22 * c22
            g00 = m00 * m00 + m10 * m10 + m20 * m20
            g01 = m00 * m01 + m10 * m11 + m20 * m21
            g02 = m00 * m02 + m10 * m12 + m20 * m22
            g11 = m01 * m01 + m11 * m11 + m21 * m21
            g12 = m01 * m02 + m11 * m12 + m21 * m22
            g22 = m02 * m02 + m12 * m12 + m22 * m22
            rot[i, 0, 0] = 0.5 * (3.0 * m00 - (m00 * g00 + m01 * g01 + m02 * g02))
            rot[i, 0, 1] = 0.5 * (3.0 * m01 - (m00 * g01 + m01 * g11 + m02 * g12))
            rot[i, 0, 2] = 0.5 * (3.0 * m02 - (m00 * g02 + m01 * g12 + m02 * g22))
            rot[i, 1, 0] = 0.5 * (3.0 * m10 - (m10 * g00 + m11 * g01 + m12 * g02))
            rot[i, 1, 1] = 0.5 * (3.0 * m11 - (m10 * g01 + m11 * g11 + m12 * g12))
            rot[i, 1, 2] = 0.5 * (3.0 * m12 - (m10 * g02 + m11 * g12 + m12 * g22))
            rot[i, 2, 0] = 0.5 * (3.0 * m20 - (m20 * g00 + m21 * g01 + m22 * g02))
            rot[i, 2, 1] = 0.5 * (3.0 * m21 - (m20 * g01 + m21 * g11 + m22 * g12))
            rot[i, 2, 2] = 0.5 * (3.0 * m22 - (m20 * g02 + m21 * g12 + m22 * g22))
            v00, v01, v02 = c00, c01, c02
            v10, v11, v12 = c10, c11, c12
            v20, v21, v22 = c20, c21, c22


@kernel
def distribute_chain(state: State, nodes: np.ndarray, start: int, k: int, ra: np.ndarray,
                     ta: np.ndarray, rb_new: np.ndarray, tb_new: np.ndarray,
                     wk: Workspace) -> None:
    """Move the chain ``nodes[start]`` (= b) ... ``nodes[start+k-1]`` (the top) so that b
    reaches its desired pose relative to the chain's top parent a, TORO's way (DESIGN §6).

    ``(ra, ta)``: a's pose, ``(rb_new, tb_new)``: b's desired pose, in any common frame.  The
    locals of the chain nodes are rewritten; everything hanging below rides along.  In a's
    frame, with cumulative weight fractions ``f_j`` (rotation) and ``g_j`` (translation) from
    the top: ``R''_j = Exp(f_j phi) Q_j`` (``Exp(phi) = R_b^new Q_b^-1``, the end exact), the
    chain re-bent with the old local translations, then node j shifted by ``g_j`` times b's
    remaining position error.  So the new locals are ``R''_{j-1}^T R''_j`` (one Newton step
    towards orthonormal) and ``t_j + (g_j - g_{j-1}) R''_{j-1}^T dpos``.  O(k) scalar work, no
    allocation: ``wk.chain_rot``, ``wk.chain_w``, ``wk.iws[0:7]``, ``wk.iws6[3]``.
    """
    chains = np.empty((1, 4), np.int64)
    chains[0, 0] = start
    chains[0, 1] = k
    chains[0, 2:] = 0
    distribute_chains(state.rot, state.trans, state.bdiag, nodes, chains, 1,
                      ra.reshape((1, 3, 3)), ta.reshape((1, 3)), rb_new.reshape((1, 3, 3)),
                      tb_new.reshape((1, 3)), wk.chain_rot, wk.chain_w, wk.iws, wk.iws6)


@kernel
def distribute(prob: Problem, state: State, c: int, d: int, na: int, keep: np.ndarray,
               nk: int, x: np.ndarray, t: float, wk: Workspace) -> None:
    """Apply the reduced step ``t x`` (kept node j: ``x[j]``) by distributing each kept node's
    desired pose change over its chain (path products ``wk.path_rot/trans`` from before the
    step; the chains are disjoint, so they are moved one after the other)."""
    s = prob.path_ptr[c]
    pr = wk.path_rot
    pt = wk.path_trans
    iws = wk.iws
    er = iws[9]
    tmp = iws[10]
    path_node = prob.path_node
    rot = state.rot
    trans = state.trans
    chains = np.empty((nk, 4), np.int64)
    bnr = np.empty((nk, 3, 3))
    bnt = np.empty((nk, 3))
    nch = 0
    for j in range(nk):
        p = keep[j]
        end = chain_end(d, na, keep, nk, j)
        k = end - p
        if k == 1:  # nothing omitted: the plain update of b's local transform
            i = path_node[s + p]
            retract_into(rot[i], trans[i], x[j], t, rot[i], trans[i], er, tmp)
            continue
        # b's desired pose (root frame): P_b Exp(t x_b), as a full update would move it
        retract_into(pr[p], pt[p], x[j], t, bnr[nch], bnt[nch], er, tmp)
        chains[nch, 0] = s + p
        chains[nch, 1] = k
        chains[nch, 2] = end if end < (na if p < na else d) else -1  # a: kept, or the root
        chains[nch, 3] = nch
        nch += 1
    distribute_chains(rot, trans, state.bdiag, path_node, chains, nch, pr, pt, bnr, bnt,
                      wk.chain_rot, wk.chain_w, iws, wk.iws6)


# --------------------------------------------------------------------------- the update
@kernel
def relax_interpolated(prob: Problem, state: State, wk: Workspace, sub: Workspace,
                       keep: np.ndarray, c: int, tau: float, mu: float, step_kind: int,
                       d_max: int) -> int:
    """Relax constraint c solving for at most ``d_max`` of its domain nodes (paper III-E).

    ``wk`` must hold the whole domain, ``sub`` and ``keep`` ``d_max`` nodes.  Returns an
    ``Update`` like :func:`~._step.relax`.  Allocation-free apart from the solve's 6x6 scratch.
    """
    s, d = domain(prob, c)
    if is_gps(prob, c):
        kr, na = linearize(prob, c, state.rot, state.trans, wk, wk.jac)
        accumulate_path(prob.path_node, s, d, kr, wk.jac, state.bdiag, state.contrib, mu,
                        wk.lfac, wk.bc, False)
    else:
        kr = 6
        na = relative_setup(prob.path_node, prob.path_sign, s, d, prob.edge_rot[c],
                            prob.edge_trans[c], prob.edge_lt[c], prob.robust_kind,
                            prob.robust_scale, state.rot, state.trans, wk.path_rot,
                            wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a)
        nk = kept_positions(d, na, d_max, keep)  # only the kept nodes' blocks are stored
        linearize_accumulate(prob.path_node, prob.path_sign, s, d, na, wk.path_rot,
                             wk.path_trans, wk.a, wk.jac, False, keep, nk, state.bdiag,
                             state.contrib, mu, wk.lfac, wk.bc, False)
    nk = kept_positions(d, na, d_max, keep)
    reduced_factors(prob, state, c, d, na, kr, wk, keep, nk, mu, sub)
    for i in range(6):
        sub.r[i] = wk.r[i]
    solve_single(nk, kr, step_kind, sub)
    t, status = step_temperature(sub.x, nk, tau)
    if status == Update.REJECTED:
        return status
    distribute(prob, state, c, d, na, keep, nk, sub.x, t, wk)
    return status
