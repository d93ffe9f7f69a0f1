"""The incremental exact solver (hybridpgo.online.incremental) against the batch exact solver.

Oracles: after every completed update cycle the solution is the Gauss-Newton step of the whole
map at the linearization point (``gauss_newton.gn_step``, a fresh batch factorization); run to
convergence the estimate is the batch optimum (``solve_exact``); work sliced by deadlines gives
bit for bit the answer of unsliced work.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from graphs import planar_rotations, random_rotations
from hypothesis import example, given, settings
from hypothesis import strategies as st
from tolerances import FLOAT64_IDENTITY, FORWARD_ERROR, INCREMENTAL_VS_BATCH, SPARSE_VS_DENSE_GN

from hybridpgo.graph import PoseGraph, lift_information_2d
from hybridpgo.online.incremental import IncrementalConfig, IncrementalExact
from hybridpgo.online.worker import ROUNDING_WILDFIRE
from hybridpgo.solvers._normal import normal_equations
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import gn_step, solve_exact


@dataclasses.dataclass
class _Stream:
    """Frames of a random drive: frame k brings pose k (odometry from k-1), loop closures from
    k to earlier poses, and maybe a GPS reading of k."""

    odo_r: np.ndarray
    odo_t: np.ndarray
    loops: list[list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]]
    gps: list[list[tuple[np.ndarray, np.ndarray]]]
    odo_info: np.ndarray

    @property
    def frames(self) -> int:
        return len(self.loops)


def _stream(seed: int, n: int, loop_p: float, gps_every: int, noise: float = 0.05,
            planar: bool = False) -> _Stream:
    """``planar``: the poses and measurements lie in the xy-plane (rotations about z exactly,
    z = 0) and the information is a planar one lifted to 3D (GPS readings, if any, are not
    planar)."""
    rng = np.random.default_rng(seed)
    rot = np.empty((n, 3, 3))
    trans = np.empty((n, 3))
    rot[0] = np.eye(3)
    trans[0] = 0.0

    def turns(k: int, scale: float) -> np.ndarray:
        if planar:
            return planar_rotations(rng.normal(scale=scale, size=k))
        return random_rotations(rng, k, scale)

    steps = turns(n, 0.3)
    for k in range(1, n):
        rot[k] = rot[k - 1] @ steps[k]
        trans[k] = trans[k - 1] + rot[k - 1] @ np.array([1.0, 0.0, 0.0])

    def measure(a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        zr = rot[a].T @ rot[b] @ turns(1, noise)[0]
        zt = rot[a].T @ (trans[b] - trans[a]) + rng.normal(scale=noise, size=3)
        if planar:
            zr[2, :], zr[:, 2], zt[2] = (0.0, 0.0, 1.0), (0.0, 0.0, 1.0), 0.0
        return zr, zt

    def info6() -> np.ndarray:
        if planar:
            q = rng.normal(size=(3, 3))
            return lift_information_2d((q @ q.T + 3.0 * np.eye(3))[None])[0]
        q = rng.normal(size=(6, 6))
        return q @ q.T + 6.0 * np.eye(6)

    odo_r = np.empty((n, 3, 3))
    odo_t = np.empty((n, 3))
    odo_info = np.empty((n, 6, 6))
    loops: list[list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]] = []
    gps: list[list[tuple[np.ndarray, np.ndarray]]] = []
    for k in range(n):
        if k:
            odo_r[k], odo_t[k] = measure(k - 1, k)
            odo_info[k] = info6()
        frame = []
        if k >= 3 and rng.random() < loop_p:
            a = int(rng.integers(0, k - 1))
            zr, zt = measure(a, k)
            frame.append((a, zr, zt, info6()))
        loops.append(frame)
        g = []
        if gps_every and k % gps_every == gps_every - 1:
            q = rng.normal(size=(3, 3))
            g.append((trans[k] + rng.normal(scale=noise, size=3), q @ q.T + 3.0 * np.eye(3)))
        gps.append(g)
    return _Stream(odo_r, odo_t, loops, gps, odo_info)


def _feed(inc: IncrementalExact, s: _Stream, k: int) -> None:
    if k == 0:
        inc.add_poses(np.eye(3)[None], np.zeros((1, 3)))
    else:
        inc.add_poses(s.odo_r[k][None], s.odo_t[k][None], [k - 1])
        inc.add_edges([k - 1], [k], s.odo_r[k][None], s.odo_t[k][None], s.odo_info[k][None])
    for a, zr, zt, info in s.loops[k]:
        inc.add_edges([a], [k], zr[None], zt[None], info[None])
    for pos, info3 in s.gps[k]:
        inc.add_gps([k], pos[None], info3[None])


def _graph(inc: IncrementalExact, rot: np.ndarray, trans: np.ndarray) -> PoseGraph:
    """Everything integrated, at the given poses, with the solver's gauge."""
    n, m, g = inc._n_in, inc._m_in, inc._g_in
    return PoseGraph(
        node_ids=np.arange(n), rotations=rot[:n], translations=trans[:n],
        edge_nodes=inc._ab[:m].astype(np.int32), edge_rotations=inc._zr[:m],
        edge_translations=inc._zt[:m], edge_information=inc._info[:m],
        gps_nodes=inc._gnode[:g].astype(np.int32), gps_positions=inc._gpos[:g],
        gps_information=inc._ginfo[:g],
        fixed_nodes=np.zeros(0 if inc._free[0] else 1, np.int32))  # fmt: skip


