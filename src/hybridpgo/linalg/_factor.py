"""Sparse symmetric factorizations for the exact solver: analyze once, factor per iteration.

Two backends factor a symmetric positive definite matrix ``A`` given as the values of a fixed CSC
pattern of its *lower triangle*, rows increasing within each column (so each column starts with
its diagonal entry), as :class:`hybridpgo.solvers.gauss_newton` assembles it:

``_Cholmod`` (``linear_solver="cholmod"``)
    SuiteSparse CHOLMOD through :mod:`cvxopt.cholmod` (a runtime dependency: manylinux, macOS and
    Windows wheels bundle CHOLMOD and OpenBLAS, nothing to compile).  Supernodal ``L L^T``; the
    symbolic analysis is done once in the constructor, each :meth:`factor` is a numeric
    factorization into the same factor object.  Measured on paris2 with GPS (251 742 unknowns,
    5.5 M nonzeros, 2 cores shared with other jobs): symbolic 0.27-0.48 s once, numeric
    0.5-1.0 s per iteration (``python -m benchmarks --only linear``).
    Memory per stored entry: the values buffer the caller assembles into (8 bytes,
    :meth:`_Cholmod.values_buffer`), cvxopt's copy of the matrix (16), and during each numeric
    factorization cvxopt's packed copy and CHOLMOD's transposed one (16 + 16, freed after), plus
    the factor L.
``_SuperLU`` (``linear_solver="splu"``)
    SciPy's SuperLU on the pre-ordered matrix (natural column order, symmetric mode, diagonal
    pivots).  A full LU (no BLAS-3 supernodes), 2-3x slower than CHOLMOD, but it no longer
    collapses on dense loop closures now that the pre-ordering is AMD: paris2 with GPS 1.3-2.1 s
    per factorization, against > 600 s (time limit) with SuperLU's block MMD ordering, the old
    default (108 s on a quiet machine in the issue's measurement).

The fill-reducing ordering (:func:`fill_reducing_order`) is computed once per solve on the 6x6
*block* graph (36x smaller than A): AMD from :mod:`cvxopt.amd` (15 ms on paris2's 42k blocks), or
SuperLU's MMD when cvxopt is missing.  The exact solver permutes its variables with it, so both
backends factor a matrix that is already in fill-reducing order and take it as given.

Both backends also give the pivots (for the singular-system check of Gauss-Newton without a
gauge, :func:`check_pivots`) and selected diagonal blocks of ``A^-1`` (:meth:`inverse_blocks`,
used by :mod:`hybridpgo.covariance`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import SolverError
from ..graph import FloatArray

Int64Array = npt.NDArray[np.int64]

#: A pivot of the factorization below this fraction of its diagonal entry of A means A is
#: singular to rounding (measured: 1e-16..5e-16 without a gauge, >= 4e-3 with one).
_SINGULAR_PIVOT = 1e-12
#: :meth:`inverse_blocks` solves for at most this many bytes of right-hand sides at once.
_RHS_BATCH_BYTES = 64 * 2**20


class SymmetricPattern(Protocol):
    """A fixed CSC pattern of the lower triangle of a symmetric (dim, dim) matrix, rows
    increasing within each column, every diagonal entry stored (first in its column)."""

    @property
    def indptr(self) -> Int64Array: ...
    @property
    def indices(self) -> Int64Array: ...
    @property
    def diag_index(self) -> Int64Array:
        """(dim,) position of each diagonal entry in the values array (``indptr[:-1]``)."""
        ...
    @property
    def dim(self) -> int: ...


def _check_lower(pattern: SymmetricPattern) -> None:
    """Cheap check of the layout: each column's first row is its diagonal."""
    ptr = pattern.indptr
    if ptr.shape[0] != pattern.dim + 1 or (pattern.dim and not (
            np.all(ptr[1:] > ptr[:-1])
            and np.array_equal(pattern.indices[ptr[:-1]], np.arange(pattern.dim)))):
        raise ValueError("the pattern must be the lower triangle with every diagonal entry "
                         "stored first in its column")


