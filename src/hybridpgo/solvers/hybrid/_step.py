"""The hybrid Hessian step of one constraint (paper III-C, III-D, III-H;
docs/mathematics.md#hybrid-step).

𝔅(H) is the block diagonal of ``H = sum_c J_c^T J_c``; every constraint remembers the blocks it
last added (eq. 24), so relaxing c updates 𝔅(H) in O(d).  The step solves

    (J_c^T J_c + B_c) x_c = J_c^T r_c,      B_c = 𝔅(H) - 𝔅(J_c^T J_c)      (eq. 25/28)

either in Woodbury form (O(d), default) or by the paper's Givens triangularization (O(d^2)).
:func:`cap_and_apply` is the one place where a step is scaled by the temperature, capped at
pi/8 (III-H) and applied; single and batch updates both use it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..._cost import retract_into
from ..._numba import kernel
from ._dense import chol_inplace, regularized_factor
from ._linearize import linearize, relative_setup
from .problem import Problem, State, StepKind, Update, Workspace, domain, is_gps

#: Largest rotation (rad) any node may turn in one step (paper III-H).
MAX_ROTATION = math.pi / 8.0


@kernel
def accumulate_path(path_node: np.ndarray, s: int, d: int, kr: int, jac: np.ndarray,
                    bdiag: np.ndarray, contrib: np.ndarray, mu: float, lfac: np.ndarray,
                    bc: np.ndarray, factor: bool) -> None:
    """:func:`accumulate_blocks` for the domain ``path_node[s:s + d]`` with the arrays passed
    one by one (what the update kernels call: fewer arrays, fewer reference-count pairs)."""
    for k in range(d):
        i = path_node[s + k]
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
                if factor:
                    bc[p, q] = b_old - old
                    bc[q, p] = b_old - old
            scale += contrib[e, p, p]
        if factor:
            regularized_factor(bc, scale, mu, lfac[k])


# Long on purpose (speed): the hottest loop of a sweep, written out so that Ad(M_k), the 6x6
# Jacobian block and J^T J stay in scalar locals (no scratch array reloaded after a store).
@kernel
def linearize_accumulate(path_node: np.ndarray, path_sign: np.ndarray, s: int, d: int, na: int,
                         pr: np.ndarray, pt: np.ndarray, a: np.ndarray, jac: np.ndarray,
                         store_all: bool, keep: np.ndarray, nk: int, bdiag: np.ndarray,
                         contrib: np.ndarray, mu: float, lfac: np.ndarray, bc: np.ndarray,
                         factor: bool) -> None:
    """:func:`~._linearize.relative_blocks` and :func:`accumulate_path` of a relative constraint
    in one pass over its domain ``path_node[s:s + d]`` (n_a nodes on the a side; path products
    ``pr``, ``pt`` and ``a = L^T Jr^-1(e0)`` from :func:`~._linearize.relative_setup`).

    Each node's ``Ad(M_k)``, Jacobian block and ``J_k^T J_k`` stay in scalar locals: the same
    products summed in the same order as the two kernels (bit-identical; ``J^T J`` is formed
    before the sign ``s_k``, which squares away exactly), and no scratch array is reloaded after
    a store (Numba's arrays may alias).  ``jac[k]`` is stored for every k with ``store_all``,
    else only at the increasing positions ``keep[:nk]`` (interpolated solving needs the kept
    nodes' blocks only).  With ``factor`` the damped ``B_c`` block is factored into ``lfac[k]``.
    """
    rb00, rb01, rb02 = 1.0, 0.0, 0.0
    rb10, rb11, rb12 = 0.0, 1.0, 0.0
    rb20, rb21, rb22 = 0.0, 0.0, 1.0
    tb0, tb1, tb2 = 0.0, 0.0, 0.0
    if na < d:  # X_b in the root's frame (an empty b side: the root itself)
        rb00, rb01, rb02 = pr[na, 0, 0], pr[na, 0, 1], pr[na, 0, 2]
        rb10, rb11, rb12 = pr[na, 1, 0], pr[na, 1, 1], pr[na, 1, 2]
        rb20, rb21, rb22 = pr[na, 2, 0], pr[na, 2, 1], pr[na, 2, 2]
        tb0, tb1, tb2 = pt[na, 0], pt[na, 1], pt[na, 2]
    kp = 0
    for k in range(d):
        # Ad(M_k) = [[R, [m]x R], [0, R]], M_k = X_b^-1 X_k: R -> r.., [m]x R -> x..
        m0 = (rb00 * (pt[k, 0] - tb0) + rb10 * (pt[k, 1] - tb1)
              + rb20 * (pt[k, 2] - tb2))
        m1 = (rb01 * (pt[k, 0] - tb0) + rb11 * (pt[k, 1] - tb1)
              + rb21 * (pt[k, 2] - tb2))
        m2 = (rb02 * (pt[k, 0] - tb0) + rb12 * (pt[k, 1] - tb1)
              + rb22 * (pt[k, 2] - tb2))
        r00 = rb00 * pr[k, 0, 0] + rb10 * pr[k, 1, 0] + rb20 * pr[k, 2, 0]
        r01 = rb00 * pr[k, 0, 1] + rb10 * pr[k, 1, 1] + rb20 * pr[k, 2, 1]
        r02 = rb00 * pr[k, 0, 2] + rb10 * pr[k, 1, 2] + rb20 * pr[k, 2, 2]
        r10 = rb01 * pr[k, 0, 0] + rb11 * pr[k, 1, 0] + rb21 * pr[k, 2, 0]
        r11 = rb01 * pr[k, 0, 1] + rb11 * pr[k, 1, 1] + rb21 * pr[k, 2, 1]
        r12 = rb01 * pr[k, 0, 2] + rb11 * pr[k, 1, 2] + rb21 * pr[k, 2, 2]
        r20 = rb02 * pr[k, 0, 0] + rb12 * pr[k, 1, 0] + rb22 * pr[k, 2, 0]
        r21 = rb02 * pr[k, 0, 1] + rb12 * pr[k, 1, 1] + rb22 * pr[k, 2, 1]
        r22 = rb02 * pr[k, 0, 2] + rb12 * pr[k, 1, 2] + rb22 * pr[k, 2, 2]
        x00 = m1 * r20 - m2 * r10
        x10 = m2 * r00 - m0 * r20
        x20 = m0 * r10 - m1 * r00
        x01 = m1 * r21 - m2 * r11
        x11 = m2 * r01 - m0 * r21
        x21 = m0 * r11 - m1 * r01
        x02 = m1 * r22 - m2 * r12
        x12 = m2 * r02 - m0 * r22
        x22 = m0 * r12 - m1 * r02
        # the block without its sign s_k (J^T J does not depend on it)
        a0, a1, a2, a3, a4, a5 = a[0, 0], a[0, 1], a[0, 2], a[0, 3], a[0, 4], a[0, 5]
        j00 = a0 * r00 + a1 * r10 + a2 * r20
        j01 = a0 * r01 + a1 * r11 + a2 * r21
        j02 = a0 * r02 + a1 * r12 + a2 * r22
        j03 = a0 * x00 + a1 * x10 + a2 * x20 + a3 * r00 + a4 * r10 + a5 * r20
        j04 = a0 * x01 + a1 * x11 + a2 * x21 + a3 * r01 + a4 * r11 + a5 * r21
        j05 = a0 * x02 + a1 * x12 + a2 * x22 + a3 * r02 + a4 * r12 + a5 * r22
        a0, a1, a2, a3, a4, a5 = a[1, 0], a[1, 1], a[1, 2], a[1, 3], a[1, 4], a[1, 5]
        j10 = a0 * r00 + a1 * r10 + a2 * r20
        j11 = a0 * r01 + a1 * r11 + a2 * r21
        j12 = a0 * r02 + a1 * r12 + a2 * r22
        j13 = a0 * x00 + a1 * x10 + a2 * x20 + a3 * r00 + a4 * r10 + a5 * r20
        j14 = a0 * x01 + a1 * x11 + a2 * x21 + a3 * r01 + a4 * r11 + a5 * r21
        j15 = a0 * x02 + a1 * x12 + a2 * x22 + a3 * r02 + a4 * r12 + a5 * r22
        a0, a1, a2, a3, a4, a5 = a[2, 0], a[2, 1], a[2, 2], a[2, 3], a[2, 4], a[2, 5]
        j20 = a0 * r00 + a1 * r10 + a2 * r20
        j21 = a0 * r01 + a1 * r11 + a2 * r21
        j22 = a0 * r02 + a1 * r12 + a2 * r22
        j23 = a0 * x00 + a1 * x10 + a2 * x20 + a3 * r00 + a4 * r10 + a5 * r20
        j24 = a0 * x01 + a1 * x11 + a2 * x21 + a3 * r01 + a4 * r11 + a5 * r21
        j25 = a0 * x02 + a1 * x12 + a2 * x22 + a3 * r02 + a4 * r12 + a5 * r22
        a0, a1, a2, a3, a4, a5 = a[3, 0], a[3, 1], a[3, 2], a[3, 3], a[3, 4], a[3, 5]
        j30 = a0 * r00 + a1 * r10 + a2 * r20
        j31 = a0 * r01 + a1 * r11 + a2 * r21
        j32 = a0 * r02 + a1 * r12 + a2 * r22
        j33 = a0 * x00 + a1 * x10 + a2 * x20 + a3 * r00 + a4 * r10 + a5 * r20
        j34 = a0 * x01 + a1 * x11 + a2 * x21 + a3 * r01 + a4 * r11 + a5 * r21
        j35 = a0 * x02 + a1 * x12 + a2 * x22 + a3 * r02 + a4 * r12 + a5 * r22
        a0, a1, a2, a3, a4, a5 = a[4, 0], a[4, 1], a[4, 2], a[4, 3], a[4, 4], a[4, 5]
        j40 = a0 * r00 + a1 * r10 + a2 * r20
        j41 = a0 * r01 + a1 * r11 + a2 * r21
        j42 = a0 * r02 + a1 * r12 + a2 * r22
        j43 = a0 * x00 + a1 * x10 + a2 * x20 + a3 * r00 + a4 * r10 + a5 * r20
        j44 = a0 * x01 + a1 * x11 + a2 * x21 + a3 * r01 + a4 * r11 + a5 * r21
        j45 = a0 * x02 + a1 * x12 + a2 * x22 + a3 * r02 + a4 * r12 + a5 * r22
        a0, a1, a2, a3, a4, a5 = a[5, 0], a[5, 1], a[5, 2], a[5, 3], a[5, 4], a[5, 5]
        j50 = a0 * r00 + a1 * r10 + a2 * r20
        j51 = a0 * r01 + a1 * r11 + a2 * r21
        j52 = a0 * r02 + a1 * r12 + a2 * r22
        j53 = a0 * x00 + a1 * x10 + a2 * x20 + a3 * r00 + a4 * r10 + a5 * r20
        j54 = a0 * x01 + a1 * x11 + a2 * x21 + a3 * r01 + a4 * r11 + a5 * r21
        j55 = a0 * x02 + a1 * x12 + a2 * x22 + a3 * r02 + a4 * r12 + a5 * r22
        if store_all or (kp < nk and keep[kp] == k):
            kp += 1
            sg = float(path_sign[s + k])
            jac[k, 0, 0], jac[k, 0, 1], jac[k, 0, 2] = sg * j00, sg * j01, sg * j02
            jac[k, 0, 3], jac[k, 0, 4], jac[k, 0, 5] = sg * j03, sg * j04, sg * j05
            jac[k, 1, 0], jac[k, 1, 1], jac[k, 1, 2] = sg * j10, sg * j11, sg * j12
            jac[k, 1, 3], jac[k, 1, 4], jac[k, 1, 5] = sg * j13, sg * j14, sg * j15
            jac[k, 2, 0], jac[k, 2, 1], jac[k, 2, 2] = sg * j20, sg * j21, sg * j22
            jac[k, 2, 3], jac[k, 2, 4], jac[k, 2, 5] = sg * j23, sg * j24, sg * j25
            jac[k, 3, 0], jac[k, 3, 1], jac[k, 3, 2] = sg * j30, sg * j31, sg * j32
            jac[k, 3, 3], jac[k, 3, 4], jac[k, 3, 5] = sg * j33, sg * j34, sg * j35
            jac[k, 4, 0], jac[k, 4, 1], jac[k, 4, 2] = sg * j40, sg * j41, sg * j42
            jac[k, 4, 3], jac[k, 4, 4], jac[k, 4, 5] = sg * j43, sg * j44, sg * j45
            jac[k, 5, 0], jac[k, 5, 1], jac[k, 5, 2] = sg * j50, sg * j51, sg * j52
            jac[k, 5, 3], jac[k, 5, 4], jac[k, 5, 5] = sg * j53, sg * j54, sg * j55
        c00 = 0.0 + j00 * j00 + j10 * j10 + j20 * j20 + j30 * j30 + j40 * j40 + j50 * j50
        c01 = 0.0 + j00 * j01 + j10 * j11 + j20 * j21 + j30 * j31 + j40 * j41 + j50 * j51
        c02 = 0.0 + j00 * j02 + j10 * j12 + j20 * j22 + j30 * j32 + j40 * j42 + j50 * j52
        c03 = 0.0 + j00 * j03 + j10 * j13 + j20 * j23 + j30 * j33 + j40 * j43 + j50 * j53
        c04 = 0.0 + j00 * j04 + j10 * j14 + j20 * j24 + j30 * j34 + j40 * j44 + j50 * j54
        c05 = 0.0 + j00 * j05 + j10 * j15 + j20 * j25 + j30 * j35 + j40 * j45 + j50 * j55
        c11 = 0.0 + j01 * j01 + j11 * j11 + j21 * j21 + j31 * j31 + j41 * j41 + j51 * j51
        c12 = 0.0 + j01 * j02 + j11 * j12 + j21 * j22 + j31 * j32 + j41 * j42 + j51 * j52
        c13 = 0.0 + j01 * j03 + j11 * j13 + j21 * j23 + j31 * j33 + j41 * j43 + j51 * j53
        c14 = 0.0 + j01 * j04 + j11 * j14 + j21 * j24 + j31 * j34 + j41 * j44 + j51 * j54
        c15 = 0.0 + j01 * j05 + j11 * j15 + j21 * j25 + j31 * j35 + j41 * j45 + j51 * j55
        c22 = 0.0 + j02 * j02 + j12 * j12 + j22 * j22 + j32 * j32 + j42 * j42 + j52 * j52
        c23 = 0.0 + j02 * j03 + j12 * j13 + j22 * j23 + j32 * j33 + j42 * j43 + j52 * j53
        c24 = 0.0 + j02 * j04 + j12 * j14 + j22 * j24 + j32 * j34 + j42 * j44 + j52 * j54
        c25 = 0.0 + j02 * j05 + j12 * j15 + j22 * j25 + j32 * j35 + j42 * j45 + j52 * j55
        c33 = 0.0 + j03 * j03 + j13 * j13 + j23 * j23 + j33 * j33 + j43 * j43 + j53 * j53
        c34 = 0.0 + j03 * j04 + j13 * j14 + j23 * j24 + j33 * j34 + j43 * j44 + j53 * j54
        c35 = 0.0 + j03 * j05 + j13 * j15 + j23 * j25 + j33 * j35 + j43 * j45 + j53 * j55
        c44 = 0.0 + j04 * j04 + j14 * j14 + j24 * j24 + j34 * j34 + j44 * j44 + j54 * j54
        c45 = 0.0 + j04 * j05 + j14 * j15 + j24 * j25 + j34 * j35 + j44 * j45 + j54 * j55
        c55 = 0.0 + j05 * j05 + j15 * j15 + j25 * j25 + j35 * j35 + j45 * j45 + j55 * j55
        i = path_node[s + k]
        e = s + k
        o00 = contrib[e, 0, 0]
        b00 = bdiag[i, 0, 0]
        o01 = contrib[e, 0, 1]
        b01 = bdiag[i, 0, 1]
        o02 = contrib[e, 0, 2]
        b02 = bdiag[i, 0, 2]
        o03 = contrib[e, 0, 3]
        b03 = bdiag[i, 0, 3]
        o04 = contrib[e, 0, 4]
        b04 = bdiag[i, 0, 4]
        o05 = contrib[e, 0, 5]
        b05 = bdiag[i, 0, 5]
        o11 = contrib[e, 1, 1]
        b11 = bdiag[i, 1, 1]
        o12 = contrib[e, 1, 2]
        b12 = bdiag[i, 1, 2]
        o13 = contrib[e, 1, 3]
        b13 = bdiag[i, 1, 3]
        o14 = contrib[e, 1, 4]
        b14 = bdiag[i, 1, 4]
        o15 = contrib[e, 1, 5]
        b15 = bdiag[i, 1, 5]
        o22 = contrib[e, 2, 2]
        b22 = bdiag[i, 2, 2]
        o23 = contrib[e, 2, 3]
        b23 = bdiag[i, 2, 3]
        o24 = contrib[e, 2, 4]
        b24 = bdiag[i, 2, 4]
        o25 = contrib[e, 2, 5]
        b25 = bdiag[i, 2, 5]
        o33 = contrib[e, 3, 3]
        b33 = bdiag[i, 3, 3]
        o34 = contrib[e, 3, 4]
        b34 = bdiag[i, 3, 4]
        o35 = contrib[e, 3, 5]
        b35 = bdiag[i, 3, 5]
        o44 = contrib[e, 4, 4]
        b44 = bdiag[i, 4, 4]
        o45 = contrib[e, 4, 5]
        b45 = bdiag[i, 4, 5]
        o55 = contrib[e, 5, 5]
        b55 = bdiag[i, 5, 5]
        v = b00 + (c00 - o00)
        bdiag[i, 0, 0] = v
        contrib[e, 0, 0] = c00
        v = b01 + (c01 - o01)
        bdiag[i, 0, 1] = bdiag[i, 1, 0] = v
        contrib[e, 0, 1] = contrib[e, 1, 0] = c01
        v = b02 + (c02 - o02)
        bdiag[i, 0, 2] = bdiag[i, 2, 0] = v
        contrib[e, 0, 2] = contrib[e, 2, 0] = c02
        v = b03 + (c03 - o03)
        bdiag[i, 0, 3] = bdiag[i, 3, 0] = v
        contrib[e, 0, 3] = contrib[e, 3, 0] = c03
        v = b04 + (c04 - o04)
        bdiag[i, 0, 4] = bdiag[i, 4, 0] = v
        contrib[e, 0, 4] = contrib[e, 4, 0] = c04
        v = b05 + (c05 - o05)
        bdiag[i, 0, 5] = bdiag[i, 5, 0] = v
        contrib[e, 0, 5] = contrib[e, 5, 0] = c05
        v = b11 + (c11 - o11)
        bdiag[i, 1, 1] = v
        contrib[e, 1, 1] = c11
        v = b12 + (c12 - o12)
        bdiag[i, 1, 2] = bdiag[i, 2, 1] = v
        contrib[e, 1, 2] = contrib[e, 2, 1] = c12
        v = b13 + (c13 - o13)
        bdiag[i, 1, 3] = bdiag[i, 3, 1] = v
        contrib[e, 1, 3] = contrib[e, 3, 1] = c13
        v = b14 + (c14 - o14)
        bdiag[i, 1, 4] = bdiag[i, 4, 1] = v
        contrib[e, 1, 4] = contrib[e, 4, 1] = c14
        v = b15 + (c15 - o15)
        bdiag[i, 1, 5] = bdiag[i, 5, 1] = v
        contrib[e, 1, 5] = contrib[e, 5, 1] = c15
        v = b22 + (c22 - o22)
        bdiag[i, 2, 2] = v
        contrib[e, 2, 2] = c22
        v = b23 + (c23 - o23)
        bdiag[i, 2, 3] = bdiag[i, 3, 2] = v
        contrib[e, 2, 3] = contrib[e, 3, 2] = c23
        v = b24 + (c24 - o24)
        bdiag[i, 2, 4] = bdiag[i, 4, 2] = v
        contrib[e, 2, 4] = contrib[e, 4, 2] = c24
        v = b25 + (c25 - o25)
        bdiag[i, 2, 5] = bdiag[i, 5, 2] = v
        contrib[e, 2, 5] = contrib[e, 5, 2] = c25
        v = b33 + (c33 - o33)
        bdiag[i, 3, 3] = v
        contrib[e, 3, 3] = c33
        v = b34 + (c34 - o34)
        bdiag[i, 3, 4] = bdiag[i, 4, 3] = v
        contrib[e, 3, 4] = contrib[e, 4, 3] = c34
        v = b35 + (c35 - o35)
        bdiag[i, 3, 5] = bdiag[i, 5, 3] = v
        contrib[e, 3, 5] = contrib[e, 5, 3] = c35
        v = b44 + (c44 - o44)
        bdiag[i, 4, 4] = v
        contrib[e, 4, 4] = c44
        v = b45 + (c45 - o45)
        bdiag[i, 4, 5] = bdiag[i, 5, 4] = v
        contrib[e, 4, 5] = contrib[e, 5, 4] = c45
        v = b55 + (c55 - o55)
        bdiag[i, 5, 5] = v
        contrib[e, 5, 5] = c55
        if factor:
            bc[0, 0] = b00 - o00
            bc[0, 1] = bc[1, 0] = b01 - o01
            bc[0, 2] = bc[2, 0] = b02 - o02
            bc[0, 3] = bc[3, 0] = b03 - o03
            bc[0, 4] = bc[4, 0] = b04 - o04
            bc[0, 5] = bc[5, 0] = b05 - o05
            bc[1, 1] = b11 - o11
            bc[1, 2] = bc[2, 1] = b12 - o12
            bc[1, 3] = bc[3, 1] = b13 - o13
            bc[1, 4] = bc[4, 1] = b14 - o14
            bc[1, 5] = bc[5, 1] = b15 - o15
            bc[2, 2] = b22 - o22
            bc[2, 3] = bc[3, 2] = b23 - o23
            bc[2, 4] = bc[4, 2] = b24 - o24
            bc[2, 5] = bc[5, 2] = b25 - o25
            bc[3, 3] = b33 - o33
            bc[3, 4] = bc[4, 3] = b34 - o34
            bc[3, 5] = bc[5, 3] = b35 - o35
            bc[4, 4] = b44 - o44
            bc[4, 5] = bc[5, 4] = b45 - o45
            bc[5, 5] = b55 - o55
            scale = 0.0 + c00 + c11 + c22 + c33 + c44 + c55
            regularized_factor(bc, scale, mu, lfac[k])


@kernel
def accumulate_blocks(prob: Problem, state: State, c: int, kr: int, jac: np.ndarray,
                      mu: float, lfac: np.ndarray, bc: np.ndarray, factor: bool = True) -> None:
    """Eq. 23/24: B_c = 𝔅(H) - 𝔅(J_c^T J_c)_old; 𝔅(H) += new - old; factor the damped B_c
    into ``lfac`` (unless ``factor`` is False: interpolated solving factors its own blocks)."""
    s, d = domain(prob, c)
    accumulate_path(prob.path_node, s, d, kr, jac, state.bdiag, state.contrib, mu, lfac, bc,
                    factor)


@kernel
def woodbury_start(kr: int, smat: np.ndarray) -> None:
    """``S = I`` (its first ``kr`` rows; the rest zero) before :func:`woodbury_gather`."""
    for p in range(6):
        for q in range(6):
            smat[p, q] = 0.0
    for i in range(kr):
        smat[i, i] = 1.0


@kernel
def woodbury_gather(k0: int, k1: int, kr: int, jac: np.ndarray, lfac: np.ndarray,
                    y: np.ndarray, smat: np.ndarray) -> None:
    """Woodbury's first pass over the domain positions ``k0 <= k < k1``: ``W_k = L_k^-1 J_k^T``
    into ``y[k]`` and ``S += W_k^T W_k`` (upper triangle)."""
    for k in range(k0, k1):
        for i in range(6):
            inv = 1.0 / lfac[k, i, i]
            for q in range(kr):
                acc = jac[k, q, i]
                for m in range(i):
                    acc -= lfac[k, i, m] * y[k, m, q]
                y[k, i, q] = acc * inv
        for p in range(kr):
            for q in range(p, kr):
                acc = 0.0
                for i in range(6):
                    acc += y[k, i, p] * y[k, i, q]
                smat[p, q] += acc


@kernel
def woodbury_factor(kr: int, smat: np.ndarray, r: np.ndarray, sv: np.ndarray) -> bool:
    """Factor the gathered ``S`` in place and solve ``S z = r`` into ``sv[0]``; False when
    ``S`` is not positive definite."""
    for p in range(kr):
        for q in range(p):
            smat[p, q] = smat[q, p]
    if not chol_inplace(smat, kr):
        return False
    # S z = r, column by column as chol_solve_cols does (z in sv[0])
    for i in range(kr):
        acc = r[i]
        for m in range(i):
            acc -= smat[i, m] * sv[0, m]
        sv[0, i] = acc / smat[i, i]
    for i in range(kr - 1, -1, -1):
        acc = sv[0, i]
        for m in range(i + 1, kr):
            acc -= smat[m, i] * sv[0, m]
        sv[0, i] = acc / smat[i, i]
    return True


@kernel
def woodbury_spread(k0: int, k1: int, kr: int, lfac: np.ndarray, y: np.ndarray,
                    x: np.ndarray, sv: np.ndarray) -> None:
    """Woodbury's second pass over ``k0 <= k < k1``: ``x_k = L_k^-T W_k z``."""
    for k in range(k0, k1):
        for i in range(6):
            acc = 0.0
            for q in range(kr):
                acc += y[k, i, q] * sv[0, q]
            sv[1, i] = acc
        for i in range(5, -1, -1):  # L_k^T x_k = v (as solve_lt)
            acc = sv[1, i]
            for m in range(i + 1, 6):
                acc -= lfac[k, m, i] * x[k, m]
            x[k, i] = acc / lfac[k, i, i]


@kernel
def woodbury_solve(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray,
                   y: np.ndarray, x: np.ndarray, smat: np.ndarray, sv: np.ndarray) -> None:
    """x = B^-1 J^T (I + J B^-1 J^T)^-1 r with B = blockdiag(L_k L_k^T): O(d)
    (docs/mathematics.md#hybrid-step).

    With W_k = L_k^-1 J_k^T (forward substitution), S = I + sum_k W_k^T W_k and
    x_k = L_k^-T W_k S^-1 r.  ``y`` holds the W_k; ``smat`` (6, 6) and ``sv`` (2, 6) scratch.
    The two passes over the domain are :func:`woodbury_gather` and :func:`woodbury_spread`
    (a sliced update, :mod:`._slices`, runs them a range of positions at a time).
    """
    woodbury_start(kr, smat)
    woodbury_gather(0, d, kr, jac, lfac, y, smat)
    if not woodbury_factor(kr, smat, r, sv):
        for k in range(d):
            for i in range(6):
                x[k, i] = np.nan
        return
    woodbury_spread(0, d, kr, lfac, y, x, sv)


@kernel
def givens_solve(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray,
                 x: np.ndarray) -> None:
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
def step_temperature(x: np.ndarray, n: int, tau: float) -> tuple[float, int]:
    """The factor t a step ``x[:n]`` is applied with (paper III-H) and the outcome.

    ``t = tau``, or smaller so that the largest rotation of ``t x`` is exactly pi/8 (CAPPED);
    REJECTED when the step is not finite.
    """
    biggest = 0.0
    for k in range(n):
        for i in range(6):
            if not math.isfinite(x[k, i]):
                return 0.0, Update.REJECTED
        ang = math.sqrt(x[k, 3] ** 2 + x[k, 4] ** 2 + x[k, 5] ** 2)
        if ang > biggest:
            biggest = ang
    if tau * biggest > MAX_ROTATION:
        return MAX_ROTATION / biggest, Update.CAPPED
    return tau, Update.APPLIED


@kernel
def apply_step(nodes: np.ndarray, start: int, n: int, x: np.ndarray, tau: float,
               rot: np.ndarray, trans: np.ndarray, ws: np.ndarray) -> int:
    """:func:`cap_and_apply` with the state's arrays passed one by one."""
    t, status = step_temperature(x, n, tau)
    if status == Update.REJECTED:
        return status
    retract_nodes(nodes, start, n, x, t, rot, trans, ws)
    return status


@kernel
def retract_nodes(nodes: np.ndarray, start: int, n: int, x: np.ndarray, t: float,
                  rot: np.ndarray, trans: np.ndarray, ws: np.ndarray) -> None:
    """``T_i <- T_i Exp(t x_k)`` for ``i = nodes[start + k]``, k < n (``ws``: scratch)."""
    er = ws[0]
    tmp = ws[1]
    for k in range(n):
        i = nodes[start + k]
        retract_into(rot[i], trans[i], x[k], t, rot[i], trans[i], er, tmp)


@kernel
def cap_and_apply(nodes: np.ndarray, start: int, n: int, x: np.ndarray, tau: float,
                  state: State, ws: np.ndarray) -> int:
    """Apply ``T_i <- T_i Exp(t x_k)`` to ``i = nodes[start + k]``, k < n, with the factor t of
    :func:`step_temperature`.  Returns APPLIED, CAPPED, or REJECTED (nothing applied)."""
    return apply_step(nodes, start, n, x, tau, state.rot, state.trans, ws)


@kernel
def solve_single(d: int, kr: int, step_kind: int, wk: Workspace) -> None:
    """The step ``wk.x`` of eq. 25 from ``wk.jac``, ``wk.lfac``, ``wk.r`` (Woodbury or Givens;
    ``wk.bc`` is overwritten)."""
    if step_kind == StepKind.GIVENS:
        givens_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.x)
    else:
        woodbury_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.w, wk.x, wk.bc, wk.sv)


