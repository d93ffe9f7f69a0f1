"""Where one hybrid sweep's time goes: ``python -m benchmarks.sweep_phases GRAPH.g2o``.

Runs ``optimize(graph, HybridConfig(sweeps=1))`` (as the scale benchmark's ``sweep`` phase)
with the solver's callees wrapped by timers and prints one JSON line: wall and CPU time of the
whole call, the solver's ``analyze``/``solve`` timings, and the seconds spent in the tree, the
initial locals, the whitening, the 𝔅(H) initialization, the sweep kernel, the global poses and
the energies; the peak RSS (VmHWM) of the call; the load average before and after.  Kernels are
compiled (or loaded) before the clock starts.
"""

from __future__ import annotations

import collections
import json
import os
import sys
import time
from typing import Any


def _vm_hwm_gb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 2**20
    return float("nan")


def main(path: str) -> dict[str, Any]:
    from hybridpgo.io import read_graph
    from hybridpgo.solvers import HybridConfig, optimize
    from hybridpgo.solvers.hybrid import solver as hs

    t = time.perf_counter()
    graph = read_graph(path)
    out: dict[str, Any] = {"file": path, "read_s": time.perf_counter() - t}
    t = time.perf_counter()
    hs.ensure_compiled(graph.num_gps > 0)
    out["compile_s"] = time.perf_counter() - t
    spent: dict[str, float] = collections.defaultdict(float)

    def wrap(owner: Any, name: str, label: str) -> None:
        func = getattr(owner, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return func(*args, **kwargs)
            finally:
                spent[label] += time.perf_counter() - t0

        setattr(owner, name, timed)

    for owner, name, label in (
        (hs, "build_tree", "tree"), (hs, "initial_locals", "init_locals"),
        (hs, "_whitening", "whitening"), (hs.HybridSolver, "rebuild_blocks", "init_blocks"),
        (hs.HybridSolver, "_sweep", "sweep_kernel"), (hs, "global_poses", "global_poses"),
        (hs, "energy", "energy"),
    ):
        if hasattr(owner, name):
            wrap(owner, name, label)
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass
    load0 = os.getloadavg()[0]
    c0 = time.process_time()
    t = time.perf_counter()
    res = optimize(graph, HybridConfig(sweeps=1))
    out["total_s"] = time.perf_counter() - t
    out["cpu_s"] = time.process_time() - c0
    out["load"] = [load0, os.getloadavg()[0]]
    out["analyze_s"] = res.timings["analyze"]
    out["solve_s"] = res.timings["solve"]
    out.update({f"{k}_s": v for k, v in spent.items()})
    out["peak_gb"] = _vm_hwm_gb()
    out["energy_start"] = float(res.energy_history[0])
    out["energy_sweep"] = float(res.energy_history[-1])
    return out


if __name__ == "__main__":
    print(json.dumps({k: round(v, 3) if isinstance(v, float) else v
                      for k, v in main(sys.argv[1]).items()}))
