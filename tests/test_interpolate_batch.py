"""Interpolated GPS batches (paper III-E with III-G, docs/mathematics.md#interpolated-solving):
kept nodes on the union of the
batch's paths, merged chains, the same distribution as single updates."""

from __future__ import annotations

import naive
import numpy as np
from graphs import random_graph
from test_interpolate import _distribute_twin, _oriented
from tolerances import SAME_EQUATION

from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, _batch, solve_hybrid
from hybridpgo.solvers.hybrid._dense import TINY
from hybridpgo.tree import LINK_GPS


def _gps_chain(seed: int, n: int = 60, gps: int = 6):
    graph, _, _ = random_graph(np.random.default_rng(seed), n=n, extra=4, gps=gps,
                               rot_scale=0.2, noise=0.05)
    return graph


def _union_size(solver: HybridSolver, cs) -> int:
    tree = solver.tree
    return len({int(v) for c in cs for v in tree.path_node[tree.path_ptr[c]:tree.path_ptr[c + 1]]})


def test_dmax_at_least_every_batch_union_is_the_full_batch_update_bit_for_bit() -> None:
    graph = _gps_chain(4)
    probe = HybridSolver(graph)
    m, g = graph.num_edges, graph.num_gps
    # D_max at least the union of *all* GPS domains (so of every batch) and the longest path
    bound = max(_union_size(probe, range(m, m + g)), int(probe.tree.path_lengths().max()))
    full = solve_hybrid(graph, HybridConfig(sweeps=3, gps_batch_size=g))
    same = solve_hybrid(graph, HybridConfig(sweeps=3, gps_batch_size=g, dmax=bound))
    assert np.array_equal(full.rotations, same.rotations)
    assert np.array_equal(full.translations, same.translations)
    # a GPS batch whose union exceeds D_max is interpolated: the result changes (the test can
    # fail); every single path fits, so only the batches differ
    longest = int(probe.tree.path_lengths().max())
    union = _union_size(probe, range(m, m + g))
    assert longest < union
    batched = solve_hybrid(graph, HybridConfig(sweeps=3, gps_batch_size=g, dmax=longest))
    assert not np.array_equal(full.translations, batched.translations)


def _link(graph, tree, solver, node):
    """Desired link transform (parent -> child), its information (6x6) and whether its error
    lives in the child's frame (plain NumPy)."""
    if tree.link_kind[node] == LINK_GPS:
        gi = int(tree.link_index[node])
        info = np.zeros((6, 6))
        info[:3, :3] = graph.gps_information[gi]
        return solver.state.rot[node].copy(), graph.gps_positions[gi], info, False
    r, t = _oriented(graph, tree, node)
    return r, t, graph.edge_information[tree.link_index[node]], bool(tree.link_forward[node])


def _merged_twin(graph, tree, solver, chain, ya, yb, old_alpha):
    """``J_β^T J_β - J_α^T J_α`` of a chain b ... top below a (eq. 31-33, NumPy 4x4)."""
    desired = [np.eye(4)]
    frames = []
    for node in chain[::-1]:  # top down
        r, t, info, child_frame = _link(graph, tree, solver, node)
        parent_r = desired[-1][:3, :3]
        desired.append(desired[-1] @ naive.to_matrix(r, t))
        frames.append((desired[-1][:3, :3] if child_frame else parent_r, info))
    p_beta = desired[-1]
    r_ab = p_beta[:3, :3]
    s_beta = np.zeros((6, 6))
    for frame, info in frames:
        rot6 = np.kron(np.eye(2), r_ab.T @ frame)
        s_beta += rot6 @ info @ rot6.T
    rab, tab = naive.between(ya[0], ya[1], yb[0], yb[1])
    e = naive.relative_error(p_beta[:3, :3], p_beta[:3, 3], rab, tab)
    jri = naive.se3_right_jacobian_inv(e)
    return jri.T @ s_beta @ jri - old_alpha


