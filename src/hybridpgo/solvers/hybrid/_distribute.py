"""Distribution of a kept node's pose change over its chain (paper III-E), TORO's way.

After an interpolated solve (:mod:`._interpolate`, :mod:`._batch_reduced`) each kept node b has
a desired pose; the chain of omitted nodes between b and its closest kept ancestor a moves so
that b reaches it: the rotation about the single axis of b's rotation change, in the
cumulative-weight profile, first; the translation linearly on the re-bent chain after.  The
weights are ``1 / min diag`` of each node's rotational and translational 3x3 block of 𝔅(H).
A rotation interpolation and a translation per node; nothing allocates (the scratch lives in
the :class:`~.problem.Workspace`).
"""

from __future__ import annotations

import math

import numpy as np

from ..._numba import kernel
from ...geometry._kernels import so3_log_into
from .problem import EYE, ZERO, State, Workspace


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


# Long on purpose (speed): the three passes over a chain keep their 3x3 products in scalar
# locals; split into helpers they would pass arrays per node (a reference-count pair each).
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
    reaches its desired pose relative to the chain's top parent a, TORO's way
    (docs/mathematics.md#interpolated-solving).

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

