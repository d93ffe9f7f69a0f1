"""Tests of the sparse factorization backends (linalg/_factor.py) against dense linear algebra."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import scipy.sparse as sp
from tolerances import FLOAT64_IDENTITY

from hybridpgo.errors import SolverError
from hybridpgo.linalg import _factor as _linear
from hybridpgo.linalg._factor import (
    NotPositiveDefinite,
    cholmod_available,
    fill_reducing_order,
    make_factorizer,
)

BACKENDS = [
    "splu",
    pytest.param("cholmod", marks=pytest.mark.skipif(not cholmod_available(),
                                                     reason="cvxopt not installed")),
]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@dataclass(frozen=True)
class Pattern:
    """A CSC pattern of the lower triangle, as the exact solver assembles it."""

    indptr: np.ndarray
    indices: np.ndarray
    diag_index: np.ndarray
    dim: int


def _pattern_of(a: np.ndarray) -> tuple[Pattern, np.ndarray]:
    """Pattern and values of the lower triangle of a dense symmetric matrix (every diagonal
    entry stored, first in its column)."""
    m = sp.csc_matrix(np.tril(a) + np.eye(a.shape[0]))  # the pattern holds the whole diagonal
    m.sort_indices()
    indptr = m.indptr.astype(np.int64)
    indices = m.indices.astype(np.int64)
    col = np.repeat(np.arange(a.shape[0]), np.diff(indptr))
    values = a[indices, col]
    assert np.array_equal(indices[indptr[:-1]], np.arange(a.shape[0]))
    return Pattern(indptr, indices, indptr[:-1], a.shape[0]), values


def _sparse_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    """A random sparse SPD matrix with a few dense rows (like loop closures)."""
    a = np.zeros((n, n))
    for _ in range(3 * n):
        i, j = rng.integers(0, n, 2)
        w = rng.normal()
        a[i, j] += w
        a[j, i] += w
    a[:, 3] += rng.normal(size=n)
    a[3, :] = a[:, 3]
    return a @ a.T + np.eye(n)


@pytest.mark.parametrize("backend", BACKENDS)
def test_solve_matches_dense(backend: str, rng: np.random.Generator) -> None:
    a = _sparse_spd(rng, 40)
    pat, values = _pattern_of(a)
    f = make_factorizer(pat, backend)
    assert f.name == backend
    for scale in (1.0, 2.0):  # the second numeric factorization reuses the symbolic analysis
        a = a * scale
        values = values * scale
        b = rng.normal(size=40)
        x = f.solve(values, b, check=True)
        np.testing.assert_allclose(a @ x, b, rtol=0, atol=FLOAT64_IDENTITY * np.abs(b).max()
                                   * np.linalg.cond(a))
    rhs = rng.normal(size=(40, 3))
    np.testing.assert_allclose(f.solve_factored(rhs), np.linalg.solve(a, rhs),
                               rtol=0, atol=FLOAT64_IDENTITY * np.linalg.cond(a)
                               * np.abs(np.linalg.solve(a, rhs)).max())


@pytest.mark.parametrize("backend", BACKENDS)
def test_inverse_blocks_match_dense_inverse(backend: str, rng: np.random.Generator,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    a = _sparse_spd(rng, 36)
    pat, values = _pattern_of(a)
    f = make_factorizer(pat, backend)
    f.factor(values)
    idx = np.array([[0, 1, 2], [33, 34, 35], [12, 5, 20], [3, 4, 7]])
    inv = np.linalg.inv(a)
    expected = np.stack([inv[np.ix_(r, r)] for r in idx])
    scale = np.abs(expected).max() * np.linalg.cond(a)
    np.testing.assert_allclose(f.inverse_blocks(idx), expected, rtol=0,
                               atol=FLOAT64_IDENTITY * scale)
    monkeypatch.setattr(_linear, "_RHS_BATCH_BYTES", 1)  # one block per batch
    np.testing.assert_allclose(f.inverse_blocks(idx), expected, rtol=0,
                               atol=FLOAT64_IDENTITY * scale)


@pytest.mark.parametrize("backend", BACKENDS)
def test_singular_matrix_raises_solver_error(backend: str) -> None:
    # Exactly singular (a free gauge): [[1, -1], [-1, 1]] + an unrelated SPD block.
    a = np.zeros((4, 4))
    a[:2, :2] = [[1.0, -1.0], [-1.0, 1.0]]
    a[2:, 2:] = [[2.0, 1.0], [1.0, 2.0]]
    pat, values = _pattern_of(a)
    with pytest.raises(SolverError, match="gauge"):
        make_factorizer(pat, backend).solve(values, np.ones(4), check=True)


@pytest.mark.parametrize("backend", BACKENDS)
def test_singular_to_rounding_raises_only_when_checked(backend: str) -> None:
    # Pivot 1e-14 of a diagonal entry: positive, so it factors, but below _SINGULAR_PIVOT.
    a = np.array([[1.0, 1.0, 0.0], [1.0, 1.0 + 1e-14, 0.0], [0.0, 0.0, 3.0]])
    pat, values = _pattern_of(a)
    f = make_factorizer(pat, backend)
    f.solve(values, np.ones(3))  # unchecked (LM): no error
    with pytest.raises(SolverError, match="singular to rounding"):
        f.solve(values, np.ones(3), check=True)


@pytest.mark.parametrize("use_cvxopt", [True, False])
def test_fill_reducing_order_is_a_permutation(use_cvxopt: bool, rng: np.random.Generator,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    if use_cvxopt and not cholmod_available():
        pytest.skip("cvxopt not installed")
    monkeypatch.setattr(_linear, "cvxopt_available", lambda: use_cvxopt)
    nv = 30
    r = rng.integers(-1, nv, 80)
    c = rng.integers(-1, nv, 80)
    rows = np.concatenate([r, c, np.arange(nv)])
    cols = np.concatenate([c, r, np.arange(nv)])
    new_pos = fill_reducing_order(nv, rows, cols)
    np.testing.assert_array_equal(np.sort(new_pos), np.arange(nv))
    # An arrow matrix (one node linked to all): minimum degree eliminates the hub last.
    hub = np.zeros(nv - 1, np.int64)
    spokes = np.arange(1, nv)
    arrow = fill_reducing_order(nv, np.concatenate([hub, spokes]),
                                 np.concatenate([spokes, hub]))
    assert arrow[0] == nv - 1


def test_cholmod_missing_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_linear, "cholmod_available", lambda: False)
    pat, _ = _pattern_of(np.eye(3))
    assert make_factorizer(pat, "auto").name == "splu"
    with pytest.raises(SolverError, match="pip install cvxopt"):
        make_factorizer(pat, "cholmod")


@pytest.mark.parametrize("backend", BACKENDS)
def test_pattern_must_be_the_lower_triangle(backend: str, rng: np.random.Generator) -> None:
    """Both triangles (the diagonal not first in its column) are refused, not misread."""
    a = _sparse_spd(rng, 20)
    m = sp.csc_matrix(a)
    m.sort_indices()
    indptr = m.indptr.astype(np.int64)
    full = Pattern(indptr, m.indices.astype(np.int64), indptr[:-1], 20)
    with pytest.raises(ValueError, match="lower triangle"):
        make_factorizer(full, backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_values_buffer_is_used_without_a_copy(backend: str, rng: np.random.Generator) -> None:
    """Values written into the factorizer's buffer are what it factors."""
    a = _sparse_spd(rng, 30)
    pat, values = _pattern_of(a)
    f = make_factorizer(pat, backend)
    buf = f.values_buffer()
    if buf is None:
        assert backend == "splu"
        return
    buf[:] = values
    b = rng.normal(size=30)
    x = f.solve(buf, b, check=True)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=0,
                               atol=FLOAT64_IDENTITY * np.linalg.cond(a) * np.abs(x).max())


