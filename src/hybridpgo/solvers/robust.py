"""``robust="auto"``: find false loop closures and false GPS fixes, and solve without them.

Every solver's least-squares result goes through :func:`check_consistency`; only when it finds
the graph inconsistent does the re-solve run (:func:`resolve`; the default of ``hybridpgo
optimize``, :func:`hybridpgo.optimize` and :class:`~hybridpgo.solvers.config.AutoConfig`).

**The test.**  For correct information a constraint's whitened error ``L^T e`` is a standard
normal vector, so its χ² ``s = e^T Omega e`` (our energy has no 1/2) follows χ²(d), d its
degrees of freedom (6; 3 for a planar graph's relative constraints and for GPS).  A graph is
planar when it is marked ``is_2d`` (a 2D file) or its data are planar
(:func:`~hybridpgo.graph.planar_data`: a 2D graph written in 3D form, an online map of a
planar stream): the out-of-plane half of each error is exactly 0 at the optimum, and counting
it would halve the scale.  Files get
the information's scale wrong both ways (``garage.g2o``'s errors are 4.5e-5 of what its
information claims, ``sphere_bignoise`` 20x), so the scale is estimated:

* relative constraints: the reduced χ² ``sum s / (d M - d (N - 1))``, the degrees of freedom
  left after the poses (at the optimum a constraint's χ² is reduced by its leverage, which
  the total accounts for: sparse graphs, whose chains absorb most of the error, are scaled as
  dense ones are), trimmed of the constraints beyond the threshold (iterated);
* GPS readings: the median χ² over χ²(3)'s median (a reading's leverage is small; χ²(2)'s
  for planar data, whose readings have no height error).

Each χ² is divided by ``nu = max(1, scale)``: an underconfident file is tested against its
stated information, an overconfident one against the data.  The graph is inconsistent when

1. some constraint's scaled χ² exceeds ``THRESHOLD_SIGMAS^2`` (its whitened error is longer
   than 7 sigma; for χ²(3) that is the 1 - 2e-10 quantile, for χ²(6) 1 - 6e-9, so no inlier of
   a correctly weighted graph of 10^6 constraints is flagged but with probability < 1%), or
2. a scale exceeds :data:`LEVEL` (the least-squares errors average 14 stated sigmas or more):
   many false constraints do not stand out at the least-squares optimum, they fold the map
   and every error grows (benchmarks/outliers.py: at 100 or 1 000 false loop closures the
   longest error is 3-9 times the typical one, the scale 300-14 000 times the stated one).

Measured at the least-squares optimum of every clean graph of ``benchmarks/auto.py``: the
largest scaled χ² is 30 (sphere_bignoise; 18 on the generated graphs) and the largest scale
110 (M3500 with 20 degrees of yaw noise added to every measurement, its information kept), so
none is flagged.

**The re-solve** (only for an inconsistent graph):

1. A start the outliers cannot corrupt (:func:`outlier_free_start`): the poses chained along
   a spanning tree of the odometry (edges between consecutive ids, in file order; other edges
   only where the odometry leaves a pose unreached); with GPS, the chain is fitted rigidly
   onto the readings (trimmed), then solved with the odometry tree and the GPS readings alone
   (least squares: without loops the false fixes only bend it locally), then again under
   Geman-McClure.
2. Geman-McClure (delta :data:`GM_SIGMAS` on the information divided by ``min(1, scale)``:
   a scale above 1 may be the outliers' doing, one below is not) from that start, with the
   caller's solver.
3. Truncated least squares, alternated: the constraints beyond the threshold at the current
   poses are rejected, the least-squares optimum of the rest is solved from the current poses
   and the scale re-estimated there (untrimmed), until the rejected set repeats (at most
   :data:`MAX_ROUNDS` rounds).  Rejecting never disconnects the graph or takes its last gauge:
   such constraints are kept.

The result is the least-squares optimum of the kept constraints, and the rejected ones are
listed (``stats["outliers"]``).  When no constraint ends up rejected the least-squares result
is returned unchanged.  GTSAM's ``GncOptimizer`` anneals from the least-squares solution,
which many false closures fold beyond repair; ``benchmarks/outliers.py`` measures both.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from ..energy import constraint_energies
from ..errors import GraphError
from ..graph import FloatArray, PoseGraph, planar_data
from .config import GaussNewtonConfig, HybridConfig, ProgressCallback, RobustName
from .result import SolveResult

if TYPE_CHECKING:
    from ..tree import PoseTree
    from .gauss_newton import IterateCallback

__all__ = ["GM_SIGMAS", "LEVEL", "MAX_ROUNDS", "THRESHOLD_SIGMAS", "Consistency",
           "ResolveFn", "check_consistency", "consistency_of", "exact_resolver", "odometry_tree",
           "outlier_free_start", "rejected_rows", "resolve", "solve_exact_auto",
           "solve_hybrid_auto"]

#: A constraint is an outlier when its whitened error is longer than this many sigmas (of
#: the larger of the stated and the estimated scale).
THRESHOLD_SIGMAS = 7.0
#: The graph is inconsistent when a scale (reduced χ² of the relative constraints, scaled
#: median of the GPS readings) exceeds this.
LEVEL = 200.0
#: Geman-McClure's delta of the re-solve's first stage, in sigmas.
GM_SIGMAS = 10.0
#: Most rounds of the truncated-least-squares alternation.
MAX_ROUNDS = 6
#: Fewer GPS readings than this are not tested (their median says nothing about their scale).
MIN_GPS = 5
#: The medians of χ²(3) and χ²(2) (the GPS scale's reference; a reading of planar data has
#: no height error, :func:`_gps_dof`).
_CHI2_3_MEDIAN = 2.365973884375338
_CHI2_2_MEDIAN = 1.386294361119891

#: ``solve(graph, rotations, translations, robust, robust_scale)``: the caller's solver from
#: the given poses, with the given kernel (``"none"`` or ``"geman_mcclure"``).
ResolveFn = Callable[[PoseGraph, FloatArray, FloatArray, RobustName, float], SolveResult]


@dataclass(frozen=True)
class Consistency:
    """:func:`check_consistency`'s verdict at some poses."""

    scale: float
    """Estimated scale of the relative constraints' χ² (1 for correct information; nan when
    the graph has no redundancy: a tree cannot be tested)."""
    gps_scale: float
    """The same for the GPS readings (nan: fewer than :data:`MIN_GPS`)."""
    sigmas: FloatArray
    """(M,) each relative constraint's whitened error in sigmas, ``sqrt(s / nu)`` with
    ``nu = max(1, scale)`` (0 where untested)."""
    gps_sigmas: FloatArray
    """(G,) the same for the GPS readings."""

    @property
    def outliers(self) -> npt.NDArray[np.bool_]:
        """(M,) relative constraints beyond :data:`THRESHOLD_SIGMAS`."""
        return self.sigmas > THRESHOLD_SIGMAS

    @property
    def gps_outliers(self) -> npt.NDArray[np.bool_]:
        """(G,) GPS readings beyond :data:`THRESHOLD_SIGMAS`."""
        return self.gps_sigmas > THRESHOLD_SIGMAS

    @property
    def misfit(self) -> bool:
        """True when a scale exceeds :data:`LEVEL` (the fit as a whole is inconsistent)."""
        return bool(self.scale > LEVEL or self.gps_scale > LEVEL)

    @property
    def inconsistent(self) -> bool:
        """True when some constraint is beyond the threshold or the fit as a whole is."""
        return bool(self.outliers.any() or self.gps_outliers.any() or self.misfit)


