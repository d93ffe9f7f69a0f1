"""``hybridpgo optimize FILE -o OUT``: optimize a graph, write it, print a summary."""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ..errors import HybridPGOError
from ._common import (
    ProgressBar,
    describe_graph,
    fmt_energy,
    log,
    output_format,
    print_json,
    print_table,
    read_input,
)

if TYPE_CHECKING:
    from ..graph import PoseGraph
    from ..solvers import SolverConfig, SolveResult

#: CLI option -> HybridConfig field, for the options only the hybrid solver takes.
HYBRID_ONLY = {"sweeps": "--sweeps", "tau0": "--tau0", "tau_decay": "--tau-decay",
               "damping": "--damping", "step": "--step", "gps_batch_size": "--gps-batch-size",
               "dmax": "--dmax", "correction": "--correction",
               "correction_iterations": "--correction-iterations", "monotone": "--monotone"}


@dataclass
class Job:
    """One optimization: what to read, how to solve, what to write."""

    input: str
    output: str
    solver: str = "auto"
    options: dict[str, Any] = field(default_factory=dict)
    """Solver options by config field name (only those given)."""
    fmt: str | None = None
    out_format: str | None = None
    plot_prefix: str | None = None
    plots_optional: bool = False
    """When matplotlib is missing: skip the plots with a note instead of failing (demo)."""
    skip_unknown: bool = False
    quiet: bool = False
    covariance: str | None = None
    """``--covariance``: where to write the poses' marginal covariances (.npz)."""
    covariance_poses: tuple[int, ...] | str | None = None
    """``--covariance-poses``: file ids, ``"all"``, or None (all)."""
    rerun: str | None = None
    """``--rerun``: where to record the run for the Rerun viewer (.rrd)."""
    rejected_out: str | None = None
    """``--rejected-out``: where to list the constraints ``--robust auto`` rejected (CSV)."""


def _covariance_nodes(job: Job, graph: PoseGraph) -> Any:
    """Dense indices of the poses of ``--covariance`` (checked before the solve), or None."""
    import numpy as np

    if job.covariance is None:
        if job.covariance_poses is not None:
            raise HybridPGOError("--covariance-poses: give --covariance NPZ too")
        return None
    sel = job.covariance_poses
    if sel is None or isinstance(sel, str):  # None or "all"
        return np.arange(graph.num_nodes)
    index = graph.index_from_id()
    missing = [i for i in sel if i not in index]
    if missing:
        raise HybridPGOError(f"--covariance-poses {missing[0]}: {job.input} has no pose with id "
                             f"{missing[0]} (ids {int(graph.node_ids[0])}.."
                             f"{int(graph.node_ids[-1])})")
    return np.array([index[i] for i in sel], np.int64)


def _covariances(job: Job, graph: PoseGraph, result: SolveResult, nodes: Any) -> Any:
    """The marginal covariances of ``nodes`` at the solution, under a visible phase."""
    from ..covariance import marginal_covariances
    from ._progress import phase

    with phase(f"covariances of {len(nodes)} poses", enabled=not job.quiet):
        return marginal_covariances(graph, result.rotations, result.translations, nodes)


#: Columns of ``optimize --rejected-out`` (:func:`hybridpgo.solvers.robust.rejected_rows`).
REJECTED_COLUMNS = ("kind", "index", "id_a", "id_b", "line", "sigmas")


def rejected_csv_lines(rows: list[dict[str, Any]]) -> list[str]:
    """``--rejected-out``: a header, then one row per rejected constraint."""
    out = [",".join(REJECTED_COLUMNS)]
    for r in rows:
        out.append(",".join("" if r[k] is None else repr(r[k]) if k == "sigmas" else str(r[k])
                            for k in REJECTED_COLUMNS))
    return out


