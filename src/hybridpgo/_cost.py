"""The cost layer: one definition of every per-constraint quantity (docs/conventions.md,
docs/mathematics.md#jacobians).

Both solvers and :mod:`hybridpgo.energy` compute a constraint's error, its inverse right
Jacobian, its whitened form, its χ² and the pose retraction through these kernels only, so they
cannot drift apart:

* relative constraint: ``e = Log(Z^-1 X_a^-1 X_b)`` (tangent order rho, phi), ``Jr^-1(e)`` and
  the Jacobians of e by both poses (:func:`edge_linearization9`);
  on planar poses and data the same quantities by SE(2)'s formulas (:func:`planar_residual`,
  :func:`planar_jacobians`: the planar system of the exact solver);
* position ("GPS") constraint: ``e = p_n - g``;
* ``χ² = e^T Omega e`` (no 1/2), whitening with ``L^T`` where ``Omega = L L^T``;
* the retraction ``T <- T Exp(s xi)``, followed by one Newton step towards the polar factor.

All kernels are allocation-free: the caller passes scratch buffers, so they can run in a
per-constraint hot loop (docs/contributing.md#kernels).  A robust kernel
(docs/conventions.md#robust-kernels) enters as a weight on the
χ² (exact solver) or on the whitened rows (hybrid solver), computed by :func:`robust_cost`
only: ``E_rho = sum_c rho(s_c)`` with ``s_c`` the χ² of constraint c (relative or position)
and the IRLS weight ``w_c = rho'(s_c)``.
"""

from __future__ import annotations

import math

import numpy as np

from ._numba import kernel
from ._robust import ROBUST_CAUCHY as ROBUST_CAUCHY
from ._robust import ROBUST_DEFAULT_SCALE as ROBUST_DEFAULT_SCALE
from ._robust import ROBUST_GEMAN_MCCLURE as ROBUST_GEMAN_MCCLURE
from ._robust import ROBUST_HUBER as ROBUST_HUBER
from ._robust import ROBUST_NAMES as ROBUST_NAMES
from ._robust import ROBUST_NONE as ROBUST_NONE
from ._robust import default_robust_scale as default_robust_scale
from ._robust import robust_kind as robust_kind
from .geometry._kernels import (
    E6,
    M3,
    SMALL_ANGLE,
    _mul3,
    _skew3,
    _tmulv,
    _transpose3,
    edge_error9,
    edge_error_into,
    jl_inv_coeff,
    jr_inv9,
    jr_inv_blocks,
    row3,
    row3x3,
    skew_into,
)

#: Scratch (3, 3) matrices :func:`residual_and_jr_inv` needs.
SCRATCH = 12


@kernel
def robust_cost(kind: int, delta: float, s: float) -> tuple[float, float]:
    """``(rho(s), w = rho'(s))`` of robust kernel ``kind`` with scale ``delta``
    (docs/conventions.md#robust-kernels).

    ``s = e^T Omega e`` (no 1/2), g2o's conventions, ``d2 = delta^2``:

    * none: ``rho = s``, ``w = 1``;
    * Huber: ``rho = s`` for ``s <= d2``, else ``2 delta sqrt(s) - d2``;
      ``w = min(1, delta / sqrt(s))``;
    * Cauchy: ``rho = d2 log(1 + s/d2)``, ``w = d2 / (d2 + s)``;
    * Geman-McClure: ``rho = d2 s / (d2 + s)``, ``w = (d2 / (d2 + s))^2``.

    A non-finite s gives ``(s, 0)`` (the callers reject non-finite energies).
    """
    if kind == ROBUST_NONE:
        return s, 1.0
    if not math.isfinite(s):
        return s, 0.0
    d2 = delta * delta
    if kind == ROBUST_HUBER:
        if s <= d2:
            return s, 1.0
        r = math.sqrt(s)
        return 2.0 * delta * r - d2, delta / r
    if kind == ROBUST_CAUCHY:
        return d2 * math.log1p(s / d2), d2 / (d2 + s)
    q = d2 / (d2 + s)  # Geman-McClure
    return s * q, q * q


