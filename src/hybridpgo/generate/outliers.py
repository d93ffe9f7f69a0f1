"""False loop closures and false GPS fixes ("outliers") added to a generated graph, with the list
of which constraints are false.

:func:`add_outliers` adds two kinds, both with the information of a real loop closure, so that
nothing but their inconsistency with the rest of the graph gives them away:

* ``random``: between two poses drawn at random (usually far apart); the measurement is a real
  loop closure's measured relative pose (one drawn at random), with fresh noise drawn from its
  information: a plausible-looking closure between the wrong places.
* ``near_miss``: between two poses whose true distance is between ``near_miss_min_m`` and
  ``near_miss_max_m`` (a few metres: perceptual aliasing of a nearby place); the measurement is
  the true relative rotation with a real loop closure's translation, plus fresh noise.  With
  ``near_miss_min_m`` above the loop-closure radius the claimed translation is wrong by at
  least ``near_miss_min_m - loop radius``.

In both, the earlier pose comes first (``a < b``, ``b - a >= min_gap``).

:func:`add_pattern_outliers` adds the four patterns of Sünderhauf and Protzel's Vertigo datasets
(:data:`OUTLIER_PATTERNS`): every false edge claims that its two poses are at the same place
(a relative pose drawn from N(0, 0.3 m) per translation axis and N(0, 10 deg) per rotation
axis, as perceptual aliasing would), with a real loop closure's information, between

* ``random``: two poses drawn uniformly;
* ``local``: a pose and one of the 20 poses after it (never its odometry neighbour);
* ``random-grouped`` / ``local-grouped``: the same, in groups of ``group_size`` mutually
  consistent edges ``(a + j, b + j)``, ``j = 0 .. group_size - 1``, sharing one measurement
  (a front end that aliased a whole stretch of road).

Every false edge is inserted in the graph's online order (right after the odometry edge that
reaches its later pose) when the graph's edges are in that order, else appended.  2D graphs get
planar measurements only (x, y, yaw).

:func:`add_gps_outliers` moves some GPS readings by a jump of tens of metres in a random
horizontal direction (multipath: the receiver locks onto a reflection).
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

__all__ = ["GPS_CSV_HEADER", "OUTLIER_KINDS", "OUTLIER_PATTERNS", "GpsOutliers", "Outliers",
           "add_gps_outliers", "add_outliers", "add_pattern_outliers", "check_pattern",
           "no_gps_outliers", "no_outliers", "write_gps_outliers", "write_outliers"]

#: Sünderhauf and Protzel's outlier patterns (:func:`add_pattern_outliers`).
OUTLIER_PATTERNS: tuple[str, ...] = ("random", "local", "random-grouped", "local-grouped")
#: Names of the outlier kinds; :attr:`Outliers.kinds` holds indices into this tuple: the two of
#: :func:`add_outliers`, then one per pattern of :func:`add_pattern_outliers`.
OUTLIER_KINDS: tuple[str, ...] = ("random", "near_miss", "aliased_random", "aliased_local",
                                  "aliased_random_grouped", "aliased_local_grouped")
#: :func:`add_pattern_outliers`: the local pattern's second pose is at most this many poses
#: after the first; the measurement's sigma per translation axis (m) and rotation axis (rad).
LOCAL_WINDOW = 20
ALIAS_TRANS_SIGMA_M = 0.3
ALIAS_ROT_SIGMA_RAD = math.radians(10.0)

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
        return _index_mask(self.edges, num_edges)


def _index_mask(indices: npt.NDArray[np.int64], size: int) -> npt.NDArray[np.bool_]:
    out = np.zeros(size, bool)
    out[indices] = True
    return out


def check_pattern(pattern: object) -> None:
    """ValueError unless ``pattern`` is ``"mixed"`` (:func:`add_outliers`) or one of
    :data:`OUTLIER_PATTERNS` (:func:`add_pattern_outliers`)."""
    if pattern != "mixed" and pattern not in OUTLIER_PATTERNS:
        raise ValueError(f"outlier_pattern must be mixed or one of {', '.join(OUTLIER_PATTERNS)}"
                         f", got {pattern!r}")


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
    loop_edges = _loop_edges(graph, loop_edges)

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

    return _insert(graph, a, b, zr, zt, info, kinds, np.linalg.norm(trans[b] - trans[a], axis=1))


def _insert(graph: PoseGraph, a: npt.NDArray[np.int64], b: npt.NDArray[np.int64],
            zr: FloatArray, zt: FloatArray, info: FloatArray, kinds: npt.NDArray[np.int8],
            dist: FloatArray) -> tuple[PoseGraph, Outliers]:
    """``graph`` with the false edges (a, b) added, in online order when the graph's edges are
    in it (sorted by their later pose), else appended; and which edges they are."""
    en = graph.edge_nodes
    later = np.maximum(en[:, 0], en[:, 1]).astype(np.int64)
    m = graph.num_edges
    k = a.shape[0]
    if m == 0 or np.all(np.diff(later) >= 0):
        order = np.argsort(np.concatenate([later, np.maximum(a, b)]), kind="stable")
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
        edge_lines=None,
    )
    idx = position[m:]
    srt = np.argsort(idx, kind="stable")
    return out, Outliers(idx[srt], kinds[srt], dist[srt])


def _loop_edges(graph: PoseGraph, loop_edges: npt.NDArray[np.int64] | None
                ) -> npt.NDArray[np.int64]:
    """The real loop closures to copy information (and measurements) from: ``loop_edges``, or
    every edge whose poses are not consecutive, or every edge when there is none."""
    if loop_edges is None:
        en = graph.edge_nodes
        loop_edges = np.flatnonzero(np.abs(en[:, 1].astype(np.int64) - en[:, 0]) != 1)
        if loop_edges.size == 0:
            loop_edges = np.arange(graph.num_edges)
    if loop_edges.size == 0:
        raise ValueError("the graph has no edge to copy a measurement from")
    return loop_edges


def add_pattern_outliers(graph: PoseGraph, truth_translations: FloatArray, num_outliers: int,
                         pattern: str = "random", *, seed: int | np.random.Generator = 0,
                         group_size: int = 10,
                         loop_edges: npt.NDArray[np.int64] | None = None
                         ) -> tuple[PoseGraph, Outliers]:
    """Return ``graph`` with ``num_outliers`` false loop closures in one of Sünderhauf and
    Protzel's patterns (module docstring), and which they are.

    Parameters
    ----------
    graph : PoseGraph
        Poses in driving order (dense index = time).
    truth_translations : (N, 3) float64
        The true positions (only for the distances reported).
    num_outliers : int
        Number of false edges K >= 0; the grouped patterns add ``ceil(K / group_size)`` groups,
        the last one cut to K edges in all.
    pattern : {"random", "local", "random-grouped", "local-grouped"}
    seed : int or numpy.random.Generator
    group_size : int
        Edges per group of the grouped patterns (>= 1).
    loop_edges : (L,) int, optional
        The real loop closures whose information is copied (default as :func:`add_outliers`).

    Returns
    -------
    (PoseGraph, Outliers)

    Raises
    ------
    ValueError
        Bad arguments, or a graph too small for the pattern.
    """
    if pattern not in OUTLIER_PATTERNS:
        raise ValueError(f"pattern must be one of {', '.join(OUTLIER_PATTERNS)}, got "
                         f"{pattern!r}")
    k = int(num_outliers)
    if k < 0:
        raise ValueError(f"num_outliers must be >= 0, got {num_outliers!r}")
    if isinstance(group_size, bool) or not isinstance(group_size, int) or group_size < 1:
        raise ValueError(f"group_size must be an integer >= 1, got {group_size!r}")
    if k == 0:
        return graph, no_outliers()
    g = group_size if pattern.endswith("grouped") else 1
    top = graph.num_nodes - g  # a group's first poses a, b satisfy b + g - 1 <= N - 1
    if top < 3:
        raise ValueError(f"a graph of {graph.num_nodes} poses is too small for the "
                         f"{pattern!r} pattern (groups of {g})")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    loops = _loop_edges(graph, loop_edges)
    groups = -(-k // g)
    if pattern.startswith("local"):  # b - a in 2 .. LOCAL_WINDOW, within the graph
        lo = rng.integers(0, top - 1, size=groups)
        hi = np.minimum(lo + rng.integers(2, LOCAL_WINDOW + 1, size=groups), top)
    else:  # two poses at least 2 apart, uniformly
        lo = np.empty(groups, np.int64)
        hi = np.empty(groups, np.int64)
        todo = np.arange(groups)
        while todo.size:
            pair = rng.integers(0, top + 1, size=(todo.size, 2))
            ok = np.abs(pair[:, 1] - pair[:, 0]) >= 2
            lo[todo[ok]] = pair[ok].min(axis=1)
            hi[todo[ok]] = pair[ok].max(axis=1)
            todo = todo[~ok]
    xi = np.zeros((groups, 6))
    xi[:, :3] = rng.normal(scale=ALIAS_TRANS_SIGMA_M, size=(groups, 3))
    xi[:, 3:] = rng.normal(scale=ALIAS_ROT_SIGMA_RAD, size=(groups, 3))
    if graph.is_2d:
        xi[:, 2:5] = 0.0
    info_src = loops[rng.integers(loops.size, size=groups)]
    j = np.arange(g)
    a = (lo[:, None] + j[None, :]).reshape(-1)[:k].astype(np.int64)
    b = (hi[:, None] + j[None, :]).reshape(-1)[:k].astype(np.int64)
    grp = np.repeat(np.arange(groups), g)[:k]
    zt = xi[:, :3].copy()
    zr = se3.exp(np.concatenate([np.zeros((groups, 3)), xi[:, 3:]], axis=1))[0]
    info = np.array(graph.edge_information[info_src])[grp]
    kinds = np.full(k, 2 + OUTLIER_PATTERNS.index(pattern), np.int8)
    trans = np.asarray(truth_translations, np.float64)
    return _insert(graph, a, b, zr[grp], zt[grp], info, kinds,
                   np.linalg.norm(trans[b] - trans[a], axis=1))


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


# =========================================================================== GPS
#: Header of the GPS outliers CSV file written by :func:`write_gps_outliers`.
GPS_CSV_HEADER = "gps_index,id,jump_m,dx,dy,dz"
#: :func:`add_gps_outliers`: the jump of a false fix is uniform in this range, metres.
GPS_JUMP_M = (20.0, 60.0)


@dataclass(frozen=True, slots=True)
class GpsOutliers:
    """Which GPS readings of a graph are false fixes, and by how much they jumped."""

    readings: npt.NDArray[np.int64]
    """(K,) int64, increasing: indices into the graph's GPS readings (``graph.gps_nodes``),
    which are also the 0-based indices among the GPS lines of a written file."""
    jumps: FloatArray
    """(K, 3) float64: what was added to each reading's position, metres (earth frame)."""

    @property
    def num_outliers(self) -> int:
        return int(self.readings.shape[0])

    def mask(self, num_gps: int) -> npt.NDArray[np.bool_]:
        """(num_gps,) bool: True for the false readings."""
        return _index_mask(self.readings, num_gps)