def _check_options(job: Job, graph: PoseGraph) -> str:
    """Reject options that do not apply; return the init kind."""
    from ..solvers import default_init

    opts = job.options
    if job.rejected_out is not None and (job.solver == "toro"
                                         or opts.get("robust", "auto") != "auto"):
        raise HybridPGOError("--rejected-out lists what --robust auto rejects (the default of "
                             "--solver auto, hybrid and exact)")
    if job.solver == "auto":
        return _check_auto_options(job, graph)
    if job.solver in ("exact", "toro"):
        skip = {"sweeps"} if job.solver == "toro" else set()
        given = [flag for key, flag in HYBRID_ONLY.items() if key in opts and key not in skip]
        if opts.get("polish"):
            given.append("--polish")
        if job.solver == "toro" and "max_iterations" in opts:
            given.append("--max-iterations (toro runs --sweeps iterations)")
        if job.solver == "toro" and "robust" in opts:
            given.append("--robust")
        if given:
            where = ("only for the hybrid solver (--solver hybrid)" if job.solver == "exact"
                     else "not an option of --solver toro")
            raise HybridPGOError(f"{', '.join(given)}: {where}")
        if job.solver == "toro" and opts.get("init") == "chordal":
            raise HybridPGOError("--init chordal: --solver toro starts from 'tree' or 'file'")
        if job.solver == "toro" and opts.get("tree") == "mst":
            raise HybridPGOError("--tree mst: --solver toro grows a 'toro' or 'bfs' tree")
    if job.solver != "toro" and opts.get("tree") == "toro":
        raise HybridPGOError("--tree toro: only for --solver toro")
    if job.solver == "hybrid" and "max_iterations" in opts and not opts.get("polish"):
        raise HybridPGOError("--max-iterations limits the exact solver or the polish: add "
                             "--polish or use --solver exact (the hybrid solver runs --sweeps)")
    init: str = opts.get("init") or default_init(graph, job.solver)
    if init == "file" and not graph.has_estimates:
        raise HybridPGOError(f"{job.input}: --init file needs vertex estimates, but the file has "
                             "none (iSAM files list only constraints); use --init tree")
    return init


def _check_auto_options(job: Job, graph: PoseGraph) -> str:
    """The default pipeline: --polish is implied; --init restricts the starts.  Returns the
    start ('auto' when the pipeline chooses)."""
    opts = job.options
    if opts.get("polish"):
        raise HybridPGOError("--polish: --solver auto (the default) always polishes; "
                             "--polish is for --solver hybrid")
    if opts.get("tree") == "toro":
        raise HybridPGOError("--tree toro: only for --solver toro")
    init: str = opts.get("init") or "auto"
    if init == "file" and not graph.has_estimates:
        raise HybridPGOError(f"{job.input}: --init file needs vertex estimates, but the file has "
                             "none (iSAM files list only constraints); use --init tree")
    return init


def _make_config(job: Job, init: str) -> SolverConfig:
    """The solver's typed options object, built once from the CLI options (whose names
    :func:`hybridpgo.solvers.config_for` translates)."""
    from ..solvers import config_for

    opts = dict(job.options)
    if job.solver in ("hybrid", "toro"):
        opts["init"] = init
    elif job.solver == "exact":
        opts.pop("init", None)
        opts.pop("tree", None)
    try:
        return config_for(job.solver, **opts)
    except (ValueError, TypeError) as exc:
        raise HybridPGOError(f"invalid solver option: {exc}") from exc


def _check_writable(path: str) -> None:
    """Refuse an output that cannot be written, before the solve (a FormatError)."""
    from .._output import check_output
    from ._common import STDOUT_NAMES

    if path not in STDOUT_NAMES:
        check_output(path)


def _plots_possible(job: Job) -> bool:
    if job.plot_prefix is None:
        return False
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        if job.plots_optional:
            log("hybridpgo: note: no plots (matplotlib is not installed): "
                "pip install hybridpgo[plot]")
            return False
        raise HybridPGOError("--plot needs matplotlib, which is not installed: "
                             "pip install hybridpgo[plot]") from None
    _check_writable(job.plot_prefix + "_before.png")
    return True