@kernel
def robust_costs(kind: int, delta: float, s: np.ndarray, out_rho: np.ndarray,
                 out_w: np.ndarray) -> None:
    """:func:`robust_cost` of every entry of ``s`` (into ``out_rho``, ``out_w``)."""
    for c in range(s.shape[0]):
        out_rho[c], out_w[c] = robust_cost(kind, delta, s[c])


@kernel
def robust_whitening(kind: int, delta: float, r: np.ndarray, n: int) -> float:
    """``sqrt(w)`` for a whitened residual ``r`` (n,): ``s = |r|^2 = e^T Omega e``, so the
    whitening ``sqrt(w) L^T`` makes a step weigh the constraint as IRLS does
    (docs/conventions.md#robust-kernels)."""
    s = 0.0
    for i in range(n):
        s += r[i] * r[i]
    return math.sqrt(robust_cost(kind, delta, s)[1])


@kernel
def relative_residual(zr: np.ndarray, zt: np.ndarray, ra: np.ndarray, ta: np.ndarray,
                      rb: np.ndarray, tb: np.ndarray, e: np.ndarray, ws: np.ndarray) -> None:
    """``e = Log(Z^-1 X_a^-1 X_b)`` (6,); ``ws`` (>= 2, 3, 3) scratch.

    On return ``ws[0]`` holds ``R_a^T R_b`` and ``ws[1][0]`` holds ``R_a^T (t_b - t_a)``.
    """
    edge_error_into(ra, ta, rb, tb, zr, zt, ws[0], ws[1][0], e)


@kernel
def residual_and_jr_inv(zr: np.ndarray, zt: np.ndarray, ra: np.ndarray, ta: np.ndarray,
                        rb: np.ndarray, tb: np.ndarray, e: np.ndarray,
                        ws: np.ndarray) -> None:
    """``e = Log(Z^-1 X_a^-1 X_b)`` and the blocks of ``Jr^-1(e) = [[J, K], [0, J]]``.

    ``ws`` is (SCRATCH, 3, 3) scratch; on return ``J = ws[8]``, ``K = ws[9]``,
    ``X_a^-1 X_b = (ws[10], ws[11][0])``.
    """
    edge_error_into(ra, ta, rb, tb, zr, zt, ws[10], ws[11][0], e)
    jr_inv_blocks(e, ws)


@kernel
def edge_linearization9(rot: np.ndarray, trans: np.ndarray, edge_rot: np.ndarray,
                        edge_trans: np.ndarray, a: int, b: int, c: int
                        ) -> tuple[E6, M3, M3, M3, M3]:
    """``(e, J, K, JR, JT)`` of relative constraint c between poses a and b, read by index
    (no array views, docs/contributing.md#kernels): the error e and the blocks of its
    Jacobians as row-major 9-tuples, ``jb = Jr^-1(e) = [[J, K], [0, J]]`` and
    ``ja = -Jr^-1(e) Ad(X_b^-1 X_a) = -[[JR, JT], [0, JR]]``.

    With X_b^-1 X_a = (R, t) = (R_ab^T, -R_ab^T t_ab) and Ad = [[R, [t]x R], [0, R]]:
    ``JR = J R`` and ``JT = J [t]x R + K R``.
    """
    e, rab, tab = edge_error9(row3x3(rot, a), row3(trans, a), row3x3(rot, b), row3(trans, b),
                              row3x3(edge_rot, c), row3(edge_trans, c))
    jm, km = jr_inv9(e)
    r = _transpose3(rab)
    s = _tmulv(rab, tab)  # R_ab^T t_ab
    txr = _mul3(_skew3(-s[0], -s[1], -s[2]), r)  # [t]x R
    jr = _mul3(jm, r)
    jt = _mul3(jm, txr)
    kr = _mul3(km, r)
    return e, jm, km, jr, (jt[0] + kr[0], jt[1] + kr[1], jt[2] + kr[2], jt[3] + kr[3],
                           jt[4] + kr[4], jt[5] + kr[5], jt[6] + kr[6], jt[7] + kr[7],
                           jt[8] + kr[8])


