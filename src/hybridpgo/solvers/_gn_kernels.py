"""Numba kernels of the exact solver (DESIGN.md §1, §7).

Global parametrization, right perturbation ``X_i <- X_i Exp(delta_i)``, tangent order (rho, phi):

* relative constraint: ``e = Log(Z^-1 X_a^-1 X_b)``, ``de/d delta_b = Jr^-1(e)``,
  ``de/d delta_a = -Jr^-1(e) Ad(X_b^-1 X_a)``;
* position constraint: ``e = p_n - g``, ``de/d delta_n = [R_n | 0]``.

The normal equations ``H = J^T Omega J``, ``g = J^T Omega e`` are written straight into the value
array of a CSC matrix whose pattern was computed once (the "analyze" step in
:mod:`hybridpgo.solvers.gauss_newton`).  Each 6x6 block ``(row i, col j)`` of H is addressed by a
*slot*: entry ``(p, q)`` of the block lives at ``data[base + q * stride + p]``.

The per-constraint maths are allocation-free twins of :mod:`hybridpgo.geometry._kernels` (same
formulas, series and thresholds; STYLE.md §3: no allocation in the per-constraint path).  The
drivers allocate one scratch buffer per call.  Measured on sphere2500 (4949 edges): assembly
31 ms -> 5 ms, energy 12 ms -> 1 ms with respect to calling the allocating geometry kernels.
``tests/test_gauss_newton.py`` checks them against the geometry kernels to float64 rounding.
"""

from __future__ import annotations

import math

import numpy as np

from .._numba import kernel
from ..geometry._kernels import NEAR_PI, Q_SERIES_ANGLE, SMALL_ANGLE, orthonormalize, se3_exp

#: Scratch (3, 3) matrices the per-edge kernels need.
_SCRATCH = 12


