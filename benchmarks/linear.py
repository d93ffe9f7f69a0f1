"""Exact LM with each sparse factorization backend vs GTSAM's LM.

Every (graph, solver) case runs in its own subprocess so that its peak resident memory
(``ru_maxrss``, which sees C allocations, unlike tracemalloc) belongs to that case alone.  All
solvers start from the file's vertices (dead reckoning for the cities), with the same factors:
GTSAM's are built from our converted information (:mod:`benchmarks.gtsam_ref`), so
``2 * GTSAM error = E``.

Solvers: ``cholmod`` (ours, CHOLMOD via cvxopt), ``splu`` (ours, SuperLU on the block AMD
ordering: the fallback), ``splu_mmd`` (the old default: SuperLU on SuperLU's block MMD ordering;
one iteration only, paris2 with GPS, with a time limit), ``gtsam_lm`` (GTSAM's
LevenbergMarquardtOptimizer, relative tolerance 1e-10 like ours).

Run one case by hand: ``python -m benchmarks.linear DATA_DIR CASE SOLVER [MAX_ITERATIONS]``.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from typing import Any

import numpy as np

from .metrics import Metric, info, markdown_table, quality, timing

#: (case name, dataset file or city preset, GPS every k poses or None)
CASES: list[tuple[str, str, int | None]] = [
    ("sphere2500", "sphere2500.g2o", None),
    ("M3500", "M3500.g2o", None),
    ("paris1", "paris1", None),
    ("paris1_gps", "paris1", 100),
    ("paris2", "paris2", None),
    ("paris2_gps", "paris2", 100),
]
#: Seconds allowed for one case's subprocess (the old SuperLU path may take minutes).
_TIME_LIMIT = 900.0
#: The old SuperLU + MMD path is timed on this case only, for one iteration, within this limit.
_OLD_CASE = "paris2_gps"
_OLD_TIME_LIMIT = 600.0


def _rss_mb() -> float:
    """Current resident set size of this process, MB (from /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _load(data_dir: str, case: str) -> Any:
    from hybridpgo.generate import generate_city
    from hybridpgo.io import read_graph

    _, source, gps = next(c for c in CASES if c[0] == case)
    if source.endswith(".g2o"):
        return read_graph(os.path.join(data_dir, source))
    return generate_city(source, seed=0, gps_every=gps).graph


def worker(data_dir: str, case: str, solver: str, max_iterations: int) -> dict[str, Any]:
    """Run one case in this process; return its numbers."""
    graph = _load(data_dir, case)
    rot = np.array(graph.rotations)
    trans = np.array(graph.translations)
    out: dict[str, Any] = {"case": case, "solver": solver, "poses": graph.num_nodes,
                           "edges": graph.num_edges, "gps": graph.num_gps}
    if solver == "gtsam_lm":
        import gtsam

        from .gtsam_ref import build

        factors, full, values = build(graph, rot, trans)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(1e-10)
        params.setAbsoluteErrorTol(0.0)
        out["initial_energy"] = 2.0 * factors.error(values)
        rss0 = _rss_mb()
        t0 = time.perf_counter()
        opt = gtsam.LevenbergMarquardtOptimizer(full, values, params)
        result = opt.optimize()
        out["seconds"] = time.perf_counter() - t0
        out["final_energy"] = 2.0 * factors.error(result)
        out["iterations"] = int(opt.iterations())
    else:
        from hybridpgo.linalg import _factor as _linear
        from hybridpgo.solvers.config import GaussNewtonConfig
        from hybridpgo.solvers.gauss_newton import ensure_compiled, solve_exact

        if solver == "splu_mmd":  # the old default: no AMD, SuperLU's MMD on the block graph
            _linear.cvxopt_available = lambda: False  # type: ignore[attr-defined]
        ensure_compiled()
        rss0 = _rss_mb()
        res = solve_exact(graph, rot, trans, GaussNewtonConfig(
            linear_solver="splu" if solver.startswith("splu") else solver,
            max_iterations=max_iterations))
        it = max(res.iterations, 1)
        out.update(
            seconds=res.timings["total"], analyze_seconds=res.timings["analyze"],
            linear_seconds_per_iteration=res.timings["factorize"] / it,
            initial_energy=float(res.energy_history[0]), final_energy=res.final_energy,
            iterations=res.iterations, status=res.status.name,
            linear_solver=res.stats["linear_solver"], unknowns=res.stats["num_variables"],
            hessian_nnz=res.stats["hessian_nnz"])
    out["rss_before_mb"] = rss0
    out["peak_mb"] = _peak_mb()
    return out


def _run_case(data_dir: str, case: str, solver: str, max_iterations: int = 100,
              limit: float = _TIME_LIMIT) -> dict[str, Any]:
    """One case in a fresh subprocess; on a time-out, {"timeout": limit}."""
    cmd = [sys.executable, "-m", "benchmarks.linear", data_dir, case, solver, str(max_iterations)]
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=here, capture_output=True, text=True, timeout=limit,
                              check=False)
    except subprocess.TimeoutExpired:
        return {"case": case, "solver": solver, "timeout": limit}
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr}")
    out: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    out["wall"] = time.perf_counter() - t0
    return out