def _check_sorted_rows(inc: IncrementalExact) -> None:
    """Every column of the last re-eliminated set lists its rows in increasing position (the
    left-looking pass reads each such column from a cursor on)."""
    for v in getattr(inc, "_s_vars", ()):  # none before the first set with a column
        rows = inc._row_var[inc._col_start[v]: inc._col_start[v] + inc._col_len[v]]
        assert np.all(np.diff(inc._position[rows]) > 0)


def _check_supernodes(inc: IncrementalExact) -> int:
    """The last set's supernodes partition it into runs of consecutive columns, each column's
    parent the next and its rows the next column and the next column's rows; returns the
    widest run."""
    import hybridpgo.online._incremental_kernels as ik

    order = getattr(inc, "_order_s", np.zeros(0, np.int64))
    if order.size == 0:
        return 0
    ptr = inc._sn_ptr[: inc._sn_count + 1]
    assert ptr[0] == 0 and ptr[-1] == order.size and np.all(np.diff(ptr) >= 1)
    widest = 0
    for s in range(inc._sn_count):
        cols = order[ptr[s]: ptr[s + 1]]
        assert cols.size <= ik.SUPERNODE_MAX
        assert np.all(inc._sn_of[cols] == s)
        for j, j2 in itertools.pairwise(cols):
            rows = inc._row_var[inc._col_start[j]: inc._col_start[j] + inc._col_len[j]]
            rows2 = inc._row_var[inc._col_start[j2]: inc._col_start[j2] + inc._col_len[j2]]
            assert inc._parent[j] == j2
            assert rows.tolist() == [j2, *rows2.tolist()]
        widest = max(widest, cols.size)
    return widest


def _check_gn_step(inc: IncrementalExact) -> None:
    """x against a batch factorization's GN step, to SPARSE_VS_DENSE_GN, or where H is worse
    conditioned, to its forward-error bound (FORWARD_ERROR cond(H) eps)."""
    n = inc._n_in
    graph = _graph(inc, inc._th_r, inc._th_t)
    ref = gn_step(graph, inc._th_r[:n], inc._th_t[:n], graph.fixed_nodes)
    got = np.where(inc._free[:n, None], inc._x[:n], 0.0)
    scale = max(1.0, float(np.abs(ref).max()))
    err = float(np.abs(got - ref).max())
    if err > SPARSE_VS_DENSE_GN * scale:  # the bound of this system's conditioning
        h = normal_equations(graph, inc._th_r[:n], inc._th_t[:n], graph.fixed_nodes).hessian
        bound = float(np.linalg.cond(h.toarray())) * np.finfo(float).eps
        assert bound <= 1e-5, bound  # a graph so ill-conditioned tests nothing
        assert err <= FORWARD_ERROR * bound * scale, (err, bound)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 40),
       loop_p=st.sampled_from([0.0, 0.3, 0.8]), gps_every=st.sampled_from([0, 3, 7]),
       beta=st.sampled_from([0.0, 1e-3, 0.05]), reorder=st.booleans(),
       capacity=st.sampled_from([4, 64]), wildfire=st.sampled_from([0.0, ROUNDING_WILDFIRE]),
       planar=st.booleans())