# --------------------------------------------------------------------------- ordering
def cvxopt_available() -> bool:
    try:
        import cvxopt.amd
        import cvxopt.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


def cholmod_available() -> bool:
    """True when CHOLMOD (through cvxopt) can be imported."""
    return cvxopt_available()


def fill_reducing_order(nv: int, rows: Int64Array, cols: Int64Array) -> Int64Array:
    """New position of every variable: a fill-reducing ordering of the block graph.

    ``rows, cols`` list the (block row, block column) of every nonzero block; entries < 0 are
    ignored (fixed nodes).  AMD (:func:`cvxopt.amd.order`) when cvxopt is importable, else
    SuperLU's multiple minimum degree on a diagonally dominant stand-in matrix (its column
    permutation ``perm_c`` maps old -> new position).
    """
    if nv <= 2:
        return np.arange(nv, dtype=np.int64)
    keep = (rows >= 0) & (cols >= 0)
    r = rows[keep]
    c = cols[keep]
    off = r != c
    if cvxopt_available():
        import cvxopt
        import cvxopt.amd

        lower = r > c
        ii = np.concatenate([r[lower], np.arange(nv)])
        jj = np.concatenate([c[lower], np.arange(nv)])
        pattern = cvxopt.spmatrix(1.0, cvxopt.matrix(ii, tc="i"), cvxopt.matrix(jj, tc="i"),
                                  (nv, nv))
        order = np.asarray(cvxopt.amd.order(pattern, "L"), dtype=np.int64).ravel()
        new_pos = np.empty(nv, np.int64)
        new_pos[order] = np.arange(nv)
        return new_pos
    deg = np.bincount(r[off], minlength=nv).astype(np.float64)
    a = sp.coo_matrix(
        (np.concatenate([-np.ones(int(off.sum())), deg + 1.0]),
         (np.concatenate([r[off], np.arange(nv)]), np.concatenate([c[off], np.arange(nv)]))),
        shape=(nv, nv),
    ).tocsc()
    lu = spla.splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                   options={"SymmetricMode": True})
    return np.asarray(lu.perm_c, dtype=np.int64)


# --------------------------------------------------------------------------- checks
def check_pivots(pivots: FloatArray, diagonal: FloatArray) -> None:
    """Raise SolverError when a pivot is tiny against its diagonal entry (A singular)."""
    ratio = pivots / np.maximum(diagonal, np.finfo(np.float64).tiny)
    if not np.all(ratio >= _SINGULAR_PIVOT):
        raise SolverError(
            f"the normal equations are singular to rounding (smallest pivot / diagonal = "
            f"{float(np.nanmin(ratio)):.2g}): the gauge is not fixed, or some pose is not "
            "determined by its constraints; fix a pose, or use method='lm'")


class NotPositiveDefinite(SolverError):
    """The factorization met a non-positive pivot."""


def not_positive_definite(detail: str) -> SolverError:
    return NotPositiveDefinite(
        f"the normal equations are not positive definite ({detail}): the gauge is not fixed, "
        "or some pose is not determined by its constraints; fix a pose, or use method='lm'")