def _dof(graph: PoseGraph) -> int:
    """Degrees of freedom of a relative constraint (a planar graph's: x, y, yaw)."""
    return 3 if graph.is_2d or planar_data(graph) else 6


def _scale_of(s: FloatArray, d: int, num_nodes: int, trim: bool) -> float:
    """Reduced χ² of the relative constraints ``s`` (``d`` degrees of freedom each, between
    ``num_nodes`` poses); with ``trim``, of those within the threshold of
    ``nu = max(1, scale)``: the smallest such fixed point, iterated up from the stated scale,
    so that a few huge χ² cannot inflate it (nan: no degrees of freedom left)."""
    free = d * (num_nodes - 1)
    finite = np.isfinite(s)
    if d * int(finite.sum()) - free <= 0:
        return math.nan
    if not trim:
        return float(s[finite].sum()) / (d * int(finite.sum()) - free)
    nu = 1.0
    while True:
        keep = finite & (s <= THRESHOLD_SIGMAS**2 * nu)
        dof = d * int(keep.sum()) - free
        if dof <= 0:  # too few within reach: the scale is larger
            nu *= 4.0
            continue
        scale = float(s[keep].sum()) / dof
        if max(1.0, scale) <= nu * (1.0 + 1e-12):
            return scale
        nu = max(1.0, scale)