#: Below this angle (radians) :func:`planar_jacobians` takes ``(th - sin th) / th^2`` from its
#: series (to th^13: truncated below 1e-15 relative there), where the closed form cancels.
PLANAR_SERIES_ANGLE = 0.5


@kernel
def planar_error(ca: float, sa: float, ta0: float, ta1: float, cb: float, sb: float,
                 tb0: float, tb1: float, cz: float, sz: float, tz0: float, tz1: float
                 ) -> tuple[float, float, float, tuple[float, float, float, float, float]]:
    """``(rho_x, rho_y, theta, rel)`` of :func:`planar_residual` from the poses' and the
    measurement's (cos, sin, x, y) (no array views)."""
    d0 = tb0 - ta0
    d1 = tb1 - ta1
    x = ca * d0 + sa * d1
    y = ca * d1 - sa * d0
    cab = ca * cb + sa * sb
    sab = ca * sb - sa * cb
    u0 = x - tz0
    u1 = y - tz1
    t0 = cz * u0 + sz * u1
    t1 = cz * u1 - sz * u0
    th = math.atan2(cz * sab - sz * cab, cz * cab + sz * sab)
    alpha = 1.0 - jl_inv_coeff(abs(th)) * th * th  # (th / 2) cot(th / 2)
    return alpha * t0 + 0.5 * th * t1, alpha * t1 - 0.5 * th * t0, th, (cab, sab, x, y, alpha)


@kernel
def planar_residual(zr: np.ndarray, zt: np.ndarray, ra: np.ndarray, ta: np.ndarray,
                    rb: np.ndarray, tb: np.ndarray, e: np.ndarray
                    ) -> tuple[float, float, float, float, float]:
    """:func:`relative_residual` of planar poses and measurement (rotations about z, no z
    translation: ``graph.planar_motions``): the SE(2) logarithm ``e = (rho_x, rho_y, 0, 0, 0,
    theta)``, which is SE(3)'s restricted to the plane (docs/mathematics.md#planar-reduction).

    Returns ``X_a^-1 X_b`` as ``(cos, sin, x, y)`` and ``alpha = (theta / 2) cot(theta / 2)``
    (for :func:`planar_jacobians`).
    """
    e0, e1, th, rel = planar_error(ra[0, 0], ra[1, 0], ta[0], ta[1], rb[0, 0], rb[1, 0],
                                   tb[0], tb[1], zr[0, 0], zr[1, 0], zt[0], zt[1])
    e[0] = e0
    e[1] = e1
    e[2] = 0.0
    e[3] = 0.0
    e[4] = 0.0
    e[5] = th
    return rel


@kernel
def planar_jacobians(e: np.ndarray, rel: tuple[float, float, float, float, float],
                     ja: np.ndarray, jb: np.ndarray) -> None:
    """``jb = Jr^-1(e)`` and ``ja = -Jr^-1(e) Ad(X_b^-1 X_a)`` of a planar constraint (its
    error ``e`` and ``rel`` from :func:`planar_residual`) as (6, 6) matrices: the
    (x, y, yaw) rows and columns of SE(3)'s, 0 elsewhere (the out-of-plane rows and columns do
    not enter the planar system; docs/mathematics.md#planar-reduction)."""
    th = e[5]
    r0 = e[0]
    r1 = e[1]
    h = 0.5 * th
    cab, sab, x, y, alpha = rel
    t2 = th * th
    # ca = (1 - cos th) / th^2 = (sin(th / 2) / th)^2 / 2, cb = (th - sin th) / th^2 (its
    # series below PLANAR_SERIES_ANGLE, where the difference cancels)
    if th == 0.0:
        ca = 0.5
    else:
        sh = math.sin(0.5 * th) / (0.5 * th)
        ca = 0.5 * sh * sh
    if abs(th) < PLANAR_SERIES_ANGLE:
        cb = th * (1.0 / 6.0 - t2 * (1.0 / 120.0 - t2 * (1.0 / 5040.0 - t2 * (
            1.0 / 362880.0 - t2 * (1.0 / 39916800.0 - t2 * (
                1.0 / 6227020800.0 - t2 / 1307674368000.0))))))
    else:
        cb = (th - math.sin(th)) / t2
    # Jr's yaw column (x, y rows), then Jr^-1's: -M^-1 b with M^-1 = [[alpha, -h], [h, alpha]]
    b0 = r0 * cb - r1 * ca
    b1 = r0 * ca + r1 * cb
    k0 = -(alpha * b0 - h * b1)
    k1 = -(h * b0 + alpha * b1)
    for i in range(6):
        for j in range(6):
            ja[i, j] = 0.0
            jb[i, j] = 0.0
    jb[0, 0] = alpha
    jb[0, 1] = -h
    jb[0, 5] = k0
    jb[1, 0] = h
    jb[1, 1] = alpha
    jb[1, 5] = k1
    jb[5, 5] = 1.0
    # Ad(X_b^-1 X_a) = [[R, (ty, -tx)], [0, 1]], R = R_ab^T, t = -R_ab^T t_ab
    tx = -(cab * x + sab * y)
    ty = sab * x - cab * y
    a00, a01, a02 = cab, sab, ty
    a10, a11, a12 = -sab, cab, -tx
    ja[0, 0] = -(alpha * a00 - h * a10)
    ja[0, 1] = -(alpha * a01 - h * a11)
    ja[0, 5] = -(alpha * a02 - h * a12 + k0)
    ja[1, 0] = -(h * a00 + alpha * a10)
    ja[1, 1] = -(h * a01 + alpha * a11)
    ja[1, 5] = -(h * a02 + alpha * a12 + k1)
    ja[5, 5] = -1.0


