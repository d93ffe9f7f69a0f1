"""The online mode (docs/mathematics.md#frames): paths, budget, accuracy, bad input, save/load."""

from __future__ import annotations

import copy
import itertools
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from graphs import random_graph
from tolerances import (
    FLOAT64_IDENTITY,
    ISAM2_VS_OPTIMUM,
    ONLINE_CITY_RATIO,
    ONLINE_REFINED,
    REFINE_REPEATED,
)

from hybridpgo.energy import energy
from hybridpgo.errors import FormatError, GraphError
from hybridpgo.io import bundled_path, read_graph
from hybridpgo.online import OnlineConfig, OnlineSolver
from hybridpgo.online._link import adopt_result
from hybridpgo.online.replay import feed_frame, make_stream, prefix_optima
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.hybrid import _batch

# the fixed budget of a deterministic frame (budget_s=None): runs do not depend on timing
UPDATES = 12


def _graph(seed: int = 0, n: int = 40, extra: int = 25, gps: int = 0):  # type: ignore[no-untyped-def]
    g, _, _ = random_graph(np.random.default_rng(seed), n=n, extra=extra, gps=gps, noise=0.02)
    return g


def _stream(solver: OnlineSolver, graph, frames: range, updates: int | None = UPDATES
            ) -> None:  # type: ignore[no-untyped-def]
    st = make_stream(graph)
    for k in frames:
        feed_frame(solver, st, k)
        solver.update(None, updates)


def _state(s: OnlineSolver) -> dict[str, np.ndarray]:
    """Every array and counter of the solver's state (what a saved state holds)."""
    return s.state_arrays()


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray], timing: bool = True) -> None:
    """Exactly equal states; ``timing=False``: except the cost model, learnt from the clock."""
    assert a.keys() == b.keys()
    for k in a:
        if k == "model" and not timing:
            continue
        assert a[k].shape == b[k].shape and np.array_equal(a[k], b[k]), k


# --------------------------------------------------------------------------- stream and paths
def test_stream_frames_bring_each_edge_once_odometry_first() -> None:
    g = _graph()
    st = make_stream(g)
    assert st.num_frames == g.num_nodes
    assert sorted(st.edges.tolist()) == list(range(g.num_edges))
    for k in range(1, st.num_frames):
        first = st.edges[st.edge_ptr[k]]
        assert first == st.odometry[k]
        fa, fb = st.frame_of[g.edge_nodes[first]]
        assert max(fa, fb) == k and min(fa, fb) == k - 1  # the chain's previous pose


def test_paths_follow_tree_conventions() -> None:
    """a side from a upward (-1), b side from b upward (+1), LCA excluded; GPS: n upward."""
    g = _graph(gps=4)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    parent = s.store.parent
    cm = s.store.cap_m

    def up(v: int) -> list[int]:
        out = []
        while v >= 0:
            out.append(v)
            v = int(parent[v])
        return out

    count = np.zeros(s.store.n + 1, np.int64)
    for c in list(range(s.num_edges)) + [cm + q for q in range(s.num_gps)]:
        if c < cm:
            a, b = (int(v) + 1 for v in s.store.edge_ab[c])
        else:
            a, b = 0, int(s.store.gps_node[c - cm]) + 1
        ua, ub = up(a), up(b)
        root = next(v for v in ua if v in ub)
        want = ua[: ua.index(root)] + ub[: ub.index(root)]
        signs = [-1] * ua.index(root) + [1] * ub.index(root)
        lo, hi = s.store.ptr[c], s.store.ptr[c + 1]
        assert s.store.path_node[lo:hi].tolist() == want
        assert s.store.path_sign[lo:hi].tolist() == signs
        np.add.at(count, want, 1)
    assert np.array_equal(count, s.store.path_count[: s.store.n + 1])
    # the tree: parents come first, the first pose hangs from the earth
    assert parent[0] == -1 and parent[1] == 0
    assert np.all(parent[1: s.store.n + 1] < np.arange(1, s.store.n + 1))


def test_oldest_tree_is_shallower_than_the_odometry_chain() -> None:
    g = _graph(n=60, extra=40)
    depth = {}
    for tree in ("oldest", "odometry"):
        s = OnlineSolver(OnlineConfig(background_refine=False, tree=tree))
        _stream(s, g, range(g.num_nodes))
        depth[tree] = s.stats()["path_entries"]
        # whatever the tree, the estimate explains the same constraints
        assert np.isfinite(s.energy())
    assert depth["oldest"] < depth["odometry"]


# --------------------------------------------------------------------------- accuracy
def test_estimate_approaches_the_batch_optimum() -> None:
    """Hybrid updates alone: within a stated factor of the optimum; refine(): the optimum."""
    g = _graph(seed=1)
    st = make_stream(g)
    opt = prefix_optima(st, [st.num_frames])[st.num_frames]
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes), updates=None)
    for _ in range(50):
        s.update(None, None)
    e = s.energy()
    start = energy(st.prefix(st.num_frames), *_odometry_start(st))
    assert e < 1.5 * opt < start  # the stochastic updates' fixed point is near the optimum
    s.refine(20)
    assert abs(s.energy() - opt) <= ONLINE_REFINED * opt


def test_planar_data_is_planar_measurements_and_decoupled_information() -> None:
    """``planar_data`` (refine() solves and tests such a map as 2D): every measurement in the
    xy-plane and no information coupling in-plane with out-of-plane coordinates, GPS included;
    the poses do not matter."""
    import dataclasses

    from hybridpgo.generate import generate_grid
    from hybridpgo.graph import decoupled_information, planar_data

    flat = generate_grid("m3500", seed=1, num_poses=30).graph
    assert flat.is_2d and planar_data(flat)
    assert not planar_data(generate_grid("grid3d", seed=1, num_poses=30).graph)
    plain = dataclasses.replace(flat, is_2d=False)
    assert planar_data(plain)  # the flag does not matter, the data do
    tilted = np.array(plain.rotations)
    tilted[:, :, :] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    assert planar_data(dataclasses.replace(plain, rotations=tilted))  # poses are not checked

    lifted = np.array(plain.edge_translations)
    lifted[3, 2] = 1e-12
    assert not planar_data(dataclasses.replace(plain, edge_translations=lifted))
    c, s = np.cos(1e-9), np.sin(1e-9)
    roll = np.array(plain.edge_rotations)
    roll[5] = roll[5] @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    assert not planar_data(dataclasses.replace(plain, edge_rotations=roll))
    info = np.array(plain.edge_information)
    info[7, 0, 2] = info[7, 2, 0] = 1e-6 * info[7, 0, 0]  # x with z
    assert not planar_data(dataclasses.replace(plain, edge_information=info))
    info = np.array(plain.edge_information)
    info[7, 3, 5] = 1e-12 * info[7, 5, 5]  # roll with yaw, on one side (within symmetry)
    assert not planar_data(dataclasses.replace(plain, edge_information=info))
    # the information test alone (the incremental solver's planar system uses it)
    assert decoupled_information(plain.edge_information) and not decoupled_information(info)

    nodes = np.array([4, 9, 20], np.int32)
    gps = dataclasses.replace(plain, gps_nodes=nodes,
                              gps_positions=np.array(plain.translations)[nodes],
                              gps_information=np.broadcast_to(np.eye(3), (3, 3, 3)).copy())
    assert planar_data(gps)
    pos = np.array(gps.gps_positions)
    pos[1, 2] = 0.5
    assert not planar_data(dataclasses.replace(gps, gps_positions=pos))
    ginfo = np.array(gps.gps_information)
    ginfo[2, 1, 2] = ginfo[2, 2, 1] = 0.1
    assert not planar_data(dataclasses.replace(gps, gps_information=ginfo))
    lone = dataclasses.replace(plain, edge_nodes=np.zeros((0, 2), np.int32),
                               edge_rotations=np.zeros((0, 3, 3)),
                               edge_translations=np.zeros((0, 3)),
                               edge_information=np.zeros((0, 6, 6)))
    assert not planar_data(lone)


def test_city_loops_through_stiff_odometry_converge() -> None:
    """The valencia defect on a small city: a revisiting pose hangs from its (soft) loop
    closure, its (stiff) odometry carries the loop's path.  Relaxed one at a time the two only
    trade the error through the junction pose (15x the optimum after 100 extra frames); as a
    junction group (the default) they are solved together."""
    from hybridpgo.generate import generate_city

    n = 600
    g = generate_city(None, seed=1, num_poses=n, nx=4, ny=4, block_size_m=60.0,
                      p_loop=0.1).graph
    st = make_stream(g)
    opt = prefix_optima(st, [n])[n]
    ratios = {}
    for junctions in (True, False):
        s = OnlineSolver(OnlineConfig(background_refine=False, junctions=junctions))
        for k in range(n):
            feed_frame(s, st, k)
            s.update(None, 40)
        for _ in range(100):
            s.update(None, 40)
        ratios[junctions] = s.energy() / opt
    assert ratios[True] < ONLINE_CITY_RATIO < ratios[False]
    assert OnlineConfig().junctions


def test_gps_poses_hang_from_the_earth() -> None:
    """gps_link: a pose whose frame brings a GPS reading hangs from the earth, so the reading's
    domain is that one node (no GPS frame pays for a path to the start of the map)."""
    g = _graph(seed=2, n=60, gps=8)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    cm = s.store.cap_m
    lengths = np.diff(s.store.ptr[cm: cm + s.num_gps + 1])
    nodes = s.store.gps_node[: s.num_gps] + 1
    assert np.all(lengths == 1) and np.all(s.store.parent[nodes] == 0)
    off = OnlineSolver(OnlineConfig(background_refine=False, gps_link=False))
    _stream(off, g, range(g.num_nodes))
    cm = off.store.cap_m
    assert np.diff(off.store.ptr[cm: cm + off.num_gps + 1]).max() > 1


def _odometry_start(st):  # type: ignore[no-untyped-def]
    s = OnlineSolver(OnlineConfig(background_refine=False))
    for k in range(st.num_frames):
        feed_frame(s, st, k)
    return s.estimate()


def test_first_gps_reading_after_many_poses_moves_the_map() -> None:
    """The earth is the root from the start: the first pose stays put until GPS arrives."""
    g = _graph(seed=2, n=40, gps=0)
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(30), updates=None)
    r0, t0 = s.pose(int(g.node_ids[st.order[0]]))
    assert np.array_equal(r0, np.eye(3)) and np.array_equal(t0, np.zeros(3))
    # GPS readings far away in the earth frame, taken from a shifted and turned copy of the map
    _rot, trans = s.estimate()
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    shift = np.array([500.0, -200.0, 10.0])
    ids = s.pose_ids()
    for p in range(0, 30, 3):
        s.add_gps(int(ids[p]), turn @ trans[p] + shift, 100.0 * np.eye(3))
    e_before = s.energy()
    _stream(s, g, range(30, 40), updates=None)
    for _ in range(200):
        s.update(None, None)
    graph = s.to_graph()
    opt = solve_exact(graph, None, None, GaussNewtonConfig(max_iterations=50)).final_energy
    assert s.energy() < 2.0 * opt < e_before
    # the first pose has moved into the earth frame (to the turned, shifted origin)
    r_first, t_first = s.pose(int(ids[0]))
    assert np.linalg.norm(t_first - shift) < 1.0
    assert np.linalg.norm(r_first - turn) < 0.1


def test_local_batch_is_the_whole_graph_batch_step_without_zero_blocks() -> None:
    """With no node whose constraints are all in the set, batch_relax takes the same segmented
    Woodbury solve: the local batch kernel must give the same poses exactly."""
    from hybridpgo.solvers.hybrid._admission import local_batch
    from hybridpgo.solvers.hybrid.problem import NUM_COUNTS

    g = _graph(seed=3)
    a, b = OnlineSolver(OnlineConfig(background_refine=False, reserve_poses=64)), OnlineSolver(
        OnlineConfig(background_refine=False, reserve_poses=64))
    for s in (a, b):  # no budget: the two states are the same
        _stream(s, g, range(g.num_nodes))
    cs = np.array([3, 9, 17, 21], np.int64)
    sa, sb = a.store, b.store
    pa, xa, _ = sa.views()
    pb, xb, _ = sb.views()
    counts = np.zeros(NUM_COUNTS, np.int64)
    nu = local_batch(pa, xa, cs, 0.7, 1e-6, np.uint64(2**63), sa.model, sa.slot, sa.xb,
                     sa.nodes_buf, counts, sa.depth)
    nu2 = _batch.batch_relax(pb, xb, cs, cs.shape[0], 0.7, 1e-6, sb.slot, sb.xb, sb.nodes_buf)
    assert nu == nu2 > 0
    n = sa.placed + 1
    assert np.array_equal(sa.rot[:n], sb.rot[:n]) and np.array_equal(sa.trans[:n], sb.trans[:n])
    assert np.array_equal(sa.bdiag[:n], sb.bdiag[:n])


def test_local_solve_runs_and_keeps_the_estimate_finite() -> None:
    g = _graph(seed=4)
    s = OnlineSolver(OnlineConfig(background_refine=False, local_size=6))
    st = make_stream(g)
    moved = 0
    for k in range(st.num_frames):
        feed_frame(s, st, k)
        moved += s.update(None, None).local_nodes
    assert moved > 0 and np.isfinite(s.energy())


# --------------------------------------------------------------------------- budget
def _twin_with_rejected(measurement: np.ndarray) -> OnlineSolver:
    """A 40-pose stream with GPS, then one more frame whose loop closure (the given
    translation) is laid and rejected before any update relaxes it."""
    g = _graph(seed=5, gps=8)
    s = OnlineSolver(OnlineConfig(background_refine=False, reserve_poses=64))
    _stream(s, g, range(30))
    ids = s.pose_ids()
    s.add_constraint(int(ids[2]), int(ids[-1]), (np.eye(3), measurement), 4.0 * np.eye(6))
    s._integrate()
    st = s.store
    e = st.m - 1
    assert st.set_rejected(np.array([e]), np.array([1]), (st.m_laid, st.g_laid)) == (2, 0)
    return s


