"""The hybrid solver's kernels against their plain NumPy twins (``tests/naive.py``), and the
behaviour of Algorithm 1 that the kernel-level tests cannot see (GPS buffering, the pi/8 cap,
damping escalation, the time budget).

Each kernel is compared with a twin built from *global* poses and dense matrices
(docs/mathematics.md#jacobians, docs/mathematics.md#batches):
the linearization (:mod:`._linearize`), 𝔅(H) bookkeeping and both single-step solves
(:mod:`._step`), the capped retraction, batch updates (:mod:`._batch`) and the cost layer
(:mod:`hybridpgo._cost`), on random graphs with and without GPS, with constraint errors near 0,
moderate and near pi.
"""

from __future__ import annotations

import dataclasses
import math

import naive
import numpy as np
import pytest
import ref_kernels
from graphs import random_graph
from scipy.spatial.transform import Rotation
from tolerances import FLOAT64_IDENTITY, SAME_EQUATION, TWIN_JACOBIAN

from hybridpgo import _cost
from hybridpgo.graph import PoseGraph
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, _dense, _linearize, _step
from hybridpgo.solvers.hybrid.problem import State, Update, new_workspace

#: (rot_scale of the graph, rotation angle of every relative constraint's error)
REGIMES = {
    "near-zero": (1e-7, 1e-9),
    "moderate": (0.5, 0.3),
    "near-pi": (0.5, math.pi - 1e-4),
}


# --------------------------------------------------------------------------------- helpers
def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _graph(seed: int, *, n: int = 9, extra: int = 7, gps: int = 0, rot_scale: float = 0.5,
           error_angle: float | None = None) -> PoseGraph:
    """A random graph; with ``error_angle`` every relative constraint's error at the file's
    poses is ``xi = (rho, error_angle * axis)`` exactly (Z = X_a^-1 X_b Exp(-xi))."""
    rng = np.random.default_rng(seed)
    graph, _, _ = random_graph(rng, n=n, extra=extra, gps=gps, rot_scale=rot_scale)
    if error_angle is None:
        return graph
    zr = np.empty_like(graph.edge_rotations)
    zt = np.empty_like(graph.edge_translations)
    for c, (a, b) in enumerate(graph.edge_nodes):
        rab, tab = naive.between(graph.rotations[a], graph.translations[a],
                                 graph.rotations[b], graph.translations[b])
        xi = np.r_[rng.normal(scale=0.5, size=3), error_angle * _unit(rng)]
        zr[c], zt[c] = naive.compose(rab, tab, *naive.se3_exp(-xi))
    return dataclasses.replace(graph, edge_rotations=zr, edge_translations=zt)


def _solver(graph: PoseGraph, **options: object) -> HybridSolver:
    return HybridSolver(graph, HybridConfig(init="file", **options))  # type: ignore[arg-type]


def _path(solver: HybridSolver, c: int) -> slice:
    return slice(int(solver.tree.path_ptr[c]), int(solver.tree.path_ptr[c + 1]))


def _twin_constraint(solver: HybridSolver, c: int) -> tuple[np.ndarray, np.ndarray,
                                                            np.ndarray, np.ndarray]:
    """``(nodes, signs, jac (d, kr, 6), r (kr,))`` of constraint c from the twins (global poses,
    the whitening recomputed from the information)."""
    g, tree = solver.graph, solver.tree
    grot, gtr = naive.tree_globals(tree.parent, solver.state.rot, solver.state.trans)
    m = g.num_edges
    if c < m:
        a, b = (int(v) for v in g.edge_nodes[c])
        nodes, signs = naive.tree_domain(tree.parent, a, b)
        lt = np.linalg.cholesky(g.edge_information[c]).T
        jac, r = naive.relative_jacobian(grot, gtr, a, b, g.edge_rotations[c],
                                         g.edge_translations[c], lt, nodes, signs)
    else:
        n = int(g.gps_nodes[c - m])
        nodes, signs = naive.tree_domain(tree.parent, tree.root, n)  # the root is the earth
        lt = np.linalg.cholesky(g.gps_information[c - m]).T
        jac, r = naive.gps_jacobian(grot, gtr, n, g.gps_positions[c - m], lt, nodes)
    return nodes, signs, jac, r


def _twin_all(solver: HybridSolver) -> tuple[list[np.ndarray], list[np.ndarray],
                                             list[np.ndarray]]:
    doms, jacs, rs = [], [], []
    for c in range(solver.num_constraints):
        nodes, _, jac, r = _twin_constraint(solver, c)
        doms.append(nodes)
        jacs.append(jac)
        rs.append(r)
    return doms, jacs, rs


def _free_nodes(solver: HybridSolver) -> list[int]:
    return [i for i in range(solver.tree.num_tree_nodes) if solver.tree.parent[i] >= 0]


def _rel_err(actual: np.ndarray, expected: np.ndarray) -> float:
    """max |actual - expected| / max(|expected|, 1e-300): an error relative to the data's size."""
    return float(np.abs(actual - expected).max() / max(np.abs(expected).max(), 1e-300))


