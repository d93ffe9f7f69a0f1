"""The default pipeline (``--solver auto``) against the best optimum known.

Two tables from one set of cases:

1. **Right by default**: every benchmark file (``--data-dir``) and generated graph: the energy
   the default command reaches (``optimize(graph)``) against the best optimum known (the lowest
   of LM from the ground truth where there is one, LM from the file's vertices, LM from the
   chordal start), its time, status, the start it chose, sweeps and polish iterations.  Target:
   ``E_auto <= E_best (1 + 1e-6)`` or a status that says why not.
2. **Local minima**: ``E / E_ref`` of LM from the file, chordal + LM and the default, where
   ``E_ref`` is LM started at the ground truth (or, without one, the best known).  Target: the
   default reaches the reference (``<= +0.1 %``) wherever any of the methods does.

Every LM here is the package's exact solver with ``max_iterations=300`` and
``energy_tolerance=1e-12`` (tighter than the default pipeline's 1e-10), so a reference is
converged where the default's polish is.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridpgo.graph import PoseGraph
from hybridpgo.initialization import initial_locals
from hybridpgo.io import read_graph
from hybridpgo.solvers import optimize
from hybridpgo.solvers.config import AutoConfig, GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.tree import build_tree, global_poses

from .gtsam_ref import gtsam_available, gtsam_solve
from .metrics import Metric, info, markdown_table, quality, timing

#: References: LM run to convergence.
REF_LM = GaussNewtonConfig(max_iterations=300, energy_tolerance=1e-12)
#: "Reaches the optimum" and "reaches the global optimum" (item 2).
OPTIMUM_REL = 1e-6
#: The default's solve and GTSAM's LM are timed this many times each, alternately, where the
#: default's solve took at most PAIRED_MAX_S seconds; the ratios use the fastest of each.
PAIRED_ROUNDS = 3
PAIRED_MAX_S = 3.0
GLOBAL_REL = 1e-3

#: Benchmark files and the ground truth file (noise-free relative measurements) of each.
FILES: dict[str, str | None] = {
    "tinyGrid3D.g2o": None,
    "smallGrid3D.g2o": None,
    "w100_toro.graph": None,
    "intel.g2o": None,
    "garage.g2o": None,
    "M3500.g2o": "M3500_groundtruth_isam.txt",
    "M3500_isam.txt": "M3500_groundtruth_isam.txt",
    "M3500_toro.graph": "M3500_groundtruth_isam.txt",
    "sphere2500.g2o": "sphere2500_groundtruth_isam.txt",
    "sphere2500_isam.txt": "sphere2500_groundtruth_isam.txt",
    "sphere2200_smallnoise_toro.graph": None,
    "sphere_bignoise_vertex3.g2o": None,
    "torus3D.g2o": None,
}
#: Files measured once and left out of the run (each over ~5 minutes on this machine, or
#: the run's 20-minute budget); say so in the table.
SKIPPED_FILES: dict[str, str] = {}

#: Generated graphs: (name, kind, preset, seed, noisify yaw sigma in degrees, GPS spacing).
GENERATED: list[tuple[str, str, str | None, int, float, int]] = [
    ("city (2000 poses)", "city", None, 0, 0.0, 0),
    ("city (2000 poses) + GPS", "city", None, 0, 0.0, 100),
    ("valencia + GPS", "city", "valencia", 0, 0.0, 100),
    ("paris2 + GPS", "city", "paris2", 0, 0.0, 100),
    ("m3500a seed 0", "grid", "m3500a", 0, 0.0, 0),
    ("m3500a seed 0 + GPS", "grid", "m3500a", 0, 0.0, 100),
    ("m3500a seed 1", "grid", "m3500a", 1, 0.0, 0),
    ("m3500b seed 0", "grid", "m3500b", 0, 0.0, 0),
    ("m3500b seed 1", "grid", "m3500b", 1, 0.0, 0),
    ("m3500b seed 2", "grid", "m3500b", 2, 0.0, 0),
    ("m3500c seed 0", "grid", "m3500c", 0, 0.0, 0),
    ("m3500c seed 1", "grid", "m3500c", 1, 0.0, 0),
    ("m3500 noisified 10 deg", "grid", "m3500", 0, 10.0, 0),
    ("m3500 noisified 20 deg", "grid", "m3500", 0, 20.0, 0),
    ("m3500b noisified 10 deg", "grid", "m3500b", 0, 10.0, 0),
]
#: Standard deviation (m) of the planar GPS readings added to a generated grid (its extent:
#: +-43 m).
GRID_GPS_SIGMA = 0.5
#: Generated graphs left out of the run, and why.
SKIPPED_GENERATED: dict[str, str] = {
    "m3500a seed 2, m3500c seed 2": "explored, left out of the 20-minute run",
    "paris1 + GPS": "27k poses: left out of the run (paris2 + GPS, larger, is in it)",
}


@dataclass
class Case:
    name: str
    graph: PoseGraph
    truth: tuple[np.ndarray, np.ndarray] | None
    truth_source: str


def _truth_from_relative(graph: PoseGraph, gt: PoseGraph) -> tuple[np.ndarray, np.ndarray]:
    """Poses of ``graph``'s nodes chained from a noise-free relative-measurement file."""
    tree = build_tree(gt, "bfs")
    rot, trans = global_poses(tree, *initial_locals(gt, tree, "tree"))
    where = {int(k): i for i, k in enumerate(gt.node_ids)}
    idx = np.array([where[int(k)] for k in graph.node_ids])
    return rot[idx], trans[idx]


