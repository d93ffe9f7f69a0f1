"""A Manhattan world after Olson (the M3500 family): a robot on a grid of streets.

The robot takes unit steps (1 m) along the streets of a rectangular grid (a box of ``nx`` by
``ny`` blocks, ``street_spacing`` steps per block; in 3D also ``nz`` levels).  At each
intersection it turns (or not) at random: in 2D straight, left, right or back (U-turn); in 3D
also up or down (pitch).  After choosing it steps once in the new direction, so each odometry
measurement is a unit translation with a rotation that is a multiple of 90 degrees, as in
Olson's M3500 (``manhattanOlson3500``: 3500 poses; 76% straight, 8% each left, right, back).
A loop closure joins the current pose b to an earlier pose a (``b - a >= loop_min_gap``) within
``loop_radius_m``, independently for each such pair, with probability
``p_loop * exp(-d^2 / (2 loop_scale_m^2))`` (d: their true distance); M3500's closures fall off
with distance like that (seen in its ground truth: 12% of the coincident pairs closed, 4.5% at
1 m, 0.6% at 2 m).

Every measurement (odometry and loop closure) gets the same noise: ``Z = (X_a^-1 X_b) Exp(xi)``
with ``xi`` ~ N(0, diag(trans_sigma_m^2, ..., rot_sigma_rad^2, ...)) over (rho, phi) (2D:
x, y and yaw only) and the matching information ``diag(1 / sigma^2)`` (2D: lifted as a g2o
``EDGE_SE2`` is, docs/conventions.md).  The graph's vertices are the noisy odometry chained from the
true first pose (the poor initial guess of M3500).  A 2D grid is written as ``VERTEX_SE2`` /
``EDGE_SE2``.

Hard graphs (robustness to local minima): :data:`GRID_PRESETS` ``m3500a``, ``m3500b``,
``m3500c`` raise the rotation noise to 0.1, 0.2 and 0.3 rad (the M3500a/b/c of Carlone et al.,
"Initialization techniques for 3D SLAM", 2015; here with information matching the noise); for a
family, vary ``rot_sigma_rad`` and ``seed``::

    for s in 0.1 0.2 0.3 0.5; do for k in 0 1 2 3; do
      hybridpgo generate grid --preset m3500 --rot-sigma $s --seed $k \\
          -o hard_${s}_${k}.g2o --ground-truth hard_${s}_${k}_gt.g2o
    done; done

Randomness: ``seed`` feeds a :class:`numpy.random.SeedSequence` whose independent children drive
the route, the odometry noise, the loop closures and the outliers (so the graphs with and
without outliers share everything else).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._numba import kernel
from ..geometry import se3
from ..graph import FloatArray, PoseGraph, lift_information_2d
from ._common import diag_information, perturb
from ._drive import drive_graph, preset_values, with_outliers
from .outliers import Outliers, no_outliers

__all__ = ["GRID_PRESETS", "Grid", "GridParams", "generate_grid"]

#: M3500's measurement sigma (m and rad): its information is 2000 (iSAM's square root 44.72).
M3500_SIGMA = 1.0 / math.sqrt(2000.0)

#: Grid side (blocks) per sqrt(pose) when ``nx``/``ny`` are not given (2D), and per cube root
#: of the poses in 3D: chosen so that the default 3500 poses revisit places about as often as
#: M3500 (2D: 43 x 43 blocks, 1 745-2 983 loop closures over seeds 0-19, mean 2 151, where
#: M3500 has 2 099; 3D: 13 x 13 x 13, about 2 100).
_SIDE_2D = 0.73
_SIDE_3D = 0.86


@dataclass(frozen=True, slots=True)
class GridParams:
    """Every knob of :func:`generate_grid`, with its default (the M3500-like grid).

    Validated in ``__post_init__``; ``nx``, ``ny``, ``nz`` left as None are filled in from
    ``num_poses`` by :func:`generate_grid`.
    """

    num_poses: int = 3500
    """Number of poses N (N - 1 unit steps)."""
    dim: int = 2
    """2: a planar grid (written as g2o SE2); 3: a cubic lattice with up/down turns."""
    nx: int | None = None
    """Blocks along x (None: about ``sqrt(num_poses)``, or its cube root in 3D)."""
    ny: int | None = None
    """Blocks along y (None: as nx)."""
    nz: int | None = None
    """Blocks along z, 3D only (None: as nx; a 2D grid has none)."""
    street_spacing: int = 1
    """Unit steps per block: the robot turns only at intersections (1: at every step)."""
    p_turn: float = 0.16
    """Probability of turning left or right (half each) at an intersection."""
    p_uturn: float = 0.08
    """Probability of turning back at an intersection."""
    p_climb: float = 0.1
    """3D: probability of turning up or down (half each) at an intersection."""
    trans_sigma_m: float = M3500_SIGMA
    """Translation noise of every measurement, each axis, metres (unit step = 1 m)."""
    rot_sigma_rad: float = M3500_SIGMA
    """Rotation noise of every measurement, each axis (2D: yaw), radians."""
    p_loop: float = 0.12
    """Probability that a pair of poses at the same place is closed (falls off with distance)."""
    loop_radius_m: float = 3.0
    """Only pairs within this true distance are candidates, metres."""
    loop_scale_m: float = 0.8
    """Gaussian fall-off of the closure probability with distance (inf: none), metres."""
    loop_min_gap: int = 4
    """A closure joins poses at least this many steps apart."""
    num_outliers: int = 0
    """Number of false loop closures added (:mod:`hybridpgo.generate.outliers`)."""
    near_miss_fraction: float = 0.5
    """Fraction of the outliers that are near misses (the rest join random pose pairs)."""
    near_miss_min_m: float = 4.0
    """A near miss joins two poses at least this far apart (true distance), metres ..."""
    near_miss_max_m: float = 8.0
    """... and at most this far apart."""

    def __post_init__(self) -> None:
        def is_int(v: object) -> bool:
            return isinstance(v, int | np.integer) and not isinstance(v, bool)

        if not is_int(self.num_poses) or self.num_poses < 2:
            raise ValueError(f"num_poses must be an integer >= 2, got {self.num_poses!r}")
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {self.dim!r}")
        for name in ("nx", "ny", "nz"):
            v = getattr(self, name)
            if v is not None and (not is_int(v) or v < 1):
                raise ValueError(f"{name} must be a positive integer or None, got {v!r}")
        if self.dim == 2 and self.nz is not None:
            raise ValueError("nz is for 3D grids (dim=3) only")
        for name in ("street_spacing", "loop_min_gap"):
            v = getattr(self, name)
            if not is_int(v) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if not is_int(self.num_outliers) or self.num_outliers < 0:
            raise ValueError(f"num_outliers must be an integer >= 0, got {self.num_outliers!r}")
        for name in ("p_turn", "p_uturn", "p_climb", "p_loop", "near_miss_fraction"):
            v = float(getattr(self, name))
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v!r}")
        climb = self.p_climb if self.dim == 3 else 0.0
        if self.p_turn + self.p_uturn + climb > 1.0:
            raise ValueError("p_turn + p_uturn (+ p_climb in 3D) must be at most 1, got "
                             f"{self.p_turn + self.p_uturn + climb!r}")
        for name in ("trans_sigma_m", "rot_sigma_rad", "loop_radius_m", "near_miss_min_m"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a non-negative number, got {v!r}")
        if not self.loop_scale_m > 0.0:
            raise ValueError(f"loop_scale_m must be positive (inf: no fall-off), got "
                             f"{self.loop_scale_m!r}")
        if not (math.isfinite(self.near_miss_max_m)
                and self.near_miss_min_m <= self.near_miss_max_m):
            raise ValueError("need near_miss_min_m <= near_miss_max_m, got "
                             f"{self.near_miss_min_m!r}, {self.near_miss_max_m!r}")

    def resolved(self) -> GridParams:
        """These parameters with ``nx``, ``ny`` (and in 3D ``nz``) filled in from num_poses."""
        if self.dim == 2:
            side = max(1, round(_SIDE_2D * math.sqrt(self.num_poses) / self.street_spacing))
        else:
            side = max(1, round(_SIDE_3D * self.num_poses ** (1.0 / 3.0) / self.street_spacing))
        nx = self.nx if self.nx is not None else side
        ny = self.ny if self.ny is not None else nx
        nz = (self.nz if self.nz is not None else nx) if self.dim == 3 else None
        return dataclasses.replace(self, nx=nx, ny=ny, nz=nz)


#: Presets: ``m3500`` is the M3500-like default; ``m3500a``/``b``/``c`` are the hard variants
#: with rotation noise 0.1/0.2/0.3 rad on every measurement (module docstring); ``grid3d`` is a
#: 3D lattice of the same size and noise.
GRID_PRESETS: dict[str, dict[str, Any]] = {
    "m3500": {},
    "m3500a": {"rot_sigma_rad": 0.1},
    "m3500b": {"rot_sigma_rad": 0.2},
    "m3500c": {"rot_sigma_rad": 0.3},
    "grid3d": {"dim": 3},
}


@dataclass(frozen=True, slots=True)
class Grid:
    """A generated grid world: the pose graph and the true poses (same dense indexing)."""

    graph: PoseGraph
    """The pose graph; node ids 0..N-1 in driving order; vertex estimates are dead reckoning;
    ``is_2d`` for a 2D grid."""
    truth_rotations: FloatArray
    """(N, 3, 3) float64: true R_world_node (entries 0 and +-1)."""
    truth_translations: FloatArray
    """(N, 3) float64: true t_world_node, metres (integers; z = 0 in 2D)."""
    name: str
    """The preset's name, or "grid" for custom parameters."""
    params: GridParams
    """The parameters the grid was generated with (nx, ny, nz filled in)."""
    outliers: Outliers = dataclasses.field(default_factory=no_outliers)
    """Which edges of ``graph`` are false loop closures (none unless ``num_outliers``)."""

    @property
    def num_loop_edges(self) -> int:
        """Number of true loop closures (edges other than odometry and outliers)."""
        return self.graph.num_edges - (self.graph.num_nodes - 1) - self.outliers.num_outliers


