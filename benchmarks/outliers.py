"""False loop closures and false GPS fixes: the default (``robust="auto"``) beside GTSAM's GNC.

Graphs (generated, with ground truth): a Manhattan grid like M3500 (``generate_grid("m3500")``,
2D, 3 500 poses), a 3D grid (``"grid3d"``, 3 500 poses) and a city with a GPS reading every
10 poses (``generate_city(num_poses=4000, gps_every=10)``).  Each gets false loop closures in
Sünderhauf and Protzel's four patterns (random, local, random-grouped, local-grouped; groups
of 10; :func:`hybridpgo.generate.add_pattern_outliers`) at 10, 100 and 1 000; the city also
false GPS fixes at 1% and 5% of its readings (jumps of 20-60 m,
:func:`hybridpgo.generate.add_gps_outliers`); every graph also clean, as the control.

Per row:

* **ours**: ``optimize(graph)``, the default, no option (the pipeline, its outlier test and,
  when the test fails, the re-solve); its rejected set is ``stats["outliers"]``;
* **GTSAM GNC**: ``GncLMOptimizer`` with its defaults (truncated least squares, inlier
  threshold at the 0.99 χ² quantile of each factor, μ step 1.4, at most 100 stages), the
  odometry (edges between consecutive poses) and the gauge prior given as known inliers,
  from the file's vertices (dead reckoning), on factors built from our information
  (:mod:`hybridpgo.gtsam_bridge`); a factor is rejected when its final weight is below 0.5.

Both are scored by the position RMSE against the ground truth (rigid alignment without GPS,
:func:`hybridpgo.metrics.evaluate`) over the RMSE of the outlier-free optimum (least squares on
the clean graph from the truth); precision and recall of the rejected set; wall time (the
kernels compiled beforehand).  An outlier is *indistinguishable* when at the outlier-free
optimum its whitened error is within the test's threshold
(:data:`hybridpgo.solvers.robust.THRESHOLD_SIGMAS`, in sigmas of the clean graph's scale):
the rest of the graph agrees with it; recall is also given over the distinguishable ones.

Run: ``PYTHONPATH=src python -m benchmarks --only outliers --run <name>``.

**Online** (``--only outliers-online``, :func:`run_online`): rows of the same graphs streamed
frame by frame through ``OnlineSolver()`` (the default: ``robust="auto"``, the background
worker on), 5 ms per frame back to back, the ``add_*`` calls included; the largest frame CPU
time; the RMSE after the last frame (what the robot has while it drives on) and after
``join_refine()`` (the end of the stream); precision and recall of the rejected set
(``OnlineSolver.outliers()``); and ``robust="none"`` on the same stream as the contrast.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridpgo.energy import constraint_energies
from hybridpgo.generate import (
    OUTLIER_PATTERNS,
    add_gps_outliers,
    add_pattern_outliers,
    generate_city,
    generate_grid,
)
from hybridpgo.graph import PoseGraph
from hybridpgo.metrics import evaluate
from hybridpgo.solvers import optimize
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.robust import THRESHOLD_SIGMAS, check_consistency

from .context import Context, Result
from .gtsam_ref import gtsam_available
from .metrics import Metric, info, markdown_table, quality, timing

#: False loop closures per pattern.
COUNTS = (10, 100, 1000)
#: False GPS fixes, as fractions of the readings.
GPS_FRACTIONS = (0.01, 0.05)
#: Seed of every outlier set.
SEED = 5
#: A GNC factor is rejected when its final weight is below this.
GNC_REJECTED = 0.5
#: Targets: RMSE within 10% of the outlier-free optimum's; precision and recall.
RATIO_TARGET = 1.10
PRECISION_TARGET = 0.99
RECALL_TARGET = 0.95


@dataclass
class Base:
    name: str
    make: Callable[[], Any]


BASES = [
    Base("grid 2D (M3500-like)", lambda: generate_grid("m3500", seed=0)),
    Base("grid 3D", lambda: generate_grid("grid3d", seed=0)),
    Base("city + GPS", lambda: generate_city(None, seed=0, num_poses=4000, gps_every=10)),
]


@dataclass
class Row:
    label: str
    graph: PoseGraph
    false_edges: np.ndarray
    false_gps: np.ndarray


def _rows(made: Any, quick: bool) -> list[Row]:
    g0 = made.graph
    rows = [Row("clean", g0, np.zeros(g0.num_edges, bool), np.zeros(g0.num_gps, bool))]
    for pattern in OUTLIER_PATTERNS:
        for k in COUNTS[:1] if quick else COUNTS:
            g, out = add_pattern_outliers(g0, made.truth_translations, k, pattern, seed=SEED)
            rows.append(Row(f"{pattern} {k}", g, out.mask(g.num_edges),
                            np.zeros(g.num_gps, bool)))
    for frac in GPS_FRACTIONS if g0.num_gps else ():
        k = max(1, round(frac * g0.num_gps))
        g, gout = add_gps_outliers(g0, k, seed=SEED)
        rows.append(Row(f"GPS {frac:.0%} ({k})", g, np.zeros(g.num_edges, bool),
                        gout.mask(g.num_gps)))
    return rows


def _selected(base: str, label: str) -> bool:
    """Whether a row runs: every row, or those named in ``$OUTLIERS_ROWS`` (``;``-separated
    ``GRAPH:LABEL`` entries, e.g. ``grid 3D:random 100;city + GPS:GPS 5%``; a row's label
    without its parenthesized count), for a run restricted to fit the machine's time."""
    spec = os.environ.get("OUTLIERS_ROWS", "").strip()
    if not spec:
        return True
    for entry in spec.split(";"):
        graph, _, row = entry.partition(":")
        if graph.strip() == base and label.split(" (")[0] == row.strip():
            return True
    return False


