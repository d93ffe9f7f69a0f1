"""Per-kernel Numba compile times of one command, from an empty cache.

Usage (from the worktree, PYTHONPATH=src)::

    python -m benchmarks.compile_profile [--top N] [--json FILE] -- demo -o /tmp/demo
    python -m benchmarks.compile_profile -- optimize src/hybridpgo/data/intel.g2o -o /tmp/o.g2o

Runs ``hybridpgo <command>`` in this process with ``NUMBA_CACHE_DIR`` set to a fresh temporary
directory (unless one is set already), listens to Numba's ``numba:compile`` events and prints,
per kernel: the number of compiled signatures, the inclusive and exclusive (callees' compiles
subtracted) wall and CPU seconds.  CPU seconds (``time.process_time``) are less sensitive to
the load of a shared machine than wall seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from typing import Any


def _install(records: list[dict[str, Any]]) -> None:
    from numba.core import event

    stack: list[dict[str, Any]] = []

    class Listener(event.Listener):  # type: ignore[misc]
        def on_start(self, ev: Any) -> None:
            data = ev.data or {}
            disp = data.get("dispatcher")
            fn = getattr(disp, "py_func", None)
            name = (f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', '?')}"
                    .replace("hybridpgo.", ""))
            rec = {"name": name, "args": str(data.get("args")), "depth": len(stack),
                   "w0": time.perf_counter(), "c0": time.process_time(),
                   "child_w": 0.0, "child_c": 0.0}
            stack.append(rec)

        def on_end(self, ev: Any) -> None:
            rec = stack.pop()
            rec["wall"] = time.perf_counter() - rec.pop("w0")
            rec["cpu"] = time.process_time() - rec.pop("c0")
            rec["excl_wall"] = rec["wall"] - rec.pop("child_w")
            rec["excl_cpu"] = rec["cpu"] - rec.pop("child_c")
            if stack:
                stack[-1]["child_w"] += rec["wall"]
                stack[-1]["child_c"] += rec["cpu"]
            records.append(rec)

    event.register("numba:compile", Listener())


#: CPU seconds inside LLVM phases of Numba's code libraries (all libraries, all depths).
LLVM_CPU: dict[str, float] = {}


def _install_llvm_timers() -> None:
    from numba.core import codegen

    cls = codegen.CPUCodeLibrary
    for meth in ("_optimize_functions", "_optimize_final_module", "_finalize_final_module"):
        orig = getattr(cls, meth)

        def wrapped(self: Any, *a: Any, _orig: Any = orig, _m: str = meth) -> Any:
            c0 = time.process_time()
            try:
                return _orig(self, *a)
            finally:
                LLVM_CPU[_m] = LLVM_CPU.get(_m, 0.0) + time.process_time() - c0

        setattr(cls, meth, wrapped)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--json", help="write every compile record here")
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args(argv)
    cmd = [a for a in args.command if a != "--"] if args.command else ["warmup"]
    # one process: a helper compiling in parallel (hybridpgo._precompile) would hide kernels
    os.environ.setdefault("HYBRIDPGO_PARALLEL_COMPILE", "0")
    if "NUMBA_CACHE_DIR" not in os.environ:
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="hpgo-numba-")
    records: list[dict[str, Any]] = []
    _install(records)
    _install_llvm_timers()
    from hybridpgo.cli import main as cli_main

    w0, c0 = time.perf_counter(), time.process_time()
    rc = cli_main(cmd)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    top = [r for r in records if r["depth"] == 0]
    per: dict[str, dict[str, Any]] = {}
    for r in records:
        p = per.setdefault(r["name"], {"sigs": 0, "excl_cpu": 0.0, "excl_wall": 0.0,
                                       "incl_cpu_top": 0.0, "args": []})
        p["sigs"] += 1
        p["excl_cpu"] += r["excl_cpu"]
        p["excl_wall"] += r["excl_wall"]
        p["args"].append(r["args"])
        if r["depth"] == 0:
            p["incl_cpu_top"] += r["cpu"]
    print(f"\ncommand: hybridpgo {' '.join(cmd)} -> {rc}; wall {wall:.1f} s, cpu {cpu:.1f} s; "
          f"{len(records)} compiles, {sum(r['cpu'] for r in top):.1f} s cpu compiling "
          f"({sum(r['wall'] for r in top):.1f} s wall); load {os.getloadavg()[0]:.2f}",
          file=sys.stderr)
    print("LLVM cpu seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in LLVM_CPU.items()),
          file=sys.stderr)
    print(f"{'kernel':58s} {'sigs':>4s} {'excl cpu':>9s} {'top-level incl':>14s}", file=sys.stderr)
    for name, p in sorted(per.items(), key=lambda kv: -kv[1]["excl_cpu"])[:args.top]:
        print(f"{name[:58]:58s} {p['sigs']:4d} {p['excl_cpu']:9.2f} {p['incl_cpu_top']:14.2f}",
              file=sys.stderr)
    multi = {n: p["args"] for n, p in per.items() if p["sigs"] > 1}
    if multi:
        print("\nkernels compiled for more than one signature:", file=sys.stderr)
        for n, a in multi.items():
            print(f"  {n}:", file=sys.stderr)
            for s in a:
                print(f"      {s[:200]}", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": cmd, "wall": wall, "cpu": cpu, "records": records}, f, indent=1)
    return rc


if __name__ == "__main__":
    sys.exit(main())
