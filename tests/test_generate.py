"""Tests of the generators ``hybridpgo.generate``: the city (paper Table II, Fig. 3,
Fig. 8), its size scaling, the grid world and outliers."""

from __future__ import annotations

import csv
import dataclasses
import math
import sys
from collections.abc import Callable
from pathlib import Path
from types import FrameType

import numpy as np
import pytest
from tolerances import FLOAT64_IDENTITY

from hybridpgo.energy import constraint_energies, energy
from hybridpgo.generate import (
    GRID_PRESETS,
    MIN_SIGMA,
    OUTLIER_KINDS,
    PRESETS,
    City,
    CityParams,
    Grid,
    GridParams,
    Outliers,
    add_outliers,
    generate_city,
    generate_grid,
    noisify,
    scale_city,
    write_ground_truth,
    write_outliers,
)
from hybridpgo.geometry import se3, so3
from hybridpgo.io import read_graph, write_graph
from hybridpgo.metrics import read_ground_truth

#: A small city that generates in milliseconds: 4 x 4 blocks of 60 m, 1500 poses (3 km).
SMALL = dict(nx=4, ny=4, block_size_m=60.0, num_poses=1500, p_loop=0.2)

#: Energy of the true poses against noise-free measurements: the residuals are rounding
#: (~1e-15 m and rad) weighted by 1 / MIN_SIGMA^2 = 1e12 information.
NOISE_FREE_ENERGY = 1e-9

#: Dead reckoning from exact odometry vs the truth (a log-depth product of ~1e3 poses of ~1e3 m).
NOISE_FREE_CHAIN = 1e-9

#: A chi^2 with k degrees of freedom is within this many standard deviations sqrt(2k) of k.
CHI2_SIGMAS = 5.0

#: Relative accuracy of a standard deviation estimated from k >= 1400 samples (its own relative
#: standard error is 1/sqrt(2k) < 2%: this is 5 of those).
SAMPLE_STD_RTOL = 0.1

#: Paper Table II loop-edge counts, matched within this fraction with the default seed.
PRESET_COUNT_RTOL = 0.1


def small_city(seed: int = 0, **kw: object) -> City:
    return generate_city(seed=seed, **{**SMALL, **kw})


def _relative_errors(city: City, rot: np.ndarray | None = None,
                     trans: np.ndarray | None = None) -> np.ndarray:
    """e_c = Log(Z_c^-1 X_a^-1 X_b) of every relative edge at the given (default true) poses."""
    g = city.graph
    r = city.truth_rotations if rot is None else rot
    t = city.truth_translations if trans is None else trans
    a, b = g.edge_nodes[:, 0], g.edge_nodes[:, 1]
    xr, xt = se3.between(r[a], t[a], r[b], t[b])
    dr, dt = se3.between(g.edge_rotations, g.edge_translations, xr, xt)
    return se3.log(dr, dt)


def _arrays(city: City) -> dict[str, np.ndarray]:
    g = city.graph
    return {"truth_rot": city.truth_rotations, "truth_trans": city.truth_translations,
            **{f.name: getattr(g, f.name) for f in dataclasses.fields(g)
               if isinstance(getattr(g, f.name), np.ndarray)}}


# --------------------------------------------------------------------------- determinism
def test_same_seed_gives_identical_arrays() -> None:
    a, b = _arrays(small_city(3, gps_every=10)), _arrays(small_city(3, gps_every=10))
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_different_seed_gives_different_city() -> None:
    a, b = small_city(1), small_city(2)
    assert not np.array_equal(a.truth_translations, b.truth_translations)
    assert not np.array_equal(a.graph.edge_translations[:100], b.graph.edge_translations[:100])


def test_gps_changes_nothing_but_the_gps_constraints() -> None:
    """Independent random streams: the w/ and w/o GPS graphs of a seed share everything else."""
    plain, gps = small_city(4), small_city(4, gps_every=25)
    a, b = _arrays(plain), _arrays(gps)
    for k in a:
        if not k.startswith("gps_"):
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert plain.graph.num_gps == 0 and gps.graph.num_gps > 0


# --------------------------------------------------------------------------- structure
def test_single_connected_drive_with_odometry_between_consecutive_poses() -> None:
    city = small_city(5)
    g = city.graph
    n = g.num_nodes
    assert n == SMALL["num_poses"]
    np.testing.assert_array_equal(g.node_ids, np.arange(n))
    pairs = {(int(a), int(b)) for a, b in g.edge_nodes}
    assert all((i, i + 1) in pairs for i in range(n - 1))
    assert city.num_loop_edges == g.num_edges - (n - 1) > 0
    g.check_connected()
    assert np.all(np.diff(np.unique(g.connected_components())) == 0)


