"""SE-Sync's certificate on the benchmark files, against SE-Sync's published optima.

For every file: the chordal start, then :func:`hybridpgo.certificate.sesync_certificate`
(Newton's method on SE-Sync's objective F from there, then the certificate); its F, verdict,
gap bound, smallest eigenvalue and cost beside the exact solver's LM from the certified start
(the solve it would start).  SE-Sync's published optimal objectives (IJRR 2019 Tables 1-2;
SE-Sync's own loader weights, reproduced by :func:`hybridpgo.certificate.sesync_weights`) are
listed beside ours.  Second table: the Riemannian staircase from the file's vertices (a poor
start) on the graphs where LM from there ends in a local minimum.
"""

from __future__ import annotations

import time
from typing import Any

from .metrics import Metric, info, markdown_table, timing

#: SE-Sync's published optimal objectives (IJRR 2019, Tables 1 and 2; 4 significant digits).
PUBLISHED = {"intel.g2o": 5.235e1, "M3500.g2o": 6.432e3, "sphere2500.g2o": 1.687e3,
             "torus3D.g2o": 2.423e4, "garage.g2o": 1.263e0}
FILES = ["tinyGrid3D.g2o", "smallGrid3D.g2o", "w100_toro.graph", "intel.g2o", "garage.g2o",
         "M3500.g2o", "M3500_isam.txt", "M3500_toro.graph", "sphere2500.g2o",
         "sphere2500_isam.txt", "sphere_bignoise_vertex3.g2o", "torus3D.g2o"]
#: Files whose LM from the file's vertices ends in a local minimum: the staircase from there.
STAIRCASE = ["torus3D.g2o", "sphere_bignoise_vertex3.g2o", "M3500.g2o"]


def _read(path: Any) -> Any:
    import warnings

    from hybridpgo.io import read_graph

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_graph(path)


def run(ctx: Any) -> tuple[list[Metric], list[str]]:
    from hybridpgo.certificate import sesync_certificate, staircase_start
    from hybridpgo.initialization import chordal_initialization
    from hybridpgo.solvers.gauss_newton import _ensure_compiled, solve_exact

    _ensure_compiled()
    metrics: list[Metric] = []
    rows: list[list[Any]] = []
    for name in FILES:
        path = ctx.data_dir / name
        if not path.exists():
            continue
        graph = _read(path)
        t0 = time.perf_counter()
        rot, trans = chordal_initialization(graph)
        t_chordal = time.perf_counter() - t0
        solve_exact(graph, rot, trans)  # warm the solver's kernels and imports
        t0 = time.perf_counter()
        lm_chordal = solve_exact(graph, rot, trans)
        t_lm_chordal = time.perf_counter() - t0
        cert = sesync_certificate(graph, rot, trans)
        t0 = time.perf_counter()
        lm = solve_exact(graph, cert.rotations, cert.translations)
        t_lm = time.perf_counter() - t0
        pub = PUBLISHED.get(name)
        key = name.split(".")[0]
        metrics += [info(f"certificate.{key}.objective", cert.objective),
                    info(f"certificate.{key}.certified", float(cert.certified)),
                    timing(f"certificate.{key}.seconds", cert.seconds),
                    info(f"certificate.{key}.over_lm", cert.seconds / t_lm, "x")]
        rows.append([
            name, graph.num_nodes, f"{cert.objective:.6g}",
            f"{pub:.4g}" if pub else "-",
            (f"{abs(cert.objective - pub) / pub:.1e}" if pub else "-"),
            "yes" if cert.certified else "no",
            f"{cert.relative_gap:.1e}" if cert.certified else "-",
            f"{cert.lambda_min:.2e}",
            cert.stats.get("newton_iterations", "-"),
            f"{cert.seconds:.3f}", f"{cert.stats.get('seconds_refine', 0.0):.3f}",
            f"{cert.stats.get('seconds_spectrum', 0.0):.3f}",
            f"{t_chordal:.3f}", f"{t_lm:.3f} ({lm.iterations})",
            f"{t_lm_chordal:.3f} ({lm_chordal.iterations})",
            f"{cert.seconds / t_lm:.2f}",
            f"{lm.final_energy:.10g}", f"{lm_chordal.final_energy:.10g}"])
        print(f"  {name}: {rows[-1]}", flush=True)
    stair_rows: list[list[Any]] = []
    for name in STAIRCASE:
        path = ctx.data_dir / name
        if not path.exists():
            continue
        graph = _read(path)
        local = solve_exact(graph)
        t0 = time.perf_counter()
        rot, trans, sinfo = staircase_start(graph, graph.rotations, graph.translations)
        t_stair = time.perf_counter() - t0
        pol = solve_exact(graph, rot, trans)
        ranks = "; ".join(f"{int(r['rank'])}: {r['relaxation']:.6g} -> {r['rounded']:.6g}"
                          for r in sinfo["ranks"])
        stair_rows.append([name, f"{local.final_energy:.10g}", ranks,
                           "yes" if sinfo["certified"] else "no",
                           f"{sinfo['objective']:.6g}", f"{t_stair:.2f}",
                           f"{pol.final_energy:.10g}"])
        metrics.append(info(f"certificate.staircase.{name.split('.')[0]}.certified",
                            float(sinfo["certified"])))
        print(f"  staircase {name}: {stair_rows[-1]}", flush=True)
    tables = [
        markdown_table(
            "Chordal start -> Newton on SE-Sync's F -> certificate; LM (our E) from the "
            "certified start and from the chordal start (warm, one run each); SE-Sync's "
            "published optimum of F beside ours",
            ["file", "poses", "F (ours)", "F (SE-Sync, published)", "rel. diff", "certified",
             "gap bound (rel.)", "lambda_min", "Newton factorizations", "certificate s",
             "Newton s", "eigenvalue s", "chordal s", "LM from certified start s (its)",
             "LM from chordal s (its)", "certificate / LM", "E (certified start)",
             "E (chordal start)"], rows),
        markdown_table(
            "Riemannian staircase from the file's vertices (where LM from them ends in a "
            "local minimum of E), then LM",
            ["file", "E: LM from the file", "rank: F relaxed -> F rounded + Newton",
             "certified", "F", "staircase s", "E: LM from the staircase"], stair_rows)]
    return metrics, tables
