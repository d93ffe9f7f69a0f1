"""Kernels of SE-Sync's objective F (:mod:`hybridpgo.certificate`): its value, gradient and
Newton Hessian summed over the constraints, one pass each; the staircase's retraction
(:func:`polar_rows`).

Per constraint ``c = (a, b)`` with weights ``w_r`` (rotation) and ``w_t`` (translation),
``F_c = w_r ||R_b - R_a Rm||_F^2 + w_t ||t_b - t_a - R_a tm||^2`` over the parameters
``[position shift (world frame), rotation]`` of pose a then pose b (3D: ``R Exp(omega)``; 2D
complex: ``z exp(i theta)``).  The kernels add ``2 ge`` (the half-gradient ``ge``) into the
two poses' rows of ``grad`` and, with ``hessian``, ``2 he`` (the half-Hessian ``he``: the
Gauss-Newton part plus the residuals' curvature along the rotation parameters) into the four
blocks of a sparse block pattern given by ``where`` (4, M): the block of (a, a), (a, b),
(b, a), (b, b), or -1 for a pose held out of the system.  The formulas are those of
:meth:`hybridpgo.certificate.SyncProblem.newton_system` (its tests compare them with finite
differences).  Each returns ``(F, rounding)``: ``rounding`` is the sum of
``w_t |r_t| (|t_a| + |t_b| + |tm|)``, the scale of F's rounding error beyond F itself.
"""

from __future__ import annotations

import numpy as np

from ._numba import kernel


@kernel
def _pair_into(m: np.ndarray, out: np.ndarray, at: int, sign: float) -> None:
    """``out[at:at+3] = sign <M, hat(e_k)>`` (twice the axial vector of M's antisymmetric
    part)."""
    out[at] = sign * (m[2, 1] - m[1, 2])
    out[at + 1] = sign * (m[0, 2] - m[2, 0])
    out[at + 2] = sign * (m[1, 0] - m[0, 1])