def test_step_lengths_follow_the_configured_step_and_jitter() -> None:
    p = CityParams(**SMALL)
    city = small_city(6)
    steps = np.linalg.norm(np.diff(city.truth_translations, axis=0), axis=1)
    # Arc length >= chord; rounded corners make chords a little shorter than the arc.
    assert steps.max() <= p.step_m * (1 + p.step_jitter) + FLOAT64_IDENTITY * 1e3
    assert np.median(steps) == pytest.approx(p.step_m, rel=0.05)
    assert steps.min() > 0.5 * p.step_m * (1 - p.step_jitter)


def test_route_follows_the_street_grid_and_re_traverses_streets() -> None:
    p = CityParams(**SMALL)
    city = small_city(7)
    xy = city.truth_translations[:, :2]
    # Every pose is on a street: within lane offset (+ corner rounding) of a grid line.
    off = np.abs(xy - np.round(xy / p.block_size_m) * p.block_size_m).min(axis=1)
    assert off.max() <= p.lane_offset_m + p.corner_radius_m
    assert np.median(off) == pytest.approx(p.lane_offset_m, abs=1e-6)
    # 3 km on 2 x 5 x 4 x 60 m = 2.4 km of streets: much is driven more than once.
    cells = np.unique(np.round(xy / 5.0).astype(np.int64), axis=0).shape[0]
    assert cells < 0.6 * city.graph.num_nodes


def test_rotations_are_proper_and_elevation_is_gentle() -> None:
    p = CityParams(**SMALL)
    city = small_city(8)
    r = city.truth_rotations
    np.testing.assert_allclose(np.swapaxes(r, 1, 2) @ r, np.broadcast_to(np.eye(3), r.shape),
                               atol=FLOAT64_IDENTITY)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=FLOAT64_IDENTITY)
    z = city.truth_translations[:, 2]
    assert np.ptp(z) <= p.elevation_m
    rpy = np.degrees(so3.matrix_to_euler_rpy(r))
    tilt = np.abs(rpy[:, :2])
    assert tilt.max() < 5.0  # gentle: a few metres over hundreds of metres
    assert tilt.max(axis=0).min() > 0.05  # but roll and pitch are not zero
    # x is the direction of travel: consecutive positions move forward.
    d = np.diff(city.truth_translations, axis=0)
    fwd = np.einsum("ij,ij->i", d, r[:-1, :, 0]) / np.linalg.norm(d, axis=1)
    assert np.median(fwd) > 0.999 and fwd.min() > 0.5


def test_flat_city_has_no_roll_pitch() -> None:
    city = small_city(9, elevation_m=0.0)
    np.testing.assert_array_equal(city.truth_translations[:, 2], 0.0)
    rpy = so3.matrix_to_euler_rpy(city.truth_rotations)
    assert np.abs(rpy[:, :2]).max() < FLOAT64_IDENTITY


# --------------------------------------------------------------------------- measurements
NOISE_FREE = dict(odom_trans_sigma_per_m=0.0, odom_yaw_sigma_deg=0.0,
                  odom_roll_pitch_sigma_deg=0.0, loop_trans_sigma_m=0.0, loop_rot_sigma_deg=0.0,
                  gps_sigma_h_m=0.0, gps_sigma_v_m=0.0)


def test_truth_has_zero_energy_against_noise_free_measurements() -> None:
    city = small_city(10, gps_every=7, **NOISE_FREE)
    g = city.graph
    assert g.num_gps > 0 and city.num_loop_edges > 0
    assert energy(g, city.truth_rotations, city.truth_translations) < NOISE_FREE_ENERGY
    # The information of an exact measurement uses MIN_SIGMA.
    np.testing.assert_allclose(np.diagonal(g.edge_information, axis1=1, axis2=2),
                               1.0 / MIN_SIGMA**2, rtol=FLOAT64_IDENTITY)
    # Dead reckoning of exact odometry is the truth.
    scale = np.abs(city.truth_translations).max()
    np.testing.assert_allclose(g.translations, city.truth_translations,
                               atol=NOISE_FREE_CHAIN * scale)
    np.testing.assert_allclose(g.rotations, city.truth_rotations, atol=NOISE_FREE_CHAIN)


def test_truth_energy_is_chi2_with_the_measurement_dof() -> None:
    city = small_city(11, gps_every=5)
    g = city.graph
    e_rel, e_gps = constraint_energies(g, city.truth_rotations, city.truth_translations)
    for e, d in ((e_rel, 6), (e_gps, 3)):
        dof = d * e.shape[0]
        assert abs(e.sum() - dof) < CHI2_SIGMAS * math.sqrt(2 * dof), (e.sum(), dof)
    # Dead reckoning drifts: its energy is far above the truth's (loop closures and GPS disagree).
    assert energy(g) > 10 * (e_rel.sum() + e_gps.sum())