def _compile_kernels(job: Job, graph: PoseGraph) -> None:
    """Compile (or load from Numba's cache) the kernels this solve uses under a visible phase
    (the GPS batches and interpolated solving only when the graph and options use them)."""
    from ..solvers.gauss_newton import ensure_compiled as ensure_exact
    from ._progress import phase

    exact = job.solver in ("exact", "auto") or bool(job.options.get("polish"))
    # the default pipeline's early try (a certified start) needs no sweep: its kernels come
    # first, and a second core compiles the sweep's in case the certificate fails (the cold
    # cache is probed by "finish", whose modules are imported anyway: "sweep"'s probe would
    # import the hybrid solver on every warm run)
    early = (job.solver == "auto" and graph.num_gps == 0 and not job.options.get("sweeps")
             and job.options.get("robust", "auto") in ("auto", "none"))
    if job.solver in ("hybrid", "auto"):  # a second core compiles what comes after the sweep
        from .._precompile import start

        # in the order the solve needs them: after the sweep, the polish, the starts
        start(["finish", "sweep"] if early else
              ["finish", "exact", "starts", "exact-solve"] if exact else ["finish", "starts"])
    with phase("compiling kernels (first run only)", enabled=not job.quiet):
        if early:
            from ..certificate import ensure_compiled as ensure_certificate

            ensure_exact()
            ensure_certificate(graph.is_2d)
            return
        if job.solver in ("hybrid", "auto"):
            from ..solvers.hybrid.solver import ensure_compiled as ensure_hybrid

            ensure_hybrid(graph.num_gps > 0, bool(job.options.get("dmax")),
                          job.options.get("step") == "givens")
        if exact:
            ensure_exact()


def _recorder(job: Job, graph: PoseGraph) -> Any:
    """The ``--rerun`` recorder (checked before the solve), or None."""
    if job.rerun is None:
        return None
    if job.solver == "toro":
        raise HybridPGOError("--rerun records --solver auto, hybrid or exact, not --solver toro")
    from ..recording import RerunRecorder, rerun_available

    if not rerun_available():
        raise HybridPGOError("--rerun needs rerun-sdk, which is not installed: "
                             "pip install hybridpgo[rerun]")
    return RerunRecorder(graph, job.rerun, name=os.path.basename(job.input))


def _optimize(graph: PoseGraph, config: SolverConfig, progress: Any, init: str | None,
              tree: str | None, iterate: Any) -> SolveResult:
    """:func:`hybridpgo.optimize` (``iterate``: the ``--rerun`` recorder, or None)."""
    from ..solvers import optimize

    return optimize(graph, config, progress=progress, iterate=iterate, init=init, tree=tree)


def _solve(job: Job, graph: PoseGraph, config: SolverConfig, init: str,
           recorder: Any = None) -> SolveResult:
    from ..solvers import AutoConfig, HybridConfig, Progress, ToroConfig, optimize

    nc = graph.num_constraints
    if isinstance(config, AutoConfig):
        return _solve_auto(job, graph, config, recorder)
    if isinstance(config, ToroConfig):
        tbar = ProgressBar("toro", config.iterations, nc, enabled=not job.quiet)
        try:
            return optimize(graph, config, progress=lambda p: tbar.update(p.iteration, p.energy))
        finally:
            tbar.close()
    if isinstance(config, HybridConfig):
        bar = ProgressBar("hybrid", config.sweeps, nc, enabled=not job.quiet)
        polish = config.polish

        def report(p: Progress) -> None:
            if p.phase == "sweeps":
                note = "polishing (exact LM)..." if polish and p.iteration == p.total else ""
                bar.update(p.iteration, p.energy, p.tau, note)

        try:
            return _optimize(graph, config, report, None, None, recorder)
        finally:
            bar.close()
    bar = ProgressBar("exact LM", config.max_iterations, nc, enabled=not job.quiet)
    try:
        return _optimize(graph, config, lambda p: bar.update(p.iteration, p.energy), init,
                         job.options.get("tree") or "bfs", recorder)
    finally:
        bar.close()


