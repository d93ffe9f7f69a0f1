"""The online worker's incremental solver, request by request: back substitution of the whole
solution against the one that skips what moved by rounding only (the worker's option), and the
planar system (3x3 blocks, the default on planar data) against the full one (6x6 blocks).

Run: ``PYTHONPATH=src python -m benchmarks --only worker --run <name>`` (about 8 minutes).

Each graph is streamed as the online solver's worker receives it: frame by frame (a pose and
its odometry, then the frame's loop closures), one :meth:`IncrementalExact.solve` without the
polish per frame (a request that brings data).  Two solvers take the same frames in the same
process, in turn, so that the ratio of their times is measured under the same load: the
worker's options (``rounding``: :data:`hybridpgo.online.worker.ROUNDING_WILDFIRE`, the planar
system), ``whole`` (``wildfire`` 0: every column below the re-eliminated ones recomputed in
every cycle) and ``full`` (the worker's options with ``planar=False``: 6x6 blocks on the same
planar data).

* ``worker.<graph>.<mode>.ms_odometry_mean``: mean time of a request whose frame brings only a
  pose and its odometry; ``ms_loop_median``: median of a request whose frame closes a loop;
  ``s_total``: all requests; ``columns_odometry_median``: columns recomputed by an
  odometry-only request.
* ``worker.<graph>.rounding_vs_whole``: total time ratio (rounding / whole);
  ``planar_vs_full``: (rounding / full).
* ``worker.<graph>.energy_rel_diff_max`` and ``position_diff_max``: the largest relative
  energy difference and position difference (m) between the rounding and whole estimates at
  every 500th frame and the last; ``full_energy_rel_diff_max``, ``full_position_diff_max``:
  between the rounding and full ones.

Requests on a large map (``worker.large.*``): paris2 streamed in requests of
:data:`LARGE_STEP` frames (one update cycle each, no polish: a worker request whose cycle
budget is one cycle) up to :data:`LARGE_FRAMES` frames, then :data:`LARGE_TIMED` requests
timed: ``ms_median`` / ``ms_max`` per request, ``numeric_ms_median`` (the factorization),
``columns_mean`` (columns re-eliminated), ``applied_mean`` (earlier columns applied to the
re-eliminated ones) and ``blocks_mean`` (the 6x6 block products of those updates, the
supernodes' own factorization not counted: ``IncrementalExact.stats["products"]``).  This
part runs in a child process with the worker's environment
(:data:`hybridpgo.online.worker.WORKER_THREADS`: one BLAS thread), as the worker does.

Requests as the map grows (``worker.growth.*``): grid10k, all :data:`GROWTH_POSES` frames, one
request per frame as the worker serves a frame-by-frame stream (one update cycle, no polish),
in a child process with the worker's environment; per :data:`GROWTH_BIN` frames the request's
``ms_mean`` / ``ms_p90`` / ``ms_max``, ``numeric_ms_mean`` (the factorization), ``columns_mean``
(columns re-eliminated) and ``pool`` (the factor's blocks at the bin's end).  Beside it, in the
same child, GTSAM's ISAM2 on the same stream (:func:`hybridpgo.online.replay.replay_isam2`:
one update and the frame's pose per frame, GTSAM's default relinearization threshold 0.1 as
the worker's, up to :data:`GROWTH_ISAM2_S` seconds of updates): ``isam2_ms_mean`` /
``isam2_ms_p90`` per whole bin it reached.  A request that takes longer than the frame
period leaves the worker behind the stream: its answers then come less often than the
frames, each covering more of them.

Growth of the per-pose and per-edge arrays (``worker.arrays.*``): paris2, all its frames, fed to
an incremental solver in requests of :data:`ARRAYS_STEP` frames (one update cycle each), in a
child process with the worker's environment, once with the arrays reserved as address space
(grown in place) and once as where nothing can be reserved (copied at each doubling); each
growth timed (``IncrementalExact._grow``): ``<arrays>_<rows>.in_place_ms`` / ``copied_ms``.

``HYBRIDPGO_BENCH_WORKER_PARTS``: ``requests``, ``large``, ``growth``, ``arrays``
(comma-separated; the default ``requests,large``).

Graphs: the valencia city preset (all 15 031 frames) and paris2's first 12 000 frames
(:func:`hybridpgo.generate.generate_city`, seed 0; both 3D, so the planar system is left at
their first frames), and grid10k's first 4 000 frames (:func:`hybridpgo.generate.generate_grid`,
seed 0, 10 000 poses; planar).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from typing import Any

import numpy as np

from hybridpgo.online.incremental import IncrementalConfig, IncrementalExact
from hybridpgo.online.replay import make_stream
from hybridpgo.online.worker import INCREMENTAL, ROUNDING_WILDFIRE, WORKER_THREADS

from .context import Context, Result
from .metrics import Metric, info, markdown_table, quality, timing

#: Frames streamed per graph (None: all).
GRAPHS: tuple[tuple[str, int | None], ...] = (("valencia", None), ("paris2", 12_000),
                                               ("grid10k", 4_000))
#: Frames between two comparisons of the estimates.
EVERY = 500
MODES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("whole", {"wildfire": 0.0}), ("rounding", {"wildfire": ROUNDING_WILDFIRE}),
    ("full", {"wildfire": ROUNDING_WILDFIRE, "planar": False}))
#: Frames a third solver takes before the timing, so that no request pays a compilation.
WARM_UP = 300
#: Requests on a large map: paris2's frames per request, frames before the timing, requests
#: timed.
LARGE_STEP = 90
LARGE_FRAMES = 39_420
LARGE_TIMED = 5


def _feed(inc: IncrementalExact, stream: Any, rank: np.ndarray, k: int) -> int:
    """Frame k's pose, odometry and loop closures; returns the frame's constraint count."""
    g = stream.graph
    if k == 0:
        inc.add_poses(np.eye(3)[None], np.zeros((1, 3)))
    else:
        a, zr, zt, _ = stream.odometry_from(k)
        inc.add_poses(zr[None], zt[None], [rank[a]])
    es = stream.edges[stream.edge_ptr[k]:stream.edge_ptr[k + 1]]
    if es.size:
        ab = rank[g.edge_nodes[es]]
        inc.add_edges(ab[:, 0], ab[:, 1], g.edge_rotations[es], g.edge_translations[es],
                      g.edge_information[es])
    return int(es.size)


def _one(name: str, frames: int | None) -> tuple[list[Metric], list[Any]]:
    from hybridpgo.generate import generate_city, generate_grid

    graph = (generate_grid(seed=0, num_poses=10_000).graph if name == "grid10k"
             else generate_city(name, seed=0).graph)
    stream = make_stream(graph)
    g = stream.graph
    rank = np.empty(g.num_nodes, np.int64)
    rank[stream.order] = np.arange(g.num_nodes)
    nf = stream.num_frames if frames is None else min(frames, stream.num_frames)
    warm = IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
    for k in range(min(WARM_UP, nf)):  # kernels compiled or loaded before the timing
        _feed(warm, stream, rank, k)
        warm.solve(polish=False)
    incs = [IncrementalExact(IncrementalConfig(**{**INCREMENTAL, **o}))  # type: ignore[arg-type]
            for _, o in MODES]
    sec = np.zeros((len(MODES), nf))
    cols = np.zeros((len(MODES), nf), np.int64)
    loop = np.zeros(nf, bool)
    de = dp = fe = fp = 0.0
    for k in range(nf):
        for i, inc in enumerate(incs):
            laid = _feed(inc, stream, rank, k)
            before = inc.stats["recomputed"]
            t0 = time.perf_counter()
            inc.solve(polish=False)
            sec[i, k] = time.perf_counter() - t0
            cols[i, k] = inc.stats["recomputed"] - before
        loop[k] = laid > 1  # the same frame for every solver
        if (k + 1) % EVERY == 0 or k == nf - 1:
            e0, e1, e2 = (inc.energy() for inc in incs)
            de = max(de, abs(e1 - e0) / max(e0, 1e-300))
            fe = max(fe, abs(e1 - e2) / max(e2, 1e-300))
            p0, p1, p2 = (inc.estimate()[1] for inc in incs)
            dp = max(dp, float(np.abs(p0 - p1).max()))
            fp = max(fp, float(np.abs(p2 - p1).max()))
    odo = ~loop
    odo[0] = False  # the first frame: a lone pose
    metrics: list[Metric] = []
    rows = []
    for i, (mode, _) in enumerate(MODES):
        key = f"worker.{name}.{mode}"
        vals = (float(sec[i, odo].mean() * 1e3), float(np.median(sec[i, loop]) * 1e3),
                float(sec[i].sum()), float(np.median(cols[i, odo])))
        metrics += [timing(f"{key}.ms_odometry_mean", vals[0], "ms"),
                    timing(f"{key}.ms_loop_median", vals[1], "ms"),
                    timing(f"{key}.s_total", vals[2]),
                    info(f"{key}.columns_odometry_median", vals[3])]
        rows.append([name, nf, int(loop.sum()), mode, *vals])
    ratio = float(sec[1].sum() / sec[0].sum())
    planar = float(sec[1].sum() / sec[2].sum())
    metrics += [info(f"worker.{name}.rounding_vs_whole", ratio),
                info(f"worker.{name}.planar_vs_full", planar),
                quality(f"worker.{name}.energy_rel_diff_max", de),
                quality(f"worker.{name}.position_diff_max", dp, "m"),
                quality(f"worker.{name}.full_energy_rel_diff_max", fe),
                quality(f"worker.{name}.full_position_diff_max", fp, "m")]
    rows[0] += ["", "", ""]
    rows[1] += [f"{ratio:.3g} / {planar:.3g}", f"{de:.2g} / {fe:.2g}", f"{dp:.2g} / {fp:.2g}"]
    rows[2] += ["", "", ""]
    return metrics, rows


def _large_numbers() -> dict[str, float]:
    """Requests of :data:`LARGE_STEP` frames on paris2 grown to :data:`LARGE_FRAMES` frames
    (module doc), in this process."""
    from hybridpgo.generate import generate_city

    stream = make_stream(generate_city("paris2", seed=0).graph)
    g = stream.graph
    rank = np.empty(g.num_nodes, np.int64)
    rank[stream.order] = np.arange(g.num_nodes)
    inc = IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
    k = 0

    def request() -> None:
        nonlocal k
        for _ in range(LARGE_STEP):
            _feed(inc, stream, rank, k)
            k += 1
        inc.solve(max_cycles=1, polish=False)

    while k + LARGE_STEP <= LARGE_FRAMES:
        request()
    keys = ("columns", "applied", "products")
    sec, num, work = [], [], []
    for _ in range(LARGE_TIMED):
        before = [inc.stats[q] for q in keys]
        n0 = inc.stats["seconds"]["numeric"]
        t0 = time.perf_counter()
        request()
        sec.append(time.perf_counter() - t0)
        num.append(inc.stats["seconds"]["numeric"] - n0)
        work.append([inc.stats[q] - b for q, b in zip(keys, before, strict=True)])
    w = np.mean(np.array(work, float), axis=0)
    return {"ms_median": float(np.median(sec) * 1e3), "ms_max": float(np.max(sec) * 1e3),
            "numeric_ms_median": float(np.median(num) * 1e3), "columns": float(w[0]),
            "applied": float(w[1]), "blocks": float(w[2]),
            "after": float(k - LARGE_TIMED * LARGE_STEP)}


def _in_worker_env(name: str, args: str = "") -> Any:
    """The JSON result of this module's function ``name`` called with ``args`` (Python source)
    in a child process with the worker's environment
    (:data:`hybridpgo.online.worker.WORKER_THREADS`)."""
    code = f"import json, benchmarks.worker as w; print(json.dumps(w.{name}({args})))"
    env = {**os.environ, **WORKER_THREADS}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _large() -> tuple[list[Metric], str]:
    """:func:`_large_numbers` in a child process with the worker's environment."""
    v = _in_worker_env("_large_numbers")
    metrics = [timing("worker.large.ms_median", v["ms_median"], "ms"),
               timing("worker.large.ms_max", v["ms_max"], "ms"),
               timing("worker.large.numeric_ms_median", v["numeric_ms_median"], "ms"),
               info("worker.large.columns_mean", v["columns"]),
               info("worker.large.applied_mean", v["applied"]),
               info("worker.large.blocks_mean", v["blocks"])]
    table = markdown_table(
        f"Requests on a large map: paris2 in requests of {LARGE_STEP} frames (one cycle, no "
        f"polish), {LARGE_TIMED} requests timed after {v['after']:.0f} frames; one BLAS thread",
        ["request ms (median / max)", "factorization ms (median)", "columns",
         "earlier columns applied", "block products"],
        [[f"{v['ms_median']:.1f} / {v['ms_max']:.1f}", f"{v['numeric_ms_median']:.1f}",
          f"{v['columns']:.0f}", f"{v['applied']:.0f}", f"{v['blocks']:.0f}"]])
    return metrics, table