@kernel
def jr_inv_matrix(ws: np.ndarray, out: np.ndarray) -> None:
    """The (6, 6) ``Jr^-1`` from the blocks :func:`residual_and_jr_inv` left in ``ws``."""
    jm = ws[8]
    km = ws[9]
    for i in range(3):
        for j in range(3):
            out[i, j] = jm[i, j]
            out[i, 3 + j] = km[i, j]
            out[3 + i, j] = 0.0
            out[3 + i, 3 + j] = jm[i, j]


@kernel
def gps_residual(p: np.ndarray, g: np.ndarray, e: np.ndarray) -> None:
    """``e = p_n - g`` (3,)."""
    for i in range(3):
        e[i] = p[i] - g[i]


@kernel
def chi2(info: np.ndarray, e: np.ndarray, n: int, oe: np.ndarray) -> float:
    """``e^T Omega e`` for the leading n entries (no 1/2, docs/conventions.md); ``oe`` receives
    ``Omega e`` (the exact solver's gradient needs it)."""
    total = 0.0
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += info[i, j] * e[j]
        oe[i] = s
        total += e[i] * s
    return total


@kernel
def whiten_residual(lt: np.ndarray, e: np.ndarray, n: int, out: np.ndarray) -> None:
    """``out = -L^T e`` (n,): the whitened residual ``r`` of the step equations
    (docs/mathematics.md#jacobians)."""
    for p in range(n):
        acc = 0.0
        for q in range(n):
            acc += lt[p, q] * e[q]
        out[p] = -acc


@kernel
def whiten_rows(lt: np.ndarray, m: np.ndarray, n: int, out: np.ndarray) -> None:
    """``out[:n, :6] = L^T m[:n, :6]`` with ``L^T`` (n, n) upper triangular."""
    for p in range(n):
        for j in range(6):
            acc = 0.0
            for q in range(p, n):
                acc += lt[p, q] * m[q, j]
            out[p, j] = acc


@kernel
def _chi2_at(edge_info: np.ndarray, c: int, e: tuple[float, float, float, float, float, float]
             ) -> float:
    """:func:`chi2` of the error tuple ``e`` with ``edge_info[c]``, in :func:`chi2`'s order."""
    total = 0.0
    for i in range(6):
        s = 0.0
        for j in range(6):
            s += edge_info[c, i, j] * e[j]
        total += e[i] * s
    return total


