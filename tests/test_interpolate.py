"""Interpolated solving (paper III-E, docs/mathematics.md#interpolated-solving): kept nodes, merged
constraints, distribution."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from scipy.spatial.transform import Rotation
from tolerances import FLOAT64_IDENTITY

from hybridpgo._cost import retract_into
from hybridpgo.solvers.hybrid import (
    HybridConfig,
    HybridSolver,
    _distribute,
    _linearize,
    _merge,
    _step,
    solve_hybrid,
)
from hybridpgo.solvers.hybrid import _interpolate as ip
from hybridpgo.solvers.hybrid.problem import State, new_workspace


def _chain_graph(rng: np.random.Generator, n: int = 40, gps: int = 0):
    """A long odometry chain closed by a loop (long domains), noisy, plus random loops."""
    graph, _, _ = random_graph(rng, n=n, extra=4, gps=gps, rot_scale=0.2, noise=0.05)
    return graph


@pytest.mark.parametrize(("d", "na", "d_max"), [
    (182, 90, 10), (182, 0, 10), (182, 181, 10), (20, 3, 10), (5, 2, 3), (182, 1, 10),
    (7, 3, 2), (9, 0, 1), (30, 29, 29),
])
def test_kept_positions_are_uniform_sorted_and_keep_the_endpoints(d: int, na: int,
                                                                  d_max: int) -> None:
    keep = np.empty(d_max, np.int64)
    n = ip.kept_positions(d, na, d_max, keep)
    kept = keep[:n]
    assert 1 <= n <= d_max
    assert np.all(np.diff(kept) > 0) and kept[0] >= 0 and kept[-1] < d
    if na > 0:
        assert 0 in kept  # endpoint a
    if (na < d and d_max >= 2) or na == 0:
        assert na in kept  # endpoint b
    for lo, hi in ((0, na), (na, d)):  # spacing within a side is uniform to one position
        side = kept[(kept >= lo) & (kept < hi)]
        if side.size >= 3:
            gaps = np.diff(side)
            assert gaps.max() - gaps.min() <= 1


def test_dmax_at_least_the_path_length_is_the_full_update_bit_for_bit() -> None:
    rng = np.random.default_rng(0)
    graph = _chain_graph(rng, gps=3)
    longest = int(HybridSolver(graph).tree.path_lengths().max())
    full = solve_hybrid(graph, HybridConfig(sweeps=4, gps_batch_size=2))
    same = solve_hybrid(graph, HybridConfig(sweeps=4, gps_batch_size=2, dmax=longest))
    assert np.array_equal(full.rotations, same.rotations)
    assert np.array_equal(full.translations, same.translations)
    fewer = solve_hybrid(graph, HybridConfig(sweeps=4, gps_batch_size=2, dmax=longest - 1))
    assert not np.array_equal(full.translations, fewer.translations)  # the test can fail


def _oriented(graph, tree, node):
    """Desired transform of node's tree link, parent -> child (plain NumPy)."""
    e = int(tree.link_index[node])
    r, t = graph.edge_rotations[e], graph.edge_translations[e]
    if tree.link_forward[node]:
        return r, t
    return r.T, -r.T @ t


