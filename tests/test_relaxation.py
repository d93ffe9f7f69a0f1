"""The planar rank-restricted relaxation (initialization.PlanarRelaxation) and the default
pipeline's relaxation check (AutoConfig.relaxation)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tolerances import FLOAT64_IDENTITY, OPTIMUM_RELATIVE

from hybridpgo.energy import energy
from hybridpgo.generate import generate_grid
from hybridpgo.initialization import PlanarRelaxation, planar_relaxation_start
from hybridpgo.solvers import AutoConfig, GaussNewtonConfig, optimize
from hybridpgo.solvers.auto import _Candidate, _relaxation_check
from hybridpgo.solvers.gauss_newton import ExactSolver, solve_exact


def _grid(seed: int = 0, rot_sigma: float = 0.05, poses: int = 120):
    return generate_grid("m3500", seed=seed, num_poses=poses, rot_sigma_rad=rot_sigma)


def _naive(graph, z: np.ndarray) -> tuple[float, np.ndarray]:
    """Twin: the chordal cost minimized over the positions by a dense least-squares solve,
    one residual row per constraint (complex), pose 0's position held at 0."""
    n = graph.num_nodes
    rows, rhs, w = [], [], []
    for c, (a, b) in enumerate(graph.edge_nodes):
        r = graph.edge_rotations[c]
        rz = (r[0, 0] + 1j * r[1, 0]) / abs(r[0, 0] + 1j * r[1, 0])
        tz = graph.edge_translations[c, 0] + 1j * graph.edge_translations[c, 1]
        info = graph.edge_information[c]
        tau = 0.5 * (info[0, 0] + info[1, 1])
        row = np.zeros(n, complex)
        row[b] += 1.0
        row[a] -= 1.0
        rows.append(row)
        rhs.append(z[a] * tz)
        w.append(tau)
    a_mat = np.array(rows)[:, 1:] * np.sqrt(w)[:, None]
    b_vec = np.array(rhs) * np.sqrt(w)
    t = np.zeros(n, complex)
    t[1:] = np.linalg.lstsq(a_mat, b_vec, rcond=None)[0]
    cost = 0.0
    for c, (a, b) in enumerate(graph.edge_nodes):
        r = graph.edge_rotations[c]
        rz = (r[0, 0] + 1j * r[1, 0]) / abs(r[0, 0] + 1j * r[1, 0])
        tz = graph.edge_translations[c, 0] + 1j * graph.edge_translations[c, 1]
        info = graph.edge_information[c]
        cost += info[5, 5] * abs(z[b] - z[a] * rz) ** 2
        cost += 0.5 * (info[0, 0] + info[1, 1]) * abs(t[b] - t[a] - z[a] * tz) ** 2
    return cost, t


def test_cost_and_positions_match_a_dense_twin() -> None:
    graph = _grid().graph
    rng = np.random.default_rng(3)
    z = np.exp(1j * rng.uniform(-np.pi, np.pi, graph.num_nodes))
    rel = PlanarRelaxation(graph)
    cost, t = _naive(graph, z)
    assert rel.cost(z[:, None]) == pytest.approx(cost, rel=FLOAT64_IDENTITY * 1e3)
    scale = 1.0 + np.abs(t).max()
    assert np.abs(rel.positions(z) - t).max() <= FLOAT64_IDENTITY * 1e3 * scale


def test_the_riemannian_descent_lowers_the_cost_and_keeps_unit_rows() -> None:
    graph = _grid(rot_sigma=0.2).graph
    rel = PlanarRelaxation(graph)
    rng = np.random.default_rng(0)
    y0 = rng.standard_normal((graph.num_nodes, 2)) + 1j * rng.standard_normal(
        (graph.num_nodes, 2))
    y0 /= np.linalg.norm(y0, axis=1, keepdims=True)
    y, f, its = rel.minimize(y0, 200)
    assert its >= 1
    assert f < 0.01 * rel.cost(y0)
    assert f == pytest.approx(rel.cost(y), rel=FLOAT64_IDENTITY * 1e3)
    assert np.allclose(np.linalg.norm(y, axis=1), 1.0, atol=FLOAT64_IDENTITY)