@kernel
def relative_chi2_at(rot: np.ndarray, trans: np.ndarray, a: int, b: int, edge_rot: np.ndarray,
                     edge_trans: np.ndarray, edge_info: np.ndarray, c: int) -> float:
    """χ² of relative constraint ``c`` between global poses ``a`` and ``b``, read from the
    arrays by index (no array views: a loop over the constraints runs several times faster
    than one passing each constraint's rows to :func:`relative_residual` and :func:`chi2`;
    same operations in the same order, so the same bits)."""
    e = edge_error9(row3x3(rot, a), row3(trans, a), row3x3(rot, b), row3(trans, b),
                    row3x3(edge_rot, c), row3(edge_trans, c))[0]
    return _chi2_at(edge_info, c, e)


@kernel
def planar_chi2_at(rot: np.ndarray, trans: np.ndarray, a: int, b: int, edge_rot: np.ndarray,
                   edge_trans: np.ndarray, edge_info: np.ndarray, c: int) -> float:
    """:func:`relative_chi2_at` of a planar constraint at planar poses
    (:func:`planar_residual`), read by index."""
    e0, e1, th, _ = planar_error(rot[a, 0, 0], rot[a, 1, 0], trans[a, 0], trans[a, 1],
                                 rot[b, 0, 0], rot[b, 1, 0], trans[b, 0], trans[b, 1],
                                 edge_rot[c, 0, 0], edge_rot[c, 1, 0], edge_trans[c, 0],
                                 edge_trans[c, 1])
    return _chi2_at(edge_info, c, (e0, e1, 0.0, 0.0, 0.0, th))


@kernel
def gps_chi2(p: np.ndarray, g: np.ndarray, info: np.ndarray, e: np.ndarray,
             oe: np.ndarray) -> float:
    """χ² of a position constraint at position p (``e`` receives its error)."""
    gps_residual(p, g, e)
    return chi2(info, e, 3, oe)


@kernel
def constraint_energies(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                        edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
                        gps_nodes: np.ndarray, gps_pos: np.ndarray, gps_info: np.ndarray,
                        out_rel: np.ndarray, out_gps: np.ndarray) -> None:
    """χ² of every relative (M,) and position (G,) constraint at global poses (may be inf/nan)."""
    e = np.empty(6)
    oe = np.empty(6)
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        out_rel[c] = relative_chi2_at(rot, trans, a, b, edge_rot, edge_trans, edge_info, c)
    for c in range(gps_nodes.shape[0]):
        out_gps[c] = gps_chi2(trans[gps_nodes[c]], gps_pos[c], gps_info[c], e, oe)


@kernel
def constraint_errors(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                      edge_rot: np.ndarray, edge_trans: np.ndarray, gps_nodes: np.ndarray,
                      gps_pos: np.ndarray, out_rel: np.ndarray, out_gps: np.ndarray) -> None:
    """Error vectors of every relative (M, 6) and position (G, 3) constraint at global poses:
    the ``e`` whose χ² :func:`constraint_energies` sums (not a hot path: reporting only)."""
    ws = np.empty((3, 3, 3))
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        relative_residual(edge_rot[c], edge_trans[c], rot[a], trans[a], rot[b], trans[b],
                          out_rel[c], ws)
    for c in range(gps_nodes.shape[0]):
        gps_residual(trans[gps_nodes[c]], gps_pos[c], out_gps[c])


@kernel
def total_energy(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                 edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
                 gps_nodes: np.ndarray, gps_pos: np.ndarray, gps_info: np.ndarray) -> float:
    """``E = sum_c e_c^T Omega_c e_c`` at global poses (may be inf/nan), summed in order."""
    e = np.empty(6)
    oe = np.empty(6)
    total = 0.0
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        total += relative_chi2_at(rot, trans, a, b, edge_rot, edge_trans, edge_info, c)
    for c in range(gps_nodes.shape[0]):
        total += gps_chi2(trans[gps_nodes[c]], gps_pos[c], gps_info[c], e, oe)
    return total