#: Poses of the graph the growth part streams (grid10k), frames per bin, and the seconds of
#: ISAM2 updates beside it.
GROWTH_POSES = 10_000
GROWTH_BIN = 1_000
GROWTH_ISAM2_S = 240.0


def _bins(values: np.ndarray) -> list[np.ndarray]:
    return [values[i: i + GROWTH_BIN] for i in range(0, values.shape[0], GROWTH_BIN)]


def _growth_numbers() -> dict[str, Any]:
    """Requests of one frame each on grid10k as it grows (module doc), in this process."""
    from hybridpgo.generate import generate_grid
    from hybridpgo.online.replay import replay_isam2

    stream = make_stream(generate_grid(seed=0, num_poses=GROWTH_POSES).graph)
    g = stream.graph
    rank = np.empty(g.num_nodes, np.int64)
    rank[stream.order] = np.arange(g.num_nodes)
    warm = IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
    for k in range(WARM_UP):  # kernels compiled or loaded before the timing
        _feed(warm, stream, rank, k)
        warm.solve(polish=False)
    inc = IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
    nf = stream.num_frames
    sec, num, cols, pool = (np.zeros(nf) for _ in range(4))
    for k in range(nf):
        _feed(inc, stream, rank, k)
        n0, c0 = inc.stats["seconds"]["numeric"], inc.stats["columns"]
        t0 = time.perf_counter()
        inc.solve(max_cycles=1, polish=False)
        sec[k] = time.perf_counter() - t0
        num[k] = inc.stats["seconds"]["numeric"] - n0
        cols[k] = inc.stats["columns"] - c0
        pool[k] = inc._pool_used[0]
    out: dict[str, Any] = {"bins": [
        {"frames": int(b.shape[0]), "ms_mean": float(b.mean() * 1e3),
         "ms_p90": float(np.percentile(b, 90) * 1e3), "ms_max": float(b.max() * 1e3),
         "numeric_ms_mean": float(n.mean() * 1e3), "columns_mean": float(c.mean()),
         "pool": float(p[-1])}
        for b, n, c, p in zip(_bins(sec), _bins(num), _bins(cols), _bins(pool), strict=True)]}
    from .gtsam_ref import gtsam_available

    if gtsam_available():
        lat = np.asarray(replay_isam2(stream, max_seconds=GROWTH_ISAM2_S).latency_s)
        done = lat.shape[0] == nf  # else stopped at its time: only its whole bins
        reached = [b for b in _bins(lat) if done or b.shape[0] == GROWTH_BIN]
        out["isam2"] = [{"ms_mean": float(b.mean() * 1e3),
                         "ms_p90": float(np.percentile(b, 90) * 1e3)} for b in reached]
        out["isam2_frames"] = int(lat.shape[0])
    return out


