"""GTSAM reference runs on factors built from *our* converted information (DESIGN.md §1).

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
    """(factors without the gauge prior, factors with it, initial values).

    The gauge prior (sigma 1e-6 on pose 0) is added only without GPS constraints: with them the
    earth frame is the gauge, as in :func:`hybridpgo.solvers.gauss_newton.default_fixed_nodes`.
    """
    import gtsam

    factors = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    perm = np.r_[3:6, 0:3]  # our (rho, phi) -> GTSAM's (rotation, translation)
    planar = graph.is_2d
    idx2 = np.array([0, 1, 5])
    for i in range(graph.num_nodes):
        if planar:
            values.insert(
                i,
                gtsam.Pose2(
                    trans[i, 0], trans[i, 1], float(np.arctan2(rot[i, 1, 0], rot[i, 0, 0]))
                ),
            )
        else:
            values.insert(i, gtsam.Pose3(gtsam.Rot3(rot[i]), trans[i]))
    for c, (a, b) in enumerate(graph.edge_nodes):
        info = graph.edge_information[c]
        rz, tz = graph.edge_rotations[c], graph.edge_translations[c]
        if planar:
            model = gtsam.noiseModel.Gaussian.Information(info[np.ix_(idx2, idx2)])
            z = gtsam.Pose2(tz[0], tz[1], float(np.arctan2(rz[1, 0], rz[0, 0])))
            factors.add(gtsam.BetweenFactorPose2(int(a), int(b), z, model))
        else:
            model = gtsam.noiseModel.Gaussian.Information(info[np.ix_(perm, perm)])
            factors.add(
                gtsam.BetweenFactorPose3(int(a), int(b), gtsam.Pose3(gtsam.Rot3(rz), tz), model)
            )
    if graph.num_gps and planar:
        raise NotImplementedError("GPS constraints on a 2D graph in the GTSAM comparison")
    for c, n in enumerate(graph.gps_nodes):  # error t_n - g_c in the earth frame, as ours
        model = gtsam.noiseModel.Gaussian.Information(graph.gps_information[c])
        factors.add(gtsam.GPSFactor(int(n), graph.gps_positions[c], model))
    full = gtsam.NonlinearFactorGraph(factors)
    if planar:
        full.add(
            gtsam.PriorFactorPose2(0, values.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6))
        )
    elif not graph.num_gps:  # with GPS the earth frame is the gauge, as in our exact solver
        full.add(
            gtsam.PriorFactorPose3(0, values.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))
        )
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
