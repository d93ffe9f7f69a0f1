"""Chordal initialization: exact on noise-free graphs, and a valid start for the solvers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from graphs import random_graph, with_gps

from hybridpgo.energy import energy
from hybridpgo.generate import generate_grid
from hybridpgo.initialization import chordal_initialization, initial_locals
from hybridpgo.tree import build_tree, global_poses

#: Linear solves of well-conditioned small systems.
LINEAR_SOLVE = 1e-9


@pytest.mark.parametrize("gps", [0, 4])
def test_chordal_recovers_noise_free_poses(gps):
    rng = np.random.default_rng(0)
    graph, rot, trans = random_graph(rng, n=20, extra=15, gps=gps, rot_scale=1.0, noise=0.0)
    # the gauge pose keeps its file value: give it the true one; GPS readings exact too
    est_rot = graph.rotations.copy()
    est_trans = graph.translations.copy()
    est_rot[0], est_trans[0] = rot[0], trans[0]
    graph = dataclasses.replace(
        graph, rotations=est_rot, translations=est_trans, gps_positions=trans[graph.gps_nodes]
    )
    r, t = chordal_initialization(graph, gauge=0)
    np.testing.assert_allclose(r, rot, rtol=0, atol=LINEAR_SOLVE)
    np.testing.assert_allclose(t, trans, rtol=0, atol=LINEAR_SOLVE * 100)
    assert energy(graph, r, t) < LINEAR_SOLVE


def test_chordal_beats_dead_reckoning_under_rotation_noise():
    rng = np.random.default_rng(1)
    graph, _, _ = random_graph(rng, n=60, extra=60, rot_scale=0.2, noise=0.15, anisotropic=False)
    tree = build_tree(graph)
    e_tree = energy(graph, *global_poses(tree, *initial_locals(graph, tree, "tree")))
    e_chordal = energy(graph, *global_poses(tree, *initial_locals(graph, tree, "chordal")))
    assert e_chordal < 0.5 * e_tree


def _dense_chordal(graph):
    """Naive twin: the two least-squares problems with dense Jacobians, row by row."""
    n, m = graph.num_nodes, graph.num_edges
    a, b = graph.edge_nodes[:, 0], graph.edge_nodes[:, 1]
    kappa = np.mean(np.diagonal(graph.edge_information[:, 3:, 3:], axis1=1, axis2=2), axis=1)
    gauge = 0
    r_g = graph.rotations[gauge]
    j = np.zeros((3 * m, 3 * n))
    for c in range(m):  # residual sqrt(kappa) (x_b - Z^T x_a), x_i a row of R_i
        w = np.sqrt(kappa[c])
        j[3 * c:3 * c + 3, 3 * b[c]:3 * b[c] + 3] = w * np.eye(3)
        j[3 * c:3 * c + 3, 3 * a[c]:3 * a[c] + 3] = -w * graph.edge_rotations[c].T
    free = np.ones(3 * n, bool)
    free[3 * gauge:3 * gauge + 3] = False
    rot = np.empty((n, 3, 3))
    for k in range(3):
        x = np.empty(3 * n)
        x[~free] = r_g[k]
        x[free] = np.linalg.lstsq(j[:, free], -j[:, ~free] @ r_g[k], rcond=None)[0]
        rot[:, k, :] = x.reshape(n, 3)
    u, _, vt = np.linalg.svd(rot)
    u[:, :, 2] *= np.linalg.det(u @ vt)[:, None]
    rot = u @ vt
    rows, rhs = [], []
    for c in range(m):  # L^T R_a^T (t_b - t_a) - L^T t_c, Omega_tt = L L^T
        lt = np.linalg.cholesky(graph.edge_information[c, :3, :3]).T
        blk = np.zeros((3, 3 * n))
        blk[:, 3 * b[c]:3 * b[c] + 3] = lt @ rot[a[c]].T
        blk[:, 3 * a[c]:3 * a[c] + 3] = -lt @ rot[a[c]].T
        rows.append(blk)
        rhs.append(lt @ graph.edge_translations[c])
    for k, node in enumerate(graph.gps_nodes):  # L^T (t_n - g)
        lt = np.linalg.cholesky(graph.gps_information[k]).T
        blk = np.zeros((3, 3 * n))
        blk[:, 3 * node:3 * node + 3] = lt
        rows.append(blk)
        rhs.append(lt @ graph.gps_positions[k])
    jt, bt = np.vstack(rows), np.concatenate(rhs)
    t = np.empty(3 * n)
    free = np.ones(3 * n, bool)
    if not graph.num_gps:
        free[3 * gauge:3 * gauge + 3] = False
        t[~free] = graph.translations[gauge]
    t[free] = np.linalg.lstsq(jt[:, free], bt - jt[:, ~free] @ t[~free], rcond=None)[0]
    return rot, t.reshape(n, 3)


def _planar(gps: int):
    graph = generate_grid("m3500", seed=gps, num_poses=40, rot_sigma_rad=0.3).graph
    return with_gps(graph, every=10) if gps else graph


@pytest.mark.parametrize("seed, gps", [(0, 0), (1, 4), (2, 0), ("planar", 0), ("planar", 1)])
def test_chordal_matches_a_dense_least_squares_twin(seed, gps):
    """The block normal equations (built straight in AMD order) solve the same problems; a
    planar graph's in-plane systems solve the twin's 3D ones."""
    if seed == "planar":
        graph = _planar(gps)
        assert graph.is_2d and graph.num_gps == (4 if gps else 0)
    else:
        graph, _, _ = random_graph(np.random.default_rng(seed), n=25, extra=20, gps=gps,
                                   rot_scale=0.6, noise=0.2)
    rot, trans = chordal_initialization(graph)
    rot_d, trans_d = _dense_chordal(graph)
    np.testing.assert_allclose(rot, rot_d, rtol=0, atol=LINEAR_SOLVE)
    np.testing.assert_allclose(trans, trans_d, rtol=0,
                               atol=LINEAR_SOLVE * max(1.0, np.abs(trans_d).max()))
