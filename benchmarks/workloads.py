"""Benchmark workloads.  Each returns (metrics, markdown tables).

Datasets are read from ``--data-dir`` (default: ``$HYBRIDPGO_DATASETS``, else the bundled graphs);
the package itself never reads them.  Every number in the benchmark tables comes from here.
"""

from __future__ import annotations

import pathlib
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hybridpgo.graph import PoseGraph
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.hybrid import HybridConfig, solve_hybrid
from hybridpgo.tree import build_tree

from .context import Context, Result, start
from .metrics import Metric, info, markdown_table, quality, timing


def _stem(name: str) -> str:
    return name.split(".")[0]


# ------------------------------------------------------------------ exact solver
EXACT_TARGETS = {
    "sphere2500.g2o": 727.285,
    "M3500.g2o": 3549.04,
    "garage.g2o": 1.23868,
    "intel.g2o": 45.0042,
    "M3500_isam.txt": 6532.8,
}


def exact(ctx: Context) -> Result:
    from .gtsam_ref import gtsam_available, gtsam_solve

    metrics: list[Metric] = []
    rows = []
    for name, target in EXACT_TARGETS.items():
        g = ctx.graph(name)
        init = "file" if g.has_estimates else "tree"
        rot, trans = start(g, init)
        solve_exact(g, rot, trans, GaussNewtonConfig(max_iterations=1))  # compile outside timing
        res = solve_exact(g, rot, trans, GaussNewtonConfig(method="lm"))
        it = max(res.iterations, 1)
        spi = res.timings["solve"] / it
        s = _stem(name)
        rel = abs(res.final_energy - target) / target
        metrics += [
            quality(f"{s}.exact.energy", res.final_energy),
            info(f"{s}.exact.iterations", res.iterations),
            timing(f"{s}.exact.s_per_iteration", spi),
            timing(f"{s}.exact.solve_s", res.timings["solve"]),
        ]
        row: list[Any] = [
            name,
            init,
            res.initial_energy,
            target,
            res.final_energy,
            f"{rel:.1e}",
            res.iterations,
            f"{spi * 1e3:.1f}",
            f"{res.timings['solve']:.3f}",
        ]
        if gtsam_available():
            gn = gtsam_solve(g, rot, trans, "gn")
            lm = gtsam_solve(g, rot, trans, "lm")
            metrics += [
                info(f"{s}.gtsam_gn.energy", gn["final_energy"]),
                info(f"{s}.gtsam_gn.seconds", gn["seconds"], "s"),
                info(f"{s}.gtsam_lm.seconds", lm["seconds"], "s"),
            ]
            row += [
                f"{abs(gn['initial_energy'] - res.initial_energy) / res.initial_energy:.1e}",
                gn["final_energy"],
                gn["iterations"],
                f"{gn['seconds']:.3f}",
                f"{res.timings['solve'] / gn['seconds']:.2f}",
                lm["final_energy"],
                f"{lm['seconds']:.3f}",
            ]
        else:
            row += ["-"] * 7
        rows.append(row)
    table = markdown_table(
        "Exact solver (our LM) vs GTSAM, same start, same machine",
        [
            "file",
            "start",
            "E at start",
            "target E",
            "our E",
            "rel. diff",
            "iters",
            "ms/iter",
            "solve s",
            "|E0 - 2 GTSAM err0| / E0",
            "GTSAM GN E",
            "GN iters",
            "GN s",
            "ours/GN time",
            "GTSAM LM E",
            "LM s",
        ],
        rows,
    )
    return metrics, [table]


# ------------------------------------------------------------------ hybrid solver
def _hybrid(g: PoseGraph, **kw: Any) -> Any:
    return solve_hybrid(g, HybridConfig(**kw))


