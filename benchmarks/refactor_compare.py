"""Update time and cold compile time of two source trees, interleaved in one run.

``python -m benchmarks.refactor_compare BEFORE_SRC AFTER_SRC [--repeats 3]`` runs each measurement
in a fresh subprocess per tree (``PYTHONPATH`` = that tree's ``src``), alternating trees, and prints
a JSON line per measurement plus the after/before ratios of the medians.
* compile: cold compile of every kernel a hybrid solve and an exact solve use (a fresh
  ``NUMBA_CACHE_DIR``), seconds;
* update: mean and steady-max time per constraint update of 10 sweeps on M3500_isam.txt (warm).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile

SNIPPET = r"""
import json, time, sys
t0 = time.perf_counter()
import hybridpgo
from hybridpgo.io import bundled_path
try:
    from hybridpgo.solvers.hybrid.solver import ensure_compiled as hyb
except ImportError:
    from hybridpgo.solvers.hybrid import _ensure_compiled as hyb
from hybridpgo.solvers.gauss_newton import ensure_compiled as ex
hyb(); ex()
compile_s = time.perf_counter() - t0
from hybridpgo.solvers import optimize
g = hybridpgo.read_graph(bundled_path("M3500_isam.txt"))
r = optimize(g, "hybrid", sweeps=10)
print(json.dumps({"compile_s": compile_s, "us_mean": r.stats["us_per_constraint_mean"],
                  "us_steady_max": r.stats["us_per_constraint_max_steady"],
                  "energy": r.final_energy}))
"""


def _run(src: str, cache: str) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=src, NUMBA_CACHE_DIR=cache)
    out = subprocess.run([sys.executable, "-c", SNIPPET], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def main() -> None:
    before, after = sys.argv[1], sys.argv[2]
    repeats = int(sys.argv[4]) if len(sys.argv) > 4 else 3
    res: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    for _ in range(repeats):
        for name, src in (("before", before), ("after", after)):
            with tempfile.TemporaryDirectory() as cache:
                cold = _run(src, cache)  # cold: compile time
                warm = _run(src, cache)  # warm: update times
            row = {"compile_s": cold["compile_s"], "us_mean": warm["us_mean"],
                   "us_steady_max": warm["us_steady_max"], "energy": warm["energy"]}
            res[name].append(row)
            print(json.dumps({"tree": name, **row}), flush=True)
    for key in ("compile_s", "us_mean", "us_steady_max"):
        b = statistics.median(r[key] for r in res["before"])
        a = statistics.median(r[key] for r in res["after"])
        print(json.dumps({"metric": key, "before_median": b, "after_median": a,
                          "after_over_before": a / b}))


if __name__ == "__main__":
    main()