def test_a_rejected_constraint_moves_nothing_and_leaves_the_preconditioner() -> None:
    """``MapStore.set_rejected``: the rejected constraints' whitening is zero, their
    contributions are out of 𝔅(H) (which stays the sum of the others'), they are not queued;
    the updates that follow do not depend on their measurements at all (two solvers that
    differ only in a rejected measurement stay bit-identical); re-admitted, a constraint gets
    its whitening back and is queued."""
    a = _twin_with_rejected(np.array([1.0, 2.0, 0.0]))
    b = _twin_with_rejected(np.array([-40.0, 25.0, 3.0]))
    st = a.store
    e = st.m - 1
    cm = st.cap_m
    assert not st.edge_lt[e].any() and not st.gps_lt[1].any()
    for c in (e, cm + 1):
        assert c not in st.pending()
        assert not st.contrib[st.ptr[c]: st.ptr[c + 1]].any()
    for s in (a, b):
        for _ in range(6):
            s.update(None)
    np.testing.assert_array_equal(a.estimate()[1], b.estimate()[1])
    np.testing.assert_array_equal(a.estimate()[0], b.estimate()[0])
    assert a.store.chi2[e] == 0.0 and a.store.chi2[cm + 1] == 0.0
    # 𝔅(H) is the sum of the contributions of the constraints' path entries
    laid = np.concatenate([np.arange(st.ptr[st.m_laid]),
                           np.arange(st.ptr[cm], st.ptr[cm + st.g_laid])])
    naive = np.zeros_like(st.bdiag[: st.placed + 1])
    np.add.at(naive, st.path_node[laid], st.contrib[laid])
    scale = float(np.abs(naive).max())
    np.testing.assert_allclose(st.bdiag[: st.placed + 1], naive, rtol=0,
                               atol=FLOAT64_IDENTITY * scale)
    assert not st.contrib[st.ptr[e]: st.ptr[e + 1]].any()
    np.testing.assert_array_equal(a.outliers()[0], [e])
    np.testing.assert_array_equal(a.outliers()[1], [1])
    # re-admitted: whitening from the information, queued as new, counted out
    assert st.set_rejected(np.zeros(0, np.int64), np.zeros(0, np.int64),
                           (st.m_laid, st.g_laid)) == (0, 2)
    np.testing.assert_array_equal(st.edge_lt[e], np.linalg.cholesky(st.edge_info[e]).T)
    np.testing.assert_array_equal(st.gps_lt[1], np.linalg.cholesky(st.gps_info[1]).T)
    assert set(st.pending().tolist()) == {e, cm + 1} and st.num_rejected == 0
    a.update(None)
    assert st.contrib[st.ptr[e]: st.ptr[e + 1]].any()


def test_update_stops_early_on_a_backlog() -> None:
    g = _graph(n=120, extra=60)
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    for k in range(st.num_frames):
        feed_frame(s, st, k)
    total = s.backlog
    assert total == g.num_edges
    r = s.update(None, 10)
    assert (r.new, r.backlog, r.old) == (10, total - 10, 0)
    r = s.update(1e-9)  # a budget nothing fits in: the first new constraint only
    assert (r.new, r.backlog) == (1, total - 11)
    assert r.skipped >= 1
    r = s.update(None, None)
    assert r.backlog == 0 and r.new == total - 11 and r.old > 0


def test_poses_hung_from_old_poses_stay_rotations_without_updates() -> None:
    """A pose hung from an old pose gets its local rotation through the inverse of that pose's
    global rotation; any error left in it doubles at every later pose hung through it.  With
    no update to re-orthonormalize anything (``max_updates=0``), M3500_isam's first 500
    frames must keep every local rotation orthonormal to rounding."""
    g = read_graph(bundled_path("M3500_isam.txt"))
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    for k in range(500):
        feed_frame(s, st, k)
        s.update(None, 0)
    assert s.backlog > 0  # nothing was relaxed
    rot = s.store.rot[1: s.store.placed + 1]
    err = np.abs(np.einsum("kji,kjl->kil", rot, rot) - np.eye(3)).max()
    assert err <= FLOAT64_IDENTITY
    _, trans = s.estimate()
    assert np.isfinite(trans).all() and np.abs(trans).max() < 1e3


def test_arrays_grow_without_changing_results() -> None:
    """Capacity doubling (edges, GPS, paths, queue) gives bit-identical results."""
    g = _graph(seed=5, n=50, extra=30, gps=6)
    small = OnlineSolver(OnlineConfig(background_refine=False, reserve_poses=1))
    big = OnlineSolver(OnlineConfig(background_refine=False, reserve_poses=4096))
    for s in (small, big):
        _stream(s, g, range(g.num_nodes))
    assert small.store.cap_n < big.store.cap_n
    ra, ta = small.estimate()
    rb, tb = big.estimate()
    assert np.array_equal(ra, rb) and np.array_equal(ta, tb)
    assert np.array_equal(small.store.chi2[: small.num_edges], big.store.chi2[: big.num_edges])


# --------------------------------------------------------------------------- bad input
def test_rejected_calls_change_nothing() -> None:
    g = _graph(seed=6, gps=3)
    st = make_stream(g)
    ref = OnlineSolver(OnlineConfig(background_refine=False))
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(ref, g, range(20))
    _stream(s, g, range(20))
    before = _state(s)
    ids = s.pose_ids()
    z = (np.eye(3), np.ones(3))
    bad_rot = (np.diag([1.0, 1.0, -1.0]), np.ones(3))
    nan = (np.eye(3), np.array([0.0, np.nan, 0.0]))
    not_spd = np.diag([1.0, 1, 1, 1, 1, -1])
    asym = np.eye(6)
    asym[0, 1] = 0.5
    calls = [
        lambda: s.add_constraint(int(ids[0]), 999_999, z, np.eye(6)),  # unknown pose
        lambda: s.add_constraint(int(ids[1]), int(ids[1]), z, np.eye(6)),  # self loop
        lambda: s.add_constraint(int(ids[0]), int(ids[2]), nan, np.eye(6)),
        lambda: s.add_constraint(int(ids[0]), int(ids[2]), bad_rot, np.eye(6)),
        lambda: s.add_constraint(int(ids[0]), int(ids[2]), z, not_spd),
        lambda: s.add_constraint(int(ids[0]), int(ids[2]), z, asym),
        lambda: s.add_constraint(int(ids[0]), int(ids[2]), z, np.full((6, 6), np.inf)),
        lambda: s.add_constraint(int(ids[0]), int(ids[2]), np.eye(3), np.eye(6)),  # shape
        lambda: s.add_pose(int(ids[3]), int(ids[2]), z, np.eye(6)),  # duplicate id
        lambda: s.add_pose(123_456, 999_999, z, np.eye(6)),  # unknown parent
        lambda: s.add_pose(123_456, None),  # a second map start
        lambda: s.add_pose(123_456, int(ids[2]), z, -np.eye(6)),
        lambda: s.add_pose(1.5, int(ids[2]), z, np.eye(6)),  # type: ignore[arg-type]
        lambda: s.add_gps(999_999, [1.0, 2.0, 3.0], np.eye(3)),
        lambda: s.add_gps(int(ids[4]), [1.0, np.inf, 3.0], np.eye(3)),
        lambda: s.add_gps(int(ids[4]), [1.0, 2.0], np.eye(3)),
        lambda: s.add_gps(int(ids[4]), [1.0, 2.0, 3.0], np.zeros((3, 3))),
    ]
    for call in calls:
        with pytest.raises(GraphError):
            call()
        _same(before, _state(s))
    _stream(ref, g, range(20, st.num_frames))
    _stream(s, g, range(20, st.num_frames))
    _same(_state(ref), _state(s), timing=False)


# --------------------------------------------------------------------------- save / load
def test_save_load_continue_is_bit_identical(tmp_path: Path) -> None:
    g = _graph(seed=7, n=60, extra=30, gps=5)
    st = make_stream(g)
    ref = OnlineSolver(OnlineConfig(background_refine=False, local_size=3, reserve_poses=8))
    s = OnlineSolver(OnlineConfig(background_refine=False, local_size=3, reserve_poses=8))
    _stream(ref, g, range(25))
    _stream(s, g, range(25))
    feed_frame(s, st, 25)  # pending input is saved too
    feed_frame(ref, st, 25)
    path = tmp_path / "state.npz"
    s.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ["state.npz"]  # no temporary left
    t = OnlineSolver.load(path)
    assert t.config == s.config
    t.update(None, UPDATES)
    ref.update(None, UPDATES)
    _stream(t, g, range(26, st.num_frames))
    _stream(ref, g, range(26, st.num_frames))
    ra, ta = ref.estimate()
    rb, tb = t.estimate()
    assert np.array_equal(ra, rb) and np.array_equal(ta, tb)
    assert ref.energy() == t.energy()
    _same(_state(ref), _state(t), timing=False)


def test_save_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, _graph(), range(10))
    path = tmp_path / "state.npz"
    s.save(path)
    good = path.read_bytes()

    def boom(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(FormatError, match="cannot write the file: disk full"):
        s.save(path)
    assert path.read_bytes() == good
    assert [p.name for p in tmp_path.iterdir()] == ["state.npz"]


def test_load_rejects_truncated_and_foreign_files(tmp_path: Path) -> None:
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, _graph(), range(10))
    path = tmp_path / "state.npz"
    s.save(path)
    data = path.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, x=np.arange(3))
    text = tmp_path / "text.npz"
    text.write_text("hello\n")
    for bad in (cut, foreign, text, tmp_path / "missing.npz"):
        with pytest.raises(FormatError, match=rf"{bad.name}"):
            OnlineSolver.load(bad)
    # a state whose sizes disagree is caught too
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["ids"] = arrays["ids"][:-1]
    broken = tmp_path / "broken.npz"
    np.savez(broken, **arrays)
    with pytest.raises(FormatError, match=r"broken\.npz"):
        OnlineSolver.load(broken)
    assert os.path.exists(path)


def test_config_is_checked() -> None:
    for bad in ({"tree": "bfs"}, {"tau_new": 0.0}, {"window": -1}, {"local_size": 65},
                {"reserve_poses": 0}, {"step": "lu"}):
        with pytest.raises(ValueError):
            OnlineConfig(**bad)  # type: ignore[arg-type]


def test_a_frames_odometry_is_given_from_the_earlier_pose() -> None:
    """Stream.odometry_from gives frame k's odometry from the earlier pose to the frame's: as
    the graph stores it, or inverted when stored the other way round (the information carried
    along, so that E is the same either way)."""
    import dataclasses

    from hybridpgo.online.replay import _inverse_edge

    g = _graph(seed=4, n=20, extra=6)
    st = make_stream(g)
    flip = np.zeros(g.num_edges, np.bool_)
    flip[st.odometry[1::2]] = True  # every other frame's odometry stored backwards
    rot, trans, info = (g.edge_rotations.copy(), g.edge_translations.copy(),
                        g.edge_information.copy())
    for c in np.flatnonzero(flip):
        rot[c], trans[c], info[c] = _inverse_edge(rot[c], trans[c], info[c])
    ab = np.where(flip[:, None], g.edge_nodes[:, ::-1], g.edge_nodes).astype(np.int32)
    back = dataclasses.replace(g, edge_nodes=ab, edge_rotations=rot, edge_translations=trans,
                               edge_information=info)
    assert energy(back, g.rotations, g.translations) == pytest.approx(
        energy(g, g.rotations, g.translations), rel=FLOAT64_IDENTITY)
    sb = make_stream(back)
    assert np.array_equal(sb.order, st.order) and np.array_equal(sb.odometry, st.odometry)
    for k in range(1, st.num_frames):
        c = int(st.odometry[k])
        a, zr, zt, om = sb.odometry_from(k)
        assert a == g.edge_nodes[c, 0] and g.edge_nodes[c, 1] == st.order[k]
        assert np.allclose(zr, g.edge_rotations[c], atol=FLOAT64_IDENTITY, rtol=0)
        assert np.allclose(zt, g.edge_translations[c], atol=FLOAT64_IDENTITY, rtol=0)
        om0 = g.edge_information[c]
        assert np.allclose(om, om0, rtol=0, atol=FLOAT64_IDENTITY * np.abs(om0).max())
        assert st.odometry_from(k)[0] == a


def test_pending_poses_have_an_estimate() -> None:
    g = _graph(seed=8)
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    for k in range(5):
        feed_frame(s, st, k)
    _rot, trans = s.estimate()  # nothing placed yet: the odometry chain from the identity
    c = int(st.odometry[1])
    assert np.allclose(trans[1], g.edge_translations[c], atol=FLOAT64_IDENTITY, rtol=0)
    _r4, t4 = s.pose(int(g.node_ids[st.order[4]]))
    assert np.array_equal(t4, trans[4])


# --------------------------------------------------------------------------- iSAM2
def test_isam2_replay_reaches_the_optimum() -> None:
    pytest.importorskip("gtsam")
    from hybridpgo.online.replay import replay_isam2

    g, _, _ = random_graph(np.random.default_rng(9), n=30, extra=15, noise=0.2)
    st = make_stream(g)
    opt = prefix_optima(st, [15, 30])
    r = replay_isam2(st, checkpoints=[15, 30], extra_frames=3)
    assert r.latency_s.shape == (30,)
    assert r.checkpoints[15] == pytest.approx(opt[15], rel=ISAM2_VS_OPTIMUM)
    assert r.checkpoints[30] > r.extra_energy[-1]  # one GN step per update: not there yet
    assert r.extra_energy[-1] == pytest.approx(opt[30], rel=ISAM2_VS_OPTIMUM)


