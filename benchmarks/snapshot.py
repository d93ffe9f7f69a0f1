"""Behaviour snapshot: write the optimized outputs of a fixed list of graphs x options.

``python -m benchmarks.snapshot OUTDIR`` runs ``hybridpgo optimize`` in-process on every case and
writes ``OUTDIR/<case>.g2o``; comparing two such folders (``--compare A B``) reports, per case,
whether the files are byte-identical and else the largest relative difference of any number.
Used to show that a refactoring changes no result (issue 12).
"""

from __future__ import annotations

import pathlib
import sys

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
BUNDLED = ROOT / "src" / "hybridpgo" / "data"
TESTDATA = ROOT / "tests" / "data"

#: (name, input, extra CLI options)
# fmt: off
CASES: list[tuple[str, str, list[str]]] = [
    ("m3500_tree_w10", "bundled:M3500_isam.txt", ["--solver", "hybrid", "--sweeps", "10", "--init", "tree"]),  # noqa: E501
    ("m3500_tree_g2", "bundled:M3500_isam.txt", ["--solver", "hybrid", "--sweeps", "2", "--step", "givens"]),  # noqa: E501
    ("m3500_polish", "bundled:M3500_isam.txt", ["--solver", "hybrid", "--sweeps", "5", "--polish"]),
    ("m3500_chordal", "bundled:M3500_isam.txt", ["--solver", "hybrid", "--sweeps", "3", "--init", "chordal"]),  # noqa: E501
    ("m3500_mst", "bundled:M3500_isam.txt", ["--solver", "hybrid", "--sweeps", "3", "--tree", "mst"]),  # noqa: E501
    ("intel_file", "bundled:intel.g2o", ["--solver", "hybrid", "--sweeps", "5", "--init", "file"]),
    ("intel_exact", "bundled:intel.g2o", ["--solver", "exact"]),
    ("garage_exact", "bundled:garage.g2o", ["--solver", "exact"]),
    ("garage_hybrid", "bundled:garage.g2o", ["--solver", "hybrid", "--sweeps", "3", "--init", "file"]),  # noqa: E501
    ("smallgrid_w", "test:smallGrid3D.g2o", ["--solver", "hybrid", "--sweeps", "10"]),
    ("smallgrid_g", "test:smallGrid3D.g2o", ["--solver", "hybrid", "--sweeps", "10", "--step", "givens"]),  # noqa: E501
    ("smallgrid_exact_tree", "test:smallGrid3D.g2o", ["--solver", "exact", "--init", "tree"]),
    ("w100_hybrid", "test:w100_toro.graph", ["--solver", "hybrid", "--sweeps", "10"]),
    ("city_gps_w", "city", ["--solver", "hybrid", "--sweeps", "5"]),
    ("city_gps_b7", "city", ["--solver", "hybrid", "--sweeps", "3", "--gps-batch-size", "7"]),
    ("city_gps_g", "city", ["--solver", "hybrid", "--sweeps", "2", "--step", "givens"]),
    ("city_gps_polish", "city", ["--solver", "hybrid", "--sweeps", "3", "--polish"]),
    ("city_gps_exact", "city", ["--solver", "exact", "--init", "tree"]),
]
# fmt: on


def _input(spec: str, work: pathlib.Path) -> str:
    from hybridpgo.cli import main

    kind, _, name = spec.partition(":")
    if kind == "bundled":
        return str(BUNDLED / name)
    if kind == "test":
        return str(TESTDATA / name)
    path = work / "city.g2o"
    if not path.exists():
        rc = main(["generate", "city", "--preset", "valencia", "--gps-every", "20", "--seed", "3",
                   "-o", str(path), "--ground-truth", str(work / "city_gt.g2o")])
        assert rc == 0
    return str(path)


def write(outdir: pathlib.Path) -> None:
    from hybridpgo.cli import main

    outdir.mkdir(parents=True, exist_ok=True)
    for name, spec, opts in CASES:
        inp = _input(spec, outdir)
        rc = main(["optimize", inp, "-o", str(outdir / f"{name}.g2o"), "--quiet", *opts])
        print(name, rc, flush=True)


def _numbers(path: pathlib.Path) -> list[float]:
    out = []
    for tok in path.read_text().split():
        try:
            out.append(float(tok))
        except ValueError:
            pass
    return out


def compare(a: pathlib.Path, b: pathlib.Path) -> int:
    worst_all = 0.0
    for name, _, _ in CASES:
        fa, fb = a / f"{name}.g2o", b / f"{name}.g2o"
        if fa.read_bytes() == fb.read_bytes():
            print(f"{name:24s} identical")
            continue
        na, nb = _numbers(fa), _numbers(fb)
        if len(na) != len(nb):
            print(f"{name:24s} DIFFERENT STRUCTURE")
            worst_all = float("inf")
            continue
        worst = max(abs(x - y) / max(abs(x), abs(y), 1.0) for x, y in zip(na, nb, strict=True))
        worst_all = max(worst_all, worst)
        print(f"{name:24s} max relative difference {worst:.3g}")
    print(f"worst: {worst_all:.3g}")
    return 0 if worst_all <= 1e-12 else 1


if __name__ == "__main__":
    if sys.argv[1] == "--compare":
        sys.exit(compare(pathlib.Path(sys.argv[2]), pathlib.Path(sys.argv[3])))
    write(pathlib.Path(sys.argv[1]))
