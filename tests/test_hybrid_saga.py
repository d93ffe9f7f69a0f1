"""``update="saga"`` (:mod:`hybridpgo.solvers.hybrid._aggregate`): the aggregated-force step
against its dense NumPy twin, the fixed-point property at the optimum, and the options."""

from __future__ import annotations

import dataclasses

import naive
import numpy as np
import pytest
import scipy.linalg
from graphs import random_graph
from tolerances import SAME_EQUATION

from hybridpgo.solvers import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, _aggregate, _dense
from hybridpgo.solvers.hybrid.problem import new_workspace

#: A sweep at a settled optimum may move a pose by at most this (relative): only rounding.
FIXED_POINT = 1e-9
#: The paper's sweep at the same optimum moves poses by more than this (it is no fixed point).
PAPER_MOVES = 1e-6


def _graph(seed: int, gps: int = 0):  # type: ignore[no-untyped-def]
    graph, _, _ = random_graph(np.random.default_rng(seed), n=12, extra=9, gps=gps,
                               rot_scale=0.4, noise=0.1)
    return graph


@pytest.mark.parametrize("kr", [6, 3])
def test_woodbury_with_general_rhs_solves_the_hybrid_system(kr: int) -> None:
    rng = np.random.default_rng(kr)
    d = 5
    jac = np.zeros((d, 6, 6))
    jac[:, :kr] = rng.normal(size=(d, kr, 6))
    lfac = np.empty((d, 6, 6))
    blocks = []
    for k in range(d):
        a = rng.normal(size=(6, 6))
        blocks.append(a @ a.T + 0.1 * np.eye(6))
        lfac[k] = np.linalg.cholesky(blocks[k])
    b = rng.normal(size=(d, 6))
    x = np.empty((d, 6))
    _aggregate.woodbury_solve_rhs(d, kr, jac, lfac, b, np.empty((d, 6, 6)), x)
    jd = np.hstack(list(jac[:, :kr]))
    h = jd.T @ jd + scipy.linalg.block_diag(*blocks)
    want = np.linalg.solve(h, b.reshape(-1)).reshape(d, 6)
    assert np.abs(x - want).max() <= SAME_EQUATION * np.abs(want).max()


def test_aggregated_updates_match_the_dense_twin() -> None:
    """Two sweeps' worth of updates, each compared with the twin (step, memory, memory sums)."""
    graph = _graph(3)
    cfg = HybridConfig(init="tree", update="saga", memory_rate=0.3)
    solver = HybridSolver(graph, cfg)
    prob, state, mem = solver.problem, solver.state, solver.memory
    tree = solver.tree
    wk = new_workspace(solver.dmax)
    g = np.empty((solver.dmax, 6))
    b = np.empty((solver.dmax, 6))
    checked = 0
    for _ in range(2):
        for c in tree.sweep_order:
            c = int(c)
            lo, hi = int(tree.path_ptr[c]), int(tree.path_ptr[c + 1])
            nodes = tree.path_node[lo:hi]
            bmo = state.bdiag[nodes] - state.contrib[lo:hi]
            m_old = mem.grad[lo:hi].copy()
            msum_old = mem.gsum[nodes].copy()
            _aggregate.relax_aggregated(prob, state, mem, wk, g, b, c, 0.5, cfg.damping,
                                        cfg.memory_rate)
            d = hi - lo
            jac = wk.jac[:d, :6].copy()  # the linearization itself is twinned elsewhere
            scale = naive.own_scale(jac)
            x, m_new, msum_new = naive.aggregated_step(
                jac, wk.r.copy(), bmo, scale, cfg.damping, _dense.TINY, m_old, msum_old,
                prob.path_count[nodes], cfg.memory_rate)
            tol = SAME_EQUATION * max(np.abs(x).max(), 1e-300)
            assert np.abs(wk.x[:d] - x).max() <= tol, c
            np.testing.assert_allclose(mem.grad[lo:hi], m_new, rtol=0,
                                       atol=1e-12 * (1 + np.abs(m_new).max()))
            np.testing.assert_allclose(mem.gsum[nodes], msum_new, rtol=0,
                                       atol=1e-12 * (1 + np.abs(msum_new).max()))
            checked += 1
    assert checked == 2 * tree.num_constraints


def test_a_settled_optimum_is_a_fixed_point_of_the_saga_sweep() -> None:
    """No GPS: GPS readings are still relaxed in the paper's batches, without memory."""
    graph = _graph(11)
    opt = solve_exact(graph, config=GaussNewtonConfig(  # converged to rounding
        method="gn", energy_tolerance=0.0, step_tolerance=1e-15, max_iterations=20))
    at_opt = dataclasses.replace(graph, rotations=opt.rotations,
                                 translations=opt.translations)
    moved = {}
    for update in ("saga", "paper"):
        solver = HybridSolver(at_opt, HybridConfig(init="file", update=update))
        if update == "saga":
            solver.init_memory()
        r0, t0 = solver.poses()
        solver.run(1)
        r1, t1 = solver.poses()
        moved[update] = max(np.abs(t1 - t0).max() / (1 + np.abs(t0).max()),
                            np.abs(r1 - r0).max())
    assert moved["saga"] <= FIXED_POINT
    assert moved["paper"] > PAPER_MOVES


def test_saga_sweeps_reduce_the_energy_below_the_paper_sweeps() -> None:
    graph = _graph(5)
    energies = {}
    for update in ("paper", "saga"):
        solver = HybridSolver(graph, HybridConfig(init="tree", update=update))
        energies[update] = solver.run(30).energy_history[-1]
    opt = solve_exact(graph).energy_history[-1]
    assert energies["saga"] - opt < energies["paper"] - opt


@pytest.mark.parametrize("options", [
    {"update": "sag"}, {"memory_rate": 0.0}, {"memory_rate": 1.5}, {"memory_rate": True},
    {"update": "saga", "step": "givens"}, {"update": "saga", "dmax": 4},
])
def test_bad_saga_options_are_refused(options: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        HybridConfig(**options)  # type: ignore[arg-type]


def test_init_memory_needs_saga() -> None:
    solver = HybridSolver(_graph(1), HybridConfig(init="tree"))
    with pytest.raises(ValueError, match="saga"):
        solver.init_memory()


def test_saga_refuses_gps() -> None:
    """Measured to diverge with GPS (benchmarks/sag.py): refused with a clear message."""
    with pytest.raises(ValueError, match="does not support GPS"):
        HybridSolver(_graph(3, gps=2), HybridConfig(update="saga"))