@example(seed=57, n=11, loop_p=0.8, gps_every=3, beta=0.0, reorder=False, capacity=4,
         wildfire=0.0, planar=True)  # H's condition number 3e8-2e9 (FORWARD_ERROR)
def test_every_cycle_solves_the_whole_map_exactly(seed: int, n: int, loop_p: float,
                                                  gps_every: int, beta: float, reorder: bool,
                                                  capacity: int, wildfire: float,
                                                  planar: bool) -> None:
    """After each completed cycle, x is the batch Gauss-Newton step at the linearization point,
    whatever was re-eliminated (partial refactorization, orphans, reordering, pool growth),
    also when the back substitution skips what moved by rounding only (the worker's
    threshold); a planar stream is solved in the planar system until its first GPS reading,
    then in the full one."""
    s = _stream(seed, n, loop_p, gps_every, planar=planar)
    cfg = IncrementalConfig(relinearize_rho=beta, relinearize_phi=beta, reorder=reorder,
                            wildfire=wildfire)
    inc = IncrementalExact(cfg, capacity=capacity)
    rng = np.random.default_rng(seed + 1)
    for k in range(s.frames):
        _feed(inc, s, k)
        for _ in range(int(rng.integers(1, 4))):
            before = inc.stats["cycles"]
            inc.solve(max_cycles=1)
            if inc.stats["cycles"] > before:
                _check_gn_step(inc)
                _check_sorted_rows(inc)
                _check_supernodes(inc)
                flat = k == 0 or (planar and not any(s.gps[i] for i in range(k + 1)))
                assert inc._nd == (3 if flat else 6)


@pytest.mark.parametrize("late", ["edge", "pose", "gps"])
def test_the_planar_system_is_the_full_systems_solution_and_leaves_it_for_3d_data(
        late: str) -> None:
    """A planar stream solved in the planar system (default) gives the estimates of the same
    stream solved in the full system (``planar=False``) to rounding, at every cycle; a datum
    out of the plane (an edge, a pose, a GPS reading) moves the solver to the full system, and
    it still solves the whole map exactly."""
    s = _stream(11, 60, 0.4, 0, planar=True)
    flat = IncrementalExact(IncrementalConfig(relinearize_rho=0.05, relinearize_phi=0.05))
    full = IncrementalExact(IncrementalConfig(relinearize_rho=0.05, relinearize_phi=0.05,
                                              planar=False))
    for k in range(s.frames):
        _feed(flat, s, k)
        _feed(full, s, k)
        flat.solve(max_cycles=1)
        full.solve(max_cycles=1)
        assert flat._nd == 3 and full._nd == 6
        for a, b in zip(flat.estimate(), full.estimate(), strict=True):
            assert np.abs(a - b).max() <= SPARSE_VS_DENSE_GN * max(1.0, np.abs(b).max())
    rot, trans = flat.estimate()
    assert np.all(rot[:, 2, :2] == 0.0) and np.all(trans[:, 2] == 0.0)  # in the plane
    tilt = random_rotations(np.random.default_rng(3), 1, 0.1)
    n = flat.num_poses
    if late == "edge":
        flat.add_edges([0], [n - 1], tilt, trans[n - 1: n], np.eye(6)[None])
    elif late == "pose":
        flat.add_poses(tilt, np.array([[1.0, 0.0, 0.2]]), [n - 1])
        flat.add_edges([n - 1], [n], tilt, np.array([[1.0, 0.0, 0.2]]), np.eye(6)[None])
    else:
        flat.add_gps([n - 1], trans[n - 1: n] + np.array([0.0, 0.0, 0.5]), np.eye(3)[None])
    flat.solve(max_cycles=1)
    assert flat._nd == 6
    _check_gn_step(flat)
    while not flat.solve(max_cycles=1):
        _check_gn_step(flat)