def _poses(solver: HybridSolver) -> tuple[np.ndarray, np.ndarray]:
    return solver.state.rot.copy(), solver.state.trans.copy()


def _assert_bit_identical(s1: HybridSolver, s2: HybridSolver) -> None:
    assert np.array_equal(s1.state.rot, s2.state.rot)
    assert np.array_equal(s1.state.trans, s2.state.trans)
    assert np.array_equal(s1.state.bdiag, s2.state.bdiag)


# --------------------------------------------------------------------------------- III-B
@pytest.mark.parametrize("regime", list(REGIMES))
@pytest.mark.parametrize("gps", [0, 3])
def test_linearize_matches_global_pose_twin(regime, gps):
    rot_scale, angle = REGIMES[regime]
    solver = _solver(_graph(20, gps=gps, rot_scale=rot_scale, error_angle=angle))
    prob, state, tree = solver.problem, solver.state, solver.tree
    wk = new_workspace(solver.dmax)
    m = solver.graph.num_edges
    grot, gtr = naive.tree_globals(tree.parent, state.rot, state.trans)
    sides = set()
    for c in range(solver.num_constraints):
        nodes, signs, jac, r = _twin_constraint(solver, c)
        # the twin's domain (ancestor lists) is the tree's CSR path, in the same order
        np.testing.assert_array_equal(tree.path_node[_path(solver, c)], nodes)
        np.testing.assert_array_equal(tree.path_sign[_path(solver, c)], signs)
        kr, na = _linearize.linearize(prob, c, state.rot, state.trans, wk, wk.jac)
        assert kr == jac.shape[1] and na == int(np.sum(signs < 0))
        d = nodes.shape[0]
        assert _rel_err(wk.jac[:d, :kr], jac) <= TWIN_JACOBIAN
        assert np.all(wk.jac[:d, kr:] == 0.0)
        assert _rel_err(wk.r[:kr], r) <= TWIN_JACOBIAN
        if c < m:
            a, b = solver.graph.edge_nodes[c]
            e = naive.relative_error(solver.graph.edge_rotations[c],
                                     solver.graph.edge_translations[c],
                                     *naive.between(grot[a], gtr[a], grot[b], gtr[b]))
            assert abs(np.linalg.norm(e[3:]) - angle) <= 1e-9  # the regime is the one asked for
            assert _rel_err(wk.e, e) <= TWIN_JACOBIAN
            assert _rel_err(wk.jri, naive.se3_right_jacobian_inv(e)) <= TWIN_JACOBIAN
        sides.update(int(s) for s in signs)
    assert sides == {-1, 1}


# --------------------------------------------------------------------------------- III-C/D
@pytest.mark.parametrize("gps", [0, 3])
def test_block_diagonal_equals_sum_of_contributions_and_twin_jtj(gps):
    """𝔅(H) (eq. 23) = sum of the stored contributions = block diagonal of J^T J (twin J)."""
    solver = _solver(_graph(21, n=10, extra=8, gps=gps))
    tree, state = solver.tree, solver.state

    def check_against_twin() -> None:
        doms, jacs, rs = _twin_all(solver)
        free = _free_nodes(solver)
        jd, _ = naive.stack_jacobian(doms, jacs, rs, free)
        h = jd.T @ jd
        for k, node in enumerate(free):
            blk = h[6 * k : 6 * k + 6, 6 * k : 6 * k + 6]
            assert _rel_err(state.bdiag[node], blk) <= TWIN_JACOBIAN
        for c in range(solver.num_constraints):
            contrib = state.contrib[_path(solver, c)]
            assert _rel_err(contrib, np.einsum("kti,ktj->kij", jacs[c], jacs[c])) <= TWIN_JACOBIAN

    def check_sum() -> None:
        summed = np.zeros_like(state.bdiag)
        np.add.at(summed, tree.path_node, state.contrib)
        assert _rel_err(state.bdiag, summed) <= FLOAT64_IDENTITY

    check_against_twin()
    check_sum()
    solver.step(tree.sweep_order, tau=0.5)  # contributions are now from different poses
    check_sum()
    solver.rebuild_blocks()
    check_against_twin()