def _growth() -> tuple[list[Metric], str]:
    """:func:`_growth_numbers` in a child process with the worker's environment."""
    v = _in_worker_env("_growth_numbers")
    metrics: list[Metric] = []
    rows = []
    isam = v.get("isam2", [])
    for i, b in enumerate(v["bins"]):
        lo, hi = i * GROWTH_BIN + 1, i * GROWTH_BIN + b["frames"]
        key = f"worker.growth.{hi}"
        metrics += [timing(f"{key}.ms_mean", b["ms_mean"], "ms"),
                    timing(f"{key}.ms_p90", b["ms_p90"], "ms"),
                    timing(f"{key}.ms_max", b["ms_max"], "ms"),
                    timing(f"{key}.numeric_ms_mean", b["numeric_ms_mean"], "ms"),
                    info(f"{key}.columns_mean", b["columns_mean"]),
                    info(f"{key}.pool", b["pool"])]
        cell = "-"
        if i < len(isam):
            metrics += [timing(f"{key}.isam2_ms_mean", isam[i]["ms_mean"], "ms"),
                        timing(f"{key}.isam2_ms_p90", isam[i]["ms_p90"], "ms")]
            cell = f"{isam[i]['ms_mean']:.2f} / {isam[i]['ms_p90']:.2f}"
        rows.append([f"{lo}-{hi}", f"{b['ms_mean']:.2f} / {b['ms_p90']:.2f} / {b['ms_max']:.1f}",
                     f"{b['numeric_ms_mean']:.2f}", f"{b['columns_mean']:.0f}",
                     f"{b['pool']:.0f}", cell])
    table = markdown_table(
        f"Requests as the map grows: grid10k streamed frame by frame, one request (one update "
        f"cycle, no polish) per frame; one BLAS thread.  ISAM2 on the same stream in the same "
        f"process, one update per frame (frames 1-{v.get('isam2_frames', 0)} within "
        f"{GROWTH_ISAM2_S:.0f} s of updates)",
        ["frames", "request ms mean / p90 / max", "factorization ms mean", "columns mean",
         "factor blocks at the end", "ISAM2 frame ms mean / p90"], rows)
    return metrics, table