def test_merged_constraint_composes_its_chain() -> None:
    """Eq. 32: p_β is the product of the links' measurements; eq. 33: S_β the sum of their
    information rotated into b's frame (a forward link's error lives in the child's frame)."""
    rng = np.random.default_rng(1)
    graph = _chain_graph(rng)
    solver = HybridSolver(graph)
    tree = solver.tree
    b = int(np.argmax(tree.depth))
    chain = [b]
    while len(chain) < 6:
        chain.append(int(tree.parent[chain[-1]]))
    nodes = np.array(chain, np.int64)  # b ... top
    zr, zt, s_beta = np.empty((3, 3)), np.empty(3), np.empty((6, 6))
    _merge.merged_constraint(solver.problem, solver.state, nodes, 0, len(chain), zr, zt,
                             s_beta, np.empty((5, 3, 3)), np.empty((6, 6)))
    r_acc, t_acc = np.eye(3), np.zeros(3)
    frames = []
    for node in chain[::-1]:
        r, t = _oriented(graph, tree, node)
        r_parent = r_acc
        t_acc = r_acc @ t + t_acc
        r_acc = r_acc @ r
        frames.append((node, r_acc if tree.link_forward[node] else r_parent))
    np.testing.assert_allclose(zr, r_acc, rtol=0, atol=FLOAT64_IDENTITY)
    np.testing.assert_allclose(zt, t_acc, rtol=0, atol=FLOAT64_IDENTITY * np.abs(t_acc).max())
    expected = np.zeros((6, 6))
    for node, frame in frames:
        rot6 = np.kron(np.eye(2), r_acc.T @ frame)
        expected += rot6 @ graph.edge_information[tree.link_index[node]] @ rot6.T
    np.testing.assert_allclose(s_beta, expected, rtol=0,
                               atol=FLOAT64_IDENTITY * np.abs(expected).max() * 10)


def _distribute_twin(rot, trans, bdiag, nodes, ra, ta, rb_new, tb_new):
    """docs/mathematics.md#interpolated-solving in plain NumPy (global frame, 4x4 matrices):
    rotation about one axis by the
    cumulative-weight profile, then translation on the re-bent chain."""
    k = len(nodes)
    top_down = nodes[::-1]
    def mat(r, t):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, t
        return m
    a = mat(ra, ta)
    glob = [a]
    for n in top_down:
        glob.append(glob[-1] @ mat(rot[n], trans[n]))
    target = mat(rb_new, tb_new)
    delta = target[:3, :3] @ glob[-1][:3, :3].T  # rotation change of b, world frame
    rotvec = Rotation.from_matrix(delta).as_rotvec()
    wr = np.array([1 / bdiag[n][3:, 3:].diagonal().min() for n in top_down])
    wt = np.array([1 / bdiag[n][:3, :3].diagonal().min() for n in top_down])
    fr, ft = np.cumsum(wr) / wr.sum(), np.cumsum(wt) / wt.sum()
    new = [a]
    for j, n in enumerate(top_down):
        r_new = Rotation.from_rotvec(fr[j] * rotvec).as_matrix() @ glob[j + 1][:3, :3]
        t_new = new[-1][:3, :3] @ trans[n] + new[-1][:3, 3]
        new.append(mat(r_new, t_new))
    shift = target[:3, 3] - new[-1][:3, 3]
    for j in range(k):
        new[j + 1][:3, 3] += ft[j] * shift
    out_r, out_t = rot.copy(), trans.copy()
    for j, n in enumerate(top_down):
        local = np.linalg.inv(new[j]) @ new[j + 1]
        out_r[n], out_t[n] = local[:3, :3], local[:3, 3]
    return out_r, out_t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_distribution_matches_a_numpy_twin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t_nodes, k = 9, 6
    rot = Rotation.random(t_nodes, random_state=seed).as_matrix()
    trans = rng.normal(size=(t_nodes, 3))
    bdiag = np.array([np.diag(rng.uniform(0.5, 4.0, 6)) for _ in range(t_nodes)])
    nodes = np.array([7, 5, 4, 2, 1, 3][:k], np.int64)  # b ... top
    ra, ta = Rotation.random(random_state=seed + 10).as_matrix(), rng.normal(size=3)
    rb_new = Rotation.random(random_state=seed + 20).as_matrix()
    tb_new = rng.normal(size=3) * 3
    state = State(rot.copy(), trans.copy(), bdiag, np.zeros((1, 6, 6)))
    # the chain starts at an offset, as in a path
    _distribute.distribute_chain(state, np.concatenate([[0, 8], nodes]), 2, k, ra, ta, rb_new,
                                 tb_new, new_workspace(k))
    want_r, want_t = _distribute_twin(rot, trans, bdiag, nodes, ra, ta, rb_new, tb_new)
    np.testing.assert_allclose(state.rot, want_r, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.trans, want_t, rtol=0, atol=1e-11)
    # b reaches its desired pose exactly, and rotations stay orthonormal
    g = np.eye(4)
    g[:3, :3], g[:3, 3] = ra, ta
    for n in nodes[::-1]:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = state.rot[n], state.trans[n]
        g = g @ m
    np.testing.assert_allclose(g[:3, :3], rb_new, rtol=0, atol=1e-12)
    np.testing.assert_allclose(g[:3, 3], tb_new, rtol=0, atol=1e-11)
    gram = np.einsum("kji,kjl->kil", state.rot, state.rot)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), rtol=0, atol=1e-14)