def _file_cases(ctx: Any) -> list[Case]:
    import warnings

    cases = []
    for name, gt_name in FILES.items():
        path = ctx.data_dir / name
        if not path.exists():
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # w100's EQUIV note
            graph = read_graph(path)
        truth = None
        if gt_name is not None and (ctx.data_dir / gt_name).exists():
            truth = _truth_from_relative(graph, read_graph(ctx.data_dir / gt_name))
        cases.append(Case(name, graph, truth, gt_name or ""))
    return cases


def _generated_case(name: str, kind: str, preset: str | None, seed: int, yaw: float,
                    gps: int) -> Case:
    from hybridpgo.generate import generate_city, generate_grid, noisify

    if kind == "city":
        made: Any = generate_city(preset, seed=seed, gps_every=gps)
    else:
        made = generate_grid(preset, seed=seed)
    graph = made.graph
    if kind == "grid" and gps:  # planar readings of the true positions, sigma GRID_GPS_SIGMA
        rng = np.random.default_rng(seed)
        idx = np.arange(0, graph.num_nodes, gps)
        pos = made.truth_translations[idx].copy()
        pos[:, :2] += GRID_GPS_SIGMA * rng.standard_normal((idx.size, 2))
        info = np.eye(3) / GRID_GPS_SIGMA ** 2
        graph = graph.add_gps(graph.node_ids[idx], pos, np.broadcast_to(info, (idx.size, 3, 3)))
    if yaw:
        graph = noisify(graph, yaw_sigma_deg=yaw, seed=seed)
    return Case(name, graph, (made.truth_rotations, made.truth_translations), "generator")


def _lm(graph: PoseGraph, start: tuple[np.ndarray, np.ndarray] | None) -> tuple[float, float,
                                                                                 str]:
    t0 = time.perf_counter()
    res = solve_exact(graph, *(start or (None, None)), REF_LM)
    return res.final_energy, time.perf_counter() - t0, res.status.value


def _chordal(graph: PoseGraph) -> tuple[np.ndarray, np.ndarray]:
    tree = build_tree(graph, "bfs")
    return global_poses(tree, *initial_locals(graph, tree, "chordal"))