def hybrid_manhattan(ctx: Context) -> Result:
    name = "M3500_isam.txt"
    g = ctx.graph(name)
    m = g.num_constraints
    opt = ctx.optimum(name)
    _hybrid(g, sweeps=1)  # compile
    r10 = _hybrid(g, sweeps=10)
    r40 = _hybrid(g, sweeps=40) if not ctx.quick else r10
    pol = _hybrid(g, sweeps=10, polish=True)
    metrics = [
        quality("M3500_isam.hybrid10.energy_per_constraint", r10.final_energy / m),
        quality("M3500_isam.hybrid40.energy_per_constraint", r40.final_energy / m),
        quality("M3500_isam.hybrid10_polish.energy_per_constraint", pol.final_energy / m),
        info("M3500_isam.optimum.energy_per_constraint", opt / m),
        timing("M3500_isam.hybrid.us_per_constraint", r10.stats["us_per_constraint_mean"], "us"),
        timing("M3500_isam.hybrid.us_per_constraint_max", r10.stats["us_per_constraint_max"], "us"),
        timing("M3500_isam.hybrid.us_per_constraint_max_steady",
               r10.stats["us_per_constraint_max_steady"], "us"),
    ]
    rows = [
        ["tree init", "-", r10.initial_energy / m, "-"],
        [
            "10 sweeps",
            f"{r10.timings['solve']:.2f}",
            r10.final_energy / m,
            f"{r10.final_energy / opt:.3f}",
        ],
        [
            "40 sweeps",
            f"{r40.timings['solve']:.2f}",
            r40.final_energy / m,
            f"{r40.final_energy / opt:.3f}",
        ],
        [
            "10 sweeps + LM polish",
            f"{pol.timings['solve'] + pol.timings['polish']:.2f}",
            pol.final_energy / m,
            f"{pol.final_energy / opt:.9f}",
        ],
        ["paper: hybrid, 10 sweeps", "-", 1.596, "-"],
        ["paper: TORO", "-", 2.062, "-"],
        ["exact optimum", "-", opt / m, "1"],
    ]
    hist = " ".join(f"{e / m:.3f}" for e in r10.energy_history)
    return metrics, [
        markdown_table(
            f"Manhattan (M3500_isam.txt, {m} constraints), tree initialization",
            ["run", "solve s", "E / constraint", "E / optimum"],
            rows,
        )
        + f"\nEnergy per constraint by sweep: {hist}\n"
        + f"\nPer-constraint update: mean {r10.stats['us_per_constraint_mean']:.2f} us, "
        f"max {r10.stats['us_per_constraint_max']:.0f} us, p99.9 "
        f"{r10.stats['us_per_constraint_p999']:.0f} us, steady max "
        f"{r10.stats['us_per_constraint_max_steady']:.0f} us "
        f"(max path {r10.stats['path_length_max']})\n"
    ]


def hybrid_quality(ctx: Context) -> Result:
    metrics: list[Metric] = []
    rows = []
    for name in ("sphere2500.g2o", "garage.g2o", "M3500.g2o", "intel.g2o"):
        g = ctx.graph(name)
        opt = ctx.optimum(name)
        s = _stem(name)
        _hybrid(g, sweeps=1)
        r30 = _hybrid(g, sweeps=10 if ctx.quick else 30)
        pol = _hybrid(g, sweeps=10, polish=True, polish_iterations=200)
        e10 = r30.energy_history[min(10, len(r30.energy_history) - 1)]
        metrics += [
            quality(f"{s}.hybrid10.energy_ratio", e10 / opt),
            quality(f"{s}.hybrid30.energy_ratio", r30.final_energy / opt),
            quality(f"{s}.hybrid10_polish.energy_ratio", pol.final_energy / opt),
            timing(f"{s}.hybrid.us_per_constraint", r30.stats["us_per_constraint_mean"], "us"),
            timing(f"{s}.hybrid.us_per_constraint_max", r30.stats["us_per_constraint_max"], "us"),
            timing(f"{s}.hybrid.us_per_constraint_max_steady",
                   r30.stats["us_per_constraint_max_steady"], "us"),
        ]
        rows.append(
            [
                name,
                r30.initial_energy / opt,
                e10 / opt,
                r30.final_energy / opt,
                f"{pol.final_energy / opt:.9f}",
                f"{r30.stats['us_per_constraint_mean']:.2f}",
                f"{r30.stats['us_per_constraint_max']:.0f}",
                f"{r30.stats['us_per_constraint_max_steady']:.0f}",
                r30.stats["path_length_max"],
                f"{r30.stats['path_length_mean']:.1f}",
            ]
        )
    return metrics, [
        markdown_table(
            "Hybrid sweeps from the tree initialization: energy / exact optimum",
            [
                "file",
                "initial",
                "10 sweeps",
                "30 sweeps",
                "10 sweeps + LM polish",
                "us/constraint mean",
                "max us",
                "steady max us",
                "max path",
                "mean path",
            ],
            rows,
        )
    ]


