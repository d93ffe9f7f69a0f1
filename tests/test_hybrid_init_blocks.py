"""𝔅(H) initialization (``_init_blocks``) and the set-up around it (issue 11 item 6).

The dedicated kernel must give bit for bit what the sweep kernel with ``apply=False`` gave (the
set-up it replaced), for relative and GPS constraints, with and without a robust kernel, also
into an uninitialized ``contrib``; the naive twin of eq. 23/24 is tests/test_hybrid_twins.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo.solvers import HybridConfig
from hybridpgo.solvers.hybrid import HybridSolver, _init_blocks, _sweep
from hybridpgo.solvers.hybrid.problem import State
from hybridpgo.solvers.hybrid.solver import _whitening
from hybridpgo.tree import global_poses


@pytest.mark.parametrize(("gps", "robust"), [(0, "none"), (4, "none"), (4, "huber")])
def test_init_blocks_is_bit_identical_to_the_sweep_kernels_blocks(gps, robust):
    graph = random_graph(np.random.default_rng(5), 14, 10, gps=gps)[0]
    solver = HybridSolver(graph, HybridConfig(robust=robust, robust_scale=0.5))
    solver.step(solver.tree.sweep_order, tau=0.6)  # away from the tree start
    prob, st = solver.problem, solver.state
    old = State(st.rot, st.trans, np.full_like(st.bdiag, 7.0), np.full_like(st.contrib, 7.0))
    _sweep.init_blocks(prob, old, solver.dmax)  # the former set-up: the sweep, apply=False
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
