"""Robust kernels against false loop closures.

M3500 (``M3500.g2o`` and the bundled ``M3500_isam.txt``, ground truth
``M3500_groundtruth_isam.txt``) and a generated city, each with 0, 10, 100 and 1000 random false
loop closures added here: random pose pairs (at least ``MIN_GAP`` poses apart) carrying the
measurement *and* information of a randomly chosen real loop closure of the same graph (a
plausible relative pose with the typical loop-closure information).  The sets are nested (the
first 10 of the 100, ...).  Every solver starts from the odometry chain (the poses a front end
has; the BFS tree would route the start through false loops).

Measured per run: position RMSE against the ground truth (rigid alignment, hybridpgo.metrics)
and its ratio to the outlier-free optimum's; precision and recall of "edge ends with w < 0.1"
as a false-loop detector; robust and plain energy; time.  Solvers: exact LM without a kernel and
with each kernel, hybrid sweeps + LM polish with each kernel, GTSAM LM with the same robust noise
model (factors built from our information, so ``E_rho = 2 x graph.error``), and the levers:
a graduated non-convexity schedule over Geman-McClure (GNC-GM) and Huber then Geman-McClure.

Run: ``PYTHONPATH=src python -m benchmarks --only outliers --run <name>``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hybridpgo.energy import energy, robust_energy, robust_weights
from hybridpgo.generate import generate_city
from hybridpgo.graph import PoseGraph
from hybridpgo.initialization import initial_locals
from hybridpgo.io import read_graph
from hybridpgo.metrics import evaluate
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.hybrid import HybridConfig, solve_hybrid
from hybridpgo.tree import build_tree, global_poses

from .metrics import Metric, info, markdown_table, quality, timing
from .workloads import Context, Result, start

#: False loop closures added to each graph (nested sets).
COUNTS = (0, 10, 100, 1000)
#: A false loop closure joins poses at least this many poses apart.
MIN_GAP = 50
#: Kernel scales delta (whitened units): 3 (Huber quadratic up to chi2 = 9; every inlier of
#: these graphs has chi2 <= 16 at the optimum) and, for Geman-McClure, 10.
DELTA = 3.0
WIDE = 10.0
#: LM iteration limit of every run (ours and GTSAM's).
ITERATIONS = 100
#: An edge "ends with a low weight" (flagged as an outlier) when w < this.
LOW_WEIGHT = 0.1
#: GNC over Geman-McClure: the control parameter mu starts at max chi2 / delta^2 (capped) and is
#: divided by this factor per stage until 1 (Yang et al., RA-L 2020).
GNC_FACTOR = 1.4
GNC_MU_MAX = 1e4
KERNELS = ("huber", "cauchy", "geman_mcclure")
SHORT = {"none": "LS", "huber": "Huber", "cauchy": "Cauchy", "geman_mcclure": "GM"}


# ----------------------------------------------------------------------------- graphs
def odometry_start(graph: PoseGraph) -> tuple[np.ndarray, np.ndarray]:
    """Global poses from chaining the odometry edges (i, i+1) from pose 0."""
    a, b = graph.edge_nodes[:, 0], graph.edge_nodes[:, 1]
    odo = np.flatnonzero(b == a + 1)
    _, first = np.unique(a[odo], return_index=True)
    odo = odo[first]
    if odo.size != graph.num_nodes - 1:
        raise ValueError("the graph has no complete odometry chain")
    chain = dataclasses.replace(
        graph, edge_nodes=graph.edge_nodes[odo], edge_rotations=graph.edge_rotations[odo],
        edge_translations=graph.edge_translations[odo],
        edge_information=graph.edge_information[odo])
    tree = build_tree(chain)
    return global_poses(tree, *initial_locals(chain, tree, "tree"))


def loop_edges(graph: PoseGraph) -> np.ndarray:
    """Indices of the loop closures (edges other than (i, i+1))."""
    return np.flatnonzero(graph.edge_nodes[:, 1] != graph.edge_nodes[:, 0] + 1)


def add_false_loops(graph: PoseGraph, k: int, seed: int) -> PoseGraph:
    """``graph`` plus the first k of a fixed random draw of false loop closures (appended last).

    Each joins a random pair at least ``MIN_GAP`` apart that no edge joins yet, with the
    measurement and information of a random real loop closure of the graph.
    """
    if k == 0:
        return graph
    rng = np.random.default_rng(seed)
    n = graph.num_nodes
    have = {(int(a), int(b)) for a, b in graph.edge_nodes}
    pairs: list[tuple[int, int]] = []
    while len(pairs) < max(COUNTS):
        a, b = (int(v) for v in rng.integers(0, n, 2))
        a, b = min(a, b), max(a, b)
        if b - a >= MIN_GAP and (a, b) not in have:
            have.add((a, b))
            pairs.append((a, b))
    donors = rng.choice(loop_edges(graph), size=max(COUNTS))
    en = np.array(pairs[:k], np.int32)
    d = donors[:k]
    return dataclasses.replace(
        graph, edge_nodes=np.concatenate([graph.edge_nodes, en]),
        edge_rotations=np.concatenate([graph.edge_rotations, graph.edge_rotations[d]]),
        edge_translations=np.concatenate([graph.edge_translations, graph.edge_translations[d]]),
        edge_information=np.concatenate([graph.edge_information, graph.edge_information[d]]))


@dataclasses.dataclass
class Case:
    name: str
    graph: PoseGraph
    truth: tuple[np.ndarray, np.ndarray]
    seed: int


def _cases(ctx: Context) -> list[Case]:
    gt_graph = read_graph(ctx.data_dir / "M3500_groundtruth_isam.txt")
    truth = start(gt_graph, "tree")  # noise-free relative measurements: any tree is exact
    out = [Case("M3500.g2o", ctx.graph("M3500.g2o"), truth, 1),
           Case("M3500_isam", ctx.graph("M3500_isam.txt"), truth, 2)]
    if not ctx.quick:
        city = generate_city(seed=0, num_poses=4000)
        out.append(Case("city4000", city.graph, (city.truth_rotations, city.truth_translations),
                        3))
    return out


# ----------------------------------------------------------------------------- solvers
Solve = Callable[[PoseGraph, tuple[np.ndarray, np.ndarray]], tuple[np.ndarray, np.ndarray, str]]


def _lm(robust: str, scale: float = DELTA, iterations: int = ITERATIONS) -> Solve:
    def run(g: PoseGraph, x0: tuple[np.ndarray, np.ndarray]) -> tuple[Any, Any, str]:
        res = solve_exact(g, *x0, GaussNewtonConfig(max_iterations=iterations, robust=robust,
                                                    robust_scale=scale))
        return res.rotations, res.translations, f"{res.iterations} it, {res.status.value}"
    return run


def _hybrid(robust: str, scale: float, sweeps: int = 10) -> Solve:
    def run(g: PoseGraph, x0: tuple[np.ndarray, np.ndarray]) -> tuple[Any, Any, str]:
        cfg = HybridConfig(sweeps=sweeps, init="file", polish=True,
                           polish_iterations=ITERATIONS, robust=robust,  # type: ignore[arg-type]
                           robust_scale=scale)
        res = solve_hybrid(g.with_poses(*x0), cfg)
        return (res.rotations, res.translations,
                f"{sweeps} sw + {res.stats['polish_iterations']} it")
    return run


def _huber_then_gm(g: PoseGraph, x0: tuple[np.ndarray, np.ndarray]) -> tuple[Any, Any, str]:
    a = solve_exact(g, *x0, GaussNewtonConfig(max_iterations=ITERATIONS, robust="huber",
                                              robust_scale=DELTA))
    b = solve_exact(g, a.rotations, a.translations,
                    GaussNewtonConfig(max_iterations=ITERATIONS, robust="geman_mcclure",
                                      robust_scale=DELTA))
    return b.rotations, b.translations, f"{a.iterations} + {b.iterations} it"


def _gnc_gm(g: PoseGraph, x0: tuple[np.ndarray, np.ndarray]) -> tuple[Any, Any, str]:
    """GNC: GM with scale sqrt(mu) delta, mu from max chi2/delta^2 down to 1 by GNC_FACTOR."""
    rot, trans = x0
    s = robust_weights(g, rot, trans, "none")[0]
    mu = float(min(max(2.0 * s.max() / DELTA**2, 1.0), GNC_MU_MAX))
    stages = iters = 0
    while True:
        last = mu <= 1.0
        res = solve_exact(g, rot, trans, GaussNewtonConfig(
            max_iterations=ITERATIONS if last else 10, robust="geman_mcclure",
            robust_scale=DELTA * np.sqrt(max(mu, 1.0)), energy_tolerance=1e-10 if last else 1e-4))
        rot, trans = res.rotations, res.translations
        stages += 1
        iters += res.iterations
        if last:
            return rot, trans, f"{stages} stages, {iters} it"
        mu /= GNC_FACTOR


def _gtsam_robust_lm(robust: str, scale: float) -> Solve:
    def run(g: PoseGraph, x0: tuple[np.ndarray, np.ndarray]) -> tuple[Any, Any, str]:
        import gtsam

        est = {"huber": gtsam.noiseModel.mEstimator.Huber,
               "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
               "geman_mcclure": gtsam.noiseModel.mEstimator.GemanMcClure}[robust](scale)
        rot, trans = x0
        fg = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        planar = g.is_2d
        idx2 = np.array([0, 1, 5])
        perm = np.r_[3:6, 0:3]
        for i in range(g.num_nodes):
            if planar:
                values.insert(i, gtsam.Pose2(trans[i, 0], trans[i, 1],
                                             float(np.arctan2(rot[i, 1, 0], rot[i, 0, 0]))))
            else:
                values.insert(i, gtsam.Pose3(gtsam.Rot3(rot[i]), trans[i]))
        for c, (a, b) in enumerate(g.edge_nodes):
            inf = g.edge_information[c]
            rz, tz = g.edge_rotations[c], g.edge_translations[c]
            if planar:
                model = gtsam.noiseModel.Robust.Create(
                    est, gtsam.noiseModel.Gaussian.Information(inf[np.ix_(idx2, idx2)]))
                z = gtsam.Pose2(tz[0], tz[1], float(np.arctan2(rz[1, 0], rz[0, 0])))
                fg.add(gtsam.BetweenFactorPose2(int(a), int(b), z, model))
            else:
                model = gtsam.noiseModel.Robust.Create(
                    est, gtsam.noiseModel.Gaussian.Information(inf[np.ix_(perm, perm)]))
                fg.add(gtsam.BetweenFactorPose3(int(a), int(b),
                                                gtsam.Pose3(gtsam.Rot3(rz), tz), model))
        if planar:
            fg.add(gtsam.PriorFactorPose2(0, values.atPose2(0),
                                          gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
        else:
            fg.add(gtsam.PriorFactorPose3(0, values.atPose3(0),
                                          gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(ITERATIONS)
        params.setRelativeErrorTol(1e-10)
        params.setAbsoluteErrorTol(0.0)
        opt = gtsam.LevenbergMarquardtOptimizer(fg, values, params)
        out = opt.optimize()
        r = np.empty_like(rot)
        t = np.empty_like(trans)
        for i in range(g.num_nodes):
            if planar:
                p = out.atPose2(i)
                c_, s_ = np.cos(p.theta()), np.sin(p.theta())
                r[i] = [[c_, -s_, 0], [s_, c_, 0], [0, 0, 1]]
                t[i] = [p.x(), p.y(), 0.0]
            else:
                p3 = out.atPose3(i)
                r[i] = p3.rotation().matrix()
                t[i] = p3.translation()
        return r, t, f"{int(opt.iterations())} it"
    return run


@dataclasses.dataclass
class Run:
    label: str
    kernel: str
    scale: float
    solve: Solve
    counts: tuple[int, ...] = COUNTS


def _solvers(quick: bool) -> list[Run]:
    """The runs: (label, kernel and scale for the weights, solver, false-loop counts)."""
    from .gtsam_ref import gtsam_available

    out = [Run("LM", "none", DELTA, _lm("none"))]
    out += [Run(f"LM {SHORT[k]} {DELTA:g}", k, DELTA, _lm(k)) for k in KERNELS]
    out += [Run(f"LM GM {WIDE:g}", "geman_mcclure", WIDE, _lm("geman_mcclure", WIDE)),
            Run(f"hybrid+LM GM {WIDE:g}", "geman_mcclure", WIDE, _hybrid("geman_mcclure", WIDE)),
            Run(f"hybrid+LM GM {DELTA:g}", "geman_mcclure", DELTA,
                _hybrid("geman_mcclure", DELTA), (100,)),
            Run(f"LM GNC-GM {DELTA:g}", "geman_mcclure", DELTA, _gnc_gm, (100,)),
            Run(f"LM Huber->GM {DELTA:g}", "geman_mcclure", DELTA, _huber_then_gm, (100,))]
    if gtsam_available():
        out += [Run(f"GTSAM LM GM {WIDE:g}", "geman_mcclure", WIDE,
                    _gtsam_robust_lm("geman_mcclure", WIDE)),
                Run(f"GTSAM LM Cauchy {DELTA:g}", "cauchy", DELTA,
                    _gtsam_robust_lm("cauchy", DELTA))]
    if quick:
        out = [r for r in out if r.label in ("LM", f"LM GM {WIDE:g}", f"hybrid+LM GM {WIDE:g}")]
    return out


# ----------------------------------------------------------------------------- the workload
def _row(case: Case, k: int, g: PoseGraph, label: str, kernel: str, scale: float,
         res: tuple[Any, Any, str], seconds: float, ref_err: float
         ) -> tuple[list[Any], dict[str, float]]:
    rot, trans, note = res
    ev = evaluate(rot, trans, *case.truth, align=True)
    err = ev["position_rmse_m"]
    e_plain = energy(g, rot, trans)
    e_rho = robust_energy(g, rot, trans, kernel, scale)[0] if kernel != "none" else e_plain
    if kernel != "none" and k:
        _, w = robust_weights(g, rot, trans, kernel, scale)
        flagged = w < LOW_WEIGHT
        m0 = g.num_edges - k
        tp = int(flagged[m0:].sum())
        prec = tp / max(int(flagged.sum()), 1)
        rec = tp / k
        pr = f"{prec:.3f} / {rec:.3f} ({int(flagged.sum())})"
    else:
        prec = rec = float("nan")
        pr = "-"
    vals = {"err": err, "ratio": err / ref_err, "seconds": seconds, "precision": prec,
            "recall": rec}
    row = [case.name, k, label, f"{err:.4g}", f"{err / ref_err:.3f}",
           f"{ev['heading_error_max_deg']:.3g}", pr, f"{e_rho:.6g}",
           f"{e_plain:.6g}", f"{seconds:.2f}", note]
    return row, vals


def run(ctx: Context) -> Result:
    metrics: list[Metric] = []
    rows: list[list[Any]] = []
    counts = (0, 100) if ctx.quick else COUNTS
    solvers = _solvers(ctx.quick)
    for case in _cases(ctx):
        # the outlier-free optimum: LM from the chordal start (the global one on these graphs)
        clean = case.graph
        ref = solve_exact(clean, *start(clean, "chordal"), GaussNewtonConfig(max_iterations=300))
        ref_err = evaluate(ref.rotations, ref.translations, *case.truth,
                           align=True)["position_rmse_m"]
        ref_ev = evaluate(ref.rotations, ref.translations, *case.truth, align=True)
        rows.append([case.name, 0, "outlier-free optimum (LM, chordal start)", f"{ref_err:.4g}",
                     "1", f"{ref_ev['heading_error_max_deg']:.3g}", "-", "-",
                     f"{ref.final_energy:.6g}", "-",
                     f"{clean.num_nodes} poses, {loop_edges(clean).size} loop closures"])
        metrics.append(info(f"outliers.{case.name}.optimum_position_rmse_m", ref_err, "m"))
        for k in counts:
            g = add_false_loops(clean, k, case.seed)
            x0 = odometry_start(g)
            for r in solvers:
                if k not in r.counts:
                    continue
                label, kernel = r.label, r.kernel
                t0 = time.perf_counter()
                try:
                    res = r.solve(g, x0)
                except Exception as exc:  # a failed run is a result too
                    rows.append([case.name, k, label, "failed", "-", "-", "-", "-", "-", "-",
                                 f"{type(exc).__name__}: {exc}"[:80]])
                    continue
                seconds = time.perf_counter() - t0
                row, vals = _row(case, k, g, label, kernel, r.scale, res, seconds, ref_err)
                rows.append(row)
                key = (f"outliers.{case.name}.k{k}."
                       + label.replace(" ", "_").replace(">", "").replace("+", "_"))
                metrics += [quality(key + ".position_rmse_ratio", vals["ratio"]),
                            timing(key + ".seconds", seconds)]
                if k and kernel != "none":
                    metrics += [info(key + ".precision", vals["precision"]),
                                info(key + ".recall", vals["recall"])]
                print(" | ".join(str(v) for v in row), flush=True)
    table = markdown_table(
        f"False loop closures: position RMSE vs ground truth (aligned) and its ratio to the "
        f"outlier-free optimum's; precision / recall (number flagged) of 'w < {LOW_WEIGHT}' as a "
        "false-loop detector; the number after the kernel is its scale delta; LM runs stop "
        f"after {ITERATIONS} iterations; every solver starts from the odometry chain.  Target: "
        "M3500 with 100 outliers within 10% (ratio <= 1.1).",
        ["graph", "false loops", "solver", "position RMSE (m)", "ratio",
         "max heading error (deg)", "precision / recall",
         "E_rho", "E plain", "time (s)", "note"], rows)
    return metrics, [table]