def run(ctx: Any) -> tuple[list[Metric], list[str]]:
    from .gtsam_ref import gtsam_available

    data_dir = str(ctx.data_dir)
    have_gtsam = gtsam_available()
    metrics: list[Metric] = []
    rows: list[list[Any]] = []
    repeats = 1 if ctx.quick else 2
    for case, _, _ in CASES:
        runs: dict[str, dict[str, Any]] = {}
        solvers = ["cholmod", "splu"] + (["gtsam_lm"] if have_gtsam else [])
        for _ in range(repeats):  # interleaved; keep each solver's fastest run
            for s in solvers:
                r = _run_case(data_dir, case, s)
                print(f"  {case} {s}: {r.get('seconds', 0.0):.2f} s", file=sys.stderr,
                      flush=True)
                if s not in runs or r["seconds"] < runs[s]["seconds"]:
                    runs[s] = r
        ours, fb = runs["cholmod"], runs["splu"]
        gt = runs.get("gtsam_lm")
        ratio = ours["seconds"] / gt["seconds"] if gt else float("nan")
        metrics += [
            quality(f"linear.{case}.cholmod.energy", ours["final_energy"]),
            timing(f"linear.{case}.cholmod.seconds", ours["seconds"]),
            timing(f"linear.{case}.cholmod.linear_s_per_iteration",
                   ours["linear_seconds_per_iteration"]),
            info(f"linear.{case}.cholmod.iterations", ours["iterations"]),
            info(f"linear.{case}.cholmod.peak_mb", ours["peak_mb"], "MB"),
            timing(f"linear.{case}.splu.seconds", fb["seconds"]),
            info(f"linear.{case}.splu.linear_s_per_iteration",
                 fb["linear_seconds_per_iteration"], "s"),
        ]
        if gt:
            metrics += [
                info(f"linear.{case}.gtsam_lm.seconds", gt["seconds"], "s"),
                info(f"linear.{case}.gtsam_lm.energy", gt["final_energy"]),
                info(f"linear.{case}.gtsam_lm.peak_mb", gt["peak_mb"], "MB"),
                Metric(f"linear.{case}.cholmod_over_gtsam_lm", ratio, "x", "lower",
                       rel_tol=1.0, note="target <= 1"),
            ]
        rows.append([
            case, ours["poses"], ours["edges"], ours["gps"], ours["unknowns"],
            ours["final_energy"], gt["final_energy"] if gt else "-",
            ours["iterations"], gt["iterations"] if gt else "-",
            f"{ours['seconds']:.2f}", f"{gt['seconds']:.2f}" if gt else "-", f"{ratio:.2f}",
            f"{ours['analyze_seconds']:.3f}", f"{ours['linear_seconds_per_iteration']:.3f}",
            f"{fb['linear_seconds_per_iteration']:.3f}", f"{fb['seconds']:.2f}",
            f"{ours['peak_mb']:.0f} ({ours['peak_mb'] - ours['rss_before_mb']:.0f})",
            f"{fb['peak_mb']:.0f} ({fb['peak_mb'] - fb['rss_before_mb']:.0f})",
            (f"{gt['peak_mb']:.0f} ({gt['peak_mb'] - gt['rss_before_mb']:.0f})" if gt
             else "-"),
        ])
    tables = [markdown_table(
        "Exact LM from the file's vertices: ours (CHOLMOD via cvxopt; SuperLU fallback) vs "
        f"GTSAM LM, same factors, one subprocess per run, fastest of {repeats}",
        ["case", "poses", "edges", "GPS", "unknowns", "our E", "GTSAM E", "our iters",
         "GTSAM iters", "our s", "GTSAM s", "ours / GTSAM", "our analyze s",
         "our linear s / iter", "SuperLU linear s / iter", "SuperLU total s",
         "our peak MB (solve)", "SuperLU peak MB (solve)", "GTSAM peak MB (solve)"],
        rows)]
    if not ctx.quick:
        old = _run_case(data_dir, _OLD_CASE, "splu_mmd", max_iterations=1,
                        limit=_OLD_TIME_LIMIT)
        if "timeout" in old:
            cell = f"> {old['timeout']:.0f} (time limit)"
            metrics.append(info(f"linear.{_OLD_CASE}.splu_mmd.timeout_s", old["timeout"], "s"))
        else:
            cell = f"{old['linear_seconds_per_iteration']:.1f}"
            metrics.append(info(f"linear.{_OLD_CASE}.splu_mmd.linear_s_per_iteration",
                                old["linear_seconds_per_iteration"], "s"))
        tables.append(markdown_table(
            "The old default (SuperLU on SuperLU's block MMD ordering), one iteration",
            ["case", "linear s / iter", "peak MB"],
            [[_OLD_CASE, cell, f"{old['peak_mb']:.0f}" if "peak_mb" in old else "-"]]))
    return metrics, tables


if __name__ == "__main__":
    _max_it = int(sys.argv[4]) if len(sys.argv) > 4 else 100
    print(json.dumps(worker(sys.argv[1], sys.argv[2], sys.argv[3], _max_it)))
