"""Selected inversion (linalg/_selinv.py): the diagonal blocks (and the blocks on the factor's
pattern) of A^-1 against the dense inverse, on random sparse SPD matrices of block sizes 1, 2,
3 and 6, and through the block Cholesky of real pose-graph normal equations."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st
from tolerances import FLOAT64_IDENTITY

from hybridpgo.errors import SolverError
from hybridpgo.linalg import BlockCholesky
from hybridpgo.linalg._selinv import inverse_diagonal_blocks
from hybridpgo.solvers import _normal
from hybridpgo.solvers import gauss_newton as gn


def _block_symbolic(nb: int, pairs: set[tuple[int, int]]) -> list[list[int]]:
    """Rows below the diagonal of each block column of L (plain Python: column j's rows join
    its parent's, the smallest of them)."""
    struct: list[set[int]] = [set() for _ in range(nb)]
    for r, c in pairs:
        struct[min(r, c)].add(max(r, c))
    for j in range(nb):
        if struct[j]:
            rows = sorted(struct[j])
            struct[rows[0]].update(rows[1:])
    return [sorted(s) for s in struct]


def _random_factor(seed: int, nb: int, b: int, density: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random block-sparse SPD A and its Cholesky factor in the kernel's layout:
    ``(A, l_ptr, l_row, diag, off)``."""
    rng = np.random.default_rng(seed)
    pairs = {(int(r), int(c)) for r in range(nb) for c in range(r) if rng.random() < density}
    a = np.zeros((nb * b, nb * b))
    for r, c in pairs:
        blk = rng.normal(size=(b, b))
        a[r * b:(r + 1) * b, c * b:(c + 1) * b] = blk
        a[c * b:(c + 1) * b, r * b:(r + 1) * b] = blk.T
    q = rng.normal(size=(nb, b, b))
    for j in range(nb):  # SPD: a random SPD diagonal block plus the row sums (dominance)
        s = slice(j * b, (j + 1) * b)
        a[s, s] = q[j] @ q[j].T + (np.abs(a[s]).sum() + 1.0) * np.eye(b)
    low = np.linalg.cholesky(a)
    struct = _block_symbolic(nb, pairs)
    l_ptr = np.zeros(nb + 1, np.int64)
    l_ptr[1:] = np.cumsum([len(s) for s in struct])
    l_row = np.array([r for s in struct for r in s], np.int64)
    diag = np.stack([low[j * b:(j + 1) * b, j * b:(j + 1) * b] for j in range(nb)])
    off = np.zeros((l_row.shape[0], b, b))
    for j, rows in enumerate(struct):
        for k, r in enumerate(rows):
            off[l_ptr[j] + k] = low[r * b:(r + 1) * b, j * b:(j + 1) * b]
    # everything outside the symbolic pattern is exactly zero (the pattern is complete)
    mask = np.zeros((nb, nb), bool)
    mask[np.arange(nb), np.arange(nb)] = True
    for j, rows in enumerate(struct):
        mask[rows, j] = True
    assert not np.any(low.reshape(nb, b, nb, b).transpose(0, 2, 1, 3)[~mask])
    return a, l_ptr, l_row, diag, off


@settings(deadline=None, max_examples=40)
@given(seed=st.integers(0, 2**32 - 1), nb=st.integers(1, 14), b=st.sampled_from([1, 2, 3, 6]),
       density=st.floats(0.0, 0.6))
def test_matches_the_dense_inverse(seed: int, nb: int, b: int, density: float) -> None:
    a, l_ptr, l_row, diag, off = _random_factor(seed, nb, b, density)
    inv = np.linalg.inv(a)
    scale = FLOAT64_IDENTITY * np.linalg.cond(a) * np.abs(inv).max()
    diag0, off0 = diag.copy(), off.copy()
    z = inverse_diagonal_blocks(l_ptr, l_row, diag, off)
    np.testing.assert_array_equal(diag, diag0)  # inputs untouched without overwrite
    np.testing.assert_array_equal(off, off0)
    expected = np.stack([inv[j * b:(j + 1) * b, j * b:(j + 1) * b] for j in range(nb)])
    np.testing.assert_allclose(z, expected, rtol=0, atol=scale)
    np.testing.assert_array_equal(z, z.transpose(0, 2, 1))
    # in place: the result is bit-identical, and off holds A^-1 on L's pattern
    z2 = inverse_diagonal_blocks(l_ptr, l_row, diag, off, overwrite=True)
    assert z2 is diag
    np.testing.assert_array_equal(z2, z)
    for j in range(nb):
        for q in range(l_ptr[j], l_ptr[j + 1]):
            r = l_row[q]
            np.testing.assert_allclose(off[q], inv[r * b:(r + 1) * b, j * b:(j + 1) * b],
                                       rtol=0, atol=scale)


def test_a_pattern_that_is_not_a_factor_is_an_error() -> None:
    """Column 0 reaches rows 1 and 2, but column 1 lacks row 2 (the fill is missing)."""
    l_ptr = np.array([0, 2, 2, 2])
    l_row = np.array([1, 2])
    diag = np.tile(np.eye(2), (3, 1, 1))
    off = np.full((2, 2, 2), 0.1)
    with pytest.raises(SolverError, match="block column 0"):
        inverse_diagonal_blocks(l_ptr, l_row, diag, off)
    with pytest.raises(ValueError, match="need l_ptr"):
        inverse_diagonal_blocks(l_ptr[:-1], l_row, diag, off)


def test_empty() -> None:
    out = inverse_diagonal_blocks(np.zeros(1, np.int64), np.zeros(0, np.int64),
                                  np.zeros((0, 6, 6)), np.zeros((0, 6, 6)))
    assert out.shape == (0, 6, 6)


@pytest.mark.parametrize(("extra", "gps"), [(0, 0), (25, 0), (25, 4)])
def test_block_cholesky_of_pose_graph_normal_equations(extra: int, gps: int) -> None:
    """H of random graphs (AMD order, fill from the loop edges, GPS as the gauge)."""
    graph, _, _ = random_graph(np.random.default_rng(10 + extra + gps), n=40, extra=extra,
                               gps=gps)
    pat = _normal.analyze(graph, gn.default_fixed_nodes(graph), reorder=True)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    _normal.assemble(graph, pat, np.array(graph.rotations), np.array(graph.translations), data,
                     grad)
    h = _normal.lower_to_full(data, pat.lower_indices(), pat.indptr, pat.dim).toarray()
    inv = np.linalg.inv(h)
    expected = np.stack([inv[6 * j:6 * j + 6, 6 * j:6 * j + 6] for j in range(pat.num_vars)])
    f = BlockCholesky(pat.num_vars, pat.block_ptr, pat.block_row, pat.indptr)
    with pytest.raises(SolverError, match="call factor"):
        f.inverse_diagonal_blocks()
    f.factor(data)
    scale = FLOAT64_IDENTITY * np.linalg.cond(h) * np.abs(expected).max()
    np.testing.assert_allclose(f.inverse_diagonal_blocks(), expected, rtol=0, atol=scale)
    x = f.solve_factored(-grad)  # the factor is intact without overwrite
    np.testing.assert_allclose(x, np.linalg.solve(h, -grad), rtol=0,
                               atol=scale / np.abs(expected).max() * np.abs(x).max())
    np.testing.assert_allclose(f.inverse_diagonal_blocks(overwrite=True), expected, rtol=0,
                               atol=scale)
    with pytest.raises(SolverError, match="call factor"):  # consumed
        f.solve_factored(-grad)
