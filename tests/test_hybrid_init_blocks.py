"""𝔅(H) initialization (``_init_blocks``) and the set-up around it.

The dedicated kernel must give bit for bit what the sweep kernel with ``apply=False`` gave (the
set-up it replaced), for relative and GPS constraints, with and without a robust kernel, also
into an uninitialized ``contrib``; the naive twin of eq. 23/24 is tests/test_hybrid_twins.py.
"""

from __future__ import annotations

import mmap
import sys

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo._memory import can_overcommit, map_only, mapped_zeros
from hybridpgo.solvers import HybridConfig
from hybridpgo.solvers.hybrid import HybridSolver, _init_blocks, _sweep
from hybridpgo.solvers.hybrid.problem import State
from hybridpgo.solvers.hybrid.solver import _whitening
from hybridpgo.tree import global_poses


@pytest.mark.parametrize("interpolation", [False, True])
@pytest.mark.parametrize(("gps", "robust"), [(0, "none"), (4, "none"), (4, "huber")])
def test_init_blocks_is_bit_identical_to_the_sweep_kernels_blocks(gps, robust, interpolation):
    """The own kernel (large graphs) against every sweep variant with ``apply=False`` (the
    small graphs' set-up, by the variant the solve uses)."""
    graph = random_graph(np.random.default_rng(5), 14, 10, gps=gps)[0]
    solver = HybridSolver(graph, HybridConfig(robust=robust, robust_scale=0.5))
    solver.step(solver.tree.sweep_order, tau=0.6)  # away from the tree start
    prob, st = solver.problem, solver.state
    old = State(st.rot, st.trans, np.full_like(st.bdiag, 7.0), np.full_like(st.contrib, 7.0))
    _sweep.init_blocks(prob, old, solver.scratch, gps > 0, interpolation)
    new = State(st.rot.copy(), st.trans.copy(), np.full_like(st.bdiag, np.nan),
                np.full_like(st.contrib, np.nan))  # garbage in: every entry is overwritten
    _init_blocks.init_blocks(prob, new, solver.dmax)
    assert np.array_equal(new.bdiag, old.bdiag)
    assert np.array_equal(new.contrib, old.contrib)
    assert np.array_equal(new.rot, st.rot) and np.array_equal(new.trans, st.trans)  # no step


def test_whitening_of_diagonal_and_full_informations_is_lapacks():
    rng = np.random.default_rng(6)
    diag = np.zeros((9, 6, 6))
    diag[:, range(6), range(6)] = rng.uniform(0.1, 1e6, size=(9, 6))
    x = rng.normal(size=(9, 6, 6))
    full = x @ np.swapaxes(x, 1, 2) + np.eye(6)
    for info in (diag, full, diag[:, :3, :3].copy()):
        k = info.shape[1]
        expected = np.swapaxes(np.linalg.cholesky(info), 1, 2)
        assert np.array_equal(_whitening(info, k), expected)
    bad = diag.copy()
    bad[4, 2, 2] = 0.0
    with pytest.raises(np.linalg.LinAlgError):
        _whitening(bad, 6)


def test_run_returns_the_poses_its_last_energy_was_computed_at():
    graph = random_graph(np.random.default_rng(7), 12, 8, gps=3)[0]
    seen = []
    solver = HybridSolver(graph, HybridConfig(sweeps=2))
    res = solver.run(iterate=lambda p, r, t: seen.append((r.copy(), t.copy())))
    rot, trans = global_poses(solver.tree, solver.state.rot, solver.state.trans)
    assert np.array_equal(res.rotations, rot) and np.array_equal(res.translations, trans)
    assert np.array_equal(seen[-1][0], rot) and np.array_equal(seen[-1][1], trans)
    assert len(seen) == 3


def test_the_set_up_kernel_is_chosen_by_size_and_gives_the_same_solve(monkeypatch):
    """Above ``INIT_KERNEL_ENTRIES`` path entries the own kernel builds 𝔅(H), below the sweep
    kernel: the same blocks, so the same sweeps, bit for bit."""
    from hybridpgo.solvers.hybrid import solver as hs

    graph = random_graph(np.random.default_rng(8), 16, 12, gps=3)[0]
    calls = []
    own = _init_blocks.init_blocks
    monkeypatch.setattr(_init_blocks, "init_blocks", lambda *a: (calls.append(1), own(*a)))
    results = []
    for threshold in (10**9, 0):
        monkeypatch.setattr(hs, "INIT_KERNEL_ENTRIES", threshold)
        solver = HybridSolver(graph, HybridConfig(sweeps=3))
        results.append(solver.run())
        results.append(calls.copy())
    small, small_calls, large, large_calls = results
    assert small_calls == [] and large_calls  # the own kernel only for the "large" graph
    assert np.array_equal(small.rotations, large.rotations)
    assert np.array_equal(small.translations, large.translations)