def _rmse(made: Any, rot: np.ndarray, trans: np.ndarray, gps: bool) -> float:
    return float(evaluate(rot, trans, made.truth_rotations, made.truth_translations,
                          align=not gps)["position_rmse_m"])


def _scores(rej: np.ndarray, rej_gps: np.ndarray, row: Row,
            distinguishable: np.ndarray, distinguishable_gps: np.ndarray) -> dict[str, float]:
    tp = int((rej & row.false_edges).sum() + (rej_gps & row.false_gps).sum())
    n_rej = int(rej.sum() + rej_gps.sum())
    n_false = int(row.false_edges.sum() + row.false_gps.sum())
    n_dist = int(distinguishable.sum() + distinguishable_gps.sum())
    tp_dist = int((rej & distinguishable).sum() + (rej_gps & distinguishable_gps).sum())
    return {"rejected": n_rej, "tp": tp,
            "precision": tp / n_rej if n_rej else (1.0 if n_false == 0 else math.nan),
            "recall": tp / n_false if n_false else math.nan,
            "recall_distinguishable": tp_dist / n_dist if n_dist else math.nan,
            "indistinguishable": n_false - n_dist}


def _ours(made: Any, row: Row, d_edges: np.ndarray, d_gps: np.ndarray) -> dict[str, Any]:
    g = row.graph
    t0 = time.perf_counter()
    res = optimize(g)
    seconds = time.perf_counter() - t0
    o = res.stats["outliers"]
    rej = np.zeros(g.num_edges, bool)
    rej_gps = np.zeros(g.num_gps, bool)
    for r in o["rejected_constraints"]:
        (rej if r["kind"] == "edge" else rej_gps)[r["index"]] = True
    trigger = ("-" if not o["inconsistent"] else
               "scale" if o["misfit"] and not (o["flagged"] or o["flagged_gps"]) else
               f"{o['flagged'] + o['flagged_gps']} flagged" + (" + scale" if o["misfit"] else ""))
    return {"rmse": _rmse(made, res.rotations, res.translations, g.num_gps > 0),
            "seconds": seconds, "outlier_seconds": float(res.timings.get("outliers", 0.0)),
            "trigger": trigger, "scale": o["scale"],
            **_scores(rej, rej_gps, row, d_edges, d_gps)}