@pytest.mark.parametrize(("seed", "gps_every"), [(0, 0), (1, 5)])
def test_an_idle_solver_reaches_the_batch_optimum(seed: int, gps_every: int) -> None:
    """Streamed with the default thresholds, then updated with nothing new: the polish
    relinearizes what still moves, down to the batch optimum."""
    s = _stream(seed, 120, 0.3, gps_every)
    inc = IncrementalExact()
    for k in range(s.frames):
        _feed(inc, s, k)
        inc.solve()
    while not inc.solve():
        pass
    rot, trans = inc.estimate()
    graph = _graph(inc, rot, trans)
    ref = solve_exact(graph, rot, trans,
                      GaussNewtonConfig(max_iterations=100, energy_tolerance=1e-15))
    assert abs(inc.energy() - ref.final_energy) <= INCREMENTAL_VS_BATCH * ref.final_energy


def test_without_the_polish_a_solve_stops_at_the_thresholds_and_keeps_the_list() -> None:
    """``solve(polish=False)`` ends once no step passes the relinearization thresholds (True:
    nothing left without the polish), relinearizes nothing below them, and leaves the poses
    listed for the polish to a later ``solve()``, which reaches the batch optimum."""
    s = _stream(3, 120, 0.3, 0)
    inc = IncrementalExact()
    for k in range(s.frames):
        _feed(inc, s, k)
        assert inc.solve(polish=False)
    listed = int(inc._pol_count[0])
    relinearized = inc.stats["relinearized"]
    assert listed > 0
    assert inc.solve(polish=False)  # nothing new, no polish: no cycle
    assert inc.stats["relinearized"] == relinearized and int(inc._pol_count[0]) == listed
    e_unpolished = inc.energy()
    while not inc.solve():
        pass
    assert inc.stats["relinearized"] > relinearized
    rot, trans = inc.estimate()
    graph = _graph(inc, rot, trans)
    ref = solve_exact(graph, rot, trans,
                      GaussNewtonConfig(max_iterations=100, energy_tolerance=1e-15))
    assert abs(inc.energy() - ref.final_energy) <= INCREMENTAL_VS_BATCH * ref.final_energy
    assert e_unpolished > ref.final_energy * (1.0 + INCREMENTAL_VS_BATCH)


def test_gauss_newton_thresholds_reach_the_batch_optimum() -> None:
    """Thresholds 0 after a stream: every update is a Gauss-Newton step of the whole map."""
    s = _stream(4, 80, 0.4, 0)
    inc = IncrementalExact()
    for k in range(s.frames):
        _feed(inc, s, k)
        inc.solve(max_cycles=1)
    inc.config = dataclasses.replace(inc.config, relinearize_rho=0.0, relinearize_phi=0.0)
    inc.relinearize_all()
    for _ in range(50):
        inc.solve(max_cycles=1)
        if np.abs(inc._x[: inc.num_poses]).max() < 1e-13:
            break
    rot, trans = inc.estimate()
    ref = solve_exact(_graph(inc, rot, trans), rot, trans,
                      GaussNewtonConfig(max_iterations=100, energy_tolerance=1e-15))
    assert abs(inc.energy() - ref.final_energy) <= INCREMENTAL_VS_BATCH * ref.final_energy


def test_deadline_slices_give_the_same_answer_bit_for_bit() -> None:
    s = _stream(7, 60, 0.5, 4)
    whole = IncrementalExact()
    sliced = IncrementalExact()
    calls = 0
    for k in range(s.frames):
        _feed(whole, s, k)
        _feed(sliced, s, k)
        whole.solve()
        while not sliced.solve(budget_s=0.0):  # one column or one solution entry per call
            calls += 1
    assert calls > 10 * s.frames  # the slices did split the work
    for a, b in zip(whole.estimate(), sliced.estimate(), strict=True):
        assert np.array_equal(a, b)


