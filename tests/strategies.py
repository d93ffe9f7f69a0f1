"""Hypothesis strategies shared by the test suite (docs/contributing.md#tests).

Rotation angles come in named regimes, because the kernels switch formulas by angle:

* ``"normal"``: theta in [1e-3, pi - 1e-3];
* ``"near_zero"``: theta = 0 or theta in [1e-9, 1e-7] (around 1e-8, deep in the Taylor series);
* ``"near_pi"``: theta = pi - delta, delta in [1e-7, 1e-5] (around pi - 1e-6);
* ``"threshold"``: within 1e-3 (relative) of a formula switch of ``_kernels`` (``SMALL_ANGLE``,
  ``Q_SERIES_ANGLE``, ``pi - NEAR_PI``), so both sides of every switch get exercised.

Generated data never goes through the kernels under test: rotations are built with scipy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hybridpgo.geometry._kernels import NEAR_PI, Q_SERIES_ANGLE, SMALL_ANGLE

FloatArray = npt.NDArray[np.float64]

ALL_REGIMES: tuple[str, ...] = ("normal", "near_zero", "near_pi", "threshold")
#: Regimes with |phi| bounded away from pi (finite differences must not wrap around pi).
BELOW_PI_REGIMES: tuple[str, ...] = ("normal", "near_zero", "threshold")
#: Largest angle of the "normal" regime; also the margin kept from pi by ``BELOW_PI_REGIMES``.
NORMAL_MARGIN = 1e-3
#: Translations (m) are drawn from [-MAX_TRANSLATION, MAX_TRANSLATION].
MAX_TRANSLATION = 10.0

_THRESHOLDS = (SMALL_ANGLE, Q_SERIES_ANGLE, math.pi - NEAR_PI)


def _floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(min_value=lo, max_value=hi, allow_nan=False, allow_infinity=False,
                     allow_subnormal=False)


def angles(regime: str) -> st.SearchStrategy[float]:
    """Rotation angles (rad) of one regime (see the module docstring)."""
    if regime == "normal":
        return _floats(NORMAL_MARGIN, math.pi - NORMAL_MARGIN)
    if regime == "near_zero":
        return st.one_of(st.just(0.0), _floats(-9.0, -7.0).map(lambda u: 10.0**u))
    if regime == "near_pi":
        return _floats(-7.0, -5.0).map(lambda u: math.pi - 10.0**u)
    if regime == "threshold":
        return st.tuples(st.sampled_from(_THRESHOLDS), _floats(-1e-3, 1e-3)).map(
            lambda tu: tu[0] * (1.0 + tu[1]))
    raise ValueError(f"unknown regime {regime!r}; expected one of {ALL_REGIMES}")


def unit_vectors() -> st.SearchStrategy[FloatArray]:
    """Unit 3-vectors (directions spread over the sphere)."""
    return (st.tuples(_floats(-1.0, 1.0), _floats(-1.0, 1.0), _floats(-1.0, 1.0))
            .filter(lambda v: math.hypot(*v) > 1e-2)
            .map(lambda v: np.array(v) / math.hypot(*v)))


def rotation_vectors(regimes: Sequence[str] = ALL_REGIMES) -> st.SearchStrategy[FloatArray]:
    """Rotation vectors phi = theta * axis, theta drawn from one of ``regimes``."""
    theta = st.one_of(*(angles(r) for r in regimes))
    return st.tuples(theta, unit_vectors()).map(lambda ta: ta[0] * ta[1])


def translations(scale: float = MAX_TRANSLATION) -> st.SearchStrategy[FloatArray]:
    """Translations with components in [-scale, scale]."""
    c = _floats(-scale, scale)
    return st.tuples(c, c, c).map(np.array)


def tangents(regimes: Sequence[str] = ALL_REGIMES,
             scale: float = MAX_TRANSLATION) -> st.SearchStrategy[FloatArray]:
    """SE(3) tangent vectors xi = (rho, phi), (6,) float64."""
    return st.tuples(translations(scale), rotation_vectors(regimes)).map(np.concatenate)


def quaternions() -> st.SearchStrategy[FloatArray]:
    """Non-normalized quaternions (x, y, z, w), norm in [1e-2, 2], any sign of w."""
    c = _floats(-1.0, 1.0)
    return st.tuples(c, c, c, c).filter(lambda q: math.hypot(*q) > 1e-2).map(np.array)


def rotations(regimes: Sequence[str] = ALL_REGIMES) -> st.SearchStrategy[FloatArray]:
    """Rotation matrices: Exp of a rotation vector of ``regimes``, or of a random quaternion."""
    from_rotvec = rotation_vectors(regimes).map(lambda p: Rotation.from_rotvec(p).as_matrix())
    from_quat = quaternions().map(lambda q: Rotation.from_quat(q).as_matrix())
    return st.one_of(from_rotvec, from_quat)


def poses(regimes: Sequence[str] = ALL_REGIMES,
          scale: float = MAX_TRANSLATION) -> st.SearchStrategy[tuple[FloatArray, FloatArray]]:
    """Poses (R, t): (3, 3) rotation and (3,) translation."""
    return st.tuples(rotations(regimes), translations(scale))


def perturbations(max_size: float) -> st.SearchStrategy[FloatArray]:
    """(3, 3) matrices with entries in [-1, 1], scaled by a size in [1e-12, max_size]."""
    size = _floats(-12.0, math.log10(max_size)).map(lambda u: 10.0**u)
    entries = st.lists(_floats(-1.0, 1.0), min_size=9, max_size=9)
    return st.tuples(size, entries).map(lambda se: se[0] * np.reshape(se[1], (3, 3)))
