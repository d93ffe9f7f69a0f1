"""Robust kernels by name and code, and their default scales (no Numba: the solvers' options
and the command line's help import this without the kernels of :mod:`hybridpgo._cost`)."""

from __future__ import annotations

import math

#: Robust kernels (docs/conventions.md#robust-kernels) by code: ``ROBUST_NAMES[code]`` is the
#: name the configs accept.
ROBUST_NAMES = ("none", "huber", "cauchy", "geman_mcclure")
ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_CAUCHY = 2
ROBUST_GEMAN_MCCLURE = 3


#: Default delta of each kernel (whitened units).  An inlier's χ² over 6 degrees of freedom is
#: below 16.8 (delta ~ 4.1) 99% of the time; measured on M3500 with 0-1000 false loop closures
#: (benchmarks/results/2026-11-23-outliers.md): Geman-McClure needs delta ~ 10 (delta 3 down-
#: weights true loop closures: 1.12-1.18x the outlier-free position error even with no
#: outliers; delta 10: 1.006-1.021x); Huber and Cauchy were measured at 3.
ROBUST_DEFAULT_SCALE: dict[str, float] = {"none": 1.0, "huber": 3.0, "cauchy": 3.0,
                                          "geman_mcclure": 10.0}


def default_robust_scale(robust: str, scale: float | None) -> float:
    """``scale``, or the default delta of the kernel ``robust`` when None."""
    if scale is not None:
        return scale
    return ROBUST_DEFAULT_SCALE.get(robust, 1.0)  # an unknown name fails in robust_kind


def robust_kind(name: str, scale: float) -> int:
    """The kernel code of a robust kernel's name; ValueError for a bad name or scale."""
    if name not in ROBUST_NAMES:
        raise ValueError(f"robust must be one of {', '.join(ROBUST_NAMES)}, got {name!r}")
    if (isinstance(scale, bool) or not isinstance(scale, (int, float))
            or not (math.isfinite(scale) and scale > 0)):
        raise ValueError(f"robust_scale must be a finite number > 0, got {scale!r}")
    return ROBUST_NAMES.index(name)
