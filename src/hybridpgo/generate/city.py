"""Synthetic city pose graphs with ground truth (paper section IV, Fig. 3, Table II, Fig. 8).

A vehicle drives for a long time through a street grid in 3D (gentle elevation), turning at
intersections at random with a bias to re-drive streets it knows.  The generator returns the
pose graph a SLAM front end would produce (odometry between consecutive poses, loop closures
detected only with some probability when the vehicle revisits a street, optional GPS readings)
together with the true poses.

Example (not a doctest)::

    from hybridpgo.generate import generate_city, write_ground_truth
    from hybridpgo.io import write_graph

    city = generate_city("valencia", seed=0, gps_every=100)  # 15031 poses, ~120 loops, 151 GPS
    write_graph(city.graph, "valencia_gps.g2o")
    write_ground_truth("valencia_gt.g2o", city.graph, city.truth_rotations,
                       city.truth_translations)

Frames and conventions
----------------------
* World ("earth") frame: x east, y north, z up, metres; the city spans
  ``[0, nx * block_size_m] x [0, ny * block_size_m]`` around height 0.
* Vehicle frame: x forward (direction of travel), y left, z up (the terrain normal
  orthogonalized against x), so roll and pitch are the terrain's cross and along slopes.
* Relative measurement of edge ``(a, b)``: ``Z = (X_a^-1 X_b) Exp(xi)`` with ``xi = (rho, phi)``
  ~ N(0, Sigma) in b's frame and information ``Omega = Sigma^-1`` (docs/conventions.md); so the
  error of
  the true poses is ``-xi`` and the true poses have energy ~ chi^2 with 6 degrees of freedom per
  relative edge (3 per GPS reading).
* A sigma of 0 gives an exact measurement; its information uses :data:`MIN_SIGMA` instead (an
  exact measurement would have infinite information).
* The graph's vertex estimates are dead reckoning: the noisy odometry chained from the true first
  pose (so with GPS the first pose sits at its true earth-frame pose).

Randomness: ``seed`` feeds one :class:`numpy.random.SeedSequence` whose independent children
drive the route, the odometry noise, the loop closures, the GPS noise and the outliers.  So the
same seed gives bit-identical output, and the graphs with and without GPS (``gps_every``) or
outliers (``num_outliers``) share the same route, odometry and loop closures: only the GPS
constraints or the false edges differ.

Size: :func:`scale_city` gives the parameters of a city of any number of poses shaped like a
preset (the street grid grows with the drive, so the loop-closure density stays the preset's);
generation is vectorized (a 1M-pose city: about 11 s of CPU time and 2 GB of memory).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from ..geometry import se3
from ..graph import FloatArray, IntArray, PoseGraph
from ._common import diag_information, perturb
from ._drive import check_preset, drive_graph, preset_values, with_outliers
from .outliers import Outliers, no_outliers

__all__ = ["PRESETS", "City", "CityParams", "generate_city", "scale_city"]

#: Resolution (m) of the densely sampled street polyline that is smoothed into the route.
_FINE_STEP_M = 0.25


@dataclass(frozen=True, slots=True)
class CityParams:
    """Every knob of :func:`generate_city`, with its default (presets override some).

    Validated in ``__post_init__``; an unknown name passed to :func:`generate_city` raises
    ``TypeError`` listing these fields.
    """

    nx: int = 8
    """Number of blocks along x (east); the grid has ``nx + 1`` north-south streets."""
    ny: int = 8
    """Number of blocks along y (north); the grid has ``ny + 1`` east-west streets."""
    block_size_m: float = 100.0
    """Distance between neighbouring parallel streets (street centre lines), metres."""
    elevation_m: float = 4.0
    """Peak-to-peak range bound of the smooth height field, metres (0: a flat city)."""
    elevation_wavelength_m: float = 600.0
    """Typical wavelength of the height field (three random plane waves within 0.7-1.4x)."""
    num_poses: int = 2000
    """Number of poses N of the drive."""
    step_m: float = 2.0
    """Mean distance driven between consecutive poses, metres."""
    step_jitter: float = 0.2
    """Each step is ``step_m * U(1 - step_jitter, 1 + step_jitter)`` (speed variation)."""
    lane_offset_m: float = 1.5
    """The vehicle drives this far right of the street's centre line: runs in opposite
    directions are ``2 * lane_offset_m`` apart."""
    corner_radius_m: float = 6.0
    """Corners are rounded by a moving average over ``2 * corner_radius_m`` of path."""
    straight_weight: float = 2.0
    """Relative weight of going straight at an intersection (a left or right turn weighs 1;
    U-turns never happen)."""
    revisit_bias: float = 1.0
    """A street segment driven before weighs ``1 + revisit_bias`` times more (> -1; a negative
    bias makes the vehicle prefer streets it has not driven yet)."""
    odom_trans_sigma_per_m: float = 0.01
    """Odometry translation noise: sigma (each axis) per metre driven in that step."""
    odom_yaw_sigma_deg: float = 0.1
    """Odometry rotation noise about the vehicle's z axis, per step, degrees."""
    odom_roll_pitch_sigma_deg: float = 0.02
    """Odometry rotation noise about the vehicle's x and y axes, per step, degrees."""
    p_loop: float = 0.05
    """Probability that a pose with a loop-closure candidate gets a loop closure."""
    loop_density: float | None = None
    """Target number of loop closures per pose: when set, ``p_loop`` is replaced by the
    probability that gives this many in expectation (the fraction of poses with a candidate is
    estimated from up to 20 000 sampled poses), capped at 1.  :func:`scale_city` sets it."""
    loop_radius_m: float = 4.0
    """A candidate is an earlier pose within this horizontal distance ..."""
    loop_max_heading_deg: float = 20.0
    """... driving along the same street: heading within this angle of the current heading
    or of its opposite ..."""
    loop_min_gap: int = 100
    """... and at least this many poses earlier (not among the recent ones)."""
    loop_trans_sigma_m: float = 0.1
    """Loop closure translation noise (each axis), metres."""
    loop_rot_sigma_deg: float = 0.5
    """Loop closure rotation noise (each axis), degrees."""
    gps_every: int | None = None
    """GPS reading on poses 0, k, 2k, ... (``ceil(N / k)`` readings); None: no GPS."""
    gps_sigma_h_m: float = 2.0
    """GPS horizontal noise (x and y), metres."""
    gps_sigma_v_m: float = 4.0
    """GPS vertical noise, metres."""
    num_outliers: int = 0
    """Number of false loop closures added (:mod:`hybridpgo.generate.outliers`)."""
    near_miss_fraction: float = 0.5
    """Fraction of the outliers that are near misses (the rest join random pose pairs)."""
    near_miss_min_m: float = 6.0
    """A near miss joins two poses at least this far apart (true 3D distance), metres ..."""
    near_miss_max_m: float = 15.0
    """... and at most this far apart."""

    def __post_init__(self) -> None:
        positive_int = ("nx", "ny", "num_poses")
        for name in positive_int:
            v = getattr(self, name)
            if not isinstance(v, int | np.integer) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if self.num_poses < 2:
            raise ValueError(f"num_poses must be at least 2, got {self.num_poses}")
        positive = ("block_size_m", "step_m", "elevation_wavelength_m", "straight_weight")
        non_negative = ("elevation_m", "lane_offset_m", "corner_radius_m",
                        "odom_trans_sigma_per_m", "odom_yaw_sigma_deg",
                        "odom_roll_pitch_sigma_deg", "loop_radius_m", "loop_trans_sigma_m",
                        "loop_rot_sigma_deg", "gps_sigma_h_m", "gps_sigma_v_m", "step_jitter")
        for name in positive:
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        for name in non_negative:
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a non-negative number, got {v!r}")
        if not (math.isfinite(self.revisit_bias) and self.revisit_bias > -1.0):
            raise ValueError(f"revisit_bias must be greater than -1, got {self.revisit_bias!r}")
        if not 0.0 <= self.p_loop <= 1.0:
            raise ValueError(f"p_loop must be in [0, 1], got {self.p_loop!r}")
        if self.loop_density is not None and not (math.isfinite(self.loop_density)
                                                  and self.loop_density >= 0.0):
            raise ValueError(f"loop_density must be a number >= 0 or None, got "
                             f"{self.loop_density!r}")
        if self.step_jitter >= 1.0:
            raise ValueError(f"step_jitter must be below 1, got {self.step_jitter!r}")
        if not 0.0 <= self.loop_max_heading_deg <= 90.0:
            raise ValueError("loop_max_heading_deg must be in [0, 90], got "
                             f"{self.loop_max_heading_deg!r}")
        if self.loop_min_gap < 1:
            raise ValueError(f"loop_min_gap must be at least 1, got {self.loop_min_gap!r}")
        if self.gps_every is not None and (not isinstance(self.gps_every, int | np.integer)
                                           or self.gps_every < 0):
            raise ValueError(f"gps_every must be an integer >= 0 or None, got "
                             f"{self.gps_every!r}")
        if self.gps_every == 0:  # 0 means no GPS, like None
            object.__setattr__(self, "gps_every", None)
        if not isinstance(self.num_outliers, int | np.integer) or self.num_outliers < 0:
            raise ValueError(f"num_outliers must be an integer >= 0, got {self.num_outliers!r}")
        if not 0.0 <= self.near_miss_fraction <= 1.0:
            raise ValueError(f"near_miss_fraction must be in [0, 1], got "
                             f"{self.near_miss_fraction!r}")
        if not (math.isfinite(self.near_miss_max_m)
                and 0.0 <= self.near_miss_min_m <= self.near_miss_max_m):
            raise ValueError("need 0 <= near_miss_min_m <= near_miss_max_m, got "
                             f"{self.near_miss_min_m!r}, {self.near_miss_max_m!r}")
        if 2.0 * self.lane_offset_m >= self.block_size_m:
            raise ValueError("lane_offset_m must be less than half of block_size_m")


