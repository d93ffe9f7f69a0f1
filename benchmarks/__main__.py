"""Run the benchmarks: ``python -m benchmarks [--quick] [--only NAME ...] [--gate]``.

Writes ``benchmarks/results/<run>.json`` and ``.md``.  ``--gate`` exits 1 when a metric regressed
against ``benchmarks/baseline.json`` beyond its tolerance; ``--update-baseline`` rewrites it.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

from .metrics import write_results
from .workloads import WORKLOADS, Context

HERE = pathlib.Path(__file__).resolve().parent
#: The environment variable naming the folder of the public benchmark graphs
#: (benchmarks/README.md lists the files and where they come from).
DATA_ENV = "HYBRIDPGO_DATASETS"
#: The graphs shipped with the package (src/hybridpgo/data).
BUNDLED = HERE.parent / "src" / "hybridpgo" / "data"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data-dir",
        type=pathlib.Path,
        default=pathlib.Path(os.environ.get(DATA_ENV) or BUNDLED),
        help=f"folder with the benchmark graphs (default: ${DATA_ENV}, else the graphs bundled "
             "with the package: M3500_isam, intel, garage)",
    )
    ap.add_argument("--only", nargs="+", choices=sorted(WORKLOADS), default=None)
    ap.add_argument("--quick", action="store_true", help="fewer sweeps, for a smoke run")
    ap.add_argument("--run", default=None, help="name of the result files (default: timestamp)")
    ap.add_argument("--gate", action="store_true", help="exit 1 on a regression vs baseline.json")
    ap.add_argument("--update-baseline", action="store_true")
    args = ap.parse_args(argv)
    if not args.data_dir.is_dir():
        print(
            f"benchmarks: error: data directory {args.data_dir} not found (--data-dir)",
            file=sys.stderr,
        )
        return 2
    ctx = Context(data_dir=args.data_dir, quick=args.quick, cache={},
                  figures=HERE / "results" / "figures")
    metrics, tables = [], []
    for name in args.only or list(WORKLOADS):
        t0 = time.perf_counter()
        print(f"[{name}] running ...", file=sys.stderr, flush=True)
        m, t = WORKLOADS[name](ctx)
        metrics += m
        tables += t
        for table in t:
            print(table, flush=True)
        print(f"[{name}] {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    run = args.run or time.strftime("%Y%m%d-%H%M%S")
    command = "python -m benchmarks " + " ".join(argv if argv is not None else sys.argv[1:])
    write_results(HERE / "results" / run, metrics, tables, command.strip())
    print(f"wrote {HERE / 'results' / run}.json and .md", file=sys.stderr)
    status = 0
    base_path = HERE / "baseline.json"
    if args.gate and base_path.exists():
        base = {m["key"]: m["value"] for m in json.loads(base_path.read_text())["metrics"]}
        for m in metrics:
            if m.key in base and m.regressed(base[m.key]):
                print(
                    f"REGRESSION {m.key}: {m.value:.6g} vs baseline {base[m.key]:.6g}",
                    file=sys.stderr,
                )
                status = 1
    if args.update_baseline:
        (HERE / "baseline.json").write_text((HERE / "results" / f"{run}.json").read_text())
    return status


if __name__ == "__main__":
    sys.exit(main())
