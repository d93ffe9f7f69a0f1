"""``hybridpgo batch INPUTS... -o OUTDIR``: many optimizations on a Dask cluster.

Every input is optimized with every combination of the ``--grid`` options (a Cartesian
product), each as one Dask task that calls the library API (``hybridpgo.read_graph``,
``hybridpgo.optimize``, ``hybridpgo.write_graph``).  The tasks run on a ``LocalCluster`` of
worker processes (one per core) unless ``--scheduler`` names a running cluster.  One task's
failure (a malformed file, a solver error, a dead worker) is recorded in the summary and does
not stop the others.  The summary goes to ``OUTDIR/summary.csv`` and ``OUTDIR/summary.json``
(one row per job) and, as a table, to stdout; the exit status is 3 when a job failed (2: bad
arguments, nothing was run).

Needs the optional Dask: ``pip install hybridpgo[dask]``.
"""

from __future__ import annotations

import argparse
import csv
import io
import itertools
import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from ..errors import HybridPGOError
from ._common import ProgressBar, log, phase, print_json

#: Per-job summary columns, in CSV order.
COLUMNS = ("input", "options", "output", "status", "energy_before", "energy_after",
           "energy_per_constraint", "solver_status", "iterations", "time_s", "error")
#: Exit status when at least one job failed (the others' results and the summary are written);
#: distinct from 1 (a bug) and 2 (bad arguments: nothing was run).
EXIT_SOME_FAILED = 3


@dataclass(frozen=True)
class BatchJob:
    """One optimization of a batch (picklable: it travels to a Dask worker)."""

    input: str
    output: str
    method: str
    options: dict[str, Any] = field(default_factory=dict)


def run_job(job: BatchJob) -> dict[str, Any]:
    """Read, optimize and write one graph with the public API; never raises.

    Returns
    -------
    dict
        One summary row (:data:`COLUMNS`): ``status`` is ``"ok"`` or ``"failed"`` (then
        ``error`` holds ``ExceptionType: message``).
    """
    import hybridpgo

    row: dict[str, Any] = {"input": job.input, "options": dict(job.options),
                           "output": job.output, "status": "failed", "energy_before": None,
                           "energy_after": None, "energy_per_constraint": None,
                           "solver_status": None, "iterations": None, "time_s": None,
                           "error": ""}
    t0 = time.perf_counter()
    try:
        graph = hybridpgo.read_graph(job.input)
        result = hybridpgo.optimize(graph, job.method, **job.options)
        fmt = "g2o" if graph.source_format == "isam" else (graph.source_format or "g2o")
        hybridpgo.write_graph(graph.with_poses(result.rotations, result.translations),
                              job.output, fmt)
        row.update(status="ok", energy_before=result.initial_energy,
                   energy_after=result.final_energy,
                   energy_per_constraint=result.final_energy / max(graph.num_constraints, 1),
                   solver_status=result.status.value, iterations=result.iterations)
    except Exception as exc:  # one bad graph must not stop the batch: report it in its row
        row["error"] = f"{type(exc).__name__}: {exc}"
    row["time_s"] = time.perf_counter() - t0
    return row


# --------------------------------------------------------------------------- planning
def _value(text: str) -> Any:
    """A grid value: int, float, true/false, else the string."""
    low = text.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text.strip()