#: Presets shaped like the paper's Table II graphs: the same pose counts, and ``p_loop`` tuned
#: so that seed 0 gives the loop-edge counts (paper -> seed 0; range over seeds 0-7):
#: Valencia 122 -> 119 (81-123), Paris1 590 -> 588 (512-588), Paris2 13 384 -> 13 416
#: (13 319-13 583).  The spread comes from the random route (how much of it revisits streets)
#: and is largest for Valencia's few closures.  Use ``gps_every=100`` for the "w/GPS" rows.
PRESETS: dict[str, dict[str, Any]] = {
    # A large city driven mostly once (the vehicle prefers new streets): few closures.
    "valencia": dict(nx=20, ny=14, block_size_m=110.0, num_poses=15031, step_m=2.0,
                     revisit_bias=-0.8, p_loop=0.046, elevation_m=6.0,
                     elevation_wavelength_m=900.0),
    # A longer drive that re-drives streets now and then; few closures per revisit, so many
    # parallel runs stay unconnected (paper Fig. 3c).
    "paris1": dict(nx=14, ny=12, block_size_m=100.0, num_poses=27093, step_m=2.0,
                   revisit_bias=0.5, p_loop=0.038, elevation_m=5.0,
                   elevation_wavelength_m=700.0),
    # A small hilly quarter (Montmartre) driven over and over: many closures.
    "paris2": dict(nx=8, ny=6, block_size_m=80.0, num_poses=41957, step_m=2.0,
                   revisit_bias=1.0, p_loop=0.36, elevation_m=8.0,
                   elevation_wavelength_m=500.0),
}