def generate_grid(preset: str | None = None, *, seed: int = 0, **params: Any) -> Grid:
    """Generate a Manhattan-world graph (M3500-like) with ground truth.

    Parameters
    ----------
    preset : {"m3500", "m3500a", "m3500b", "m3500c", "grid3d"} or None
        Start from the preset's parameters (:data:`GRID_PRESETS`); None: the
        :class:`GridParams` defaults (which are ``m3500``'s).
    seed : int
        Seed of all the randomness; the same seed gives bit-identical output.
    **params
        Any :class:`GridParams` field, overriding the preset.

    Returns
    -------
    Grid

    Raises
    ------
    ValueError
        Unknown preset or an invalid parameter value.
    TypeError
        A parameter name that is not a :class:`GridParams` field.
    """
    values = preset_values(GRID_PRESETS, preset, params, GridParams, "grid", "grid preset")
    p = GridParams(**values).resolved()
    route_rng, odom_rng, loop_rng, outlier_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4))

    rot, trans = _true_poses(p, route_rng)
    n = p.num_poses
    planar = p.dim == 2
    ts, rs = p.trans_sigma_m, p.rot_sigma_rad
    sigma6 = np.array([ts, ts, 0.0, 0.0, 0.0, rs] if planar else [ts] * 3 + [rs] * 3)
    if planar:  # information as a g2o EDGE_SE2 line is read (docs/conventions.md)
        info1 = lift_information_2d(diag_information(np.array([[ts, ts, rs]])))[0]
    else:
        info1 = diag_information(sigma6[None])[0]

    zr, zt = se3.between(rot[:-1], trans[:-1], rot[1:], trans[1:])
    zr, zt = perturb(zr, zt, np.broadcast_to(sigma6, (n - 1, 6)), odom_rng)
    la, lb = _loop_pairs(p, trans, loop_rng)
    lr, lt = se3.between(rot[la], trans[la], rot[lb], trans[lb])
    lr, lt = perturb(lr, lt, np.broadcast_to(sigma6, (la.shape[0], 6)), loop_rng)

    m = n - 1 + la.shape[0]
    graph = drive_graph(rot, trans, (zr, zt), (la, lb, lr, lt),
                        np.broadcast_to(info1, (m, 6, 6)), is_2d=planar)
    graph, outliers = with_outliers(graph, rot, trans, p, outlier_rng)
    return Grid(graph=graph, truth_rotations=rot, truth_translations=trans,
                name=preset if preset is not None else "grid", params=p, outliers=outliers)


