"""Scale: generated cities of 100k and 1M poses, with and without GPS (issue 11 item 6).

Each case runs in its own process (``python -m benchmarks.scale N GPS_EVERY``) so its peak
memory is that process's ``ru_maxrss`` (numpy's buffers included, which tracemalloc misses).
Phases, timed separately, in order:

* ``generate``: ``generate_city(**scale_city(None, N))`` (not part of a user's pipeline);
* ``write_input``: the g2o file written (the input a user would have);
* ``read``: ``read_graph`` of that file;
* ``sweep``: one hybrid sweep from the tree initialization (``HybridConfig(sweeps=1)``), with
  its ``analyze`` (tree, problem set-up) and ``solve`` parts;
* ``pipeline``: the default-like pipeline of the demo: 10 sweeps, then the exact polish (LM)
  to convergence (``HybridConfig(sweeps=10, polish=True)``), skipped with ``--no-pipeline``;
* ``write``: the optimized graph written as g2o.

Kernels are compiled (or loaded) before the clock starts.  The peak memory after each phase is
recorded (it only grows).  Targets (issue 11): one sweep <= 10 s, pipeline <= 5 min, peak
<= 4 GB at 1M poses.

Run: ``PYTHONPATH=src python -m benchmarks --only scale --run <name>`` (``--quick``: 20k and
100k poses only).
"""

from __future__ import annotations

import json
import os
import pathlib
import resource
import subprocess
import sys
import tempfile
import time
from typing import Any

from .metrics import Metric, info, markdown_table, timing

#: (poses, gps_every) of the full run; --quick runs the first two sizes only.
CASES = ((100_000, 0), (100_000, 100), (1_000_000, 0), (1_000_000, 100))
QUICK_CASES = ((20_000, 0), (20_000, 100))
#: A case that has not finished after this many seconds is reported as timed out.
TIMEOUT_S = 3600.0
#: Targets at 1M poses (issue 11 item 6).
TARGET_SWEEP_S, TARGET_PIPELINE_S, TARGET_PEAK_GB = 10.0, 300.0, 4.0


def _peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def run_case(poses: int, gps_every: int, pipeline: bool = True) -> dict[str, Any]:
    """One case in this process; returns the phase times (s) and peaks (GB)."""
    from hybridpgo.generate import generate_city
    from hybridpgo.generate.city import scale_city
    from hybridpgo.io import read_graph, write_graph
    from hybridpgo.solvers import HybridConfig, optimize
    from hybridpgo.solvers.gauss_newton import _ensure_compiled
    from hybridpgo.solvers.hybrid.solver import ensure_compiled

    out: dict[str, Any] = {"poses": poses, "gps_every": gps_every, "times": {}, "peak_gb": {}}
    t0 = time.perf_counter()
    ensure_compiled()
    _ensure_compiled()
    out["compile_or_load_s"] = time.perf_counter() - t0
    out["peak_gb"]["start"] = _peak_gb()

    def phase(name: str, t_start: float) -> None:
        out["times"][name] = time.perf_counter() - t_start
        out["peak_gb"][name] = _peak_gb()
        print(f"  {poses} gps {gps_every}: {name} {out['times'][name]:.2f} s, peak "
              f"{out['peak_gb'][name]:.2f} GB", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="hybridpgo-scale-") as tmp:
        path = pathlib.Path(tmp) / "city.g2o"
        t = time.perf_counter()
        city = generate_city(seed=0, gps_every=gps_every, **scale_city(None, poses))
        phase("generate", t)
        t = time.perf_counter()
        write_graph(city.graph, path)
        phase("write_input", t)
        del city
        out["file_mb"] = path.stat().st_size / 2**20
        t = time.perf_counter()
        graph = read_graph(path)
        phase("read", t)
        out["constraints"] = graph.num_constraints
        out["gps"] = graph.num_gps
        t = time.perf_counter()
        res = optimize(graph, HybridConfig(sweeps=1))
        phase("sweep", t)
        out["sweep_parts"] = {k: float(v) for k, v in res.timings.items()}
        out["energy_start"] = float(res.energy_history[0])
        out["energy_sweep"] = float(res.energy_history[-1])
        final = res
        if pipeline:
            del res
            t = time.perf_counter()
            final = optimize(graph, HybridConfig(sweeps=10, polish=True))
            phase("pipeline", t)
            out["pipeline_parts"] = {k: float(v) for k, v in final.timings.items()}
            out["energy_pipeline"] = float(final.energy_history[-1])
            out["pipeline_status"] = final.status.value
            out["polish_iterations"] = int(final.stats.get("polish_iterations", -1))
        t = time.perf_counter()
        write_graph(graph.with_poses(final.rotations, final.translations),
                    pathlib.Path(tmp) / "out.g2o")
        phase("write", t)
    return out