def test_noise_statistics_match_the_configured_sigmas() -> None:
    p = CityParams(**SMALL)
    city = small_city(12, gps_every=1)
    g = city.graph
    err = _relative_errors(city)
    odo = (g.edge_nodes[:, 1] - g.edge_nodes[:, 0]) == 1
    loop = ~odo
    dist = np.linalg.norm(g.edge_translations[odo], axis=1)
    # The error at the truth is -xi: the drawn noise.
    yaw = np.std(err[odo, 5])
    rp = np.std(err[odo, 3:5])
    trans_per_m = np.std(err[odo, :3] / dist[:, None])
    assert yaw == pytest.approx(math.radians(p.odom_yaw_sigma_deg), rel=SAMPLE_STD_RTOL)
    assert rp == pytest.approx(math.radians(p.odom_roll_pitch_sigma_deg), rel=SAMPLE_STD_RTOL)
    assert trans_per_m == pytest.approx(p.odom_trans_sigma_per_m, rel=SAMPLE_STD_RTOL)
    assert np.std(err[loop, :3]) == pytest.approx(p.loop_trans_sigma_m, rel=3 * SAMPLE_STD_RTOL)
    # GPS on every pose: horizontal and vertical sigmas.
    d = g.gps_positions - city.truth_translations[g.gps_nodes]
    assert np.std(d[:, :2]) == pytest.approx(p.gps_sigma_h_m, rel=SAMPLE_STD_RTOL)
    assert np.std(d[:, 2]) == pytest.approx(p.gps_sigma_v_m, rel=SAMPLE_STD_RTOL)
    # Information = inverse covariance.
    np.testing.assert_allclose(g.gps_information[0],
                               np.diag(1.0 / np.array([p.gps_sigma_h_m, p.gps_sigma_h_m,
                                                       p.gps_sigma_v_m]) ** 2),
                               rtol=FLOAT64_IDENTITY)
    sig_yaw = math.radians(p.odom_yaw_sigma_deg)
    np.testing.assert_allclose(g.edge_information[odo][:, 5, 5], 1.0 / sig_yaw**2,
                               rtol=FLOAT64_IDENTITY)


@pytest.mark.parametrize("n, k", [(1500, 100), (1500, 7), (1500, 1), (1500, 1499)])
def test_gps_count_and_nodes(n: int, k: int) -> None:
    city = small_city(13, num_poses=n, gps_every=k)
    g = city.graph
    assert g.num_gps == math.ceil(n / k)
    np.testing.assert_array_equal(g.gps_nodes, np.arange(0, n, k))
    g.check_connected()


def test_loop_edges_connect_poses_close_in_truth_on_the_same_street() -> None:
    p = CityParams(**SMALL)
    city = small_city(14)
    g = city.graph
    a, b = g.edge_nodes[:, 0], g.edge_nodes[:, 1]
    loop = (b - a) != 1
    a, b = a[loop], b[loop]
    assert a.size > 50
    t = city.truth_translations
    assert np.all(np.linalg.norm(t[a, :2] - t[b, :2], axis=1) <= p.loop_radius_m)
    assert np.all(b - a >= p.loop_min_gap)
    ha, hb = city.truth_rotations[a, :2, 0], city.truth_rotations[b, :2, 0]
    cos = np.einsum("ij,ij->i", ha, hb) / (np.linalg.norm(ha, axis=1) * np.linalg.norm(hb, axis=1))
    assert np.all(np.abs(cos) >= math.cos(math.radians(p.loop_max_heading_deg)) - 1e-12)
    # Both directions of travel are matched (parallel runs in opposite lanes).
    assert np.any(cos > 0) and np.any(cos < 0)
    # Edges arrive online: each closure right after the odometry edge that reaches its pose.
    later = g.edge_nodes.max(axis=1)
    assert np.all(np.diff(later) >= 0)


def test_p_loop_controls_the_number_of_closures() -> None:
    assert small_city(15, p_loop=0.0).num_loop_edges == 0
    some = small_city(15, p_loop=0.1).num_loop_edges
    more = small_city(15, p_loop=0.5).num_loop_edges
    assert 0 < some < more
    # Every candidate pose is closed with p_loop = 1; about half with 0.5.
    assert more == pytest.approx(0.5 * small_city(15, p_loop=1.0).num_loop_edges, rel=0.15)


def test_bad_parameters_raise() -> None:
    with pytest.raises(ValueError, match="unknown preset 'rome'"):
        generate_city("rome")
    with pytest.raises(TypeError, match=r"unknown city parameter.*num_pose\b"):
        generate_city(num_pose=10)
    with pytest.raises(ValueError, match="p_loop"):
        generate_city(p_loop=1.5)
    with pytest.raises(ValueError, match="gps_every"):
        generate_city(gps_every=-1)
    with pytest.raises(ValueError, match="num_poses"):
        generate_city(num_poses=1)


# --------------------------------------------------------------------------- presets
TABLE_II = {"valencia": (15031, 122), "paris1": (27093, 590), "paris2": (41957, 13384)}