# =========================================================================== route
def _turns(p: GridParams) -> tuple[FloatArray, FloatArray]:
    """Turn rotations in the body frame (x forward, y left, z up) and their probabilities:
    straight, left, right, back (and in 3D up, down)."""
    rz = np.array([[[1, 0, 0], [0, 1, 0], [0, 0, 1]],       # straight
                   [[0, -1, 0], [1, 0, 0], [0, 0, 1]],      # left: Rz(+90)
                   [[0, 1, 0], [-1, 0, 0], [0, 0, 1]],      # right: Rz(-90)
                   [[-1, 0, 0], [0, -1, 0], [0, 0, 1]]],    # back: Rz(180)
                  dtype=np.float64)
    w = [1.0 - p.p_turn - p.p_uturn, p.p_turn / 2, p.p_turn / 2, p.p_uturn]
    if p.dim == 3:
        ry = np.array([[[0, 0, -1], [0, 1, 0], [1, 0, 0]],   # up: Ry(-90), x -> +z
                       [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]],  # down: Ry(+90), x -> -z
                      dtype=np.float64)
        rz = np.concatenate([rz, ry])
        w[0] -= p.p_climb
        w += [p.p_climb / 2, p.p_climb / 2]
    return rz, np.maximum(np.array(w), 0.0)


