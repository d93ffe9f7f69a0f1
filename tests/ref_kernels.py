"""Reference SO(3)/SE(3) kernels (allocating, one element at a time), used only by the tests.

The same formulas and thresholds as the allocation-free kernels of
:mod:`hybridpgo.geometry._kernels` (whose ``skew_into`` gives the cross-product matrices
here); the tests check those kernels against these, and these against the independent NumPy
twins of ``naive.py`` and SciPy.

Conventions: tangent vectors xi = (rho, phi) (translation first); ``Exp(xi)`` is the SE(3)
exponential; poses are (R, t) pairs of a (3, 3) rotation and a (3,) translation.

Small-angle handling: below ``SMALL_ANGLE`` (rad) every coefficient is evaluated with its Taylor
series (terms listed beside each one), which are accurate to ~1e-16 there; the SE(3) coupling
block Q uses longer series below ``Q_SERIES_ANGLE``.  Near pi the rotation logarithm switches to the
symmetric-part formula (``NEAR_PI``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from hybridpgo._numba import kernel
from hybridpgo.geometry._kernels import (
    GIMBAL_LOCK_COS,
    NEAR_PI,
    Q_SERIES_ANGLE,
    SMALL_ANGLE,
    skew_into,
)


@kernel
def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues: R = I + sin(th)/th [phi]x + (1-cos th)/th^2 [phi]x^2."""
    th2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    th = math.sqrt(th2)
    if th < SMALL_ANGLE:
        a = 1.0 - th2 / 6.0  # sin(th)/th = 1 - th^2/6 + th^4/120
        b = 0.5 - th2 / 24.0  # (1-cos th)/th^2 = 1/2 - th^2/24 + th^4/720
    else:
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th2
    k = np.empty((3, 3))
    skew_into(phi[0], phi[1], phi[2], k)
    out: np.ndarray = np.eye(3) + a * k + b * (k @ k)
    return out


@kernel
def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector phi with |phi| in [0, pi] and Exp(phi) = R."""
    vx = 0.5 * (r[2, 1] - r[1, 2])
    vy = 0.5 * (r[0, 2] - r[2, 0])
    vz = 0.5 * (r[1, 0] - r[0, 1])
    s = math.sqrt(vx * vx + vy * vy + vz * vz)  # sin(theta)
    c = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)  # cos(theta)
    th = math.atan2(s, c)
    out = np.empty(3)
    if th < SMALL_ANGLE:
        f = 1.0 + th * th / 6.0  # th/sin(th) = 1 + th^2/6 + 7 th^4/360
        out[0] = f * vx
        out[1] = f * vy
        out[2] = f * vz
        return out
    if math.pi - th > NEAR_PI:
        f = th / s
        out[0] = f * vx
        out[1] = f * vy
        out[2] = f * vz
        return out
    # Near pi: R + R^T = 2 cos(th) I + 2 (1 - cos th) a a^T; take the largest diagonal column.
    d0 = r[0, 0] - c
    d1 = r[1, 1] - c
    d2 = r[2, 2] - c
    k = 0
    if d1 > d0 and d1 >= d2:
        k = 1
    elif d2 > d0 and d2 > d1:
        k = 2
    a = np.empty(3)
    for i in range(3):
        a[i] = 0.5 * (r[i, k] + r[k, i]) - (c if i == k else 0.0)
    n = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    sign = 1.0
    if a[0] * vx + a[1] * vy + a[2] * vz < 0.0:
        sign = -1.0
    for i in range(3):
        out[i] = sign * th * a[i] / n
    return out


@kernel
def _v_coeffs(th: float) -> tuple[float, float]:
    """Coefficients of V(phi) = I + b [phi]x + c [phi]x^2."""
    th2 = th * th
    if th < SMALL_ANGLE:
        return 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    sh = math.sin(0.5 * th)  # 1 - cos th = 2 sin^2(th/2): no cancellation (b multiplies [phi]x)
    return 2.0 * sh * sh / th2, (th - math.sin(th)) / (th2 * th)


@kernel
def so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_l(phi) = V(phi) of SO(3)."""
    th = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    b, c = _v_coeffs(th)
    k = np.empty((3, 3))
    skew_into(phi[0], phi[1], phi[2], k)
    out: np.ndarray = np.eye(3) + b * k + c * (k @ k)
    return out


