"""Checks of what enters the online mode: ids, rigid transforms, information matrices.

Every check raises :class:`~hybridpgo.errors.GraphError` naming what is wrong, before anything
is changed (the API's ``add_*`` calls and a loaded state alike).
"""

from __future__ import annotations

import numpy as np

from .._numba import kernel
from ..errors import GraphError
from ..graph import SYMMETRY_RTOL, FloatArray

#: Largest deviation of ``R^T R`` from the identity accepted in a measured rotation.
ROTATION_TOL = 1e-6


def check_id(value: object, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise GraphError(f"{what} must be an integer, got {value!r}")
    return int(value)


def as_pose(measurement: object, what: str) -> tuple[FloatArray, FloatArray]:
    """``(R, t)`` from a (4, 4) homogeneous matrix or a pair ``(R (3, 3), t (3,))``."""
    try:
        if isinstance(measurement, tuple) and len(measurement) == 2:
            rot = np.array(measurement[0], dtype=np.float64, order="C")
            trans = np.array(measurement[1], dtype=np.float64, order="C").reshape(-1)
        else:
            m = np.array(measurement, dtype=np.float64, order="C")
            if m.shape != (4, 4):
                raise GraphError(f"{what} must be a (4, 4) matrix or a pair (R, t), "
                                 f"got shape {m.shape}")
            rot, trans = m[:3, :3].copy(), m[:3, 3].copy()
    except (TypeError, ValueError) as exc:
        if isinstance(exc, GraphError):
            raise
        raise GraphError(f"{what} is not numeric: {exc}") from exc
    if rot.shape != (3, 3) or trans.shape != (3,):
        raise GraphError(f"{what}: R must be (3, 3) and t (3,), got {rot.shape} and "
                         f"{trans.shape}")
    finite, dev, det = _rigid(rot, trans)
    if not finite:
        raise GraphError(f"{what} is not finite")
    if dev > ROTATION_TOL or det <= 0:
        raise GraphError(f"{what}: R is not a rotation (|R^T R - I| = {dev:.3g}, "
                         f"det = {det:.3g})")
    return rot, trans


@kernel
def _rigid(rot: FloatArray, trans: FloatArray) -> tuple[bool, float, float]:
    """``(finite, max |R^T R - I|, det R)`` of a (3, 3) ``rot`` and a (3,) ``trans`` (one call
    for the checks of :func:`as_pose`: each ``add_*`` call makes them)."""
    for i in range(3):
        if not np.isfinite(trans[i]):
            return False, 0.0, 0.0
        for j in range(3):
            if not np.isfinite(rot[i, j]):
                return False, 0.0, 0.0
    dev = 0.0
    for i in range(3):
        for j in range(3):
            g = rot[0, i] * rot[0, j] + rot[1, i] * rot[1, j] + rot[2, i] * rot[2, j]
            dev = max(dev, abs(g - 1.0 if i == j else g))
    det = (rot[0, 0] * (rot[1, 1] * rot[2, 2] - rot[1, 2] * rot[2, 1])
           - rot[0, 1] * (rot[1, 0] * rot[2, 2] - rot[1, 2] * rot[2, 0])
           + rot[0, 2] * (rot[1, 0] * rot[2, 1] - rot[1, 1] * rot[2, 0]))
    return True, dev, det


@kernel
def _finite_symmetric(info: FloatArray, rtol: float) -> int:
    """0 when the square ``info`` is finite and symmetric to ``rtol`` times its largest
    magnitude; 1: not finite; 2: not symmetric.  The per-call twin of
    :func:`hybridpgo.graph.asymmetric` (one matrix, compiled: no array temporaries in a
    frame's ``add_*``)."""
    k = info.shape[0]
    scale = 0.0
    for i in range(k):
        for j in range(k):
            if not np.isfinite(info[i, j]):
                return 1
            scale = max(scale, abs(info[i, j]))
    tol = rtol * max(scale, 1e-300)
    for i in range(k):
        for j in range(i):
            if abs(info[i, j] - info[j, i]) > tol:
                return 2
    return 0


def whitening(information: object, k: int, what: str) -> tuple[FloatArray, FloatArray]:
    """``(Omega, L^T)`` of an SPD (k, k) information, or GraphError."""
    try:
        info = np.array(information, dtype=np.float64, order="C")
    except (TypeError, ValueError) as exc:
        raise GraphError(f"{what}: information is not numeric: {exc}") from exc
    if info.shape != (k, k):
        raise GraphError(f"{what}: information must be ({k}, {k}), got shape {info.shape}")
    bad = _finite_symmetric(info, SYMMETRY_RTOL)
    if bad == 1:
        raise GraphError(f"{what}: information is not finite")
    if bad == 2:
        raise GraphError(f"{what}: information matrix is not symmetric")
    try:
        low = np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        low = None
    if low is None or not np.isfinite(low).all():
        raise GraphError(f"{what}: information matrix is not positive definite")
    return info, np.ascontiguousarray(low.T)