def parse_grid(specs: Sequence[str], method: str) -> list[dict[str, Any]]:
    """``["sweeps=10,40", "tau_decay=0.99"]`` -> every combination as option dicts.

    Keys are the solver's option names (``HybridConfig`` / ``GaussNewtonConfig`` fields;
    ``-`` may stand for ``_``); each combination is validated by building the config.

    Raises
    ------
    HybridPGOError
        A malformed item, an unknown or repeated key, or a value the solver rejects.
    """
    from ..solvers import config_for, option_names

    allowed = option_names(method)
    axes: dict[str, list[Any]] = {}
    for spec in specs:
        key, sep, values = spec.partition("=")
        key = key.strip().replace("-", "_")
        items = [v for v in values.split(",") if v.strip()]
        if not sep or not key or not items:
            raise HybridPGOError(f"--grid {spec!r}: expected KEY=V1,V2,... "
                                 "(e.g. --grid sweeps=10,40)")
        if key not in allowed:
            raise HybridPGOError(f"--grid {spec!r}: {key!r} is not an option of the {method} "
                                 f"solver; options: {', '.join(allowed)}")
        if key in axes:
            raise HybridPGOError(f"--grid {spec!r}: {key} is given twice; list every value "
                                 f"in one --grid {key}=V1,V2")
        axes[key] = [_value(v) for v in items]
    combos = [dict(zip(axes, values, strict=True)) for values in itertools.product(*axes.values())]
    for opts in combos:
        try:
            if method in ("auto", "hybrid"):
                config_for(method, **opts)
            else:
                config_for(method, **{k: v for k, v in opts.items() if k not in ("init", "tree")})
                if opts.get("init", "file") not in ("tree", "file", "chordal"):
                    raise ValueError(f"init must be 'tree', 'file' or 'chordal', got "
                                     f"{opts['init']!r}")
        except (TypeError, ValueError) as exc:
            raise HybridPGOError(f"--grid: invalid solver option: {exc}") from exc
    return combos


def _tag(options: dict[str, Any]) -> str:
    """``sweeps-10_tau_decay-0.9``: an option combination in a file name."""
    return "_".join(f"{k}-{v}" for k, v in options.items()).replace(os.sep, "-")


def plan_jobs(inputs: Sequence[str], out_dir: str, method: str,
              combos: list[dict[str, Any]]) -> list[BatchJob]:
    """One job per (input, option combination), with distinct output paths.

    Outputs are ``OUTDIR/<input stem>[__<options>]<ext>`` (iSAM inputs are written as g2o,
    since iSAM files hold no poses).

    Raises
    ------
    HybridPGOError
        An input does not exist, or two jobs would write the same file.
    """
    jobs: list[BatchJob] = []
    seen: dict[str, str] = {}
    for path in inputs:
        if not os.path.isfile(path):
            raise HybridPGOError(f"{path}: no such file")
        stem, ext = os.path.splitext(os.path.basename(path))
        if ext.lower() not in (".g2o", ".graph"):
            ext = ".g2o"
        for opts in combos:
            name = stem + (f"__{_tag(opts)}" if len(combos) > 1 or opts else "") + ext
            out = os.path.join(out_dir, name)
            if out in seen:
                raise HybridPGOError(f"{path} and {seen[out]} would both write {out}: give "
                                     "inputs different file names")
            if os.path.abspath(out) == os.path.abspath(path):
                raise HybridPGOError(f"{path}: the output would overwrite the input; choose "
                                     "another -o OUTDIR")
            seen[out] = path
            jobs.append(BatchJob(input=path, output=out, method=method, options=dict(opts)))
    return jobs


# --------------------------------------------------------------------------- running
def _require_distributed() -> Any:
    try:
        import distributed
    except ImportError as exc:
        raise HybridPGOError("hybridpgo batch needs Dask (dask.distributed), which is not "
                             "installed: pip install hybridpgo[dask]") from exc
    return distributed


def run_on_dask(jobs: Sequence[BatchJob], *, scheduler: str | None = None,
                workers: int | None = None, bar: ProgressBar | None = None
                ) -> list[dict[str, Any]]:
    """Run ``jobs`` on Dask; rows in the order of ``jobs``.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running scheduler (``tcp://host:8786``); default: a ``LocalCluster`` of
        ``workers`` single-threaded worker processes (default: one per core), closed afterwards.
    bar : ProgressBar, optional
        Advanced as jobs finish (in any order).
    """
    import logging

    distributed = _require_distributed()
    cluster = None
    with phase("starting Dask" if scheduler is None else f"connecting to {scheduler}",
               enabled=bar is not None and bar.enabled):
        if scheduler is None:
            n = workers or os.cpu_count() or 1
            cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1,
                                               processes=True, dashboard_address=None,
                                               silence_logs=logging.ERROR)
        try:
            client = distributed.Client(cluster if cluster is not None else scheduler,
                                        timeout="30s")
        except (OSError, TimeoutError) as exc:
            if cluster is not None:
                cluster.close()
            raise HybridPGOError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from exc
    rows: list[dict[str, Any] | None] = [None] * len(jobs)
    failed = 0
    if bar is not None:
        bar.update(0, None)  # the rate counts from here, not from the cluster's start
    try:
        futures = client.map(run_job, list(jobs), pure=False)
        index = {f.key: k for k, f in enumerate(futures)}
        for done, future in enumerate(distributed.as_completed(futures), start=1):
            k = index[future.key]
            try:
                row = future.result()
            except Exception as exc:  # the task itself died (e.g. its worker was killed)
                row = run_job_failed(jobs[k], exc)
            rows[k] = row
            failed += row["status"] != "ok"
            if bar is not None:
                bar.update(done, None, note=f"{failed} failed" if failed else "")
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return [r for r in rows if r is not None]


