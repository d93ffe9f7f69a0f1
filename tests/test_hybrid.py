"""The hybrid Hessian solver: Jacobians, both solves, 𝔅(H) bookkeeping, batch = GN, convergence."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from graphs import random_graph
from ref_kernels import se3_exp, se3_log

from hybridpgo import _cost
from hybridpgo.energy import energy
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, solve_hybrid
from hybridpgo.solvers.hybrid._dense import TINY
from hybridpgo.tree import global_poses

#: Central differences with h = 1e-6 on O(1) quantities.
CENTRAL_DIFF = 1e-6
#: Two exact solves of the same equation (Woodbury vs Givens).
SAME_EQUATION = 1e-9
#: Bookkeeping identities that only accumulate rounding.
ROUNDING = 1e-10


def _state(graph, tree_kind="bfs", init="file", **options):
    return HybridSolver(graph, HybridConfig(tree=tree_kind, init=init, **options))


def _whitened_residuals(state, rot_l, trans_l):
    """w = L^T e of every constraint (relative then GPS), computed from global poses."""
    g = state.graph
    grot, gtr = global_poses(state.tree, rot_l, trans_l)
    out = []
    for c in range(g.num_edges):
        a, b = g.edge_nodes[c]
        rab = grot[a].T @ grot[b]
        tab = grot[a].T @ (gtr[b] - gtr[a])
        zr, zt = g.edge_rotations[c], g.edge_translations[c]
        e = se3_log(zr.T @ rab, zr.T @ (tab - zt))
        out.append(state.problem.edge_lt[c] @ e)
    for k in range(g.num_gps):
        out.append(state.problem.gps_lt[k] @ (gtr[g.gps_nodes[k]] - g.gps_positions[k]))
    return out


def _fd_jacobian(state, h=1e-6):
    """Dense d w / d delta over all non-root tree nodes, by central differences."""
    tree = state.tree
    free = [i for i in range(tree.num_tree_nodes) if tree.parent[i] >= 0]
    w0 = np.concatenate(_whitened_residuals(state, state.state.rot, state.state.trans))
    jac = np.zeros((w0.shape[0], 6 * len(free)))
    for col, i in enumerate(free):
        for k in range(6):
            cols = []
            for sgn in (1.0, -1.0):
                rot = state.state.rot.copy()
                trans = state.state.trans.copy()
                d = np.zeros(6)
                d[k] = sgn * h
                dr, dt = se3_exp(d)
                trans[i] = rot[i] @ dt + trans[i]
                rot[i] = rot[i] @ dr
                cols.append(np.concatenate(_whitened_residuals(state, rot, trans)))
            jac[:, 6 * col + k] = (cols[0] - cols[1]) / (2 * h)
    return jac, w0, free


def _row_offsets(state):
    g = state.graph
    kr = [6] * g.num_edges + [3] * g.num_gps
    return np.concatenate([[0], np.cumsum(kr)])


def _step_of(state, c, step_kind):
    kr = 6 if c < state.graph.num_edges else 3
    jac, r, x = state.probe(c, step_kind)
    return kr, jac, r, x


@pytest.mark.parametrize("rot_scale", [1e-7, 0.3, 1.2])
@pytest.mark.parametrize("gps", [0, 3])
def test_constraint_jacobians_match_central_differences(rot_scale, gps):
    rng = np.random.default_rng(1)
    graph, _, _ = random_graph(rng, n=9, extra=7, gps=gps, rot_scale=rot_scale)
    state = _state(graph)
    fd, _, free = _fd_jacobian(state)
    col_of = {node: k for k, node in enumerate(free)}
    offs = _row_offsets(state)
    tree = state.tree
    checked_sides = set()
    for c in range(tree.num_constraints):
        kr, jac, _, _ = _step_of(_state(graph), c, "woodbury")
        rows = slice(offs[c], offs[c] + kr)
        nodes = tree.path_node[tree.path_ptr[c] : tree.path_ptr[c + 1]]
        signs = tree.path_sign[tree.path_ptr[c] : tree.path_ptr[c + 1]]
        expected = np.zeros((kr, fd.shape[1]))
        for k, node in enumerate(nodes):
            expected[:, 6 * col_of[node] : 6 * col_of[node] + 6] = jac[k, :kr]
            checked_sides.add(int(signs[k]))
        scale = max(1.0, np.abs(fd[rows]).max())
        np.testing.assert_allclose(expected, fd[rows], rtol=0, atol=CENTRAL_DIFF * scale * 10)
    assert checked_sides == {-1, 1}


@pytest.mark.parametrize("gps", [0, 2])
def test_woodbury_equals_givens(gps):
    rng = np.random.default_rng(2)
    graph, _, _ = random_graph(rng, n=12, extra=10, gps=gps, rot_scale=0.5)
    for c in range(graph.num_constraints):
        _, _, _, xw = _step_of(_state(graph), c, "woodbury")
        _, _, _, xg = _step_of(_state(graph), c, "givens")
        scale = np.abs(xw).max()
        np.testing.assert_allclose(xg, xw, rtol=0, atol=SAME_EQUATION * scale)


def test_step_solves_the_hybrid_normal_equations():
    """x solves (J^T J + B_c) x = J^T r with B_c = 𝔅(H) - 𝔅(J^T J) (paper eq. 25), damping aside."""
    rng = np.random.default_rng(3)
    graph, _, _ = random_graph(rng, n=10, extra=8, rot_scale=0.4)
    state = _state(graph)
    tree = state.tree
    c = int(np.argmax(tree.path_lengths()))
    nodes = tree.path_node[tree.path_ptr[c] : tree.path_ptr[c + 1]]
    bc = state.state.bdiag[nodes] - state.state.contrib[tree.path_ptr[c] : tree.path_ptr[c + 1]]
    kr, jac, r, x = _step_of(state, c, "woodbury")
    d = nodes.shape[0]
    jd = np.concatenate([jac[k, :kr] for k in range(d)], axis=1)
    bd = np.zeros((6 * d, 6 * d))
    for k in range(d):
        b = bc[k] + (
            1e-6 * np.trace(bc[k]) / 6 + TINY * np.trace(jac[k, :kr].T @ jac[k, :kr])
        ) * np.eye(6)
        bd[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] = b
    lhs = (jd.T @ jd + bd) @ x.reshape(-1)
    rhs = jd.T @ r[:kr]
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=ROUNDING * np.abs(rhs).max() * 1e3)


def test_block_diagonal_matches_finite_difference_hessian():
    rng = np.random.default_rng(4)
    graph, _, _ = random_graph(rng, n=8, extra=6, gps=2, rot_scale=0.5)
    state = _state(graph)
    fd, _, free = _fd_jacobian(state)
    h = fd.T @ fd
    for k, node in enumerate(free):
        blk = h[6 * k : 6 * k + 6, 6 * k : 6 * k + 6]
        np.testing.assert_allclose(
            state.state.bdiag[node], blk, rtol=0, atol=CENTRAL_DIFF * 100 * np.abs(blk).max()
        )


def test_incremental_block_diagonal_stays_consistent():
    rng = np.random.default_rng(5)
    graph, _, _ = random_graph(rng, n=15, extra=12, gps=3, rot_scale=0.5)
    state = _state(graph, init="tree", gps_batch_size=4)
    tree = state.tree
    for tau in (1.0, 0.5):
        state.step(tree.sweep_order, tau=tau)
        summed = np.zeros_like(state.state.bdiag)
        np.add.at(summed, tree.path_node, state.state.contrib)
        np.testing.assert_allclose(
            state.state.bdiag, summed, rtol=0, atol=ROUNDING * np.abs(summed).max()
        )
    # with tau = 0 the poses stay put, so the maintained 𝔅(H) equals one rebuilt from scratch
    state.step(tree.sweep_order, tau=0.0)
    kept = state.state.bdiag.copy()
    state.rebuild_blocks()
    np.testing.assert_allclose(kept, state.state.bdiag, rtol=0, atol=ROUNDING * np.abs(kept).max())


@pytest.mark.parametrize("gps", [0, 3])
def test_batch_of_all_constraints_is_the_gauss_newton_step(gps):
    """Paper eq. 37 reduces to eq. 14 when C is every constraint (docs/mathematics.md#batches)."""
    rng = np.random.default_rng(6)
    graph, _, _ = random_graph(rng, n=9, extra=8, gps=gps, rot_scale=0.5)
    state = _state(graph)
    fd, w0, free = _fd_jacobian(state)
    x_gn = np.linalg.lstsq(fd, -w0, rcond=None)[0].reshape(-1, 6)
    nodes, x = state.batch_step(np.arange(graph.num_constraints), damping=0.0)
    pos = {node: k for k, node in enumerate(free)}
    got = np.zeros_like(x_gn)
    for node, xi in zip(nodes, x, strict=True):
        got[pos[int(node)]] = xi
    np.testing.assert_allclose(got, x_gn, rtol=0, atol=CENTRAL_DIFF * 100 * np.abs(x_gn).max())


def test_single_batch_equals_single_update():
    rng = np.random.default_rng(7)
    graph, _, _ = random_graph(rng, n=10, extra=8, rot_scale=0.5)
    for c in range(graph.num_constraints):
        s1 = _state(graph)
        _, _, _, x = _step_of(s1, c, "woodbury")
        s2 = _state(graph)
        nodes, xb = s2.batch_step([c])
        path = s1.tree.path_node[s1.tree.path_ptr[c] : s1.tree.path_ptr[c + 1]]
        np.testing.assert_array_equal(nodes, path)
        np.testing.assert_allclose(xb, x, rtol=0, atol=SAME_EQUATION * np.abs(x).max())


def test_same_input_gives_bit_identical_output():
    rng = np.random.default_rng(8)
    graph, _, _ = random_graph(rng, n=30, extra=20, gps=4, rot_scale=0.5)
    cfg = HybridConfig(sweeps=5, gps_batch_size=2)
    r1 = solve_hybrid(graph, cfg)
    r2 = solve_hybrid(graph, cfg)
    assert np.array_equal(r1.rotations, r2.rotations)
    assert np.array_equal(r1.translations, r2.translations)
    assert np.array_equal(r1.energy_history, r2.energy_history)


def test_never_emits_non_finite_poses_on_degenerate_chain():
    """A chain whose end nodes only one constraint touches: B_c is singular there
    (docs/mathematics.md#hybrid-step)."""
    rng = np.random.default_rng(9)
    graph, _, _ = random_graph(rng, n=6, extra=0, rot_scale=1.0)
    res = solve_hybrid(graph, HybridConfig(sweeps=30, init="file"))
    assert np.all(np.isfinite(res.rotations)) and np.all(np.isfinite(res.translations))
    assert res.stats["rejected_steps"] == 0
    # a tree has an exact solution: each update is then a damped Newton step on its own node
    assert res.final_energy < 1e-12 * res.initial_energy


@pytest.mark.parametrize("gps", [0, 3])
def test_hybrid_reaches_the_exact_optimum_on_small_graphs(gps):
    from hybridpgo.solvers.gauss_newton import GaussNewtonConfig, solve_exact

    rng = np.random.default_rng(10)
    graph, _, _ = random_graph(rng, n=25, extra=15, gps=gps, rot_scale=0.3, noise=0.02)
    exact = solve_exact(graph, config=GaussNewtonConfig(method="lm"))
    res = solve_hybrid(graph, HybridConfig(sweeps=60, init="tree"))
    # The stochastic sweeps alone close in slowly (block-diagonal curvature, decaying tau):
    # measured 1.30x (no GPS) and 1.46x (GPS) of the optimum after 60 sweeps from 76x / 282x.
    assert res.initial_energy > 50 * exact.final_energy
    assert res.final_energy <= exact.final_energy * 1.5
    pol = solve_hybrid(graph, HybridConfig(sweeps=10, init="tree", polish=True))
    assert abs(pol.final_energy - exact.final_energy) <= 1e-8 * exact.final_energy
    assert energy(graph, pol.rotations, pol.translations) == pytest.approx(
        pol.final_energy, rel=1e-12
    )


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="step"):
        HybridConfig(step="qr")
    with pytest.raises(ValueError, match="tau_decay"):
        HybridConfig(tau_decay=1.5)
    with pytest.raises(ValueError):
        HybridConfig(tree="dfs")
    with pytest.raises(ValueError, match="sweeps"):
        HybridConfig(sweeps=-1)
    assert dataclasses.replace(HybridConfig(), sweeps=3).sweeps == 3