# --------------------------------------------------------------------------- CLI
def test_cli_replay_json(capsys: pytest.CaptureFixture[str], data_dir: Path) -> None:
    import json

    from hybridpgo.cli import main

    rc = main(["replay", str(data_dir / "tinyGrid3D.g2o"), "--budget-ms", "5", "--every", "4",
               "--extra-frames", "3", "--json", "--quiet"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    r = out["solvers"]["hybridpgo+background"]  # the worker runs by default
    assert out["frames"] == r["frames"] == 9
    assert r["info"]["background"]["error"] is None
    assert set(out["optima"]) == {"4", "8", "9"}
    assert len(r["extra_ratio"]) == 3 and r["latency_ms_max"] >= r["latency_ms_mean"] > 0


def test_worst_frames_say_what_the_machine_took(data_dir: Path, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Each worst frame carries the thread's wait for a CPU and the host's steal during it:
    read from the scheduler's files (here stand-ins with known numbers), None where there are
    none; the command line says them."""
    import os

    from hybridpgo.cli.replay import _machine
    from hybridpgo.online import replay as rp

    sched, stat = tmp_path / "schedstat", tmp_path / "stat"
    sched.write_text("7433221 2500000000 4\n")  # run time, run delay (ns), time slices
    stat.write_text("cpu  1 2 3 4 5 6 7 42 0 0\ncpu0 1 2 3 4 5 6 7 21 0 0\n")
    monkeypatch.setattr(rp._MachineClock, "PATHS", (str(sched), str(stat)))
    tick = 1.0 / os.sysconf("SC_CLK_TCK")
    clock = rp._MachineClock()
    assert clock.read()[:2] == (2.5, 42 * tick)  # the delay's field and unit, steal's field
    sched.write_text("7433221 2600000000 4\n")
    stat.write_text("cpu  1 2 3 4 5 6 7 45 0 0\n")
    waited, stolen = clock.read()[:2]
    assert waited == pytest.approx(2.6) and stolen == 45 * tick  # read again, not cached
    stat.write_text("intr 1 2 3\n")  # not the CPU line: steal unknown, the delay still read
    assert np.isnan(clock.read()[1]) and clock.read()[0] == pytest.approx(2.6)
    clock.close()
    stream = rp.make_stream(read_graph(data_dir / "tinyGrid3D.g2o"))
    worst = rp.replay_online(stream, OnlineConfig(background_refine=False),
                             5e-3).info["worst_frames"]
    assert worst and all(w["waited_ms"] == 0.0 for w in worst)  # the stand-ins did not move
    monkeypatch.setattr(rp._MachineClock, "PATHS", ("/nonexistent/a", "/nonexistent/b"))
    worst = rp.replay_online(stream, OnlineConfig(background_refine=False),
                             5e-3).info["worst_frames"]
    assert all(w["waited_ms"] is None and w["stolen_ms"] is None for w in worst)
    assert _machine(worst[0]) == ""
    assert _machine({"wall_ms": 4.0, "waited_ms": 1.234, "stolen_ms": 10.0}) == (
        "; 4.00 ms wall, of it 1.23 ms waiting for a CPU, the host took 10 ms of CPU (both "
        "CPUs, 10 ms ticks)")
    assert _machine({"wall_ms": 4.0, "waited_ms": 0.001, "stolen_ms": 0.0}) == ""
    assert _machine({"wall_ms": 4.0, "collected_ms": 2.5, "faults": 1234}) == (
        "; 2.50 ms of garbage collection, 1234 page faults")
    assert _machine({"wall_ms": 4.0, "collected_ms": 0.0, "faults": 99}) == ""


def test_the_machine_clock_counts_collections_and_page_faults() -> None:
    """The clock's collection time grows by a collection between two reads and not
    otherwise; page faults grow when the thread writes fresh memory (Linux); closing the
    clock removes its collection callback."""
    import gc

    from hybridpgo.online import replay as rp

    callbacks = len(gc.callbacks)
    clock = rp._MachineClock()
    assert len(gc.callbacks) == callbacks + 1
    was = gc.isenabled()
    gc.disable()  # no automatic collection between the two reads
    try:
        a = clock.read()
        b = clock.read()
    finally:
        (gc.enable if was else gc.disable)()
    assert b[2] == a[2]  # no collection in between
    gc.collect()
    c = clock.read()
    assert c[2] > b[2]
    if hasattr(rp.resource, "RUSAGE_THREAD"):
        import mmap

        fresh = mmap.mmap(-1, 1 << 24)  # 16 MiB never written, in small pages
        if hasattr(mmap, "MADV_NOHUGEPAGE"):
            fresh.madvise(mmap.MADV_NOHUGEPAGE)
        np.frombuffer(fresh, np.uint8)[::4096] = 1  # one write per page: 4096 faults
        d = clock.read()
        assert d[3] - c[3] >= 1000
        fresh.close()
    clock.close()
    assert len(gc.callbacks) == callbacks


def test_cli_replay_robust_option(capsys: pytest.CaptureFixture[str], data_dir: Path,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """``replay --robust`` takes what ``optimize --robust`` takes and reaches the solver's
    configuration (default ``auto``)."""
    import json

    import hybridpgo.online as online
    from hybridpgo.cli import main

    made: list[OnlineConfig] = []

    def config(**kw: Any) -> OnlineConfig:
        made.append(OnlineConfig(**kw))
        return made[-1]

    monkeypatch.setattr(online, "OnlineConfig", config)
    path = str(data_dir / "tinyGrid3D.g2o")
    for spec, want in (([], ("auto", None)), (["--robust", "none"], ("none", None)),
                       (["--robust", "cauchy:2"], ("cauchy", 2.0))):
        assert main(["replay", path, *spec, "--no-background-refine", "--every", "3",
                     "--extra-frames", "0", "--json", "--quiet"]) == 0
        out = json.loads(capsys.readouterr().out)
        r = out["solvers"]["hybridpgo"]
        assert r["info"]["rejected"] == 0 and set(out["optima"]) == {"3", "6", "9"}
        assert (made[-1].robust, made[-1].robust_scale) == want
    assert main(["replay", path, "--robust", "bogus"]) == 2
    assert "--robust" in capsys.readouterr().err
    assert main(["replay", path, "--robust", "auto:2"]) == 2


def test_cli_replay_errors(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                           data_dir: Path) -> None:
    from hybridpgo.cli import main

    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n")
    assert main(["replay", str(bad)]) == 2
    assert "bad.g2o" in capsys.readouterr().err
    missing = tmp_path / "no" / "plots"
    assert main(["replay", str(data_dir / "tinyGrid3D.g2o"), "--plot", str(missing)]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["replay", str(data_dir / "tinyGrid3D.g2o"), "--budget-ms", "0"]) == 2


def test_isam2_replay_time_cap() -> None:
    pytest.importorskip("gtsam")
    from hybridpgo.online.replay import replay_isam2

    st = make_stream(_graph(seed=10, n=20, extra=5))
    r = replay_isam2(st, checkpoints=[10, 20], extra_frames=3, max_seconds=0.0)
    assert r.latency_s.shape == (1,) and r.info["frames_reached"] == 1
    assert "stopped at frame 1" in r.name and r.extra_energy == []
    assert set(r.checkpoints) == {1}


# --------------------------------------------------------------------------- background refine
def _bg(**kw: object) -> OnlineConfig:
    return OnlineConfig(background_refine=True, background_join=4, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("gps", [0, 6])
def test_background_refine_reaches_the_batch_optimum(gps: int) -> None:
    """After the stream, join_refine() adopts the worker's optimum of the whole map, and the
    frames that follow keep it (no constraint is left outside the optimum, so no spare-time
    update perturbs it; the joins re-adopt the same optimum)."""
    g = _graph(seed=11, n=50, extra=30, gps=gps)
    st = make_stream(g)
    opt = prefix_optima(st, [st.num_frames])[st.num_frames]
    with OnlineSolver(_bg()) as s:
        _stream(s, g, range(g.num_nodes))
        assert s.stats()["background"]["results_adopted"] > 0  # adopted along the way
        assert s.join_refine(timeout=120.0)
        e = s.energy()
        assert abs(e - opt) <= ONLINE_REFINED * opt
        for _ in range(10):
            s.update(None, UPDATES)
        assert abs(s.energy() - e) <= REFINE_REPEATED * e
        bgi = s.stats()["background"]
        assert bgi["error"] is None
        # the worker's own word on its solver, passed on with each adopted answer
        assert bgi["worker_resets"] == 0 and bgi["worker_with_lm"] is False
        assert bgi["worker_fallback"] == ""


def test_a_frame_adopts_the_answer_to_its_own_data_when_it_comes_in_time() -> None:
    """Asynchronously, a frame with a budget waits for the worker's answer to its own data
    (once a round trip has been measured and it fits) and adopts it: the map is then the
    worker's optimum of everything added, with nothing requeued and no request outstanding
    (the next frame's data comes with the next request)."""
    g = _graph(seed=14, n=40, extra=20)
    st = make_stream(g)
    with OnlineSolver(OnlineConfig()) as s:
        assert s.wait_background_ready(120.0)
        link = s._link
        assert link is not None
        settled = 0
        for k in range(st.num_frames):
            feed_frame(s, st, k)
            s.update(2.0)  # a generous budget: the answer of a tiny map comes in it
            if not np.isfinite(link.answer_s) and link.join_req >= 0:
                # no round trip measured yet (a frame does not wait then): the next frame
                # takes this answer and measures it, however busy the machine is
                assert link.refiner.wait_answered(link.join_req, 120.0)
            if link.settled > settled:
                settled = link.settled
                store = s.store
                assert link.refined == (store.m_laid, store.g_laid)
                assert store.requeue.size == 0 and link.join_req == -1
                assert link.holds(store)
        assert settled >= st.num_frames // 2
        assert s.stats()["background"]["results_settled"] == settled


def test_a_frame_waits_only_for_an_answer_expected_before_its_deadline() -> None:
    """``WorkerLink.settle`` waits only when the outstanding request's answer is expected
    (its request time plus the median round trip) early enough to be adopted before the
    frame's deadline; never before a round trip was measured, nor for a request that brought
    no new data; and at most until the deadline less the adoption's margin."""
    import time

    from hybridpgo.online import _link

    class Refiner:  # never answers; records the waits
        def __init__(self) -> None:
            self.waits: list[float] = []

        def answered(self, req: int) -> bool:
            return False

        def wait_answered(self, req: int, timeout: float) -> bool:
            self.waits.append(timeout)
            return False

    link = _link.WorkerLink.__new__(_link.WorkerLink)  # the bookkeeping only
    link.refiner = ref = Refiner()
    link.adopt_s = 1e-3
    store = OnlineSolver(OnlineConfig(background_refine=False)).store
    now = time.perf_counter()

    def settle(answer_s: float, new: bool, deadline: float) -> bool:
        link.join_req, link._req_at, link._req_new, link.answer_s = 0, now, new, answer_s
        return link.settle(store, 0, True, deadline)

    assert not settle(np.nan, True, now + 10.0) and ref.waits == []  # nothing measured
    assert not settle(1e-3, False, now + 10.0) and ref.waits == []  # no new data: a polish
    assert not settle(5.0, True, now + 1.0) and ref.waits == []  # expected too late
    assert not settle(1e-3, True, now + 10.0)  # expected in time: waited, until the margin
    assert len(ref.waits) == 1
    margin = _link.ADOPT_MARGIN * 1e-3 + _link.WAKE_S
    assert 10.0 - margin - 1.0 < ref.waits[0] <= 10.0 - margin
    assert link.join_req == 0  # the request is still outstanding


def test_new_data_supersedes_a_polish_request() -> None:
    """Asynchronously, a frame that ships new data while the worker polishes an unchanged
    map (the outstanding request brought no data) asks again at once: the new request,
    answered instead of the polish, covers the new data.  A request that brought data is
    waited for as before."""
    from hybridpgo.online import _link

    class Refiner:  # never answers
        def answered(self, req: int) -> bool:
            return False

        def take(self) -> None:
            return None

    link = _link.WorkerLink.__new__(_link.WorkerLink)  # the bookkeeping only
    link.refiner = Refiner()
    asked: list[int] = []
    link.ship = lambda store, frame: True  # type: ignore[method-assign]
    link.request = lambda store, frame, thorough=False: asked.append(frame)  # type: ignore
    store = OnlineSolver(OnlineConfig(background_refine=False)).store
    link.join_req, link._req_new = 3, False  # a polish is running
    link.step(store, 7, 0, True)
    assert asked == [7]
    link._req_new = True  # the outstanding request brought data: wait for it
    link.step(store, 8, 0, True)
    assert asked == [7]
    link.ship = lambda store, frame: False  # type: ignore[method-assign]
    link._req_new = False  # nothing new to ship: the polish goes on
    link.step(store, 9, 0, True)
    assert asked == [7]


def test_a_frame_adopts_an_answer_that_comes_while_it_waits() -> None:
    """Asynchronously, an answer that arrives while the frames wait for the outstanding
    request (the worker's second answer to the request before, after its outlier test
    re-solved the map) is adopted at the next frame, without a new request; the outstanding
    one stays outstanding until it is answered, and then the next frame asks again."""
    from types import SimpleNamespace

    from hybridpgo.online import _link

    ready: list[Any] = []
    state = {"answered": 4}

    class Refiner:
        def answered(self, req: int) -> bool:
            return state["answered"] >= req

        def take(self) -> Any:
            return ready.pop() if ready else None

    link = _link.WorkerLink.__new__(_link.WorkerLink)  # the bookkeeping only
    link.refiner = Refiner()
    asked: list[int] = []
    adopted: list[int] = []
    link.ship = lambda store, frame: True  # type: ignore[method-assign]
    link.request = lambda store, frame, thorough=False, defer=True: (  # type: ignore
        asked.append(frame), setattr(link, "join_req", 6))
    link.fresh = lambda store, res: True  # type: ignore[method-assign]
    link.adopt = lambda store, res, frame, rebase: adopted.append(res.req)  # type: ignore
    store = OnlineSolver(OnlineConfig(background_refine=False)).store
    link.join_req, link._req_new = 5, True  # request 5, with data, outstanding
    ready.append(SimpleNamespace(req=4, status="screened"))  # request 4's second answer
    link.step(store, 10, 0, True)
    assert adopted == [4] and asked == [] and link.join_req == 5
    link.step(store, 11, 0, True)  # nothing came: wait
    assert adopted == [4] and asked == []
    state["answered"] = 5
    ready.append(SimpleNamespace(req=5, status="converged", received=0.0))
    link._req_at, link._trips, link._ntrips = 0.0, np.full(4, np.nan), 0
    link.step(store, 12, 0, True)  # answered: adopted, and the frame asks again
    assert adopted == [4, 5] and asked == [12] and link.join_req == 6


def test_background_join_is_reproducible() -> None:
    g = _graph(seed=12, n=40, extra=25, gps=3)
    out = []
    for _ in range(2):
        with OnlineSolver(_bg()) as s:
            _stream(s, g, range(g.num_nodes))
            out.append(s.estimate())
    assert np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1])


def _random_locals(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n random local transforms (rotations, translations): a made-up worker result."""
    rng = np.random.default_rng(seed)
    lrot = np.empty((n, 3, 3))
    for i in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        lrot[i] = q * np.sign(np.linalg.det(q))
    return lrot, rng.normal(size=(n, 3))


def test_adoption_keeps_newer_poses_relative_to_their_parents() -> None:
    """Naive check of _adopt: the result's poses take its local transforms; every pose added
    after its snapshot keeps its pose relative to its tree parent."""
    from hybridpgo.online.worker import Refined

    g = _graph(seed=13, n=40, extra=20)
    s = OnlineSolver(OnlineConfig(background_refine=False, background_rebase=False))
    _stream(s, g, range(g.num_nodes))
    rot0, trans0 = s.estimate()
    parent = s.store.parent[1: s.store.n + 1] - 1  # pose index of each tree parent (-1: earth)
    n = 25
    lrot, ltrans = _random_locals(n, seed=0)
    assert adopt_result(s.store, Refined(n, 30, 0, 0, lrot, ltrans, 0.0, 1, "converged", 0.0),
                        rebase=False)
    rot1, trans1 = s.estimate()
    for p in range(s.store.n):
        a = int(parent[p])
        if p < n:  # naive composition of the adopted local transforms
            pr, pt = (np.eye(3), np.zeros(3)) if a < 0 else (rot1[a], trans1[a])
            assert np.allclose(rot1[p], pr @ lrot[p], atol=FLOAT64_IDENTITY)
            assert np.allclose(trans1[p], pr @ ltrans[p] + pt, atol=FLOAT64_IDENTITY)
        else:  # the same pose relative to the parent as before
            assert a >= 0
            before = (rot0[a].T @ rot0[p], rot0[a].T @ (trans0[p] - trans0[a]))
            after = (rot1[a].T @ rot1[p], rot1[a].T @ (trans1[p] - trans1[a]))
            assert np.allclose(before[0], after[0], atol=FLOAT64_IDENTITY)
            assert np.allclose(before[1], after[1], atol=FLOAT64_IDENTITY * 100)


def test_adoption_with_rebase_queues_the_tail_once() -> None:
    from hybridpgo.online.worker import Refined

    g = _graph(seed=14, n=30, extra=10)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    rot, trans = s.store.rot[1:11].copy(), s.store.trans[1:11].copy()
    s.store.push(s.store.m - 1)  # a queued constraint that is also in the tail
    adopt_result(s.store, Refined(10, 12, 0, 0, rot, trans, 0.0, 1, "converged", 0.0), True)
    # relaxed before: requeued; still waiting for its first update: stays a new one
    assert s.store.requeue.tolist() == list(range(12, s.store.m_laid - 1))
    assert s.store.pending().tolist() == [s.store.m - 1]


def test_a_requeued_constraint_is_started_only_when_it_fits() -> None:
    """After an adopted answer the constraints laid since are relaxed again (requeued), but
    none is started whatever its cost, as the first new constraint of a frame is: in a frame
    whose budget is spent nothing of them starts, and none is lost; one that does not fit a
    whole frame is dropped (spare time revisits it), at most ``MAX_DROPS`` per frame; with no
    limit every one is relaxed in arrival order."""
    from hybridpgo.online.solver import MAX_DROPS
    from hybridpgo.online.worker import Refined

    g = _graph(seed=14, n=30, extra=10)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    st = s.store
    rot, trans = st.rot[1:11].copy(), st.trans[1:11].copy()
    adopt_result(st, Refined(10, 12, 0, 0, rot, trans, 0.0, 1, "converged", 0.0), True)
    tail = st.requeue.copy()
    assert tail.size > MAX_DROPS + 1 and s.backlog == 0
    s._input_cycles = 1 << 62  # this frame's add_* calls used its budget
    before = s.estimate()
    r = s.update(5e-3)
    assert r.old == 0 and np.array_equal(st.requeue, tail)  # not started, not dropped
    for a, b in zip(before, s.estimate(), strict=True):
        np.testing.assert_array_equal(a, b)
    model = st.model.copy()
    st.model[:] = 1e12  # every update predicted longer than a whole frame
    r = s.update(5e-3)
    assert r.old == 0 and np.array_equal(st.requeue, tail[MAX_DROPS:])
    st.model[:] = model
    r = s.update(None)
    assert st.requeue.size == 0 and r.old >= tail.size - MAX_DROPS


def test_background_rejected_calls_change_nothing() -> None:
    g = _graph(seed=15, gps=3)
    with OnlineSolver(_bg()) as s:
        _stream(s, g, range(20))
        before = _state(s)
        ids = s.pose_ids()
        with pytest.raises(GraphError):
            s.add_constraint(int(ids[0]), 999_999, (np.eye(3), np.ones(3)), np.eye(6))
        with pytest.raises(GraphError):
            s.add_gps(int(ids[4]), [1.0, np.inf, 3.0], np.eye(3))
        with pytest.raises(GraphError):
            s.add_pose(int(ids[3]), int(ids[2]), (np.eye(3), np.ones(3)), np.eye(6))
        _same(before, _state(s))


def _running(pid: int) -> bool:
    """True while process ``pid`` exists (and has not been reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_background_worker_stops_cleanly() -> None:
    import gc

    g = _graph(seed=16, n=20, extra=5)
    with OnlineSolver(_bg()) as s:
        _stream(s, g, range(g.num_nodes))
        pid = s.worker_pid
        assert pid is not None and _running(pid)
    assert s.worker_pid is None and not _running(pid)
    s.close()  # idempotent
    with pytest.raises(ValueError):
        s.join_refine()
    s.update(None, UPDATES)  # still usable, without the worker
    # dropped without close(): the finalizer stops the worker
    t = OnlineSolver(_bg())
    pid = t.worker_pid
    assert pid is not None and _running(pid)
    del t
    gc.collect()
    assert not _running(pid)


def test_background_state_survives_save_load(tmp_path: Path) -> None:
    g = _graph(seed=17, n=40, extra=20, gps=4)
    st = make_stream(g)
    opt = prefix_optima(st, [st.num_frames])[st.num_frames]
    path = tmp_path / "bg.npz"
    with OnlineSolver(_bg()) as s:
        _stream(s, g, range(25))
        s.save(path)
    with OnlineSolver.load(path) as t:  # a new worker gets the whole map
        assert t.config.background_refine
        _stream(t, g, range(25, st.num_frames))
        assert t.join_refine(timeout=120.0)
        assert abs(t.energy() - opt) <= ONLINE_REFINED * opt


@pytest.mark.parametrize("hold", [True, False])
def test_background_hold_keeps_an_optimum_that_covers_everything(hold: bool) -> None:
    """OnlineConfig.background_hold: once the adopted optimum covers every constraint, frames
    make no spare-time update (the estimate stays bit-identical); without it they do."""
    g = _graph(seed=18, n=40, extra=20, gps=3)
    with OnlineSolver(OnlineConfig(background_refine=True, background_join=1000,
                                   background_hold=hold)) as s:
        _stream(s, g, range(g.num_nodes))
        assert s.join_refine(timeout=120.0)
        rot, trans = s.estimate()
        rep = s.update(None, UPDATES)
        rot1, trans1 = s.estimate()
        same = np.array_equal(rot, rot1) and np.array_equal(trans, trans1)
        assert (rep.old == 0 and same) if hold else (rep.old > 0 and not same)
        s.add_constraint(int(s.pose_ids()[0]), int(s.pose_ids()[-1]),
                         s.pose(int(s.pose_ids()[-1])), np.eye(6))
        rep = s.update(None, UPDATES)  # a constraint outside the optimum: spare time again
        assert rep.new == 1 and rep.old > 0


def test_spare_time_waits_for_the_answer_that_holds_a_long_loop(monkeypatch) -> None:
    """``WorkerLink.awaits_loop``: while a loop closure of at least ``LONG_LOOP`` path nodes,
    laid after the adopted answer's snapshot and not rejected, waits for an answer that holds
    it (at most ``LONG_LOOP_WAIT`` frames from the first call that found the newest such
    closure waiting, and while the worker is alive and its newest message was no error), the
    frames make no spare-time update; a newer long closure starts its own wait; shorter
    closures, covered or rejected ones, closures of a restored map, a dead worker, a worker
    whose newest message was an error (the closure's wait runs on meanwhile), or the
    synchronous mode leave spare time as it is."""
    import dataclasses

    from hybridpgo.online import _link
    from hybridpgo.online._frame import NO_DEADLINE
    from hybridpgo.solvers.hybrid.problem import NUM_COUNTS

    class Refiner:
        alive = True
        failing = False

    g = _graph(seed=21, n=40, extra=20)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    st = s.store
    laid = st.m_laid
    lens = st.ptr[1: laid + 1] - st.ptr[:laid]
    two = np.sort(np.argsort(-lens, kind="stable")[:2])  # the two longest paths, in order
    first, second = int(two[0]), int(two[1])
    assert lens[first] >= 4 and lens[second] >= 4  # loop closures
    monkeypatch.setattr(_link, "LONG_LOOP", int(min(lens[first], lens[second])))
    link = _link.WorkerLink.__new__(_link.WorkerLink)  # the bookkeeping only
    link.refiner = Refiner()
    link.tail_ok = False  # the adopted optimum does not hold what came after it
    link._loop_edge, link._loop_since, link.loop_floor = -1, (0, 0.0), 0
    link.refined = (first, 0)  # both closures came after the answer's snapshot
    wait = _link.LONG_LOOP_WAIT
    assert all(link.awaits_loop(st, f) for f in range(5, 5 + wait))
    assert not link.awaits_loop(st, 5 + wait)  # waited long enough: spare time goes on
    link.refined = (first + 1, 0)  # an answer holding the first: the second still waited long
    assert not link.awaits_loop(st, 6 + wait)
    st.rejected[second] = True  # the second rejected: nothing waits
    st.num_rejected += 1
    assert not link.awaits_loop(st, 7 + wait)
    link.refined = (first, 0)
    assert link.awaits_loop(st, 8 + wait)  # the first, newest now: its own wait begins
    st.rejected[second] = False  # the second again: a newer closure, a wait of its own
    st.num_rejected -= 1
    assert all(link.awaits_loop(st, f) for f in range(wait + 9, 2 * wait + 9))
    assert not link.awaits_loop(st, 2 * wait + 9)
    link.refined = (laid, 0)  # an answer that holds everything
    assert not link.awaits_loop(st, 2 * wait + 10)
    link.refined = (first, 0)
    link.loop_floor = laid  # a restored map's closures wait for no answer
    assert not link.awaits_loop(st, 2 * wait + 11)
    link.loop_floor = 0
    link.refiner.failing = True  # the worker's newest message was an error
    assert not link.awaits_loop(st, 2 * wait + 12)
    link.refiner.failing = False  # a result came after it: the hold acts again
    assert link.awaits_loop(st, 2 * wait + 12)
    link.refiner.failing = True  # an error while that closure waits: its wait runs on
    assert not link.awaits_loop(st, 2 * wait + 13)
    link.refiner.failing = False
    assert link.awaits_loop(st, 3 * wait + 11)  # the wait's last frame
    assert not link.awaits_loop(st, 3 * wait + 12)  # waited long enough, the error included
    link.refiner.alive = False
    assert not link.awaits_loop(st, 2 * wait + 13)
    link.refiner.alive = True
    monkeypatch.setattr(_link, "LONG_LOOP", int(lens.max()) + 1)
    assert not link.awaits_loop(st, 2 * wait + 14)  # no closure that long
    # the frames' spare time: none while a long closure waits, as usual without it and in
    # the synchronous mode
    monkeypatch.setattr(_link, "LONG_LOOP", int(min(lens[first], lens[second])))
    s._link = link
    try:
        counts = np.zeros(NUM_COUNTS, np.int64)
        assert s._spare_time(NO_DEADLINE, counts, 1 << 62, 99) == 0
        s.config = dataclasses.replace(s.config, background_join=10)
        assert s._spare_time(NO_DEADLINE, counts, 1 << 62, 100) > 0
        s.config = dataclasses.replace(s.config, background_join=0)
        monkeypatch.setattr(_link, "LONG_LOOP", int(lens.max()) + 1)
        assert s._spare_time(NO_DEADLINE, counts, 1 << 62, 101) > 0
    finally:
        s._link = None
        s.close()


def test_a_frame_that_adds_nothing_waits_for_the_answer_that_holds_everything(
        monkeypatch) -> None:
    """``WorkerLink.awaits_all``: while the outstanding request holds everything placed and
    laid (at most ``LONG_LOOP_WAIT`` frames and ``LONG_LOOP_WAIT_S`` seconds from the first
    frame that found the map as it stands awaited, requests made again meanwhile included,
    and while the worker is alive and its newest message was no error; here every request is
    answered at once with nothing to adopt, and asked again), a frame that adds
    nothing (the robot stands, or the stream ended) makes no spare-time update: the single
    steps would only move the map away from the optimum the answer brings.  The frame that
    ships new data, a frame that adds a constraint, no request outstanding, a request that
    does not hold everything, a long wait, a dead or failing worker, or the synchronous mode
    leave spare time as it is."""
    import dataclasses

    from hybridpgo.online import _link

    class Refiner:  # answers every request at once, with nothing to adopt
        alive = True
        failing = False
        error = ""
        results = 0

        def __init__(self, *args: object) -> None:
            self.req = -1

        def ship(self, meta: object, arrays: object) -> None:
            pass

        def request(self, thorough: bool = False, defer: bool = True) -> int:
            self.req += 1
            return self.req

        def answered(self, req: int) -> bool:
            return True

        def take(self) -> None:
            return None

        def wait(self, req: int, timeout: float | None = None) -> None:
            return None

        def close(self) -> None:
            pass

    monkeypatch.setattr(_link, "BackgroundRefiner", Refiner)
    monkeypatch.setattr(_link, "LONG_LOOP_WAIT", 4)
    monkeypatch.setattr(_link, "LONG_LOOP_WAIT_S", 1e9)  # frames bound the wait here
    g = _graph(seed=21, n=40, extra=20)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    st = s.store
    link = _link.WorkerLink(20)
    s._link = link
    try:
        # the frame that ships everything: spare time as usual
        assert s.update(None, UPDATES).old > 0
        # frames that add nothing, each asking again: held for LONG_LOOP_WAIT frames
        assert [s.update(None, UPDATES).old for _ in range(4)] == [0] * 4
        assert link.awaits_all(st, s.frame - 1)
        assert s.update(None, UPDATES).old > 0  # waited long enough: spare time goes on
        s.add_constraint(int(s.pose_ids()[0]), int(s.pose_ids()[-1]),
                         s.pose(int(s.pose_ids()[-1])), np.eye(6))
        rep = s.update(None, UPDATES)  # a frame that adds a constraint
        assert rep.new == 1 and rep.old > 0
        assert s.update(None, UPDATES).old == 0  # the map as it stands now: a wait of its own
        assert link.awaits_all(st, s.frame)  # still waiting, but not in the synchronous mode
        s.config = dataclasses.replace(s.config, background_join=10)
        assert s.update(None, UPDATES).old > 0
        s.config = dataclasses.replace(s.config, background_join=0)
        assert s.update(None, UPDATES).old == 0
        # the conditions, one at a time
        frame = s.frame
        assert link.awaits_all(st, frame)
        link.refiner.failing = True
        assert not link.awaits_all(st, frame)
        link.refiner.failing = False
        link.refiner.alive = False
        assert not link.awaits_all(st, frame)
        link.refiner.alive = True
        sent = link._req_sent
        link._req_sent = (sent[0], sent[1] - 1, sent[2])
        assert not link.awaits_all(st, frame)  # the request misses a constraint
        link._req_sent = sent
        req, link.join_req = link.join_req, -1
        assert not link.awaits_all(st, frame)  # answered: nothing is awaited
        link.join_req = req
        assert link.awaits_all(st, frame)
        assert not link.awaits_all(st, frame + 3)  # LONG_LOOP_WAIT frames since it began
        monkeypatch.setattr(_link, "LONG_LOOP_WAIT_S", 0.0)
        assert not link.awaits_all(st, frame)  # likewise in seconds
    finally:
        s._link = None
        s.close()


def test_background_hold_keeps_an_optimum_extended_by_new_tree_links() -> None:
    """background_hold also holds while every constraint since the adopted result is the tree
    link of a new pose and the only constraint through it (odometry driving on): that map's
    optimum is the adopted one with the new poses composed on, which the frames keep; a loop
    closure among the new constraints ends the hold (it needs spare time again)."""
    g = _graph(seed=19, n=60, extra=20)
    st = make_stream(g)
    sizes = np.diff(st.edge_ptr)  # edges each frame brings (its odometry first)
    odometry_only = [k for k in range(31, st.num_frames) if sizes[k] == 1]
    assert len(odometry_only) >= 4
    first = odometry_only[0]
    with OnlineSolver(OnlineConfig(background_refine=True, background_join=1000)) as s:
        _stream(s, g, range(first))
        assert s.join_refine(timeout=120.0)
        e0 = s.energy()
        feed_frame(s, st, first)  # a new pose with its odometry only
        rep = s.update(None, UPDATES)
        assert rep.new == 1 and rep.old == 0  # held: no spare-time update
        e1 = s.energy()
        assert abs(e1 - e0) <= ONLINE_REFINED * max(e0, 1.0)  # the new pose is exact
        loop = next(k for k in range(first + 1, st.num_frames) if sizes[k] > 1)
        for k in range(first + 1, loop + 1):
            feed_frame(s, st, k)
            rep = s.update(None, UPDATES)
        assert rep.old > 0  # the loop closure: spare time again


def test_background_worker_waits_ready_and_runs_one_thread() -> None:
    """wait_background_ready() returns once the worker has loaded its kernels (False without a
    worker); the worker runs with one BLAS / OpenMP / Numba thread (a second BLAS thread
    fighting the frames for the other core made its solves 4-10x slower)."""
    from hybridpgo.online import worker

    assert OnlineSolver(OnlineConfig(background_refine=False)).wait_background_ready(1.0) is False
    assert OnlineConfig().background_refine  # on by default
    with OnlineSolver() as s:
        assert s.worker_pid is not None and s.wait_background_ready(120.0)
        environ = Path(f"/proc/{s.worker_pid}/environ")
        if environ.exists():  # Linux
            env = dict(v.split("=", 1) for v in environ.read_text().split("\0") if "=" in v)
            for key, value in worker.WORKER_THREADS.items():
                assert env.get(key) == value, key


def _worker_map(s: OnlineSolver, robust: tuple[str, float | None]) -> Any:
    """A worker's map (:class:`hybridpgo.online.worker._Map`) holding all of ``s``'s map;
    no request counts as slow (the LM measurement after a slow one depends on the clock), nor
    stops after its first cycles (likewise)."""
    from hybridpgo.online import worker

    mp = worker._Map(robust)
    mp.slow_s = mp.more_cycles_s = np.inf
    _ship(mp, s)
    return mp


def _w100_worker_map(data_dir: Path) -> tuple[Any, float]:
    """A worker's least-squares map holding the whole of w100_toro, streamed frame by frame,
    and the graph's optimum."""
    from hybridpgo.io import read_graph

    g = read_graph(data_dir / "w100_toro.graph")
    st = make_stream(g)
    opt = prefix_optima(st, [st.num_frames])[st.num_frames]
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    return _worker_map(s, ("none", None)), opt


def _ship(mp: Any, s: OnlineSolver) -> None:
    """Ship to the worker's map ``mp`` what ``s`` placed and laid since the last call."""
    st = s.store
    n0, m0, g0 = mp.n, mp.m, mp.g
    t, m, g = st.placed + 1, st.m_laid, st.g_laid
    mp.add({"parent": st.parent[n0 + 1:t], "rot": st.rot[n0 + 1:t], "trans": st.trans[n0 + 1:t],
            "edge_ab": st.edge_ab[m0:m], "edge_rot": st.edge_rot[m0:m],
            "edge_trans": st.edge_trans[m0:m], "edge_info": st.edge_info[m0:m],
            "gps_node": st.gps_node[g0:g], "gps_pos": st.gps_pos[g0:g],
            "gps_info": st.gps_info[g0:g]})


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_robust_solves_a_planar_map_in_the_plane(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a robust kernel the worker hands a map without GPS to solve_exact as is_2d, which
    takes the (x, y, yaw) system when the map is exactly planar (Huber with a delta above every
    residual: the optimum of the squared loss)."""
    from hybridpgo.io import read_graph
    from hybridpgo.solvers import gauss_newton

    g = read_graph(data_dir / "w100_toro.graph")
    st = make_stream(g)
    opt = prefix_optima(st, [st.num_frames])[st.num_frames]
    seen: list[bool] = []
    real = gauss_newton.is_planar

    def spy(*args: object) -> bool:
        seen.append(real(*args))  # type: ignore[arg-type]
        return seen[-1]

    monkeypatch.setattr(gauss_newton, "is_planar", spy)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    mp = _worker_map(s, ("huber", 1e6))
    assert mp.inc is None
    _, meta = mp.solve(50)
    assert seen and all(seen)
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt


def test_a_budget_beyond_the_clock_is_no_deadline() -> None:
    """``update(budget_s=1e12)`` overflowed the cycle counter (OverflowError); it is the same
    frame as ``update(None)``."""
    g = _graph()
    st = make_stream(g)
    cfg = OnlineConfig(background_refine=False)
    a, b = OnlineSolver(cfg), OnlineSolver(cfg)
    for k in range(st.num_frames):
        feed_frame(a, st, k)
        feed_frame(b, st, k)
        a.update(1e12, UPDATES)
        b.update(None, UPDATES)
    _same(_state(a), _state(b), timing=False)


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_falls_back_to_lm_when_the_incremental_solve_fails(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An incremental solve that raises (a factorization that is not positive definite) hands
    the request to the LM solve, which still reaches the optimum, and says why; a new
    incremental solver starts at that optimum and answers the next request; after MAX_RESETS
    failures the map stays with LM."""
    from hybridpgo.errors import SolverError
    from hybridpgo.online import worker

    mp, opt = _w100_worker_map(data_dir)

    def broken(*args: object, **kwargs: object) -> bool:
        raise SolverError("normal equations are not positive definite")

    monkeypatch.setattr(mp.inc, "solve", broken)
    _, meta = mp.solve(50)
    assert not meta["incremental"] and meta["resets"] == 1
    assert "not positive definite" in meta["fallback"]
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt
    _, meta = mp.solve(50)  # the new incremental solver, started at the optimum
    assert meta["incremental"] and abs(meta["energy"] - opt) <= ONLINE_REFINED * opt
    for _ in range(worker.MAX_RESETS):
        monkeypatch.setattr(mp.inc, "solve", broken)
        _, meta = mp.solve(50)
    assert mp.inc is None and meta["resets"] == worker.MAX_RESETS + 1
    _, meta = mp.solve(50)  # LM from then on
    assert not meta["incremental"] and abs(meta["energy"] - opt) <= ONLINE_REFINED * opt


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_refuses_an_incremental_answer_above_its_start(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An incremental answer whose energy is above the estimate it started from is not
    adopted: LM answers from that estimate instead."""

    mp, opt = _w100_worker_map(data_dir)
    rot, trans = mp.inc.estimate()
    worse = trans + 10.0 * np.arange(trans.shape[0])[:, None]  # a map torn apart
    monkeypatch.setattr(mp.inc, "solve", lambda *a, **k: True)
    monkeypatch.setattr(mp.inc, "estimate", lambda: (rot, worse))
    _, meta = mp.solve(50)
    assert not meta["incremental"] and "raised E" in meta["fallback"]
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_answers_with_the_data_of_its_request(data_dir: Path) -> None:
    """One update cycle per request with new data (the worker's): every answer holds every
    constraint shipped before its request, also after a cycle that left poses to relinearize
    (status "cycles"), whose look at what is left begins no cycle (a cycle begun then would
    hold only the data there by then, and the next request would answer without its own)."""
    from hybridpgo.io import read_graph

    g = read_graph(data_dir / "w100_toro.graph")
    s = OnlineSolver(OnlineConfig(background_refine=False))
    half = g.num_nodes // 2
    _stream(s, g, range(half))
    mp = _worker_map(s, ("none", None))
    mp.more_cycles_s = 0.0  # the worker's: one cycle per request with new data
    # no time cap: a cycle that compiles a kernel on a cold cache may take over SOLVE_CAP_S
    # and answer "max_time" with less than it was asked (what is tested here is the data)
    mp.cap_s = np.inf
    mp.solve(50)
    statuses = []
    for k in range(half, g.num_nodes):
        _stream(s, g, range(k, k + 1))
        _ship(mp, s)
        assert mp.inc.pending
        _, meta = mp.solve(50)
        statuses.append(meta["status"])
        assert (meta["m_held"], meta["g_held"]) == (meta["m"], meta["g"]), k
        # settled says what a cycle's start would decide, and begins nothing
        assert not mp.inc.busy and mp.inc.settled == (meta["status"] == "converged")
        assert mp.inc.settled == (not copy.deepcopy(mp.inc)._start_cycle(False)), k
    assert "cycles" in statuses and "converged" in statuses


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_the_worker_map_energy_refresh_equals_a_full_evaluation(data_dir: Path) -> None:
    """The worker's E after each answer (only the constraints that are new or touch a pose
    that moved evaluated) equals E summed over every constraint solved, also with rejected
    constraints and a pose moved by hand."""
    from hybridpgo import _cost
    from hybridpgo.io import read_graph

    g = read_graph(data_dir / "w100_toro.graph")
    s = OnlineSolver(OnlineConfig(background_refine=False))
    half = g.num_nodes // 2
    _stream(s, g, range(half))
    mp = _worker_map(s, ("none", None))

    def full() -> float:
        n, m, g = mp.n, mp.m, mp.g
        out, out_g = np.empty(m), np.empty(g)
        _cost.constraint_energies(mp.grot[1: n + 1], mp.gtr[1: n + 1], mp.edge_ab[:m],
                                  mp.edge_rot[:m], mp.edge_trans[:m], mp.edge_info[:m],
                                  mp.gps_node[:g], mp.gps_pos[:g], mp.gps_info[:g], out, out_g)
        return float(out[mp.keep_m[:m]].sum() + out_g[mp.keep_g[:g]].sum())

    _, meta = mp.solve(50)
    assert meta["energy"] == full()
    for k in range(half, g.num_nodes, 7):
        _stream(s, g, range(k, min(k + 7, g.num_nodes)))
        _ship(mp, s)
        _, meta = mp.solve(50)
        assert meta["energy"] == full(), k
    mp.keep_m[[3, mp.m - 1]] = False  # rejected: left out of E
    mp.gtr[5] += 0.25  # node 5 (pose 4) moved
    assert mp._energy() == full()
    # two GPS readings (fewer than the gauge needs: answered unsolved, E evaluated), one on the
    # moved pose; then that pose moves again, and one reading is rejected
    pos = mp.gtr[[5, 30]] + 0.5
    mp.add({"parent": np.zeros(0, np.int32), "rot": np.zeros((0, 3, 3)),
            "trans": np.zeros((0, 3)), "edge_ab": np.zeros((0, 2), np.int32),
            "edge_rot": np.zeros((0, 3, 3)), "edge_trans": np.zeros((0, 3)),
            "edge_info": np.zeros((0, 6, 6)), "gps_node": np.array([4, 29], np.int32),
            "gps_pos": pos, "gps_info": np.array([np.eye(3), 2 * np.eye(3)])})
    _, meta = mp.solve(50)
    assert meta["status"] == "not solved" and meta["energy"] == full() > 0
    mp.gtr[5] -= 0.125
    e_moved = mp._energy()
    assert e_moved == full()
    mp.keep_g[1] = False
    assert mp._energy() == full() < e_moved


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_integrates_what_an_answer_missed_before_it_polishes(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An answer that holds fewer constraints than the map (its update cycle began before the
    last data came, as a request stopped inside a cycle leaves it) is followed, at the next
    request without new data, by an update cycle that integrates the rest, not by the polish
    (which would answer only at its end); the request after an answer that held everything
    polishes.  A polish answers ("polishing") at the end of a slice once POLISH_ANSWER_S
    passed with a cycle done, and the next requests go on with it, E never rising, to the
    prefix optimum."""
    from hybridpgo.io import read_graph
    from hybridpgo.online import worker

    g = read_graph(data_dir / "w100_toro.graph")
    st = make_stream(g)
    opt = prefix_optima(st, [st.num_frames])[st.num_frames]
    s = OnlineSolver(OnlineConfig(background_refine=False))
    half = g.num_nodes // 2
    _stream(s, g, range(half))
    mp = _worker_map(s, ("none", None))
    mp.more_cycles_s = 0.0  # the worker's: one cycle per request with new data
    _, meta = mp.solve(50)
    _stream(s, g, range(half, half + 5))
    _ship(mp, s)
    mp.inc.solve(0.0, polish=False)  # a cycle begun at these data (a request stopped in it)
    _stream(s, g, range(half + 5, g.num_nodes))
    _ship(mp, s)
    _, meta = mp.solve(50)  # finishes the cycle begun before the last data came
    assert (meta["m_held"], meta["g_held"]) != (meta["m"], meta["g"])
    polished = []

    def polish(interrupted):  # type: ignore[no-untyped-def]
        polished.append(True)
        return "converged"

    with monkeypatch.context() as mpatch:
        mpatch.setattr(mp, "_polish", polish)
        _, meta = mp.solve(50, interrupted=lambda: False)  # nothing new
        assert not polished and meta["iterations"] >= 1
        assert (meta["m_held"], meta["g_held"]) == (meta["m"], meta["g"])
        while meta["status"] != "converged":  # relinearization left: cycles, not the polish
            assert not polished
            _, meta = mp.solve(50, interrupted=lambda: False)
        _, meta = mp.solve(50, interrupted=lambda: False)
        assert polished  # everything held: the polish
    monkeypatch.setattr(worker, "POLISH_ANSWER_S", 0.0)
    monkeypatch.setattr(worker, "POLISH_SLICE_S", 1e-9)  # slices too short for a whole cycle
    energies = [meta["energy"]]
    statuses = []
    for _ in range(100):
        _, meta = mp.solve(50, interrupted=lambda: False)
        energies.append(meta["energy"])
        statuses.append(meta["status"])
        if meta["status"] == "converged":
            break
    assert statuses[0] == "polishing" and statuses[-1] == "converged"
    assert all(b <= a * (1.0 + FLOAT64_IDENTITY) for a, b in itertools.pairwise(energies))
    assert abs(energies[-1] - opt) <= ONLINE_REFINED * opt


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_incremental_reaches_the_optimum(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without a robust kernel the worker's map is an IncrementalExact.  A request that brings
    new data stops once no pose's step passes the relinearization thresholds (no polish); the
    next request, with nothing new, polishes to the prefix optimum; a thorough request
    (``join_refine``) with new data reaches the optimum at once; and the locals returned
    compose to poses of the answer's energy."""
    from hybridpgo.io import read_graph

    g = read_graph(data_dir / "w100_toro.graph")
    st = make_stream(g)
    half = g.num_nodes // 2
    opts = prefix_optima(st, [half, st.num_frames])
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(half))
    mp = _worker_map(s, ("none", None))
    assert mp.inc is not None
    _, meta = mp.solve(50)
    assert meta["n"] == s.store.placed and meta["status"] == "converged"
    relinearized = mp.inc.stats["relinearized"]
    assert meta["energy"] > (1.0 + ONLINE_REFINED) * opts[half]  # not polished: not there
    from hybridpgo.online import worker

    cycles = mp.inc.stats["cycles"]
    with monkeypatch.context() as mpatch:  # a slice too short for a whole cycle
        mpatch.setattr(worker, "POLISH_SLICE_S", 1e-9)
        _, meta = mp.solve(50, interrupted=lambda: True)  # nothing new: a polish, cut short
    assert meta["status"] == "interrupted" and mp.inc.stats["cycles"] <= cycles + 1
    _, meta = mp.solve(50, interrupted=lambda: False)  # nothing new: the polish, to the end
    assert meta["status"] == "converged"
    assert mp.inc.stats["relinearized"] > relinearized
    assert abs(meta["energy"] - opts[half]) <= ONLINE_REFINED * opts[half]
    _stream(s, g, range(half, g.num_nodes))
    store = s.store
    _ship(mp, s)
    arrays, meta = mp.solve(50, thorough=True)
    opt = opts[st.num_frames]
    assert meta["status"] == "converged" and meta["iterations"] >= 1
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt
    # the locals returned are the estimate's: adopted into the store, the same energy
    store.rot[1: meta["n"] + 1] = arrays["rot"]
    store.trans[1: meta["n"] + 1] = arrays["trans"]
    assert abs(s.energy() - meta["energy"]) <= 1e-9 * opt


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_the_workers_energy_is_the_sum_over_the_constraints_solved(data_dir: Path) -> None:
    """The worker evaluates E from the χ² it kept, re-evaluating only the new constraints and
    those with a moved end: equal (summation order aside) to a whole evaluation over the
    constraints solved, after solves of growing prefixes, a changed rejected set, and a pose
    moved by hand."""
    from hybridpgo import _cost
    from hybridpgo.io import read_graph

    def naive(mp: Any) -> float:
        n, m, g = mp.n, mp.m, mp.g
        e, k = np.flatnonzero(mp.keep_m[:m]), np.flatnonzero(mp.keep_g[:g])
        return float(_cost.total_energy(
            mp.grot[1: n + 1], mp.gtr[1: n + 1], mp.edge_ab[e].astype(np.int32),
            mp.edge_rot[e], mp.edge_trans[e], mp.edge_info[e],
            mp.gps_node[k].astype(np.int32), mp.gps_pos[k], mp.gps_info[k]))

    g = read_graph(data_dir / "w100_toro.graph")
    s = OnlineSolver(OnlineConfig(background_refine=False))
    mp = None
    for lo in range(0, g.num_nodes, 20):
        _stream(s, g, range(lo, min(lo + 20, g.num_nodes)))
        if mp is None:
            mp = _worker_map(s, ("none", None))
        else:
            _ship(mp, s)
        assert abs(mp._energy() - naive(mp)) <= FLOAT64_IDENTITY * naive(mp)  # new data
        _, meta = mp.solve(50)
        assert abs(meta["energy"] - naive(mp)) <= FLOAT64_IDENTITY * naive(mp)  # solved
    assert mp is not None
    mp.keep_m[[3, 40, 77]] = False  # rejected: their χ² leave the sum
    assert abs(mp._energy() - naive(mp)) <= FLOAT64_IDENTITY * naive(mp)
    mp.gtr[9] += 0.5  # one pose moved: its constraints are evaluated again
    assert abs(mp._energy() - naive(mp)) <= FLOAT64_IDENTITY * naive(mp)
    mp.keep_m[:] = True  # re-admitted
    assert abs(mp._energy() - naive(mp)) <= FLOAT64_IDENTITY * naive(mp)


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_a_capped_incremental_answer_says_which_constraints_it_holds(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An incremental solve stopped by its cap before completing an update cycle answers with
    the last completed cycle's estimate, and says which edges that estimate holds (``held``)
    beside those shipped: the missing ones count in the answer's age (MAX_TAIL)."""
    import dataclasses
    from types import SimpleNamespace

    from hybridpgo.io import read_graph
    from hybridpgo.online import _link
    from hybridpgo.online.worker import Refined

    g = read_graph(data_dir / "w100_toro.graph")
    half = g.num_nodes // 2
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(half))
    mp = _worker_map(s, ("none", None))
    _, meta = mp.solve(50)
    m_half = meta["m"]
    assert m_half == meta["m_held"] == mp.m == s.store.m_laid
    _stream(s, g, range(half, g.num_nodes))
    store = s.store
    _ship(mp, s)
    assert mp.m > m_half
    monkeypatch.setattr(mp.inc, "solve", lambda *a, **k: False)  # no cycle completed
    arrays, meta = mp.solve(50)
    assert meta["status"] == "max_time" and meta["incremental"]
    assert (meta["n"], meta["m"], meta["g"]) == (mp.n, mp.m, 0)
    assert (meta["m_held"], meta["g_held"]) == (m_half, 0)
    res = Refined(meta["n"], meta["m"], meta["g"], 0, arrays["rot"], arrays["trans"],
                  meta["energy"], meta["iterations"], meta["status"], meta["seconds"],
                  (meta["m_held"], meta["g_held"]))
    link = _link.WorkerLink.__new__(_link.WorkerLink)  # the bookkeeping only
    link.stale = 0
    missing = store.m_laid - m_half
    monkeypatch.setattr(_link, "MAX_TAIL", missing)
    assert link.fresh(store, res)
    monkeypatch.setattr(_link, "MAX_TAIL", missing - 1)  # one more missing than allowed
    assert not link.fresh(store, res) and link.stale == 1
    assert link.fresh(SimpleNamespace(m_laid=store.m_laid, g_laid=0),
                      dataclasses.replace(res, held=None))  # all shipped held: fresh


def test_the_worker_solves_the_gauge_switch_to_gps_with_lm() -> None:
    """Before GPS_GAUGE readings the worker holds the first pose (its answers are not adopted
    then): a request with fewer readings is answered unsolved; the request that brings the
    GPS_GAUGE-th reading is solved by LM, not by an undamped incremental step from the
    estimate in the old gauge (which raised E there), and its answer is the prefix optimum;
    the incremental solver starts again there."""
    from hybridpgo.generate import generate_city
    from hybridpgo.online import worker

    g = generate_city(None, seed=0, num_poses=400, gps_every=20).graph
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    mp = worker._Map(("none", None))
    mp.slow_s = mp.more_cycles_s = np.inf  # both depend on the clock
    k = 0
    while st.gps_ptr[k + 1] < worker.GPS_GAUGE - 1:
        feed_frame(s, st, k)
        s.update(None, UPDATES)
        k += 1
    _ship(mp, s)
    assert mp.inc is not None
    cycles = mp.inc.stats["cycles"]
    _, meta = mp.solve(50)  # readings, but fewer than GPS_GAUGE: the first pose held
    assert 0 < meta["g"] < worker.GPS_GAUGE and not mp.earth
    assert meta["status"] == "not solved" and meta["iterations"] == 0
    assert mp.inc.stats["cycles"] == cycles
    switch = int(np.searchsorted(st.gps_ptr, worker.GPS_GAUGE))  # frames to hold that many
    end = switch + 5
    opt = prefix_optima(st, [end])[end]
    for f in range(k, end):
        feed_frame(s, st, f)
        s.update(None, UPDATES)
    _ship(mp, s)
    _, meta = mp.solve(50)
    assert mp.earth and meta["g"] >= worker.GPS_GAUGE
    assert not meta["incremental"] and meta["resets"] == 0, meta["fallback"]
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt
    assert mp.inc is not None  # the incremental solver, started again at that optimum


def test_an_answer_in_the_first_poses_gauge_is_not_adopted_once_gps_moves_the_map() -> None:
    """An answer holding 1 .. GPS_GAUGE-1 readings was solved with the first pose held, the
    frames' map with it free: not adopted, counted; no reading or enough of them: adopted."""
    from types import SimpleNamespace

    from hybridpgo.online import worker
    from hybridpgo.online._link import WorkerLink

    link = WorkerLink.__new__(WorkerLink)  # the bookkeeping only, no worker process
    link.other_gauge = 0
    for g in range(1, worker.GPS_GAUGE):
        assert not link.adopt(SimpleNamespace(), SimpleNamespace(n=5, m=4, g=g), 7, True)
    assert link.other_gauge == worker.GPS_GAUGE - 1


def test_an_adopted_answer_passes_on_the_workers_word_on_its_solver() -> None:
    """The worker's count of failed incremental solves, whether its map went to LM and why,
    reach ``stats()["background"]`` with each adopted answer."""
    from types import SimpleNamespace

    from hybridpgo.online._link import WorkerLink
    from hybridpgo.online.worker import Refined

    link = WorkerLink.__new__(WorkerLink)  # the bookkeeping only, no worker process
    link.__dict__.update(adopted=0, adopt_s_max=0.0, adopt_s=0.0, lag_max=0, _ship_frames={},
                         other_gauge=0, stale=0, settled=0, refined=(0, 0), rescreens=0,
                         fallback="", resets=0, with_lm=False,
                         refiner=SimpleNamespace(results=1, error=None))
    store = SimpleNamespace(placed=2, rot=np.zeros((3, 3, 3)), trans=np.zeros((3, 3)))
    res = Refined(2, 0, 0, 0, np.repeat(np.eye(3)[None], 2, 0), np.ones((2, 3)), 0.0, 1,
                  "converged", 0.0, fallback="LM is faster", resets=2, with_lm=True)
    assert link.adopt(store, res, 3, False)
    bgi = link.stats()
    assert (bgi["worker_resets"], bgi["worker_with_lm"]) == (2, True)
    assert bgi["worker_fallback"] == "LM is faster" and bgi["results_adopted"] == 1
    assert np.array_equal(store.trans[1:], np.ones((2, 3)))


def test_an_answer_older_than_the_tail_limit_is_not_adopted() -> None:
    """An asynchronous answer is adopted only while at most MAX_TAIL constraints were laid
    after its snapshot; a staler one is counted and left."""
    from types import SimpleNamespace

    from hybridpgo.online._link import MAX_TAIL, WorkerLink

    link = WorkerLink.__new__(WorkerLink)  # the bookkeeping only, no worker process
    link.stale = 0
    store = SimpleNamespace(m_laid=MAX_TAIL + 50, g_laid=10)
    assert link.fresh(store, SimpleNamespace(holds_all=(50, 10)))  # exactly MAX_TAIL
    assert not link.fresh(store, SimpleNamespace(holds_all=(50, 9)))  # one GPS more
    assert not link.fresh(store, SimpleNamespace(holds_all=(0, 0)))
    assert link.stale == 2


@pytest.mark.parametrize("lm_faster", [True, False])
@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_measures_lm_after_a_slow_incremental_request(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch, lm_faster: bool) -> None:
    """An incremental request that took SLOW_INCREMENTAL_S (past the warm-up requests, on a
    large enough map) has the next request solved by LM (which still reaches the optimum);
    when LM was the faster (prefer_lm) the map stays with LM and says why, else a new
    incremental solver starts at LM's optimum and answers the request after.  The choice
    itself is a pure function of the two times."""
    from hybridpgo.online import worker

    assert worker.prefer_lm(1.0, 0.4) and not worker.prefer_lm(1.0, 0.6)
    assert not worker.prefer_lm(np.nan, 0.1) and not worker.prefer_lm(1.0, np.nan)
    # with LM already, the map keeps it up to LM_RETURN_SHARE of the incremental time
    assert worker.prefer_lm(1.0, 0.6, with_lm=True) and worker.prefer_lm(1.0, 1.0, True)
    assert not worker.prefer_lm(1.0, 1.1, with_lm=True)
    assert worker.prefer_lm(np.nan, 5.0, True) and worker.prefer_lm(1.0, np.nan, True)
    mp, opt = _w100_worker_map(data_dir)
    mp.slow_s, mp.warmup, mp.min_poses = 0.0, 0, 0  # every incremental request is slow
    monkeypatch.setattr(worker, "prefer_lm", lambda inc, lm, with_lm=False: lm_faster)
    _, meta = mp.solve(50)
    assert meta["incremental"] and np.isfinite(mp.inc_seconds)
    _, meta = mp.solve(50)  # the measurement: LM
    assert not meta["incremental"] and np.isfinite(mp.lm_seconds)
    assert meta["with_lm"] is lm_faster and meta["resets"] == 0
    assert mp._lm_timed == (mp.lm_seconds, mp.n)  # the map it was measured on
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt
    if lm_faster:
        assert mp.inc is None and "LM is faster" in meta["fallback"]
    else:
        assert mp.inc is not None and meta["fallback"] == ""
    _, meta = mp.solve(50)
    assert meta["incremental"] is not lm_faster
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt
    if lm_faster:  # LM grown slower than the incremental requests were: back to them
        monkeypatch.setattr(worker, "prefer_lm", lambda inc, lm, with_lm=False: False)
        _, meta = mp.solve(50)
        assert not meta["incremental"] and meta["fallback"] == ""
        assert mp.inc is not None and not mp.with_lm and not np.isfinite(mp.inc_seconds)
        _, meta = mp.solve(50)
        assert meta["incremental"] and abs(meta["energy"] - opt) <= ONLINE_REFINED * opt


def test_background_worker_measures_lm_again_only_when_it_could_be_preferred() -> None:
    """Before LM was measured a request is slow from ``slow_s``; after, only from the time a
    request must take for LM to be preferred (prefer_lm), LM's measured time scaled by the
    map's growth since, and never below ``slow_s``."""
    from hybridpgo.online import worker

    mp = worker._Map(("none", None))
    assert mp._slow(5000) == mp.slow_s == worker.SLOW_INCREMENTAL_S
    mp._lm_timed = (1.2, 20_000)  # the last measuring LM solve: 1.2 s on 20 000 poses
    need = 1.2 / worker.LM_PREFERRED_SHARE
    assert mp._slow(20_000) == pytest.approx(need)
    assert mp._slow(30_000) == pytest.approx(1.5 * need)
    # a request that long makes LM the preferred choice at that LM time, a shorter one not
    assert worker.prefer_lm(1.01 * need, 1.2) and not worker.prefer_lm(0.99 * need, 1.2)
    mp._lm_timed = (0.01, 20_000)
    assert mp._slow(20_000) == worker.SLOW_INCREMENTAL_S
    mp._lm_timed = (np.nan, 20_000)  # not measured
    assert mp._slow(20_000) == worker.SLOW_INCREMENTAL_S


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_times_no_warm_up_request_nor_a_small_map(data_dir: Path) -> None:
    """The first INCREMENTAL_WARMUP requests of an incremental solver are not timed (the first
    factors the whole map, the worker's first may load kernels), nor are requests on a map
    of fewer than LM_MIN_POSES poses: however slow, they never send the map to LM."""
    from hybridpgo.io import read_graph
    from hybridpgo.online import worker

    g = read_graph(data_dir / "w100_toro.graph")
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    small = _worker_map(s, ("none", None))
    small.slow_s = 0.0  # every request is slow, but the map has 100 poses
    assert small.min_poses == worker.LM_MIN_POSES > g.num_nodes
    for _ in range(worker.INCREMENTAL_WARMUP + 2):
        _, meta = small.solve(50)
        assert meta["incremental"]
    mp = _worker_map(s, ("none", None))
    mp.slow_s, mp.min_poses = 0.0, 0
    for _ in range(worker.INCREMENTAL_WARMUP):
        _, meta = mp.solve(50)
        assert meta["incremental"] and not np.isfinite(mp.inc_seconds)
    _, meta = mp.solve(50)  # timed, and slow: the next request measures LM
    assert meta["incremental"] and np.isfinite(mp.inc_seconds)
    _, meta = mp.solve(50)
    assert not meta["incremental"] and np.isfinite(mp.lm_seconds)


@pytest.mark.parametrize("rise", [0.5, 2.0])
@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_accepts_an_answer_a_hair_above_its_start(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch, rise: float) -> None:
    """The incremental step is not an exact Gauss-Newton step: an answer whose E is above its
    start by less than RISE_RTOL (relative) is the answer; beyond it, LM answers."""
    from hybridpgo.online import worker

    mp, _ = _w100_worker_map(data_dir)
    mp.solve(50)
    e_start = mp._energy()
    rot, trans = mp.inc.estimate()
    monkeypatch.setattr(mp.inc, "solve", lambda *a, **k: True)
    monkeypatch.setattr(mp.inc, "estimate", lambda: (rot, trans))
    evaluate = mp._evaluate  # the answer's E (at the incremental estimate), raised by hand

    def raised(r: np.ndarray, t: np.ndarray) -> tuple[float, Any]:
        e, change = evaluate(r, t)
        return (e_start * (1.0 + rise * worker.RISE_RTOL) if r is rot else e), change

    monkeypatch.setattr(mp, "_evaluate", raised)
    _, meta = mp.solve(50)
    assert meta["incremental"] is (rise < 1.0)
    assert (meta["resets"] == 0) is (rise < 1.0)


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_polishes_an_answer_that_raised_e_before_it_fails(
        data_dir: Path) -> None:
    """An incremental answer above its start by more than RISE_RTOL is not refused at once:
    the solve goes on with the polish, and when that brings E back within the bound, that is
    the answer (no LM, no reset)."""
    mp, opt = _w100_worker_map(data_dir)
    evaluate = mp._evaluate
    seen: list[float] = []

    def raised_once(r: np.ndarray, t: np.ndarray) -> tuple[float, Any]:
        e, change = evaluate(r, t)
        seen.append(e)
        # the first call is the start's E (_energy), the second the answer's: raised by hand
        return (10.0 * e + 1.0 if len(seen) == 2 else e), change

    mp._evaluate = raised_once
    _, meta = mp.solve(50)
    assert len(seen) == 3  # the start, the raised answer, the answer after the polish
    assert meta["incremental"] and meta["resets"] == 0 and meta["fallback"] == ""
    assert abs(meta["energy"] - opt) <= ONLINE_REFINED * opt


@pytest.mark.parametrize("more_s", [0.0, np.inf])
@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_background_worker_answers_after_one_cycle_once_its_cycles_are_slow(
        data_dir: Path, more_s: float) -> None:
    """A request with new data starts no further update cycle once MORE_CYCLES_S passed since
    its first began: at 0 s it answers after one cycle ("cycles"), without the bound it runs
    its cycles until no step exceeds the relinearization thresholds; either way the request
    after it (nothing new: the polish) ends at the optimum."""
    from hybridpgo.online import worker

    mp, opt = _w100_worker_map(data_dir)
    mp.slow_s, mp.warmup, mp.min_poses = 0.0, 0, 0  # every request timed is slow
    assert worker._Map(("none", None)).more_cycles_s == worker.MORE_CYCLES_S
    mp.more_cycles_s = more_s
    _, meta = mp.solve(50)
    assert meta["incremental"]
    if more_s == 0.0:
        assert meta["status"] == "cycles" and meta["iterations"] == 1
        # a request that did part of its work is no sample of its cost against LM's
        assert not np.isfinite(mp.inc_seconds) and not mp._measure_lm
    else:
        assert meta["status"] == "converged" and meta["iterations"] > 1
        assert np.isfinite(mp.inc_seconds) and mp._measure_lm
        mp._measure_lm = False  # (the LM measurement is another test's)
    _, meta = mp.solve(50)
    assert meta["incremental"] and abs(meta["energy"] - opt) <= ONLINE_REFINED * opt
    # a new pose on its exact odometry: one cycle does all the work, which the request
    # finds ("converged", a sample of a request's cost) whatever the bound
    n = mp.n
    step = np.array([[1.0, 0.0, 0.0]])
    mp.add({"parent": np.array([n], np.int32), "rot": np.eye(3)[None], "trans": step,
            "edge_ab": np.array([[n - 1, n]], np.int32), "edge_rot": np.eye(3)[None],
            "edge_trans": step, "edge_info": np.eye(6)[None],
            "gps_node": np.zeros(0, np.int32), "gps_pos": np.zeros((0, 3)),
            "gps_info": np.zeros((0, 3, 3))})
    mp._measure_lm, mp.inc_seconds = False, np.nan
    _, meta = mp.solve(50)
    assert meta["incremental"] and meta["status"] == "converged" and meta["iterations"] == 1
    assert np.isfinite(mp.inc_seconds) and abs(meta["energy"] - opt) <= ONLINE_REFINED * opt


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
@pytest.mark.parametrize("defer", [True, False])
def test_the_worker_screens_an_answer_after_sending_it(data_dir: Path, defer: bool) -> None:
    """``robust="auto"``: a request's answer goes out before the outlier test that fell due
    with it (``screen_after``), so the test does not hold it back; when the test rejects a
    false closure, the re-solved map is a second answer naming it.  A thorough request, or
    ``defer_screening`` off, screens before answering."""
    from hybridpgo.io import read_graph

    g = read_graph(data_dir / "w100_toro.graph")
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    mp = _worker_map(s, ("auto", None))
    mp.defer_screening = defer
    mp.solve(50)
    mp.screen_after()
    n = mp.n
    false = n // 2
    mp.add({"parent": np.zeros(0, np.int32), "rot": np.zeros((0, 3, 3)),
            "trans": np.zeros((0, 3)), "edge_ab": np.array([[1, false]], np.int32),
            "edge_rot": np.eye(3)[None], "edge_trans": np.array([[40.0, 0.0, 0.0]]),
            "edge_info": np.eye(6)[None] * 100.0, "gps_node": np.zeros(0, np.int32),
            "gps_pos": np.zeros((0, 3)), "gps_info": np.zeros((0, 3, 3))})
    bad = mp.m - 1
    mp._screened_at = -np.inf  # the test is due
    arrays, meta = mp.solve(50)
    later = mp.screen_after()
    if defer:  # the least-squares answer first, then the re-solved one
        assert bad not in arrays["rejected_m"] and later is not None
        arrays, meta = later
        assert meta["status"] == "screened" and meta["m_held"] == mp.m
    else:
        assert later is None
    assert list(arrays["rejected_m"]) == [bad] and mp.rescreens == 1
    assert mp.screen_after() is None  # nothing more due
    mp._screened_at = -np.inf
    mp.solve(50, thorough=True)  # a thorough request: screened before its answer
    assert np.isfinite(mp._screened_at) and not mp._screen_later
    assert mp.screen_after() is None


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
def test_the_worker_process_answers_again_after_a_screening_that_rejects(
        data_dir: Path) -> None:
    """The worker process (``robust="auto"``) sends a request's least-squares answer, then
    runs the outlier test due with it and, when the test rejects a false closure, answers the
    same request again with the re-solved map (status ``"screened"``), which names it."""
    from hybridpgo.io import read_graph
    from hybridpgo.online.worker import BackgroundRefiner

    g = read_graph(data_dir / "w100_toro.graph")
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    st = s.store
    t, m = st.placed + 1, st.m_laid
    ab = np.concatenate([st.edge_ab[:m], [[1, t // 2]]]).astype(np.int32)
    ref = BackgroundRefiner(20, "auto")
    try:
        assert ref.wait_ready(120.0)
        ref.ship({"type": "data"}, {
            "parent": st.parent[1:t], "rot": st.rot[1:t], "trans": st.trans[1:t],
            "edge_ab": ab, "edge_rot": np.concatenate([st.edge_rot[:m], np.eye(3)[None]]),
            "edge_trans": np.concatenate([st.edge_trans[:m], [[40.0, 0.0, 0.0]]]),
            "edge_info": np.concatenate([st.edge_info[:m], np.eye(6)[None] * 100.0]),
            "gps_node": np.zeros(0, np.int32), "gps_pos": np.zeros((0, 3)),
            "gps_info": np.zeros((0, 3, 3))})
        req = ref.request()
        with ref._cond:
            assert ref._cond.wait_for(lambda: ref.results >= 2 or ref.error, 120.0)
        res = ref.take()
        assert ref.error is None and res is not None and res.req == req
        assert res.status == "screened" and list(res.rejected[0]) == [m]
    finally:
        ref.close()


def test_the_receiver_says_whether_the_workers_newest_message_was_an_error() -> None:
    """``BackgroundRefiner.failing``: True after an error message, False again after a
    result; True for good once the link failed (a result does not clear it) and once the
    worker's output ends; ``error`` keeps the last error's text."""
    import threading
    import types

    from hybridpgo.online import worker

    rd, wr = os.pipe()
    ref = worker.BackgroundRefiner.__new__(worker.BackgroundRefiner)  # no process
    ref._proc = types.SimpleNamespace(stdout=os.fdopen(rd, "rb", buffering=0))
    ref._cond = threading.Condition()
    ref._latest, ref._answered, ref.error, ref.failing = None, -1, None, False
    ref.results, ref._alive, ref._ready, ref._broken = 0, True, False, False
    out = os.fdopen(wr, "wb", buffering=0)
    recv = threading.Thread(target=ref._recv_loop, daemon=True)
    recv.start()

    def sent(data: bytes, done: Any) -> None:
        worker.write_all(out, data)
        with ref._cond:
            assert ref._cond.wait_for(done, 60.0)

    result = {"type": "result", "n": 1, "m": 0, "g": 0, "req": 1, "energy": 0.0,
              "iterations": 0, "status": "converged", "seconds": 0.0, "m_held": 0,
              "g_held": 0, "rescreens": 0}
    arrays = {"rot": np.eye(3)[None], "trans": np.zeros((1, 3)),
              "rejected_m": np.zeros(0, np.int64), "rejected_g": np.zeros(0, np.int64)}
    try:
        sent(worker._error(0, ValueError("no factorization today")),
             lambda: ref._answered >= 0)
        assert ref.failing and ref.error == "ValueError: no factorization today"
        sent(worker.encode(result, arrays), lambda: ref.results >= 1)
        assert not ref.failing and ref.error == "ValueError: no factorization today"
        ref._fail("the worker stopped reading")  # the link failed (the sender's side)
        sent(worker.encode({**result, "req": 2}, arrays), lambda: ref.results >= 2)
        assert ref.failing  # a result does not mend a failed link
    finally:
        out.close()  # the worker's output ends
        recv.join(60.0)
        ref._proc.stdout.close()
    assert ref.failing and not ref.alive


@pytest.mark.parametrize("robust", [("none", None), ("auto", None), ("huber", 1.0)])
def test_the_worker_warms_up_every_path_a_request_can_take(
        robust: tuple[str, float | None]) -> None:
    """Before it says it is ready the worker answers requests of a tiny map through the
    incremental solve, LM in the plane, the gauge switch to GPS and (``auto``) the outlier test
    with its robust re-solve, so that no kernel is first loaded in the middle of a stream."""
    from hybridpgo.online import worker

    calls: dict[str, int] = {}

    def counted(name: str, fn: Any) -> Any:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            if name == "lm":
                key = "lm planar" if args[0]._graph(True).is_2d else "lm 3d"
                calls[key] = calls.get(key, 0) + 1
            else:
                calls[name] = calls.get(name, 0) + 1
            return fn(*args, **kwargs)
        return wrapper

    mp_cls = worker._Map
    with pytest.MonkeyPatch.context() as mpatch:
        mpatch.setattr(mp_cls, "_solve_lm", counted("lm", mp_cls._solve_lm))
        mpatch.setattr(mp_cls, "_incremental_here",
                       counted("incremental", mp_cls._incremental_here))
        mp = worker.warm_up(robust)
    assert mp.earth and mp.g == worker.GPS_GAUGE
    assert calls.get("lm planar", 0) >= 1 and calls.get("lm 3d", 0) >= 1, calls
    if robust[0] in ("none", "auto"):
        assert mp.inc is not None and calls.get("incremental", 0) >= 2, calls
        assert mp.resets == 0 and mp.fallback == "", mp.fallback
    if robust[0] == "auto":  # the false closure, the last edge: tested, rejected
        assert mp.rescreens >= 1 and not mp.keep_m[mp.m - 1] and mp.keep_m[: mp.m - 1].all()


def test_the_worker_warm_up_loads_every_kernel_of_the_incremental_solver() -> None:
    """Every kernel the incremental solver calls is loaded by the warm-up, the AMD ordering of
    a re-eliminated set and the relinearization included, even when the request's time cap
    would stop a cycle at once (as a cold cache's compilation does): in a fresh process, so
    that no other test has loaded them."""
    import re
    import subprocess
    import sys

    from hybridpgo.online import incremental

    called = sorted(set(re.findall(r"\bik\.([a-z]\w*)\(",
                                   Path(incremental.__file__).read_text())))
    assert {"numeric", "back_substitute", "reduced_pattern", "relinearize"} <= set(called)
    program = (
        "import hybridpgo.online._incremental_kernels as ik\n"
        "from hybridpgo.online import worker\n"
        "worker.SOLVE_CAP_S = 0.0\n"
        "mp = worker.warm_up(('none', None))\n"
        "assert mp.inc is not None and mp.resets == 0, mp.fallback\n"
        f"print(' '.join(k for k in {called!r} if not getattr(ik, k).signatures))\n")
    out = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == [], f"not loaded by the warm-up: {out.stdout}"


@pytest.mark.filterwarnings("ignore:.*EQUIV line:UserWarning")  # the file's EQUIV lines
@pytest.mark.parametrize("kind", ["planar", "planar_gps", "3d_gps"])
def test_the_worker_screens_with_the_outlier_test_of_a_whole_graph(
        data_dir: Path, monkeypatch: pytest.MonkeyPatch, kind: str) -> None:
    """The worker's screening tests the χ² it keeps, without building a PoseGraph of its map:
    its verdict (scales and every constraint's sigmas) is check_consistency's on the graph of
    the constraints solved (and of all of them, thorough), to the bit; on planar data (3
    degrees of freedom per constraint, 2 per GPS reading), without and with GPS readings, and
    on a 3D map with GPS readings, each with a false closure that makes it inconsistent."""
    from hybridpgo.generate import generate_city
    from hybridpgo.graph import planar_data
    from hybridpgo.io import read_graph
    from hybridpgo.solvers import robust

    g = (generate_city(None, seed=0, num_poses=300, gps_every=10).graph if kind == "3d_gps"
         else read_graph(data_dir / "w100_toro.graph"))
    s = OnlineSolver(OnlineConfig(background_refine=False))
    _stream(s, g, range(g.num_nodes))
    mp = _worker_map(s, ("auto", None))
    mp.solve(50)
    mp.screen_after()
    if kind == "planar_gps":  # readings in the plane, every 10th pose, near its estimate
        nodes = np.arange(0, mp.n, 10, dtype=np.int32)
        pos = mp.gtr[1 + nodes].copy()
        pos[:, :2] += np.random.default_rng(0).normal(scale=0.3, size=(nodes.size, 2))
        pos[:, 2] = 0.0
        mp.add({"parent": np.zeros(0, np.int32), "rot": np.zeros((0, 3, 3)),
                "trans": np.zeros((0, 3)), "edge_ab": np.zeros((0, 2), np.int32),
                "edge_rot": np.zeros((0, 3, 3)), "edge_trans": np.zeros((0, 3)),
                "edge_info": np.zeros((0, 6, 6)), "gps_node": nodes, "gps_pos": pos,
                "gps_info": np.broadcast_to(np.eye(3) * 10.0, (nodes.size, 3, 3)).copy()})
        mp.solve(50)
        mp.screen_after()
    mp.add({"parent": np.zeros(0, np.int32), "rot": np.zeros((0, 3, 3)),
            "trans": np.zeros((0, 3)), "edge_ab": np.array([[1, mp.n // 2]], np.int32),
            "edge_rot": np.eye(3)[None], "edge_trans": np.array([[40.0, 0.0, 0.0]]),
            "edge_info": np.eye(6)[None] * 100.0, "gps_node": np.zeros(0, np.int32),
            "gps_pos": np.zeros((0, 3)), "gps_info": np.zeros((0, 3, 3))})
    mp.defer_screening = True
    mp.solve(50)  # the least-squares answer with the false closure
    seen: list[Any] = []
    original = robust.consistency_of

    def recording(*args: Any, **kwargs: Any) -> Any:
        seen.append(original(*args, **kwargs))
        return seen[-1]

    monkeypatch.setattr(robust, "consistency_of", recording)
    n = mp.n
    for thorough in (False, True):
        graph = mp._graph(not thorough)
        assert (graph.gps_nodes.size > 0) == (kind != "planar")
        assert planar_data(graph) == (kind != "3d_gps")
        want = robust.check_consistency(graph, mp.grot[1: n + 1], mp.gtr[1: n + 1])
        seen.clear()
        changed = mp._screen(thorough)
        got = seen[0]  # the screening's test (a re-solve tests again)
        assert got.scale == want.scale or (np.isnan(got.scale) and np.isnan(want.scale))
        assert got.gps_scale == want.gps_scale or (np.isnan(got.gps_scale)
                                                   and np.isnan(want.gps_scale))
        np.testing.assert_array_equal(got.sigmas, want.sigmas)
        np.testing.assert_array_equal(got.gps_sigmas, want.gps_sigmas)
        assert got.inconsistent == want.inconsistent
        if not thorough:  # the false closure makes the map inconsistent
            assert got.inconsistent
            if kind == "planar":  # and on w100 the re-solve rejects it
                assert changed and not mp.keep_m[mp.m - 1]


def test_worker_messages_are_written_from_the_arrays_as_encoded() -> None:
    """An answer written straight from its arrays (``write_message``) is ``encode``'s bytes,
    and reads back as the same arrays (dtypes, shapes, byte order and empty arrays included);
    the answers' pipe is widened to ``PIPE_BYTES`` where the system has the call."""
    import io

    from hybridpgo.online import worker

    arrays = {"rot": np.arange(18.0).reshape(2, 3, 3), "flags": np.array([True, False]),
              "none": np.zeros(0, np.int32), "no_poses": np.zeros((0, 3, 3)),
              "big": np.arange(5, dtype=">i8"),
              "cols": np.asfortranarray(np.arange(6.0).reshape(2, 3))}
    buf = io.BytesIO()
    worker.write_message(buf, {"type": "result", "n": 2}, arrays)
    assert buf.getvalue() == worker.encode({"type": "result", "n": 2}, arrays)
    buf.seek(0)
    msg = worker.read_message(buf)
    assert msg is not None
    meta, got = msg
    assert meta == {"type": "result", "n": 2} and list(got) == list(arrays)
    for name, arr in arrays.items():
        assert got[name].dtype == arr.dtype and got[name].shape == arr.shape
        np.testing.assert_array_equal(got[name], arr)
    fcntl = pytest.importorskip("fcntl")  # POSIX
    if hasattr(fcntl, "F_GETPIPE_SZ"):  # Linux
        r, w = os.pipe()
        try:
            worker.widen_pipe(w)
            limit = int(Path("/proc/sys/fs/pipe-max-size").read_text())
            if worker.PIPE_BYTES <= limit:
                assert fcntl.fcntl(w, fcntl.F_GETPIPE_SZ) == worker.PIPE_BYTES
        finally:
            os.close(r)
            os.close(w)