def robustness(ctx: Context) -> Result:
    metrics: list[Metric] = []
    rows = []
    cases = [("torus3D.g2o", 15), ("sphere_bignoise_vertex3.g2o", 10)]
    for name, sweeps in cases:
        g = ctx.graph(name)
        s = _stem(name)
        opt = ctx.optimum(name)
        rot, trans = start(g, "tree")
        lm = solve_exact(g, rot, trans, GaussNewtonConfig(max_iterations=300))
        hy = _hybrid(g, sweeps=sweeps, polish=True, polish_iterations=300)
        hc = _hybrid(g, sweeps=sweeps, init="chordal", polish=True, polish_iterations=300)
        lf = solve_exact(g, None, None, GaussNewtonConfig(max_iterations=300))
        hf = _hybrid(g, sweeps=sweeps, init="file", polish=True, polish_iterations=300)
        for label, res in (
            ("lm_tree", lm),
            ("hybrid_polish_tree", hy),
            ("hybrid_polish_chordal", hc),
            ("lm_file", lf),
            ("hybrid_polish_file", hf),
        ):
            metrics.append(quality(f"{s}.{label}.energy_ratio", res.final_energy / opt))
        rows += [
            [name, "LM from the file's vertices", lf.final_energy, lf.final_energy / opt],
            [
                name,
                f"hybrid {sweeps} sweeps + LM, file's vertices",
                hf.final_energy,
                hf.final_energy / opt,
            ],
            [name, "LM from tree (BFS concatenation)", lm.final_energy, lm.final_energy / opt],
            [
                name,
                f"hybrid {sweeps} sweeps + LM, tree init",
                hy.final_energy,
                hy.final_energy / opt,
            ],
            [
                name,
                f"hybrid {sweeps} sweeps + LM, chordal init",
                hc.final_energy,
                hc.final_energy / opt,
            ],
        ]
    # the paper's noisified Manhattan (Fig. 8)
    from hybridpgo.generate import noisify

    g = noisify(ctx.graph("M3500_isam.txt"), yaw_sigma_deg=3.0, seed=0)
    ctx.cache["noisy"] = g
    rot, trans = start(g, "chordal")
    best = solve_exact(g, rot, trans, GaussNewtonConfig(max_iterations=300)).final_energy
    rot, trans = start(g, "tree")
    lm = solve_exact(g, rot, trans, GaussNewtonConfig(max_iterations=300))
    hy = _hybrid(g, sweeps=40, polish=True, polish_iterations=300)
    best = min(best, lm.final_energy, hy.final_energy)
    metrics += [
        quality("M3500_noisy3deg.lm_tree.energy_ratio", lm.final_energy / best),
        quality("M3500_noisy3deg.hybrid_polish_tree.energy_ratio", hy.final_energy / best),
    ]
    rows += [
        [
            "M3500_isam noisified 3 deg (seed 0)",
            "LM from tree",
            lm.final_energy,
            lm.final_energy / best,
        ],
        [
            "M3500_isam noisified 3 deg (seed 0)",
            "hybrid 40 sweeps + LM, tree init",
            hy.final_energy,
            hy.final_energy / best,
        ],
    ]
    return metrics, [
        markdown_table(
            "Robustness to poor starts: final energy / best known optimum",
            ["graph", "method", "final E", "E / optimum"],
            rows,
        )
    ]