@pytest.mark.parametrize("gps", [0, 3])
def test_accumulate_blocks_updates_and_factors_like_the_twin(gps):
    """Eq. 24 for one constraint at moved poses, and each lfac[k] factors the damped B_c block."""
    solver = _solver(_graph(22, n=10, extra=8, gps=gps))
    solver.step(solver.tree.sweep_order, tau=0.7)  # move the poses: stored contributions are old
    prob, state = solver.problem, solver.state
    mu = solver.config.damping
    wk = new_workspace(solver.dmax)
    for c in range(solver.num_constraints):
        p = _path(solver, c)
        nodes = solver.tree.path_node[p]
        d = nodes.shape[0]
        bdiag0, contrib0 = state.bdiag.copy(), state.contrib.copy()
        kr, _ = _linearize.linearize(prob, c, state.rot, state.trans, wk, wk.jac)
        _step.accumulate_blocks(prob, state, c, kr, wk.jac, mu, wk.lfac, wk.bc)
        jac = wk.jac[:d, :kr]
        new = np.einsum("kti,ktj->kij", jac, jac)
        np.testing.assert_array_equal(state.contrib[p], new)  # the same sums, stored
        expected = bdiag0.copy()
        expected[nodes] += new - contrib0[p]
        assert _rel_err(state.bdiag, expected) <= FLOAT64_IDENTITY  # other nodes untouched
        others = np.ones(state.contrib.shape[0], bool)
        others[p] = False
        np.testing.assert_array_equal(state.contrib[others], contrib0[others])
        bc = bdiag0[nodes] - contrib0[p]
        scale = naive.own_scale(jac)
        for k in range(d):
            lo = wk.lfac[k]
            assert np.all(np.triu(lo, 1) == 0.0) and np.all(np.diag(lo) > 0.0)
            want = naive.damped_block(bc[k], float(scale[k]), mu, _dense.TINY)
            assert _rel_err(lo @ lo.T, want) <= FLOAT64_IDENTITY
        assert _rel_err(wk.bc, bc[-1]) <= FLOAT64_IDENTITY


@pytest.mark.parametrize("step", ["woodbury", "givens"])
@pytest.mark.parametrize("gps", [0, 3])
def test_single_step_matches_dense_twin(step, gps):
    """Woodbury and Givens vs numpy.linalg.solve of (J^T J + B_c + damping) x = J^T r."""
    solver = _solver(_graph(23, n=12, extra=10, gps=gps))
    state = solver.state
    mu = solver.config.damping
    worst = 0.0
    for c in range(solver.num_constraints):
        p = _path(solver, c)
        bc = state.bdiag[solver.tree.path_node[p]] - state.contrib[p]  # before the probe
        kr = 6 if c < solver.graph.num_edges else 3
        jac, r, x = solver.probe(c, step)
        jac = jac[:, :kr]
        x_twin = naive.hybrid_step(jac, r[:kr], bc, naive.own_scale(jac), mu, _dense.TINY)
        worst = max(worst, _rel_err(x, x_twin))
    assert worst <= SAME_EQUATION


def test_probe_leaves_poses_and_block_diagonal_unchanged_at_the_same_poses():
    solver = _solver(_graph(24, gps=2))
    rot, trans = _poses(solver)
    bdiag = solver.state.bdiag.copy()
    for c in range(solver.num_constraints):
        solver.probe(c)
    assert np.array_equal(solver.state.rot, rot) and np.array_equal(solver.state.trans, trans)
    # J is recomputed bitwise at the same poses, so new - old is exactly 0
    assert np.array_equal(solver.state.bdiag, bdiag)


# --------------------------------------------------------------------------------- III-H
@pytest.mark.parametrize("tau", [1.0, 0.3, 1e-3])
def test_cap_and_apply_matches_twin(tau):
    rng = np.random.default_rng(25)
    solver = _solver(_graph(25, n=12, extra=6))
    nodes = np.array([3, 7, 1, 10], np.int32)
    capped_seen = set()
    for rot_size in (1e-10, 0.05, 0.5, 3.0):
        x = rng.normal(size=(nodes.shape[0], 6))
        x[:, 3:] *= rot_size / np.linalg.norm(x[:, 3:], axis=1).max()
        rot0, trans0 = _poses(solver)
        state = State(rot0.copy(), trans0.copy(), solver.state.bdiag, solver.state.contrib)
        ws = np.empty((12, 3, 3))
        status = _step.cap_and_apply(nodes, 1, 3, x, tau, state, ws)  # nodes[1:4]
        rot_t, trans_t, capped = naive.apply_step(rot0, trans0, nodes[1:4], x, tau)
        assert status == (Update.CAPPED if capped else Update.APPLIED)
        capped_seen.add(capped)
        assert _rel_err(state.rot, rot_t) <= FLOAT64_IDENTITY
        assert _rel_err(state.trans, trans_t) <= FLOAT64_IDENTITY
        untouched = np.setdiff1d(np.arange(rot0.shape[0]), nodes[1:4])
        assert np.array_equal(state.rot[untouched], rot0[untouched])
    assert capped_seen == ({False, True} if tau > 1e-3 else {False})


def test_cap_and_apply_rejects_non_finite_steps_without_applying():
    solver = _solver(_graph(26))
    rot0, trans0 = _poses(solver)
    x = np.zeros((2, 6))
    x[1, 4] = np.nan
    status = _step.cap_and_apply(np.array([1, 2], np.int32), 0, 2, x, 1.0, solver.state,
                                 np.empty((12, 3, 3)))
    assert status == Update.REJECTED
    assert np.array_equal(solver.state.rot, rot0) and np.array_equal(solver.state.trans, trans0)


