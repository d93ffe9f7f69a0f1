"""Behaviour snapshot: write the optimized outputs of a fixed list of graphs x options.

``python -m benchmarks.snapshot OUTDIR`` runs ``hybridpgo optimize`` in-process on every case and
writes ``OUTDIR/<case>.g2o``; comparing two such folders (``--compare A B``) reports, per case,
whether the files are byte-identical and else the largest relative difference of any number.
Used to show that a refactoring changes no result.
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
    ("m3500_auto", "bundled:M3500_isam.txt", []),
    ("intel_auto", "bundled:intel.g2o", []),
    ("garage_auto", "bundled:garage.g2o", []),
    ("smallgrid_auto", "test:smallGrid3D.g2o", []),
    ("city_gps_auto", "city", []),
    ("m3500_toro", "bundled:M3500_isam.txt", ["--solver", "toro", "--sweeps", "20"]),
    ("w100_toro_bfs", "test:w100_toro.graph", ["--solver", "toro", "--sweeps", "20", "--tree", "bfs"]),  # noqa: E501
    ("intel_exact_huber", "bundled:intel.g2o", ["--solver", "exact", "--robust", "huber:2"]),
    ("m3500_cov", "bundled:M3500_isam.txt", ["--solver", "exact", "--covariance", "{out}.npz", "--covariance-poses", "0,100,3499"]),  # noqa: E501
    ("garage_cov", "bundled:garage.g2o", ["--solver", "exact", "--covariance", "{out}.npz", "--covariance-poses", "0,500,1600"]),  # noqa: E501
]
#: Online replays, no time budget (reproducible): (name, input, OnlineConfig keywords)
ONLINE: list[tuple[str, str, dict[str, object]]] = [
    ("m3500_online", "bundled:M3500_isam.txt", {}),
    ("city_gps_online", "city", {}),
    ("m3500_online_local", "bundled:M3500_isam.txt", {"local_size": 4, "tree": "odometry"}),
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
        out = str(outdir / name)
        rc = main(["optimize", inp, "-o", out + ".g2o", "--quiet",
                   *(o.format(out=out) for o in opts)])
        print(name, rc, flush=True)
    for name, spec, kw in ONLINE:
        _online(_input(spec, outdir), outdir / f"{name}.g2o", kw)
        print(name, flush=True)


def _online(inp: str, out: pathlib.Path, kw: dict[str, object]) -> None:
    """Stream the graph through the online solver with no budget (one update per frame, then
    five more: reproducible), and write the estimate."""
    import hybridpgo
    from hybridpgo.online import OnlineConfig, OnlineSolver, replay

    graph = hybridpgo.read_graph(inp)
    stream = replay.make_stream(graph)
    solver = OnlineSolver(OnlineConfig(**{"background_refine": False, **kw}))  # type: ignore
    for k in range(stream.num_frames):
        replay.feed_frame(solver, stream, k)
        solver.update(None)
    for _ in range(5):
        solver.update(None)
    hybridpgo.write_graph(solver.to_graph(), str(out))


def _numbers(path: pathlib.Path) -> list[float]:
    out = []
    for tok in path.read_text().split():
        try:
            out.append(float(tok))
        except ValueError:
            pass
    return out


def _compare_npz(name: str, fa: pathlib.Path, fb: pathlib.Path) -> float:
    import numpy as np

    with np.load(fa) as za, np.load(fb) as zb:
        worst = 0.0
        for key in za.files:
            x, y = za[key], zb[key]
            if x.dtype.kind in "fi" and x.shape == y.shape:
                d = np.abs(x - y) / np.maximum(np.maximum(np.abs(x), np.abs(y)), 1.0)
                worst = max(worst, float(d.max()) if d.size else 0.0)
            elif not np.array_equal(x, y):
                worst = float("inf")
    print(f"{name + '.npz':24s} max relative difference {worst:.3g}")
    return worst


def compare(a: pathlib.Path, b: pathlib.Path) -> int:
    worst_all = 0.0
    names = [c[0] for c in CASES] + [c[0] for c in ONLINE]
    for name in names:
        npz = a / f"{name}.npz"
        if npz.exists():
            worst_all = max(worst_all, _compare_npz(name, npz, b / f"{name}.npz"))
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