@kernel
def _add_blocks(e: int, pp: int, where: np.ndarray, he: np.ndarray, blocks: np.ndarray) -> None:
    """``2 he``'s four (pp, pp) parts into their blocks of the pattern."""
    for q in range(4):
        k = where[q, e]
        if k < 0:
            continue
        r0 = pp * (q // 2)
        c0 = pp * (q % 2)
        for r in range(pp):
            for c in range(pp):
                blocks[k, r, c] += 2.0 * he[r0 + r, c0 + c]


@kernel
def sync_terms_3d(rot: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray,
                  wr: np.ndarray, wt: np.ndarray, rm: np.ndarray, tm: np.ndarray,
                  where: np.ndarray, hessian: bool, grad: np.ndarray,
                  blocks: np.ndarray) -> tuple[float, float]:
    """F of 3D rotations ``rot`` (N, 3, 3) and positions ``t`` (N, 3); adds its gradient into
    ``grad`` (N, 6) and, with ``hessian``, its Newton Hessian into ``blocks`` (nb, 6, 6)."""
    f = 0.0
    rounding = 0.0
    rr = np.empty((3, 3))
    rt = np.empty(3)
    ma = np.empty((3, 3))
    mb = np.empty((3, 3))
    tmp = np.empty((3, 3))
    jta = np.empty((3, 3))
    pab = np.empty((3, 3))
    q = np.empty((3, 3))
    v = np.empty(3)
    gen = np.zeros((3, 3, 3))
    gen[0, 2, 1], gen[0, 1, 2] = 1.0, -1.0
    gen[1, 0, 2], gen[1, 2, 0] = 1.0, -1.0
    gen[2, 1, 0], gen[2, 0, 1] = 1.0, -1.0
    ge = np.empty(12)
    he = np.empty((12, 12))
    pv = np.empty(3)
    for e in range(a.shape[0]):
        i = a[e]
        j = b[e]
        w1 = wr[e]
        w2 = wt[e]
        for r in range(3):
            s = 0.0
            for k in range(3):
                s += rot[i, r, k] * tm[e, k]
            rt[r] = t[j, r] - t[i, r] - s
            for c in range(3):
                s = 0.0
                for k in range(3):
                    s += rot[i, r, k] * rm[e, k, c]
                rr[r, c] = rot[j, r, c] - s
        fr = 0.0
        ft = 0.0
        for r in range(3):
            ft += rt[r] * rt[r]
            for c in range(3):
                fr += rr[r, c] * rr[r, c]
        f += w1 * fr + w2 * ft
        na = 0.0
        nb = 0.0
        nm = 0.0
        for r in range(3):
            na += t[i, r] * t[i, r]
            nb += t[j, r] * t[j, r]
            nm += tm[e, r] * tm[e, r]
        rounding += w2 * np.sqrt(ft) * (np.sqrt(na) + np.sqrt(nb) + np.sqrt(nm))
        # mb = w_r R_b^T r_R;  ma = w_r R_a^T r_R Rm^T + w_t (R_a^T r_t) tm^T
        for r in range(3):
            s = 0.0
            for k in range(3):
                s += rot[i, k, r] * rt[k]
            v[r] = s
            for c in range(3):
                s1 = 0.0
                s2 = 0.0
                for k in range(3):
                    s1 += rot[j, k, r] * rr[k, c]
                    s2 += rot[i, k, r] * rr[k, c]
                mb[r, c] = w1 * s1
                tmp[r, c] = s2
        for r in range(3):
            for c in range(3):
                s = 0.0
                for k in range(3):
                    s += tmp[r, k] * rm[e, c, k]
                ma[r, c] = w1 * s + w2 * v[r] * tm[e, c]
        for r in range(3):
            ge[r] = -w2 * rt[r]
            ge[6 + r] = w2 * rt[r]
        _pair_into(ma, ge, 3, -1.0)
        _pair_into(mb, ge, 9, 1.0)
        for k in range(6):
            grad[i, k] += 2.0 * ge[k]
            grad[j, k] += 2.0 * ge[6 + k]
        if not hessian:
            continue
        he[:, :] = 0.0
        # jta = R_a hat(tm): d r_t / d omega_a
        for r in range(3):
            jta[r, 0] = rot[i, r, 1] * tm[e, 2] - rot[i, r, 2] * tm[e, 1]
            jta[r, 1] = rot[i, r, 2] * tm[e, 0] - rot[i, r, 0] * tm[e, 2]
            jta[r, 2] = rot[i, r, 0] * tm[e, 1] - rot[i, r, 1] * tm[e, 0]
        for r in range(3):
            he[r, r] = w2
            he[6 + r, 6 + r] = w2
            he[r, 6 + r] = -w2
            he[6 + r, r] = -w2
            for c in range(3):
                he[r, 3 + c] = -w2 * jta[r, c]
                he[6 + r, 3 + c] = w2 * jta[r, c]
                he[3 + c, r] = -w2 * jta[r, c]
                he[3 + c, 6 + r] = w2 * jta[r, c]
        # rotation blocks: 2 w_r I (+ w_t jta^T jta for a), curvature sym(M) - tr(M) I
        tra = ma[0, 0] + ma[1, 1] + ma[2, 2]
        trb = mb[0, 0] + mb[1, 1] + mb[2, 2]
        for r in range(3):
            for c in range(3):
                s = 0.0
                for k in range(3):
                    s += jta[k, r] * jta[k, c]
                he[3 + r, 3 + c] = w2 * s - 0.5 * (ma[r, c] + ma[c, r])
                he[9 + r, 9 + c] = 0.5 * (mb[r, c] + mb[c, r])
            he[3 + r, 3 + r] += 2.0 * w1 + tra
            he[9 + r, 9 + r] += 2.0 * w1 - trb
        # he[a_k, b_l] = -w_r <hat(e_k), P hat(e_l) Rm^T>, P = R_a^T R_b
        for r in range(3):
            for c in range(3):
                s = 0.0
                for k in range(3):
                    s += rot[i, k, r] * rot[j, k, c]
                pab[r, c] = s
        for ll in range(3):
            for r in range(3):
                for c in range(3):
                    s = 0.0
                    for k in range(3):
                        s += pab[r, k] * gen[ll, k, c]
                    tmp[r, c] = s
            for r in range(3):
                for c in range(3):
                    s = 0.0
                    for k in range(3):
                        s += tmp[r, k] * rm[e, c, k]
                    q[r, c] = s
            _pair_into(q, pv, 0, 1.0)
            for k in range(3):
                he[3 + k, 9 + ll] = -w1 * pv[k]
                he[9 + ll, 3 + k] = -w1 * pv[k]
        _add_blocks(e, 6, where, he, blocks)
    return f, rounding


@kernel
def sync_terms_2d(z: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray,
                  wr: np.ndarray, wt: np.ndarray, rz: np.ndarray, tz: np.ndarray,
                  where: np.ndarray, hessian: bool, grad: np.ndarray,
                  blocks: np.ndarray) -> tuple[float, float]:
    """F of planar rotations ``z`` (N,) and positions ``t`` (N,), both complex, with
    measurements ``rz``, ``tz`` (M,) complex; adds its gradient over ``[x, y, theta]`` into
    ``grad`` (N, 3) and, with ``hessian``, its Newton Hessian into ``blocks`` (nb, 3, 3)."""
    f = 0.0
    rounding = 0.0
    jr = np.zeros(6, np.complex128)
    jt = np.zeros(6, np.complex128)
    jt[0], jt[1], jt[3], jt[4] = -1.0, -1.0j, 1.0, 1.0j
    he = np.empty((6, 6))
    for e in range(a.shape[0]):
        i = a[e]
        j = b[e]
        w1 = wr[e]
        w2 = wt[e]
        za = z[i]
        zb = z[j]
        r_r = zb - za * rz[e]
        r_t = t[j] - t[i] - za * tz[e]
        f += w1 * (r_r.real * r_r.real + r_r.imag * r_r.imag) + w2 * (
            r_t.real * r_t.real + r_t.imag * r_t.imag)
        rounding += w2 * abs(r_t) * (abs(t[i]) + abs(t[j]) + abs(tz[e]))
        jr[2] = -1.0j * za * rz[e]
        jr[5] = 1.0j * zb
        jt[2] = -1.0j * za * tz[e]
        for k in range(6):
            g = w1 * (jr[k].conjugate() * r_r).real + w2 * (jt[k].conjugate() * r_t).real
            if k < 3:
                grad[i, k] += 2.0 * g
            else:
                grad[j, k - 3] += 2.0 * g
        if not hessian:
            continue
        for k in range(6):
            for ll in range(6):
                he[k, ll] = (w1 * (jr[k].conjugate() * jr[ll]).real
                             + w2 * (jt[k].conjugate() * jt[ll]).real)
        # second derivatives along theta: z_b -> -z_b, -z_a rm -> z_a rm, -z_a tm -> z_a tm
        he[2, 2] += (w1 * (r_r.conjugate() * za * rz[e]).real
                     + w2 * (r_t.conjugate() * za * tz[e]).real)
        he[5, 5] -= w1 * (r_r.conjugate() * zb).real
        _add_blocks(e, 3, where, he, blocks)
    return f, rounding


#: :func:`polar_rows`: a block whose ``det(X X^T)`` is below this times ``(tr(X X^T) / 3)^3`` is
#: left to the SVD: its rows nearly dependent, ``X X^T`` would lose the polar factor's digits
#: (above it the iteration agrees with the SVD to rounding, tests/test_certificate.py).
POLAR_SINGULAR = 1e-4
#: :func:`polar_rows`: steps after which a block still moving is left to the SVD (a block of
#: full rank converges in fewer than 60 from any scale).
_POLAR_STEPS = 100
#: :func:`polar_rows`: the iteration is scaled while its change exceeds this (relative).
_POLAR_SCALED = 1e-2
#: :func:`polar_rows`: once a change is below this (relative), one more step reaches rounding.
_POLAR_CLOSE = 1e-8


@kernel
def polar_rows(v: np.ndarray, out: np.ndarray, ok: np.ndarray) -> None:
    """The polar factor ``U = (X X^T)^-1/2 X`` of each (3, p) block X of ``v`` (n, 3, p): the
    nearest matrix with orthonormal rows (what the SVD gives as ``u @ vh``), into ``out``.

    Newton's iteration ``X <- (g X + (X X^T)^-1 X / g) / 2`` (Higham, "Functions of
    Matrices", 8.3), with the determinant scaling ``g = det(X X^T)^(-1/6)`` while the steps are
    large: quadratic convergence from any block of full row rank.  ``ok[i]`` is False where
    block i has nearly dependent rows (:data:`POLAR_SINGULAR`), is not finite, or still moves
    after :data:`_POLAR_STEPS` steps: those are left to the caller (the SVD)."""
    n = v.shape[0]
    p = v.shape[2]
    x = np.empty((3, p))
    y = np.empty((3, p))
    for i in range(n):
        for r in range(3):
            for c in range(p):
                x[r, c] = v[i, r, c]
        ok[i] = False
        scaled = True
        for _ in range(_POLAR_STEPS):
            g00 = g01 = g02 = g11 = g12 = g22 = 0.0
            for c in range(p):
                g00 += x[0, c] * x[0, c]
                g01 += x[0, c] * x[1, c]
                g02 += x[0, c] * x[2, c]
                g11 += x[1, c] * x[1, c]
                g12 += x[1, c] * x[2, c]
                g22 += x[2, c] * x[2, c]
            # the adjugate of the symmetric G
            a00 = g11 * g22 - g12 * g12
            a01 = g02 * g12 - g01 * g22
            a02 = g01 * g12 - g02 * g11
            a11 = g00 * g22 - g02 * g02
            a12 = g01 * g02 - g00 * g12
            a22 = g00 * g11 - g01 * g01
            det = g00 * a00 + g01 * a01 + g02 * a02
            tr = (g00 + g11 + g22) / 3.0
            if not det > POLAR_SINGULAR * tr * tr * tr:  # NaN and inf blocks too
                break
            gam = det ** (-1.0 / 6.0) if scaled else 1.0
            h = 0.5 / (gam * det)
            change = 0.0
            size = 0.0
            for c in range(p):
                x0 = x[0, c]
                x1 = x[1, c]
                x2 = x[2, c]
                y[0, c] = 0.5 * gam * x0 + h * (a00 * x0 + a01 * x1 + a02 * x2)
                y[1, c] = 0.5 * gam * x1 + h * (a01 * x0 + a11 * x1 + a12 * x2)
                y[2, c] = 0.5 * gam * x2 + h * (a02 * x0 + a12 * x1 + a22 * x2)
                for r in range(3):
                    change = max(change, abs(y[r, c] - x[r, c]))
                    size = max(size, abs(y[r, c]))
            for r in range(3):
                for c in range(p):
                    x[r, c] = y[r, c]
            if change <= _POLAR_CLOSE * size:
                if not scaled:  # the step after a change this small reaches rounding
                    ok[i] = True
                    break
                scaled = False
                continue
            scaled = scaled and change > _POLAR_SCALED * size
        if ok[i]:
            for r in range(3):
                for c in range(p):
                    out[i, r, c] = x[r, c]