def _gnc(made: Any, row: Row, d_edges: np.ndarray, d_gps: np.ndarray) -> dict[str, Any]:
    import gtsam

    from hybridpgo.gtsam_bridge import from_gtsam, gauge_prior, to_gtsam

    g = row.graph
    factors, values = to_gtsam(g)
    full = gtsam.NonlinearFactorGraph(factors)
    if not g.num_gps:
        full.push_back(gauge_prior(g, values))
    ids = g.node_ids[g.edge_nodes]
    odometry = np.flatnonzero(np.abs(ids[:, 1] - ids[:, 0]) == 1)
    params = gtsam.GncLMParams()
    params.setKnownInliers([int(k) for k in odometry]
                           + list(range(g.num_edges + g.num_gps, full.size())))
    t0 = time.perf_counter()
    opt = gtsam.GncLMOptimizer(full, values, params)
    result = opt.optimize()
    seconds = time.perf_counter() - t0
    w = np.asarray(opt.getWeights())
    rot, trans = from_gtsam(g, result)
    rej = w[:g.num_edges] < GNC_REJECTED
    rej_gps = w[g.num_edges:g.num_edges + g.num_gps] < GNC_REJECTED
    return {"rmse": _rmse(made, rot, trans, g.num_gps > 0), "seconds": seconds,
            **_scores(rej, rej_gps, row, d_edges, d_gps)}