def test_the_pool_compacted_in_place_gives_the_copied_pools_answer_bit_for_bit(
        monkeypatch) -> None:
    """The factor's pool grows and is compacted in place in its reserved address space
    (``_compact``, ``compact_pool``), and the per-pose, per-edge and per-reading arrays grow
    in theirs (``_grow``): the same answers, bit for bit, as arrays copied into new ones at
    each growth (the path where no address space can be reserved)."""
    from hybridpgo.online import incremental

    s = _stream(11, 300, 0.8, 5)
    inplace = IncrementalExact(capacity=4)
    if inplace._pool_var is None:
        pytest.skip("no address space can be reserved here (not Linux, or a strict limit)")
    names = (*IncrementalExact._POSE_ARRAYS, *IncrementalExact._EDGE_ARRAYS,
             *IncrementalExact._GPS_ARRAYS)
    where = {name: getattr(inplace, name).ctypes.data for name in names}
    compactions = []
    compact = IncrementalExact._compact

    def counted(self: IncrementalExact, cap: int) -> None:
        compactions.append(self._pool_var is not None and cap <= self._pool_var.shape[0])
        compact(self, cap)

    monkeypatch.setattr(IncrementalExact, "_compact", counted)
    for k in range(s.frames):
        _feed(inplace, s, k)
        inplace.solve()
        _check_sorted_rows(inplace)
    assert len(compactions) >= 3 and all(compactions)  # in place, several times
    assert np.all(inplace._pool_var[inplace._pool_used[0]:] == 0)  # zeros past the segments
    assert inplace._cap_n >= 256 and inplace._cap_m >= 256  # grown from 4 poses, 8 edges
    for name, arrays in (("_diag", "_POSE_ARRAYS"), ("_parent", "_POSE_ARRAYS"),
                         ("_haa", "_EDGE_ARRAYS"), ("_inc_next", "_EDGE_ARRAYS")):
        base = inplace._bases[name]
        arr = getattr(inplace, name)
        assert base is not None and np.shares_memory(arr, base)  # views: grown in place
        assert arr.shape[0] == getattr(IncrementalExact, arrays)[name][3] * (
            inplace._cap_n if arrays == "_POSE_ARRAYS" else inplace._cap_m)
    assert all(getattr(inplace, name).ctypes.data == where[name] for name in names)  # unmoved
    assert np.all(inplace._parent[inplace._n:] == -1)  # the rows past the poses: their fill
    assert np.all(inplace._e_stamp[inplace._m:] == -1)
    monkeypatch.setattr(incremental, "reserved_only", lambda shape, dtype=np.float64: None)
    copied = IncrementalExact(capacity=4)
    assert copied._pool_var is None and not any(b is not None for b in copied._bases.values())
    for k in range(s.frames):
        _feed(copied, s, k)
        copied.solve()
    assert not all(compactions[-3:])  # the copies
    for a, b in zip(inplace.estimate(), copied.estimate(), strict=True):
        assert np.array_equal(a, b)
    for name in names:
        if name != "_col_start":  # the pool's layout (in place: the segments' old order)
            assert np.array_equal(getattr(inplace, name), getattr(copied, name)), name
    monkeypatch.undo()  # address space can be reserved again
    twin = __import__("copy").deepcopy(inplace)  # a copy holds plain arrays, not the reservation
    assert twin._pool_var is None and twin._row_blk.shape == inplace._row_blk.shape
    assert twin._bases == {} and not np.shares_memory(twin._diag, inplace._diag)
    for a, b in zip(twin.estimate(), inplace.estimate(), strict=True):
        assert np.array_equal(a, b)
    n = twin._n
    parent = twin._parent.copy()
    twin._grow_poses(2 * twin._cap_n)  # copied into a new reservation...
    assert np.array_equal(twin._parent[:n], parent[:n]) and np.all(twin._parent[n:] == -1)
    base = twin._bases["_parent"]
    assert base is not None and np.shares_memory(twin._parent, base)
    at = twin._parent.ctypes.data
    twin._grow_poses(2 * twin._cap_n)  # ...where it grows in place from then on
    assert twin._parent.ctypes.data == at and np.all(twin._parent[n:] == -1)


@pytest.mark.parametrize("count", [0, 1, 2, 5, 32, 33, 100])
def test_rows_are_sorted_by_position_as_a_plain_sort_does(count: int) -> None:
    """The symbolic phase's row sort (insertion sort up to 32 rows, argsort above) against
    Python's sort of the same segment; the rows around the segment stay as they were."""
    from hybridpgo.online._incremental_kernels import _sort_rows

    rng = np.random.default_rng(count)
    position = rng.permutation(1000).astype(np.int64)
    row_var = rng.permutation(1000)[:count + 10].astype(np.int64)
    before = row_var.copy()
    _sort_rows(row_var, 4, count, position)
    want = sorted(before[4: 4 + count].tolist(), key=lambda v: position[v])
    assert row_var[4: 4 + count].tolist() == want
    assert np.array_equal(row_var[:4], before[:4])
    assert np.array_equal(row_var[4 + count:], before[4 + count:])


