"""Merged chains (paper III-E, eq. 31-33): a chain of omitted nodes as one constraint.

When an update solves for a subset of its nodes (:mod:`._interpolate`, :mod:`._batch_reduced`),
the chain of tree links between a kept node b and its closest kept ancestor a (or the
constraint's root) is merged into one constraint β: measurement ``p_β = Π p_i`` (eq. 32),
stiffness ``S_β = Σ R_{b,i} S_i R_{b,i}^T`` (eq. 33, expressed in b's frame, where our errors
live), and b's block of B is temporarily ``B - J_α^T J_α + J_β^T J_β`` (eq. 31).  O(1) scalar
work per omitted node (a 3x3 product and a rotated 6x6 information).

The kernels never allocate and take a chain as ``nodes[start + n]``, n = 0 (b) ... k-1 (the
top, a's child): a slice of a constraint's path (single updates) or nodes collected by walking
up the tree (batches).
"""

from __future__ import annotations

import numpy as np

from ..._cost import jr_inv_matrix, residual_and_jr_inv
from ..._numba import kernel
from .problem import EYE, ZERO, Problem, State, Workspace


# Long on purpose (speed): one pass per chain with every per-node product in scalar locals; a
# helper per step would pass arrays (a reference-count pair each) and reload them after stores.
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