#: Frames per request of the arrays part (paris2 streamed as a worker's requests).
ARRAYS_STEP = 50


def _arrays_numbers(reserve: bool = True) -> dict[str, Any]:
    """Every growth of the per-pose and per-edge arrays of an incremental solver fed all of
    paris2 in requests of :data:`ARRAYS_STEP` frames (one update cycle each), timed
    (``IncrementalExact._grow``).  ``reserve`` False: as where no address space can be
    reserved (each growth a copy into a plain array)."""
    from hybridpgo.generate import generate_city
    from hybridpgo.online import incremental

    stream = make_stream(generate_city("paris2", seed=0).graph)
    g = stream.graph
    rank = np.empty(g.num_nodes, np.int64)
    rank[stream.order] = np.arange(g.num_nodes)
    grew: list[dict[str, Any]] = []
    grow = IncrementalExact._grow
    kinds = {id(IncrementalExact._POSE_ARRAYS): "poses", id(IncrementalExact._EDGE_ARRAYS): "edges",
             id(IncrementalExact._GPS_ARRAYS): "gps"}

    def timed(self: IncrementalExact, arrays: Any, old: int, cap: int) -> None:
        t0 = time.perf_counter()
        grow(self, arrays, old, cap)
        grew.append({"arrays": kinds[id(arrays)], "from": old, "to": cap,
                     "ms": (time.perf_counter() - t0) * 1e3})

    saved = incremental.reserved_only
    if not reserve:
        incremental.reserved_only = lambda shape, dtype=np.float64: None
    IncrementalExact._grow = timed  # type: ignore[method-assign]
    try:
        inc = IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
        nf = stream.num_frames
        for k in range(nf):
            n0 = len(grew)
            _feed(inc, stream, rank, k)
            for d in grew[n0:]:
                d["frame"] = k + 1
            if (k + 1) % ARRAYS_STEP == 0 or k + 1 == nf:
                inc.solve(max_cycles=1, polish=False)
                for d in grew[n0:]:
                    d.setdefault("frame", k + 1)
    finally:
        incremental.reserved_only = saved
        IncrementalExact._grow = grow  # type: ignore[method-assign]
    from hybridpgo._memory import can_overcommit

    return {"growths": grew, "frames": int(stream.num_frames), "reserved": can_overcommit()}