def test_rotation_cap_is_exactly_pi_over_8_and_scales_every_node_alike():
    """A short loop closure off by 3 rad: tau x turns some node by more than pi/8 (III-H)."""
    graph = _graph(27, n=10, extra=5, rot_scale=0.3)
    probe_solver = _solver(graph)
    tree = probe_solver.tree
    lengths = tree.path_lengths()[: graph.num_edges]
    c = int(np.argmin(np.where(lengths >= 2, lengths, 10**6)))  # a loop closure, few nodes
    a, b = graph.edge_nodes[c]
    rab, tab = naive.between(graph.rotations[a], graph.translations[a], graph.rotations[b],
                             graph.translations[b])
    zr, zt = graph.edge_rotations.copy(), graph.edge_translations.copy()
    zr[c], zt[c] = naive.compose(rab, tab, *naive.se3_exp(np.r_[0.0, 0.0, 0.0, 0.0, 0.0, -3.0]))
    graph = dataclasses.replace(graph, edge_rotations=zr, edge_translations=zt)

    s1, s2 = _solver(graph), _solver(graph)
    rot0, trans0 = _poses(s1)
    _, _, x = s1.probe(c)
    norms = np.linalg.norm(x[:, 3:], axis=1)
    assert norms.max() > 1.5 * math.pi / 8  # really capped
    report = s2.step([c], tau=1.0)
    assert (report.done, report.capped, report.rejected) == (1, 1, 0)
    # the same update through the kernel: status CAPPED, bit-identical poses
    status = _step.cap_and_apply(tree.path_node, int(tree.path_ptr[c]), x.shape[0], x, 1.0,
                                 s1.state, np.empty((12, 3, 3)))
    assert status == Update.CAPPED
    _assert_bit_identical(s1, s2)
    # every node moved by T_old^-1 T_new = Exp(t x_k), one t for all, the largest turn is pi/8
    t = (math.pi / 8) / norms.max()
    nodes = tree.path_node[_path(s2, c)]
    for k, i in enumerate(nodes):
        inc = naive.se3_log(*naive.between(rot0[i], trans0[i], s2.state.rot[i],
                                           s2.state.trans[i]))
        assert _rel_err(inc, t * x[k]) <= FLOAT64_IDENTITY * 10
    turns = [Rotation.from_matrix(rot0[i].T @ s2.state.rot[i]).magnitude() for i in nodes]
    assert abs(max(turns) - math.pi / 8) <= FLOAT64_IDENTITY
    rot_t, trans_t, capped = naive.apply_step(rot0, trans0, nodes, x, 1.0)
    assert capped
    assert _rel_err(s2.state.rot, rot_t) <= FLOAT64_IDENTITY
    assert _rel_err(s2.state.trans, trans_t) <= FLOAT64_IDENTITY


# --------------------------------------------------------------------------------- cost layer
@pytest.mark.parametrize("angle", [1e-9, 1e-5, 0.3, 2.0, math.pi - 1e-4])
def test_cost_kernels_match_twins(angle):
    rng = np.random.default_rng(28)
    ws = np.empty((_cost.SCRATCH, 3, 3))
    for _ in range(5):
        (ra, ta), (rb, tb) = (naive.se3_exp(np.r_[rng.normal(size=3), angle * _unit(rng)])
                              for _ in range(2))
        xi = np.r_[rng.normal(size=3), angle * _unit(rng)]
        rab, tab = naive.between(ra, ta, rb, tb)
        zr, zt = naive.compose(rab, tab, *naive.se3_exp(-xi))  # error exactly xi
        e = np.empty(6)
        _cost.relative_residual(zr, zt, ra, ta, rb, tb, e, ws)
        e_twin = naive.relative_error(zr, zt, rab, tab)
        assert _rel_err(e, e_twin) <= FLOAT64_IDENTITY
        assert _rel_err(e, xi) <= FLOAT64_IDENTITY * 10
        q = rng.normal(size=(6, 6))
        info = q @ q.T + 6 * np.eye(6)
        lt = np.linalg.cholesky(info).T
        want6 = naive.chi2(info, e)
        assert abs(_cost.chi2(info, e, 6, np.empty(6)) - want6) <= FLOAT64_IDENTITY * want6
        want3 = naive.chi2(info[:3, :3], e[:3])
        assert abs(_cost.chi2(info[:3, :3], e, 3, np.empty(3)) - want3) <= FLOAT64_IDENTITY * want3
        for n in (6, 3):
            mat = rng.normal(size=(6, 6))
            out = np.full((6, 6), 7.0)
            ltn = np.linalg.cholesky(info[:n, :n]).T
            _cost.whiten_rows(ltn, mat, n, out)
            assert _rel_err(out[:n], ltn @ mat[:n]) <= FLOAT64_IDENTITY
            assert np.all(out[n:] == 7.0)  # rows beyond n are not written
        r = np.empty(6)
        _cost.whiten_residual(lt, e, 6, r)
        assert _rel_err(r, -lt @ e) <= FLOAT64_IDENTITY
        for scale in (1.0, 0.25):
            r_out, t_out = np.empty((3, 3)), np.empty(3)
            _cost.retract_into(ra, ta, xi, scale, r_out, t_out, np.empty((3, 3)),
                               np.empty((3, 3)))
            r_t, t_t = naive.retract(ra, ta, xi, scale)
            assert _rel_err(r_out, r_t) <= FLOAT64_IDENTITY
            assert _rel_err(t_out, t_t) <= FLOAT64_IDENTITY
            assert np.abs(r_out.T @ r_out - np.eye(3)).max() <= FLOAT64_IDENTITY
        r_in, t_in = ra.copy(), ta.copy()  # in place (output aliases the input)
        _cost.retract_into(r_in, t_in, xi, 0.5, r_in, t_in, np.empty((3, 3)), np.empty((3, 3)))
        r_t, t_t = naive.retract(ra, ta, xi, 0.5)
        assert _rel_err(r_in, r_t) <= FLOAT64_IDENTITY and _rel_err(t_in, t_t) <= FLOAT64_IDENTITY


