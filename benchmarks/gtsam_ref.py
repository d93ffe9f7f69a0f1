"""GTSAM reference runs on factors built from *our* converted information (docs/conventions.md) by
:mod:`hybridpgo.gtsam_bridge`.

Built this way, ``2 * graph.error`` equals our energy E, so energies and times compare directly.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from hybridpgo.graph import PoseGraph


def gtsam_available() -> bool:
    try:
        import gtsam  # noqa: F401
    except ImportError:
        return False
    return True


def build(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray) -> tuple[Any, Any, Any]:
    """(factors without the gauge prior, factors with it, initial values), from the bridge."""
    import gtsam

    from hybridpgo.gtsam_bridge import gauge_prior, to_gtsam

    factors, values = to_gtsam(graph, rot, trans)
    full = gtsam.NonlinearFactorGraph(factors)
    full.push_back(gauge_prior(graph, values))
    return factors, full, values


def gtsam_solve(
    graph: PoseGraph, rot: np.ndarray, trans: np.ndarray, method: str, max_iterations: int = 100
) -> dict[str, Any]:
    import gtsam

    factors, full, values = build(graph, rot, trans)
    if method == "gn":
        params = gtsam.GaussNewtonParams()
    else:
        params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    e0 = 2.0 * factors.error(values)
    t0 = time.perf_counter()
    opt = (
        gtsam.GaussNewtonOptimizer(full, values, params)
        if method == "gn"
        else gtsam.LevenbergMarquardtOptimizer(full, values, params)
    )
    result = opt.optimize()
    seconds = time.perf_counter() - t0
    return {
        "initial_energy": e0,
        "final_energy": 2.0 * factors.error(result),
        "iterations": int(opt.iterations()),
        "seconds": seconds,
    }


def gtsam_time_to(
    graph: PoseGraph,
    rot: np.ndarray,
    trans: np.ndarray,
    optimum: float,
    fractions: tuple[float, ...],
    max_iterations: int = 200,
) -> dict[float, float]:
    """Seconds GTSAM's LM needs to reach E <= optimum (1 + f) (NaN if never)."""
    import gtsam

    factors, full, values = build(graph, rot, trans)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(0.0)
    params.setAbsoluteErrorTol(0.0)
    opt = gtsam.LevenbergMarquardtOptimizer(full, values, params)
    out = {f: float("nan") for f in fractions}
    t0 = time.perf_counter()
    for _ in range(max_iterations):
        opt.iterate()
        e = 2.0 * factors.error(opt.values())
        now = time.perf_counter() - t0
        for f in fractions:
            if np.isnan(out[f]) and e <= optimum * (1 + f):
                out[f] = now
        if not any(np.isnan(v) for v in out.values()):
            break
    return out