def _arrays() -> tuple[list[Metric], str]:
    """:func:`_arrays_numbers` in place and copied, each in a child process with the worker's
    environment."""
    runs = {mode: _in_worker_env("_arrays_numbers", flag)
            for mode, flag in (("in_place", "True"), ("copied", "False"))}
    if not runs["in_place"]["reserved"]:
        raise RuntimeError("no address space can be reserved here (_memory.can_overcommit): "
                           "both modes would copy")
    metrics: list[Metric] = []
    rows = []
    for a, b in zip(runs["in_place"]["growths"], runs["copied"]["growths"], strict=True):
        if a["to"] < 4096:
            continue
        key = f"worker.arrays.{a['arrays']}_{a['to']}"
        metrics += [timing(f"{key}.in_place_ms", a["ms"], "ms"),
                    timing(f"{key}.copied_ms", b["ms"], "ms")]
        rows.append([a["arrays"], f"{a['from']} -> {a['to']}", str(a["frame"]),
                     f"{a['ms']:.2f}", f"{b['ms']:.2f}"])
    table = markdown_table(
        f"Growth of the per-pose and per-edge arrays: paris2 ({runs['in_place']['frames']} "
        f"frames) fed to an incremental solver in requests of {ARRAYS_STEP} frames (one update "
        "cycle each), in a child process with the worker's environment; each growth "
        "(IncrementalExact._grow) timed, with the arrays reserved as address space "
        "(grown in place) and without (copied at each doubling); growths to 4 096 rows and more",
        ["arrays", "rows", "frame", "in place ms", "copied ms"], rows)
    return metrics, table