def _mapping(a: np.ndarray) -> object:
    """The object at the root of ``a``'s chain of bases."""
    while isinstance(a.base, np.ndarray):
        a = a.base
    return a.base.obj if isinstance(a.base, memoryview) else a.base


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="anonymous maps: Linux")
def test_the_blocks_live_on_an_anonymous_map_not_numpys_huge_pages() -> None:
    """𝔅(H) and every constraint's blocks (GBs at 1M poses) are views of anonymous memory
    maps (:mod:`hybridpgo._memory`), not NumPy allocations, which ask for huge pages."""
    graph = random_graph(np.random.default_rng(6), 400, 300)[0]
    st = HybridSolver(graph).state
    assert st.contrib.nbytes >= mmap.PAGESIZE
    for a in (st.bdiag, st.contrib):
        assert isinstance(_mapping(a), mmap.mmap)
        assert a.flags.writeable and a.flags.c_contiguous


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux's overcommit")
@pytest.mark.parametrize("case", ["strict", "limited"])
def test_no_reservation_where_it_would_not_cost_address_space_only(monkeypatch, case) -> None:
    """``overcommit=True`` maps only where ``MAP_NORESERVE`` costs address space only: under
    the strict overcommit policy (2) or an address-space limit nothing is mapped (the callers
    fall back to plain arrays of their capacity); a committed map is made as usual."""
    import builtins
    import io
    import resource

    if case == "strict":
        real_open = builtins.open

        def strict_open(path, *args, **kwargs):  # type: ignore[no-untyped-def]
            if str(path) == "/proc/sys/vm/overcommit_memory":
                return io.StringIO("2\n")
            return real_open(path, *args, **kwargs)

        monkeypatch.setattr(builtins, "open", strict_open)
    else:
        monkeypatch.setattr(resource, "getrlimit", lambda what: (1 << 34, 1 << 34))
    can_overcommit.cache_clear()
    try:
        assert not can_overcommit()
        assert map_only((1 << 16,), np.uint8, overcommit=True) is None
        assert map_only((1 << 16,), np.uint8, overcommit=False) is not None
    finally:
        monkeypatch.undo()
        can_overcommit.cache_clear()


def test_the_online_store_starts_small_where_nothing_can_be_reserved(monkeypatch) -> None:
    """Where a reservation would not cost address space only, the online store starts at
    1 024 poses (its arrays then double when full) instead of reserving a million."""
    from hybridpgo import _memory
    from hybridpgo.online.store import RESERVE_POSES, MapStore

    big = MapStore(None)
    assert big.cap_n == (RESERVE_POSES if _memory.can_overcommit() else 1024) + 2
    monkeypatch.setattr(_memory, "can_overcommit", lambda: False)
    small = MapStore(None)
    assert small.cap_n == 1024 + 2 and small.cap_pe == 16 * 1024


@pytest.mark.parametrize("overcommit", [False, True])
def test_mapped_zeros_are_zero_writable_and_fall_back_to_numpy(monkeypatch, overcommit) -> None:
    a, mapped = mapped_zeros((300, 6, 6), np.float64, overcommit)
    assert a.shape == (300, 6, 6) and a.dtype == np.float64 and not a.any()
    assert mapped == (sys.platform.startswith("linux") and (not overcommit or can_overcommit()))
    a[-1] = 2.0
    assert a.sum() == 72.0

    def refuse(*_args: object, **_kwargs: object) -> None:
        raise OSError("no map")

    monkeypatch.setattr(mmap, "mmap", refuse)
    b, mapped = mapped_zeros((300, 6, 6), np.int64, overcommit)
    assert not mapped and b.dtype == np.int64 and b.shape == (300, 6, 6) and not b.any()
    tiny, mapped = mapped_zeros((3,), np.float64, overcommit)  # below a page: NumPy's
    assert not mapped and tiny.shape == (3,)