def _gps_dof(graph: PoseGraph) -> int:
    """Degrees of freedom of a GPS reading: 3, or 2 when the data are planar
    (:func:`~hybridpgo.graph.planar_data`: readings at z = 0 whose information does not
    couple z with x, y), whose height error is exactly 0 at the optimum."""
    return 2 if planar_data(graph) else 3


def _gps_scale(s_gps: FloatArray, dof: int = 3) -> float:
    if s_gps.shape[0] < MIN_GPS:
        return math.nan
    return float(np.median(s_gps)) / (_CHI2_2_MEDIAN if dof == 2 else _CHI2_3_MEDIAN)


def _nu(scale: float) -> float:
    """The divisor of the χ²: the larger of the stated (1) and the estimated scale."""
    return max(1.0, scale) if math.isfinite(scale) else 1.0


def _sigmas(s: FloatArray, scale: float, tested: bool = True) -> FloatArray:
    if not tested:
        return np.zeros_like(s)
    with np.errstate(invalid="ignore", over="ignore"):
        out = np.sqrt(np.maximum(s, 0.0) / _nu(scale))
    return np.where(np.isfinite(s), out, np.inf)


def check_consistency(graph: PoseGraph, rotations: FloatArray, translations: FloatArray, *,
                      trim: bool = True) -> Consistency:
    """Test every constraint's χ² at the given poses (module docstring).

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64
        Poses at which to test: a least-squares optimum.
    trim : bool
        Estimate the relative scale without the constraints beyond the threshold (iterated);
        False: over every constraint (the optimum of a set already cleaned).

    Returns
    -------
    Consistency
    """
    s, s_gps = constraint_energies(graph, rotations, translations)
    planar = planar_data(graph)
    return consistency_of(s, s_gps, graph.num_nodes, graph.is_2d or planar, planar, trim=trim)


def consistency_of(s: FloatArray, s_gps: FloatArray, num_nodes: int, planar: bool,
                   planar_gps: bool, *, trim: bool = True) -> Consistency:
    """:func:`check_consistency` from the constraints' χ² at the poses: ``s`` (M,) of the
    relative constraints between ``num_nodes`` poses, ``s_gps`` (G,) of the GPS readings;
    ``planar``: each relative constraint has 3 degrees of freedom (a 2D graph, or planar data:
    :func:`~hybridpgo.graph.planar_data`), else 6; ``planar_gps``: each reading has 2 (planar
    data), else 3.  For a caller that keeps the χ² of a map it checked as it grew (the
    online worker), without building and checking a :class:`PoseGraph` of it."""
    scale = _scale_of(s, 3 if planar else 6, num_nodes, trim)
    gps_scale = _gps_scale(s_gps, 2 if planar_gps else 3)
    return Consistency(scale, gps_scale, _sigmas(s, scale, math.isfinite(scale)),
                       _sigmas(s_gps, gps_scale, math.isfinite(gps_scale)))


# --------------------------------------------------------------------------- the start
def _subgraph(graph: PoseGraph, edges: npt.NDArray[np.int64],
              gps: npt.NDArray[np.int64]) -> PoseGraph:
    """The graph with only the relative constraints ``edges`` and GPS readings ``gps``."""
    lines = graph.edge_lines
    glines = graph.gps_lines
    return dataclasses.replace(
        graph, edge_nodes=graph.edge_nodes[edges], edge_rotations=graph.edge_rotations[edges],
        edge_translations=graph.edge_translations[edges],
        edge_information=graph.edge_information[edges], gps_nodes=graph.gps_nodes[gps],
        gps_positions=graph.gps_positions[gps], gps_information=graph.gps_information[gps],
        edge_lines=None if lines is None else lines[edges],
        gps_lines=None if glines is None else glines[gps])