def step_scaling(ctx: Context) -> Result:
    """Woodbury O(d) vs Givens O(d^2): one loop closure of path length d."""
    from hybridpgo.solvers.hybrid import HybridSolver

    metrics: list[Metric] = []
    rows = []
    for d in (10, 100, 1000):
        n = 2 * d  # a ring: the tree splits it in two, the closing edge spans ~d nodes
        rng = np.random.default_rng(0)
        pairs = [(i, i + 1) for i in range(n - 1)] + [(0, n - 1)]
        en = np.array(pairs, np.int32)
        m = en.shape[0]
        zr = np.tile(np.eye(3), (m, 1, 1))
        zt = np.zeros((m, 3))
        zt[:, 0] = 1.0
        zt[-1, 0] = float(n - 1) + 0.5
        zt += rng.normal(scale=0.01, size=zt.shape)
        g = PoseGraph(
            node_ids=np.arange(n),
            rotations=np.tile(np.eye(3), (n, 1, 1)),
            translations=np.zeros((n, 3)),
            edge_nodes=en,
            edge_rotations=zr,
            edge_translations=zt,
            edge_information=np.tile(np.eye(6), (m, 1, 1)),
        )
        tree = build_tree(g)
        st = HybridSolver(g, HybridConfig(init="tree"), tree=tree)
        c = int(np.argmax(tree.path_lengths()))
        dd = int(tree.path_ptr[c + 1] - tree.path_ptr[c])
        out = {}
        for name in ("woodbury", "givens"):
            st.probe(c, name)
            reps = 2000 if (name == "woodbury" or d <= 100) else 3
            t0 = time.perf_counter()
            for _ in range(reps):
                st.probe(c, name)
            out[name] = (time.perf_counter() - t0) / reps * 1e6
        metrics += [
            timing(f"step_d{d}.woodbury_us", out["woodbury"], "us"),
            timing(f"step_d{d}.givens_us", out["givens"], "us"),
        ]
        rows.append(
            [
                dd,
                f"{out['woodbury']:.1f}",
                f"{out['givens']:.1f}",
                f"{out['givens'] / out['woodbury']:.1f}",
            ]
        )
    return metrics, [
        markdown_table(
            "One constraint update (linearize + solve, Python call overhead included): "
            "Woodbury vs Givens",
            ["path length d", "Woodbury us", "Givens us", "ratio"],
            rows,
        )
    ]


def time_to_optimum(ctx: Context) -> Result:
    from .gtsam_ref import gtsam_available, gtsam_time_to

    metrics: list[Metric] = []
    rows = []
    for name in ("M3500_isam.txt", "sphere2500.g2o", "garage.g2o"):
        g = ctx.graph(name)
        s = _stem(name)
        opt = ctx.optimum(name)
        rot, trans = start(g, "tree")
        t0 = time.perf_counter()
        hy = _hybrid(g, sweeps=10, polish=True, polish_iterations=200)
        wall = time.perf_counter() - t0
        lm = solve_exact(g, rot, trans, GaussNewtonConfig(max_iterations=300))

        def reach(res: Any, frac: float, offset: float = 0.0, opt: float = opt) -> float:
            hit = np.nonzero(np.asarray(res.energy_history) <= opt * (1 + frac))[0]
            return float(res.times[hit[0]]) + offset if hit.size else float("nan")

        # hybrid times: analyze (tree + init + blocks) counted too
        off = hy.timings["analyze"]
        rowm = [name]
        for frac in (0.01, 0.001):
            th = reach(hy, frac, off)
            tl = reach(lm, frac)
            metrics += [
                timing(f"{s}.hybrid_polish.seconds_to_{frac:g}", th),
                timing(f"{s}.lm.seconds_to_{frac:g}", tl),
            ]
            rowm += [f"{th:.2f}", f"{tl:.2f}"]
        if gtsam_available():
            gt = gtsam_time_to(g, rot, trans, opt, (0.01, 0.001))
            rowm += [f"{gt[0.01]:.2f}", f"{gt[0.001]:.2f}"]
        else:
            rowm += ["-", "-"]
        rowm.append(f"{wall:.2f}")
        rows.append(rowm)
    return metrics, [
        markdown_table(
            "Wall time (s) from the tree initialization to within 1% / 0.1% of the optimum",
            [
                "file",
                "hybrid+polish 1%",
                "our LM 1%",
                "hybrid+polish 0.1%",
                "our LM 0.1%",
                "GTSAM LM 1%",
                "GTSAM LM 0.1%",
                "hybrid+polish total",
            ],
            rows,
        )
    ]