def test_noise_free_relaxation_recovers_the_truth_from_a_scrambled_start() -> None:
    made = generate_grid("m3500", seed=1, num_poses=120, rot_sigma_rad=0.0,
                         trans_sigma_m=0.0)
    graph = made.graph
    rng = np.random.default_rng(2)
    n = graph.num_nodes
    yaw = rng.uniform(-np.pi, np.pi, n)
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0] = rot[:, 1, 1] = np.cos(yaw)
    rot[:, 1, 0], rot[:, 0, 1] = np.sin(yaw), -np.sin(yaw)
    rot[:, 2, 2] = 1.0
    rot[0] = made.truth_rotations[0]  # the gauge pose as the truth's
    trans = np.zeros((n, 3))
    trans[0] = made.truth_translations[0]
    r, t, info = planar_relaxation_start(graph, rot, trans, max_iterations=2000)
    assert info["max_angle"] > 1.0  # it left the scrambled start
    # the noise-free optimum (E = 0), in the frame of the gauge pose
    assert np.abs(r - made.truth_rotations).max() < 1e-5
    assert np.abs(t - made.truth_translations).max() < 1e-4 * (
        1.0 + np.abs(made.truth_translations).max())


def test_relaxation_needs_a_planar_graph_without_gps() -> None:
    from hybridpgo.generate import generate_city

    city = generate_city(None, seed=0, gps_every=50, num_poses=50)
    with pytest.raises(ValueError, match="2D graph without GPS"):
        planar_relaxation_start(city.graph, city.truth_rotations, city.truth_translations)
    res = optimize(city.graph)
    assert res.stats["relaxation"]["ran"] is False
    assert res.stats["relaxation"]["why"]


def test_the_check_agrees_where_the_pipeline_is_right() -> None:
    graph = _grid().graph
    res = optimize(graph)
    relax = res.stats["relaxation"]
    assert relax["ran"] and not relax["polished"]
    assert relax["max_angle"] <= AutoConfig().relaxation_angle
    assert "relaxation agrees" in res.stats["reason"]
    assert res.timings["relaxation"] > 0.0
    off = optimize(graph, AutoConfig(relaxation=False))
    assert off.stats["relaxation"] == {"ran": False, "why": "off"}
    assert off.final_energy == res.final_energy


def test_a_winner_in_another_basin_is_replaced() -> None:
    """A fake winner: LM stopped after 0 iterations at scrambled rotations.  The check leaves
    its basin, polishes the relaxation's start and returns it lower (the optimum of LM from
    the truth)."""
    made = _grid(rot_sigma=0.05)
    graph = made.graph
    rng = np.random.default_rng(5)
    rot = made.truth_rotations.copy()
    yaw = rng.uniform(-np.pi, np.pi, graph.num_nodes)
    rot[1:, 0, 0] = rot[1:, 1, 1] = np.cos(yaw[1:])
    rot[1:, 1, 0], rot[1:, 0, 1] = np.sin(yaw[1:]), -np.sin(yaw[1:])
    fake = solve_exact(graph, rot, made.truth_translations,
                       GaussNewtonConfig(max_iterations=0))
    win = _Candidate("tree")
    win.polished = fake
    cfg = AutoConfig()
    out = _relaxation_check(ExactSolver(graph, cfg.polish), cfg, False, win, 0.0, None, None)
    cand = out["candidate"]
    assert out["ran"] and out["polished"] and out["max_angle"] > cfg.relaxation_angle
    ref = solve_exact(graph, made.truth_rotations, made.truth_translations,
                      dataclasses.replace(cfg.polish, max_iterations=300))
    assert cand.energy <= ref.final_energy * (1.0 + OPTIMUM_RELATIVE)
    assert cand.energy < fake.final_energy
    assert energy(graph, cand.polished.rotations, cand.polished.translations) == pytest.approx(
        cand.energy, rel=FLOAT64_IDENTITY * 1e3)
    assert "lower: it wins" in out["summary"]