# --------------------------------------------------------------------------- inner kernels
@kernel
def _mm3(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out = a @ b for (3, 3) arrays (out must not alias a or b)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@kernel
def _skew_into(v0: float, v1: float, v2: float, out: np.ndarray) -> None:
    out[0, 0] = 0.0
    out[0, 1] = -v2
    out[0, 2] = v1
    out[1, 0] = v2
    out[1, 1] = 0.0
    out[1, 2] = -v0
    out[2, 0] = -v1
    out[2, 1] = v0
    out[2, 2] = 0.0


@kernel
def _matmul6(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out = a @ b for (6, 6) arrays."""
    for i in range(6):
        for j in range(6):
            s = 0.0
            for k in range(6):
                s += a[i, k] * b[k, j]
            out[i, j] = s


@kernel
def _add_block_atb(a: np.ndarray, b: np.ndarray, data: np.ndarray, base: int,
                   stride: int) -> None:
    """data-block += a^T @ b for (6, 6) a, b, into the CSC slot (base, stride)."""
    for q in range(6):
        col = base + q * stride
        for p in range(6):
            s = 0.0
            for k in range(6):
                s += a[k, p] * b[k, q]
            data[col + p] += s


@kernel
def _so3_log_into(r: np.ndarray, out: np.ndarray) -> None:
    """out[3:6] = Log(R), exactly as geometry's ``so3_log`` (series / generic / near pi)."""
    vx = 0.5 * (r[2, 1] - r[1, 2])
    vy = 0.5 * (r[0, 2] - r[2, 0])
    vz = 0.5 * (r[1, 0] - r[0, 1])
    s = math.sqrt(vx * vx + vy * vy + vz * vz)  # sin(theta)
    c = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)  # cos(theta)
    th = math.atan2(s, c)
    if th < SMALL_ANGLE:
        f = 1.0 + th * th / 6.0  # th/sin(th) = 1 + th^2/6 + 7 th^4/360
        out[3] = f * vx
        out[4] = f * vy
        out[5] = f * vz
        return
    if math.pi - th > NEAR_PI:
        f = th / s
        out[3] = f * vx
        out[4] = f * vy
        out[5] = f * vz
        return
    # Near pi: R + R^T = 2 cos(th) I + 2 (1 - cos th) a a^T; take the largest diagonal column.
    d0 = r[0, 0] - c
    d1 = r[1, 1] - c
    d2 = r[2, 2] - c
    k = 0
    if d1 > d0 and d1 >= d2:
        k = 1
    elif d2 > d0 and d2 > d1:
        k = 2
    a0 = 0.5 * (r[0, k] + r[k, 0]) - (c if k == 0 else 0.0)
    a1 = 0.5 * (r[1, k] + r[k, 1]) - (c if k == 1 else 0.0)
    a2 = 0.5 * (r[2, k] + r[k, 2]) - (c if k == 2 else 0.0)
    n = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    sign = 1.0
    if a0 * vx + a1 * vy + a2 * vz < 0.0:
        sign = -1.0
    out[3] = sign * th * a0 / n
    out[4] = sign * th * a1 / n
    out[5] = sign * th * a2 / n


@kernel
def _jl_inv_coeff(th: float) -> float:
    """c of J_l(phi)^-1 = I - 1/2 [phi]x + c [phi]x^2 (geometry's ``so3_left_jacobian_inv``)."""
    if th < SMALL_ANGLE:
        return 1.0 / 12.0 + th * th / 720.0  # + th^4/30240
    return 1.0 / (th * th) - math.cos(0.5 * th) / (2.0 * th * math.sin(0.5 * th))


@kernel
def edge_error_into(ra: np.ndarray, ta: np.ndarray, rb: np.ndarray, tb: np.ndarray,
                    rz: np.ndarray, tz: np.ndarray, rab: np.ndarray, tab: np.ndarray,
                    re: np.ndarray, e: np.ndarray) -> None:
    """e = Log(Z^-1 X_a^-1 X_b) = (V(phi)^-1 t_e, phi); also X_a^-1 X_b -> (rab, tab).

    ``re`` (3, 3) is scratch (it receives the rotation of Z^-1 X_a^-1 X_b).
    """
    d0 = tb[0] - ta[0]
    d1 = tb[1] - ta[1]
    d2 = tb[2] - ta[2]
    for i in range(3):
        tab[i] = ra[0, i] * d0 + ra[1, i] * d1 + ra[2, i] * d2
        for j in range(3):
            rab[i, j] = ra[0, i] * rb[0, j] + ra[1, i] * rb[1, j] + ra[2, i] * rb[2, j]
    u0 = tab[0] - tz[0]
    u1 = tab[1] - tz[1]
    u2 = tab[2] - tz[2]
    for i in range(3):
        for j in range(3):
            re[i, j] = rz[0, i] * rab[0, j] + rz[1, i] * rab[1, j] + rz[2, i] * rab[2, j]
    t0 = rz[0, 0] * u0 + rz[1, 0] * u1 + rz[2, 0] * u2
    t1 = rz[0, 1] * u0 + rz[1, 1] * u1 + rz[2, 1] * u2
    t2 = rz[0, 2] * u0 + rz[1, 2] * u1 + rz[2, 2] * u2
    _so3_log_into(re, e)
    p0 = e[3]
    p1 = e[4]
    p2 = e[5]
    c = _jl_inv_coeff(math.sqrt(p0 * p0 + p1 * p1 + p2 * p2))
    # rho = Jl^-1(phi) t = t - 1/2 phi x t + c phi x (phi x t)
    x0 = p1 * t2 - p2 * t1
    x1 = p2 * t0 - p0 * t2
    x2 = p0 * t1 - p1 * t0
    y0 = p1 * x2 - p2 * x1
    y1 = p2 * x0 - p0 * x2
    y2 = p0 * x1 - p1 * x0
    e[0] = t0 - 0.5 * x0 + c * y0
    e[1] = t1 - 0.5 * x1 + c * y1
    e[2] = t2 - 0.5 * x2 + c * y2


@kernel
def _q_into(r0: float, r1: float, r2: float, p0: float, p1: float, p2: float,
            w: np.ndarray, q: np.ndarray) -> None:
    """Barfoot's Q(rho, phi) into q, exactly as geometry's ``_q_matrix``; w: >= 7 scratch."""
    th2 = p0 * p0 + p1 * p1 + p2 * p2
    th = math.sqrt(th2)
    if th < Q_SERIES_ANGLE:
        # (th - sin th)/th^3 = 1/6 - th^2/120 + th^4/5040 - th^6/362880
        a1 = 1.0 / 6.0 - th2 / 120.0 * (1.0 - th2 / 42.0 * (1.0 - th2 / 72.0))
        # (1 - th^2/2 - cos th)/th^4 = -1/24 + th^2/720 - th^4/40320 + th^6/3628800
        a2 = -1.0 / 24.0 + th2 / 720.0 * (1.0 - th2 / 56.0 * (1.0 - th2 / 90.0))
        # (th - sin th - th^3/6)/th^5 = -1/120 + th^2/5040 - th^4/362880 + th^6/39916800
        a3 = -1.0 / 120.0 + th2 / 5040.0 * (1.0 - th2 / 72.0 * (1.0 - th2 / 110.0))
    else:
        s = math.sin(th)
        c = math.cos(th)
        a1 = (th - s) / (th2 * th)
        a2 = (1.0 - 0.5 * th2 - c) / (th2 * th2)
        a3 = (th - s - th2 * th / 6.0) / (th2 * th2 * th)
    rx = w[0]
    px = w[1]
    pr = w[2]
    rp = w[3]
    prp = w[4]
    m1 = w[5]
    m2 = w[6]
    _skew_into(r0, r1, r2, rx)
    _skew_into(p0, p1, p2, px)
    _mm3(px, rx, pr)
    _mm3(rx, px, rp)
    _mm3(pr, px, prp)
    b4 = 0.5 * (a2 - 3.0 * a3)
    for i in range(3):
        for j in range(3):
            q[i, j] = 0.5 * rx[i, j] + a1 * (pr[i, j] + rp[i, j] + prp[i, j]) + 3.0 * a2 * prp[i, j]
    _mm3(px, pr, m1)  # px pr
    _mm3(rp, px, m2)  # rp px
    for i in range(3):
        for j in range(3):
            q[i, j] -= a2 * (m1[i, j] + m2[i, j])
    _mm3(prp, px, m1)
    _mm3(px, prp, m2)
    for i in range(3):
        for j in range(3):
            q[i, j] -= b4 * (m1[i, j] + m2[i, j])


@kernel
def _jr_inv_blocks(e: np.ndarray, w: np.ndarray) -> None:
    """Jr^-1(e) = Jl^-1(-e) = [[J, K], [0, J]]: J -> w[8], K -> w[9] (w[0:8] scratch).

    J = Jl^-1(-phi) = I + 1/2 [phi]x + c [phi]x^2, K = -J Q(-rho, -phi) J.
    """
    p0 = e[3]
    p1 = e[4]
    p2 = e[5]
    c = _jl_inv_coeff(math.sqrt(p0 * p0 + p1 * p1 + p2 * p2))
    jm = w[8]
    km = w[9]
    q = w[7]
    px = w[0]
    _skew_into(p0, p1, p2, px)
    _mm3(px, px, w[1])
    for i in range(3):
        for j in range(3):
            jm[i, j] = (1.0 if i == j else 0.0) + 0.5 * px[i, j] + c * w[1][i, j]
    _q_into(-e[0], -e[1], -e[2], -p0, -p1, -p2, w, q)
    _mm3(q, jm, w[0])
    _mm3(jm, w[0], km)
    for i in range(3):
        for j in range(3):
            km[i, j] = -km[i, j]


@kernel
def _edge_linearization(ra: np.ndarray, ta: np.ndarray, rb: np.ndarray, tb: np.ndarray,
                        rz: np.ndarray, tz: np.ndarray, e: np.ndarray, ja: np.ndarray,
                        jb: np.ndarray, w: np.ndarray) -> None:
    """Error e (6,) and Jacobians ja, jb (6, 6) of one relative constraint; w: scratch.

    ``jb = Jr^-1(e)``, ``ja = -Jr^-1(e) Ad(X_b^-1 X_a)``.  With X_b^-1 X_a = (R, t) =
    (R_ab^T, -R_ab^T t_ab) and Ad = [[R, [t]x R], [0, R]], Jr^-1 = [[J, K], [0, J]]:
    ``ja = -[[J R, J [t]x R + K R], [0, J R]]``.
    """
    rab = w[10]
    tab = w[11][0]
    edge_error_into(ra, ta, rb, tb, rz, tz, rab, tab, w[0], e)
    _jr_inv_blocks(e, w)
    jm = w[8]
    km = w[9]
    r = w[0]
    for i in range(3):
        for j in range(3):
            r[i, j] = rab[j, i]
    s0 = -(r[0, 0] * tab[0] + r[0, 1] * tab[1] + r[0, 2] * tab[2])
    s1 = -(r[1, 0] * tab[0] + r[1, 1] * tab[1] + r[1, 2] * tab[2])
    s2 = -(r[2, 0] * tab[0] + r[2, 1] * tab[1] + r[2, 2] * tab[2])
    txr = w[1]
    _skew_into(s0, s1, s2, w[2])
    _mm3(w[2], r, txr)  # [t]x R
    jr = w[3]
    _mm3(jm, r, jr)  # J R
    _mm3(jm, txr, w[4])  # J [t]x R
    _mm3(km, r, w[5])  # K R
    for i in range(3):
        for j in range(3):
            ja[i, j] = -jr[i, j]
            ja[i, j + 3] = -(w[4][i, j] + w[5][i, j])
            ja[i + 3, j] = 0.0
            ja[i + 3, j + 3] = -jr[i, j]
            jb[i, j] = jm[i, j]
            jb[i, j + 3] = km[i, j]
            jb[i + 3, j] = 0.0
            jb[i + 3, j + 3] = jm[i, j]


# --------------------------------------------------------------------------- drivers
@kernel
def edge_jacobians(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                   edge_rot: np.ndarray, edge_trans: np.ndarray, out_err: np.ndarray,
                   out_ja: np.ndarray, out_jb: np.ndarray) -> None:
    """Errors (M, 6) and Jacobians (M, 6, 6) w.r.t. delta_a and delta_b of every relative edge."""
    w = np.empty((_SCRATCH, 3, 3))
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        _edge_linearization(rot[a], trans[a], rot[b], trans[b], edge_rot[c], edge_trans[c],
                            out_err[c], out_ja[c], out_jb[c], w)


@kernel
def total_energy(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                 edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
                 gps_nodes: np.ndarray, gps_pos: np.ndarray, gps_info: np.ndarray) -> float:
    """E = sum_c e_c^T Omega_c e_c (same errors as :mod:`hybridpgo.energy`); may be inf/nan."""
    w = np.empty((3, 3, 3))
    e = np.empty(6)
    total = 0.0
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        edge_error_into(rot[a], trans[a], rot[b], trans[b], edge_rot[c], edge_trans[c], w[0],
                        w[1][0], w[2], e)
        om = edge_info[c]
        for i in range(6):
            s = 0.0
            for j in range(6):
                s += om[i, j] * e[j]
            total += e[i] * s
    for c in range(gps_nodes.shape[0]):
        n = gps_nodes[c]
        om = gps_info[c]
        for i in range(3):
            s = 0.0
            for j in range(3):
                s += om[i, j] * (trans[n, j] - gps_pos[c, j])
            total += (trans[n, i] - gps_pos[c, i]) * s
    return total


@kernel
def assemble_normal_equations(
    rot: np.ndarray, trans: np.ndarray,
    edge_nodes: np.ndarray, edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
    edge_base: np.ndarray, edge_stride: np.ndarray,
    gps_nodes: np.ndarray, gps_pos: np.ndarray, gps_info: np.ndarray,
    gps_base: np.ndarray, gps_stride: np.ndarray,
    var_of_node: np.ndarray, data: np.ndarray, grad: np.ndarray,
) -> tuple[int, float]:
    """Fill ``data`` (CSC values of H) and ``grad`` (g = J^T Omega e) in one pass; return energy.

    ``edge_base``/``edge_stride`` (M, 4): slots of the blocks (a, a), (b, b), (a, b), (b, a)
    (row, column), -1 where a node is fixed.  ``gps_base``/``gps_stride`` (G,): slot of (n, n).
    ``var_of_node`` (N,): variable index of each node, -1 when fixed.

    Returns ``(status, energy)``: status -1 when every quantity is finite, else the index of
    the first offending constraint (relative edges 0..M-1, then M + GPS index).
    """
    data[:] = 0.0
    grad[:] = 0.0
    m = edge_nodes.shape[0]
    w = np.empty((_SCRATCH, 3, 3))
    e = np.empty(6)
    oe = np.empty(6)
    ja = np.empty((6, 6))
    jb = np.empty((6, 6))
    wa = np.empty((6, 6))
    wb = np.empty((6, 6))
    energy = 0.0
    for c in range(m):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        _edge_linearization(rot[a], trans[a], rot[b], trans[b], edge_rot[c], edge_trans[c],
                            e, ja, jb, w)
        om = edge_info[c]
        ec = 0.0
        for i in range(6):
            s = 0.0
            for j in range(6):
                s += om[i, j] * e[j]
            oe[i] = s
            ec += e[i] * s
        ok = math.isfinite(ec)
        for i in range(6):
            for j in range(6):
                if not (math.isfinite(ja[i, j]) and math.isfinite(jb[i, j])):
                    ok = False
        if not ok:
            return c, energy
        energy += ec
        _matmul6(om, ja, wa)
        _matmul6(om, jb, wb)
        va = var_of_node[a]
        vb = var_of_node[b]
        if va >= 0:
            _add_block_atb(ja, wa, data, edge_base[c, 0], edge_stride[c, 0])
            for p in range(6):
                s = 0.0
                for k in range(6):
                    s += ja[k, p] * oe[k]
                grad[6 * va + p] += s
        if vb >= 0:
            _add_block_atb(jb, wb, data, edge_base[c, 1], edge_stride[c, 1])
            for p in range(6):
                s = 0.0
                for k in range(6):
                    s += jb[k, p] * oe[k]
                grad[6 * vb + p] += s
        if va >= 0 and vb >= 0:
            _add_block_atb(ja, wb, data, edge_base[c, 2], edge_stride[c, 2])
            _add_block_atb(jb, wa, data, edge_base[c, 3], edge_stride[c, 3])
    for c in range(gps_nodes.shape[0]):
        n = gps_nodes[c]
        om = gps_info[c]
        r = rot[n]
        ec = 0.0
        for i in range(3):
            s = 0.0
            for j in range(3):
                s += om[i, j] * (trans[n, j] - gps_pos[c, j])
            oe[i] = s
            ec += (trans[n, i] - gps_pos[c, i]) * s
        if not math.isfinite(ec):
            return m + c, energy
        energy += ec
        vn = var_of_node[n]
        if vn < 0:
            continue
        # J = [R | 0]: H_nn = [[R^T Omega R, 0], [0, 0]], g_n = (R^T Omega e, 0).
        base = gps_base[c]
        stride = gps_stride[c]
        for q in range(3):
            for p in range(3):
                s = 0.0
                for k in range(3):
                    for l in range(3):
                        s += r[k, p] * om[k, l] * r[l, q]
                data[base + q * stride + p] += s
        for p in range(3):
            grad[6 * vn + p] += r[0, p] * oe[0] + r[1, p] * oe[1] + r[2, p] * oe[2]
    return -1, energy


@kernel
def retract(rot: np.ndarray, trans: np.ndarray, step: np.ndarray, var_of_node: np.ndarray,
            scale: float, out_rot: np.ndarray, out_trans: np.ndarray) -> None:
    """``X_i <- X_i Exp(scale * delta_i)`` for free nodes (re-orthonormalized); copy fixed ones.

    ``step`` is the solution vector (6 * num_vars,) indexed by ``var_of_node``.
    """
    xi = np.empty(6)
    for i in range(rot.shape[0]):
        v = var_of_node[i]
        if v < 0:
            out_rot[i] = rot[i]
            out_trans[i] = trans[i]
            continue
        for k in range(6):
            xi[k] = scale * step[6 * v + k]
        dr, dt = se3_exp(xi)
        out_rot[i] = orthonormalize(rot[i] @ dr)
        out_trans[i] = trans[i] + rot[i] @ dt