def test_interpolated_gps_batch_matches_a_numpy_twin() -> None:
    """D_max below the union: kept nodes (every endpoint and branch point), the reduced system
    with merged chains, its solve and the distribution, against plain NumPy."""
    graph = _gps_chain(5)
    solver = HybridSolver(graph, HybridConfig(init="tree"))
    tree, prob, state = solver.tree, solver.problem, solver.state
    m, g = graph.num_edges, graph.num_gps
    cs = np.arange(m, m + g, dtype=np.int64)
    d_max = 10
    nu = _union_size(solver, cs)
    assert d_max < nu
    before = (state.rot.copy(), state.trans.copy(), state.bdiag.copy(), state.contrib.copy())
    nt = tree.num_tree_nodes
    slot = np.full(nt, -1, np.int64)
    x_out = np.zeros((nt, 6))
    nodes_out = np.zeros(nt, np.int64)
    tau = 0.7
    nk = _batch.batch_relax(prob, state, cs, g, tau, solver.config.damping, slot, x_out,
                            nodes_out, d_max)
    assert 0 < nk < nu and np.all(slot == -1)
    kept = [int(v) for v in nodes_out[:nk]]
    rot0, trans0, bdiag0, contrib0 = before
    grot, gtr = naive.tree_globals(tree.parent, rot0, trans0)
    # the union, its per-node constraint sets, and the kept-node rules
    doms = [tree.path_node[tree.path_ptr[c]:tree.path_ptr[c + 1]].astype(np.int64) for c in cs]
    union = sorted({int(v) for d in doms for v in d})
    through = {v: frozenset(q for q, d in enumerate(doms) if v in d) for v in union}
    children = {v: [u for u in union if tree.parent[u] == v] for v in union}
    forced = [v for v in union if len(children[v]) != 1 or any(int(d[0]) == v for d in doms)]
    assert set(forced) <= set(kept)  # every endpoint and branch point is solved for
    assert len(kept) <= max(d_max, len(forced))
    # the twin's B̃ on the kept nodes (eq. 36 then eq. 31)
    bc, scale = {}, {}
    jacs, rs = [], []
    for c, dom in zip(cs, doms, strict=True):
        gi = int(c - m)
        jac, r = naive.gps_jacobian(grot, gtr, int(dom[0]), graph.gps_positions[gi],
                                    prob.gps_lt[gi], dom)
        jacs.append(jac)
        rs.append(r)
    for v in union:
        bc[v] = bdiag0[v].copy()
        scale[v] = 0.0
        for q, (c, dom) in enumerate(zip(cs, doms, strict=True)):
            for k, u in enumerate(dom):
                if int(u) == v:
                    bc[v] -= contrib0[tree.path_ptr[c] + k]
                    scale[v] += float(np.trace(jacs[q][k].T @ jacs[q][k]))
        if len(through[v]) == prob.path_count[v]:  # every constraint on v is in the batch
            bc[v] = np.zeros((6, 6))
    chains = {}
    for b in kept:
        chain = [b]
        while tree.parent[chain[-1]] >= 0 and int(tree.parent[chain[-1]]) in union \
                and int(tree.parent[chain[-1]]) not in kept:
            chain.append(int(tree.parent[chain[-1]]))
        chains[b] = chain
        if len(chain) > 1:
            assert len({through[v] for v in chain}) == 1  # a chain stays in one segment
            a = int(tree.parent[chain[-1]])
            ya = (grot[a], gtr[a]) if a >= 0 else (np.eye(3), np.zeros(3))
            old = contrib0[tree.path_ptr[prob.link_constraint[b]]]
            bc[b] = bc[b] + _merged_twin(graph, tree, solver, chain, ya, (grot[b], gtr[b]), old)
    assert any(len(ch) > 1 for ch in chains.values())
    # a zero block of B_C (the anchor, only GPS pass through it): the undamped dense branch
    zero = [v for v in kept if len(through[v]) == prob.path_count[v]]
    assert zero
    bd = np.zeros((6 * nk, 6 * nk))
    for j, v in enumerate(kept):
        bd[6 * j:6 * j + 6, 6 * j:6 * j + 6] = bc[v] if zero else naive.damped_block(
            bc[v], scale[v], solver.config.damping, TINY)
    sub_doms = [np.array([v for v in d if int(v) in kept], np.int64) for d in doms]
    sub_jacs = [j[[int(v) in kept for v in d]] for j, d in zip(jacs, doms, strict=True)]
    jd, r = naive.stack_jacobian(sub_doms, sub_jacs, rs, kept)
    x_twin = np.linalg.solve(jd.T @ jd + bd, jd.T @ r).reshape(nk, 6)
    err = np.abs(x_out[:nk] - x_twin).max() / np.abs(x_twin).max()
    assert err <= SAME_EQUATION
    # the distribution: each kept node's desired pose Y_b Exp(t x_b), spread over its chain
    t, _ = naive.capped_temperature(x_twin, tau)
    want_r, want_t = rot0.copy(), trans0.copy()
    for j, b in enumerate(kept):
        chain = chains[b]
        if len(chain) == 1:
            want_r[b], want_t[b] = naive.retract(rot0[b], trans0[b], x_twin[j], t)
            continue
        a = int(tree.parent[chain[-1]])
        ra, ta = (grot[a], gtr[a]) if a >= 0 else (np.eye(3), np.zeros(3))
        rb, tb = naive.retract(grot[b], gtr[b], x_twin[j], t)
        want_r, want_t = _distribute_twin(want_r, want_t, state.bdiag, np.array(chain), ra, ta,
                                          rb, tb)
    # the kernel's and the twin's steps agree to SAME_EQUATION (relative), the poses follow
    size = max(1.0, float(np.abs(want_t).max()))
    assert np.abs(state.rot - want_r).max() <= SAME_EQUATION
    assert np.abs(state.trans - want_t).max() <= SAME_EQUATION * size
    # 𝔅(H) was updated over the whole union, as a full batch does
    ref = HybridSolver(graph, HybridConfig(init="tree"))
    ref.batch_step(cs)
    assert np.array_equal(state.bdiag, ref.state.bdiag)