def _check_preset(name: str) -> None:
    poses, loops = TABLE_II[name]
    city = generate_city(name, gps_every=100)
    assert city.name == name
    assert city.graph.num_nodes == poses
    assert city.num_loop_edges == pytest.approx(loops, rel=PRESET_COUNT_RTOL)
    assert city.graph.num_gps == math.ceil(poses / 100)
    city.graph.check_connected()


def test_valencia_preset_matches_table_ii() -> None:
    _check_preset("valencia")


def _generator_lines(fn: Callable[[], object]) -> int:
    """Python lines of ``hybridpgo.generate`` executed by ``fn()`` (NumPy and kernels: none)."""
    import hybridpgo.generate

    root = str(Path(hybridpgo.generate.__file__).parent)
    count = 0

    def local(frame: FrameType, event: str, arg: object) -> object:
        nonlocal count
        count += event == "line"
        return local

    def outer(frame: FrameType, event: str, arg: object) -> object:
        return local if frame.f_code.co_filename.startswith(root) else None

    sys.settrace(outer)
    try:
        fn()
    finally:
        sys.settrace(None)
    return count


def test_city_generation_runs_no_python_per_pose() -> None:
    """The generator is vectorized: its Python runs per street block driven (the route walk),
    never per pose, so a preset of 15 031 poses stays fast (benchmarks/scale.py times 1M)."""
    p = CityParams(**PRESETS["valencia"])
    blocks = math.ceil(p.num_poses * p.step_m / p.block_size_m)
    lines = _generator_lines(lambda: generate_city("valencia", gps_every=100))
    assert 0 < lines <= 60 * blocks + 500, (lines, blocks, p.num_poses)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["paris1", "paris2"])
def test_paris_presets_match_table_ii(name: str) -> None:
    _check_preset(name)


def test_presets_only_use_known_parameters() -> None:
    fields = {f.name for f in dataclasses.fields(CityParams)}
    for name, values in PRESETS.items():
        assert set(values) <= fields, name
        CityParams(**values)


# --------------------------------------------------------------------------- noisify
def test_noisify_rotates_each_edge_about_its_local_up_axis() -> None:
    city = small_city(16, gps_every=50)
    g = city.graph
    sigma_deg = 3.0
    h = noisify(g, yaw_sigma_deg=sigma_deg, seed=1)
    delta = np.swapaxes(g.edge_rotations, 1, 2) @ h.edge_rotations  # Z^-1 Z' = Rz(angle)
    np.testing.assert_allclose(delta[:, 2, :], np.broadcast_to([0.0, 0.0, 1.0], (g.num_edges, 3)),
                               atol=FLOAT64_IDENTITY)
    np.testing.assert_allclose(delta[:, :, 2], np.broadcast_to([0.0, 0.0, 1.0], (g.num_edges, 3)),
                               atol=FLOAT64_IDENTITY)
    ang = np.arctan2(delta[:, 1, 0], delta[:, 0, 0])
    assert np.degrees(np.std(ang)) == pytest.approx(sigma_deg, rel=SAMPLE_STD_RTOL)
    assert abs(np.degrees(np.mean(ang))) < 5 * sigma_deg / math.sqrt(g.num_edges)
    for name in ("edge_nodes", "edge_translations", "edge_information", "rotations",
                 "translations", "gps_nodes", "gps_positions", "gps_information", "node_ids"):
        np.testing.assert_array_equal(getattr(h, name), getattr(g, name), err_msg=name)
    assert h.has_estimates == g.has_estimates
    # Deterministic per seed; zero sigma changes nothing.
    np.testing.assert_array_equal(noisify(g, sigma_deg, seed=1).edge_rotations, h.edge_rotations)
    assert not np.array_equal(noisify(g, sigma_deg, seed=2).edge_rotations, h.edge_rotations)
    np.testing.assert_array_equal(noisify(g, 0.0).edge_rotations, g.edge_rotations)
    with pytest.raises(ValueError, match="yaw_sigma_deg"):
        noisify(g, -1.0)


# --------------------------------------------------------------------------- output
def test_write_ground_truth_round_trip(tmp_path: object) -> None:
    city = small_city(17, gps_every=100)
    path = f"{tmp_path}/gt.g2o"
    write_ground_truth(path, city.graph, city.truth_rotations, city.truth_translations)
    rot, trans, ids = read_ground_truth(path)
    np.testing.assert_array_equal(ids, city.graph.node_ids)
    scale = np.abs(city.truth_translations).max()
    np.testing.assert_allclose(trans, city.truth_translations, atol=FLOAT64_IDENTITY * scale)
    np.testing.assert_allclose(rot, city.truth_rotations, atol=FLOAT64_IDENTITY)
    # The file is the whole problem, with the truth as vertex estimates.
    g = read_graph(path)
    assert g.num_edges == city.graph.num_edges and g.num_gps == city.graph.num_gps


