"""Vectorised SO(3) over stacks of rotation vectors (..., 3) and matrices (..., 3, 3).

Pure NumPy, no Python loop per element: for the I/O boundary (quaternions, Euler angles) and for
metrics.  The hot loops use the Numba kernels of :mod:`hybridpgo.geometry._kernels`; these
functions follow the same formulas, thresholds and conventions, so both agree to rounding:

* ``exp(phi)`` is Rodrigues' formula; ``log(R)`` returns ``phi`` with ``|phi|`` in [0, pi].
* Quaternions are scalar-last ``(x, y, z, w)``, returned unit-norm with ``w >= 0``.
* Euler angles are ``(roll, pitch, yaw)`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (TORO/iSAM;
  scipy's ``Rotation.from_euler("ZYX", [yaw, pitch, roll])``), pitch in [-pi/2, pi/2].

Leading dimensions broadcast where two arguments meet (:func:`compose`).  Bad trailing shapes raise
``ValueError``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from ._kernels import NEAR_PI, SMALL_ANGLE

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "angle",
    "compose",
    "euler_rpy_to_matrix",
    "exp",
    "hat",
    "inverse",
    "left_jacobian",
    "left_jacobian_inv",
    "log",
    "matrix_to_euler_rpy",
    "matrix_to_quat_xyzw",
    "normalize_quaternions",
    "orthonormalize",
    "quat_xyzw_to_matrix",
    "vee",
]


def _vectors(x: Any, k: int, name: str) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != k:
        raise ValueError(f"{name} must have shape (..., {k}), got {arr.shape}")
    return arr


def _matrices(x: Any, name: str) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {arr.shape}")
    return arr


def _mat(c: FloatArray) -> FloatArray:
    """Append two axes to a per-element coefficient so that it scales (..., 3, 3) matrices."""
    return c[..., None, None]


def hat(phi: npt.ArrayLike) -> FloatArray:
    """Cross-product matrices [phi]x.

    Parameters
    ----------
    phi : (..., 3) array_like

    Returns
    -------
    (..., 3, 3) float64 array with ``hat(phi) @ v == cross(phi, v)``.
    """
    p = _vectors(phi, 3, "phi")
    out = np.zeros((*p.shape[:-1], 3, 3))
    out[..., 0, 1] = -p[..., 2]
    out[..., 0, 2] = p[..., 1]
    out[..., 1, 0] = p[..., 2]
    out[..., 1, 2] = -p[..., 0]
    out[..., 2, 0] = -p[..., 1]
    out[..., 2, 1] = p[..., 0]
    return out


def vee(m: npt.ArrayLike) -> FloatArray:
    """Vector of the antisymmetric part of (..., 3, 3) matrices (inverse of :func:`hat`)."""
    a = _matrices(m, "m")
    return 0.5 * np.stack([a[..., 2, 1] - a[..., 1, 2], a[..., 0, 2] - a[..., 2, 0],
                           a[..., 1, 0] - a[..., 0, 1]], axis=-1)


def _angle_and_safe(p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """theta^2, theta, the small-angle mask and theta with 1 where small (safe to divide by)."""
    th2 = np.einsum("...i,...i->...", p, p)
    th = np.sqrt(th2)
    small = th < SMALL_ANGLE
    return th2, th, small, np.where(small, 1.0, th)


def exp(phi: npt.ArrayLike) -> FloatArray:
    """Rotation matrices Exp(phi) (Rodrigues).

    Parameters
    ----------
    phi : (..., 3) array_like
        Rotation vectors (axis times angle, rad).

    Returns
    -------
    (..., 3, 3) float64 array of rotation matrices.
    """
    p = _vectors(phi, 3, "phi")
    th2, _, small, ts = _angle_and_safe(p)
    # Series below SMALL_ANGLE: sin(th)/th = 1 - th^2/6 + ..., (1 - cos th)/th^2 = 1/2 - th^2/24.
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - th2 / 24.0, 2.0 * np.sin(0.5 * ts) ** 2 / (ts * ts))
    k = hat(p)
    return np.eye(3) + _mat(a) * k + _mat(b) * (k @ k)


def log(rotation: npt.ArrayLike) -> FloatArray:
    """Rotation vectors Log(R), with angle in [0, pi].

    Parameters
    ----------
    rotation : (..., 3, 3) array_like
        Rotation matrices.

    Returns
    -------
    (..., 3) float64 array ``phi`` with ``exp(phi) == R``.  At exactly pi the sign of the axis
    is arbitrary (both are correct).
    """
    r = _matrices(rotation, "rotation")
    v = vee(r)  # sin(th) * axis
    s = np.linalg.norm(v, axis=-1)
    c = 0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1.0)
    th = np.arctan2(s, c)
    small = th < SMALL_ANGLE
    near_pi = ~small & (np.pi - th <= NEAR_PI)
    generic = ~small & ~near_pi
    # th / sin(th) = 1 + th^2/6 + ... below SMALL_ANGLE.
    f = np.where(small, 1.0 + th * th / 6.0, th / np.where(generic, s, 1.0))
    out = f[..., None] * v
    if np.any(near_pi):
        # R + R^T = 2 cos(th) I + 2 (1 - cos th) a a^T: take the column of the largest diagonal
        # entry (ties to the first, as the kernel does) and the sign that agrees with vee(R).
        d = np.diagonal(r, axis1=-2, axis2=-1) - c[..., None]
        k = np.argmax(d, axis=-1)
        sym = 0.5 * (r + np.swapaxes(r, -1, -2)) - c[..., None, None] * np.eye(3)
        a = np.take_along_axis(sym, k[..., None, None], axis=-1)[..., 0]
        n = np.linalg.norm(a, axis=-1)
        sign = np.where(np.einsum("...i,...i->...", a, v) < 0.0, -1.0, 1.0)
        scale = sign * th / np.where(near_pi, n, 1.0)
        out = np.where(near_pi[..., None], scale[..., None] * a, out)
    return np.asarray(out, dtype=np.float64)


def angle(rotation: npt.ArrayLike) -> FloatArray:
    """Rotation angles |Log(R)| in [0, pi] (rad), accurate at 0 and pi (atan2, not acos).

    Parameters
    ----------
    rotation : (..., 3, 3) array_like

    Returns
    -------
    (...) float64 array.
    """
    r = _matrices(rotation, "rotation")
    s = np.linalg.norm(vee(r), axis=-1)
    c = 0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1.0)
    return np.asarray(np.arctan2(s, c), dtype=np.float64)


def left_jacobian(phi: npt.ArrayLike) -> FloatArray:
    """Left Jacobians J_l(phi) = I + (1 - cos th)/th^2 [phi]x + (th - sin th)/th^3 [phi]x^2.

    Parameters
    ----------
    phi : (..., 3) array_like

    Returns
    -------
    (..., 3, 3) float64 array; ``Exp(phi + d) ~ Exp(J_l(phi) d) Exp(phi)``.
    """
    p = _vectors(phi, 3, "phi")
    th2, _, small, ts = _angle_and_safe(p)
    b = np.where(small, 0.5 - th2 / 24.0, 2.0 * np.sin(0.5 * ts) ** 2 / (ts * ts))
    c = np.where(small, 1.0 / 6.0 - th2 / 120.0, (ts - np.sin(ts)) / (ts * ts * ts))
    k = hat(p)
    return np.eye(3) + _mat(b) * k + _mat(c) * (k @ k)


def left_jacobian_inv(phi: npt.ArrayLike) -> FloatArray:
    """Inverse left Jacobians I - [phi]x/2 + (1/th^2 - cot(th/2)/(2 th)) [phi]x^2 (|phi| < 2 pi).

    Parameters
    ----------
    phi : (..., 3) array_like

    Returns
    -------
    (..., 3, 3) float64 array.
    """
    p = _vectors(phi, 3, "phi")
    th2, _, small, ts = _angle_and_safe(p)
    half = 0.5 * ts
    c = np.where(small, 1.0 / 12.0 + th2 / 720.0,
                 1.0 / (ts * ts) - np.cos(half) / (2.0 * ts * np.sin(half)))
    k = hat(p)
    return np.eye(3) - 0.5 * k + _mat(c) * (k @ k)


def compose(r_a_b: npt.ArrayLike, r_b_c: npt.ArrayLike) -> FloatArray:
    """Products R_a_c = R_a_b R_b_c (leading dimensions broadcast)."""
    return np.asarray(_matrices(r_a_b, "r_a_b") @ _matrices(r_b_c, "r_b_c"), dtype=np.float64)


def inverse(rotation: npt.ArrayLike) -> FloatArray:
    """Inverses R^T of rotation matrices."""
    return np.swapaxes(_matrices(rotation, "rotation"), -1, -2).copy()


def orthonormalize(matrix: npt.ArrayLike) -> FloatArray:
    """Nearest rotations (Frobenius norm) to (..., 3, 3) matrices: the SVD polar factor.

    Unlike the kernel's Newton step this is exact for any input with positive determinant; a
    reflection (det < 0) is mapped to the nearest proper rotation.
    """
    m = _matrices(matrix, "matrix")
    u, _, vt = np.linalg.svd(m)
    d = np.ones((*m.shape[:-2], 3))
    d[..., 2] = np.sign(np.linalg.det(u @ vt))
    return np.asarray((u * d[..., None, :]) @ vt, dtype=np.float64)


def normalize_quaternions(quat_xyzw: npt.ArrayLike) -> FloatArray:
    """Unit quaternions, exact for any finite non-zero input: each one is divided by its largest
    magnitude before the norm is taken, so nothing over- or underflows (a component of 1e300
    is fine).  Zero quaternions stay zero.

    Parameters
    ----------
    quat_xyzw : (..., 4) array_like
    """
    q = _vectors(quat_xyzw, 4, "quat_xyzw")
    peak = np.abs(q).max(axis=-1, keepdims=True)
    scaled = q / np.where(peak > 0.0, peak, 1.0)
    norm = np.linalg.norm(scaled, axis=-1, keepdims=True)
    return np.asarray(scaled / np.where(norm > 0.0, norm, 1.0), dtype=np.float64)


def quat_xyzw_to_matrix(quat_xyzw: npt.ArrayLike) -> FloatArray:
    """Rotation matrices of quaternions (x, y, z, w); each quaternion is normalized first
    (:func:`normalize_quaternions`).

    Parameters
    ----------
    quat_xyzw : (..., 4) array_like
        Scalar-last quaternions, any finite non-zero norm.

    Returns
    -------
    (..., 3, 3) float64 array.

    Raises
    ------
    ValueError
        A quaternion is zero or not finite.
    """
    q = _vectors(quat_xyzw, 4, "quat_xyzw")
    peak = np.abs(q).max(axis=-1)
    if not np.all(np.isfinite(peak) & (peak > 0.0)):
        raise ValueError("every quaternion must be finite with a non-zero norm")
    q = normalize_quaternions(q)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty((*q.shape[:-1], 3, 3))
    out[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[..., 0, 1] = 2.0 * (x * y - z * w)
    out[..., 0, 2] = 2.0 * (x * z + y * w)
    out[..., 1, 0] = 2.0 * (x * y + z * w)
    out[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[..., 1, 2] = 2.0 * (y * z - x * w)
    out[..., 2, 0] = 2.0 * (x * z - y * w)
    out[..., 2, 1] = 2.0 * (y * z + x * w)
    out[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return out


def matrix_to_quat_xyzw(rotation: npt.ArrayLike) -> FloatArray:
    """Unit quaternions (x, y, z, w) with w >= 0 of rotation matrices (Shepperd's method: the
    divisor comes from the largest of the trace and the diagonal, so it is >= 1/2).

    Parameters
    ----------
    rotation : (..., 3, 3) array_like

    Returns
    -------
    (..., 4) float64 array.
    """
    r_in = _matrices(rotation, "rotation")
    lead = r_in.shape[:-2]
    r = r_in.reshape(-1, 3, 3)
    q = np.empty((r.shape[0], 4))
    tr = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    d = np.stack([r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    case = np.where(tr > d.max(axis=1), 3, d.argmax(axis=1))
    m = case == 3
    s = 2.0 * np.sqrt(1.0 + tr[m])
    q[m, 3] = 0.25 * s
    q[m, 0] = (r[m, 2, 1] - r[m, 1, 2]) / s
    q[m, 1] = (r[m, 0, 2] - r[m, 2, 0]) / s
    q[m, 2] = (r[m, 1, 0] - r[m, 0, 1]) / s
    m = case == 0
    s = 2.0 * np.sqrt(1.0 + r[m, 0, 0] - r[m, 1, 1] - r[m, 2, 2])
    q[m, 3] = (r[m, 2, 1] - r[m, 1, 2]) / s
    q[m, 0] = 0.25 * s
    q[m, 1] = (r[m, 0, 1] + r[m, 1, 0]) / s
    q[m, 2] = (r[m, 0, 2] + r[m, 2, 0]) / s
    m = case == 1
    s = 2.0 * np.sqrt(1.0 + r[m, 1, 1] - r[m, 0, 0] - r[m, 2, 2])
    q[m, 3] = (r[m, 0, 2] - r[m, 2, 0]) / s
    q[m, 0] = (r[m, 0, 1] + r[m, 1, 0]) / s
    q[m, 1] = 0.25 * s
    q[m, 2] = (r[m, 1, 2] + r[m, 2, 1]) / s
    m = case == 2
    s = 2.0 * np.sqrt(1.0 + r[m, 2, 2] - r[m, 0, 0] - r[m, 1, 1])
    q[m, 3] = (r[m, 1, 0] - r[m, 0, 1]) / s
    q[m, 0] = (r[m, 0, 2] + r[m, 2, 0]) / s
    q[m, 1] = (r[m, 1, 2] + r[m, 2, 1]) / s
    q[m, 2] = 0.25 * s
    q[q[:, 3] < 0.0] *= -1.0
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.asarray(q.reshape(*lead, 4), dtype=np.float64)


def euler_rpy_to_matrix(rpy: npt.ArrayLike) -> FloatArray:
    """Rotation matrices R = Rz(yaw) Ry(pitch) Rx(roll).

    Parameters
    ----------
    rpy : (..., 3) array_like
        (roll, pitch, yaw) in rad.

    Returns
    -------
    (..., 3, 3) float64 array.
    """
    a = _vectors(rpy, 3, "rpy")
    cr, sr = np.cos(a[..., 0]), np.sin(a[..., 0])
    cp, sp = np.cos(a[..., 1]), np.sin(a[..., 1])
    cy, sy = np.cos(a[..., 2]), np.sin(a[..., 2])
    out = np.empty((*a.shape[:-1], 3, 3))
    out[..., 0, 0] = cy * cp
    out[..., 0, 1] = cy * sp * sr - sy * cr
    out[..., 0, 2] = cy * sp * cr + sy * sr
    out[..., 1, 0] = sy * cp
    out[..., 1, 1] = sy * sp * sr + cy * cr
    out[..., 1, 2] = sy * sp * cr - cy * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


def matrix_to_euler_rpy(rotation: npt.ArrayLike) -> FloatArray:
    """(roll, pitch, yaw) of rotation matrices, R = Rz(yaw) Ry(pitch) Rx(roll).

    Accurate to rounding everywhere, including near gimbal lock: roll is read from row 2, then
    yaw and pitch from ``M = R Rx(roll)^T = Rz(yaw) Ry(pitch)`` (``M01 = -sin yaw``,
    ``M11 = cos yaw``, ``M20 = -sin pitch``, ``M22 = cos pitch``).  Near the lock roll itself is
    ill-determined, but any error in it is absorbed by yaw, so ``R`` is reproduced to ~1e-16.

    Parameters
    ----------
    rotation : (..., 3, 3) array_like

    Returns
    -------
    (..., 3) float64 array; pitch in [-pi/2, pi/2], roll and yaw in [-pi, pi].
    """
    r = _matrices(rotation, "rotation")
    roll = np.arctan2(r[..., 2, 1], r[..., 2, 2])
    cr, sr = np.cos(roll), np.sin(roll)
    # M = R Rx(roll)^T; columns 1 and 2 mix, column 0 is unchanged.
    m01 = r[..., 0, 1] * cr - r[..., 0, 2] * sr
    m11 = r[..., 1, 1] * cr - r[..., 1, 2] * sr
    m22 = r[..., 2, 1] * sr + r[..., 2, 2] * cr
    yaw = np.arctan2(-m01, m11)
    pitch = np.arctan2(-r[..., 2, 0], m22)
    return np.stack([roll, pitch, yaw], axis=-1)