WORKLOADS: dict[str, Callable[[Context], Result]] = {
    "exact": exact,
    "hybrid_manhattan": hybrid_manhattan,
    "hybrid_quality": hybrid_quality,
    "robustness": robustness,
    "step_scaling": step_scaling,
    "time_to_optimum": time_to_optimum,
}


# ------------------------------------------------------------------ GPS and the city
def _city_figure(c: Any, res: Any, path: pathlib.Path) -> None:
    """Before (tree initialization) / after (hybrid) map with residuals, GPS ones included."""
    try:
        from hybridpgo.plot import graph_figure, save_figure
    except ImportError:  # pragma: no cover - matplotlib missing
        return
    g = c.graph
    before = start(g, "tree")
    fig = graph_figure(g, [before, (res.rotations, res.translations)],
                       titles=[f"{c.name}: tree initialization", f"{c.name}: hybrid, 10 sweeps"])
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)


def city(ctx: Context) -> Result:
    from hybridpgo.generate import generate_city
    from hybridpgo.metrics import evaluate

    metrics: list[Metric] = []
    rows = []
    presets = ("valencia",) if ctx.quick else ("valencia", "paris1", "paris2")
    for preset in presets:
        for gps_every in (None, 100):
            c = generate_city(preset, seed=0, gps_every=gps_every)
            g = c.graph
            tag = f"{preset}{'_gps' if gps_every else ''}"
            align = not gps_every
            runs = {}
            t0 = time.perf_counter()
            runs["hybrid"] = _hybrid(g, sweeps=10)
            runs["hybrid+polish"] = _hybrid(g, sweeps=10, polish=True, polish_iterations=100)
            runs["exact (LM from dead reckoning)"] = solve_exact(
                g, None, None, GaussNewtonConfig(max_iterations=100)
            )
            ctx.cache[f"city:{tag}"] = (c, runs)
            if gps_every and ctx.figures is not None:
                _city_figure(c, runs["hybrid"], ctx.figures / f"city_{tag}.png")
            for label, res in runs.items():
                ev = evaluate(
                    res.rotations,
                    res.translations,
                    c.truth_rotations,
                    c.truth_translations,
                    align=align,
                )
                secs = sum(v for k, v in res.timings.items() if k in ("analyze", "solve", "polish"))
                key = f"{tag}.{label.split()[0]}"
                metrics += [
                    quality(f"{key}.position_rmse_m", ev["position_rmse_m"], "m"),
                    # the key predates the metrics' rename: its value is the full rotation angle
                    quality(f"{key}.heading_mean_deg", ev["rotation_error_mean_deg"], "deg"),
                    quality(f"{key}.energy_per_constraint", res.final_energy / g.num_constraints),
                    timing(f"{key}.seconds", secs),
                ]
                max_ms = max(res.stats.get("us_per_constraint_max_steady", float("nan")) / 1e3,
                             res.stats.get("ms_per_gps_batch_max_steady", 0.0))
                if label == "hybrid":
                    metrics.append(timing(f"{key}.max_update_ms", max_ms, "ms"))
                rows.append(
                    [
                        tag,
                        g.num_nodes,
                        g.num_edges,
                        g.num_gps,
                        label,
                        ev["position_rmse_m"],
                        ev["rotation_error_mean_deg"],
                        ev["rotation_error_max_deg"],
                        res.final_energy / g.num_constraints,
                        f"{secs:.2f}",
                        f"{max_ms:.2f}" if label == "hybrid" else "-",
                    ]
                )
            print(f"  {tag}: {time.perf_counter() - t0:.1f} s", flush=True)
    return metrics, [
        markdown_table(
            "Generated cities (seed 0): accuracy against ground truth "
            "(no GPS: after rigid alignment; GPS: in the earth frame, no alignment)",
            [
                "graph",
                "poses",
                "edges",
                "GPS",
                "method",
                "position RMSE m",
                "rotation error mean deg",
                "rotation error max deg",
                "E / constraint",
                "seconds",
                "steady max update ms",
            ],
            rows,
        )
    ]