def test_gps_every_zero_means_no_gps() -> None:
    city = small_city(18, gps_every=0)
    assert city.graph.num_gps == 0 and city.params.gps_every is None
    np.testing.assert_array_equal(city.graph.edge_translations,
                                  small_city(18).graph.edge_translations)


def test_write_ground_truth_reusing_the_graph_file_gives_the_same_bytes(tmp_path: Path) -> None:
    """Oracle: the fast path (copying the graph file's constraint lines) writes exactly what the
    plain path writes, for a 3D city with GPS and a 2D grid."""
    for k, made in enumerate((small_city(19, gps_every=9),
                              generate_grid(seed=2, num_poses=400, num_outliers=6))):
        g = made.graph
        graph_file = tmp_path / f"g{k}.g2o"
        write_graph(g, graph_file)
        plain, fast = tmp_path / f"plain{k}.g2o", tmp_path / f"fast{k}.g2o"
        write_ground_truth(plain, g, made.truth_rotations, made.truth_translations)
        write_ground_truth(fast, g, made.truth_rotations, made.truth_translations,
                           graph_file=graph_file)
        assert fast.read_bytes() == plain.read_bytes()


def test_g2o_writer_output_does_not_depend_on_its_chunk_size(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import hybridpgo.io.g2o as g2o

    for k, g in enumerate((small_city(20, gps_every=11).graph,
                           generate_grid(seed=3, num_poses=300).graph)):
        write_graph(g, tmp_path / "big.g2o")
        monkeypatch.setattr(g2o, "_WRITE_CHUNK", 7)
        write_graph(g, tmp_path / "small.g2o")
        monkeypatch.undo()
        assert (tmp_path / "small.g2o").read_bytes() == (tmp_path / "big.g2o").read_bytes(), k


# =========================================================================== city size
def test_scale_city_grows_the_street_grid_and_keeps_the_loop_density() -> None:
    kw = scale_city("paris1", 4 * 27093)
    assert kw["num_poses"] == 4 * 27093 and (kw["nx"], kw["ny"]) == (28, 24)  # 2 x (14, 12)
    small = scale_city(None, 2)
    assert (small["nx"], small["ny"]) == (1, 1)
    base = generate_city("paris1")
    density = base.num_loop_edges / base.graph.num_nodes
    assert kw["loop_density"] == density
    # A city 1/3 and one 1.5 times the preset's size close loops at its rate (sampling spread
    # of a few hundred closures: 15%).
    for n in (9000, 40000):
        city = generate_city("paris1", seed=1, **scale_city("paris1", n))
        assert city.graph.num_nodes == n
        assert city.num_loop_edges / n == pytest.approx(density, rel=0.15), n
    with pytest.raises(ValueError, match="num_poses"):
        scale_city(None, 1)
    with pytest.raises(ValueError, match="unknown preset"):
        scale_city("rome", 10)


def test_loop_density_replaces_p_loop() -> None:
    few = small_city(21, loop_density=0.01).num_loop_edges
    many = small_city(21, loop_density=0.05).num_loop_edges
    n = SMALL["num_poses"]
    assert few == pytest.approx(0.01 * n, rel=0.35) and many == pytest.approx(0.05 * n, rel=0.2)
    assert small_city(21, loop_density=0.0).num_loop_edges == 0


# =========================================================================== grid
#: A small grid that generates in milliseconds.
GRID = dict(num_poses=600)


def _grid_errors(grid: Grid) -> np.ndarray:
    g = grid.graph
    r, t = grid.truth_rotations, grid.truth_translations
    a, b = g.edge_nodes[:, 0], g.edge_nodes[:, 1]
    xr, xt = se3.between(r[a], t[a], r[b], t[b])
    dr, dt = se3.between(g.edge_rotations, g.edge_translations, xr, xt)
    return se3.log(dr, dt)


def test_grid_is_deterministic_per_seed() -> None:
    a, b = generate_grid(seed=5, **GRID), generate_grid(seed=5, **GRID)
    for name in ("truth_rotations", "truth_translations"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for f in dataclasses.fields(a.graph):
        va, vb = getattr(a.graph, f.name), getattr(b.graph, f.name)
        if isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vb, err_msg=f.name)
    c = generate_grid(seed=6, **GRID)
    assert not np.array_equal(a.truth_translations, c.truth_translations)


@pytest.mark.parametrize("dim", [2, 3])
def test_grid_walks_unit_steps_on_the_street_grid(dim: int) -> None:
    grid = generate_grid(seed=7, dim=dim, street_spacing=3, num_poses=1500)
    p = grid.params
    t, r = grid.truth_translations, grid.truth_rotations
    assert grid.graph.is_2d == (dim == 2) and grid.graph.num_nodes == 1500
    # positions are integers inside the box; rotations are proper with entries 0, +-1
    np.testing.assert_array_equal(t, np.round(t))
    hi = np.array([p.nx, p.ny, p.nz or 0]) * p.street_spacing
    assert np.all(t >= 0) and np.all(t <= hi)
    if dim == 2:
        np.testing.assert_array_equal(t[:, 2], 0.0)
        np.testing.assert_array_equal(r[:, 2, 2], 1.0)
    else:
        assert np.unique(t[:, 2]).size > 1
    assert set(np.unique(r)) <= {-1.0, 0.0, 1.0}
    np.testing.assert_array_equal(np.linalg.det(r), 1.0)
    # every step is one metre along the new heading (turn, then step, as in M3500)
    np.testing.assert_array_equal(t[1:] - t[:-1], r[1:, :, 0])
    # turns only at intersections (all coordinates multiples of the street spacing)
    turned = np.any(r[1:] != r[:-1], axis=(1, 2))
    assert turned.sum() > 20
    np.testing.assert_array_equal(t[:-1][turned] % p.street_spacing, 0.0)
    # odometry edges come first per pose and join consecutive poses
    g = grid.graph
    later = g.edge_nodes.max(axis=1)
    assert np.all(np.diff(later) >= 0)
    g.check_connected()


def test_grid_turn_frequencies_follow_m3500() -> None:
    """With a turn at every step, the heading changes with the configured probabilities
    (straight 76%, left 8%, right 8%, back 8%), up to the walls' forced turns."""
    grid = generate_grid(seed=8, num_poses=20000, nx=200)
    r = grid.truth_rotations
    rel = np.swapaxes(r[:-1], 1, 2) @ r[1:]
    yaw = np.round(np.degrees(np.arctan2(rel[:, 1, 0], rel[:, 0, 0]))).astype(int)
    n = yaw.size
    p = grid.params
    for angle, prob in ((0, 1 - p.p_turn - p.p_uturn), (90, p.p_turn / 2), (-90, p.p_turn / 2),
                        (180, p.p_uturn)):
        sd = math.sqrt(n * prob * (1 - prob))
        assert abs((yaw == angle).sum() - n * prob) < CHI2_SIGMAS * sd + 0.01 * n, angle


@pytest.mark.parametrize("dim", [2, 3])
def test_grid_truth_has_zero_energy_against_noise_free_measurements(dim: int) -> None:
    grid = generate_grid(seed=9, dim=dim, trans_sigma_m=0.0, rot_sigma_rad=0.0, **GRID)
    g = grid.graph
    assert grid.num_loop_edges > 20
    assert energy(g, grid.truth_rotations, grid.truth_translations) < NOISE_FREE_ENERGY
    # the odometry chained from the true first pose is the truth (the file's vertices)
    np.testing.assert_allclose(g.translations, grid.truth_translations, atol=NOISE_FREE_CHAIN)
    np.testing.assert_allclose(g.rotations, grid.truth_rotations, atol=NOISE_FREE_CHAIN)


@pytest.mark.parametrize("dim, dof", [(2, 3), (3, 6)])
def test_grid_truth_energy_is_chi2_and_noise_matches_sigmas(dim: int, dof: int) -> None:
    grid = generate_grid(seed=10, dim=dim, num_poses=2000, rot_sigma_rad=0.2,
                         trans_sigma_m=0.05)
    g = grid.graph
    e = constraint_energies(g, grid.truth_rotations, grid.truth_translations)[0]
    k = dof * e.size
    assert abs(e.sum() - k) < CHI2_SIGMAS * math.sqrt(2 * k), (e.sum(), k)
    err = _grid_errors(grid)
    if dim == 2:  # planar: no z, roll or pitch error at all
        np.testing.assert_array_equal(err[:, 2:5], 0.0)
        assert np.std(err[:, 5]) == pytest.approx(0.2, rel=SAMPLE_STD_RTOL)
        assert np.std(err[:, :2]) == pytest.approx(0.05, rel=SAMPLE_STD_RTOL)
    else:
        assert np.std(err[:, 3:]) == pytest.approx(0.2, rel=SAMPLE_STD_RTOL)
        assert np.std(err[:, :3]) == pytest.approx(0.05, rel=SAMPLE_STD_RTOL)
    # information is the inverse covariance (2D: lifted like a g2o EDGE_SE2 line)
    diag = np.diagonal(g.edge_information, axis1=1, axis2=2)
    expect = ([1 / 0.05**2] * 2 + [1 / 0.05**2] * 3 + [1 / 0.2**2] if dim == 2
              else [1 / 0.05**2] * 3 + [1 / 0.2**2] * 3)
    np.testing.assert_allclose(diag, np.broadcast_to(expect, diag.shape), rtol=FLOAT64_IDENTITY)


def test_grid_loop_closures_join_nearby_earlier_poses() -> None:
    grid = generate_grid(seed=0)
    p = grid.params
    g, t = grid.graph, grid.truth_translations
    a, b = g.edge_nodes[:, 0], g.edge_nodes[:, 1]
    loop = b - a != 1
    d = np.linalg.norm(t[b[loop]] - t[a[loop]], axis=1)
    assert np.all(d <= p.loop_radius_m) and np.all(b[loop] - a[loop] >= p.loop_min_gap)
    # M3500-like (2 099 closures on 3 500 poses, 90% at distance 0 or 1): seeds 0-19 give
    # 1 745-2 983, mean 2 151
    assert 1500 < grid.num_loop_edges < 3100
    assert np.mean(d <= 1.0) > 0.7
    assert generate_grid(seed=0, p_loop=0.0).num_loop_edges == 0
    assert generate_grid(seed=0, p_loop=0.24).num_loop_edges > 1.5 * grid.num_loop_edges


def test_grid_presets_raise_the_rotation_noise() -> None:
    assert GRID_PRESETS["m3500a"]["rot_sigma_rad"] == 0.1
    for name, sigma in (("m3500", GridParams().rot_sigma_rad), ("m3500c", 0.3)):
        grid = generate_grid(name, seed=12, num_poses=3000)
        assert grid.name == name and grid.params.rot_sigma_rad == sigma
        assert np.std(_grid_errors(grid)[:, 5]) == pytest.approx(sigma, rel=SAMPLE_STD_RTOL)
    g3 = generate_grid("grid3d", **GRID)
    assert g3.params.dim == 3 and not g3.graph.is_2d
    assert g3.params.nx == g3.params.ny == g3.params.nz


def test_grid_is_written_as_se2_and_reads_back(tmp_path: Path) -> None:
    grid = generate_grid(seed=13, **GRID)
    path = tmp_path / "grid.g2o"
    write_graph(grid.graph, path)
    tags = {line.split()[0] for line in path.read_text().splitlines()}
    assert tags == {"VERTEX_SE2", "EDGE_SE2"}
    back = read_graph(path)
    assert back.is_2d and back.num_edges == grid.graph.num_edges
    e0 = energy(grid.graph, grid.truth_rotations, grid.truth_translations)
    assert energy(back, grid.truth_rotations, grid.truth_translations) == pytest.approx(
        e0, rel=1e-9)


def test_grid_bad_parameters_raise() -> None:
    with pytest.raises(ValueError, match="unknown grid preset 'm4000'"):
        generate_grid("m4000")
    with pytest.raises(TypeError, match=r"unknown grid parameter.*poses"):
        generate_grid(poses=10)
    with pytest.raises(ValueError, match="dim"):
        generate_grid(dim=4)
    with pytest.raises(ValueError, match="nz"):
        generate_grid(nz=3)
    with pytest.raises(ValueError, match="at most 1"):
        generate_grid(p_turn=0.6, p_uturn=0.5)
    with pytest.raises(ValueError, match="num_poses"):
        generate_grid(num_poses=1)


# =========================================================================== outliers
def _strip(graph_edges: np.ndarray, outliers: Outliers) -> np.ndarray:
    return np.delete(graph_edges, outliers.edges, axis=0)


@pytest.mark.parametrize("kind", ["city", "grid2d", "grid3d"])
def test_outliers_are_false_closures_listed_exactly(kind: str) -> None:
    k = 30
    if kind == "city":
        make = lambda **kw: small_city(22, **kw)  # noqa: E731
        lo, hi, gap = CityParams().near_miss_min_m, CityParams().near_miss_max_m, 100
    else:
        make = lambda **kw: generate_grid(  # noqa: E731
            seed=22, dim=2 if kind == "grid2d" else 3, **GRID, **kw)
        lo, hi, gap = GridParams().near_miss_min_m, GridParams().near_miss_max_m, 4
    clean, dirty = make(), make(num_outliers=k)
    o = dirty.outliers
    g, c = dirty.graph, clean.graph
    assert o.num_outliers == k and g.num_edges == c.num_edges + k
    assert dirty.num_loop_edges == clean.num_loop_edges
    assert np.all(np.diff(o.edges) > 0)
    # Oracle: without the listed edges the graph is exactly the clean one.
    for name in ("edge_nodes", "edge_rotations", "edge_translations", "edge_information"):
        np.testing.assert_array_equal(_strip(getattr(g, name), o), getattr(c, name))
    for name in ("rotations", "translations", "gps_nodes"):
        np.testing.assert_array_equal(getattr(g, name), getattr(c, name))
    # Still in online order; earlier pose first, the real closures' minimum gap.
    assert np.all(np.diff(g.edge_nodes.max(axis=1)) >= 0)
    a, b = g.edge_nodes[o.edges, 0], g.edge_nodes[o.edges, 1]
    assert np.all(b - a >= gap)
    t = dirty.truth_translations
    np.testing.assert_allclose(o.true_distances_m, np.linalg.norm(t[b] - t[a], axis=1),
                               rtol=FLOAT64_IDENTITY)
    near = o.kinds == OUTLIER_KINDS.index("near_miss")
    assert near.sum() == k // 2
    assert np.all((o.true_distances_m[near] >= lo) & (o.true_distances_m[near] <= hi))
    # The information of a real loop closure.
    real = np.flatnonzero(np.diff(c.edge_nodes, axis=1)[:, 0] != 1)
    real_info = {c.edge_information[i].tobytes() for i in real}
    assert all(g.edge_information[i].tobytes() in real_info for i in o.edges)
    # False: at the truth every near miss is off by at least near_miss_min_m - loop radius
    # (energies of hundreds; real closures have chi^2 ~ 6), and random pairs mostly far off.
    e = constraint_energies(g, dirty.truth_rotations, t)[0]
    assert np.all(e[o.edges][near] > 100.0)
    assert np.median(e[o.edges][~near]) > 100.0
    assert np.median(np.delete(e, o.edges)) < 10.0
    if kind == "grid2d":  # planar outliers, so the graph is still written as SE2
        np.testing.assert_array_equal(g.edge_translations[o.edges, 2], 0.0)
        np.testing.assert_array_equal(g.edge_rotations[o.edges, 2, 2], 1.0)


def test_outliers_are_deterministic_and_use_their_own_random_stream() -> None:
    a = generate_grid(seed=23, num_outliers=10, **GRID)
    b = generate_grid(seed=23, num_outliers=10, **GRID)
    np.testing.assert_array_equal(a.outliers.edges, b.outliers.edges)
    np.testing.assert_array_equal(a.graph.edge_rotations, b.graph.edge_rotations)
    c = generate_grid(seed=24, num_outliers=10, **GRID)
    assert not np.array_equal(a.graph.edge_nodes[a.outliers.edges],
                              c.graph.edge_nodes[c.outliers.edges])
    only_random = generate_grid(seed=23, num_outliers=10, near_miss_fraction=0.0, **GRID)
    assert np.all(only_random.outliers.kinds == OUTLIER_KINDS.index("random"))


def test_add_outliers_errors() -> None:
    grid = generate_grid(seed=25, **GRID)
    args = (grid.graph, grid.truth_rotations, grid.truth_translations)
    with pytest.raises(ValueError, match="near-miss"):
        add_outliers(*args, 5, near_miss_min_m=1e4, near_miss_max_m=2e4)
    with pytest.raises(ValueError, match="num_outliers"):
        add_outliers(*args, -1)
    with pytest.raises(ValueError, match="near_miss_fraction"):
        add_outliers(*args, 3, near_miss_fraction=1.5)
    same, none = add_outliers(*args, 0)
    assert same is grid.graph and none.num_outliers == 0


def test_write_outliers_csv_names_the_file_lines(tmp_path: Path) -> None:
    city = small_city(26, num_outliers=8, gps_every=50)
    graph_file, csv_file = tmp_path / "c.g2o", tmp_path / "c.outliers.csv"
    write_graph(city.graph, graph_file)
    write_outliers(csv_file, city.graph, city.outliers)
    with csv_file.open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["edge_index", "id_a", "id_b", "kind", "true_distance_m"]
    back = read_graph(graph_file)
    edge_lines = [ln.split() for ln in graph_file.read_text().splitlines()
                  if ln.startswith("EDGE_SE3:QUAT")]
    assert len(rows) == 8
    for row, e, dist in zip(rows, city.outliers.edges, city.outliers.true_distances_m,
                            strict=True):
        i = int(row["edge_index"])
        assert i == e
        ids = back.node_ids[back.edge_nodes[i]]
        assert (int(row["id_a"]), int(row["id_b"])) == tuple(ids)
        assert edge_lines[i][1:3] == [row["id_a"], row["id_b"]]
        assert float(row["true_distance_m"]) == dist
        assert row["kind"] in OUTLIER_KINDS


def test_dead_reckoning_kernel_matches_a_naive_loop() -> None:
    """``chain`` (a Numba kernel) against the plain NumPy twin: one compose per step."""
    from hybridpgo.generate._common import chain

    rng = np.random.default_rng(27)
    zr, zt = se3.exp(rng.normal(size=(300, 6)))
    r0, t0 = se3.exp(rng.normal(size=6))
    r, t = chain(r0, t0, zr, zt)
    nr, nt = r0, t0
    for i in range(300):
        np.testing.assert_allclose(r[i], nr, atol=FLOAT64_IDENTITY)
        np.testing.assert_allclose(t[i], nt, atol=FLOAT64_IDENTITY * (1 + np.abs(nt).max()))
        nr, nt = se3.compose(nr, nt, zr[i], zt[i])
    np.testing.assert_allclose(r[300], nr, atol=FLOAT64_IDENTITY)
