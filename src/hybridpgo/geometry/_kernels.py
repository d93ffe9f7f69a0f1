"""Allocation-free SE(3) kernels for the solvers' hot loops (used through :mod:`hybridpgo._cost`).

They write into caller-provided buffers, so a per-constraint update allocates nothing.  The
thresholds of the small-angle series are defined here, once.  ``tests/ref_kernels.py`` holds
allocating reference kernels with the same formulas; the tests check these against them and
against the NumPy twins of ``tests/naive.py``.

Small-angle handling: below ``SMALL_ANGLE`` (rad) every coefficient is evaluated with its Taylor
series, accurate to ~1e-16 there; the SE(3) coupling block Q uses longer series below
``Q_SERIES_ANGLE``.  Near pi the rotation logarithm switches to the symmetric-part formula
(``NEAR_PI``).
"""

from __future__ import annotations

import math

import numpy as np

from .._numba import kernel

#: Below this rotation angle (rad) coefficients use Taylor series (error O(theta^4) ~ 1e-16).
SMALL_ANGLE = 1e-4
#: Within this distance of pi, Log(R) reads the axis from the symmetric part of R.
NEAR_PI = 1e-2
#: Below this angle (rad) Q(rho, phi) uses series to theta^6: its closed-form coefficients cancel
#: like eps / theta^2 (1e-8 at theta = 1e-4), the series' truncation error is < 1e-15 here.
Q_SERIES_ANGLE = 0.1
#: Below this |cos(pitch)| (gimbal lock) matrix_to_euler_rpy sets roll = 0 and puts it all in yaw.
GIMBAL_LOCK_COS = 1e-14


# 3x3 matrices as row-major 9-tuples of floats: kept in registers, so the products below cost
# no array views (each view or array argument of a Numba call costs an atomic reference-count
# pair, more than the arithmetic: a loop over constraints that passes each constraint's rows
# as views spends most of its time there).  Each entry of a product is summed over k = 0, 1, 2
# in order, as :func:`mm3` sums.
M3 = tuple[float, float, float, float, float, float, float, float, float]
#: 3-vectors and 6-vectors as tuples of floats.
V3 = tuple[float, float, float]
E6 = tuple[float, float, float, float, float, float]


@kernel
def load3x3(a: np.ndarray) -> M3:
    """A (3, 3) array as a row-major 9-tuple."""
    return (a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2], a[2, 0], a[2, 1], a[2, 2])


@kernel
def load3(a: np.ndarray) -> V3:
    """A (3,) array as a 3-tuple."""
    return a[0], a[1], a[2]


@kernel
def row3x3(a: np.ndarray, i: int) -> M3:
    """``a[i]`` of a (k, 3, 3) array as a row-major 9-tuple, read element by element (no
    view)."""
    return (a[i, 0, 0], a[i, 0, 1], a[i, 0, 2], a[i, 1, 0], a[i, 1, 1], a[i, 1, 2],
            a[i, 2, 0], a[i, 2, 1], a[i, 2, 2])


@kernel
def row3(a: np.ndarray, i: int) -> V3:
    """``a[i]`` of a (k, 3) array as a 3-tuple (no view)."""
    return a[i, 0], a[i, 1], a[i, 2]


@kernel
def _transpose3(a: M3) -> M3:
    """a^T for a row-major 9-tuple."""
    return a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]


@kernel
def _tmulv(a: M3, v: V3) -> V3:
    """a^T v for a row-major 9-tuple, each entry summed in order."""
    return (a[0] * v[0] + a[3] * v[1] + a[6] * v[2],
            a[1] * v[0] + a[4] * v[1] + a[7] * v[2],
            a[2] * v[0] + a[5] * v[1] + a[8] * v[2])