def _solve_auto(job: Job, graph: PoseGraph, config: Any, recorder: Any = None) -> SolveResult:
    """The default pipeline, with one progress bar per start's sweeps and per polish (and every
    start, sweep and polish iteration recorded by ``recorder``, ``--rerun``)."""
    from ..solvers import Progress, optimize

    nc = graph.num_constraints
    current: list[Any] = [None, None]  # (phase, detail), its bar

    def report(p: Progress) -> None:
        if p.phase == "start":
            if current[1] is not None:
                current[1].close()
                current[:] = [None, None]
            if not job.quiet:
                log(f"auto: start {p.detail}: E/c {p.energy / max(nc, 1):.4g}")
            return
        if current[0] != (p.phase, p.detail):
            if current[1] is not None:
                current[1].close()
            label = f"{p.detail} {'sweeps' if p.phase == 'sweeps' else 'polish (LM)'}"
            current[0] = (p.phase, p.detail)
            current[1] = ProgressBar(label, p.total, nc, enabled=not job.quiet,
                                     unit="sweep" if p.phase == "sweeps" else "it")
        current[1].update(p.iteration, p.energy, p.tau)

    try:
        return optimize(graph, config, progress=report, iterate=recorder)
    finally:
        if current[1] is not None:
            current[1].close()


def run_job(job: Job) -> dict[str, Any]:
    """Read, optimize, write (and plot); return the JSON-friendly summary."""
    t0 = time.perf_counter()
    graph = read_input(job.input, job.fmt, skip_unknown=job.skip_unknown)
    t_read = time.perf_counter() - t0
    init = _check_options(job, graph)
    config = _make_config(job, init)
    out_fmt = output_format(job.output, job.out_format, graph, allow_isam=False)
    if out_fmt == "toro" and graph.num_gps:
        raise HybridPGOError(f"{job.output}: the TORO format cannot store GPS constraints; "
                             "write g2o (--out-format g2o)")
    _check_writable(job.output)
    cov_nodes = _covariance_nodes(job, graph)
    plots = _plots_possible(job)
    if not job.quiet:
        log(f"read {job.input} ({describe_graph(graph)}) in {t_read:.2f} s")
    _compile_kernels(job, graph)

    recorder = _recorder(job, graph)
    try:
        result = _solve(job, graph, config, init, recorder)
        if job.solver == "auto":
            init = str(result.stats["init"])  # the start the pipeline chose
        cov = None if cov_nodes is None else _covariances(job, graph, result, cov_nodes)
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise

    from ..io import write_graph

    t0 = time.perf_counter()
    write_graph(graph.with_poses(result.rotations, result.translations), job.output, out_fmt)
    if job.rejected_out is not None:
        from ..io._lines import write_atomic

        rows = result.stats.get("outliers", {}).get("rejected_constraints", [])
        write_atomic(job.rejected_out, lambda: rejected_csv_lines(rows))
    if recorder is not None:
        recorder.close()
    if cov is not None:
        from ..covariance import save_covariances
        from ..solvers.gauss_newton import default_fixed_nodes

        assert job.covariance is not None
        save_covariances(job.covariance, graph.node_ids[cov_nodes], cov,
                         fixed_ids=graph.node_ids[default_fixed_nodes(graph)])
    t_write = time.perf_counter() - t0
    written_plots: list[str] = []
    if plots:
        assert job.plot_prefix is not None
        default_tree = "toro" if job.solver == "toro" else "bfs"
        written_plots = write_plots(graph, result, init, job.options.get("tree") or default_tree,
                                    job.plot_prefix, os.path.basename(job.input))
    nc = graph.num_constraints
    summary = result.summary()
    extra: dict[str, Any] = {}
    if job.solver == "auto":
        extra["reason"] = result.stats["reason"]
    if "polish_iterations" in result.stats:
        extra["energy_after_sweeps"] = float(result.energy_history[result.iterations])
    return {
        "input": {"path": job.input, "format": graph.source_format,
                  "dimension": "2D" if graph.is_2d else "3D", "poses": graph.num_nodes,
                  "relative_edges": graph.num_edges, "gps": graph.num_gps, "constraints": nc},
        "output": {"path": job.output, "format": out_fmt},
        "solver": job.solver,
        "init": init,
        "energy_before": result.initial_energy,
        "energy_after": result.final_energy,
        "energy_before_per_constraint": result.initial_energy / max(nc, 1),
        "energy_after_per_constraint": result.final_energy / max(nc, 1),
        **extra,
        "time_read": t_read,
        "time_write": t_write,
        "plots": written_plots,
        "covariance": None if cov is None else {"path": job.covariance,
                                                "poses": int(cov.shape[0])},
        "rerun": None if recorder is None else {"path": job.rerun,
                                                "iterations": recorder.frames},
        "result": summary,
    }


