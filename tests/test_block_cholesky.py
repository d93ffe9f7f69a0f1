"""Tests of the block sparse Cholesky (linalg/_block_cholesky.py) against dense linear algebra
and against CHOLMOD inside the exact solver."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from tolerances import FLOAT64_IDENTITY, OPTIMUM_RELATIVE

from hybridpgo.errors import SolverError
from hybridpgo.generate import generate_city
from hybridpgo.graph import PoseGraph
from hybridpgo.linalg import BlockCholesky
from hybridpgo.linalg._factor import NotPositiveDefinite, cholmod_available
from hybridpgo.solvers import GaussNewtonConfig, _normal
from hybridpgo.solvers import gauss_newton as gn


def _system(graph: PoseGraph, fixed: np.ndarray | None = None
            ) -> tuple[_normal.Pattern, np.ndarray, np.ndarray]:
    """Pattern (AMD order), lower-triangle values of H and g at the graph's estimate."""
    fx = gn.default_fixed_nodes(graph) if fixed is None else fixed
    pat = _normal.analyze(graph, fx, reorder=True)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    _normal.assemble(graph, pat, np.array(graph.rotations), np.array(graph.translations), data,
                     grad)
    return pat, data, grad


def _factorizer(pat: _normal.Pattern) -> BlockCholesky:
    return BlockCholesky(pat.num_vars, pat.block_ptr, pat.block_row, pat.indptr)


@pytest.mark.parametrize(("extra", "gps"), [(40, 0), (40, 5), (0, 0)])
def test_solve_matches_dense(extra: int, gps: int) -> None:
    """Random graphs with many loop edges (fill, updates between columns) and GPS."""
    graph, _, _ = random_graph(np.random.default_rng(extra + gps), n=60, extra=extra, gps=gps)
    pat, data, grad = _system(graph)
    f = _factorizer(pat)
    x = f.solve(data, -grad, check=True)
    h = _normal.lower_to_full(data, pat.lower_indices(), pat.indptr, pat.dim).toarray()
    expected = np.linalg.solve(h, -grad)
    np.testing.assert_allclose(x, expected, rtol=0, atol=FLOAT64_IDENTITY * np.linalg.cond(h)
                               * np.abs(expected).max())
    if extra:
        assert f.factor_blocks > pat.num_vars + pat.block_row.size  # the factor filled in


def test_second_factorization_reuses_the_analysis() -> None:
    graph, _, _ = random_graph(np.random.default_rng(3), n=40, extra=30)
    pat, data, grad = _system(graph)
    f = _factorizer(pat)
    f.factor(data)
    data2 = data * 3.0
    x = f.solve(data2, -grad)
    h = _normal.lower_to_full(data2, pat.lower_indices(), pat.indptr, pat.dim).toarray()
    expected = np.linalg.solve(h, -grad)
    np.testing.assert_allclose(x, expected, rtol=0, atol=FLOAT64_IDENTITY * np.linalg.cond(h)
                               * np.abs(expected).max())


def test_not_positive_definite_and_singular() -> None:
    graph, _, _ = random_graph(np.random.default_rng(4), n=20, extra=10)
    pat, data, _ = _system(graph)
    f = _factorizer(pat)
    bad = data.copy()
    bad[pat.diag_index[7]] = -1.0
    with pytest.raises(NotPositiveDefinite):
        f.factor(bad)
    # no gauge (nothing fixed, no GPS): H is singular, PSD to rounding
    pat0, data0, grad0 = _system(graph, fixed=np.zeros(0, np.int32))
    f0 = _factorizer(pat0)
    with pytest.raises(SolverError, match=r"singular|positive definite"):
        f0.solve(data0, -grad0, check=True)


def test_exact_solver_picks_it_on_a_city_and_agrees_with_cholmod() -> None:
    if not cholmod_available():
        pytest.skip("cvxopt not installed")
    graph = generate_city(seed=1, num_poses=600, nx=3, ny=3, gps_every=50).graph
    block = gn.solve_exact(graph, config=GaussNewtonConfig(method="lm"))
    chol = gn.solve_exact(graph, config=GaussNewtonConfig(method="lm", linear_solver="cholmod"))
    assert block.stats["linear_solver"] == "block"
    assert chol.stats["linear_solver"] == "cholmod"
    assert block.status.value == chol.status.value == "converged"
    assert abs(block.final_energy - chol.final_energy) <= OPTIMUM_RELATIVE * chol.final_energy
