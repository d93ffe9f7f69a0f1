"""Vectorised SE(3) over stacks of poses: rotations (..., 3, 3) with translations (..., 3).

Pure NumPy, no Python loop per element: for the I/O boundary and for metrics.  Conventions
(docs/conventions.md) as in :mod:`hybridpgo.geometry._kernels`: a tangent vector is ``xi = (rho,
phi)``
(translation first), ``Exp(xi) = (Exp_SO3(phi), J_l(phi) rho)``, and a pose ``T_a_b = (R, t)``
maps b-frame coordinates into frame a: ``p_a = R p_b + t``.

Leading dimensions broadcast where poses meet (:func:`compose`, :func:`between`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from . import so3

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "adjoint",
    "between",
    "compose",
    "exp",
    "from_matrix",
    "inverse",
    "log",
    "to_matrix",
]


def _rotations(x: Any, name: str) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {arr.shape}")
    return arr


def _translations(x: Any, name: str) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {arr.shape}")
    return arr


def _apply(r: FloatArray, v: FloatArray) -> FloatArray:
    """R v for stacks, broadcasting leading dimensions."""
    return np.asarray((r @ v[..., None])[..., 0], dtype=np.float64)


def exp(xi: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Poses Exp(xi) of tangent vectors xi = (rho, phi).

    Parameters
    ----------
    xi : (..., 6) array_like
        Translation part rho (m) first, then rotation vector phi (rad).

    Returns
    -------
    rotation : (..., 3, 3) float64 array
    translation : (..., 3) float64 array, ``J_l(phi) rho``.
    """
    x = np.asarray(xi, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] != 6:
        raise ValueError(f"xi must have shape (..., 6), got {x.shape}")
    phi = x[..., 3:]
    return so3.exp(phi), _apply(so3.left_jacobian(phi), x[..., :3])


def log(rotation: npt.ArrayLike, translation: npt.ArrayLike) -> FloatArray:
    """Tangent vectors Log(R, t) = (J_l(phi)^-1 t, phi) with |phi| in [0, pi].

    Parameters
    ----------
    rotation : (..., 3, 3) array_like
    translation : (..., 3) array_like

    Returns
    -------
    (..., 6) float64 array ``(rho, phi)``.
    """
    r = _rotations(rotation, "rotation")
    t = _translations(translation, "translation")
    phi = so3.log(r)
    rho = _apply(so3.left_jacobian_inv(phi), t)
    rho, phi = np.broadcast_arrays(rho, phi)
    return np.concatenate([rho, phi], axis=-1)


def compose(r_a_b: npt.ArrayLike, t_a_b: npt.ArrayLike, r_b_c: npt.ArrayLike,
            t_b_c: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Products T_a_c = T_a_b T_b_c.

    Returns
    -------
    rotation : (..., 3, 3) float64 array, ``R_a_b R_b_c``
    translation : (..., 3) float64 array, ``R_a_b t_b_c + t_a_b``
    """
    ra = _rotations(r_a_b, "r_a_b")
    ta = _translations(t_a_b, "t_a_b")
    rb = _rotations(r_b_c, "r_b_c")
    tb = _translations(t_b_c, "t_b_c")
    return np.asarray(ra @ rb, dtype=np.float64), _apply(ra, tb) + ta


def inverse(rotation: npt.ArrayLike,
            translation: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverses T^-1 = (R^T, -R^T t)."""
    rt = so3.inverse(_rotations(rotation, "rotation"))
    return rt, -_apply(rt, _translations(translation, "translation"))


def between(r_w_a: npt.ArrayLike, t_w_a: npt.ArrayLike, r_w_b: npt.ArrayLike,
            t_w_b: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Relative poses T_a_b = T_w_a^-1 T_w_b.

    Returns
    -------
    rotation : (..., 3, 3) float64 array, ``R_w_a^T R_w_b``
    translation : (..., 3) float64 array, ``R_w_a^T (t_w_b - t_w_a)``
    """
    rat = so3.inverse(_rotations(r_w_a, "r_w_a"))
    rb = _rotations(r_w_b, "r_w_b")
    ta = _translations(t_w_a, "t_w_a")
    tb = _translations(t_w_b, "t_w_b")
    return np.asarray(rat @ rb, dtype=np.float64), _apply(rat, tb - ta)


def adjoint(rotation: npt.ArrayLike, translation: npt.ArrayLike) -> FloatArray:
    """Adjoint matrices Ad(T) = [[R, [t]x R], [0, R]] in (rho, phi) order.

    ``T Exp(xi) T^-1 = Exp(Ad(T) xi)``.

    Returns
    -------
    (..., 6, 6) float64 array.
    """
    r = _rotations(rotation, "rotation")
    t = _translations(translation, "translation")
    r, t_hat = np.broadcast_arrays(r, so3.hat(t))
    out = np.zeros((*r.shape[:-2], 6, 6))
    out[..., :3, :3] = r
    out[..., 3:, 3:] = r
    out[..., :3, 3:] = t_hat @ r
    return out


def to_matrix(rotation: npt.ArrayLike, translation: npt.ArrayLike) -> FloatArray:
    """4x4 homogeneous matrices [[R, t], [0, 1]].

    Returns
    -------
    (..., 4, 4) float64 array.
    """
    r = _rotations(rotation, "rotation")
    t = _translations(translation, "translation")
    shape = np.broadcast_shapes(r.shape[:-2], t.shape[:-1])
    out = np.zeros((*shape, 4, 4))
    out[..., :3, :3] = r
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def from_matrix(matrix: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(R, t) of 4x4 homogeneous matrices; the bottom row is not checked.

    Parameters
    ----------
    matrix : (..., 4, 4) array_like

    Returns
    -------
    rotation : (..., 3, 3) float64 array
    translation : (..., 3) float64 array
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (4, 4):
        raise ValueError(f"matrix must have shape (..., 4, 4), got {m.shape}")
    return m[..., :3, :3].copy(), m[..., :3, 3].copy()