def odometry_tree(graph: PoseGraph) -> npt.NDArray[np.int64]:
    """Indices of the edges of a spanning tree that prefers the odometry.

    Odometry edges join consecutive ids; among parallel edges the first in file order is used
    (a false closure duplicating an odometry edge comes later in the files we know); other
    edges enter only where the odometry leaves poses unreached (a minimum spanning tree with
    weight 1 for odometry, 2 for the rest).

    Parameters
    ----------
    graph : PoseGraph

    Returns
    -------
    (N - 1,) int64 array
        Edge indices, increasing.

    Raises
    ------
    GraphError
        The relative edges do not connect the graph.
    """
    n = graph.num_nodes
    en = graph.edge_nodes.astype(np.int64)
    ids = graph.node_ids
    odo = np.abs(ids[en[:, 1]] - ids[en[:, 0]]) == 1
    lo, hi = en.min(axis=1), en.max(axis=1)
    keep = lo != hi
    weight = np.where(odo, 1.0, 2.0)
    key = lo * n + hi
    order = np.lexsort((np.arange(en.shape[0]), weight, key))
    order = order[keep[order]]
    first = np.ones(order.shape[0], bool)
    first[1:] = key[order[1:]] != key[order[:-1]]
    pick = order[first]  # one edge per pair of poses: odometry first, then file order
    mst = minimum_spanning_tree(sp.csr_matrix((weight[pick], (lo[pick], hi[pick])),
                                              shape=(n, n))).tocoo()
    if mst.nnz != n - 1:
        raise GraphError("the relative constraints do not connect the graph")
    where = np.searchsorted(key[pick], np.minimum(mst.row, mst.col) * n
                            + np.maximum(mst.row, mst.col))
    return np.sort(pick[where])


def outlier_free_start(graph: PoseGraph, solve: ResolveFn | None = None
                       ) -> tuple[FloatArray, FloatArray]:
    """Global poses chained along :func:`odometry_tree` (module docstring, re-solve step 1).

    Parameters
    ----------
    graph : PoseGraph
    solve : callable, optional
        :data:`ResolveFn`.  With GPS readings the chain is fitted rigidly onto them (three
        trimmed fits) and, when ``solve`` is given, solved with the odometry tree and the
        readings alone (least squares, then Geman-McClure).

    Returns
    -------
    rotations, translations : (N, 3, 3), (N, 3) float64
    """
    from ..initialization import initial_locals
    from ..metrics import align_rigid
    from ..tree import build_tree, global_poses

    tree_edges = odometry_tree(graph)
    chain = _subgraph(graph, tree_edges, np.zeros(0, np.int64))
    tree = build_tree(chain)
    rot, trans = global_poses(tree, *initial_locals(chain, tree, "tree"))
    if graph.num_gps == 0:
        return rot, trans
    p = trans[graph.gps_nodes]
    q = graph.gps_positions
    use = np.ones(q.shape[0], bool)
    for _ in range(3):
        r_fit, t_fit = align_rigid(p[use], q[use])
        dist = np.linalg.norm(p @ r_fit.T + t_fit - q, axis=1)
        use = dist <= max(3.0 * float(np.median(dist)), 1e-9)
    rot = np.einsum("ij,njk->nik", r_fit, rot)
    trans = trans @ r_fit.T + t_fit
    if solve is None:
        return rot, trans
    anchored = _subgraph(graph, tree_edges, np.arange(graph.num_gps))
    res = solve(anchored, rot, trans, "none", 1.0)  # no loop: the readings cannot fold it
    res = solve(anchored, res.rotations, res.translations, "geman_mcclure", GM_SIGMAS)
    return res.rotations, res.translations