@kernel
def robust_total_energy(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                        edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
                        gps_nodes: np.ndarray, gps_pos: np.ndarray, gps_info: np.ndarray,
                        kind: int, delta: float, planar: bool = False) -> tuple[float, float]:
    """``(E_rho, E)``: robust and plain energy at global poses (may be inf/nan), in order.

    ``E_rho = sum_c rho(s_c)`` over the relative and the GPS constraints (``kind`` 0: no
    kernel, ``E_rho = E``).  ``planar``: the poses and measurements are planar
    (``graph.planar_motions``): each relative χ² from :func:`planar_chi2_at`.
    """
    e = np.empty(6)
    oe = np.empty(6)
    total = 0.0
    plain = 0.0
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        if planar:
            s = planar_chi2_at(rot, trans, a, b, edge_rot, edge_trans, edge_info, c)
        else:
            s = relative_chi2_at(rot, trans, a, b, edge_rot, edge_trans, edge_info, c)
        total += robust_cost(kind, delta, s)[0]
        plain += s
    for c in range(gps_nodes.shape[0]):
        s = gps_chi2(trans[gps_nodes[c]], gps_pos[c], gps_info[c], e, oe)
        total += robust_cost(kind, delta, s)[0]
        plain += s
    return total, plain


@kernel
def retract_into(r_in: np.ndarray, t_in: np.ndarray, xi: np.ndarray, scale: float,
                 r_out: np.ndarray, t_out: np.ndarray, er: np.ndarray, tmp: np.ndarray) -> None:
    """``T_out = T_in Exp(scale xi)``, rotation re-orthonormalized; ``er``, ``tmp`` (3, 3) scratch.

    The output may alias the input (in-place update).  One Newton step towards the polar factor,
    ``R <- R (3I - R^T R) / 2``, keeps the rotation orthonormal to rounding over many steps.
    """
    rx, ry, rz = scale * xi[0], scale * xi[1], scale * xi[2]
    px, py, pz = scale * xi[3], scale * xi[4], scale * xi[5]
    th2 = px * px + py * py + pz * pz
    th = math.sqrt(th2)
    if th < SMALL_ANGLE:
        sa = 1.0 - th2 / 6.0  # sin(th)/th
        sb = 0.5 - th2 / 24.0  # (1 - cos th)/th^2
        sc = 1.0 / 6.0 - th2 / 120.0  # (th - sin th)/th^3
    else:
        sn = math.sin(th)
        sh = math.sin(0.5 * th)
        sa = sn / th
        sb = 2.0 * sh * sh / th2
        sc = (th - sn) / (th2 * th)
    # K = [phi]x, K^2 = phi phi^T - th^2 I
    k = tmp
    skew_into(px, py, pz, k)
    ph = (px, py, pz)
    for i in range(3):
        for j in range(3):
            k2 = ph[i] * ph[j] - (th2 if i == j else 0.0)
            idn = 1.0 if i == j else 0.0
            er[i, j] = idn + sa * k[i, j] + sb * k2
    # t_exp = V rho, V = I + sb K + sc K^2
    rho = (rx, ry, rz)
    dt0 = rx
    dt1 = ry
    dt2 = rz
    for j in range(3):
        v0 = sb * k[0, j] + sc * (ph[0] * ph[j] - (th2 if j == 0 else 0.0))
        v1 = sb * k[1, j] + sc * (ph[1] * ph[j] - (th2 if j == 1 else 0.0))
        v2 = sb * k[2, j] + sc * (ph[2] * ph[j] - (th2 if j == 2 else 0.0))
        dt0 += v0 * rho[j]
        dt1 += v1 * rho[j]
        dt2 += v2 * rho[j]
    for i in range(3):
        t_out[i] = t_in[i] + (r_in[i, 0] * dt0 + r_in[i, 1] * dt1 + r_in[i, 2] * dt2)
    for i in range(3):
        for j in range(3):
            tmp[i, j] = r_in[i, 0] * er[0, j] + r_in[i, 1] * er[1, j] + r_in[i, 2] * er[2, j]
    for i in range(3):
        for j in range(3):
            er[i, j] = -(tmp[0, i] * tmp[0, j] + tmp[1, i] * tmp[1, j] + tmp[2, i] * tmp[2, j])
        er[i, i] += 3.0
    for i in range(3):
        for j in range(3):
            r_out[i, j] = 0.5 * (tmp[i, 0] * er[0, j] + tmp[i, 1] * er[1, j]
                                 + tmp[i, 2] * er[2, j])