@pytest.mark.parametrize("angle", [1e-9, 1e-5, 0.05, 0.3, 2.0, np.pi - 1e-4])
def test_hot_path_error_and_jacobian_match_reference_kernels(angle):
    from ref_kernels import relative_error, se3_right_jacobian_inv

    rng = np.random.default_rng(11)
    for _ in range(5):
        poses = []
        for _k in range(3):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            poses.append(se3_exp(np.r_[rng.normal(size=3), angle * axis]))
        (zr, zt), (ra, ta), (rb, tb) = poses
        # put the error near the requested angle: measurement = X_a^-1 X_b Exp(-xi)
        rab, tab = ra.T @ rb, ra.T @ (tb - ta)
        e = np.empty(6)
        jri = np.empty((6, 6))
        ws = np.empty((_cost.SCRATCH, 3, 3))
        _cost.residual_and_jr_inv(zr, zt, ra, ta, rb, tb, e, ws)
        _cost.jr_inv_matrix(ws, jri)
        e_ref = relative_error(zr, zt, rab, tab)
        np.testing.assert_allclose(e, e_ref, rtol=0, atol=1e-12 * max(1.0, np.abs(e_ref).max()))
        np.testing.assert_allclose(jri, se3_right_jacobian_inv(e_ref), rtol=0, atol=1e-11)