def _subprocess_case(poses: int, gps_every: int, pipeline: bool) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "benchmarks.scale", str(poses), str(gps_every)]
    if not pipeline:
        cmd.append("--no-pipeline")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S,
                              env=dict(os.environ))
    except subprocess.TimeoutExpired:
        return {"poses": poses, "gps_every": gps_every, "error": f"timeout {TIMEOUT_S:.0f} s"}
    sys.stderr.write(proc.stderr)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"poses": poses, "gps_every": gps_every,
                "error": f"exit {proc.returncode}: {last}",
                "wall_s": time.perf_counter() - t0}
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def run(ctx: Any) -> tuple[list[Metric], list[str]]:
    cases = QUICK_CASES if ctx.quick else CASES
    metrics: list[Metric] = []
    rows = []
    for poses, gps in cases:
        r = _subprocess_case(poses, gps, pipeline=True)
        key = f"scale.{poses // 1000}k.{'gps' if gps else 'nogps'}"
        if "error" in r:
            rows.append([f"{poses:,}", "yes" if gps else "no", r["error"], "", "", "", "", "",
                         "", ""])
            continue
        tm, pk = r["times"], r["peak_gb"]
        for name, value in tm.items():
            metrics.append(timing(f"{key}.{name}_s", value))
        metrics.append(Metric(f"{key}.peak_gb", max(pk.values()), "GB", "lower", rel_tol=0.25))
        metrics.append(info(f"{key}.energy_sweep_per_constraint",
                            r["energy_sweep"] / r["constraints"]))
        if "energy_pipeline" in r:
            metrics.append(info(f"{key}.energy_pipeline_per_constraint",
                                r["energy_pipeline"] / r["constraints"]))
        sweep_solve = r["sweep_parts"].get("solve", float("nan"))
        rows.append([
            f"{poses:,}", "yes" if gps else "no", f"{r['constraints']:,} + {r['gps']:,} GPS",
            f"{tm['read']:.1f}", f"{tm['sweep']:.1f} ({sweep_solve:.1f})",
            f"{tm.get('pipeline', float('nan')):.0f}",
            f"{r.get('polish_iterations', '')}", f"{tm['write']:.1f}",
            f"{max(pk.values()):.2f}", f"{r['energy_sweep'] / r['constraints']:.3g} / "
            f"{r.get('energy_pipeline', float('nan')) / r['constraints']:.4g}",
        ])
    header = ["poses", "GPS", "constraints", "read s", "1 sweep s (solve)", "pipeline s",
              "polish its", "write s", "peak GB", "E/c sweep / pipeline"]
    table = markdown_table("Scale: generated cities", header, rows)
    note = (f"Targets at 1M poses: one sweep <= {TARGET_SWEEP_S:.0f} s, pipeline (10 sweeps + "
            f"polish) <= {TARGET_PIPELINE_S:.0f} s, peak <= {TARGET_PEAK_GB:.0f} GB.  Each case "
            "in its own process; peak = ru_maxrss.  1 sweep = analyze (tree, set-up) + solve.")
    return metrics, [table + "\n" + note + "\n"]


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    result = run_case(int(args[0]), int(args[1]), pipeline="--no-pipeline" not in sys.argv)
    print(json.dumps(result))