def test_interpolated_gps_batches_converge() -> None:
    graph = _gps_chain(6, n=80, gps=8)
    full = solve_hybrid(graph, HybridConfig(sweeps=10, init="tree", gps_batch_size=8))
    res = solve_hybrid(graph, HybridConfig(sweeps=10, init="tree", gps_batch_size=8, dmax=16))
    assert res.stats["rejected_steps"] == 0
    # measured: E 60.4 -> 2.68 (full batches: 1.64; D_max = 8: 3.31, and 3.34 when every
    # reading is its own interpolated update, gps_batch_size 1); longest path 25, union of a
    # batch up to ~50 nodes
    assert res.final_energy < 0.06 * res.initial_energy
    assert res.final_energy < 2.0 * full.final_energy


def test_a_gps_batch_with_a_zero_block_is_solved_densely_only_on_a_small_union() -> None:
    """All the GPS readings in one batch leave the tree's root with nothing but them through it
    (a zero block of B_C).  Up to MAX_DENSE_NODES union nodes the batch takes the exact dense
    step (not the segments' damped one); beyond, the segments with that block damped: the step
    of ``dense=False`` to the bit (the dense solve would cost O((6 |U|)^3))."""
    from hybridpgo.solvers.hybrid._batch_solve import MAX_DENSE_NODES

    for n, gps, small in ((30, 5, True), (300, 12, False)):
        graph = _gps_chain(6, n=n, gps=gps)
        m, g = graph.num_edges, graph.num_gps
        cs = np.arange(m, m + g, dtype=np.int64)
        poses = {}
        for dense in (True, False):
            solver = HybridSolver(graph, HybridConfig(init="tree"))
            nt = solver.tree.num_tree_nodes
            nu = _batch.batch_relax(solver.problem, solver.state, cs, g, 0.7,
                                    solver.config.damping, np.full(nt, -1, np.int64),
                                    np.zeros((nt, 6)), np.zeros(nt, np.int64), 0, dense)
            assert nu == _union_size(solver, cs)
            poses[dense] = (solver.state.rot.copy(), solver.state.trans.copy())
        assert (nu <= MAX_DENSE_NODES) == small
        same = all(np.array_equal(a, b) for a, b in zip(poses[True], poses[False], strict=True))
        assert same != small