def _distinguishable(row: Row, ref: Any, scale: float, gps_scale: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Outliers whose whitened error at the outlier-free optimum exceeds the threshold."""
    s, s_gps = constraint_energies(row.graph, ref.rotations, ref.translations)
    limit = THRESHOLD_SIGMAS**2
    nu = max(1.0, scale) if math.isfinite(scale) else 1.0
    nu_gps = max(1.0, gps_scale) if math.isfinite(gps_scale) else 1.0
    return row.false_edges & (s > limit * nu), row.false_gps & (s_gps > limit * nu_gps)


def _warm_up() -> None:
    """Compile every kernel the rows use (2D and 3D, with and without GPS, robust re-solve)."""
    small = [generate_grid("m3500", seed=1, num_poses=300),
             generate_grid("grid3d", seed=1, num_poses=300),
             generate_city(None, seed=1, num_poses=400, gps_every=10)]
    for made in small:
        g, _ = add_pattern_outliers(made.graph, made.truth_translations, 5, "random", seed=1)
        optimize(g)


def _fmt(x: float, digits: int = 3) -> str:
    return "—" if not math.isfinite(x) else f"{x:.{digits}f}"


def _met(ok: bool) -> str:
    return "met" if ok else "MISSED"


def run(ctx: Context, *, log: Callable[[str], None] | None = None) -> Result:
    say = log or (lambda text: print(text, file=sys.stderr, flush=True))
    with_gtsam = gtsam_available()
    _warm_up()
    metrics: list[Metric] = []
    table: list[list[Any]] = []
    for base in BASES[:1] if ctx.quick else BASES:
        made = base.make()
        g0 = made.graph
        ref = solve_exact(g0, made.truth_rotations, made.truth_translations,
                          GaussNewtonConfig(max_iterations=300, energy_tolerance=1e-12))
        rmse_ref = _rmse(made, ref.rotations, ref.translations, g0.num_gps > 0)
        clean = check_consistency(g0, ref.rotations, ref.translations)
        say(f"[outliers] {base.name}: {g0.num_nodes} poses, {g0.num_edges} edges, "
            f"{g0.num_gps} GPS; outlier-free optimum RMSE {rmse_ref:.4g} m")
        for row in _rows(made, ctx.quick):
            if not _selected(base.name, row.label):
                continue
            d_edges, d_gps = _distinguishable(row, ref, clean.scale, clean.gps_scale)
            ours = _ours(made, row, d_edges, d_gps)
            gnc = _gnc(made, row, d_edges, d_gps) if with_gtsam else None
            ratio = ours["rmse"] / rmse_ref
            n_false = int(row.false_edges.sum() + row.false_gps.sum())
            ok_ratio = ratio <= RATIO_TARGET
            ok_p = not n_false or ours["precision"] >= PRECISION_TARGET
            ok_r = not n_false or not math.isfinite(ours["recall_distinguishable"]) or (
                ours["recall_distinguishable"] >= RECALL_TARGET)
            ok_clean = n_false or ours["rejected"] == 0
            g_ratio = gnc["rmse"] / rmse_ref if gnc else math.nan
            line = [base.name, row.label,
                    f"{ours['rmse']:.4g}", _fmt(ratio),
                    f"{_fmt(ours['precision'])} / {_fmt(ours['recall'])} ({ours['rejected']})",
                    f"{_fmt(ours['recall_distinguishable'])} ({ours['indistinguishable']})",
                    ours["trigger"], f"{ours['seconds']:.1f} ({ours['outlier_seconds']:.1f})",
                    (f"{gnc['rmse']:.4g}" if gnc else "—"), _fmt(g_ratio),
                    (f"{_fmt(gnc['precision'])} / {_fmt(gnc['recall'])} ({gnc['rejected']})"
                     if gnc else "—"),
                    (f"{gnc['seconds']:.1f}" if gnc else "—"),
                    (f"{ours['seconds'] / gnc['seconds']:.2f}" if gnc else "—"),
                    _met(bool(ok_ratio and ok_p and ok_r and ok_clean)
                         and (not gnc or ours["rmse"] <= gnc["rmse"] * (1 + 1e-3))),
                    f"{os.getloadavg()[0]:.1f}"]
            table.append(line)
            say("[outliers] " + " | ".join(str(v) for v in line))
            key = ("outliers." + base.name.split()[0] + "_" + base.name.split()[1] + "."
                   + row.label.split(" (")[0].replace(" ", "_").replace("%", "pct"))
            metrics += [quality(key + ".rmse_ratio", ratio), timing(key + ".seconds",
                                                                    ours["seconds"]),
                        info(key + ".rejected", ours["rejected"])]
            if n_false:
                metrics += [info(key + ".precision", ours["precision"]),
                            info(key + ".recall", ours["recall"])]
            if gnc:
                metrics += [info(key + ".gnc_rmse_ratio", g_ratio),
                            info(key + ".gnc_seconds", gnc["seconds"], "s")]
    header = ["graph", "outliers", "ours RMSE (m)", "ours / optimum",
              "ours precision / recall (rejected)", "recall of distinguishable "
              "(indistinguishable)", "test fired by", "ours s (re-solve s)", "GNC RMSE (m)",
              "GNC / optimum", "GNC precision / recall (rejected)", "GNC s", "time ours / GNC",
              "targets", "load"]
    title = ("False loop closures and false GPS fixes: the default (optimize(graph), no "
             "option) beside GTSAM's GncOptimizer (defaults, odometry known inliers).  RMSE: "
             "aligned position error against the ground truth; ours / optimum: over the "
             "outlier-free optimum's.  Targets per row: ratio <= 1.10, precision >= 0.99, "
             "recall of the distinguishable >= 0.95, clean rows reject nothing, RMSE <= GNC's")
    return metrics, [markdown_table(title, header, table)]


def run_clean(ctx: Context, *, log: Callable[[str], None] | None = None) -> Result:
    """Clean graphs (every graph of ``benchmarks/auto.py``): the default (``robust="auto"``)
    against least squares alone (``robust="none"``), same run.  Targets: the same energy to
    1e-9 (relative) and at most 10% more time; the time the outlier test itself took is given
    beside the wall times, which the shared machine's load moves by more than that."""
    from .auto import GENERATED, _file_cases, _generated_case

    say = log or (lambda text: print(text, file=sys.stderr, flush=True))
    cases: list[Any] = [*_file_cases(ctx)] + ([] if ctx.quick else GENERATED)
    metrics: list[Metric] = []
    table: list[list[Any]] = []
    for item in cases:
        case = item if not isinstance(item, tuple) else _generated_case(*item)
        g = case.graph
        t0 = time.perf_counter()
        plain = optimize(g, robust="none")
        t_plain = time.perf_counter() - t0
        t0 = time.perf_counter()
        auto = optimize(g)
        t_auto = time.perf_counter() - t0
        o = auto.stats["outliers"]
        rel = abs(auto.final_energy - plain.final_energy) / plain.final_energy
        check = float(auto.timings.get("outliers", 0.0))
        same = bool(np.array_equal(auto.translations, plain.translations))
        ok = rel <= 1e-9 and o["rejected"] == 0 and o["rejected_gps"] == 0
        line = [case.name, g.num_nodes, g.num_constraints, f"{plain.final_energy:.10g}",
                f"{rel:.1e}", "yes" if same else "no", "yes" if o["inconsistent"] else "no",
                f"{o['max_sigmas']:.3g}", f"{o['scale']:.3g}", f"{t_plain:.2f}",
                f"{t_auto:.2f}", f"{t_auto / t_plain:.2f}", f"{check:.3f}",
                f"{check / t_auto:.2%}", _met(ok and check <= 0.10 * t_plain),
                f"{os.getloadavg()[0]:.1f}"]
        table.append(line)
        say("[outliers-clean] " + " | ".join(str(v) for v in line))
        key = "outliers_clean." + case.name.replace(" ", "_").replace("(", "").replace(
            ")", "").replace("+", "plus")
        metrics += [quality(key + ".energy_rel_diff", rel),
                    info(key + ".time_ratio", t_auto / t_plain),
                    info(key + ".check_seconds", check, "s")]
    header = ["graph", "poses", "constraints", "E least squares", "|E auto / E - 1|",
              "same poses (bits)", "test fired", "longest error (sigma)", "scale",
              "least squares s", "auto s", "auto / least squares", "test s",
              "test / auto", "targets", "load"]
    title = ("Clean graphs: the default (robust='auto') against least squares alone "
             "(robust='none'), same run.  Targets: energies equal to 1e-9, nothing rejected, "
             "the test's own time at most 10% of the least-squares time (the wall-time ratio "
             "beside it moves with the machine's load)")
    return metrics, [markdown_table(title, header, table)]


#: Rows streamed by :func:`run_online`: (graph, row label).
ONLINE_ROWS = (("grid 2D (M3500-like)", "random 100"),
               ("grid 2D (M3500-like)", "local-grouped 100"), ("grid 3D", "random 100"),
               ("city + GPS", "random 100"), ("city + GPS", "GPS 5%"))
#: The online rows' frame budget (seconds).
ONLINE_BUDGET_S = 5e-3


def _stream_online(row: Row, robust: str) -> dict[str, Any]:
    """``row``'s graph streamed through ``OnlineSolver(OnlineConfig(robust=robust))``: the
    frames' largest CPU time, the poses after the last frame and after ``join_refine()``
    (id order), the rejected sets (the graph's edge and GPS order)."""
    from hybridpgo.online import OnlineConfig, OnlineSolver
    from hybridpgo.online.replay import feed_frame, make_stream

    st = make_stream(row.graph)
    cpu = np.zeros(st.num_frames)
    with OnlineSolver(OnlineConfig(robust=robust)) as s:  # type: ignore[arg-type]
        s.wait_background_ready(60.0)
        t0 = time.perf_counter()
        for k in range(st.num_frames):
            c0 = time.thread_time()
            feed_frame(s, st, k)
            s.update(ONLINE_BUDGET_S)
            cpu[k] = time.thread_time() - c0
        seconds = time.perf_counter() - t0
        last = s.to_graph()
        t1 = time.perf_counter()
        joined = s.join_refine(600.0)
        join_s = time.perf_counter() - t1
        end = s.to_graph()
        edges, gps = s.outliers()
    rej = np.zeros(row.graph.num_edges, bool)
    rej[st.edges[edges]] = True  # arrival order -> the graph's edge order
    rej_gps = np.zeros(row.graph.num_gps, bool)
    rej_gps[st.gps[gps]] = True
    return {"cpu_max_ms": float(cpu.max() * 1e3), "over_6ms": int((cpu > 6e-3).sum()),
            "seconds": seconds, "join_s": join_s, "joined": joined, "last": last,
            "end": end, "rej": rej, "rej_gps": rej_gps}


def run_online(ctx: Context, *, log: Callable[[str], None] | None = None) -> Result:
    """:data:`ONLINE_ROWS` streamed with ``robust="auto"`` (the default) and ``"none"``."""
    say = log or (lambda text: print(text, file=sys.stderr, flush=True))
    metrics: list[Metric] = []
    table: list[list[Any]] = []
    for base in BASES:
        labels = [lab for name, lab in ONLINE_ROWS if name == base.name]
        if not labels or (ctx.quick and base is not BASES[0]):
            continue
        made = base.make()
        g0 = made.graph
        ref = solve_exact(g0, made.truth_rotations, made.truth_translations,
                          GaussNewtonConfig(max_iterations=300, energy_tolerance=1e-12))
        gps = g0.num_gps > 0
        rmse_ref = _rmse(made, ref.rotations, ref.translations, gps)
        for row in _rows(made, False):
            if row.label.split(" (")[0] not in labels or not _selected(base.name, row.label):
                continue
            cells = [base.name, row.label]
            for robust in ("auto", "none"):
                r = _stream_online(row, robust)
                sc = _scores(r["rej"], r["rej_gps"], row, row.false_edges, row.false_gps)
                last = _rmse(made, r["last"].rotations, r["last"].translations, gps) / rmse_ref
                end = _rmse(made, r["end"].rotations, r["end"].translations, gps) / rmse_ref
                cells += [_fmt(last), _fmt(end)]
                if robust == "auto":
                    cells += [f"{_fmt(sc['precision'])} / {_fmt(sc['recall'])} "
                              f"({sc['rejected']})", f"{r['cpu_max_ms']:.1f} ({r['over_6ms']})",
                              f"{r['seconds']:.1f} + {r['join_s']:.1f}"]
                    key = ("outliers_online." + base.name.split()[0] + "_"
                           + base.name.split()[1] + "."
                           + row.label.split(" (")[0].replace(" ", "_").replace("%", "pct"))
                    metrics += [quality(key + ".end_rmse_ratio", end),
                                info(key + ".last_frame_rmse_ratio", last),
                                info(key + ".precision", sc["precision"]),
                                info(key + ".recall", sc["recall"]),
                                info(key + ".cpu_max_ms", r["cpu_max_ms"], "ms")]
            cells.append(f"{os.getloadavg()[0]:.1f}")
            table.append(cells)
            say("[outliers-online] " + " | ".join(cells))
    header = ["graph", "outliers", "auto: RMSE / optimum after the last frame",
              "auto: after join_refine()", "auto: precision / recall (rejected)",
              "auto: max frame CPU ms (frames > 6 ms)", "auto: stream s + join s",
              "none: after the last frame", "none: after join_refine()", "load"]
    title = ("False loop closures and GPS fixes, streamed: OnlineSolver() (robust='auto', the "
             "worker on) against robust='none', 5 ms per frame back to back.  RMSE: aligned "
             "position error against the ground truth over the outlier-free optimum's")
    return metrics, [markdown_table(title, header, table)]