def _true_poses(p: GridParams, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """True (R_world_node, t_world_node): exact integers (positions) and 0/+-1 (rotations)."""
    assert p.nx is not None and p.ny is not None
    k = p.street_spacing
    hi = np.array([p.nx * k, p.ny * k, (p.nz or 0) * k], dtype=np.float64)
    start = np.array([rng.integers(0, p.nx + 1) * k, rng.integers(0, p.ny + 1) * k,
                      rng.integers(0, (p.nz or 0) + 1) * k], dtype=np.float64)
    yaw = int(rng.integers(4))
    c, s = [1, 0, -1, 0][yaw], [0, 1, 0, -1][yaw]
    rot0 = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)
    turns, weights = _turns(p)
    u = rng.random(p.num_poses - 1)
    rot = np.empty((p.num_poses, 3, 3))
    trans = np.empty((p.num_poses, 3))
    _walk(u, turns, weights, hi, float(k), start, rot0, rot, trans)
    return rot, trans


@kernel
def _walk(u: FloatArray, turns: FloatArray, weights: FloatArray, hi: FloatArray,
          spacing: float, start: FloatArray, rot0: FloatArray, rot: FloatArray,
          trans: FloatArray) -> None:
    """The random walk: at an intersection choose a turn (weights among those that stay in the
    box [0, hi]; uniformly among those if all their weights are 0), then step once along the
    new x axis.  ``u`` (n - 1,) uniform numbers in [0, 1) drive the choices."""
    n = trans.shape[0]
    nt = turns.shape[0]
    w = np.empty(nt)
    cand = np.empty((nt, 3, 3))
    trans[0] = start
    rot[0] = rot0
    for i in range(n - 1):
        at_x = True
        for d in range(3):
            if trans[i, d] % spacing != 0.0:
                at_x = False
        total = 0.0
        feasible = 0
        for j in range(nt):
            w[j] = -1.0  # infeasible
            if j > 0 and not at_x:
                continue
            for r in range(3):
                for c in range(3):
                    acc = 0.0
                    for q in range(3):
                        acc += rot[i, r, q] * turns[j, q, c]
                    cand[j, r, c] = acc
            inside = True
            for d in range(3):
                x = trans[i, d] + cand[j, d, 0]
                if x < 0.0 or x > hi[d]:
                    inside = False
            if inside:
                w[j] = weights[j]
                total += weights[j]
                feasible += 1
        if total > 0.0:
            target = u[i] * total
        else:  # every feasible turn has weight 0: choose uniformly among them
            for j in range(nt):
                if w[j] >= 0.0:
                    w[j] = 1.0
            target = u[i] * feasible
        pick = -1
        acc = 0.0
        for j in range(nt):
            if w[j] > 0.0:
                pick = j
                acc += w[j]
                if acc > target:
                    break
        rot[i + 1] = cand[pick]
        for d in range(3):
            trans[i + 1, d] = trans[i, d] + cand[pick, d, 0]


# =========================================================================== loop closures
def _loop_pairs(p: GridParams, trans: FloatArray, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
    """Loop closures (a, b), a < b, sorted by (b, a): each candidate pair is closed
    independently with its probability (module docstring)."""
    from scipy.spatial import cKDTree

    empty = np.zeros(0, np.int64)
    if p.p_loop == 0.0:
        return empty, empty
    pairs = cKDTree(trans).query_pairs(r=p.loop_radius_m, output_type="ndarray")
    if pairs.shape[0] == 0:
        return empty, empty
    a = pairs.min(axis=1).astype(np.int64)
    b = pairs.max(axis=1).astype(np.int64)
    keep = b - a >= p.loop_min_gap
    a, b = a[keep], b[keep]
    srt = np.lexsort((a, b))  # canonical order before drawing
    a, b = a[srt], b[srt]
    d2 = np.sum((trans[b] - trans[a]) ** 2, axis=1)
    prob = p.p_loop * np.exp(-0.5 * d2 / p.loop_scale_m**2)
    hit = rng.random(a.shape[0]) < prob
    return a[hit], b[hit]