def run_job_failed(job: BatchJob, exc: BaseException) -> dict[str, Any]:
    """The row of a job whose task did not return (its worker died, it was cancelled)."""
    return {"input": job.input, "options": dict(job.options), "output": job.output,
            "status": "failed", "energy_before": None, "energy_after": None,
            "energy_per_constraint": None, "solver_status": None, "iterations": None,
            "time_s": None, "error": f"{type(exc).__name__}: {exc}"}


# --------------------------------------------------------------------------- summary
def _csv_text(rows: Sequence[dict[str, Any]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        cells = []
        for col in COLUMNS:
            value = row[col]
            if col == "options":
                value = " ".join(f"{k}={v}" for k, v in value.items())
            elif isinstance(value, float):
                value = repr(value)
            cells.append("" if value is None else value)
        writer.writerow(cells)
    return buf.getvalue()


def write_summary(rows: Sequence[dict[str, Any]], out_dir: str) -> list[str]:
    """``OUTDIR/summary.csv`` and ``OUTDIR/summary.json``, each written atomically."""
    from ..io._lines import write_atomic
    from ._common import _clean

    csv_path = os.path.join(out_dir, "summary.csv")
    json_path = os.path.join(out_dir, "summary.json")
    write_atomic(csv_path, lambda: [_csv_text(rows)])
    write_atomic(json_path, lambda: [json.dumps(_clean({"jobs": list(rows)}), indent=2) + "\n"])
    return [csv_path, json_path]


def print_summary(rows: Sequence[dict[str, Any]]) -> None:
    """An aligned table on stdout, one line per job."""
    table = [("input", "options", "status", "E/c", "time s", "error")]
    for r in rows:
        opts = " ".join(f"{k}={v}" for k, v in r["options"].items()) or "-"
        per = "-" if r["energy_per_constraint"] is None else f"{r['energy_per_constraint']:.4g}"
        secs = "-" if r["time_s"] is None else f"{r['time_s']:.2f}"
        table.append((os.path.basename(r["input"]), opts, r["status"], per, secs,
                      r["error"][:60]))
    widths = [max(len(row[c]) for row in table) for c in range(len(table[0]))]
    for row in table:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())


def run(args: argparse.Namespace) -> int:
    _require_distributed()  # before any work: a missing extra is a one-line error
    if args.scheduler is not None and args.workers is not None:
        raise HybridPGOError("--workers sizes the local cluster; a running one (--scheduler) "
                             "has its own workers")
    combos = parse_grid(args.grid or [], args.solver)
    out_dir = args.output_dir
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise HybridPGOError(f"{out_dir}: exists and is not a directory")
    jobs = plan_jobs(args.inputs, out_dir, args.solver, combos)
    parent = os.path.dirname(os.path.abspath(out_dir))
    if not os.path.isdir(parent):
        raise HybridPGOError(f"{out_dir}: cannot create: directory {parent} does not exist")
    os.makedirs(out_dir, exist_ok=True)
    if not args.quiet:
        log(f"{len(jobs)} job(s): {len(args.inputs)} input(s) x {len(combos)} option "
            f"combination(s), solver {args.solver}")
    bar = ProgressBar("batch", len(jobs), 0, enabled=not args.quiet, unit="job")
    try:
        rows = run_on_dask(jobs, scheduler=args.scheduler, workers=args.workers, bar=bar)
    finally:
        bar.close()
    paths = write_summary(rows, out_dir)
    if args.json:
        print_json({"jobs": rows, "summary": paths})
    else:
        print_summary(rows)
        for p in paths:
            print(f"wrote {p}")
    return EXIT_SOME_FAILED if any(r["status"] != "ok" for r in rows) else 0
