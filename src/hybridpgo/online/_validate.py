"""Checks of what enters the online mode: ids, rigid transforms, information matrices.

Every check raises :class:`~hybridpgo.errors.GraphError` naming what is wrong, before anything
is changed (the API's ``add_*`` calls and a loaded state alike).
"""

from __future__ import annotations

import numpy as np

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
            rot = np.array(measurement[0], dtype=np.float64)
            trans = np.array(measurement[1], dtype=np.float64).reshape(-1)
        else:
            m = np.array(measurement, dtype=np.float64)
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
    if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(trans))):
        raise GraphError(f"{what} is not finite")
    dev = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if dev > ROTATION_TOL or np.linalg.det(rot) <= 0:
        raise GraphError(f"{what}: R is not a rotation (|R^T R - I| = {dev:.3g}, "
                         f"det = {np.linalg.det(rot):.3g})")
    return rot, trans


def whitening(information: object, k: int, what: str) -> tuple[FloatArray, FloatArray]:
    """``(Omega, L^T)`` of an SPD (k, k) information, or GraphError."""
    try:
        info = np.array(information, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GraphError(f"{what}: information is not numeric: {exc}") from exc
    if info.shape != (k, k):
        raise GraphError(f"{what}: information must be ({k}, {k}), got shape {info.shape}")
    if not np.all(np.isfinite(info)):
        raise GraphError(f"{what}: information is not finite")
    scale = float(np.abs(info).max())
    if float(np.abs(info - info.T).max()) > SYMMETRY_RTOL * max(scale, 1e-300):
        raise GraphError(f"{what}: information matrix is not symmetric")
    try:
        low = np.linalg.cholesky(info)
    except np.linalg.LinAlgError:
        low = None
    if low is None or not np.all(np.isfinite(low)):
        raise GraphError(f"{what}: information matrix is not positive definite")
    return info, np.ascontiguousarray(low.T)
