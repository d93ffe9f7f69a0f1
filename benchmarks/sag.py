"""Sweeps that converge (issue 11 item 3): ``update="saga"`` against the paper's update.

From the paper's setup (tree initialization, BFS tree, tau = 1 x 0.99 per sweep, no polish) on
M3500_isam, intel and a generated 4000-pose city with a GPS reading every 100 poses: energy /
optimum after 10, 30 and 100 sweeps (30 with ``--quick``) and the solve time per sweep.  The
optimum is LM from the chordal start (``Context.optimum``; the city's: LM from the city's
vertices, which are its ground truth).

Run: ``PYTHONPATH=src python -m benchmarks --only sag --run <name>``.
"""

from __future__ import annotations

from hybridpgo.generate import generate_city
from hybridpgo.graph import PoseGraph
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver

from .metrics import Metric, markdown_table, quality, timing
from .workloads import Context, Result

UPDATES = ("paper", "saga")
CHECKPOINTS = (10, 30, 100)


def _graphs(ctx: Context) -> list[tuple[str, PoseGraph, float]]:
    out = []
    for name in ("M3500_isam.txt", "intel.g2o"):
        out.append((name.split(".")[0], ctx.graph(name), ctx.optimum(name)))
    city = generate_city(seed=0, num_poses=4000, gps_every=100).graph
    opt = solve_exact(city, config=GaussNewtonConfig(max_iterations=300)).final_energy
    out.append(("city4000_gps", city, opt))
    return out


def run(ctx: Context) -> Result:
    metrics: list[Metric] = []
    rows = []
    checkpoints = tuple(k for k in CHECKPOINTS if not ctx.quick or k <= 30)
    for stem, graph, opt in _graphs(ctx):
        m = graph.num_constraints
        for update in UPDATES:
            if update == "saga" and graph.num_gps:
                continue  # refused: diverged here (2026-11-23-sag: 1.3e6 per constraint)
            solver = HybridSolver(graph, HybridConfig(init="tree", update=update))
            res = solver.run(max(checkpoints))
            hist = res.energy_history
            per_sweep = res.timings["solve"] / max(res.iterations, 1)
            for k in checkpoints:
                metrics.append(quality(f"{stem}.{update}{k}.energy_ratio", hist[k] / opt))
            metrics.append(timing(f"{stem}.{update}.s_per_sweep", per_sweep, "s"))
            rows.append([stem, update, f"{opt / m:.4f}"]
                        + [f"{hist[k] / m:.4f} ({hist[k] / opt:.3f})" for k in checkpoints]
                        + [f"{per_sweep * 1e3:.1f}"])
    return metrics, [markdown_table(
        "Sweeps alone from the tree initialization (tau = 1 x 0.99 per sweep, no polish): "
        "energy per constraint (energy / optimum)",
        ["graph", "update", "optimum"] + [f"{k} sweeps" for k in checkpoints] + ["ms / sweep"],
        rows)]
