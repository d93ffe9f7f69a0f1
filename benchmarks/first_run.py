"""First run: cold-cache wall and CPU time of the commands a new user types.

Each command runs as ``python -m hybridpgo ...`` in its own process with ``NUMBA_CACHE_DIR`` set to
a fresh empty directory (a first run after ``pip install``), then once more with that cache
(warm); each both with the default parallel compile (a helper process, ``hybridpgo._precompile``)
and with ``HYBRIDPGO_PARALLEL_COMPILE=0``.  CPU = user + system time of the child and its helper
(less sensitive to a shared machine's load than wall time); the load average is recorded beside
each run.  Target: a cold first run <= 30 s.

Run: ``PYTHONPATH=src python -m benchmarks --only first_run --run <name>``.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time

from hybridpgo.io import bundled_path

from .metrics import Metric, markdown_table, timing
from .workloads import Context, Result

#: Target of the cold first run (seconds).
TARGET_S = 30.0


def _commands(out: str) -> list[tuple[str, list[str]]]:
    intel = str(bundled_path("intel.g2o"))
    return [
        ("demo", ["demo", "-o", os.path.join(out, "demo"), "-q"]),
        ("optimize intel.g2o (default auto)", ["optimize", intel, "-o",
                                               os.path.join(out, "a.g2o"), "-q"]),
        ("optimize intel.g2o --solver hybrid", ["optimize", intel, "-o",
                                                os.path.join(out, "h.g2o"), "--solver",
                                                "hybrid", "-q"]),
    ]


def _timed(argv: list[str], cache: str, parallel: bool = True) -> tuple[float, float, float]:
    """(wall s, CPU s, load average) of one ``python -m hybridpgo`` run (CPU: with the helper
    process that compiles in parallel, ``hybridpgo._precompile``)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": cache,
           "HYBRIDPGO_PARALLEL_COMPILE": "1" if parallel else "0"}  # 1: even on a busy machine
    env.pop("NUMBA_DISABLE_JIT", None)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "hybridpgo", *argv], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=1800)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, load


def run(ctx: Context) -> Result:
    metrics: list[Metric] = []
    rows = []
    with tempfile.TemporaryDirectory(prefix="hybridpgo-first-run-") as out:
        for label, argv in _commands(out):
            key = label.split(" (")[0].replace(" ", "_").replace("--", "")
            for parallel in (True, False):
                cache = tempfile.mkdtemp(dir=out, prefix="cache-")
                cold = _timed(argv, cache, parallel)
                warm = _timed(argv, cache, parallel)
                mode = "" if parallel else ".serial"
                metrics += [timing(f"first_run.{key}{mode}.cold_wall", cold[0]),
                            timing(f"first_run.{key}{mode}.cold_cpu", cold[1]),
                            timing(f"first_run.{key}{mode}.warm_wall", warm[0])]
                rows.append([f"`hybridpgo {label}`",
                             "2 (`=1`)" if parallel else "1 (`HYBRIDPGO_PARALLEL_COMPILE=0`)",
                             f"{cold[0]:.1f}", f"{cold[1]:.1f}", f"{cold[2]:.2f}",
                             f"{warm[0]:.1f}", f"{warm[1]:.1f}",
                             "met" if cold[0] <= TARGET_S else "missed"])
    return metrics, [markdown_table(
        f"First run: empty Numba cache (cold) then the same command again (warm), compiling in "
        f"2 processes (`HYBRIDPGO_PARALLEL_COMPILE=1`: hybridpgo._precompile, even when no "
        f"core is idle) or 1; CPU: both processes; target: "
        f"cold <= {TARGET_S:g} s wall on 2 cores",
        ["command", "compiling processes", "cold wall s", "cold CPU s", "load at start",
         "warm wall s", "warm CPU s", "target"], rows)]
