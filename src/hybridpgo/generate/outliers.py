"""False loop closures ("outliers") added to a generated graph, with the list of which edges are
false.

Two kinds, both with the information of a real loop closure, so that nothing but their
inconsistency with the rest of the graph gives them away:

* ``random``: between two poses drawn at random (usually far apart); the measurement is a real
  loop closure's measured relative pose (one drawn at random), with fresh noise drawn from its
  information: a plausible-looking closure between the wrong places.
* ``near_miss``: between two poses whose true distance is between ``near_miss_min_m`` and
  ``near_miss_max_m`` (a few metres: perceptual aliasing of a nearby place); the measurement is
  the true relative rotation with a real loop closure's translation, plus fresh noise.  With
  ``near_miss_min_m`` above the loop-closure radius the claimed translation is wrong by at
  least ``near_miss_min_m - loop radius``.

In both, the earlier pose comes first (``a < b``, ``b - a >= min_gap``) and the edges are inserted
in the graph's online order (right after the odometry edge that reaches ``b``) when the graph's
edges are in that order, else appended.  2D graphs get planar noise only (x, y, yaw).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from ..geometry import se3
from ..graph import FloatArray, PoseGraph
from ..io._lines import PathLike, write_atomic

__all__ = ["OUTLIER_KINDS", "Outliers", "add_outliers", "no_outliers", "write_outliers"]

#: Names of the outlier kinds; :attr:`Outliers.kinds` holds indices into this tuple.
OUTLIER_KINDS: tuple[str, ...] = ("random", "near_miss")

#: Header of the outliers CSV file written by :func:`write_outliers`.
CSV_HEADER = "edge_index,id_a,id_b,kind,true_distance_m"


@dataclass(frozen=True, slots=True)
class Outliers:
    """Which relative constraints of a graph are false."""

    edges: npt.NDArray[np.int64]
    """(K,) int64, increasing: indices into the graph's edges (``graph.edge_nodes``), which are
    also the 0-based indices among the relative-constraint lines of a written file."""
    kinds: npt.NDArray[np.int8]
    """(K,) int8: index into :data:`OUTLIER_KINDS` of each false edge."""
    true_distances_m: FloatArray
    """(K,) float64: true distance between the two poses of each false edge, metres."""

    @property
    def num_outliers(self) -> int:
        return int(self.edges.shape[0])

    def mask(self, num_edges: int) -> npt.NDArray[np.bool_]:
        """(num_edges,) bool: True for the false edges."""
        out = np.zeros(num_edges, bool)
        out[self.edges] = True
        return out


def no_outliers() -> Outliers:
    """An empty :class:`Outliers`."""
    return Outliers(np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0))


def add_outliers(graph: PoseGraph, truth_rotations: FloatArray, truth_translations: FloatArray,
                 num_outliers: int, *, seed: int | np.random.Generator = 0,
                 near_miss_fraction: float = 0.5, near_miss_min_m: float = 6.0,
                 near_miss_max_m: float = 15.0, min_gap: int = 1,
                 loop_edges: npt.NDArray[np.int64] | None = None) -> tuple[PoseGraph, Outliers]:
    """Return ``graph`` with ``num_outliers`` false loop closures added, and which they are.

    Parameters
    ----------
    graph : PoseGraph
    truth_rotations, truth_translations : (N, 3, 3), (N, 3) float64
        The true poses (dense order), used to place the near misses and to give the near misses'
        rotations and the distances reported.
    num_outliers : int
        Number of false edges K >= 0.
    seed : int or numpy.random.Generator
        Randomness; the same seed gives the same outliers.
    near_miss_fraction : float in [0, 1]
        ``round(K * near_miss_fraction)`` of them are near misses, the rest random pairs.
    near_miss_min_m, near_miss_max_m : float
        True distance range (3D, metres) of the near misses' two poses.
    min_gap : int
        ``b - a >= min_gap`` for every false edge (the real closures' minimum gap).
    loop_edges : (L,) int, optional
        Indices of the real loop closures whose measurements and information are copied;
        default: every edge whose poses are not consecutive (``|b - a| != 1``), or every edge
        when there is none.

    Returns
    -------
    (PoseGraph, Outliers)

    Raises
    ------
    ValueError
        Bad arguments, or fewer near-miss pairs exist than asked for.
    """
    n = graph.num_nodes
    k = int(num_outliers)
    if k < 0:
        raise ValueError(f"num_outliers must be >= 0, got {num_outliers!r}")
    if not 0.0 <= near_miss_fraction <= 1.0:
        raise ValueError(f"near_miss_fraction must be in [0, 1], got {near_miss_fraction!r}")
    if not (math.isfinite(near_miss_max_m) and 0.0 <= near_miss_min_m <= near_miss_max_m):
        raise ValueError("need 0 <= near_miss_min_m <= near_miss_max_m, got "
                         f"{near_miss_min_m!r}, {near_miss_max_m!r}")
    if min_gap < 1:
        raise ValueError(f"min_gap must be >= 1, got {min_gap!r}")
    if k == 0:
        return graph, no_outliers()
    if n - min_gap < 1:
        raise ValueError(f"a graph of {n} poses has no pair {min_gap} or more poses apart")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    rot = np.asarray(truth_rotations, np.float64)
    trans = np.asarray(truth_translations, np.float64)
    en = graph.edge_nodes
    if loop_edges is None:
        loop_edges = np.flatnonzero(np.abs(en[:, 1].astype(np.int64) - en[:, 0]) != 1)
        if loop_edges.size == 0:
            loop_edges = np.arange(graph.num_edges)
    if loop_edges.size == 0:
        raise ValueError("the graph has no edge to copy a measurement from")

    k_near = round(k * near_miss_fraction)
    k_rand = k - k_near
    # Random pairs: b uniform in [min_gap, n), a uniform in [0, b - min_gap].
    rb = rng.integers(min_gap, n, size=k_rand)
    ra = (rng.random(k_rand) * (rb - min_gap + 1)).astype(np.int64)
    na, nb = _near_pairs(trans, k_near, near_miss_min_m, near_miss_max_m, min_gap, rng)
    a = np.concatenate([ra, na])
    b = np.concatenate([rb, nb])
    kinds = np.concatenate([np.zeros(k_rand, np.int8), np.ones(k_near, np.int8)])

    src = loop_edges[rng.integers(loop_edges.size, size=k)]
    zr = np.array(graph.edge_rotations[src])
    zt = np.array(graph.edge_translations[src])
    true_r, _ = se3.between(rot[a], trans[a], rot[b], trans[b])
    near = kinds == 1
    zr[near] = true_r[near]
    info = np.array(graph.edge_information[src])
    zr, zt = _noisy(zr, zt, info, graph.is_2d, rng)

    # Insert in online order when the graph is in it (edges sorted by their later pose).
    later = np.maximum(en[:, 0], en[:, 1]).astype(np.int64)
    m = graph.num_edges
    if m == 0 or np.all(np.diff(later) >= 0):
        order = np.argsort(np.concatenate([later, b]), kind="stable")
    else:
        order = np.arange(m + k)
    position = np.empty(m + k, np.int64)
    position[order] = np.arange(m + k)
    out = dataclasses.replace(
        graph,
        edge_nodes=np.concatenate([en, np.column_stack([a, b]).astype(np.int32)])[order],
        edge_rotations=np.concatenate([graph.edge_rotations, zr])[order],
        edge_translations=np.concatenate([graph.edge_translations, zt])[order],
        edge_information=np.concatenate([graph.edge_information, info])[order],
    )
    idx = position[m:]
    srt = np.argsort(idx, kind="stable")
    dist = np.linalg.norm(trans[b] - trans[a], axis=1)
    return out, Outliers(idx[srt], kinds[srt], dist[srt])


def _near_pairs(trans: FloatArray, k: int, lo: float, hi: float, min_gap: int,
                rng: np.random.Generator) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """``k`` pairs (a, b), ``b - a >= min_gap``, true distance in [lo, hi], distinct b's."""
    empty = np.zeros(0, np.int64)
    if k == 0:
        return empty, empty
    n = trans.shape[0]
    tree = cKDTree(trans)
    perm = rng.permutation(np.arange(min_gap, n))
    chunk = max(8 * k, 1024)
    out_a: list[npt.NDArray[np.int64]] = []
    out_b: list[npt.NDArray[np.int64]] = []
    found = 0
    for start in range(0, perm.size, chunk):
        owners = perm[start:start + chunk]
        hits = tree.query_ball_point(trans[owners], r=hi)
        counts = np.fromiter((len(h) for h in hits), np.int64, owners.size)
        cand = np.fromiter(itertools.chain.from_iterable(hits), np.int64, int(counts.sum()))
        pos = np.repeat(np.arange(owners.size), counts)  # the owner's place in the chunk
        owner = owners[pos]
        d = np.linalg.norm(trans[cand] - trans[owner], axis=1)
        ok = (cand <= owner - min_gap) & (d >= lo) & (d <= hi)
        pos, cand = pos[ok], cand[ok]
        # canonical order (the tree's hit order is an implementation detail), then one random
        # candidate per owner, owners in the permutation's order
        srt = np.lexsort((cand, pos))
        pos, cand = pos[srt], cand[srt]
        key = rng.random(pos.size)
        pick = np.lexsort((key, pos))
        last = np.concatenate([pos[pick][1:] != pos[pick][:-1], [True]])
        chosen = pick[last] if pos.size else empty
        take = chosen[: k - found]
        out_a.append(cand[take])
        out_b.append(owners[pos[take]])
        found += take.size
        if found == k:
            return np.concatenate(out_a), np.concatenate(out_b)
    raise ValueError(f"only {found} pose pairs are {lo:g} to {hi:g} m apart (and at least "
                     f"{min_gap} poses apart); asked for {k} near-miss outliers")


def _noisy(zr: FloatArray, zt: FloatArray, info: FloatArray, planar: bool,
           rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """``Z Exp(xi)`` with ``xi ~ N(0, info^-1)``; only (x, y, yaw) for a planar graph."""
    if zr.shape[0] == 0:
        return zr, zt
    chol = np.linalg.cholesky(info)  # info = L L^T, so L^-T w ~ N(0, info^-1)
    w = rng.normal(size=(zr.shape[0], 6, 1))
    xi = np.linalg.solve(np.swapaxes(chol, 1, 2), w)[..., 0]
    if planar:
        xi[:, 2:5] = 0.0
    nr, nt = se3.exp(xi)
    return se3.compose(zr, zt, nr, nt)


def write_outliers(path: PathLike, graph: PoseGraph, outliers: Outliers) -> None:
    """Write the false edges as CSV (atomically): one header line, then one row per false edge.

    Columns: ``edge_index`` (0-based index among the relative-constraint lines of the graph
    file, i.e. into ``read_graph(file).edge_nodes``), ``id_a``, ``id_b`` (the file's pose ids),
    ``kind`` (``random`` or ``near_miss``), ``true_distance_m``.
    """
    ids = graph.node_ids[graph.edge_nodes[outliers.edges]]

    def lines() -> list[str]:
        rows = [CSV_HEADER]
        rows += [f"{e},{i},{j},{OUTLIER_KINDS[kd]},{d!r}" for e, (i, j), kd, d in zip(
            outliers.edges.tolist(), ids.tolist(), outliers.kinds.tolist(),
            outliers.true_distances_m.tolist(), strict=True)]
        return rows

    write_atomic(path, lines)