@pytest.mark.parametrize("angle", [1e-9, 1e-5, 0.3, 2.0, math.pi - 3e-3, math.pi - 1e-4])
def test_energy_loops_match_twins(angle):
    """The loops over constraints (χ² read from the arrays by index) against the twins, and
    bit for bit against the same formulas on arrays (``ref_kernels``: same operations, same
    order)."""
    rng = np.random.default_rng(29)
    n, m = 6, 12
    poses = [naive.se3_exp(np.r_[rng.normal(size=3), angle * _unit(rng)]) for _ in range(n)]
    rot = np.array([p[0] for p in poses])
    trans = np.array([p[1] for p in poses])
    ab = np.array([rng.choice(n, 2, replace=False) for _ in range(m)], np.int32)
    zr, zt = np.empty((m, 3, 3)), np.empty((m, 3))
    for c in range(m):
        # an error of angle ``angle`` (near pi: the log's symmetric-part branch)
        xi = np.r_[rng.normal(size=3), angle * _unit(rng)]
        rab, tab = naive.between(rot[ab[c, 0]], trans[ab[c, 0]], rot[ab[c, 1]], trans[ab[c, 1]])
        zr[c], zt[c] = naive.compose(rab, tab, *naive.se3_exp(-xi))
    q = rng.normal(size=(m, 6, 6))
    info = q @ q.transpose(0, 2, 1) + 6 * np.eye(6)
    gps = np.array([1, 4], np.int32)
    gpos = rng.normal(size=(2, 3))
    ginfo = np.array([np.eye(3), 2 * np.eye(3)])
    out, out_g = np.empty(m), np.empty(2)
    _cost.constraint_energies(rot, trans, ab, zr, zt, info, gps, gpos, ginfo, out, out_g)
    ws = np.empty((_cost.SCRATCH, 3, 3))
    e = np.empty(6)
    for c in range(m):
        a, b = ab[c]
        rab, tab = naive.between(rot[a], trans[a], rot[b], trans[b])
        want = naive.chi2(info[c], naive.relative_error(zr[c], zt[c], rab, tab))
        assert abs(out[c] - want) <= FLOAT64_IDENTITY * 10 * want
        assert out[c] == ref_kernels.relative_chi2_in_order(zr[c], zt[c], info[c], rot[a],
                                                            trans[a], rot[b], trans[b])
        _cost.relative_residual(zr[c], zt[c], rot[a], trans[a], rot[b], trans[b], e, ws)
        assert out[c] == _cost.chi2(info[c], e, 6, np.empty(6))
    for k in range(2):
        d = trans[gps[k]] - gpos[k]
        assert abs(out_g[k] - d @ ginfo[k] @ d) <= FLOAT64_IDENTITY * (d @ ginfo[k] @ d)
    total = _cost.total_energy(rot, trans, ab, zr, zt, info, gps, gpos, ginfo)
    assert total == sum(out.tolist() + out_g.tolist())  # summed in order
    rho, plain = _cost.robust_total_energy(rot, trans, ab, zr, zt, info, gps, gpos, ginfo,
                                           _cost.ROBUST_NONE, 1.0)
    assert rho == plain == total


