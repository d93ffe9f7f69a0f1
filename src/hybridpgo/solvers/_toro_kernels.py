"""Numba kernels of the TORO-style baseline (``hybridpgo.solvers.toro``, docs/mathematics.md#toro).

Layout (docs/contributing.md#data): tree nodes ``0..N-1`` are the poses, node ``N`` the earth when
the graph
has GPS constraints.  Constraints are the M relative edges, then the G GPS readings (constraint
``M + g`` joins the earth to ``gps_nodes[g]``).  Paths are CSR: the a-side nodes from a up to
(excluding) the top with sign -1, then the b-side nodes from b up with sign +1.

Every constraint update works in the frame of the constraint's *top* (its lowest common
ancestor): the poses of the path nodes relative to the top are composed from the local
transforms along the path, the update is made there, and the path's local transforms are
rewritten.  The top and everything outside the path keep their local transforms, so this is the
global-frame rule of docs/mathematics.md#toro exactly (a rotation about the global axis ``a`` is a
rotation about
``R_top^T a`` in the top's frame), at O(path length) cost and without stale global poses.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._numba import cycle_counter, kernel
from ..geometry._kernels import so3_log_into

# ----------------------------------------------------------------------------- small maths


@kernel
def _compose_into(qa: np.ndarray, pa: np.ndarray, rb: np.ndarray, tb: np.ndarray,
                  qout: np.ndarray, pout: np.ndarray) -> None:
    """(qout, pout) = (qa, pa) * (rb, tb)."""
    for r in range(3):
        for s in range(3):
            qout[r, s] = qa[r, 0] * rb[0, s] + qa[r, 1] * rb[1, s] + qa[r, 2] * rb[2, s]
        pout[r] = pa[r] + qa[r, 0] * tb[0] + qa[r, 1] * tb[1] + qa[r, 2] * tb[2]


@kernel
def _local_into(qa: np.ndarray, pa: np.ndarray, qb: np.ndarray, pb: np.ndarray,
                rout: np.ndarray, tout: np.ndarray, with_rotation: bool) -> None:
    """(rout, tout) = (qa, pa)^-1 * (qb, pb); the rotation only when ``with_rotation``."""
    d0 = pb[0] - pa[0]
    d1 = pb[1] - pa[1]
    d2 = pb[2] - pa[2]
    for r in range(3):
        if with_rotation:
            for s in range(3):
                rout[r, s] = qa[0, r] * qb[0, s] + qa[1, r] * qb[1, s] + qa[2, r] * qb[2, s]
        tout[r] = qa[0, r] * d0 + qa[1, r] * d1 + qa[2, r] * d2


@kernel
def _orthonormalize_rows(r: np.ndarray) -> None:
    """Gram-Schmidt on the rows of a nearly orthonormal R, in place (removes rounding drift)."""
    n0 = math.sqrt(r[0, 0] * r[0, 0] + r[0, 1] * r[0, 1] + r[0, 2] * r[0, 2])
    for s in range(3):
        r[0, s] /= n0
    d = r[0, 0] * r[1, 0] + r[0, 1] * r[1, 1] + r[0, 2] * r[1, 2]
    for s in range(3):
        r[1, s] -= d * r[0, s]
    n1 = math.sqrt(r[1, 0] * r[1, 0] + r[1, 1] * r[1, 1] + r[1, 2] * r[1, 2])
    for s in range(3):
        r[1, s] /= n1
    r[2, 0] = r[0, 1] * r[1, 2] - r[0, 2] * r[1, 1]
    r[2, 1] = r[0, 2] * r[1, 0] - r[0, 0] * r[1, 2]
    r[2, 2] = r[0, 0] * r[1, 1] - r[0, 1] * r[1, 0]


@kernel
def _rotate_left(ax: float, ay: float, az: float, angle: float, q: np.ndarray,
                 tmp: np.ndarray) -> None:
    """q <- Rot(a, angle) q for the unit axis a (Rodrigues), in place."""
    s = math.sin(angle)
    c1 = 1.0 - math.cos(angle)
    # Rot = I + s K + c1 K^2, K = [a]x, K^2 = a a^T - I
    m00 = 1.0 + c1 * (ax * ax - 1.0)
    m11 = 1.0 + c1 * (ay * ay - 1.0)
    m22 = 1.0 + c1 * (az * az - 1.0)
    m01 = -s * az + c1 * ax * ay
    m10 = s * az + c1 * ax * ay
    m02 = s * ay + c1 * ax * az
    m20 = -s * ay + c1 * ax * az
    m12 = -s * ax + c1 * ay * az
    m21 = s * ax + c1 * ay * az
    for j in range(3):
        x = q[0, j]
        y = q[1, j]
        z = q[2, j]
        tmp[0, j] = m00 * x + m01 * y + m02 * z
        tmp[1, j] = m10 * x + m11 * y + m12 * z
        tmp[2, j] = m20 * x + m21 * y + m22 * z
    q[:, :] = tmp


# ----------------------------------------------------------------------------- one wing
# A wing is the path positions ``lo .. hi-1`` of one side, listed from its endpoint up to the
# node below the top (position ``hi - 1``); the kernels below walk it from the top down.


@kernel
def _wing_poses(path_node: np.ndarray, s0: int, lo: int, hi: int, rot: np.ndarray,
                trans: np.ndarray, wq: np.ndarray, wp: np.ndarray, eye: np.ndarray,
                zero: np.ndarray) -> None:
    """Poses ``(wq[j], wp[j])`` of the wing's nodes relative to the top, composed from the
    local transforms downwards."""
    for j in range(hi - 1, lo - 1, -1):
        node = path_node[s0 + j]
        if j == hi - 1:
            _compose_into(eye, zero, rot[node], trans[node], wq[j], wp[j])
        else:
            _compose_into(wq[j + 1], wp[j + 1], rot[node], trans[node], wq[j], wp[j])


@kernel
def _rotate_wing(path_node: np.ndarray, s0: int, lo: int, hi: int, w_rot: np.ndarray,
                 ax: float, ay: float, az: float, step: float, wq: np.ndarray,
                 tmp: np.ndarray) -> None:
    """Turn node j's rotation about the axis a by ``step`` times the cumulative weight from
    the top to j."""
    cum = 0.0
    for j in range(hi - 1, lo - 1, -1):
        cum += w_rot[path_node[s0 + j]]
        _rotate_left(ax, ay, az, step * cum, wq[j], tmp)


@kernel
def _rebend_wing(path_node: np.ndarray, s0: int, lo: int, hi: int, trans: np.ndarray,
                 wq: np.ndarray, wp: np.ndarray) -> None:
    """Positions ``wp`` of the wing's nodes from their (turned) rotations ``wq`` and the kept
    local translations."""
    for j in range(hi - 1, lo - 1, -1):
        node = path_node[s0 + j]
        if j == hi - 1:
            for r in range(3):
                wp[j, r] = trans[node, r]
        else:
            for r in range(3):
                wp[j, r] = wp[j + 1, r] + (wq[j + 1, r, 0] * trans[node, 0]
                                           + wq[j + 1, r, 1] * trans[node, 1]
                                           + wq[j + 1, r, 2] * trans[node, 2])


@kernel
def _shift_wing(path_node: np.ndarray, s0: int, lo: int, hi: int, w_trans: np.ndarray,
                gain: float, t0: float, t1: float, t2: float, wp: np.ndarray) -> None:
    """Move node j by ``gain`` times the cumulative weight from the top to j times ``t``."""
    cum = 0.0
    for j in range(hi - 1, lo - 1, -1):
        cum += w_trans[path_node[s0 + j]]
        wp[j, 0] += gain * cum * t0
        wp[j, 1] += gain * cum * t1
        wp[j, 2] += gain * cum * t2


# ----------------------------------------------------------------------------- the update


@kernel
def update_constraint(
    c: int, k: float, prob: tuple[Any, ...], state: tuple[Any, ...], work: tuple[Any, ...]
) -> int:
    """Relax constraint ``c`` once with sweep counter ``k`` (docs/mathematics.md#toro: the
    rotation, then the translation).

    ``prob = (num_edges, path_ptr, path_node, path_sign, top, meas_rot, meas_trans, rho, tau,
    gamma_r, gamma_t, w_rot, w_trans)``: ``meas_trans`` has M + G rows (a GPS constraint's row
    is the measured position), ``meas_rot`` M; ``rho``/``tau`` the per-constraint gains' Omega
    terms (rho = 0 for GPS); ``w_rot``/``w_trans`` the node weights 1/M_n.
    ``state = (rot, trans)``: local transforms, updated in place.
    ``work = (wq, wp, tmp, eye, zero)``: workspaces of the longest path.

    Returns 0, or 1 when the update was not finite (then nothing is written).
    """
    (num_edges, ptr, path_node, path_sign, _top, meas_rot, meas_trans, rho, tau, gamma_r,
     gamma_t, w_rot, w_trans) = prob
    rot, trans = state
    wq, wp, tmp, eye, zero = work
    s0 = ptr[c]
    ell = ptr[c + 1] - s0
    if ell == 0:
        return 0
    na = 0
    while na < ell and path_sign[s0 + na] < 0:
        na += 1
    # poses of the path nodes relative to the top, composed down each wing from the top
    _wing_poses(path_node, s0, 0, na, rot, trans, wq, wp, eye, zero)
    _wing_poses(path_node, s0, na, ell, rot, trans, wq, wp, eye, zero)

    rotated = False
    if c < num_edges:
        # 1. rotation: dR = R_v1 R_e R_v2^-1 = Rot(a, theta), in the top's frame
        qv1 = wq[0] if na > 0 else eye
        qv2 = wq[na] if na < ell else eye
        re = meas_rot[c]
        for r in range(3):
            for s in range(3):
                acc = 0.0
                for u in range(3):
                    acc += (qv1[r, 0] * re[0, u] + qv1[r, 1] * re[1, u]
                            + qv1[r, 2] * re[2, u]) * qv2[s, u]
                tmp[r, s] = acc
        phi6 = np.empty(6)
        so3_log_into(tmp, phi6)
        phi = phi6[3:]
        theta = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
        if not math.isfinite(theta):
            return 1
        wsum = 0.0
        for j in range(ell):
            wsum += w_rot[path_node[s0 + j]]
        if theta > 0.0 and wsum > 0.0:
            rotated = True
            ax = phi[0] / theta
            ay = phi[1] / theta
            az = phi[2] / theta
            f_r = min(1.0, math.sqrt(ell) * rho[c] / (gamma_r * k))
            step = f_r * theta / wsum
            # C(n) - C(top): minus the cumulative weight from the top on the v1 wing, plus on v2
            _rotate_wing(path_node, s0, 0, na, w_rot, ax, ay, az, -step, wq, tmp)
            _rotate_wing(path_node, s0, na, ell, w_rot, ax, ay, az, step, wq, tmp)
            # re-bend the path: local translations are kept
            _rebend_wing(path_node, s0, 0, na, trans, wq, wp)
            _rebend_wing(path_node, s0, na, ell, trans, wq, wp)

    # 2. translation on the re-bent path: t_R = (T_v1 T_e).t - t_v2
    qv1 = wq[0] if na > 0 else eye
    pv1 = wp[0] if na > 0 else zero
    pv2 = wp[na] if na < ell else zero
    te = meas_trans[c]
    t0 = qv1[0, 0] * te[0] + qv1[0, 1] * te[1] + qv1[0, 2] * te[2] + pv1[0] - pv2[0]
    t1 = qv1[1, 0] * te[0] + qv1[1, 1] * te[1] + qv1[1, 2] * te[2] + pv1[1] - pv2[1]
    t2 = qv1[2, 0] * te[0] + qv1[2, 1] * te[1] + qv1[2, 2] * te[2] + pv1[2] - pv2[2]
    if not (math.isfinite(t0) and math.isfinite(t1) and math.isfinite(t2)):
        return 1
    wsum = 0.0
    for j in range(ell):
        wsum += w_trans[path_node[s0 + j]]
    if wsum > 0.0:
        f_t = min(1.0, ell * tau[c] / (gamma_t * k))
        g = f_t / wsum
        # (-g) c t is -(g c t) exactly, so the v1 wing moves by exactly minus the v2 rule
        _shift_wing(path_node, s0, 0, na, w_trans, -g, t0, t1, t2, wp)
        _shift_wing(path_node, s0, na, ell, w_trans, g, t0, t1, t2, wp)

    # rewrite the path's local transforms (rotations only when they turned)
    for j in range(ell):
        node = path_node[s0 + j]
        last = na - 1 if j < na else ell - 1
        if j == last:
            _local_into(eye, zero, wq[j], wp[j], rot[node], trans[node], rotated)
        else:
            _local_into(wq[j + 1], wp[j + 1], wq[j], wp[j], rot[node], trans[node], rotated)
        if rotated:
            _orthonormalize_rows(rot[node])
    return 0


@kernel
def sweep(order: np.ndarray, k: float, prob: tuple[Any, ...], state: tuple[Any, ...],
          work: tuple[Any, ...], cycles: np.ndarray) -> int:
    """Relax every constraint in ``order`` once; ``cycles[c]``: CPU cycles of c's update.

    Returns -1, or the first constraint whose update was not finite (it is skipped).
    """
    bad = -1
    for q in range(order.shape[0]):
        c = order[q]
        c0 = cycle_counter()
        status = update_constraint(c, k, prob, state, work)
        cycles[c] = cycle_counter() - c0
        if status != 0 and bad < 0:
            bad = c
    return bad