def _make_relax(with_gps: bool, step: int) -> Any:
    """The single update of one variant: ``with_gps`` compiles the GPS linearization in (a
    graph without GPS readings never reaches it); ``step`` is ``StepKind.WOODBURY`` or
    ``GIVENS`` to compile that solve only (its ``step_kind`` argument is then ignored), -1 to
    choose by ``step_kind`` at run time.  Closure constants: Numba prunes the dead branches
    before typing, so each variant compiles only its own callees (``sweep`` variants)."""
    givens_only = step == StepKind.GIVENS
    by_argument = step < 0

    def relax_variant(prob: Problem, state: State, wk: Workspace, c: int, tau: float,
                      mu: float, step_kind: int, apply: bool) -> int:
        s, d = domain(prob, c)
        if d == 0:
            return Update.APPLIED
        if with_gps and is_gps(prob, c):
            kr = linearize(prob, c, state.rot, state.trans, wk, wk.jac)[0]
            accumulate_path(prob.path_node, s, d, kr, wk.jac, state.bdiag, state.contrib, mu,
                            wk.lfac, wk.bc, True)
        else:
            kr = 6
            na = relative_setup(prob.path_node, prob.path_sign, s, d, prob.edge_rot[c],
                                prob.edge_trans[c], prob.edge_lt[c], prob.robust_kind,
                                prob.robust_scale, state.rot, state.trans, wk.path_rot,
                                wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a)
            linearize_accumulate(prob.path_node, prob.path_sign, s, d, na, wk.path_rot,
                                 wk.path_trans, wk.a, wk.jac, True, prob.path_ptr, 0,
                                 state.bdiag, state.contrib, mu, wk.lfac, wk.bc, True)
        if not apply:
            return Update.APPLIED
        if givens_only or (by_argument and step_kind == StepKind.GIVENS):
            givens_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.x)
        else:
            woodbury_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.w, wk.x, wk.bc, wk.sv)
        return apply_step(prob.path_node, s, d, wk.x, tau, state.rot, state.trans, wk.ws)

    relax_variant.__qualname__ = relax_variant.__name__ = (
        "relax" + ("_gps" if with_gps else "")
        + ("_givens" if givens_only else "" if by_argument else "_woodbury"))
    return kernel(relax_variant)


#: Single updates that compile one solve, by ``(with_gps, step kind)`` (the sweep variants').
#: -1 (the key ``(with_gps, -1)``): the solve chosen by ``step_kind`` at run time, both compiled.
BY_ARGUMENT = -1
RELAX = {(g, int(k)): _make_relax(g, int(k)) for g in (False, True)
         for k in (StepKind.WOODBURY, StepKind.GIVENS, BY_ARGUMENT)}

#: Relax constraint c (paper eq. 25): linearize, update 𝔅(H), solve, apply ``tau x``.  With
#: ``apply=False`` only 𝔅(H) and c's contributions are updated.  Returns an ``Update``.  Every
#: branch compiled in (GPS readings, the solve chosen by ``step_kind``): the budgeted loop's;
#: the sweeps use the :data:`RELAX` variant they need (the same arithmetic).
relax = RELAX[True, BY_ARGUMENT]