@dataclass(frozen=True, slots=True)
class City:
    """A generated city: the pose graph and the true poses (same dense indexing)."""

    graph: PoseGraph
    """The pose graph; node ids 0..N-1 in driving order; vertex estimates are dead reckoning."""
    truth_rotations: FloatArray
    """(N, 3, 3) float64: true R_world_node."""
    truth_translations: FloatArray
    """(N, 3) float64: true t_world_node, metres."""
    name: str
    """The preset's name, or "city" for custom parameters."""
    params: CityParams
    """The parameters the city was generated with."""
    outliers: Outliers = dataclasses.field(default_factory=no_outliers)
    """Which edges of ``graph`` are false loop closures (none unless ``num_outliers``)."""

    @property
    def num_loop_edges(self) -> int:
        """Number of true loop closures (edges other than the N - 1 odometry edges and the
        outliers)."""
        return self.graph.num_edges - (self.graph.num_nodes - 1) - self.outliers.num_outliers


def generate_city(preset: str | None = None, *, seed: int = 0, gps_every: int | None = None,
                  **params: Any) -> City:
    """Generate a city drive with odometry, loop closures, optional GPS and ground truth.

    Parameters
    ----------
    preset : {"valencia", "paris1", "paris2"} or None
        Start from the preset's parameters (:data:`PRESETS`); None: the :class:`CityParams`
        defaults.
    seed : int
        Seed of all the randomness; the same seed gives bit-identical output.
    gps_every : int or None
        A GPS reading on every ``gps_every``-th pose (the paper: 100); 0: no GPS; None: the
        preset's (no GPS).
    **params
        Any :class:`CityParams` field, overriding the preset.

    Returns
    -------
    City

    Raises
    ------
    ValueError
        Unknown preset or an invalid parameter value.
    TypeError
        A parameter name that is not a :class:`CityParams` field.
    """
    values = preset_values(PRESETS, preset, params, CityParams, "city", "preset")
    if gps_every is not None:
        values["gps_every"] = gps_every
    p = CityParams(**values)

    route_rng, odom_rng, loop_rng, gps_rng, outlier_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5))
    rot, trans = _true_poses(p, route_rng)
    n = p.num_poses

    # Odometry: consecutive true relative poses, noise on the right (module docstring).
    zr, zt = se3.between(rot[:-1], trans[:-1], rot[1:], trans[1:])
    dist = np.linalg.norm(zt, axis=1)
    sig_t = p.odom_trans_sigma_per_m * dist
    sig_rp = math.radians(p.odom_roll_pitch_sigma_deg)
    sig_y = math.radians(p.odom_yaw_sigma_deg)
    odom_sigma = np.column_stack([sig_t, sig_t, sig_t, np.full((n - 1, 2), sig_rp),
                                  np.full(n - 1, sig_y)])
    zr, zt = perturb(zr, zt, odom_sigma, odom_rng)

    # Loop closures (a = earlier pose, b = later pose).
    la, lb = _loop_pairs(p, rot, trans, loop_rng)
    lr, lt = se3.between(rot[la], trans[la], rot[lb], trans[lb])
    sig_lt = p.loop_trans_sigma_m
    sig_lr = math.radians(p.loop_rot_sigma_deg)
    loop_sigma = np.tile([sig_lt] * 3 + [sig_lr] * 3, (la.shape[0], 1))
    lr, lt = perturb(lr, lt, loop_sigma, loop_rng)

    gps_nodes = np.zeros(0, np.int32)
    gps_pos = np.zeros((0, 3))
    gps_info = np.zeros((0, 3, 3))
    if p.gps_every is not None:
        gps_nodes = np.arange(0, n, p.gps_every, dtype=np.int32)
        gps_sigma = np.array([p.gps_sigma_h_m, p.gps_sigma_h_m, p.gps_sigma_v_m])
        gps_pos = trans[gps_nodes] + gps_rng.normal(size=(gps_nodes.shape[0], 3)) * gps_sigma
        gps_info = diag_information(np.tile(gps_sigma, (gps_nodes.shape[0], 1)))

    # Edges in the order they would arrive online: each closure right after its later pose.
    graph = drive_graph(rot, trans, (zr, zt), (la, lb, lr, lt),
                        diag_information(np.concatenate([odom_sigma, loop_sigma])),
                        gps_nodes=gps_nodes, gps_positions=gps_pos, gps_information=gps_info)
    graph, outliers = with_outliers(graph, rot, trans, p, outlier_rng)
    return City(graph=graph, truth_rotations=rot, truth_translations=trans,
                name=preset if preset is not None else "city", params=p, outliers=outliers)


