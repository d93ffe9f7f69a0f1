"""Plain NumPy twins of the Numba kernels, used as test oracles (STYLE.md §3, §7).

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

FloatArray = npt.NDArray[np.float64]


# ============================================================================================
# hybridpgo.geometry._kernels: SO(3) / SE(3)  (tests/test_geometry.py)
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


def so3_exp(phi: FloatArray) -> FloatArray:
    """Matrix exponential of [phi]x."""
    return np.asarray(scipy.linalg.expm(skew(phi)), dtype=np.float64)


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


def so3_log(r: FloatArray) -> FloatArray:
    """Rotation vector through the quaternion: phi = 2 atan2(|v|, w) v / |v|, |phi| <= pi."""
    q = matrix_to_quat_xyzw(r)
    n = np.linalg.norm(q[:3])
    if n == 0.0:
        return np.zeros(3)
    return 2.0 * np.arctan2(n, q[3]) * q[:3] / n


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
    phi = so3_log(r)
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
    """e = Log(Z^-1 X_ab) (DESIGN.md §1) through 4x4 matrices."""
    r, t = from_matrix(np.linalg.inv(to_matrix(rz, tz)) @ to_matrix(rab, tab))
    return se3_log(r, t)