def _unit_batches(dim: int, block_index: Int64Array) -> Iterator[tuple[int, int]]:
    """Ranges [lo, hi) of rows of ``block_index`` whose unit right-hand sides fit one batch."""
    k, b = block_index.shape
    per = max(1, _RHS_BATCH_BYTES // (8 * max(dim, 1) * max(b, 1)))
    for lo in range(0, k, per):
        yield lo, min(k, lo + per)


# --------------------------------------------------------------------------- the interface
class Factorizer:
    """What every factorizer shares: analyze once (in the constructor), then per matrix
    :meth:`factor` its values, :meth:`check` it (optional), :meth:`solve_factored`; :meth:`solve`
    does the three."""

    def factor(self, values: FloatArray) -> None:
        """Numeric factorization of A with the given values (in the pattern's order)."""
        raise NotImplementedError

    def check(self) -> None:
        """Raise SolverError when the last factored matrix is singular to rounding."""
        raise NotImplementedError

    def solve_factored(self, rhs: FloatArray) -> FloatArray:
        """``A^-1 rhs`` with the last factorization."""
        raise NotImplementedError

    def is_empty(self) -> bool:
        """True for a 0 x 0 system (solved without a factorization)."""
        return False

    def solve(self, values: FloatArray, rhs: FloatArray, check: bool = False) -> FloatArray:
        """Solve ``A x = rhs`` for the system matrix A with the given values."""
        if self.is_empty():
            return np.zeros(0)
        self.factor(values)
        if check:
            self.check()
        return self.solve_factored(rhs)


# --------------------------------------------------------------------------- SuperLU
class _SuperLU(Factorizer):
    """SuperLU on the pre-ordered SPD matrix: natural column order, diagonal pivots."""

    name = "splu"

    def __init__(self, pattern: SymmetricPattern) -> None:
        _check_lower(pattern)
        self._pat = pattern
        self._lu: Any = None
        self._diagonal: FloatArray | None = None

    def values_buffer(self) -> FloatArray | None:
        """None: SuperLU builds its own matrix from the values at each factorization."""
        return None

    def factor(self, values: FloatArray) -> None:
        """Numeric factorization of A with the given values (in the pattern's order)."""
        p = self._pat
        low = sp.csc_matrix((values, p.indices, p.indptr), shape=(p.dim, p.dim))
        h = (low + low.T - sp.diags(low.diagonal())).tocsc()  # SuperLU needs both triangles
        h.sort_indices()
        try:
            self._lu = spla.splu(h, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise SolverError(f"the normal equations are singular ({exc}); is the gauge fixed?"
                              ) from exc
        self._diagonal = values[p.diag_index]

    def check(self) -> None:
        """Raise SolverError when the last factored matrix is singular to rounding."""
        assert self._lu is not None and self._diagonal is not None
        pivots = np.abs(self._lu.U.diagonal())  # U's diagonal, in the order of perm_c
        check_pivots(pivots, self._diagonal[np.argsort(self._lu.perm_c)])

    def solve_factored(self, rhs: FloatArray) -> FloatArray:
        """``A^-1 rhs`` with the last factorization (rhs: (dim,) or (dim, k))."""
        assert self._lu is not None
        return np.asarray(self._lu.solve(np.ascontiguousarray(rhs, np.float64)), np.float64)

    def inverse_blocks(self, block_index: Int64Array) -> FloatArray:
        """(k, b, b) blocks ``A^-1[idx, idx]`` for each row ``idx`` of ``block_index`` (k, b).

        Solves with the ``k b`` unit right-hand sides (in batches): ``2 nnz(L + U)`` flops each.
        """
        dim = self._pat.dim
        k, b = block_index.shape
        out = np.empty((k, b, b))
        for lo, hi in _unit_batches(dim, block_index):
            idx = block_index[lo:hi]
            rhs = np.zeros((dim, idx.size))
            rhs[idx.ravel(), np.arange(idx.size)] = 1.0
            x = self.solve_factored(rhs).reshape(dim, hi - lo, b)
            out[lo:hi] = x[idx, np.arange(hi - lo)[:, None], :]
        return 0.5 * (out + out.transpose(0, 2, 1))


# --------------------------------------------------------------------------- CHOLMOD
@contextlib.contextmanager
def _cholmod_options(**options: int) -> Iterator[Any]:
    """cvxopt.cholmod with the given (module-global) options, restored afterwards."""
    import cvxopt.cholmod as cm

    saved = dict(cm.options)
    cm.options.clear()
    cm.options.update(options)
    try:
        yield cm
    finally:
        cm.options.clear()
        cm.options.update(saved)


#: Supernodal L L^T (the diagonal of L gives the pivots); only the given (natural) ordering:
#: the matrix is already in fill-reducing order (CHOLMOD still postorders its elimination tree).
_CHOLMOD_OPTIONS = {"supernodal": 2, "nmethods": 1}


class _Cholmod(Factorizer):
    """CHOLMOD (cvxopt): symbolic analysis once, numeric factorization per iteration."""

    name = "cholmod"

    def __init__(self, pattern: SymmetricPattern) -> None:
        import cvxopt

        _check_lower(pattern)
        self._cvxopt = cvxopt
        dim = pattern.dim
        self._dim = dim
        self._diag_index = pattern.diag_index
        self._perm: Int64Array | None = None
        self._diagonal: FloatArray | None = None
        self._factor: Any = None
        nnz = int(pattern.indptr[-1]) if dim else 0
        #: the values the caller assembles into (numpy view of a cvxopt matrix, no copy)
        self._store = cvxopt.matrix(0.0, (max(nnz, 1), 1))
        self._buffer: FloatArray = np.asarray(self._store)[:nnz, 0]
        if dim == 0:
            return
        rows = cvxopt.matrix(pattern.indices, tc="i")
        col = np.repeat(np.arange(dim, dtype=np.int64), np.diff(pattern.indptr))
        cols = cvxopt.matrix(col, tc="i")
        del col
        self._matrix = cvxopt.spmatrix(0.0, rows, cols, (dim, dim))
        del rows, cols
        natural = cvxopt.matrix(np.arange(dim, dtype=np.int64), tc="i")
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            self._factor = cm.symbolic(self._matrix, p=natural)

    def values_buffer(self) -> FloatArray:
        """The array to assemble the values into: :meth:`factor` then copies nothing more."""
        return self._buffer

    def factor(self, values: FloatArray) -> None:
        """Numeric factorization of A with the given values (in the pattern's order)."""
        if values is not self._buffer:
            self._buffer[:] = values
        self._matrix.V = self._store  # one copy, into the matrix cvxopt hands to CHOLMOD
        self._diagonal = values[self._diag_index]
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            try:
                cm.numeric(self._matrix, self._factor)
            except ArithmeticError as exc:  # cvxopt: the column where a pivot was <= 0
                raise not_positive_definite(f"non-positive pivot in column {exc}") from exc

    def _permutation(self) -> Int64Array:
        """p with ``(P A P^T)[i, j] = A[p[i], p[j]]``: CHOLMOD's final order (postordered)."""
        if self._perm is None:
            b = self._cvxopt.matrix(np.arange(self._dim, dtype=np.float64))
            with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
                cm.solve(self._factor, b, sys=7)  # b := P b
            self._perm = np.asarray(b, np.float64).ravel().astype(np.int64)
        return self._perm

    def check(self) -> None:
        """Raise SolverError when the last factored matrix is singular to rounding."""
        assert self._diagonal is not None
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            pivots = np.asarray(cm.diag(self._factor), np.float64).ravel() ** 2  # D of L D L^T
        check_pivots(pivots, self._diagonal[self._permutation()])

    def solve_factored(self, rhs: FloatArray) -> FloatArray:
        """``A^-1 rhs`` with the last factorization (rhs: (dim,) or (dim, k))."""
        b = self._cvxopt.matrix(np.asfortranarray(rhs, np.float64))
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            cm.solve(self._factor, b)
        out = np.asarray(b, np.float64)
        return out.ravel() if rhs.ndim == 1 else out

    def is_empty(self) -> bool:
        return self._dim == 0

    def inverse_blocks(self, block_index: Int64Array) -> FloatArray:
        """(k, b, b) blocks ``A^-1[idx, idx]`` for each row ``idx`` of ``block_index`` (k, b).

        With ``A = P^T L L^T P``: ``E^T A^-1 E = Y^T Y`` where ``Y = L^-1 P E`` for the unit
        columns E of one block, so each block costs one forward solve with b right-hand sides
        (``2 b nnz(L)`` flops) and a (b, dim) x (dim, b) product; batched.
        """
        dim = self._dim
        k, b = block_index.shape
        pinv = np.empty(dim, np.int64)
        pinv[self._permutation()] = np.arange(dim)
        out = np.empty((k, b, b))
        for lo, hi in _unit_batches(dim, block_index):
            idx = block_index[lo:hi]
            rhs = np.zeros((dim, idx.size), order="F")
            rhs[pinv[idx.ravel()], np.arange(idx.size)] = 1.0
            y = self._cvxopt.matrix(rhs)
            with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
                cm.solve(self._factor, y, sys=4)  # y := L^-1 y
            yy = np.asarray(y, np.float64).reshape(dim, hi - lo, b)
            yt = yy.transpose(1, 2, 0)  # (k, b, dim)
            out[lo:hi] = yt @ yt.transpose(0, 2, 1)
        return out


def make_factorizer(pattern: SymmetricPattern, backend: str) -> _SuperLU | _Cholmod:
    """The factorizer for ``linear_solver`` (see :data:`config.LINEAR_SOLVERS`)."""
    if backend == "cholmod" or (backend == "auto" and cholmod_available()):
        if not cholmod_available():
            raise SolverError("linear_solver='cholmod' needs cvxopt (pip install cvxopt; its "
                              "wheels bundle SuiteSparse's CHOLMOD)")
        return _Cholmod(pattern)
    return _SuperLU(pattern)


class CscPattern:
    """A lower-triangle pattern (:class:`SymmetricPattern`) from a SciPy CSC matrix."""

    def __init__(self, low: sp.csc_matrix) -> None:
        self.indptr: Int64Array = low.indptr.astype(np.int64)
        self.indices: Int64Array = low.indices.astype(np.int64)
        self.dim = int(low.shape[0])

    @property
    def diag_index(self) -> Int64Array:
        return self.indptr[:-1]


def solve_spd(a: sp.spmatrix, rhs: FloatArray, block: int = 1) -> FloatArray:
    """Solve ``A x = rhs`` once for a sparse SPD ``A`` (rhs: (dim,) or (dim, k)).

    The unknowns come in blocks of ``block`` (a pose's 3 or 6 entries): they are permuted by a
    fill-reducing ordering of the block graph (:func:`fill_reducing_order`), then factored by
    CHOLMOD when cvxopt is available (else SuperLU), one factorization for every right-hand side.

    Raises
    ------
    SolverError
        ``A`` is not positive definite, or singular to rounding.
    """
    csc = sp.csc_matrix(a)
    dim = int(csc.shape[0])
    if dim == 0:
        return np.zeros_like(rhs, dtype=np.float64)
    coo = csc.tocoo()
    nb = dim // block
    br = coo.row.astype(np.int64) // block
    bc = coo.col.astype(np.int64) // block
    del coo
    lower = br > bc
    key = np.unique(bc[lower] * nb + br[lower])  # each block pair once (block^2 fewer)
    del br, bc, lower
    new_block = fill_reducing_order(nb, key % nb, key // nb)
    del key
    new_pos = (block * new_block[:, None] + np.arange(block, dtype=np.int64)[None, :]).ravel()
    old_at = np.empty(dim, np.int64)
    old_at[new_pos] = np.arange(dim)
    low = sp.tril(csc[old_at][:, old_at], format="csc")
    del csc
    low.sort_indices()
    pattern = CscPattern(low)
    factorizer = make_factorizer(pattern, "auto")
    x = factorizer.solve(np.asarray(low.data, np.float64), np.asarray(rhs, np.float64)[old_at],
                         check=True)
    return np.asarray(x[new_pos], np.float64)