def scale_city(preset: str | None, num_poses: int) -> dict[str, Any]:
    """Parameters of a city of ``num_poses`` poses shaped like ``preset`` (None: the defaults).

    The street grid is scaled by ``sqrt(num_poses / preset poses)`` along each axis (at least
    one block), so the drive covers its streets about as often as the preset's does, and
    ``loop_density`` is set to the preset's own (its seed-0 drive's loop closures per pose):
    without it the density would creep up with the size, since a longer random drive in 2D
    revisits a larger share of its streets.  Everything else (block size, noise, GPS spacing
    when ``gps_every`` is given) is the preset's.  Pass the result to :func:`generate_city`::

        city = generate_city("paris1", **scale_city("paris1", 1_000_000), gps_every=100)

    Returns
    -------
    dict
        ``{"num_poses": ..., "nx": ..., "ny": ..., "loop_density": ...}``.
    """
    check_preset(PRESETS, preset, "preset")
    if not isinstance(num_poses, int | np.integer) or num_poses < 2:
        raise ValueError(f"num_poses must be an integer >= 2, got {num_poses!r}")
    base = CityParams(**(PRESETS[preset] if preset is not None else {}))
    f = math.sqrt(num_poses / base.num_poses)
    return {"num_poses": int(num_poses), "nx": max(1, round(base.nx * f)),
            "ny": max(1, round(base.ny * f)), "loop_density": _preset_loop_density(preset)}


