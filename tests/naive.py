"""Plain NumPy twins of the Numba kernels, used as test oracles (docs/contributing.md#kernels,
docs/contributing.md#tests).

A twin is slow and obvious and, where possible, *independent* of the kernel it checks (a different
formula, not a copy): a matrix exponential instead of Rodrigues, an eigenvector instead of
Shepperd's method, a 4x4 homogeneous inverse instead of the closed form.  Twins work on single
elements (no batching) and never call into ``hybridpgo``.

Each kernel module gets its own section below, headed by the module it mirrors.  Append new
sections at the end; do not edit another section's twins to make a test pass.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import scipy.linalg
from scipy.spatial.transform import Rotation

FloatArray = npt.NDArray[np.float64]


# ============================================================================================
# tests/ref_kernels.py (and hybridpgo.geometry): SO(3) / SE(3)  (tests/test_geometry.py)
#
# Conventions as in the kernels: tangent xi = (rho, phi), translation first; a pose is an
# (R, t) pair; quaternions are (x, y, z, w); R = Rz(yaw) Ry(pitch) Rx(roll).
# ============================================================================================


def skew(v: FloatArray) -> FloatArray:
    """[v]x through the cross product: column j is v x e_j."""
    return np.asarray(np.cross(np.asarray(v, dtype=np.float64), np.eye(3)).T, dtype=np.float64)


def vee(m: FloatArray) -> FloatArray:
    """Inverse of :func:`skew` applied to the antisymmetric part of ``m``."""
    a = 0.5 * (m - m.T)
    return np.array([a[2, 1], a[0, 2], a[1, 0]])


def to_matrix(r: FloatArray, t: FloatArray) -> FloatArray:
    """4x4 homogeneous matrix of the pose (R, t)."""
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def from_matrix(m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(R, t) of a 4x4 homogeneous matrix."""
    return m[:3, :3].copy(), m[:3, 3].copy()


def se3_hat(xi: FloatArray) -> FloatArray:
    """4x4 twist matrix [[phi]x, rho; 0, 0] of xi = (rho, phi)."""
    m = np.zeros((4, 4))
    m[:3, :3] = skew(xi[3:])
    m[:3, 3] = xi[:3]
    return m


def se3_vee(m: FloatArray) -> FloatArray:
    """Inverse of :func:`se3_hat`."""
    return np.concatenate([m[:3, 3], vee(m[:3, :3])])


def se3_ad(xi: FloatArray) -> FloatArray:
    """6x6 ad(xi) = [[phi]x, [rho]x; 0, [phi]x] in (rho, phi) order: ad(a) b = vee([a^, b^])."""
    out = np.zeros((6, 6))
    out[:3, :3] = skew(xi[3:])
    out[3:, 3:] = skew(xi[3:])
    out[:3, 3:] = skew(xi[:3])
    return out


def _phi_series(a: FloatArray) -> FloatArray:
    """sum_n a^n / (n+1)! = top-right block of expm([[a, I], [0, 0]])."""
    n = a.shape[0]
    big = np.zeros((2 * n, 2 * n))
    big[:n, :n] = a
    big[:n, n:] = np.eye(n)
    return np.asarray(scipy.linalg.expm(big)[:n, n:], dtype=np.float64)


def matrix_to_quat_xyzw(r: FloatArray) -> FloatArray:
    """Unit quaternion (x, y, z, w), w >= 0: top eigenvector of 4 q q^T - I (Bar-Itzhack)."""
    k = np.array([
        [r[0, 0] - r[1, 1] - r[2, 2], r[0, 1] + r[1, 0], r[0, 2] + r[2, 0], r[2, 1] - r[1, 2]],
        [r[0, 1] + r[1, 0], r[1, 1] - r[0, 0] - r[2, 2], r[1, 2] + r[2, 1], r[0, 2] - r[2, 0]],
        [r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], r[2, 2] - r[0, 0] - r[1, 1], r[1, 0] - r[0, 1]],
        [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
    ])
    _, vectors = np.linalg.eigh(k)
    q = vectors[:, -1]
    q = q if q[3] >= 0.0 else -q
    return np.asarray(q / np.linalg.norm(q), dtype=np.float64)