WORKLOADS["city"] = city


def _toro(ctx: Context) -> Result:
    from .toro import run

    return run(ctx)


WORKLOADS["toro"] = _toro


# ------------------------------------------------------------------ fuzzing
from .fuzz import run as _fuzz  # noqa: E402
from .fuzz import run_grammar as _fuzz_cli  # noqa: E402

WORKLOADS["fuzz"] = _fuzz
WORKLOADS["fuzz_cli"] = _fuzz_cli

from .linear import run as _linear_run  # noqa: E402

WORKLOADS["linear"] = _linear_run

from .paper import run as _paper_run  # noqa: E402
from .paper import run_table_one as _paper_table1_run  # noqa: E402

WORKLOADS["paper"] = _paper_run
WORKLOADS["paper_table1"] = _paper_table1_run


def _outliers(ctx: Context) -> Result:
    from .outliers import run

    return run(ctx)


def _outliers_clean(ctx: Context) -> Result:
    from .outliers import run_clean

    return run_clean(ctx)


def _outliers_online(ctx: Context) -> Result:
    from .outliers import run_online

    return run_online(ctx)


def _outlier_kernels(ctx: Context) -> Result:
    from .outlier_kernels import run

    return run(ctx)


WORKLOADS["outliers"] = _outliers
WORKLOADS["outliers-clean"] = _outliers_clean
WORKLOADS["outliers-online"] = _outliers_online
WORKLOADS["outlier-kernels"] = _outlier_kernels


def _online(ctx: Context) -> Result:
    from .online import run

    return run(ctx)


def _scale(ctx: Context) -> Result:
    from .scale import run

    return run(ctx)

def _auto(ctx: Context) -> Result:
    from .auto import run

    return run(ctx)


WORKLOADS["online"] = _online


from .interp import run as _interp_run  # noqa: E402  (interpolated update times)

WORKLOADS["interp"] = _interp_run

WORKLOADS["scale"] = _scale

WORKLOADS["auto"] = _auto  # the default pipeline and local minima

from .converge import run as _converge_run  # noqa: E402  (levers)

WORKLOADS["converge"] = _converge_run

from .first_run import run as _first_run  # noqa: E402  (cold first run)

WORKLOADS["first_run"] = _first_run


def _linear_backends(ctx: Context) -> Result:
    from .linear_backends import run

    return run(ctx)


WORKLOADS["linear_backends"] = _linear_backends


def _certificate(ctx: Context) -> Result:
    from .certificate import run

    return run(ctx)


WORKLOADS["certificate"] = _certificate

from .covariance import run as _covariance_run  # noqa: E402

WORKLOADS["covariance"] = _covariance_run

from .worker import run as _worker_run  # noqa: E402  (the worker's incremental requests)

WORKLOADS["worker"] = _worker_run