@pytest.mark.parametrize("d_max", [2, 5])
def test_all_chains_at_once_equal_chain_by_chain(d_max: int) -> None:
    """reduced_factors and distribute treat every merged chain of an update in one call; the
    result is merged_block / distribute_chain applied chain by chain, bit for bit (d_max = 2:
    both sides keep only their endpoint, whose chain reaches the root)."""
    rng = np.random.default_rng(4)
    solver = HybridSolver(_chain_graph(rng, n=60))
    prob, state, tree = solver.problem, solver.state, solver.tree
    lengths = tree.path_lengths()
    c = int(np.argmax(lengths))
    d = int(lengths[c])
    s = int(prob.path_ptr[c])
    wk, sub, keep = new_workspace(solver.dmax), new_workspace(d_max), np.empty(d_max, np.int64)
    kr, na = _linearize.linearize(prob, c, state.rot, state.trans, wk, wk.jac)
    assert 0 < na < d
    _step.accumulate_blocks(prob, state, c, kr, wk.jac, 0.1, wk.lfac, wk.bc, False)
    nk = ip.kept_positions(d, na, d_max, keep)
    ip.reduced_factors(prob, state, c, d, na, kr, wk, keep, nk, 0.1, sub)
    pr, pt = wk.path_rot.copy(), wk.path_trans.copy()
    x = rng.normal(size=(nk, 6)) * 0.05
    chains = []
    roots = 0  # merged chains whose top parent is the root
    for j in range(nk):
        p = int(keep[j])
        end = int(ip.chain_end(d, na, keep, nk, j))
        if end < (na if p < na else d):
            ra, ta = pr[end], pt[end]
        else:  # the chain reaches the constraint's root
            ra, ta = np.eye(3), np.zeros(3)
        roots += end - p > 1 and not end < (na if p < na else d)
        want = state.bdiag[prob.path_node[s + p]] - state.contrib[s + p]
        if end - p > 1:
            _merge.merged_block(prob, state, prob.path_node, s + p, end - p, ra, ta,
                                pr[p].copy(), pt[p].copy(), want, new_workspace(1))
        assert np.array_equal(sub.w[j], want)
        chains.append((p, end - p, ra, ta))
    assert any(k > 1 for _, k, _, _ in chains)
    assert roots >= 1 or d_max != 2
    rot0, trans0 = state.rot.copy(), state.trans.copy()
    before = state.trans.copy()
    ip.distribute(prob, state, c, d, na, keep, nk, x, 0.7, wk)
    twin = State(rot0, trans0, state.bdiag, state.contrib)
    er, tmp = np.empty((3, 3)), np.empty((3, 3))
    for j, (p, k, ra, ta) in enumerate(chains):
        i = prob.path_node[s + p]
        if k == 1:
            retract_into(rot0[i], trans0[i], x[j], 0.7, rot0[i], trans0[i], er, tmp)
            continue
        rb, tb = np.empty((3, 3)), np.empty(3)
        retract_into(pr[p], pt[p], x[j], 0.7, rb, tb, er, tmp)
        _distribute.distribute_chain(twin, prob.path_node, s + p, k, ra, ta, rb, tb,
                                     new_workspace(d))
    assert np.array_equal(state.rot, rot0) and np.array_equal(state.trans, trans0)
    assert not np.array_equal(state.trans, before)  # the test can fail