@pytest.mark.parametrize("gps", [0, 5])
def test_segmented_woodbury_batch_matches_dense_hybrid_system(gps):
    """Batch step (eq. 35-37) in its segment-compressed Woodbury form vs a dense solve."""
    rng = np.random.default_rng(12)
    graph, _, _ = random_graph(rng, n=14, extra=14, gps=gps, rot_scale=0.5)
    state = _state(graph)
    tree = state.tree
    m = graph.num_edges
    # a batch that leaves every node some other constraint (so B_C has no zero block)
    batch, in_batch = [], np.zeros(tree.num_tree_nodes, int)
    for c in list(range(m, m + gps)) + [int(c) for c in np.argsort(-tree.path_lengths()[:m])]:
        path = tree.path_node[tree.path_ptr[c] : tree.path_ptr[c + 1]]
        if np.all(in_batch[path] + 1 < state.problem.path_count[path]):
            batch.append(c)
            in_batch[path] += 1
        if len(batch) >= gps + 3:
            break
    assert len(batch) >= 3
    nodes_all = sorted(
        {int(v) for c in batch for v in tree.path_node[tree.path_ptr[c] : tree.path_ptr[c + 1]]}
    )
    pos = {v: k for k, v in enumerate(nodes_all)}
    rows, rhs = [], []
    bc = {v: state.state.bdiag[v].copy() for v in nodes_all}
    scale = dict.fromkeys(nodes_all, 0.0)
    for c in batch:
        kr, jac, r, _ = _step_of(_state(graph), c, "woodbury")
        row = np.zeros((kr, 6 * len(nodes_all)))
        for k, v in enumerate(tree.path_node[tree.path_ptr[c] : tree.path_ptr[c + 1]]):
            v = int(v)
            row[:, 6 * pos[v] : 6 * pos[v] + 6] = jac[k, :kr]
            bc[v] -= state.state.contrib[tree.path_ptr[c] + k]
            scale[v] += np.trace(jac[k, :kr].T @ jac[k, :kr])
        rows.append(row)
        rhs.append(r[:kr])
    jd = np.concatenate(rows)
    bd = np.zeros((jd.shape[1], jd.shape[1]))
    for v in nodes_all:
        if np.abs(bc[v]).max() < 1e-9 * max(scale[v], 1.0):
            pytest.skip("a node only the batch touches: the dense branch applies instead")
        b = bc[v] + (1e-6 * np.trace(bc[v]) / 6 + TINY * scale[v]) * np.eye(6)
        bd[6 * pos[v] : 6 * pos[v] + 6, 6 * pos[v] : 6 * pos[v] + 6] = b
    x_ref = np.linalg.solve(jd.T @ jd + bd, jd.T @ np.concatenate(rhs)).reshape(-1, 6)
    nodes, x = state.batch_step(batch)
    got = np.zeros_like(x_ref)
    for v, xi in zip(nodes, x, strict=True):
        got[pos[int(v)]] = xi
    np.testing.assert_allclose(got, x_ref, rtol=0, atol=SAME_EQUATION * np.abs(x_ref).max())