@pytest.mark.skipif(not cholmod_available(), reason="cvxopt not installed")
def test_shared_patterns_copy_the_matrix_and_keep_values_apart(rng: np.random.Generator
                                                               ) -> None:
    """Inside shared_patterns, a second CHOLMOD factorizer with an equal pattern starts from a
    copy of the first one's matrix (not from triplets, not the same object); the two factor
    their own values, also interleaved; a different pattern is not shared; nothing is kept
    after the context."""
    from hybridpgo.linalg import shared_patterns

    a = _sparse_spd(rng, 40)
    c = _sparse_spd(rng, 40) + 5.0 * np.eye(40)
    pat, va = _pattern_of(a)
    assert np.all(a != 0) and np.all(c != 0)  # dense: c's values fit a's pattern
    built: list[int] = []  # calls of cvxopt's constructor from triplets
    import cvxopt

    original = cvxopt.spmatrix

    def counting(*args: object, **kwargs: object) -> object:
        built.append(1)
        return original(*args, **kwargs)

    cvxopt.spmatrix = counting  # type: ignore[assignment]
    try:
        with shared_patterns():
            f1 = make_factorizer(pat, "cholmod")
            f2 = make_factorizer(Pattern(pat.indptr.copy(), pat.indices.copy(),
                                         pat.diag_index.copy(), pat.dim), "cholmod")
            other, _ = _pattern_of(np.eye(40) + np.diag(np.ones(39), -1) * 0.1
                                   + np.diag(np.ones(39), 1) * 0.1)
            make_factorizer(other, "cholmod")
            assert _linear._PATTERNS.get() is not None
        assert _linear._PATTERNS.get() is None
        make_factorizer(pat, "cholmod")  # outside: built from triplets again
    finally:
        cvxopt.spmatrix = original  # type: ignore[assignment]
    assert len(built) == 3  # f1, the other pattern, the one outside; not f2
    assert f2._matrix is not f1._matrix
    assert list(f2._matrix.CCS[0]) == list(f1._matrix.CCS[0])
    assert list(f2._matrix.CCS[1]) == list(f1._matrix.CCS[1])
    vc = c[pat.indices, np.repeat(np.arange(40), np.diff(pat.indptr))]
    b = rng.normal(size=40)
    f1.factor(va)
    f2.factor(vc)  # interleaved: each keeps its own factor
    for f, m in ((f1, a), (f2, c)):
        x = f.solve_factored(b)
        np.testing.assert_allclose(m @ x, b, rtol=0,
                                   atol=FLOAT64_IDENTITY * np.abs(b).max() * np.linalg.cond(m))