@pytest.mark.parametrize("angle", [1e-9, 1e-5, 0.3, 2.0, math.pi - 1e-4])
def test_planar_energy_loop_matches_the_3d_one(angle):
    """The planar χ² loop (``robust_total_energy(..., planar=True)``) against the 3D one on
    planar poses and measurements, and bit for bit against the same formula on arrays
    (``ref_kernels``) and against :func:`planar_residual` with :func:`chi2`."""
    rng = np.random.default_rng(30)
    n, m = 6, 12

    def rz(t: float) -> np.ndarray:
        return np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0],
                         [0.0, 0.0, 1.0]])

    rot = np.array([rz(t) for t in rng.uniform(-math.pi, math.pi, n)])
    trans = np.c_[rng.normal(size=(n, 2)) * 5, np.zeros(n)]
    ab = np.array([rng.choice(n, 2, replace=False) for _ in range(m)], np.int32)
    zr, zt = np.empty((m, 3, 3)), np.c_[rng.normal(size=(m, 2)), np.zeros(m)]
    for c in range(m):  # a yaw error of +-angle
        rab = rot[ab[c, 0]].T @ rot[ab[c, 1]]
        zr[c] = rab @ rz(-angle * rng.choice([-1.0, 1.0]))
    q = rng.normal(size=(m, 6, 6))
    info = q @ q.transpose(0, 2, 1) + 6 * np.eye(6)
    no_gps = (np.zeros(0, np.int32), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    rho, plain = _cost.robust_total_energy(rot, trans, ab, zr, zt, info, *no_gps,
                                           _cost.ROBUST_NONE, 1.0, True)
    want = _cost.total_energy(rot, trans, ab, zr, zt, info, *no_gps)
    assert rho == plain
    assert abs(plain - want) <= FLOAT64_IDENTITY * 10 * want
    e = np.empty(6)
    total = 0.0
    for c in range(m):
        a, b = ab[c]
        _cost.planar_residual(zr[c], zt[c], rot[a], trans[a], rot[b], trans[b], e)
        s = _cost.chi2(info[c], e, 6, np.empty(6))
        assert s == ref_kernels.planar_chi2_in_order(zr[c], zt[c], info[c], rot[a], trans[a],
                                                     rot[b], trans[b])
        total += s
    assert plain == total


# --------------------------------------------------------------------------------- III-F/G
def _batch_twin(solver: HybridSolver, batch: list[int], mu: float,
                damped: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``batch_step(batch)`` at the solver's current poses and 𝔅(H)."""
    doms, jacs, rs, olds = [], [], [], []
    for c in batch:
        nodes, _, jac, r = _twin_constraint(solver, c)
        doms.append(nodes)
        jacs.append(jac)
        rs.append(r)
        olds.append(solver.state.contrib[_path(solver, c)].copy())
    count = np.bincount(solver.tree.path_node, minlength=solver.tree.num_tree_nodes)
    return naive.batch_step(doms, jacs, rs, solver.state.bdiag.copy(), olds, count, mu,
                            _dense.TINY, damped)


def _by_node(nodes: np.ndarray, x: np.ndarray) -> dict[int, np.ndarray]:
    return {int(v): xi for v, xi in zip(nodes, x, strict=True)}


def _assert_same_steps(nodes, x, nodes_t, x_t, tol):
    assert sorted(int(v) for v in nodes) == sorted(int(v) for v in nodes_t)
    got, want = _by_node(nodes, x), _by_node(nodes_t, x_t)
    scale = np.abs(x_t).max()
    for v, xv in want.items():
        assert np.abs(got[v] - xv).max() <= tol * scale, (v, got[v], xv)


def _batch_without_zero_block(solver: HybridSolver, gps: int) -> list[int]:
    """GPS readings and the longest loop closures, while every node keeps a constraint outside."""
    tree = solver.tree
    m = solver.graph.num_edges
    batch, used = [], np.zeros(tree.num_tree_nodes, int)
    for c in list(range(m, m + gps)) + [int(c) for c in np.argsort(-tree.path_lengths()[:m])]:
        path = tree.path_node[_path(solver, c)]
        if np.all(used[path] + 1 < solver.problem.path_count[path]):
            batch.append(c)
            used[path] += 1
        if len(batch) >= gps + 3:
            break
    return batch


@pytest.mark.parametrize("gps", [0, 4])
def test_batch_step_without_zero_blocks_matches_damped_twin(gps):
    """Segmented Woodbury branch (every block of B_C non-zero, damped) vs the dense twin."""
    solver = _solver(_graph(29, n=14, extra=14, gps=gps))
    batch = _batch_without_zero_block(solver, gps)
    assert len(batch) >= 3
    mu = solver.config.damping
    nodes_t, x_t = _batch_twin(solver, batch, mu)
    nodes, x = solver.batch_step(batch)
    _assert_same_steps(nodes, x, nodes_t, x_t, SAME_EQUATION)
    # eq. 24: the batch's contributions are stored, 𝔅(H) is still their sum
    for c in batch:
        _, _, jac, _ = _twin_constraint(solver, c)
        got = solver.state.contrib[_path(solver, c)]
        assert _rel_err(got, np.einsum("kti,ktj->kij", jac, jac)) <= TWIN_JACOBIAN
    summed = np.zeros_like(solver.state.bdiag)
    np.add.at(summed, solver.tree.path_node, solver.state.contrib)
    assert _rel_err(solver.state.bdiag, summed) <= FLOAT64_IDENTITY


def test_gps_batch_with_a_zero_block_matches_undamped_twin():
    """All GPS readings at once: the anchor's B_C block is 0 (only GPS pass through it), so the
    kernel solves the dense normal equations, without damping."""
    solver = _solver(_graph(30, n=12, extra=8, gps=5))
    m = solver.graph.num_edges
    batch = list(range(m, m + 5))
    nodes_t, x_t = _batch_twin(solver, batch, solver.config.damping)
    nodes, x = solver.batch_step(batch)
    _assert_same_steps(nodes, x, nodes_t, x_t, SAME_EQUATION)
    # the twin's damped variant is measurably different: the branch really is undamped
    _, x_d = _batch_twin(solver, batch, 1e-2, damped=True)
    assert np.abs(x_d - x_t).max() > 1e3 * SAME_EQUATION * np.abs(x_t).max()


@pytest.mark.parametrize("gps", [0, 3])
def test_batch_of_all_constraints_is_the_twin_gauss_newton_step(gps):
    """Eq. 37 reduces to eq. 14 (docs/mathematics.md#batches): against lstsq on the stacked twin
    Jacobian."""
    solver = _solver(_graph(31, n=9, extra=8, gps=gps))
    doms, jacs, rs = _twin_all(solver)
    free = _free_nodes(solver)
    jd, r = naive.stack_jacobian(doms, jacs, rs, free)
    x_gn = naive.gauss_newton_step(jd, r).reshape(-1, 6)
    nodes_t, x_t = _batch_twin(solver, list(range(solver.num_constraints)), 0.0)
    _assert_same_steps(nodes_t, x_t, np.array(free), x_gn, SAME_EQUATION)  # twin vs twin
    nodes, x = solver.batch_step(np.arange(solver.num_constraints), damping=0.0)
    _assert_same_steps(nodes, x, np.array(free), x_gn, SAME_EQUATION)


# --------------------------------------------------------------------------------- Algorithm 1
def _gps_and_relative(solver: HybridSolver) -> tuple[list[int], int]:
    m = solver.graph.num_edges
    return list(range(m, m + solver.graph.num_gps)), int(np.argmax(solver.tree.path_lengths()[:m]))


def test_gps_buffer_is_flushed_as_one_batch_before_a_relative_constraint():
    """Order [g1, g2, rel, g3], gps_batch_size 40: batch [g1, g2], then rel, then batch [g3]."""
    graph = _graph(32, n=12, extra=8, gps=4)
    tau = 0.8
    s1 = _solver(graph, gps_batch_size=40)
    (g1, g2, g3, _), rel = _gps_and_relative(s1)
    report = s1.step([g1, g2, rel, g3], tau=tau)
    assert (report.done, report.rejected) == (4, 0)

    s2 = _solver(graph, gps_batch_size=40)
    s2.batch_step([g1, g2], tau=tau)
    _, _, x = s2.probe(rel)
    p = _path(s2, rel)
    assert _step.cap_and_apply(s2.tree.path_node, p.start, p.stop - p.start, x, tau, s2.state,
                               np.empty((12, 3, 3))) != Update.REJECTED
    s2.batch_step([g3], tau=tau)
    _assert_bit_identical(s1, s2)

    # the grouping matters: one GPS reading at a time, or g3 with the others, moves elsewhere
    alternatives = (
        lambda s: (s.batch_step([g1], tau=tau), s.batch_step([g2], tau=tau),
                   s.step([rel], tau=tau), s.batch_step([g3], tau=tau)),
        lambda s: (s.batch_step([g1, g2, g3], tau=tau), s.step([rel], tau=tau)),
    )
    for run in alternatives:
        s3 = _solver(graph, gps_batch_size=40)
        run(s3)
        assert not np.array_equal(s3.state.trans, s1.state.trans)


def test_gps_buffer_is_flushed_when_full():
    """gps_batch_size 2 with three GPS readings in a row: batches [g1, g2] then [g3]."""
    graph = _graph(33, n=12, extra=8, gps=4)
    s1 = _solver(graph, gps_batch_size=2)
    (g1, g2, g3, _), _ = _gps_and_relative(s1)
    assert s1.step([g1, g2, g3], tau=0.9).done == 3
    s2 = _solver(graph, gps_batch_size=2)
    s2.batch_step([g1, g2], tau=0.9)
    s2.batch_step([g3], tau=0.9)
    _assert_bit_identical(s1, s2)
    s3 = _solver(graph, gps_batch_size=2)
    s3.batch_step([g1], tau=0.9)
    s3.batch_step([g2, g3], tau=0.9)
    assert not np.array_equal(s3.state.trans, s1.state.trans)


def test_gps_batch_size_reaches_the_kernel():
    graph = _graph(34, n=14, extra=8, gps=6)
    order = list(range(graph.num_edges, graph.num_constraints))  # six GPS readings in a row
    runs = {}
    for size in (1, 40):
        s = _solver(graph, gps_batch_size=size)
        s.step(order, tau=1.0)
        runs[size] = s
    assert not np.array_equal(runs[1].state.trans, runs[40].state.trans)
    one_by_one = _solver(graph)
    for g in order:
        one_by_one.batch_step([g], tau=1.0)
    _assert_bit_identical(runs[1], one_by_one)
    together = _solver(graph)
    together.batch_step(order, tau=1.0)
    _assert_bit_identical(runs[40], together)


def test_a_time_budget_stops_the_step_early_and_counts_what_it_did():
    graph = _graph(35, n=60, extra=40, gps=4)
    order = _solver(graph).tree.sweep_order
    reports, solvers = [], []
    for _ in range(2):
        s = _solver(graph)
        reports.append(s.step(order, budget_s=1e-9, tau=1.0))
        solvers.append(s)
    done = reports[0].done
    assert 1 <= done < order.shape[0]
    assert reports[1].done == done  # same seed, same work
    _assert_bit_identical(solvers[0], solvers[1])
    # StepReport.done is what was processed: the first `done` constraints, nothing more
    s = _solver(graph)
    s.step(order[:done], tau=1.0)
    _assert_bit_identical(solvers[0], s)
    assert _solver(graph).step(order, tau=1.0).done == order.shape[0]


# --------------------------------------------------------------------------------- damping
def _escalated_damping(bc: np.ndarray, scale: float, mu: float, k: int) -> float:
    """The damping after k tenfold escalations (the rule of docs/mathematics.md#hybrid-step /
    _dense)."""
    tr = max(float(np.trace(bc)), 0.0)
    damp = mu * tr / 6 + _dense.TINY * scale
    for _ in range(k):
        damp = max(10 * damp, 1e-12 * (tr + scale))
    return damp


def test_damping_escalates_until_an_indefinite_block_factors():
    rng = np.random.default_rng(36)
    q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    bc = q @ np.diag([-1e-10, 1.0, 2.0, 3.0, 4.0, 5.0]) @ q.T  # indefinite by "rounding"
    mu, scale = 1e-13, 0.0
    out = np.empty((6, 6))
    k = _dense.regularized_factor(bc, scale, mu, out)
    assert 0 < k < _dense.MAX_DAMPING_ESCALATIONS
    damp = _escalated_damping(bc, scale, mu, k)
    assert np.all(np.triu(out, 1) == 0.0) and np.all(np.diag(out) > 0.0)
    want = 0.5 * (bc + bc.T) + damp * np.eye(6)
    assert _rel_err(out @ out.T, want) <= FLOAT64_IDENTITY
    # and it stopped at the first damping that works: one step less is still indefinite
    assert np.linalg.eigvalsh(0.5 * (bc + bc.T) + _escalated_damping(bc, scale, mu, k - 1)
                             * np.eye(6))[0] < 0.0
    # a positive definite block factors with no escalation
    assert _dense.regularized_factor(q @ np.diag(np.arange(1.0, 7.0)) @ q.T, 1.0, mu, out) == 0


def test_a_block_that_never_factors_reports_max_escalations():
    bc = np.eye(6)
    bc[2, 2] = np.nan
    assert _dense.regularized_factor(bc, 1.0, 1e-6, np.empty((6, 6))) == (
        _dense.MAX_DAMPING_ESCALATIONS)


# --------------------------------------------------------------------------------- known bugs
def test_a_single_gps_reading_is_relaxed():
    """Was a bug: with one GPS reading the anchor's block of B_C is exactly 0, the undamped
    dense system is singular (a rotation about the reading is free), and every GPS batch was
    rejected.  The dense branch now falls back to the damped system
    (docs/mathematics.md#hybrid-step)."""
    graph = _graph(37, n=10, extra=6, gps=1)
    solver = _solver(graph, sweeps=5)
    anchor = int(graph.gps_nodes[0])
    before = np.linalg.norm(graph.translations[anchor] - graph.gps_positions[0])
    result = solver.run()
    after = np.linalg.norm(result.translations[anchor] - graph.gps_positions[0])
    assert result.stats["rejected_steps"] == 0
    assert after < 0.5 * before


def test_non_finite_updates_are_rejected_counted_and_not_applied():
    """A NaN whitening makes a single update and a GPS batch non-finite: nothing moves."""
    from hybridpgo.errors import SolverError

    solver = _solver(_graph(38, gps=2))
    m = solver.graph.num_edges
    rot0, trans0 = _poses(solver)
    solver.problem.edge_lt[0, 0, 0] = np.nan
    solver.problem.gps_lt[1, 0, 0] = np.nan
    report = solver.step([0, m + 1], tau=1.0)
    assert (report.done, report.capped, report.rejected) == (2, 0, 2)
    assert np.array_equal(solver.state.rot, rot0) and np.array_equal(solver.state.trans, trans0)
    with pytest.raises(SolverError, match="not finite"):
        solver.batch_step([m + 1], tau=1.0)
    assert np.array_equal(solver.state.rot, rot0) and np.array_equal(solver.state.trans, trans0)