def quat_xyzw_to_matrix(q: FloatArray) -> FloatArray:
    """R = (w^2 - v.v) I + 2 v v^T + 2 w [v]x of the normalized quaternion."""
    q = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    v, w = q[:3], q[3]
    return (w * w - v @ v) * np.eye(3) + 2.0 * np.outer(v, v) + 2.0 * w * skew(v)


def so3_left_jacobian(phi: FloatArray) -> FloatArray:
    """J_l(phi) = sum_n [phi]x^n / (n+1)!."""
    return _phi_series(skew(phi))


def so3_left_jacobian_inv(phi: FloatArray) -> FloatArray:
    """Numerical inverse of :func:`so3_left_jacobian`."""
    return np.asarray(np.linalg.inv(so3_left_jacobian(phi)), dtype=np.float64)


def se3_exp(xi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Matrix exponential of the 4x4 twist."""
    return from_matrix(scipy.linalg.expm(se3_hat(xi)))


def se3_log(r: FloatArray, t: FloatArray) -> FloatArray:
    """(rho, phi) with phi = Log(R) and rho solving J_l(phi) rho = t."""
    phi = Rotation.from_matrix(r).as_rotvec()  # SciPy's Log(R), |phi| <= pi
    rho = np.linalg.solve(so3_left_jacobian(phi), t)
    return np.concatenate([rho, phi])


def se3_left_jacobian(xi: FloatArray) -> FloatArray:
    """J_l(xi) = sum_n ad(xi)^n / (n+1)! of SE(3), (rho, phi) order."""
    return _phi_series(se3_ad(xi))


def se3_left_jacobian_inv(xi: FloatArray) -> FloatArray:
    """Numerical inverse of :func:`se3_left_jacobian`."""
    return np.asarray(np.linalg.inv(se3_left_jacobian(xi)), dtype=np.float64)


def se3_right_jacobian_inv(xi: FloatArray) -> FloatArray:
    """J_r(xi)^-1 = (sum_n (-ad(xi))^n / (n+1)!)^-1."""
    return np.asarray(np.linalg.inv(_phi_series(-se3_ad(xi))), dtype=np.float64)


def se3_adjoint(r: FloatArray, t: FloatArray) -> FloatArray:
    """Ad(T), column by column: Ad(T) e_i = vee(T hat(e_i) T^-1)."""
    m = to_matrix(r, t)
    m_inv = np.linalg.inv(m)
    return np.stack([se3_vee(m @ se3_hat(e) @ m_inv) for e in np.eye(6)], axis=1)


def orthonormalize(r: FloatArray) -> FloatArray:
    """Nearest rotation in the Frobenius norm: the polar factor U V^T of the SVD."""
    u, _, vt = np.linalg.svd(r)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return np.asarray(u @ d @ vt, dtype=np.float64)


def _rx(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_rpy_to_matrix(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll) from the elementary rotations."""
    return _rz(yaw) @ _ry(pitch) @ _rx(roll)


def matrix_to_euler_rpy(r: FloatArray) -> FloatArray:
    """Textbook (roll, pitch, yaw); only meaningful away from gimbal lock (|pitch| < pi/2)."""
    pitch = np.arctan2(-r[2, 0], np.hypot(r[0, 0], r[1, 0]))
    return np.array([np.arctan2(r[2, 1], r[2, 2]), pitch, np.arctan2(r[1, 0], r[0, 0])])


def compose(ra: FloatArray, ta: FloatArray, rb: FloatArray,
            tb: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(Ra, ta) * (Rb, tb) as a 4x4 product."""
    return from_matrix(to_matrix(ra, ta) @ to_matrix(rb, tb))


def between(ra: FloatArray, ta: FloatArray, rb: FloatArray,
            tb: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(Ra, ta)^-1 * (Rb, tb) with a general 4x4 inverse."""
    return from_matrix(np.linalg.inv(to_matrix(ra, ta)) @ to_matrix(rb, tb))


def relative_error(rz: FloatArray, tz: FloatArray, rab: FloatArray, tab: FloatArray) -> FloatArray:
    """e = Log(Z^-1 X_ab) (docs/conventions.md) through 4x4 matrices."""
    r, t = from_matrix(np.linalg.inv(to_matrix(rz, tz)) @ to_matrix(rab, tab))
    return se3_log(r, t)


# ============================================================================================
# hybridpgo.solvers.hybrid: linearization, hybrid and batch steps, the capped retraction,
# and the cost layer hybridpgo._cost  (tests/test_hybrid_twins.py)
#
# Independent of the kernels by construction: poses are GLOBAL (4x4 products down the tree,
# not the kernels' path products relative to a constraint's root), Jacobians come from the
# geometry twins above (matrix-series Jr^-1, Ad through T hat(e) T^-1, 4x4 inverses), and every
# linear system is built densely and handed to numpy.linalg.solve / lstsq (no Cholesky of
# 6x6 blocks, no Woodbury, no Givens, no segments).  A tree is a parent array (-1: root); the
# root's "local" transform is its global pose, every other node's is relative to its parent.
# The damping rule is the one of docs/mathematics.md#hybrid-step: each block of B gets mu * tr(B)/6
# + tiny * scale on
# its diagonal (``tiny`` is a parameter: twins never import hybridpgo).
# ============================================================================================


def tree_globals(parent: npt.NDArray[np.integer], rot: FloatArray,
                 trans: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Global poses of every tree node: the 4x4 product of the locals from the root down."""
    n = parent.shape[0]
    mats: list[FloatArray | None] = [None] * n

    def pose(i: int) -> FloatArray:
        m = mats[i]
        if m is None:
            local = to_matrix(rot[i], trans[i])
            m = local if parent[i] < 0 else pose(int(parent[i])) @ local
            mats[i] = m
        return m

    grot = np.empty((n, 3, 3))
    gtr = np.empty((n, 3))
    for i in range(n):
        grot[i], gtr[i] = from_matrix(pose(i))
    return grot, gtr


def _ancestors(parent: npt.NDArray[np.integer], i: int) -> list[int]:
    out = [i]
    while parent[out[-1]] >= 0:
        out.append(int(parent[out[-1]]))
    return out


def tree_domain(parent: npt.NDArray[np.integer], a: int,
                b: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Domain of a constraint between a and b: the tree path a -> lca -> b without the lca.

    Nodes from a upwards (sign -1), then from b upwards (sign +1); a GPS reading on n is the
    constraint (earth, n).
    """
    up_a, up_b = _ancestors(parent, a), _ancestors(parent, b)
    lca = next(v for v in up_a if v in set(up_b))
    side_a = up_a[: up_a.index(lca)]
    side_b = up_b[: up_b.index(lca)]
    nodes = np.array(side_a + side_b, np.int64)
    signs = np.array([-1] * len(side_a) + [1] * len(side_b), np.int64)
    return nodes, signs


def relative_jacobian(grot: FloatArray, gtr: FloatArray, a: int, b: int, zr: FloatArray,
                      zt: FloatArray, lt: FloatArray, nodes: npt.NDArray[np.integer],
                      signs: npt.NDArray[np.integer]) -> tuple[FloatArray, FloatArray]:
    """Whitened blocks ``s_i L^T Jr^-1(e) Ad(X_b^-1 X_i)`` (d, 6, 6) and ``r = -L^T e`` (6,).

    ``e = Log(Z^-1 X_a^-1 X_b)`` from global poses (docs/mathematics.md#jacobians).
    """
    rab, tab = between(grot[a], gtr[a], grot[b], gtr[b])
    e = relative_error(zr, zt, rab, tab)
    ja = lt @ se3_right_jacobian_inv(e)
    jac = np.stack([
        s * ja @ se3_adjoint(*between(grot[b], gtr[b], grot[i], gtr[i]))
        for i, s in zip(nodes, signs, strict=True)
    ])
    return jac, -lt @ e


def gps_jacobian(grot: FloatArray, gtr: FloatArray, n: int, g: FloatArray, lt: FloatArray,
                 nodes: npt.NDArray[np.integer]) -> tuple[FloatArray, FloatArray]:
    """Whitened blocks ``L^T R_i [I | -[t_{i->n}]x]`` (d, 3, 6) and ``r = -L^T (p_n - g)`` (3,).

    Global poses are in the earth frame (the earth is the tree's root, the identity).
    """
    blocks = []
    for i in nodes:
        _, t_in = between(grot[i], gtr[i], grot[n], gtr[n])  # position of n in i's frame
        blocks.append(lt @ grot[i] @ np.hstack([np.eye(3), -skew(t_in)]))
    return np.stack(blocks), -lt @ (gtr[n] - g)


def own_scale(jac_blocks: FloatArray) -> FloatArray:
    """trace(J_k^T J_k) of each block (d,): the ``scale`` of the damping rule."""
    return np.asarray([np.trace(j.T @ j) for j in jac_blocks], dtype=np.float64)


def damped_block(bc: FloatArray, scale: float, mu: float, tiny: float) -> FloatArray:
    """sym(B) + (mu * max(tr B, 0)/6 + tiny * scale) I (docs/mathematics.md#hybrid-step, no
    escalation)."""
    sym = 0.5 * (bc + bc.T)
    damp = mu * max(float(np.trace(bc)), 0.0) / 6.0 + tiny * scale
    return np.asarray(sym + damp * np.eye(6), dtype=np.float64)


def hybrid_step(jac_blocks: FloatArray, r: FloatArray, bdiag_minus_old: FloatArray,
                scale: FloatArray, mu: float, tiny: float) -> FloatArray:
    """Paper eq. 25: (J^T J + B_c + damping) x = J^T r as one dense (6d x 6d) solve; x (d, 6)."""
    d = jac_blocks.shape[0]
    jd = np.hstack(list(jac_blocks))  # (kr, 6d)
    bd = scipy.linalg.block_diag(*[
        damped_block(bdiag_minus_old[k], float(scale[k]), mu, tiny) for k in range(d)
    ])
    return np.asarray(np.linalg.solve(jd.T @ jd + bd, jd.T @ r).reshape(d, 6), np.float64)


def batch_step(domains: list[npt.NDArray[np.integer]], jacs: list[FloatArray],
               residuals: list[FloatArray], bdiag: FloatArray, old_contrib: list[FloatArray],
               count: npt.NDArray[np.integer], mu: float, tiny: float,
               damped: bool | None = None) -> tuple[npt.NDArray[np.int64], FloatArray]:
    """Paper eq. 35-37 densely over the union U of the domains: ``(nodes (|U|,), x (|U|, 6))``.

    ``B_C = 𝔅(H) - sum_{c in C} 𝔅(J_c^T J_c)_old`` per union node (``bdiag`` before the batch,
    ``old_contrib[q][k]`` the block constraint q last added for its k-th domain node), exactly 0
    where every constraint through the node is in C (``count[node]`` constraints in the whole
    graph).  ``damped`` (default: no block is 0, the kernel's rule) adds the damping of
    :func:`damped_block` with ``scale`` = sum of the batch's ``trace(J^T J)`` on the node.
    Union nodes are numbered in order of first appearance.
    """
    union: list[int] = []
    for dom in domains:
        union.extend(int(v) for v in dom if int(v) not in union)
    pos = {v: u for u, v in enumerate(union)}
    nu = len(union)
    bc = np.stack([bdiag[v].copy() for v in union])
    through = np.zeros(nu, np.int64)
    scale = np.zeros(nu)
    for dom, jac, old in zip(domains, jacs, old_contrib, strict=True):
        for k, v in enumerate(dom):
            u = pos[int(v)]
            bc[u] -= old[k]
            through[u] += 1
            scale[u] += np.trace(jac[k].T @ jac[k])
    zero = np.array([through[u] == count[v] for u, v in enumerate(union)])
    bc[zero] = 0.0
    if damped is None:
        damped = not bool(zero.any())
    bd = scipy.linalg.block_diag(*[
        damped_block(bc[u], float(scale[u]), mu, tiny) if damped else bc[u] for u in range(nu)
    ])
    jd, r = stack_jacobian(domains, jacs, residuals, union)
    x = np.linalg.solve(jd.T @ jd + bd, jd.T @ r)
    return np.array(union, np.int64), np.asarray(x.reshape(nu, 6), np.float64)


def stack_jacobian(domains: list[npt.NDArray[np.integer]], jacs: list[FloatArray],
                   residuals: list[FloatArray],
                   columns: list[int]) -> tuple[FloatArray, FloatArray]:
    """Dense stacked ``J`` (sum kr, 6 len(columns)) and ``r`` of constraints given blockwise."""
    pos = {v: u for u, v in enumerate(columns)}
    rows = []
    for dom, jac in zip(domains, jacs, strict=True):
        row = np.zeros((jac.shape[1], 6 * len(columns)))
        for k, v in enumerate(dom):
            row[:, 6 * pos[int(v)] : 6 * pos[int(v)] + 6] = jac[k]
        rows.append(row)
    return np.vstack(rows), np.concatenate(residuals)


def gauss_newton_step(jac: FloatArray, r: FloatArray) -> FloatArray:
    """The exact Gauss-Newton step (paper eq. 14): least squares ``J x ~ r``."""
    return np.asarray(np.linalg.lstsq(jac, r, rcond=None)[0], dtype=np.float64)


def capped_temperature(x: FloatArray, tau: float,
                       max_rotation: float = np.pi / 8) -> tuple[float, bool]:
    """Paper III-H: ``(t, capped)``, t = min(tau, max_rotation / largest rotation norm of x)."""
    biggest = float(np.max(np.linalg.norm(x[:, 3:], axis=1)))
    if tau * biggest > max_rotation:
        return max_rotation / biggest, True
    return tau, False


def retract(r: FloatArray, t: FloatArray, xi: FloatArray,
            scale: float) -> tuple[FloatArray, FloatArray]:
    """``T Exp(scale xi)`` with the matrix exponential of the 4x4 twist."""
    return compose(r, t, *se3_exp(scale * np.asarray(xi, dtype=np.float64)))


def apply_step(rot: FloatArray, trans: FloatArray, nodes: npt.NDArray[np.integer], x: FloatArray,
               tau: float) -> tuple[FloatArray, FloatArray, bool]:
    """``T_i <- T_i Exp(t x_k)``, ``i = nodes[k]``, with the capped t: ``(rot, trans, capped)``."""
    t, capped = capped_temperature(x, tau)
    rot, trans = rot.copy(), trans.copy()
    for k, i in enumerate(nodes):
        rot[i], trans[i] = retract(rot[i], trans[i], x[k], t)
    return rot, trans, capped


def chi2(info: FloatArray, e: FloatArray) -> float:
    """``e^T Omega e`` (no 1/2)."""
    return float(e @ info @ e)


def aggregated_step(jac_blocks: FloatArray, r: FloatArray, bdiag_minus_old: FloatArray,
                    scale: FloatArray, mu: float, tiny: float, memory: FloatArray,
                    memory_sum: FloatArray, count: npt.NDArray[np.integer], rate: float
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``update="saga"``: ``(J^T J + B_c + damping) x = b`` with ``b_k = g_k - m_k + M_k / n_k``,
    ``g_k = J_k^T r``; returns ``(x (d, 6), new memory (d, 6), new memory sums (d, 6))``."""
    d = jac_blocks.shape[0]
    g = np.stack([jk.T @ r for jk in jac_blocks])
    b = g - memory + memory_sum / np.asarray(count, np.float64)[:, None]
    jd = np.hstack(list(jac_blocks))
    bd = scipy.linalg.block_diag(*[
        damped_block(bdiag_minus_old[k], float(scale[k]), mu, tiny) for k in range(d)
    ])
    x = np.linalg.solve(jd.T @ jd + bd, b.reshape(-1)).reshape(d, 6)
    dm = rate * (g - memory)
    return np.asarray(x, np.float64), memory + dm, memory_sum + dm