def write_plots(graph: PoseGraph, result: SolveResult, init: str, tree_kind: str,
                prefix: str, name: str) -> list[str]:
    """PREFIX_before.png (the solver's initial poses), PREFIX_after.png, PREFIX_energy.png."""
    from ..initialization import initial_locals
    from ..plot import energy_figure, graph_figure, height_scale, save_figure
    from ..tree import build_tree, global_poses

    tree = build_tree(graph, tree_kind)
    before = global_poses(tree, *initial_locals(graph, tree, init))
    before_title = {"tree": f"{name}: tree initialization", "file": f"{name}: file vertices"
                    }.get(init, f"{name}: {init} initialization")
    paths = [f"{prefix}_before.png", f"{prefix}_after.png", f"{prefix}_energy.png"]
    after = (result.rotations, result.translations)
    # one height exaggeration for both maps; each map its own colour scale (graph_figure's
    # default), so the after map shows its own residuals; titles carry E/c themselves
    z_scale = height_scale([before, after])
    figs = [
        graph_figure(graph, [before], z_scale=z_scale, titles=[before_title]),
        graph_figure(graph, [after], z_scale=z_scale, titles=[f"{name}: {result.method}"]),
        energy_figure({result.method: result}, title=f"{name}: energy per constraint"),
    ]
    for fig, path in zip(figs, paths, strict=True):
        save_figure(fig, path)
    return paths


def _describe_starts(cands: dict[str, Any]) -> str:
    """``chordal 8219.7 -> 6532.84 (polished), tree 3.3e+06 -> 1.1e+04 (0 sweeps)``."""
    parts = []
    for name, c in cands.items():
        if c.get("initial_energy") is None:
            parts.append(f"{name} failed ({c.get('error', '')})")
            continue
        text = f"{name} {c['initial_energy']:.6g} -> {c['energy_after_sweeps']:.6g} " \
               f"({c['sweeps']} sweeps)"
        if "final_energy" in c:
            text += f" -> {c['final_energy']:.6g} (polished)"
        parts.append(text)
    return ", ".join(parts)


def describe_outliers(o: dict[str, Any]) -> str:
    """The summary line of ``--robust auto`` (``stats["outliers"]``)."""
    if not o.get("inconsistent"):
        return (f"none found: the longest whitened error is {o['max_sigmas']:.3g} sigma"
                + (f" (GPS {o['max_gps_sigmas']:.3g})" if o.get("max_gps_sigmas") else "")
                + f"; an outlier is beyond {o['threshold_sigmas']:g}")
    k, g = o["rejected"], o["rejected_gps"]
    if not k and not g:
        return ("the least-squares optimum looked inconsistent, but the robust re-solve "
                "rejected nothing: least squares kept")
    parts = ([f"{k} relative"] if k else []) + ([f"{g} GPS"] if g else [])
    return (f"{k + g} rejected ({', '.join(parts)}): the result is the least-squares optimum "
            "without them and the energies are theirs (list: --json, --rejected-out)")