def _measure(case: Case) -> dict[str, Any]:
    g = case.graph
    row: dict[str, Any] = {"name": case.name, "poses": g.num_nodes,
                           "constraints": g.num_constraints, "gps": g.num_gps}
    t0 = time.perf_counter()
    res = optimize(g)  # the default command's library call
    row["auto_time"] = time.perf_counter() - t0
    row["auto"] = res.final_energy
    row["auto_status"] = res.status.value
    s = res.stats
    row.update(init=s["init"], sweeps=s["sweeps"], polish_its=s["polish_iterations"],
               finalists="/".join(s["finalists"]), auto_timings=dict(res.timings),
               candidates=s["candidates"])
    cert = s["certificate"]
    row.update(certified=bool(cert["certified"]), cert_summary=str(cert["summary"]),
               cert_seconds=float(cert.get("seconds", 0.0)), polished=s["polished_starts"],
               solve_time=float(res.timings["solve"]))
    # every start polished, no certificate: the pipeline's answer without the certificate
    t0 = time.perf_counter()
    every = optimize(g, AutoConfig(certify=False))
    row["every_time"] = time.perf_counter() - t0
    row["every"], row["every_polished"] = every.final_energy, every.stats["polished_starts"]
    if gtsam_available():
        start = (g.rotations, g.translations) if g.has_estimates else _chordal(g)
        gt = gtsam_solve(g, *start, "lm")
        row["gtsam"] = {"from": "file" if g.has_estimates else "chordal",
                        "energy": gt["final_energy"], "seconds": gt["seconds"]}
    refs: dict[str, float] = {}
    if g.has_estimates:
        refs["file"], row["file_time"], row["file_status"] = _lm(g, None)
    t0 = time.perf_counter()
    start = _chordal(g)
    refs["chordal"], _, row["chordal_status"] = _lm(g, start)
    row["chordal_time"] = time.perf_counter() - t0
    if case.truth is not None:
        refs["truth"], row["truth_time"], row["truth_status"] = _lm(g, case.truth)
    row["refs"] = refs
    best_src = min(refs, key=lambda k: refs[k])
    row["best"], row["best_source"] = refs[best_src], best_src
    # the local-minima reference: LM from the truth where known, else the best known
    row["ref"] = refs.get("truth", row["best"])
    gt = row.get("gtsam")
    peer_start = (g.rotations, g.translations) if g.has_estimates else start
    if gt is not None and gt["from"] == "file" and gt["energy"] > row["best"] * (1 + OPTIMUM_REL):
        # GTSAM's LM from the file ends above the optimum: GTSAM from the chordal start too
        gc = gtsam_solve(g, *start, "lm")
        row["gtsam_chordal"] = {"energy": gc["final_energy"], "seconds": gc["seconds"]}
        peer_start = start
    if gt is not None and row["solve_time"] <= PAIRED_MAX_S:
        _paired(g, row, peer_start)
    return row


def _paired(g: PoseGraph, row: dict[str, Any], peer_start: tuple[np.ndarray, np.ndarray]
            ) -> None:
    """Time the default and GTSAM's LM (from the start the ratio uses) again, alternately,
    :data:`PAIRED_ROUNDS` times; the fastest of each (the first measurement included) gives
    the ratio.  A shared machine slows single timings by tens of percent, each its own way."""
    peer = row.get("gtsam_chordal", row["gtsam"])
    solve, whole, cert = row["solve_time"], row["auto_time"], row["cert_seconds"]
    best = peer["seconds"]
    for _ in range(PAIRED_ROUNDS - 1):
        t0 = time.perf_counter()
        res = optimize(g)
        took = time.perf_counter() - t0
        if res.timings["solve"] < solve:
            solve, cert = float(res.timings["solve"]), float(
                res.stats["certificate"].get("seconds", 0.0))
        whole = min(whole, took)
        best = min(best, gtsam_solve(g, *peer_start, "lm")["seconds"])
    row["paired"] = {"solve": solve, "whole": whole, "certificate": cert, "gtsam": best,
                     "rounds": PAIRED_ROUNDS}


def _fmt_ratio(x: float | None) -> str:
    if x is None:
        return "—"
    return f"{x:.6f}" if x < 10 else f"{x:.4g}"


