"""Marginal covariances of every pose (``optimize --covariance``) against the solve and GTSAM.

For each generated 10 000-pose graph: the default pipeline's solve (``hybridpgo.optimize``, as
``hybridpgo optimize`` runs it) and, for scale, the exact solver from the file's vertices; then
:func:`hybridpgo.covariance.marginal_covariances` of all poses at the solution (block Cholesky
+ selected inversion), and in the same process ``gtsam.Marginals`` of all poses on factors built
from the same information (:func:`hybridpgo.gtsam_bridge.to_gtsam`, Pose3, the gauge held by
its 1e-6 prior).  Agreement: for each pose, the largest entry of the difference over the
largest entry of GTSAM's block (after the tangent permutation), worst over all poses.

The per-pose route (one triangular solve with 6 right-hand sides per pose, CHOLMOD) is timed
on ``PER_POSE_SAMPLE`` poses and scaled to all of them, for comparison.

Run alone: ``python -m benchmarks --only covariance --run NAME`` (quick: the city only).
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from hybridpgo.graph import PoseGraph

from .metrics import Metric, info, markdown_table, quality, timing

#: (case, generator, keyword arguments): 10 000 poses each.
CASES: list[tuple[str, str, dict[str, Any]]] = [
    ("city", "city", {"num_poses": 10_000}),
    ("paris2", "city", {"preset": "paris2", "num_poses": 10_000}),
    ("paris2_gps", "city", {"preset": "paris2", "num_poses": 10_000, "gps_every": 100}),
    ("grid", "grid", {"num_poses": 10_000}),
]
PER_POSE_SAMPLE = 200
#: Repetitions of each of our timed steps (the minimum is reported: the machine is shared).
REPEATS = 3


def _graph(kind: str, kw: dict[str, Any]) -> PoseGraph:
    from hybridpgo.generate import generate_city, generate_grid

    kw = dict(kw)
    preset = kw.pop("preset", None)
    if kind == "city":
        return generate_city(preset, seed=0, **kw).graph
    return generate_grid(preset, seed=0, **kw).graph


def _best(fn: Any, repeats: int = REPEATS) -> tuple[float, Any]:
    best = float("inf")
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _gtsam_marginals(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray
                     ) -> tuple[float, np.ndarray] | None:
    """Seconds for gtsam.Marginals of every pose, and the blocks in our tangent order."""
    try:
        import gtsam
    except ImportError:
        return None
    from hybridpgo.gtsam_bridge import TO_GTSAM_TANGENT, to_gtsam

    fg, values = to_gtsam(graph, rot, trans, anchor=True, planar=False)
    back = np.argsort(TO_GTSAM_TANGENT)
    out = np.empty((graph.num_nodes, 6, 6))
    t0 = time.perf_counter()
    marginals = gtsam.Marginals(fg, values)
    for i, key in enumerate(graph.node_ids.tolist()):
        out[i] = np.asarray(marginals.marginalCovariance(key))
    seconds = time.perf_counter() - t0
    return seconds, out[:, back][:, :, back]


def _case(name: str, graph: PoseGraph) -> tuple[list[Metric], list[Any]]:
    import hybridpgo
    from hybridpgo.covariance import marginal_covariances
    from hybridpgo.linalg import BlockCholesky
    from hybridpgo.solvers import _normal
    from hybridpgo.solvers import gauss_newton as gn
    from hybridpgo.solvers.gauss_newton import solve_exact

    t_solve, res = _best(lambda: hybridpgo.optimize(graph), repeats=1)
    t_exact, _ = _best(lambda: solve_exact(graph), repeats=1)
    rot, trans = res.rotations, res.translations
    marginal_covariances(graph, rot, trans, [0])  # compile / load the kernels first
    t_cov, cov = _best(lambda: marginal_covariances(graph, rot, trans))
    # one factorization alone, for the "about twice a factorization" claim
    pat = _normal.analyze(graph, gn.default_fixed_nodes(graph), reorder=True)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    _normal.assemble(graph, pat, rot, trans, data, grad)
    block = BlockCholesky(pat.num_vars, pat.block_ptr, pat.block_row, pat.indptr)
    t_factor, _ = _best(lambda: block.factor(data))
    fill = block.factor_blocks / max(pat.num_vars, 1)
    sample = np.linspace(0, graph.num_nodes - 1, PER_POSE_SAMPLE).astype(np.int64)
    t_pp, per_pose = _best(lambda: marginal_covariances(graph, rot, trans, sample,
                                                        linear_solver="cholmod"), repeats=1)
    scale = np.maximum(np.abs(per_pose).max(axis=(1, 2)), np.finfo(float).tiny)
    pp_diff = float((np.abs(cov[sample] - per_pose).max(axis=(1, 2)) / scale).max())
    t_pp_all = t_pp * graph.num_nodes / PER_POSE_SAMPLE
    g = _gtsam_marginals(graph, rot, trans)
    key = f"covariance.{name}"
    metrics = [
        timing(f"{key}.seconds", t_cov, note="marginal_covariances of every pose"),
        info(f"{key}.solve_seconds", t_solve, "s", "hybridpgo.optimize (the default pipeline)"),
        info(f"{key}.exact_seconds", t_exact, "s", "solve_exact from the file's vertices"),
        Metric(f"{key}.over_solve", t_cov / t_solve, "", "lower", rel_tol=1.0,
               note="target <= 2"),
        info(f"{key}.over_exact", t_cov / t_exact),
        info(f"{key}.factor_seconds", t_factor, "s", "one block Cholesky factorization"),
        info(f"{key}.over_factor", t_cov / t_factor),
        info(f"{key}.factor_blocks_per_column", fill),
        info(f"{key}.per_pose_all_seconds", t_pp_all, "s",
             f"CHOLMOD triangular solves, {PER_POSE_SAMPLE} poses timed, scaled to all"),
        quality(f"{key}.vs_per_pose", pp_diff, note="worst relative block difference"),
    ]
    row: list[Any] = [name, graph.num_nodes, graph.num_constraints, f"{fill:.2f}",
                      t_solve, t_exact, t_factor, t_cov, t_cov / t_solve, t_cov / t_exact,
                      t_pp_all, pp_diff]
    if g is None:
        row += ["–", "–", "–"]
    else:
        t_g, theirs = g
        diff = np.abs(cov - theirs).max(axis=(1, 2))
        ref = np.abs(theirs).max(axis=(1, 2))
        free = ref > 1e-9  # the gauge pose: ours 0, GTSAM's the prior's 1e-12
        rel = float((diff[free] / ref[free]).max())
        metrics += [info(f"{key}.gtsam_seconds", t_g, "s", "gtsam.Marginals, every pose"),
                    info(f"{key}.over_gtsam", t_cov / t_g),
                    quality(f"{key}.vs_gtsam", rel, note="target <= 1e-6")]
        row += [t_g, t_cov / t_g, rel]
    return metrics, row


def _load() -> float:
    """The 1-minute load average (0 where the platform has none)."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return 0.0


def run(ctx: Any) -> tuple[list[Metric], list[str]]:
    metrics: list[Metric] = []
    rows: list[list[Any]] = []
    loads = [_load()]
    for name, kind, kw in CASES[:1] if ctx.quick else CASES:
        m, row = _case(name, _graph(kind, kw))
        metrics += m
        rows.append(row)
        loads.append(_load())
    metrics.append(info("covariance.load_max", max(loads), "", "1-minute load average"))
    header = ["graph", "poses", "constraints", "L blocks / column", "solve s (default)",
              "exact s", "factor s", "covariances s (all)", "/ solve", "/ exact",
              "per-pose route s (all, est.)", "vs per-pose", "GTSAM Marginals s (all)",
              "/ GTSAM", "vs GTSAM"]
    table = markdown_table("Marginal covariances of every pose (10 000-pose graphs)", header,
                           rows)
    cpus = os.cpu_count() or 0
    note = (f"Load (1-minute average) before and after each graph: "
            f"{', '.join(f'{v:.1f}' for v in loads)} on {cpus} CPUs.  Our times are the best of "
            f"{REPEATS} runs; the solves, the per-pose route and GTSAM run once.\n")
    return metrics, [table + "\n" + note]
