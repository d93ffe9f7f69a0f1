"""Tests of the city generator ``hybridpgo.generate`` (issue 4; paper Table II, Fig. 3, Fig. 8)."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
from tolerances import FLOAT64_IDENTITY

from hybridpgo.energy import constraint_energies, energy
from hybridpgo.generate import (
    MIN_SIGMA,
    PRESETS,
    City,
    CityParams,
    generate_city,
    noisify,
    write_ground_truth,
)
from hybridpgo.geometry import se3, so3
from hybridpgo.io import read_graph
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
        generate_city(gps_every=0)
    with pytest.raises(ValueError, match="num_poses"):
        generate_city(num_poses=1)


# --------------------------------------------------------------------------- presets
TABLE_II = {"valencia": (15031, 122), "paris1": (27093, 590), "paris2": (41957, 13384)}


def _check_preset(name: str) -> None:
    poses, loops = TABLE_II[name]
    start = time.perf_counter()
    city = generate_city(name, gps_every=100)
    elapsed = time.perf_counter() - start
    assert elapsed < 10.0, f"{name} took {elapsed:.1f} s"
    assert city.name == name
    assert city.graph.num_nodes == poses
    assert city.num_loop_edges == pytest.approx(loops, rel=PRESET_COUNT_RTOL)
    assert city.graph.num_gps == math.ceil(poses / 100)
    city.graph.check_connected()


def test_valencia_preset_matches_table_ii() -> None:
    _check_preset("valencia")


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