@functools.cache
def _preset_loop_density(preset: str | None) -> float:
    """Loop closures per pose of the preset's seed-0 drive (generated once, then cached)."""
    city = generate_city(preset, seed=0)
    return city.num_loop_edges / city.graph.num_nodes


# =========================================================================== route
def _route_nodes(p: CityParams, rng: np.random.Generator, length_m: float) -> FloatArray:
    """Intersections (k, 2) in metres visited by a random drive of at least ``length_m``."""
    dirs = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # E, N, W, S (index + 1 = left turn)
    node = np.array([rng.integers(0, p.nx + 1), rng.integers(0, p.ny + 1)])
    valid = [d for d in range(4) if _inside(node + dirs[d], p)]
    heading = valid[rng.integers(len(valid))]
    visited: set[tuple[int, int, int, int]] = set()
    path = [node.copy()]
    needed = math.ceil(length_m / p.block_size_m) + 1
    for _ in range(needed):
        nxt = node + dirs[heading]
        visited.add(_segment(node, nxt))
        node = nxt
        path.append(node.copy())
        options, weights = [], []
        for turn, w in ((0, p.straight_weight), (1, 1.0), (3, 1.0)):  # straight, left, right
            d = (heading + turn) % 4
            after = node + dirs[d]
            if not _inside(after, p):
                continue
            if _segment(node, after) in visited:
                w *= 1.0 + p.revisit_bias
            options.append(d)
            weights.append(w)
        if not options:  # a 1-block-wide grid's end: the only way on is back
            options, weights = [(heading + 2) % 4], [1.0]
        wts = np.array(weights)
        heading = options[int(rng.choice(len(options), p=wts / wts.sum()))]
    return np.array(path, dtype=np.float64) * p.block_size_m


def _segment(a: npt.NDArray[np.int64], b: npt.NDArray[np.int64]) -> tuple[int, int, int, int]:
    """The undirected street segment between neighbouring intersections a and b."""
    lo, hi = sorted(((int(a[0]), int(a[1])), (int(b[0]), int(b[1]))))
    return (*lo, *hi)


def _inside(node: npt.NDArray[np.int64], p: CityParams) -> bool:
    return bool(0 <= node[0] <= p.nx and 0 <= node[1] <= p.ny)


