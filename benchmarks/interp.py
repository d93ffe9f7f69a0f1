"""Interpolated solving (paper III-E): time per update on valencia for several D_max.

Run: ``PYTHONPATH=src python -m benchmarks --only interp --run <name>`` (about 2 minutes; the
same valencia runs as Table I of ``benchmarks/paper.py``, Woodbury step only, plus the GPS
variant and a micro-benchmark of the longest constraint).

* ``interp.valencia.dmax<D>.us_mean / us_max_steady``: 10 sweeps from the tree initialization,
  mean and steady max (largest over constraints of each one's cheapest update) per update.
* ``interp.valencia.longest.dmax<D>.us_best``: best of 30 single updates of the constraint with
  the longest domain (``HybridSolver.step([c], tau=1e-9)``).
* ``interp.valencia_gps.dmax<D>.ms_gps_batch_max_steady``: the GPS batches' steady max.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver

from .metrics import Metric, info, markdown_table, quality, timing
from .workloads import Context, Result

SWEEPS = 10
DMAXES: tuple[int | None, ...] = (75, 100, 150, 200, None)
REPEAT = 30


def _graph(ctx: Context, tag: str) -> Any:
    key = f"paper:graph:{tag}"  # shared with benchmarks/paper.py when both run
    if key not in ctx.cache:
        from hybridpgo.generate import generate_city

        preset, _, gps = tag.partition("_")
        city = generate_city(preset, seed=0, gps_every=100 if gps else None)
        ctx.cache[key] = (city.graph, city)
    return ctx.cache[key][0]


def _tag(dmax: int | None) -> str:
    return "inf" if dmax is None else str(dmax)


def _longest(graph: Any, dmax: int | None) -> float:
    """Best single-update time (us) of the constraint with the longest domain."""
    solver = HybridSolver(graph, HybridConfig(dmax=dmax))
    c = int(np.argmax(solver.tree.path_lengths()))
    best = float("inf")
    for _ in range(REPEAT):
        t0 = time.perf_counter()
        solver.step([c], tau=1e-9)
        best = min(best, time.perf_counter() - t0)
    return best * 1e6


def run(ctx: Context) -> Result:
    metrics: list[Metric] = []
    rows: list[list[Any]] = []
    HybridSolver(_graph(ctx, "valencia_gps"), HybridConfig(sweeps=1, dmax=10)).run()  # compile
    for tag in ("valencia", "valencia_gps"):
        g = _graph(ctx, tag)
        dmaxes = DMAXES if tag == "valencia" else (200, None)
        for dmax in dmaxes:
            res = HybridSolver(g, HybridConfig(sweeps=SWEEPS, dmax=dmax)).run()
            st = res.stats
            key = f"interp.{tag}.dmax{_tag(dmax)}"
            e_c = res.final_energy / max(res.num_constraints, 1)
            longest = _longest(g, dmax)
            metrics += [
                timing(f"{key}.us_mean", st["us_per_constraint_mean"], "us"),
                timing(f"{key}.us_max_steady", st["us_per_constraint_max_steady"], "us"),
                timing(f"{key}.ms_gps_batch_max_steady", st["ms_per_gps_batch_max_steady"], "ms"),
                timing(f"interp.{tag}.longest.dmax{_tag(dmax)}.us_best", longest, "us"),
                quality(f"{key}.energy_per_constraint", e_c),
                info(f"{key}.solve_s", res.timings["solve"], "s"),
            ]
            rows.append([tag, _tag(dmax), f"{st['us_per_constraint_mean']:.2f}",
                         f"{st['us_per_constraint_max_steady']:.0f}",
                         f"{st['us_per_constraint_max']:.0f}",
                         f"{st['ms_per_gps_batch_max_steady']:.2f}", f"{longest:.0f}",
                         f"{res.timings['solve']:.2f}", f"{e_c:.4g}"])
    table = markdown_table(
        f"Interpolated solving: time per update, {SWEEPS} sweeps, Woodbury step (longest: best "
        f"of {REPEAT} updates of the constraint with the longest domain)",
        ["graph", "D_max", "mean us", "steady max us", "max us", "GPS batch steady max ms",
         "longest us", "solve s", "E / constraint"], rows)
    return metrics, [table]