@pytest.mark.parametrize(("width", "below"), [(1, 0), (1, 3), (3, 5), (8, 40), (20, 60)])
def test_a_panel_is_factored_as_numpys_cholesky(width: int, below: int) -> None:
    """The supernode panel's factorization (blocked; loops for small steps, BLAS with the
    diagonal block's inverse for large ones) against numpy's Cholesky factor of the whole
    matrix: the panel's columns of it; only the lower triangle of the panel's top is read."""
    from hybridpgo.online._incremental_kernels import _factor_panel, panel_scratch

    rng = np.random.default_rng(width * 100 + below)
    nc, nrow = 6 * width, 6 * (width + below)
    g = rng.standard_normal((nrow, nrow))
    h = g @ g.T + nrow * np.eye(nrow)
    want = np.linalg.cholesky(h)[:, :nc]
    panel = np.ascontiguousarray(h[:, :nc])
    panel[np.triu_indices(nc, 1)] = np.nan  # never read
    scratch = np.full(panel_scratch(nrow, nc), np.nan)  # written before it is read
    assert _factor_panel(panel, nc, scratch)
    got = panel.copy()
    got[np.triu_indices(nc, 1)] = 0.0
    assert np.abs(got - want).max() <= FLOAT64_IDENTITY * np.abs(want).max()
    h[0, 0] = -1.0
    assert not _factor_panel(np.ascontiguousarray(h[:, :nc]), nc, scratch)


def test_supernodes_group_the_columns_of_a_loop_closed_map() -> None:
    """On a drive with many loop closures the re-eliminated columns' rows nest over long runs:
    they are grouped into supernodes wider than a few columns (every cycle checked), and the
    step is still the batch Gauss-Newton step."""
    s = _stream(11, 120, 0.3, 0)
    inc = IncrementalExact(IncrementalConfig(relinearize_rho=0.0, relinearize_phi=0.0))
    widest = 0
    for k in range(s.frames):
        _feed(inc, s, k)
        inc.solve(max_cycles=1)
        widest = max(widest, _check_supernodes(inc))
    _check_gn_step(inc)
    assert widest > 8


def test_estimate_composes_poses_added_since_the_last_update() -> None:
    s = _stream(3, 10, 0.0, 0)
    inc = IncrementalExact()
    for k in range(5):
        _feed(inc, s, k)
    inc.solve()
    _feed(inc, s, 5)
    rot, trans = inc.estimate()
    assert np.allclose(rot[5], rot[4] @ s.odo_r[5], atol=1e-15)
    assert np.allclose(trans[5], rot[4] @ s.odo_t[5] + trans[4], atol=1e-15)


def test_bad_input_is_rejected_and_changes_nothing() -> None:
    inc = IncrementalExact()
    inc.add_poses(np.eye(3)[None], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="earlier pose"):
        inc.add_poses(np.eye(3)[None], np.zeros((1, 3)), [1])
    with pytest.raises(ValueError, match="finite"):
        inc.add_poses(np.eye(3)[None], np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match="already added"):
        inc.add_edges([0], [3], np.eye(3)[None], np.zeros((1, 3)), np.eye(6)[None])
    with pytest.raises(ValueError, match="already added"):
        inc.add_gps([2], np.zeros((1, 3)), np.eye(3)[None])
    inc.add_poses(np.eye(3)[None], np.ones((1, 3)))
    with pytest.raises(ValueError, match="not finite"):
        inc.add_edges([0], [1], np.eye(3)[None], np.full((1, 3), np.inf), np.eye(6)[None])
    with pytest.raises(ValueError, match="positive definite"):
        inc.add_edges([0], [1], np.eye(3)[None], np.zeros((1, 3)), -np.eye(6)[None])
    with pytest.raises(ValueError, match="positive definite"):
        inc.add_gps([1], np.zeros((1, 3)), np.diag([1.0, 0.0, 1.0])[None])
    assert (inc.num_poses, inc.num_edges, inc.num_gps) == (2, 0, 0)