# --------------------------------------------------------------------------- rejection
def _keep_solvable(graph: PoseGraph, keep: npt.NDArray[np.bool_],
                   keep_gps: npt.NDArray[np.bool_], sigmas: FloatArray,
                   gps_sigmas: FloatArray) -> None:
    """Re-admit rejected constraints (least inconsistent first) until the kept ones connect
    the graph as all of them do and every part anchored by GPS readings keeps one (in place;
    with every reading rejected, the first pose is the gauge)."""
    n = graph.num_nodes
    en = graph.edge_nodes

    def parts(mask: npt.NDArray[np.bool_]) -> tuple[int, npt.NDArray[np.int32]]:
        k = np.flatnonzero(mask)
        adj = sp.csr_matrix((np.ones(k.size), (en[k, 0], en[k, 1])), shape=(n, n))
        count, labels = connected_components(adj, directed=False)
        return int(count), labels

    count, labels = parts(keep)
    full = parts(np.ones_like(keep))[0]
    if count > full:
        for c in np.flatnonzero(~keep)[np.argsort(sigmas[~keep], kind="stable")]:
            la, lb = labels[en[c, 0]], labels[en[c, 1]]
            if la != lb:  # joins two parts: kept (cold path, over rejected edges only)
                keep[c] = True
                labels[labels == lb] = la
                count -= 1
                if count == full:
                    break
    if graph.num_gps and not graph.fixed_nodes.size and keep_gps.any():
        anchored = np.zeros(n, bool)
        anchored[np.unique(labels[graph.gps_nodes[keep_gps]])] = True
        lost = ~anchored[labels[graph.gps_nodes]] & ~keep_gps
        for g in np.flatnonzero(lost)[np.argsort(gps_sigmas[lost], kind="stable")]:
            if not anchored[labels[graph.gps_nodes[g]]]:
                keep_gps[g] = True
                anchored[labels == labels[graph.gps_nodes[g]]] = True


def _scaled(graph: PoseGraph, verdict: Consistency) -> PoseGraph:
    """The graph with its information divided by ``min(1, scale)`` (module docstring,
    re-solve step 2): a larger scale may be the outliers' doing, a smaller one is not."""
    def low(scale: float) -> float:
        return min(1.0, scale) if math.isfinite(scale) and scale > 0.0 else 1.0

    if low(verdict.scale) == 1.0 and low(verdict.gps_scale) == 1.0:
        return graph
    return dataclasses.replace(graph,
                               edge_information=graph.edge_information / low(verdict.scale),
                               gps_information=graph.gps_information / low(verdict.gps_scale))


def rejected_rows(graph: PoseGraph, edges: npt.NDArray[np.int64],
                  gps: npt.NDArray[np.int64], sigmas: FloatArray,
                  gps_sigmas: FloatArray) -> list[dict[str, Any]]:
    """The rejected constraints as ``info``-style rows (JSON-friendly).

    Parameters
    ----------
    graph : PoseGraph
    edges, gps : int arrays
        Indices of the rejected relative constraints and GPS readings.
    sigmas, gps_sigmas : (M,), (G,) float64
        Every constraint's whitened error in sigmas (:class:`Consistency`).

    Returns
    -------
    list of dict
        ``kind`` (``"edge"`` or ``"gps"``), ``index`` (within its kind, file order), ``id_a``,
        ``id_b`` (the file's ids; None for GPS), ``line`` (in the file; None when unknown),
        ``sigmas``; relative constraints first.
    """
    ids = graph.node_ids
    rows: list[dict[str, Any]] = []
    for c in edges.tolist():
        a, b = (int(ids[i]) for i in graph.edge_nodes[c])
        line = None if graph.edge_lines is None else int(graph.edge_lines[c])
        rows.append({"kind": "edge", "index": c, "id_a": a, "id_b": b, "line": line,
                     "sigmas": float(sigmas[c])})
    for g in gps.tolist():
        line = None if graph.gps_lines is None else int(graph.gps_lines[g])
        rows.append({"kind": "gps", "index": g, "id_a": int(ids[graph.gps_nodes[g]]),
                     "id_b": None, "line": line, "sigmas": float(gps_sigmas[g])})
    return rows