@kernel
def mm3(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """out = a @ b for (3, 3) arrays (out must not alias a or b)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@kernel
def skew_into(v0: float, v1: float, v2: float, out: np.ndarray) -> None:
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
def adjoint_into(r: np.ndarray, t: np.ndarray, out: np.ndarray) -> None:
    """Ad(T) = [[R, [t]x R], [0, R]] of the pose T = (r, t) into the (6, 6) ``out``."""
    for i in range(3):
        for j in range(3):
            out[i, j] = r[i, j]
            out[3 + i, 3 + j] = r[i, j]
            out[3 + i, j] = 0.0
    for j in range(3):
        out[0, 3 + j] = t[1] * r[2, j] - t[2] * r[1, j]
        out[1, 3 + j] = t[2] * r[0, j] - t[0] * r[2, j]
        out[2, 3 + j] = t[0] * r[1, j] - t[1] * r[0, j]


@kernel
def so3_log9(r: M3) -> V3:
    """Log(R) of a rotation given as a row-major 9-tuple, exactly as geometry's ``so3_log``
    (series / generic / near pi)."""
    vx = 0.5 * (r[7] - r[5])
    vy = 0.5 * (r[2] - r[6])
    vz = 0.5 * (r[3] - r[1])
    s = math.sqrt(vx * vx + vy * vy + vz * vz)  # sin(theta)
    c = 0.5 * (r[0] + r[4] + r[8] - 1.0)  # cos(theta)
    th = math.atan2(s, c)
    if th < SMALL_ANGLE:
        f = 1.0 + th * th / 6.0  # th/sin(th) = 1 + th^2/6 + 7 th^4/360
        return f * vx, f * vy, f * vz
    if math.pi - th > NEAR_PI:
        f = th / s
        return f * vx, f * vy, f * vz
    # Near pi: R + R^T = 2 cos(th) I + 2 (1 - cos th) a a^T; take the largest diagonal column.
    d0 = r[0] - c
    d1 = r[4] - c
    d2 = r[8] - c
    k = 0
    if d1 > d0 and d1 >= d2:
        k = 1
    elif d2 > d0 and d2 > d1:
        k = 2
    a0 = 0.5 * (r[k] + r[3 * k]) - (c if k == 0 else 0.0)
    a1 = 0.5 * (r[3 + k] + r[3 * k + 1]) - (c if k == 1 else 0.0)
    a2 = 0.5 * (r[6 + k] + r[3 * k + 2]) - (c if k == 2 else 0.0)
    n = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    sign = 1.0
    if a0 * vx + a1 * vy + a2 * vz < 0.0:
        sign = -1.0
    return sign * th * a0 / n, sign * th * a1 / n, sign * th * a2 / n


@kernel
def so3_log_into(r: np.ndarray, out: np.ndarray) -> None:
    """out[3:6] = Log(R) of a (3, 3) array (:func:`so3_log9`)."""
    out[3], out[4], out[5] = so3_log9(load3x3(r))


@kernel
def jl_inv_coeff(th: float) -> float:
    """c of J_l(phi)^-1 = I - 1/2 [phi]x + c [phi]x^2 (geometry's ``so3_left_jacobian_inv``)."""
    if th < SMALL_ANGLE:
        return 1.0 / 12.0 + th * th / 720.0  # + th^4/30240
    return 1.0 / (th * th) - math.cos(0.5 * th) / (2.0 * th * math.sin(0.5 * th))


@kernel
def edge_error9(ra: M3, ta: V3, rb: M3, tb: V3, rz: M3, tz: V3) -> tuple[E6, M3, V3]:
    """``(e, R_ab, t_ab)``: e = Log(Z^-1 X_a^-1 X_b) = (V(phi)^-1 t_e, phi) and
    X_a^-1 X_b = (R_ab, t_ab), of poses and measurement given as 9- and 3-tuples (no array
    views: a loop over constraints reads them by index, :func:`row3x3`, :func:`row3`)."""
    d = (tb[0] - ta[0], tb[1] - ta[1], tb[2] - ta[2])
    tab = _tmulv(ra, d)
    rab = _mul3(_transpose3(ra), rb)
    tu = _tmulv(rz, (tab[0] - tz[0], tab[1] - tz[1], tab[2] - tz[2]))
    t0, t1, t2 = tu
    p0, p1, p2 = so3_log9(_mul3(_transpose3(rz), rab))
    c = jl_inv_coeff(math.sqrt(p0 * p0 + p1 * p1 + p2 * p2))
    # rho = Jl^-1(phi) t = t - 1/2 phi x t + c phi x (phi x t)
    x0 = p1 * t2 - p2 * t1
    x1 = p2 * t0 - p0 * t2
    x2 = p0 * t1 - p1 * t0
    y0 = p1 * x2 - p2 * x1
    y1 = p2 * x0 - p0 * x2
    y2 = p0 * x1 - p1 * x0
    e = (t0 - 0.5 * x0 + c * y0, t1 - 0.5 * x1 + c * y1, t2 - 0.5 * x2 + c * y2, p0, p1, p2)
    return e, rab, tab


@kernel
def edge_error_into(ra: np.ndarray, ta: np.ndarray, rb: np.ndarray, tb: np.ndarray,
                    rz: np.ndarray, tz: np.ndarray, rab: np.ndarray, tab: np.ndarray,
                    e: np.ndarray) -> None:
    """:func:`edge_error9` of (3, 3) and (3,) arrays into ``e`` (6,), ``rab``, ``tab``."""
    ev, r, t = edge_error9(load3x3(ra), load3(ta), load3x3(rb), load3(tb), load3x3(rz),
                           load3(tz))
    for i in range(6):
        e[i] = ev[i]
    for i in range(3):
        tab[i] = t[i]
        for j in range(3):
            rab[i, j] = r[3 * i + j]


@kernel
def _mul3(a: M3, b: M3) -> M3:
    """a @ b for row-major 9-tuples, summed as :func:`mm3` does."""
    return (
        a[0] * b[0] + a[1] * b[3] + a[2] * b[6],
        a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
        a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
        a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
        a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
        a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
        a[6] * b[0] + a[7] * b[3] + a[8] * b[6],
        a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
        a[6] * b[2] + a[7] * b[5] + a[8] * b[8],
    )


@kernel
def _skew3(v0: float, v1: float, v2: float) -> M3:
    """[v]x as a row-major 9-tuple (the entries of :func:`skew_into`)."""
    return (0.0, -v2, v1, v2, 0.0, -v0, -v1, v0, 0.0)


@kernel
def _q_matrix3(r0: float, r1: float, r2: float, p0: float, p1: float, p2: float) -> M3:
    """Barfoot's Q(rho, phi) as a row-major 9-tuple (see :func:`q_into`)."""
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
    rx = _skew3(r0, r1, r2)
    px = _skew3(p0, p1, p2)
    pr = _mul3(px, rx)
    rp = _mul3(rx, px)
    prp = _mul3(pr, px)
    b4 = 0.5 * (a2 - 3.0 * a3)
    m1 = _mul3(px, pr)
    m2 = _mul3(rp, px)
    m3 = _mul3(prp, px)
    m4 = _mul3(px, prp)
    return (
        _q_entry(0, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(1, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(2, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(3, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(4, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(5, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(6, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(7, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
        _q_entry(8, rx, pr, rp, prp, m1, m2, m3, m4, a1, a2, b4),
    )


@kernel
def _q_entry(n: int, rx: M3, pr: M3, rp: M3, prp: M3, m1: M3, m2: M3, m3: M3, m4: M3,
             a1: float, a2: float, b4: float) -> float:
    """Entry n of Q (:func:`_q_matrix3`) from the 9-tuples of its products."""
    v = 0.5 * rx[n] + a1 * (pr[n] + rp[n] + prp[n]) + 3.0 * a2 * prp[n]
    v -= a2 * (m1[n] + m2[n])
    v -= b4 * (m3[n] + m4[n])
    return v


@kernel
def q_into(r0: float, r1: float, r2: float, p0: float, p1: float, p2: float,
           w: np.ndarray, q: np.ndarray) -> None:
    """Barfoot's Q(rho, phi) into q, exactly as geometry's ``_q_matrix``; ``w`` is unused
    (kept for the signature)."""
    m = _q_matrix3(r0, r1, r2, p0, p1, p2)
    for i in range(3):
        for j in range(3):
            q[i, j] = m[3 * i + j]


@kernel
def jr_inv9(e: E6) -> tuple[M3, M3]:
    """``(J, K)`` of Jr^-1(e) = Jl^-1(-e) = [[J, K], [0, J]] as row-major 9-tuples.

    J = Jl^-1(-phi) = I + 1/2 [phi]x + c [phi]x^2, K = -J Q(-rho, -phi) J.
    """
    p0 = e[3]
    p1 = e[4]
    p2 = e[5]
    c = jl_inv_coeff(math.sqrt(p0 * p0 + p1 * p1 + p2 * p2))
    px = _skew3(p0, p1, p2)
    px2 = _mul3(px, px)
    jm = (
        1.0 + 0.5 * px[0] + c * px2[0], 0.0 + 0.5 * px[1] + c * px2[1],
        0.0 + 0.5 * px[2] + c * px2[2], 0.0 + 0.5 * px[3] + c * px2[3],
        1.0 + 0.5 * px[4] + c * px2[4], 0.0 + 0.5 * px[5] + c * px2[5],
        0.0 + 0.5 * px[6] + c * px2[6], 0.0 + 0.5 * px[7] + c * px2[7],
        1.0 + 0.5 * px[8] + c * px2[8],
    )
    q = _q_matrix3(-e[0], -e[1], -e[2], -p0, -p1, -p2)
    km = _mul3(jm, _mul3(q, jm))
    return jm, (-km[0], -km[1], -km[2], -km[3], -km[4], -km[5], -km[6], -km[7], -km[8])


@kernel
def jr_inv_blocks(e: np.ndarray, w: np.ndarray) -> None:
    """:func:`jr_inv9` of the array ``e``: J -> w[8], K -> w[9]."""
    jm, km = jr_inv9((e[0], e[1], e[2], e[3], e[4], e[5]))
    for i in range(3):
        for j in range(3):
            w[8, i, j] = jm[3 * i + j]
            w[9, i, j] = km[3 * i + j]