@pytest.mark.parametrize("gps", [0, 4])
def test_subsampled_sweeps_converge_and_stay_orthonormal(gps: int) -> None:
    rng = np.random.default_rng(3)
    graph = _chain_graph(rng, n=60, gps=gps)
    full = solve_hybrid(graph, HybridConfig(sweeps=15, init="tree"))
    res = solve_hybrid(graph, HybridConfig(sweeps=15, dmax=8, init="tree"))  # longest path: 28
    assert res.stats["rejected_steps"] == 0
    # measured: E 53.7 -> 0.675 (full update: 0.387) without GPS; 121 -> 0.731 (0.712) with
    # GPS.  Much smaller D_max oscillates on this graph (paper IV: over-subsampling), e.g. D_max
    # = 4 stops at 11.1 / 6.0.
    assert res.final_energy < 0.02 * res.initial_energy
    assert res.final_energy < 2.0 * full.final_energy
    gram = np.einsum("kji,kjl->kil", res.rotations, res.rotations)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), rtol=0, atol=1e-12)


def test_dmax_is_validated() -> None:
    for bad in (0, 1, -3, 2.5, True):
        with pytest.raises(ValueError, match="dmax"):
            HybridConfig(dmax=bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("factor", [True, False])
def test_linearize_accumulate_equals_the_two_kernels_bit_for_bit(factor: bool) -> None:
    """The fused pass (Jacobian blocks and 𝔅(H) in one loop) against its naive twin:
    ``relative_linearization`` then ``accumulate_path``; with a keep list only those blocks are
    stored."""
    rng = np.random.default_rng(3)
    graph = _chain_graph(rng)
    solver = HybridSolver(graph)
    prob = solver.problem
    lengths = solver.tree.path_lengths()
    for c in (int(np.argmax(lengths)), int(np.argmin(lengths))):
        s, d = int(prob.path_ptr[c]), int(lengths[c])
        twin, fused = (State(*(a.copy() for a in solver.state)) for _ in range(2))
        shift = 0.1 * rng.standard_normal(twin.trans.shape)  # moved: 𝔅(H) must change
        twin.trans[:] += shift
        fused.trans[:] += shift
        wt, wf = new_workspace(d), new_workspace(d)
        args = (prob.path_node, prob.path_sign, s, d, prob.edge_rot[c], prob.edge_trans[c],
                prob.edge_lt[c], prob.robust_kind, prob.robust_scale)
        na = _linearize.relative_linearization(*args, twin.rot, twin.trans, wt.path_rot,
                                               wt.path_trans, wt.iws, wt.ws, wt.e, wt.r, wt.jri,
                                               wt.a, wt.jac)
        _step.accumulate_path(prob.path_node, s, d, 6, wt.jac, twin.bdiag, twin.contrib, 0.1,
                              wt.lfac, wt.bc, factor)
        assert _linearize.relative_setup(*args, fused.rot, fused.trans, wf.path_rot,
                                         wf.path_trans, wf.iws, wf.ws, wf.e, wf.r, wf.jri,
                                         wf.a) == na
        keep = np.array([0, d // 2, d - 1][: min(d, 3)], np.int64)
        keep = np.unique(keep)
        _step.linearize_accumulate(prob.path_node, prob.path_sign, s, d, na, wf.path_rot,
                                   wf.path_trans, wf.a, wf.jac, False, keep, keep.size,
                                   fused.bdiag, fused.contrib, 0.1, wf.lfac, wf.bc, factor)
        assert np.array_equal(fused.bdiag, twin.bdiag)
        assert np.array_equal(fused.contrib, twin.contrib)
        assert np.array_equal(wf.jac[keep], wt.jac[keep])
        assert np.array_equal(wf.r, wt.r)
        assert not np.array_equal(twin.bdiag, solver.state.bdiag)  # the test can fail
        if factor:
            assert np.array_equal(wf.lfac[:d], wt.lfac[:d])
        _step.linearize_accumulate(prob.path_node, prob.path_sign, s, d, na, wf.path_rot,
                                   wf.path_trans, wf.a, wf.jac, True, keep, 0, fused.bdiag,
                                   fused.contrib, 0.1, wf.lfac, wf.bc, factor)
        assert np.array_equal(wf.jac[:d], wt.jac[:d])