def print_summary(s: dict[str, Any]) -> None:
    """The human-readable summary on stdout."""
    r = s["result"]
    nc = s["input"]["constraints"]
    inp = s["input"]
    timings = r.get("timings", {})
    times = [f"read {s['time_read']:.2f} s"]
    times += [f"{k} {timings[k]:.2f} s"
              for k in ("compile", "analyze", "solve", "polish", "outliers")
              if k in timings]
    times.append(f"write {s['time_write']:.2f} s")
    iters = f"{r['iterations']} {'sweeps' if s['solver'] in ('hybrid', 'auto') else 'iterations'}"
    if "polish_iterations" in r:
        iters += f" + {r['polish_iterations']} polish iterations"
    rows = [
        ("input", f"{inp['path']} ({inp['format']}, {inp['dimension']}, {inp['poses']} poses, "
                  f"{inp['relative_edges']} relative constraints, {inp['gps']} GPS)"),
        ("solver", f"{r['method']}, init {s['init']}"
                   + (f", {r['step']} step" if "step" in r else "")
                   + (" (chosen by the pipeline)" if s["solver"] == "auto" else "")
                   + (f"; linear solver {r['linear_solver']}" if r.get("linear_solver")
                      else "")),
        ("iterations", f"{iters}: {r['message']}"),
        ("energy before", fmt_energy(s["energy_before"], nc)),
    ]
    if "reason" in s:
        rows.append(("starts", _describe_starts(r.get("candidates", {}))))
    if "energy_after_sweeps" in s:
        rows.append(("after sweeps", fmt_energy(s["energy_after_sweeps"], nc) + ", before the "
                                     "polish"))
    if "robust" in r:
        rows.append(("robust kernel", f"{r['robust']}, scale {r['robust_scale']:g}: the "
                                      "energies are E_rho = sum rho(chi2)"))
    rows += [
        ("energy after", fmt_energy(s["energy_after"], nc)),
    ]
    if isinstance(r.get("certificate"), dict):
        rows.append(("certificate", str(r["certificate"]["summary"])))
    if "plain_energy" in r:
        rows.append(("plain energy", fmt_energy(r["plain_energy"], nc) + " after (least "
                                     "squares, no kernel)"))
    if "outliers" in r:
        rows.append(("outliers", describe_outliers(r["outliers"])))
    rows.append(("time", ", ".join(times)))
    if "us_per_constraint_mean" in r:
        line = (f"{r['us_per_constraint_mean']:.3g} us mean, "
                f"{r.get('us_per_constraint_max_steady', float('nan')):.4g} us steady max, "
                f"{r['us_per_constraint_max']:.4g} us max measured")
        rows.append(("per constraint", line))
        if r.get("gps_batches"):
            rows.append(("GPS batches", f"{r['gps_batches']} updates, slowest "
                                        f"{r.get('ms_per_gps_batch_max_steady', float('nan')):.3g}"
                                        " ms (steady)"))
    rows.append(("output", f"{s['output']['path']} ({s['output']['format']})"))
    for path in s["plots"]:
        rows.append(("plot", path))
    if s.get("rerun"):
        rows.append(("rerun", f"{s['rerun']['path']} ({s['rerun']['iterations']} iterations "
                              "recorded; open with: rerun FILE)"))
    if s.get("covariance"):
        rows.append(("covariance", f"{s['covariance']['path']} ({s['covariance']['poses']} "
                                   "poses, 6x6 each, tangent order tx ty tz rx ry rz)"))
    print_table(rows)


def options_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Solver options the user gave (config field names), leaving the rest to the defaults."""
    opts: dict[str, Any] = {}
    for key in ("sweeps", "tau0", "tau_decay", "damping", "step", "tree", "gps_batch_size",
                "max_iterations", "init", "dmax", "correction", "correction_iterations"):
        value = getattr(args, key)
        if value is not None:
            opts[key] = value
    if args.tolerance is not None:
        opts["energy_tolerance"] = args.tolerance
    if args.polish:
        opts["polish"] = True
    if getattr(args, "monotone", False):
        opts["monotone"] = True
    if args.robust is not None:
        opts["robust"], scale = args.robust
        if scale is not None:
            opts["robust_scale"] = scale
    return opts


def run(args: argparse.Namespace) -> int:
    job = Job(input=args.file, output=args.output, solver=args.solver,
              options=options_from_args(args), fmt=args.format, out_format=args.out_format,
              plot_prefix=args.plot, skip_unknown=args.skip_unknown, quiet=args.quiet,
              covariance=args.covariance, covariance_poses=args.covariance_poses,
              rerun=args.rerun, rejected_out=args.rejected_out)
    summary = run_job(job)
    if args.json:
        print_json(summary)
    else:
        print_summary(summary)
    return 0