def run(ctx: Any, *, log: Callable[[str], None] | None = None) -> tuple[list[Metric], list[str]]:
    import sys

    say = log or (lambda text: print(text, file=sys.stderr, flush=True))
    cases: list[Case | tuple[str, str, str | None, int, float, int]] = [*_file_cases(ctx)]
    if not ctx.quick:
        cases += GENERATED
    rows = []
    files = [c for c in cases if isinstance(c, Case)]
    for planar in (True, False):  # every kernel a row runs, compiled or loaded before timing
        warm = next((c for c in files if c.graph.is_2d == planar), None)
        if warm is not None:
            _measure(warm)
    gps = next((c for c in cases if not isinstance(c, Case) and c[5]), None)
    if gps is not None:  # the sweeps' GPS kernels
        _measure(_generated_case(*gps))
    for item in cases:
        case = item if isinstance(item, Case) else _generated_case(*item)
        t0 = time.perf_counter()
        row = _measure(case)
        rows.append(row)
        say(f"[auto] {row['name']}: auto/best {row['auto'] / row['best']:.8f} "
            f"({row['init']}, {row['sweeps']} sweeps, {row['polish_its']} its, "
            f"{row['auto_status']}, {row['auto_time']:.1f} s); "
            f"case {time.perf_counter() - t0:.0f} s")

    metrics: list[Metric] = []
    t1 = []
    met_opt = 0
    for r in rows:
        key = "auto." + r["name"].replace(" ", "_").replace("(", "").replace(")", "").replace(
            "+", "plus")
        excess = r["auto"] / r["best"] - 1.0
        ok = excess <= OPTIMUM_REL
        met_opt += ok
        metrics += [quality(f"{key}.energy_over_best", r["auto"] / r["best"]),
                    timing(f"{key}.time", r["auto_time"]),
                    info(f"{key}.chordal_lm_time", r["chordal_time"], "s")]
        t1.append([r["name"], r["poses"], r["constraints"], f"{r['best']:.8g}",
                   r["best_source"], f"{excess:+.1e}", "met" if ok else "MISSED",
                   r["auto_status"], r["init"], r["finalists"], r["sweeps"], r["polish_its"],
                   f"{r['auto_time']:.1f}", f"{r['chordal_time']:.1f}"])
    metrics.append(info("auto.cases_at_optimum", met_opt, note=f"of {len(rows)}"))
    tables = [markdown_table(
        header=["graph", "poses", "constraints", "best known E", "from", "auto E / best - 1",
         "≤ 1e-6", "status", "start chosen", "polished", "sweeps", "polish its", "auto s",
         "chordal+LM s"], rows=t1,
        title="Default pipeline (optimize(graph), --solver auto) vs the best optimum known "
              "(lowest of LM from the ground truth, the file, the chordal start)")]
    skipped = {**SKIPPED_FILES, **SKIPPED_GENERATED}
    if skipped:
        tables.append(markdown_table(title="Graphs not in this run", header=["left out", "why"],
                                     rows=[[k, v] for k, v in skipped.items()]))

    t4 = []
    for r in rows:
        key = "auto." + r["name"].replace(" ", "_").replace("(", "").replace(")", "").replace(
            "+", "plus")
        same = abs(r["auto"] - r["every"]) / r["every"]
        gt = r.get("gtsam")
        gtsam_cols = ["—", "—", "—", "—"]
        pair = r.get("paired", {"solve": r["solve_time"], "whole": r["auto_time"],
                                "certificate": r["cert_seconds"], "rounds": 1})
        if gt is not None:
            peer = r.get("gtsam_chordal", gt)
            src = "chordal (file: local min.)" if "gtsam_chordal" in r else gt["from"]
            peer_s = pair.get("gtsam", peer["seconds"])
            ratio = pair["solve"] / peer_s
            metrics.append(info(f"{key}.solve_over_gtsam_lm", ratio))
            gtsam_cols = [f"{peer_s:.2f} ({src}; E/best {peer['energy'] / r['best']:.6g})",
                          f"{ratio:.2f}", f"{pair['whole'] / peer_s:.2f}", str(pair["rounds"])]
        frac = pair["certificate"] / pair["solve"] if pair["solve"] > 0 else float("nan")
        metrics += [quality(f"{key}.same_as_every_start", same),
                    info(f"{key}.certificate_fraction", frac)]
        t4.append([r["name"], "yes" if r["certified"] else "no", r["cert_summary"],
                   f"{r['polished']} / {r['every_polished']}", f"{same:.1e}",
                   "met" if same <= 1e-9 else "MISSED", f"{pair['solve']:.2f}",
                   f"{r['every_time']:.2f}", f"{pair['certificate']:.2f}", f"{frac:.0%}",
                   *gtsam_cols])
    tables.append(markdown_table(
        header=["graph", "certified", "certificate", "polished starts (cert / every)",
                "|E - E_every| / E_every", "≤ 1e-9", "default solve s", "every start s",
                "certificate s", "certificate / solve", "GTSAM LM s (from; E / best)",
                "solve / GTSAM", "whole call / GTSAM", "timings"], rows=t4,
        title="Certificate on the default path (solve: the default's timings['solve'], warm; "
              "every start: AutoConfig(certify=False), every finalist polished; GTSAM: "
              "LevenbergMarquardtOptimizer from the file, or from the chordal start where the "
              "file's ends above the best known; timings: the default and GTSAM each timed "
              f"that many times, alternately (rows whose solve took <= {PAIRED_MAX_S:g} s), "
              "the fastest of each in the solve, certificate and GTSAM columns)"))

    t2 = []
    reach_any = reach_auto = 0
    for r in rows:
        ref = r["ref"]
        cols = {k: r["refs"].get(k) for k in ("file", "chordal")}
        ratios = {k: (v / ref if v is not None else None) for k, v in cols.items()}
        ratios["auto"] = r["auto"] / ref
        anyone = any(x is not None and x <= 1 + GLOBAL_REL for x in ratios.values())
        auto_ok = ratios["auto"] <= 1 + GLOBAL_REL
        reach_any += anyone
        reach_auto += anyone and auto_ok
        verdict = ("met" if auto_ok else "MISSED") if anyone else (
            "none reaches it" + (" (auto best)" if ratios["auto"] <= min(
                x for x in ratios.values() if x is not None) else ""))
        t2.append([r["name"], f"{ref:.8g}", "LM from truth" if "truth" in r["refs"]
                   else f"best known ({r['best_source']})", _fmt_ratio(ratios["file"]),
                   _fmt_ratio(ratios["chordal"]), _fmt_ratio(ratios["auto"]), verdict])
    metrics += [info("auto.minima.cases_any_reaches", reach_any),
                info("auto.minima.cases_auto_reaches", reach_auto)]
    tables.append(markdown_table(
        header=["graph", "E_ref", "reference", "LM from file", "chordal + LM", "default (auto)",
         "default ≤ +0.1% where any reaches"], rows=t2,
        title="Local minima: E / E_ref (E_ref = LM started at the ground truth where known)"))
    t3 = []
    for r in rows:
        c = r["candidates"]
        t3.append([r["name"]] + [
            (f"{c[k]['initial_energy']:.4g} → {c[k]['energy_after_sweeps']:.4g} "
             f"({c[k]['sweeps']} sw)"
             + (f" → {c[k]['final_energy'] / r['ref']:.6f}×ref" if "final_energy" in c[k]
                else "")) if k in c and c[k].get("initial_energy") is not None else "—"
            for k in ("chordal", "tree", "file")] + [
            " / ".join(f"{k} {v:.1f}" for k, v in r["auto_timings"].items()
                       if k in ("start", "sweeps", "polish", "relaxation"))])
    tables.append(markdown_table(
        header=["graph", "chordal", "tree", "file", "auto time by phase (s)"], rows=t3,
        title="What the default did per start: E0 → E after the kept sweeps → polished "
              "(E / E_ref)"))
    return metrics, tables