@pytest.mark.skipif(not cholmod_available(), reason="cvxopt not installed")
def test_shared_patterns_share_one_analysis_and_each_solves_with_its_own_values(
        rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch) -> None:
    """Inside shared_patterns, factorizers of an equal pattern share one symbolic analysis
    (CHOLMOD's analysis runs once), and whichever factored last, each one's solves, pivot
    check and inverse blocks are those of its own last factored values (the other's
    factorization in between is undone by factoring them again, not the values buffer the
    caller may have changed since), against the dense inverse; one that never factored
    refuses to solve with the other's factorization."""
    import cvxopt.cholmod as cm

    from hybridpgo.linalg import shared_patterns

    n = 30
    a = _sparse_spd(rng, n)
    c = _sparse_spd(rng, n) + 3.0 * np.eye(n)
    singular = np.ones((n, n))  # positive semidefinite, rank 1: its factorization fails
    pat, va = _pattern_of(a)
    assert np.all(a != 0) and np.all(c != 0)  # dense: c's values fit a's pattern
    lower = (pat.indices, np.repeat(np.arange(n), np.diff(pat.indptr)))
    vc, vs = c[lower], singular[lower]
    analyses: list[int] = []
    numerics: list[int] = []
    symbolic, numeric = cm.symbolic, cm.numeric
    monkeypatch.setattr(cm, "symbolic", lambda *x, **k: analyses.append(1) or symbolic(*x, **k))
    monkeypatch.setattr(cm, "numeric", lambda *x, **k: numerics.append(1) or numeric(*x, **k))
    with shared_patterns():
        f1 = make_factorizer(pat, "cholmod")
        f2 = make_factorizer(Pattern(pat.indptr.copy(), pat.indices.copy(),
                                     pat.diag_index.copy(), pat.dim), "cholmod")
        f3 = make_factorizer(pat, "cholmod")
    assert len(analyses) == 1
    assert f1._factor is f2._factor is f3._factor
    b = rng.normal(size=(n, 2))
    blocks = np.arange(n).reshape(-1, 3)
    f1.factor(va)
    f1.values_buffer()[:] = 0.0  # the caller's buffer changes (LM restores its diagonal)
    f2.factor(vc)
    with pytest.raises(NotPositiveDefinite):
        f3.factor(vs)  # the shared factor object now holds a failed factorization
    assert len(numerics) == 3

    def solves(f: Any, m: np.ndarray) -> None:
        x = f.solve_factored(b)
        np.testing.assert_allclose(m @ x, b, rtol=0,
                                   atol=FLOAT64_IDENTITY * np.abs(b).max() * np.linalg.cond(m))

    def checks(f: Any, m: np.ndarray) -> None:
        f.check()

    def inverts(f: Any, m: np.ndarray) -> None:
        inv = np.linalg.inv(m)
        want = np.stack([inv[np.ix_(r, r)] for r in blocks])
        np.testing.assert_allclose(f.inverse_blocks(blocks), want, rtol=0,
                                   atol=FLOAT64_IDENTITY * np.abs(inv).max() * np.linalg.cond(m))

    # each switch of factorizer factors again, whichever method comes first
    for f, m, first in ((f1, a, inverts), (f2, c, checks), (f1, a, solves), (f2, c, inverts),
                        (f1, a, checks)):
        for use in (first, solves, checks, inverts):
            use(f, m)
    assert len(numerics) == 3 + 5
    with shared_patterns():
        g1 = make_factorizer(pat, "cholmod")
        g2 = make_factorizer(pat, "cholmod")
    g1.factor(va)
    with pytest.raises(SolverError, match="before its first factorization"):
        g2.solve_factored(b)