def _lane_polyline(nodes: FloatArray, offset: float) -> FloatArray:
    """The route's intersections shifted ``offset`` to the right of the direction of travel."""
    d = np.diff(nodes, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    right = np.column_stack([d[:, 1], -d[:, 0]])
    out = np.empty_like(nodes)
    out[0] = nodes[0] + offset * right[0]
    out[-1] = nodes[-1] + offset * right[-1]
    r1, r2 = right[:-1], right[1:]
    # Corner of the two offset lines: (r1 + r2) / (1 + r1.r2) (r1 for straight, r1 + r2 at a
    # right angle).  A U-turn (r1 = -r2) only happens at a 1-block grid's end: use the node.
    den = 1.0 + np.einsum("ij,ij->i", r1, r2)
    corner = np.where(den[:, None] > 1e-9, (r1 + r2) / np.maximum(den, 1e-9)[:, None], 0.0)
    out[1:-1] = nodes[1:-1] + offset * corner
    return out


def _resample(poly: FloatArray, step: float) -> tuple[FloatArray, FloatArray]:
    """Points every ``step`` metres along a polyline, and the polyline's arc length."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 0.0])
    poly = poly[keep]
    s = np.concatenate([[0.0], np.cumsum(seg[seg > 0.0])])
    q = np.arange(0.0, s[-1], step)
    return np.column_stack([np.interp(q, s, poly[:, 0]), np.interp(q, s, poly[:, 1])]), q


def _height_field(p: CityParams, rng: np.random.Generator
                  ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Three random plane waves: (amplitude (3,), wave vectors (3, 2), phases (3,))."""
    k = 3
    ang = rng.uniform(0.0, 2.0 * np.pi, k)
    lam = p.elevation_wavelength_m * rng.uniform(0.7, 1.4, k)
    wave = (2.0 * np.pi / lam)[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    phase = rng.uniform(0.0, 2.0 * np.pi, k)
    amp = np.full(k, 0.5 * p.elevation_m / k)  # |h| <= elevation_m / 2
    return amp, wave, phase


def _true_poses(p: CityParams, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """True (R_world_node, t_world_node) of the drive."""
    n = p.num_poses
    steps = p.step_m * rng.uniform(1.0 - p.step_jitter, 1.0 + p.step_jitter, n - 1)
    window = max(1, round(2.0 * p.corner_radius_m / _FINE_STEP_M))
    margin = (window + 2) * _FINE_STEP_M
    # Driving on the right cuts every right turn's corner by up to 2 * lane_offset_m (and the
    # rounding a little more): ask the route for that much extra.
    slack = 1.05 + 4.0 * p.lane_offset_m / p.block_size_m
    length = (float(steps.sum()) + 2.0 * margin) * slack + 2.0 * p.block_size_m
    nodes = _route_nodes(p, rng, length)
    fine, _ = _resample(_lane_polyline(nodes, p.lane_offset_m), _FINE_STEP_M)
    if window > 1:  # round the corners: a moving average keeps straight streets straight
        kern = np.full(window, 1.0 / window)
        fine = np.column_stack([np.convolve(fine[:, 0], kern, mode="valid"),
                                np.convolve(fine[:, 1], kern, mode="valid")])
    seg = np.linalg.norm(np.diff(fine, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    tangent = np.gradient(fine, s, axis=0)
    q = margin + np.concatenate([[0.0], np.cumsum(steps)])
    assert q[-1] < s[-1], "the route is shorter than the drive"
    xy = np.column_stack([np.interp(q, s, fine[:, 0]), np.interp(q, s, fine[:, 1])])
    fwd = np.column_stack([np.interp(q, s, tangent[:, 0]), np.interp(q, s, tangent[:, 1])])
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)

    amp, wave, phase = _height_field(p, rng)
    arg = xy @ wave.T + phase  # (n, 3)
    z = np.sin(arg) @ amp
    grad = (np.cos(arg) * amp) @ wave  # (n, 2): dh/dx, dh/dy
    along = np.einsum("ij,ij->i", grad, fwd)
    x_axis = np.column_stack([fwd, along])
    x_axis /= np.linalg.norm(x_axis, axis=1, keepdims=True)
    normal = np.column_stack([-grad, np.ones(n)])
    y_axis = np.cross(normal, x_axis)
    y_axis /= np.linalg.norm(y_axis, axis=1, keepdims=True)
    z_axis = np.cross(x_axis, y_axis)
    rot = np.ascontiguousarray(np.stack([x_axis, y_axis, z_axis], axis=2))
    trans = np.column_stack([xy, z])
    return rot, trans


# =========================================================================== loop closures
def _loop_pairs(p: CityParams, rot: FloatArray, trans: FloatArray, rng: np.random.Generator
                ) -> tuple[IntArray, IntArray]:
    """Loop closures (earlier a, later b): each pose b is drawn with probability ``p_loop``
    (or the one that gives ``loop_density``); if it has candidates (the ``loop_*`` fields of
    :class:`CityParams`), one of them is chosen uniformly at random."""
    n = trans.shape[0]
    xy = trans[:, :2]
    tree = None
    p_loop = p.p_loop
    if p.loop_density is not None:
        tree = cKDTree(xy)
        p_loop = _p_loop_for_density(p, rot, xy, tree, rng)
    drawn = np.flatnonzero(rng.random(size=(n,)) < p_loop)
    drawn = drawn[drawn >= p.loop_min_gap]
    empty = np.zeros(0, np.int32)
    if drawn.size == 0 or p.loop_radius_m == 0.0:
        return empty, empty
    owner, cand = _candidates(p, rot, xy, cKDTree(xy) if tree is None else tree, drawn)
    order = np.lexsort((cand, owner))  # canonical order, then a random key per candidate
    owner, cand = owner[order], cand[order]
    key = rng.random(size=(owner.shape[0],))
    pick = np.lexsort((key, owner))
    last = np.concatenate([owner[pick][1:] != owner[pick][:-1], [True]])
    chosen = pick[last] if owner.size else np.zeros(0, np.int64)
    return cand[chosen].astype(np.int32), owner[chosen].astype(np.int32)


def _candidates(p: CityParams, rot: FloatArray, xy: FloatArray, tree: cKDTree,
                owners: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64],
                                                        npt.NDArray[np.int64]]:
    """Every (owner, candidate) pair: an earlier pose within ``loop_radius_m``, at least
    ``loop_min_gap`` poses back, driving along the same street (either direction)."""
    hits = tree.query_ball_point(xy[owners], r=p.loop_radius_m)
    counts = np.fromiter((len(h) for h in hits), np.int64, owners.size)
    cand = np.fromiter(itertools.chain.from_iterable(hits), np.int64, int(counts.sum()))
    owner = np.repeat(owners, counts)
    heading = rot[:, :2, 0]  # horizontal part of the x axis
    cos = np.einsum("ij,ij->i", heading[owner], heading[cand])
    cos /= np.linalg.norm(heading[owner], axis=1) * np.linalg.norm(heading[cand], axis=1)
    ok = (cand <= owner - p.loop_min_gap) & (np.abs(cos) >= math.cos(
        math.radians(p.loop_max_heading_deg)))
    return owner[ok], cand[ok]


def _p_loop_for_density(p: CityParams, rot: FloatArray, xy: FloatArray, tree: cKDTree,
                        rng: np.random.Generator) -> float:
    """The p_loop that gives ``loop_density`` closures per pose in expectation."""
    assert p.loop_density is not None
    n = xy.shape[0]
    eligible = n - p.loop_min_gap
    if eligible <= 0 or p.loop_radius_m == 0.0:
        return 1.0
    sample = p.loop_min_gap + rng.choice(eligible, size=min(eligible, 20000), replace=False)
    owner, _ = _candidates(p, rot, xy, tree, np.sort(sample))
    with_candidates = np.unique(owner).size / sample.size * eligible
    if with_candidates == 0:
        return 1.0
    return min(1.0, float(p.loop_density * n / with_candidates))