def resolve(graph: PoseGraph, result: SolveResult, solve: ResolveFn) -> SolveResult:
    """The least-squares ``result``, or when it is inconsistent the robust re-solve's
    (module docstring).

    Parameters
    ----------
    graph : PoseGraph
    result : SolveResult
        A least-squares optimum of ``graph``.
    solve : callable
        :data:`ResolveFn`: the caller's solver, run from given poses with a given kernel.

    Returns
    -------
    SolveResult
        ``result`` itself with ``stats["outliers"]`` (the verdict) when the graph is
        consistent or nothing is rejected; else the least-squares optimum of the kept
        constraints, its energies those of the kept constraints (``energy_history`` goes on
        from ``result``'s), ``stats["outliers"]`` listing the rejected ones.
    """
    t0 = time.perf_counter()
    verdict = check_consistency(graph, result.rotations, result.translations)
    report: dict[str, Any] = {
        "scale": verdict.scale, "gps_scale": verdict.gps_scale,
        "threshold_sigmas": THRESHOLD_SIGMAS, "level": LEVEL,
        "flagged": int(verdict.outliers.sum()), "flagged_gps": int(verdict.gps_outliers.sum()),
        "max_sigmas": float(verdict.sigmas.max(initial=0.0)),
        "max_gps_sigmas": float(verdict.gps_sigmas.max(initial=0.0)),
        "misfit": verdict.misfit, "inconsistent": verdict.inconsistent, "rejected": 0,
        "rejected_gps": 0, "rejected_constraints": [], "rounds": 0}
    if not verdict.inconsistent:
        report["seconds"] = time.perf_counter() - t0
        return _with(result, report)
    rot, trans = outlier_free_start(graph, solve)
    first = solve(_scaled(graph, verdict), rot, trans, "geman_mcclure", GM_SIGMAS)
    rot, trans = first.rotations, first.translations
    verdict = check_consistency(graph, rot, trans)
    seen: list[tuple[bytes, bytes]] = []
    final: SolveResult | None = None
    t_final = 0.0
    kept = np.arange(graph.num_edges)
    kept_gps = np.arange(graph.num_gps)
    while len(seen) < MAX_ROUNDS:
        keep = ~verdict.outliers
        keep_gps = ~verdict.gps_outliers
        _keep_solvable(graph, keep, keep_gps, verdict.sigmas, verdict.gps_sigmas)
        key = (np.packbits(keep).tobytes(), np.packbits(keep_gps).tobytes())
        if key in seen:
            break
        seen.append(key)
        kept, kept_gps = np.flatnonzero(keep), np.flatnonzero(keep_gps)
        t_final = time.perf_counter() - t0
        final = solve(_subgraph(graph, kept, kept_gps), rot, trans, "none", 1.0)
        rot, trans = final.rotations, final.translations
        verdict = _rescaled(graph, kept, kept_gps, rot, trans)
    assert final is not None
    rejected = np.setdiff1d(np.arange(graph.num_edges), kept)
    rejected_gps = np.setdiff1d(np.arange(graph.num_gps), kept_gps)
    report.update(rounds=len(seen), rejected=int(rejected.size),
                  rejected_gps=int(rejected_gps.size), scale_after=verdict.scale,
                  gps_scale_after=verdict.gps_scale, gm_iterations=first.iterations,
                  rejected_constraints=rejected_rows(graph, rejected, rejected_gps,
                                                     verdict.sigmas, verdict.gps_sigmas))
    report["seconds"] = time.perf_counter() - t0
    if rejected.size == 0 and rejected_gps.size == 0:
        return _with(result, report)
    offset = float(result.times[-1]) if len(result.times) else 0.0
    return dataclasses.replace(
        result, rotations=final.rotations, translations=final.translations,
        status=final.status,
        energy_history=np.concatenate([result.energy_history, final.energy_history[1:]]),
        times=np.concatenate([result.times, offset + t_final + np.asarray(final.times[1:])]),
        timings=_timings(result, report), stats={**result.stats, "outliers": report})


def _rescaled(graph: PoseGraph, kept: npt.NDArray[np.int64], kept_gps: npt.NDArray[np.int64],
              rot: FloatArray, trans: FloatArray) -> Consistency:
    """Every constraint's sigmas at the optimum of the kept ones, the scales estimated on the
    kept ones (untrimmed: they are the inliers)."""
    s, s_gps = constraint_energies(graph, rot, trans)
    scale = _scale_of(s[kept], _dof(graph), graph.num_nodes, False)
    gps_scale = _gps_scale(s_gps[kept_gps], _gps_dof(graph))
    return Consistency(scale, gps_scale, _sigmas(s, scale, math.isfinite(scale)),
                       _sigmas(s_gps, gps_scale, math.isfinite(gps_scale)))


def _with(result: SolveResult, report: dict[str, Any]) -> SolveResult:
    return dataclasses.replace(result, stats={**result.stats, "outliers": report},
                               timings=_timings(result, report))