@kernel
def so3_left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """J_l(phi)^-1 = I - 1/2 [phi]x + (1/th^2 - cot(th/2)/(2 th)) [phi]x^2 (stable at pi)."""
    th = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    if th < SMALL_ANGLE:
        c = 1.0 / 12.0 + th * th / 720.0  # + th^4/30240
    else:
        c = 1.0 / (th * th) - math.cos(0.5 * th) / (2.0 * th * math.sin(0.5 * th))
    k = np.empty((3, 3))
    skew_into(phi[0], phi[1], phi[2], k)
    out: np.ndarray = np.eye(3) - 0.5 * k + c * (k @ k)
    return out


@kernel
def se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exp(xi) for xi = (rho, phi): R = exp(phi), t = V(phi) rho."""
    phi = xi[3:6].copy()
    rho = xi[0:3].copy()
    return so3_exp(phi), so3_left_jacobian(phi) @ rho


@kernel
def se3_log(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Log(R, t) = (V(phi)^-1 t, phi)."""
    phi = so3_log(r)
    rho = so3_left_jacobian_inv(phi) @ t
    out = np.empty(6)
    out[0:3] = rho
    out[3:6] = phi
    return out


@kernel
def _q_matrix(rho: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Barfoot's Q(rho, phi), the off-diagonal block of the SE(3) left Jacobian (rho, phi order)."""
    th2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
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
    rx = np.empty((3, 3))
    skew_into(rho[0], rho[1], rho[2], rx)
    px = np.empty((3, 3))
    skew_into(phi[0], phi[1], phi[2], px)
    pr = px @ rx
    rp = rx @ px
    prp = pr @ px
    out: np.ndarray = (0.5 * rx + a1 * (pr + rp + prp) - a2 * (px @ pr + rp @ px - 3.0 * prp)
                       - 0.5 * (a2 - 3.0 * a3) * (prp @ px + px @ prp))
    return out


@kernel
def se3_left_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """J_l(xi)^-1 of SE(3) in (rho, phi) order: [[Jl^-1, -Jl^-1 Q Jl^-1], [0, Jl^-1]]."""
    rho = xi[0:3].copy()
    phi = xi[3:6].copy()
    ji = so3_left_jacobian_inv(phi)
    q = _q_matrix(rho, phi)
    out = np.zeros((6, 6))
    out[0:3, 0:3] = ji
    out[3:6, 3:6] = ji
    out[0:3, 3:6] = -(ji @ q @ ji)
    return out


@kernel
def se3_right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """J_r(xi)^-1 = J_l(-xi)^-1 (docs/mathematics.md#jacobians's ``Jr^-1``)."""
    return se3_left_jacobian_inv(-xi)


@kernel
def se3_adjoint(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Ad(T) = [[R, [t]x R], [0, R]] in (rho, phi) order."""
    out = np.zeros((6, 6))
    out[0:3, 0:3] = r
    out[3:6, 3:6] = r
    tx = np.empty((3, 3))
    skew_into(t[0], t[1], t[2], tx)
    out[0:3, 3:6] = tx @ r
    return out


@kernel
def orthonormalize(r: np.ndarray) -> np.ndarray:
    """Nearest rotation to a nearly orthonormal R: one Newton step R (3I - R^T R)/2, twice."""
    out = r.copy()
    for _ in range(2):
        out = 0.5 * out @ (3.0 * np.eye(3) - out.T @ out)
    return out


@kernel
def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of the quaternion (x, y, z, w); the quaternion is normalized first."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x = q[0] / n
    y = q[1] / n
    z = q[2] / n
    w = q[3] / n
    r = np.empty((3, 3))
    r[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    r[0, 1] = 2.0 * (x * y - z * w)
    r[0, 2] = 2.0 * (x * z + y * w)
    r[1, 0] = 2.0 * (x * y + z * w)
    r[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    r[1, 2] = 2.0 * (y * z - x * w)
    r[2, 0] = 2.0 * (x * z - y * w)
    r[2, 1] = 2.0 * (y * z + x * w)
    r[2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return r


@kernel
def matrix_to_quat_xyzw(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (Shepperd's method)."""
    q = np.empty(4)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q[3] = 0.25 * s
        q[0] = (r[2, 1] - r[1, 2]) / s
        q[1] = (r[0, 2] - r[2, 0]) / s
        q[2] = (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q[3] = (r[2, 1] - r[1, 2]) / s
        q[0] = 0.25 * s
        q[1] = (r[0, 1] + r[1, 0]) / s
        q[2] = (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q[3] = (r[0, 2] - r[2, 0]) / s
        q[0] = (r[0, 1] + r[1, 0]) / s
        q[1] = 0.25 * s
        q[2] = (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q[3] = (r[1, 0] - r[0, 1]) / s
        q[0] = (r[0, 2] + r[2, 0]) / s
        q[1] = (r[1, 2] + r[2, 1]) / s
        q[2] = 0.25 * s
    if q[3] < 0.0:
        q = -q
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return q / n


@kernel
def euler_rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (TORO/iSAM convention)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    r = np.empty((3, 3))
    r[0, 0] = cy * cp
    r[0, 1] = cy * sp * sr - sy * cr
    r[0, 2] = cy * sp * cr + sy * sr
    r[1, 0] = sy * cp
    r[1, 1] = sy * sp * sr + cy * cr
    r[1, 2] = sy * sp * cr - cy * sr
    r[2, 0] = -sp
    r[2, 1] = cp * sr
    r[2, 2] = cp * cr
    return r


@kernel
def matrix_to_euler_rpy(r: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) with R = Rz(yaw) Ry(pitch) Rx(roll); pitch in [-pi/2, pi/2]."""
    out = np.empty(3)
    cp = math.sqrt(r[2, 1] * r[2, 1] + r[2, 2] * r[2, 2])  # |cos(pitch)|
    out[1] = math.atan2(-r[2, 0], cp)  # atan2, not asin: accurate near +-pi/2
    # Gimbal lock (cp ~ 0): roll is arbitrary, put everything in yaw.  Elsewhere take roll from
    # row 2 and yaw from R Rx(roll)^T = Rz(yaw) Ry(pitch), whose column 1 is (-sin yaw, cos yaw, 0):
    # exact for any roll, so R is reproduced to rounding even close to gimbal lock.
    out[0] = math.atan2(r[2, 1], r[2, 2]) if cp > GIMBAL_LOCK_COS else 0.0
    sr = math.sin(out[0])
    cr = math.cos(out[0])
    out[2] = math.atan2(sr * r[0, 2] - cr * r[0, 1], cr * r[1, 1] - sr * r[1, 2])
    return out


# --------------------------------------------------------------------------- pose algebra
@kernel
def compose(ra: np.ndarray, ta: np.ndarray, rb: np.ndarray,
            tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Ra, ta) * (Rb, tb)."""
    return ra @ rb, ra @ tb + ta


@kernel
def between(ra: np.ndarray, ta: np.ndarray, rb: np.ndarray,
            tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Ra, ta)^-1 * (Rb, tb)."""
    return ra.T @ rb, ra.T @ (tb - ta)


@kernel
def relative_error(rz: np.ndarray, tz: np.ndarray, rab: np.ndarray, tab: np.ndarray) -> np.ndarray:
    """e = Log(Z^-1 X_ab) for measurement Z = (rz, tz) and X_ab = X_a^-1 X_b."""
    return se3_log(rz.T @ rab, rz.T @ (tab - tz))


# ------------------------------------------------------------ χ² in the loops' operation order
# The energy loops of hybridpgo._cost read each constraint into registers; these are the same
# formulas written on (3, 3) and (3,) arrays, entry by entry, with every sum in the same order,
# so the two must agree bit for bit (an index or sign slip in either shows).
@kernel
def chi2_in_order(info: np.ndarray, e: np.ndarray) -> float:
    """``e^T Omega e`` summed row by row: ``sum_i e_i (sum_j Omega_ij e_j)``, j and i in order."""
    total = 0.0
    for i in range(6):
        s = 0.0
        for j in range(6):
            s += info[i, j] * e[j]
        total += e[i] * s
    return total


@kernel
def relative_chi2_in_order(zr: np.ndarray, zt: np.ndarray, info: np.ndarray, ra: np.ndarray,
                           ta: np.ndarray, rb: np.ndarray, tb: np.ndarray) -> float:
    """χ² of ``e = Log(Z^-1 X_a^-1 X_b)``: products entry by entry, each summed over k in order;
    Log by the branches of :func:`so3_log`; ``rho = Jl^-1(phi) t``."""
    d = tb - ta
    tab = np.empty(3)
    rab = np.empty((3, 3))
    for i in range(3):
        tab[i] = ra[0, i] * d[0] + ra[1, i] * d[1] + ra[2, i] * d[2]
        for j in range(3):
            rab[i, j] = ra[0, i] * rb[0, j] + ra[1, i] * rb[1, j] + ra[2, i] * rb[2, j]
    re = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            re[i, j] = zr[0, i] * rab[0, j] + zr[1, i] * rab[1, j] + zr[2, i] * rab[2, j]
    u = tab - zt
    t = np.empty(3)
    for i in range(3):
        t[i] = zr[0, i] * u[0] + zr[1, i] * u[1] + zr[2, i] * u[2]
    vx = 0.5 * (re[2, 1] - re[1, 2])
    vy = 0.5 * (re[0, 2] - re[2, 0])
    vz = 0.5 * (re[1, 0] - re[0, 1])
    s = math.sqrt(vx * vx + vy * vy + vz * vz)
    c = 0.5 * (re[0, 0] + re[1, 1] + re[2, 2] - 1.0)
    th = math.atan2(s, c)
    if th < SMALL_ANGLE:
        f = 1.0 + th * th / 6.0
        p = (f * vx, f * vy, f * vz)
    elif math.pi - th > NEAR_PI:
        f = th / s
        p = (f * vx, f * vy, f * vz)
    else:
        d0, d1, d2 = re[0, 0] - c, re[1, 1] - c, re[2, 2] - c
        k = 0
        if d1 > d0 and d1 >= d2:
            k = 1
        elif d2 > d0 and d2 > d1:
            k = 2
        a0 = 0.5 * (re[0, k] + re[k, 0]) - (c if k == 0 else 0.0)
        a1 = 0.5 * (re[1, k] + re[k, 1]) - (c if k == 1 else 0.0)
        a2 = 0.5 * (re[2, k] + re[k, 2]) - (c if k == 2 else 0.0)
        nrm = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        sign = -1.0 if a0 * vx + a1 * vy + a2 * vz < 0.0 else 1.0
        p = (sign * th * a0 / nrm, sign * th * a1 / nrm, sign * th * a2 / nrm)
    tp = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
    if tp < SMALL_ANGLE:
        cc = 1.0 / 12.0 + tp * tp / 720.0
    else:
        cc = 1.0 / (tp * tp) - math.cos(0.5 * tp) / (2.0 * tp * math.sin(0.5 * tp))
    x0 = p[1] * t[2] - p[2] * t[1]
    x1 = p[2] * t[0] - p[0] * t[2]
    x2 = p[0] * t[1] - p[1] * t[0]
    y0 = p[1] * x2 - p[2] * x1
    y1 = p[2] * x0 - p[0] * x2
    y2 = p[0] * x1 - p[1] * x0
    e = np.array([t[0] - 0.5 * x0 + cc * y0, t[1] - 0.5 * x1 + cc * y1,
                  t[2] - 0.5 * x2 + cc * y2, p[0], p[1], p[2]])
    return chi2_in_order(info, e)


@kernel
def planar_chi2_in_order(zr: np.ndarray, zt: np.ndarray, info: np.ndarray, ra: np.ndarray,
                         ta: np.ndarray, rb: np.ndarray, tb: np.ndarray) -> float:
    """χ² of the SE(2) logarithm ``(rho_x, rho_y, 0, 0, 0, theta)`` of planar poses and
    measurement, in the operation order of the planar loop."""
    ca, sa = ra[0, 0], ra[1, 0]
    d0, d1 = tb[0] - ta[0], tb[1] - ta[1]
    x = ca * d0 + sa * d1
    y = ca * d1 - sa * d0
    cab = ca * rb[0, 0] + sa * rb[1, 0]
    sab = ca * rb[1, 0] - sa * rb[0, 0]
    cz, sz = zr[0, 0], zr[1, 0]
    u0, u1 = x - zt[0], y - zt[1]
    t0 = cz * u0 + sz * u1
    t1 = cz * u1 - sz * u0
    th = math.atan2(cz * sab - sz * cab, cz * cab + sz * sab)
    a = abs(th)
    if a < SMALL_ANGLE:
        cc = 1.0 / 12.0 + a * a / 720.0
    else:
        cc = 1.0 / (a * a) - math.cos(0.5 * a) / (2.0 * a * math.sin(0.5 * a))
    alpha = 1.0 - cc * th * th
    e = np.array([alpha * t0 + 0.5 * th * t1, alpha * t1 - 0.5 * th * t0, 0.0, 0.0, 0.0, th])
    return chi2_in_order(info, e)


def assemble_in_order(ja: np.ndarray, jb: np.ndarray, info: np.ndarray, weight: np.ndarray,
                      var_a: np.ndarray, var_b: np.ndarray, edge_off: np.ndarray,
                      dofs: tuple[int, ...], indptr: np.ndarray, data: np.ndarray,
                      grad: np.ndarray, e: np.ndarray) -> None:
    """The relative constraints' terms of the exact solver's normal equations (layout of
    :mod:`hybridpgo.solvers._gn_kernels`) from given Jacobians ``ja, jb`` (M, 6, 6), errors
    ``e`` (M, 6) and robust weights, with every product summed over all six rows in order
    (the kernel leaves out the Jacobians' structural zeros).  Plain Python: for small graphs."""
    nd = len(dofs)
    data[:] = 0.0
    grad[:] = 0.0
    for c in range(ja.shape[0]):
        om = info[c]
        oe = [sum_in_order(om[i, k] * e[c, k] for k in range(6)) for i in range(6)]
        wa = [[sum_in_order(om[i, k] * ja[c, k, dofs[q]] for k in range(6)) for q in range(nd)]
              for i in range(6)]
        wb = [[sum_in_order(om[i, k] * jb[c, k, dofs[q]] for k in range(6)) for q in range(nd)]
              for i in range(6)]
        wc = weight[c]
        if wc != 1.0:
            oe = [x * wc for x in oe]
            wa = [[x * wc for x in row] for row in wa]
            wb = [[x * wc for x in row] for row in wb]
        va, vb = int(var_a[c]), int(var_b[c])

        def diag(j: np.ndarray, w: list[list[float]], v: int) -> None:
            for q in range(nd):
                col = indptr[nd * v + q] - q
                for p in range(q, nd):
                    data[col + p] += sum_in_order(j[k, dofs[p]] * w[k][q] for k in range(6))

        def lower(j: np.ndarray, w: list[list[float]], v: int, k: int) -> None:
            for q in range(nd):
                col = indptr[nd * v + q] + nd - q + nd * k
                for p in range(nd):
                    data[col + p] += sum_in_order(j[i, dofs[p]] * w[i][q] for i in range(6))

        for j, v, w in ((ja[c], va, wa), (jb[c], vb, wb)):
            if v >= 0:
                diag(j, w, v)
                for p in range(nd):
                    grad[6 * v + dofs[p]] += sum_in_order(j[k, dofs[p]] * oe[k]
                                                          for k in range(6))
        if va >= 0 and vb >= 0:
            if va > vb:
                lower(ja[c], wb, vb, int(edge_off[c]))
            elif vb > va:
                lower(jb[c], wa, va, int(edge_off[c]))
            else:
                diag(ja[c], wb, va)
                diag(jb[c], wa, va)


def sum_in_order(terms: Iterable[float]) -> float:
    """``0.0 + t_0 + t_1 + ...`` in float64, left to right (a kernel's accumulation loop)."""
    s = 0.0
    for t in terms:
        s += float(t)
    return s