@pytest.mark.skipif(not cholmod_available(), reason="cvxopt not installed")
def test_shared_patterns_keep_larger_patterns_only_for_factorizers_made_to_share(
        rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch) -> None:
    """A pattern above SHARED_PATTERN_MAX is kept only from a factorizer made with
    ``share=True`` (up to SHARED_PATTERN_MAX_SHARED): a later factorizer of it then starts from
    the kept matrix; from one made without, each builds its own."""
    import cvxopt

    from hybridpgo.linalg import shared_patterns

    pat, _ = _pattern_of(_sparse_spd(rng, 40))
    entries = int(pat.indptr[-1])
    monkeypatch.setattr(_linear, "SHARED_PATTERN_MAX", entries - 1)
    monkeypatch.setattr(_linear, "SHARED_PATTERN_MAX_SHARED", entries)
    built: list[int] = []
    original = cvxopt.spmatrix
    monkeypatch.setattr(cvxopt, "spmatrix", lambda *a, **k: built.append(1) or original(*a, **k))
    with shared_patterns():
        make_factorizer(pat, "cholmod")
        make_factorizer(pat, "cholmod")
    assert len(built) == 2  # not kept: each from triplets
    with shared_patterns():
        first = make_factorizer(pat, "cholmod", share=True)
        second = make_factorizer(pat, "cholmod")
    assert len(built) == 3 and second._factor is first._factor  # kept, and shared
    monkeypatch.setattr(_linear, "SHARED_PATTERN_MAX_SHARED", entries - 1)
    with shared_patterns():
        make_factorizer(pat, "cholmod", share=True)
        make_factorizer(pat, "cholmod")
    assert len(built) == 5  # above both limits: not kept