def _timings(result: SolveResult, report: dict[str, Any]) -> dict[str, float]:
    """``result``'s timings with the outlier test and re-solve's seconds added to
    ``"outliers"`` (the pipeline's own checks may be there already)."""
    return {**result.timings,
            "outliers": result.timings.get("outliers", 0.0) + report["seconds"]}



# --------------------------------------------------------------------------- the solvers' side
def exact_resolver(config: GaussNewtonConfig, progress: ProgressCallback | None = None,
                   iterate: IterateCallback | None = None) -> ResolveFn:
    """:data:`ResolveFn` of the exact solver.

    Parameters
    ----------
    config : GaussNewtonConfig
        Method and limits; ``robust`` and ``robust_scale`` are set per call.
    progress, iterate : callable, optional
        As :func:`~hybridpgo.solvers.gauss_newton.solve_exact`'s, reported as phase
        ``"polish"`` with detail ``"outliers"``.

    Returns
    -------
    callable
    """
    from .gauss_newton import solve_exact

    report = None if progress is None else (
        lambda p: progress(p._replace(phase="polish", detail="outliers")))
    each = None if iterate is None else (
        lambda p, r, t: iterate(p._replace(phase="polish", detail="outliers"), r, t))

    def solve(graph: PoseGraph, rot: FloatArray, trans: FloatArray, kernel: RobustName,
              delta: float) -> SolveResult:
        cfg = dataclasses.replace(config, robust=kernel, robust_scale=delta)
        return solve_exact(graph, rot, trans, cfg, progress=report, iterate=each)

    return solve


def solve_exact_auto(graph: PoseGraph, rotations: FloatArray | None,
                     translations: FloatArray | None, config: GaussNewtonConfig, *,
                     progress: ProgressCallback | None = None,
                     iterate: IterateCallback | None = None) -> SolveResult:
    """:func:`~hybridpgo.solvers.gauss_newton.solve_exact` with ``robust="auto"``: least
    squares, then :func:`resolve` with the same solver.

    Parameters
    ----------
    graph, rotations, translations, config, progress, iterate
        As :func:`~hybridpgo.solvers.gauss_newton.solve_exact`'s.

    Returns
    -------
    SolveResult
    """
    from .gauss_newton import solve_exact

    plain = dataclasses.replace(config, robust="none", robust_scale=None)
    result = solve_exact(graph, rotations, translations, plain, progress=progress,
                         iterate=iterate)
    return resolve(graph, result, exact_resolver(plain, progress, iterate))


def solve_hybrid_auto(graph: PoseGraph, config: HybridConfig, *, tree: PoseTree | None = None,
                      progress: ProgressCallback | None = None,
                      locals0: tuple[FloatArray, FloatArray] | None = None,
                      iterate: IterateCallback | None = None) -> SolveResult:
    """:func:`~hybridpgo.solvers.hybrid.solve_hybrid` with ``robust="auto"``: least squares,
    then :func:`resolve` with the same sweeps (and polish) from the re-solve's poses.

    Parameters
    ----------
    graph, config, tree, progress, locals0, iterate
        As :func:`~hybridpgo.solvers.hybrid.solve_hybrid`'s.

    Returns
    -------
    SolveResult
    """
    from ..tree import build_tree, locals_from_globals
    from .hybrid.solver import solve_hybrid

    plain = dataclasses.replace(config, robust="none", robust_scale=None)
    result = solve_hybrid(graph, plain, tree=tree, progress=progress, locals0=locals0,
                          iterate=iterate)

    def solve(sub: PoseGraph, rot: FloatArray, trans: FloatArray, kernel: RobustName,
              delta: float) -> SolveResult:
        t = build_tree(sub, plain.tree)
        grot, gtr = rot, trans
        if t.has_earth:
            grot = np.concatenate([rot, np.eye(3)[None]])
            gtr = np.concatenate([trans, np.zeros((1, 3))])
        lr = np.empty((t.num_tree_nodes, 3, 3))
        lt = np.empty((t.num_tree_nodes, 3))
        locals_from_globals(t.parent, grot, gtr, lr, lt)
        cfg = dataclasses.replace(plain, robust=kernel, robust_scale=delta)
        return solve_hybrid(sub, cfg, tree=t, progress=progress, locals0=(lr, lt))

    return resolve(graph, result, solve)