@pytest.mark.parametrize("two", [False, True])
def test_gps_only_graphs_are_solved(two):
    """One pose with one GPS reading, or two poses each with one and no relative
    edge, made every hybrid update non-finite (the batch system is singular in rotation)."""
    from hybridpgo.graph import PoseGraph

    n = 2 if two else 1
    graph = PoseGraph(
        node_ids=np.arange(n), rotations=np.tile(np.eye(3), (n, 1, 1)),
        translations=np.zeros((n, 3)), edge_nodes=np.zeros((0, 2), np.int32),
        edge_rotations=np.zeros((0, 3, 3)), edge_translations=np.zeros((0, 3)),
        edge_information=np.zeros((0, 6, 6)), gps_nodes=np.arange(n, dtype=np.int32),
        gps_positions=np.arange(3 * n, dtype=float).reshape(n, 3) + 1.0,
        gps_information=np.tile(np.eye(3), (n, 1, 1)),
    )
    res = solve_hybrid(graph, HybridConfig(sweeps=5, init="file"))
    assert res.stats["rejected_steps"] == 0
    np.testing.assert_allclose(res.translations, graph.gps_positions, rtol=0, atol=1e-6)


def test_sweeps_and_tau0_are_bounded():
    from hybridpgo.solvers.config import MAX_SWEEPS, MAX_TAU

    with pytest.raises(ValueError, match="sweeps"):
        HybridConfig(sweeps=MAX_SWEEPS + 1)
    with pytest.raises(ValueError, match="tau0"):
        HybridConfig(tau0=MAX_TAU)
    HybridConfig(sweeps=MAX_SWEEPS, tau0=1.99)