def no_gps_outliers() -> GpsOutliers:
    """An empty :class:`GpsOutliers`."""
    return GpsOutliers(np.zeros(0, np.int64), np.zeros((0, 3)))


def add_gps_outliers(graph: PoseGraph, num_outliers: int, *,
                     seed: int | np.random.Generator = 0,
                     jump_m: tuple[float, float] = GPS_JUMP_M) -> tuple[PoseGraph, GpsOutliers]:
    """Return ``graph`` with ``num_outliers`` of its GPS readings moved by a multipath jump, and
    which they are.

    Each chosen reading (distinct, uniformly among the readings) moves by a length uniform in
    ``jump_m`` in a uniformly random horizontal direction; its information is kept, so nothing
    but its inconsistency with the rest of the graph gives it away.

    Raises
    ------
    ValueError
        ``num_outliers`` negative or more than the graph's GPS readings, or a bad ``jump_m``.
    """
    k = int(num_outliers)
    if not 0 <= k <= graph.num_gps:
        raise ValueError(f"num_outliers must be in 0..{graph.num_gps} (the graph's GPS "
                         f"readings), got {num_outliers!r}")
    lo, hi = (float(v) for v in jump_m)
    if not (math.isfinite(hi) and 0.0 <= lo <= hi):
        raise ValueError(f"need 0 <= jump_m[0] <= jump_m[1], got {jump_m!r}")
    if k == 0:
        return graph, no_gps_outliers()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    idx = np.sort(rng.choice(graph.num_gps, size=k, replace=False)).astype(np.int64)
    length = rng.uniform(lo, hi, size=k)
    angle = rng.uniform(0.0, 2.0 * math.pi, size=k)
    jumps = np.column_stack([length * np.cos(angle), length * np.sin(angle), np.zeros(k)])
    pos = np.array(graph.gps_positions)
    pos[idx] += jumps
    return dataclasses.replace(graph, gps_positions=pos), GpsOutliers(idx, jumps)


def write_gps_outliers(path: PathLike, graph: PoseGraph, outliers: GpsOutliers) -> None:
    """Write the false GPS readings as CSV (atomically): one header line, then one row each.

    Columns: ``gps_index`` (0-based index among the GPS lines of the graph file, i.e. into
    ``read_graph(file).gps_nodes``), ``id`` (the pose's file id), ``jump_m`` (the jump's
    length) and ``dx``, ``dy``, ``dz`` (the jump, earth frame, metres).
    """
    ids = graph.node_ids[graph.gps_nodes[outliers.readings]]

    def lines() -> list[str]:
        rows = [GPS_CSV_HEADER]
        rows += [f"{g},{i},{float(np.linalg.norm(d))!r},{d[0]!r},{d[1]!r},{d[2]!r}"
                 for g, i, d in zip(outliers.readings.tolist(), ids.tolist(),
                                    outliers.jumps.tolist(), strict=True)]
        return rows

    write_atomic(path, lines)