def run(ctx: Context) -> Result:
    parts = os.environ.get("HYBRIDPGO_BENCH_WORKER_PARTS", "requests,large").split(",")
    metrics: list[Metric] = []
    rows: list[Any] = []
    tables = []
    if "growth" in parts:
        m, t = _growth()
        metrics += m
        tables.append(t)
    if "arrays" in parts:
        m, t = _arrays()
        metrics += m
        tables.append(t)
    if "large" in parts:
        m, t = _large()
        metrics += m
        tables.append(t)
    if "requests" not in parts:
        return metrics, tables
    for name, frames in GRAPHS:
        m, r = _one(name, frames)
        metrics += m
        rows += r
    table = markdown_table(
        "Worker requests (one incremental solve per frame, no polish): back substitution of "
        "the whole solution (whole) vs skipping what moved by rounding only (rounding: "
        "ROUNDING_WILDFIRE, the worker's), and the planar system (rounding) vs 6x6 blocks "
        "(full)",
        ["graph", "frames", "loop frames", "mode", "odometry-only request mean ms",
         "loop request median ms", "total s", "columns per odometry-only request (median)",
         "total rounding / whole, rounding / full", "max rel. energy diff (vs whole / full)",
         "max position diff (m) (vs whole / full)"], rows)
    return metrics, [table, *tables]