def test_take_changes_lists_every_pose_whose_estimate_moved() -> None:
    s = _stream(11, 50, 0.5, 6)
    inc = IncrementalExact()
    before_r = np.zeros((0, 3, 3))
    before_t = np.zeros((0, 3))
    for k in range(s.frames):
        _feed(inc, s, k)
        inc.solve(budget_s=0.0 if k % 3 else None)  # some updates stop half-way
        rot, trans = inc.estimate()
        n0 = before_r.shape[0]
        changed = set(inc.take_changes().tolist())
        moved = ~(np.all(rot[:n0] == before_r, axis=(1, 2)) & np.all(trans[:n0] == before_t,
                                                                    axis=1))
        assert set(np.flatnonzero(moved).tolist()) <= changed
        assert set(range(n0, inc.covered[0])) <= changed  # integrated since: all listed
        before_r, before_t = rot[: inc.covered[0]], trans[: inc.covered[0]]


def test_fill_beyond_max_fill_is_an_error_not_a_huge_allocation(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A factor whose fill-in would pass ``max_fill`` blocks per pose and constraint raises
    SolverError before allocating (a map kept in a poor elimination order asked for 36 GiB);
    with room for it the same stream solves."""
    from hybridpgo.errors import SolverError
    from hybridpgo.online import incremental

    monkeypatch.setattr(incremental, "POOL_FLOOR", 64)
    s = _stream(seed=4, n=120, loop_p=0.8, gps_every=0)
    tight = IncrementalExact(IncrementalConfig(max_fill=1, reorder=False), capacity=4)
    roomy = IncrementalExact(IncrementalConfig(reorder=False), capacity=4)
    with pytest.raises(SolverError, match="max_fill=1"):
        for k in range(s.frames):
            _feed(tight, s, k)
            tight.solve()
    for k in range(s.frames):
        _feed(roomy, s, k)
        roomy.solve()
    assert np.all(np.isfinite(roomy.estimate()[1]))


@pytest.mark.parametrize("seed", [0, 3])
def test_a_pose_with_its_odometry_recomputes_only_the_columns_it_changes(seed: int) -> None:
    """A frame that brings only a pose and its odometry changes no other pose's step: with the
    worker's threshold (rounding) its cycle recomputes a few columns, where the exact back
    substitution recomputes every column below the re-eliminated ones; the steps of the two
    solvers stay the batch Gauss-Newton step's."""
    s = _stream(seed, 160, 0.3, 0)
    for k in range(80, 160):  # loop closures in the first half only
        s.loops[k] = []
    per_frame = {}
    for wildfire in (0.0, ROUNDING_WILDFIRE):
        inc = IncrementalExact(IncrementalConfig(relinearize_rho=0.1, relinearize_phi=0.1,
                                                 wildfire=wildfire))
        counts = []
        for k in range(s.frames):
            _feed(inc, s, k)
            before = inc.stats["recomputed"]
            inc.solve(polish=False)
            if k >= 100:
                counts.append(inc.stats["recomputed"] - before)
        _check_gn_step(inc)
        per_frame[wildfire] = np.array(counts)
    assert per_frame[ROUNDING_WILDFIRE].max() <= 4
    assert per_frame[0.0].min() > 5 * per_frame[ROUNDING_WILDFIRE].max()


def _rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(("seed", "n", "laps", "noise"), [(0, 1500, 2, 0.03), (8, 2500, 3, 0.02)])
def test_the_workers_options_converge_in_few_cycles_after_a_long_loop(
        seed: int, n: int, laps: int, noise: float) -> None:
    """Laps of a planar circle with noisy odometry, solved; then the last lap is tied to the
    first by 10 loop closures at once.  With the worker's options (the whole solution in every
    back substitution, but for what moved by rounding only) the solve that integrates them
    converges in at most 30 cycles (11 and 19 here) and ends at the batch optimum.  A back
    substitution stopped below 1e-4 leaves the steps of the columns it skips stale: 62 and 109
    cycles for these two (and 512 for one request of a city streamed back to back)."""
    from hybridpgo.online.worker import INCREMENTAL

    rng = np.random.default_rng(seed)
    turn = 2.0 * np.pi * laps / n
    odo_r = np.empty((n - 1, 3, 3))
    odo_t = np.empty((n - 1, 3))
    for i in range(n - 1):
        odo_r[i] = _rot_z(turn + noise * rng.standard_normal())
        odo_t[i] = np.array([1.0, 0.0, 0.0]) + 0.05 * rng.standard_normal(3) * [1.0, 1.0, 0.0]
    rot, trans = np.empty((n, 3, 3)), np.zeros((n, 3))
    rot[0] = np.eye(3)
    for i in range(n - 1):
        rot[i + 1] = rot[i] @ odo_r[i]
        trans[i + 1] = rot[i] @ odo_t[i] + trans[i]
    inc = IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
    inc.add_poses(rot, trans)
    inc.add_edges(np.arange(n - 1), np.arange(1, n), odo_r, odo_t,
                  np.tile(np.diag([100.0, 100, 100, 1e3, 1e3, 1e3]), (n - 1, 1, 1)))
    assert inc.solve()
    lap = n // laps
    b = np.arange(n - lap, n, lap // 10)
    k = b.shape[0]
    inc.add_edges(b - lap * (laps - 1), b, np.tile(np.eye(3), (k, 1, 1)), np.zeros((k, 3)),
                  np.tile(np.diag([10.0, 10, 10, 100, 100, 100]), (k, 1, 1)))
    c0 = inc.stats["cycles"]
    assert inc.solve()
    assert inc.stats["cycles"] - c0 <= 30
    rot, trans = inc.estimate()
    ref = solve_exact(_graph(inc, rot, trans), rot, trans,
                      GaussNewtonConfig(max_iterations=100, energy_tolerance=1e-15))
    assert abs(inc.energy() - ref.final_energy) <= INCREMENTAL_VS_BATCH * ref.final_energy


def test_edge_linearization_blocks_equal_the_full_products_to_the_bit() -> None:
    """``linearize_edges`` sums its products only over the Jacobians' rows that can be
    non-zero (as the batch assembly does); the same products over all six rows, in order, from
    the same Jacobians give every block, gradient and χ² equal to the bit."""
    from graphs import random_graph
    from ref_kernels import sum_in_order

    from hybridpgo.online._incremental_kernels import linearize_edges
    from hybridpgo.solvers._gn_kernels import edge_jacobians

    g = random_graph(np.random.default_rng(54), 12, 10)[0]
    m = g.num_edges
    rot, trans = np.array(g.rotations), np.array(g.translations)
    out = [np.zeros((m, 6, 6)) for _ in range(3)] + [np.zeros((m, 6)) for _ in range(2)]
    chi = np.zeros(m)
    ids = np.arange(m, dtype=np.int64)
    assert linearize_edges(ids, rot, trans, g.edge_nodes, g.edge_rotations,
                           g.edge_translations, g.edge_information, *out, chi) == -1
    e, ja, jb = np.empty((m, 6)), np.empty((m, 6, 6)), np.empty((m, 6, 6))
    edge_jacobians(rot, trans, g.edge_nodes, g.edge_rotations, g.edge_translations, e, ja, jb)
    r6 = range(6)
    for c in range(m):
        om = g.edge_information[c]
        oe = [sum_in_order(om[i, k] * e[c, k] for k in r6) for i in r6]
        wa = [[sum_in_order(om[i, k] * ja[c, k, q] for k in r6) for q in r6] for i in r6]
        wb = [[sum_in_order(om[i, k] * jb[c, k, q] for k in r6) for q in r6] for i in r6]
        for p in r6:
            assert out[3][c, p] == sum_in_order(ja[c, k, p] * oe[k] for k in r6)
            assert out[4][c, p] == sum_in_order(jb[c, k, p] * oe[k] for k in r6)
            for r in r6:
                assert out[0][c, p, r] == sum_in_order(ja[c, k, p] * wa[k][r] for k in r6)
                assert out[1][c, p, r] == sum_in_order(jb[c, k, p] * wb[k][r] for k in r6)
                assert out[2][c, p, r] == sum_in_order(ja[c, k, p] * wb[k][r] for k in r6)
        assert chi[c] == sum_in_order(e[c, i] * oe[i] for i in r6)
