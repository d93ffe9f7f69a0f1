"""Scale: generated cities of 100k and 1M poses, with and without GPS.

Each case is generated in one process (``python -m benchmarks.scale generate N GPS PATH``) and
solved in another (``python -m benchmarks.scale solve PATH``), so the solver's peak memory is
that process's ``ru_maxrss`` (numpy's buffers included, which tracemalloc misses).
Phases, timed separately, in order:

* ``generate`` (its own process, its own peak): ``generate_city(**scale_city(None, N))`` and
  the g2o file written (the input a user would have);
* ``read``: ``read_graph`` of that file;
* ``pipeline``: the default pipeline, ``optimize(graph)`` (``--solver auto``, AutoConfig()):
  the full policy below ``AutoConfig.large_poses`` poses, the large-graph policy (one start,
  at most ``large_max_sweeps`` sweeps, one polish) from there on; skipped with
  ``--no-pipeline``;
* ``pipeline_other`` (cases below ``large_poses`` only, ``--compare``): the large-graph policy
  forced on the same graph, to measure what it costs in energy against the full one;
* ``sweep``: one hybrid sweep from the tree initialization, ``optimize(graph,
  HybridConfig(sweeps=1))``, timed as a whole and in parts: ``setup`` (the solver's
  ``analyze``: tree, initial locals, problem arrays, 𝔅(H) with every constraint's blocks --
  once per solve), ``kernel`` (the sweep itself, ``solve``), ``energies`` (the rest: the start
  and end energies with their global poses, the result);
* ``sweep_gpstree`` (graphs with GPS): the same with ``tree="gps"`` (every GPS pose a child of
  the earth: GPS domains of one pose, so far fewer per-path blocks);
* ``write``: the optimized graph written as g2o.

Kernels are compiled (or loaded) before the clock starts.  Each phase's own peak memory is
recorded (Linux: VmHWM, reset between phases through ``/proc/self/clear_refs``); the pipeline
runs before the sweep, whose hybrid solver keeps a 6x6 block per constraint-path entry.
Targets: one sweep <= 10 s, pipeline <= 5 min, peak
<= 4 GB at 1M poses.

Run: ``PYTHONPATH=src python -m benchmarks --only scale --run <name>`` (``--quick``: 20k
poses only).  ``HYBRIDPGO_SCALE_PHASES="sweep"`` (a comma list of ``pipeline``, ``sweep``;
default both) runs only those solving phases (read and write always run).  Every phase also
records its CPU time and the load average before and after it (the machine is shared: wall
times under load are 2-3x the CPU times of these single-threaded phases).
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
#: The one-sweep phase is skipped (and said so) when the hybrid solver's per-path 6x6 blocks
#: alone would need more than this (measured: a 1M-pose city with GPS grew past 17 GB).
SWEEP_BLOCKS_LIMIT_GB = 6.0
#: Targets at 1M poses.
TARGET_SWEEP_S, TARGET_PIPELINE_S, TARGET_PEAK_GB = 10.0, 300.0, 4.0


def _peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def _reset_phase_peak() -> None:
    """Linux: reset the process's peak RSS (VmHWM), so each phase reports its own peak."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass


def _phase_peak_gb() -> float:
    """Peak RSS since the last :func:`_reset_phase_peak` (VmHWM; else the process's peak)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return _peak_gb()


def generate_case(poses: int, gps_every: int, path: pathlib.Path) -> dict[str, Any]:
    """Generate the city and write it as g2o (in its own process: the generator's memory is not
    the solver's)."""
    from hybridpgo.generate import generate_city
    from hybridpgo.generate.city import scale_city
    from hybridpgo.io import write_graph

    out: dict[str, Any] = {"times": {}}
    t = time.perf_counter()
    city = generate_city(seed=0, gps_every=gps_every, **scale_city(None, poses))
    out["times"]["generate"] = time.perf_counter() - t
    t = time.perf_counter()
    write_graph(city.graph, path)
    out["times"]["write_input"] = time.perf_counter() - t
    out["peak_gb"] = _peak_gb()
    out["file_mb"] = path.stat().st_size / 2**20
    return out


def _phases() -> set[str]:
    """The solving phases to run: ``HYBRIDPGO_SCALE_PHASES`` (default all three)."""
    spec = os.environ.get("HYBRIDPGO_SCALE_PHASES", "pipeline,sweep,sweep_gpstree")
    phases = {p.strip() for p in spec.split(",") if p.strip()}
    unknown = phases - {"pipeline", "sweep", "sweep_gpstree"}
    if unknown:
        raise ValueError(f"HYBRIDPGO_SCALE_PHASES: unknown phase(s) {sorted(unknown)}")
    return phases


def solve_case(path: pathlib.Path, pipeline: bool = True,
               compare: bool = True) -> dict[str, Any]:
    """Read, one sweep, the pipeline, write: the phase times (s) and the peak (GB) after each."""
    from hybridpgo.io import read_graph, write_graph
    from hybridpgo.solvers import AutoConfig, optimize
    from hybridpgo.solvers.gauss_newton import ensure_compiled as ensure_exact
    from hybridpgo.solvers.hybrid.solver import ensure_compiled

    out: dict[str, Any] = {"times": {}, "peak_gb": {}}
    t0 = time.perf_counter()
    ensure_compiled()
    ensure_exact()
    out["compile_or_load_s"] = time.perf_counter() - t0
    out["peak_gb"]["start"] = _peak_gb()

    out["cpu_s"] = {}
    out["load"] = {}
    cpu = [time.process_time()]
    load = [os.getloadavg()[0]]

    def phase(name: str, t_start: float) -> None:
        out["times"][name] = time.perf_counter() - t_start
        out["peak_gb"][name] = _phase_peak_gb()
        out["cpu_s"][name] = time.process_time() - cpu[0]
        out["load"][name] = [load[0], os.getloadavg()[0]]
        print(f"  {path.name}: {name} {out['times'][name]:.2f} s (CPU "
              f"{out['cpu_s'][name]:.2f} s, load {load[0]:.1f} -> {out['load'][name][1]:.1f}), "
              f"peak {out['peak_gb'][name]:.2f} GB", file=sys.stderr, flush=True)
        _reset_phase_peak()
        cpu[0] = time.process_time()
        load[0] = os.getloadavg()[0]

    _reset_phase_peak()
    t = time.perf_counter()
    graph = read_graph(path)
    phase("read", t)
    out["constraints"] = graph.num_constraints
    out["gps"] = graph.num_gps
    t = time.perf_counter()
    ensure_compiled(graph.num_gps > 0)  # the GPS sweep variant, before the clocks
    out["compile_or_load_s"] += time.perf_counter() - t
    _reset_phase_peak()
    cpu[0] = time.process_time()
    load[0] = os.getloadavg()[0]
    rot = trans = None
    phases = _phases()
    pipeline = pipeline and "pipeline" in phases
    if pipeline:  # first: the sweep's per-path blocks are the hybrid solver's, not the pipeline's
        t = time.perf_counter()
        final = optimize(graph)  # the default: --solver auto
        phase("pipeline", t)
        out.update(_pipeline_summary(final, "pipeline"))
        rot, trans = final.rotations, final.translations
        del final
        if compare and not AutoConfig().is_large(graph.num_nodes):
            t = time.perf_counter()
            other = optimize(graph, AutoConfig(large_poses=2))
            phase("pipeline_other", t)
            out.update(_pipeline_summary(other, "pipeline_other"))
            del other
    from hybridpgo.tree import build_tree

    tree = build_tree(graph, "bfs")
    lengths = tree.path_lengths()
    out["tree"] = {"tree_max_depth": float(tree.max_depth),
                   "path_length_max": float(lengths.max()),
                   "path_length_mean": float(lengths.mean())}
    entries = int(tree.path_ptr[-1])
    del tree, lengths
    out["sweep_block_gb"] = entries * 36 * 8 / 2**30  # the hybrid solver's per-path 6x6 blocks
    if "sweep" in phases and out["sweep_block_gb"] > SWEEP_BLOCKS_LIMIT_GB:
        # would swap or be killed: not run
        print(f"  {path.name}: sweep skipped: the hybrid solver's per-path blocks alone "
              f"need {out['sweep_block_gb']:.1f} GB", file=sys.stderr, flush=True)
    elif "sweep" in phases:
        rot, trans = _sweep_phase(graph, "bfs", "sweep", phase, out, rot, trans)
    if "sweep_gpstree" in phases and graph.num_gps:
        rot, trans = _sweep_phase(graph, "gps", "sweep_gpstree", phase, out, rot, trans)
    if rot is None:
        rot, trans = graph.rotations, graph.translations
    t = time.perf_counter()
    write_graph(graph.with_poses(rot, trans), path.with_name(path.stem + "_out.g2o"))
    phase("write", t)
    return out


def _sweep_phase(graph: Any, tree: str, name: str, phase: Any, out: dict[str, Any],
                 rot: Any, trans: Any) -> tuple[Any, Any]:
    """One hybrid sweep from the tree start (``optimize(graph, HybridConfig(sweeps=1,
    tree=tree))``): its time in parts, its energies; returns the poses to write."""
    from hybridpgo.solvers import HybridConfig, optimize

    t = time.perf_counter()
    res = optimize(graph, HybridConfig(sweeps=1, tree=tree))  # type: ignore[arg-type]
    phase(name, t)
    parts = {k: float(v) for k, v in res.timings.items()}
    parts["setup"] = float(res.timings["analyze"])
    parts["kernel"] = float(res.timings["solve"])
    parts["energies"] = (out["times"][name] - res.timings["analyze"] - res.timings["solve"]
                         - res.timings.get("compile", 0.0))
    suffix = "" if name == "sweep" else "_" + name
    out["sweep_parts" + suffix] = parts
    out["energy_start" + suffix] = float(res.energy_history[0])
    out["energy_sweep" + suffix] = float(res.energy_history[-1])
    out["sweep_blocks" + suffix] = int(res.stats["path_length_mean"] * res.num_constraints)
    if rot is None:
        return res.rotations, res.translations
    return rot, trans


def _pipeline_summary(res: Any, key: str) -> dict[str, Any]:
    """What a pipeline run did: policy, start, sweeps, polish, energies, time per part."""
    return {
        f"{key}_parts": {k: float(v) for k, v in res.timings.items()},
        f"energy_{key}": float(res.energy_history[-1]),
        f"{key}_status": res.status.value,
        f"{key}_policy": res.stats.get("policy", ""),
        f"{key}_init": res.stats.get("init", ""),
        f"{key}_sweeps": int(res.stats.get("sweeps", 0)),
        f"{key}_polish_iterations": int(res.stats.get("polish_iterations", -1)),
        f"{key}_reason": res.stats.get("reason", ""),
        f"{key}_candidates": {
            label: {k: c.get(k) for k in ("initial_energy", "energy_after_sweeps",
                                           "final_energy", "sweeps", "polish_iterations",
                                           "start_seconds", "sweep_seconds", "polish_seconds")}
            for label, c in res.stats.get("candidates", {}).items()},
    }


def _child(args: list[str]) -> dict[str, Any]:
    """Run ``python -m benchmarks.scale ARGS``; its last stdout line is JSON."""
    # stderr is inherited: the phase lines show up as they happen (a killed case keeps them)
    proc = subprocess.run([sys.executable, "-m", "benchmarks.scale", *args],
                          stdout=subprocess.PIPE, text=True, timeout=TIMEOUT_S,
                          env=dict(os.environ))
    if proc.returncode != 0:
        raise RuntimeError(f"exit {proc.returncode} (its stderr is above)")
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def _subprocess_case(poses: int, gps_every: int, pipeline: bool) -> dict[str, Any]:
    out: dict[str, Any] = {"poses": poses, "gps_every": gps_every}
    with tempfile.TemporaryDirectory(prefix="hybridpgo-scale-") as tmp:
        path = pathlib.Path(tmp) / f"city{poses}_gps{gps_every}.g2o"
        try:
            gen = _child(["generate", str(poses), str(gps_every), str(path)])
            out["generate"] = gen
            out.update(_child(["solve", str(path)] + ([] if pipeline else ["--no-pipeline"])))
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            out["error"] = str(exc)
    return out


def _cases(quick: bool) -> tuple[tuple[int, int], ...]:
    """``HYBRIDPGO_SCALE_CASES="100000:0,1000000:100"`` (poses:gps_every) overrides the list."""
    spec = os.environ.get("HYBRIDPGO_SCALE_CASES")
    if spec:
        return tuple((int(a), int(b)) for a, b in (c.split(":") for c in spec.split(",")))
    return QUICK_CASES if quick else CASES


def run(ctx: Any) -> tuple[list[Metric], list[str]]:
    cases = _cases(ctx.quick)
    metrics: list[Metric] = []
    rows = []
    compare_rows: list[list[str]] = []
    for poses, gps in cases:
        r = _subprocess_case(poses, gps, pipeline=True)
        key = f"scale.{poses // 1000}k.{'gps' if gps else 'nogps'}"
        if "error" in r:
            rows.append([f"{poses:,}", "yes" if gps else "no", r["error"]] + [""] * 11)
            continue
        tm, pk = r["times"], r["peak_gb"]
        for name, value in tm.items():
            metrics.append(timing(f"{key}.{name}_s", value))
        metrics.append(Metric(f"{key}.peak_gb", max(pk.values()), "GB", "lower", rel_tol=0.25))
        if "pipeline" in pk:
            metrics.append(info(f"{key}.pipeline_peak_gb", pk["pipeline"], "GB"))
        metrics.append(info(f"{key}.path_length_mean", r["tree"]["path_length_mean"]))
        e_sweep = r.get("energy_sweep", float("nan"))
        metrics.append(info(f"{key}.energy_sweep_per_constraint", e_sweep / r["constraints"]))
        if "energy_pipeline" in r:
            metrics.append(info(f"{key}.energy_pipeline_per_constraint",
                                r["energy_pipeline"] / r["constraints"]))
        if "energy_pipeline_other" in r:
            ratio = r["energy_pipeline_other"] / r["energy_pipeline"]
            metrics.append(info(f"{key}.large_policy_energy_ratio", ratio))
            compare_rows.append([
                f"{poses:,}", "yes" if gps else "no",
                f"{tm['pipeline']:.0f} ({r['pipeline_init']}, {r['pipeline_sweeps']} sweeps, "
                f"{r['pipeline_polish_iterations']} LM)",
                f"{tm['pipeline_other']:.0f} ({r['pipeline_other_init']}, "
                f"{r['pipeline_other_sweeps']} sweeps, {r['pipeline_other_polish_iterations']} "
                "LM)",
                f"{r['energy_pipeline'] / r['constraints']:.10g}",
                f"{r['energy_pipeline_other'] / r['constraints']:.10g}", f"{ratio - 1.0:+.2e}"])
        parts = r.get("sweep_parts", {})
        nan = float("nan")
        for part in ("setup", "kernel", "energies", "compile"):
            if part in parts:
                metrics.append(info(f"{key}.sweep_{part}_s", parts[part], "s"))
        compiled = parts.get("compile", 0.0)  # kernels compiled, not loaded (a fresh cache)
        cpu = r.get("cpu_s", {})
        if "sweep" in cpu:
            metrics.append(info(f"{key}.sweep_cpu_s", cpu["sweep"], "s"))
        sweep_cell = (
            f"{tm['sweep']:.1f} = {parts.get('setup', nan):.1f} + {parts.get('kernel', nan):.1f}"
            f" + {parts.get('energies', nan):.1f}"
            + (f" + {compiled:.1f} compiling" if compiled >= 0.05 else "")
            + f" (CPU {cpu.get('sweep', nan):.1f}; load "
            f"{r.get('load', {}).get('sweep', [nan])[0]:.1f})" if "sweep" in tm
            else f"skipped: {r['sweep_block_gb']:.0f} GB of blocks"
            if r["sweep_block_gb"] > SWEEP_BLOCKS_LIMIT_GB else "not run")
        gen = r["generate"]
        metrics.append(info(f"{key}.generate_s", gen["times"]["generate"], "s"))
        metrics.append(info(f"{key}.generate_peak_gb", gen["peak_gb"], "GB"))
        gps_tree_cell = "-"
        if "sweep_gpstree" in tm:
            gparts = r["sweep_parts_sweep_gpstree"]
            gps_tree_cell = (
                f"{tm['sweep_gpstree']:.1f} = {gparts['setup']:.1f} + {gparts['kernel']:.1f} + "
                f"{gparts['energies']:.1f} (CPU {cpu['sweep_gpstree']:.1f}) / "
                f"{pk['sweep_gpstree']:.2f} GB / E/c "
                f"{r['energy_sweep_sweep_gpstree'] / r['constraints']:.3g}")
            metrics.append(info(f"{key}.sweep_gpstree_s", tm["sweep_gpstree"], "s"))
            metrics.append(info(f"{key}.sweep_gpstree_peak_gb", pk["sweep_gpstree"], "GB"))
        rows.append([
            f"{poses:,}", "yes" if gps else "no", f"{r['constraints']:,} + {r['gps']:,} GPS",
            f"{gen['times']['generate']:.0f} / {gen['peak_gb']:.2f}",
            f"{r['tree']['tree_max_depth']:.0f} / {r['tree']['path_length_mean']:.1f}",
            f"{tm['read']:.1f}", sweep_cell, gps_tree_cell,
            f"{tm.get('pipeline', float('nan')):.0f}",
            f"{r['pipeline_policy']}: {r['pipeline_init']}, {r['pipeline_sweeps']} sweeps, "
            f"{r['pipeline_polish_iterations']} LM {r['pipeline_status']}"
            if "pipeline" in tm else "not run",
            f"{tm['write']:.1f}",
            f"{pk['read']:.2f} / {pk.get('pipeline', float('nan')):.2f} / "
            f"{pk.get('sweep', float('nan')):.2f} / {pk['write']:.2f}",
            f"{e_sweep / r['constraints']:.3g} / "
            f"{r.get('energy_pipeline', float('nan')) / r['constraints']:.4g}",
        ])
    header = ["poses", "GPS", "constraints", "generate s / GB", "tree depth / mean path",
              "read s", "1 sweep s = setup + kernel + energies",
              "1 sweep, tree=gps: s / peak / E/c", "pipeline s",
              "pipeline: policy, start, sweeps, LM",
              "write s", "peak GB read / pipeline / sweep / write", "E/c sweep / pipeline"]
    table = markdown_table("Scale: generated cities", header, rows)
    note = (f"Targets at 1M poses: one sweep <= {TARGET_SWEEP_S:.0f} s, default pipeline "
            f"(`optimize(graph)`, --solver auto) <= {TARGET_PIPELINE_S:.0f} s, peak <= "
            f"{TARGET_PEAK_GB:.0f} GB.  Each case solved in its own process (generated and written "
            "by another); peak = the phase's own peak RSS (VmHWM) in the solving process.  "
            "1 sweep = `optimize(graph, HybridConfig(sweeps=1))` from the tree start: setup "
            "(tree, locals, problem, 𝔅(H) and every constraint's blocks; once per solve) + the "
            "sweep kernel + energies (start and end energy, result poses); its CPU time and "
            "the load average when it started in brackets.")
    out = [table + "\n" + note + "\n"]
    if compare_rows:
        out.append(markdown_table(
            "Large-graph policy vs the full one (below AutoConfig.large_poses)",
            ["poses", "GPS", "full policy s", "large policy forced s", "E/c full",
             "E/c large", "E large / E full - 1"], compare_rows))
    return metrics, out


if __name__ == "__main__":
    argv = [a for a in sys.argv[1:] if not a.startswith("--")]
    if argv[0] == "generate":
        result = generate_case(int(argv[1]), int(argv[2]), pathlib.Path(argv[3]))
    else:
        result = solve_case(pathlib.Path(argv[1]), pipeline="--no-pipeline" not in sys.argv,
                            compare="--no-compare" not in sys.argv)
    print(json.dumps(result))
