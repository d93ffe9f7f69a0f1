"""Sparse symmetric factorizations for the exact solver: analyze once, factor per iteration.

Two backends factor a symmetric positive definite matrix ``A`` given as the values of a fixed CSC
pattern of its *lower triangle*, rows increasing within each column (so each column starts with
its diagonal entry), as :class:`hybridpgo.solvers.gauss_newton` assembles it:

``_Cholmod`` (``linear_solver="cholmod"``)
    SuiteSparse CHOLMOD through :mod:`cvxopt.cholmod` (GPL-3.0, the optional extra
    ``hybridpgo[cholmod]``: manylinux, macOS and Windows wheels bundle CHOLMOD and OpenBLAS,
    nothing to compile; used whenever cvxopt imports).  Supernodal ``L L^T``; the
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
    pivots).  A full LU (no BLAS-3 supernodes), 2-3x slower than CHOLMOD; with the AMD
    pre-ordering it does not collapse on dense loop closures: paris2 with GPS 1.3-2.1 s per
    factorization, against > 600 s (time limit) with SuperLU's own block MMD ordering.

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
import contextvars
from collections.abc import Iterator
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._numba import kernel
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
        # With diagonal pivots U = D L^T: A is positive definite iff every pivot is > 0
        # (Sylvester), as CHOLMOD's L L^T tells; an off-diagonal pivot means it is not.
        pivots = self._lu.U.diagonal()
        if not (np.all(pivots > 0.0) and np.array_equal(self._lu.perm_r, np.arange(p.dim))):
            bad = int(np.argmax(~(pivots > 0.0)))
            raise not_positive_definite(f"non-positive pivot in column {bad}")

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

#: The cvxopt matrices built inside :func:`shared_patterns` (None outside one): ``(indptr,
#: indices, matrix, analysis)`` per pattern.
_PATTERNS: contextvars.ContextVar[list[tuple[Any, Any, Any, Any]] | None] = contextvars.ContextVar(
    "hybridpgo_cholmod_patterns", default=None)
#: Patterns with more stored entries than this are not kept (their construction is small
#: beside their factorization, and what is kept, the matrix's copy and its analysis with the
#: numeric factor, lives until the context ends).
SHARED_PATTERN_MAX = 1 << 20
#: The same for factorizers made to be shared (``share=True``: the certificate's Newton
#: system and LM's normal equations, whose pattern is the same).  The 42 000-pose paris2 with
#: GPS: a pattern of 2.9 M entries, its construction and analysis made once instead of twice
#: (``benchmarks/results/2026-12-01-auto-ac.md``); the million-pose graphs' patterns stay out.
SHARED_PATTERN_MAX_SHARED = 1 << 22


@contextlib.contextmanager
def shared_patterns() -> Iterator[None]:
    """Within this context, a CHOLMOD factorizer whose pattern equals that of one built
    earlier in it starts from a copy of that one's cvxopt matrix (0.1 ms) instead of building
    it from triplets (cvxopt sorts and de-duplicates them: 8 ms for garage's 260 000 entries).
    The default pipeline opens one per solve: the certificate's Newton system and the
    polish's normal equations have the same pattern.  Such factorizers also share one symbolic
    analysis (garage: 7 ms of CHOLMOD's analysis, and the first factorization's fresh pages),
    each with its own matrix values: the factor object holds the numeric factorization of the
    factorizer that factored last, and another one that solves with it first factors its own
    values again (:class:`_Analysis`).  Nothing is kept after the context.  The factorizers
    made in one context are for one thread: two threads solving with factorizers that share
    an analysis would factor into the same object."""
    token = _PATTERNS.set([])
    try:
        yield
    finally:
        _PATTERNS.reset(token)


class _Analysis:
    """A CHOLMOD factor object shared by the factorizers of one pattern in a
    :func:`shared_patterns` context: its symbolic analysis is the same for all of them, its
    numeric factorization is that of the factorizer whose token is ``user`` (the one that
    factored last; -1: none yet)."""

    __slots__ = ("factor", "tokens", "user")

    def __init__(self, factor: Any) -> None:
        self.factor = factor
        self.user = -1
        self.tokens = 0

    def token(self) -> int:
        """A new factorizer's token (an integer, so that the analysis keeps no factorizer
        alive)."""
        self.tokens += 1
        return self.tokens


def _shared_matrix(pattern: SymmetricPattern) -> tuple[Any, _Analysis] | None:
    """A copy of the matrix built in this :func:`shared_patterns` context for an equal pattern
    and its analysis, else None."""
    known = _PATTERNS.get()
    if not known:
        return None
    for indptr, indices, matrix, analysis in known:
        if (indptr.shape == pattern.indptr.shape and np.array_equal(indptr, pattern.indptr)
                and np.array_equal(indices, pattern.indices)):
            return +matrix, analysis  # a copy with the same stored entries (zeros included)
    return None


def _remember(pattern: SymmetricPattern, matrix: Any, analysis: _Analysis,
              share: bool = False) -> bool:
    """Keep ``matrix`` and its analysis for the factorizers of an equal pattern made later in
    this :func:`shared_patterns` context; False when none is open or the pattern is too
    large to keep (:data:`SHARED_PATTERN_MAX`, or with ``share``
    :data:`SHARED_PATTERN_MAX_SHARED`)."""
    known = _PATTERNS.get()
    limit = SHARED_PATTERN_MAX_SHARED if share else SHARED_PATTERN_MAX
    if known is None or int(pattern.indptr[-1]) > limit:
        return False
    known.append((np.array(pattern.indptr, copy=True), np.array(pattern.indices, copy=True),
                  matrix, analysis))
    return True


class _Cholmod(Factorizer):
    """CHOLMOD (cvxopt): symbolic analysis once, numeric factorization per iteration."""

    name = "cholmod"

    def __init__(self, pattern: SymmetricPattern, share: bool = False) -> None:
        import cvxopt

        _check_lower(pattern)
        self._cvxopt = cvxopt
        dim = pattern.dim
        self._dim = dim
        self._diag_index = pattern.diag_index
        self._perm: Int64Array | None = None
        self._diagonal: FloatArray | None = None
        self._factor: Any = None
        #: the factor object when shared with factorizers of an equal pattern (None: its own),
        #: and this factorizer's token there
        self._analysis: _Analysis | None = None
        self._token = 0
        nnz = int(pattern.indptr[-1]) if dim else 0
        #: the values the caller assembles into (numpy view of a cvxopt matrix, no copy)
        self._store = cvxopt.matrix(0.0, (max(nnz, 1), 1))
        self._buffer: FloatArray = np.asarray(self._store)[:nnz, 0]
        if dim == 0:
            return
        shared = _shared_matrix(pattern)
        if shared is not None:
            self._matrix, self._analysis = shared
            self._factor = self._analysis.factor
            self._token = self._analysis.token()
            return
        rows = cvxopt.matrix(pattern.indices, tc="i")
        col = np.repeat(np.arange(dim, dtype=np.int64), np.diff(pattern.indptr))
        cols = cvxopt.matrix(col, tc="i")
        del col
        # values given as a matrix (the zeros of the store): about twice as fast as a scalar
        self._matrix = cvxopt.spmatrix(self._store, rows, cols, (dim, dim))
        del rows, cols
        natural = cvxopt.matrix(np.arange(dim, dtype=np.int64), tc="i")
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            self._factor = cm.symbolic(self._matrix, p=natural)
        analysis = _Analysis(self._factor)
        if _remember(pattern, self._matrix, analysis, share):
            self._analysis = analysis
            self._token = analysis.token()

    def values_buffer(self) -> FloatArray:
        """The array to assemble the values into: :meth:`factor` then copies nothing more."""
        return self._buffer

    def factor(self, values: FloatArray) -> None:
        """Numeric factorization of A with the given values (in the pattern's order)."""
        if values is not self._buffer:
            self._buffer[:] = values
        self._matrix.V = self._store  # one copy, into the matrix cvxopt hands to CHOLMOD
        self._diagonal = values[self._diag_index]
        self._numeric()

    def _numeric(self) -> None:
        """CHOLMOD's numeric factorization of the matrix's values (those of the last
        :meth:`factor`), into the factor object."""
        if self._analysis is not None:
            self._analysis.user = self._token
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            try:
                cm.numeric(self._matrix, self._factor)
            except ArithmeticError as exc:  # cvxopt: the column where a pivot was <= 0
                raise not_positive_definite(f"non-positive pivot in column {exc}") from exc

    def _mine(self) -> Any:
        """The factor object holding this factorizer's last factorization: where another
        factorizer of the same analysis factored since, this one's values (kept in its
        matrix) are factored again.

        Raises
        ------
        SolverError
            This factorizer has not factored yet while another one's factorization is there.
        """
        a = self._analysis
        if a is not None and a.user != self._token:
            if self._diagonal is None:
                raise SolverError("a CHOLMOD factorizer was used before its first "
                                  "factorization")
            self._numeric()
        return self._factor

    def _permutation(self) -> Int64Array:
        """p with ``(P A P^T)[i, j] = A[p[i], p[j]]``: CHOLMOD's final order (postordered)."""
        if self._perm is None:
            b = self._cvxopt.matrix(np.arange(self._dim, dtype=np.float64))
            # CHOLMOD refuses any solve, this permutation too, with a factor whose last
            # factorization failed: another factorizer's, where the analysis is shared
            factor = self._mine()
            with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
                cm.solve(factor, b, sys=7)  # b := P b
            self._perm = np.asarray(b, np.float64).ravel().astype(np.int64)
        return self._perm

    def check(self) -> None:
        """Raise SolverError when the last factored matrix is singular to rounding."""
        assert self._diagonal is not None
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            pivots = np.asarray(cm.diag(self._mine()), np.float64).ravel() ** 2  # D of L D L^T
        check_pivots(pivots, self._diagonal[self._permutation()])

    def solve_factored(self, rhs: FloatArray) -> FloatArray:
        """``A^-1 rhs`` with the last factorization (rhs: (dim,) or (dim, k))."""
        b = self._cvxopt.matrix(np.asfortranarray(rhs, np.float64))
        factor = self._mine()
        with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
            cm.solve(factor, b)
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
            factor = self._mine()
            with _cholmod_options(**_CHOLMOD_OPTIONS) as cm:
                cm.solve(factor, y, sys=4)  # y := L^-1 y
            yy = np.asarray(y, np.float64).reshape(dim, hi - lo, b)
            yt = yy.transpose(1, 2, 0)  # (k, b, dim)
            out[lo:hi] = yt @ yt.transpose(0, 2, 1)
        return out


def make_factorizer(pattern: SymmetricPattern, backend: str, share: bool = False
                    ) -> _SuperLU | _Cholmod:
    """The factorizer for ``linear_solver`` (see :data:`config.LINEAR_SOLVERS`); ``share``: one
    made to be shared with a later factorizer of its pattern in a :func:`shared_patterns`
    context (kept up to :data:`SHARED_PATTERN_MAX_SHARED` entries)."""
    if backend == "cholmod" or (backend == "auto" and cholmod_available()):
        if not cholmod_available():
            raise SolverError("linear_solver='cholmod' needs cvxopt (pip install "
                              "'hybridpgo[cholmod]', or pip install cvxopt: its wheels bundle "
                              "SuiteSparse's CHOLMOD)")
        return _Cholmod(pattern, share)
    return _SuperLU(pattern)


class CscPattern:
    """A lower-triangle pattern (:class:`SymmetricPattern`) from a SciPy CSC matrix."""

    def __init__(self, low: sp.csc_matrix) -> None:
        self.indptr: Int64Array = low.indptr.astype(np.int64)
        self.indices: Int64Array = low.indices.astype(np.int64)
        self.dim = int(low.shape[0])

    @classmethod
    def from_arrays(cls, indptr: Int64Array, indices: Int64Array) -> CscPattern:
        """The pattern of the column pointers ``indptr`` and row indices ``indices``."""
        out = cls.__new__(cls)
        out.indptr, out.indices, out.dim = indptr, indices, int(indptr.shape[0]) - 1
        return out

    @property
    def diag_index(self) -> Int64Array:
        return self.indptr[:-1]


#: The sparse formats whose stored entries :class:`SparseSPD` reads in place.
_ENTRY_FORMATS = ("csr", "csc", "coo", "bsr")


def _entries(a: sp.spmatrix) -> tuple[Int64Array, Int64Array, int]:
    """``(rows, cols, b)``: the (b, b) blocks of ``a`` in the order of its values, by block
    row and column: BSR's own blocks, else every stored entry (b = 1), so the entry (i, j) of
    block k is ``a.data.ravel()[k b^2 + i b + j]``."""
    if a.format == "bsr":
        b = int(a.blocksize[0])
        return (np.repeat(np.arange(a.shape[0] // b, dtype=np.int64), np.diff(a.indptr)),
                np.asarray(a.indices, np.int64), b)
    if a.format == "coo":
        return np.asarray(a.row, np.int64), np.asarray(a.col, np.int64), 1
    major = np.repeat(np.arange(a.shape[0], dtype=np.int64), np.diff(a.indptr))
    minor = np.asarray(a.indices, np.int64)
    return (major, minor, 1) if a.format == "csr" else (minor, major, 1)


@kernel
def permuted_lower(rows: np.ndarray, cols: np.ndarray, b: int, new_pos: np.ndarray,
                   indptr: np.ndarray, indices: np.ndarray, source: np.ndarray) -> int:
    """The lower triangle of ``P A P^T`` as CSC: ``indptr`` (dim + 1,) and ``indices`` (rows
    increasing in each column, the diagonal first), and ``source``, the place in A's values of
    each of its entries, for A given by its (b, b) blocks (:func:`_entries`: block k at block
    row ``rows[k]``, column ``cols[k]``) and ``new_pos``, the new index of each block row.

    The blocks are sorted by new block column, then row (two stable counting sorts), and each
    block column is written out entry by entry.  Returns -1, or the first new block column
    without its diagonal block (nothing else is checked: A is canonical)."""
    nb = new_pos.shape[0]
    by_row = np.zeros(nb + 1, np.int64)
    by_col = np.zeros(nb + 1, np.int64)
    for k in range(rows.shape[0]):
        r = new_pos[rows[k]]
        c = new_pos[cols[k]]
        if r >= c:
            by_row[r + 1] += 1
            by_col[c + 1] += 1
    for j in range(nb):
        by_row[j + 1] += by_row[j]
        by_col[j + 1] += by_col[j]
    order = np.empty(by_row[nb], np.int64)  # the lower blocks by increasing new row
    for k in range(rows.shape[0]):
        r = new_pos[rows[k]]
        if r >= new_pos[cols[k]]:
            order[by_row[r]] = k
            by_row[r] += 1
    column = np.empty(order.shape[0], np.int64)  # then by new column (stable)
    fill = by_col[:nb].copy()
    for q in range(order.shape[0]):
        c = new_pos[cols[order[q]]]
        column[fill[c]] = order[q]
        fill[c] += 1
    bb = b * b
    p = 0
    for c in range(nb):
        lo = by_col[c]
        hi = by_col[c + 1]
        if hi == lo or new_pos[rows[column[lo]]] != c:
            return c
        for j in range(b):
            indptr[b * c + j] = p
            kd = column[lo]  # the diagonal block: its rows j..b-1
            for i in range(j, b):
                indices[p] = b * c + i
                source[p] = kd * bb + i * b + j
                p += 1
            for q in range(lo + 1, hi):
                ko = column[q]
                r = new_pos[rows[ko]]
                for i in range(b):
                    indices[p] = b * r + i
                    source[p] = ko * bb + i * b + j
                    p += 1
    indptr[b * nb] = p
    return -1


class SparseSPD:
    """A sparse symmetric matrix ``A`` prepared for factorizations of ``A + diag(shift)``.

    The unknowns come in blocks of ``block`` (a pose's 3 or 6 entries): they are permuted once
    by a fill-reducing ordering of the block graph (:func:`fill_reducing_order`) and the
    factorizer (CHOLMOD when cvxopt is available, else SuperLU) analyzes the pattern once;
    each :meth:`factor` is then one numeric factorization, of ``A``'s values or of new values
    on the same pattern.  ``A`` is a CSR, CSC, COO or BSR matrix in canonical form with every
    diagonal entry stored (as it is for a matrix whose diagonal is positive); its lower
    triangle in the new order is laid out block by block (:func:`permuted_lower`: a BSR
    matrix's blocks are permuted whole, 36 times fewer items than its 6x6 blocks' entries).
    ``share``: :func:`make_factorizer`'s.
    """

    def __init__(self, a: sp.spmatrix, block: int = 1, share: bool = False) -> None:
        if not sp.issparse(a) or a.format not in _ENTRY_FORMATS or not a.has_canonical_format:
            raise ValueError("SparseSPD needs a sparse CSR, CSC, COO or BSR matrix in canonical "
                             "format (sorted indices, no duplicates)")
        dim = int(a.shape[0])
        self.dim = dim
        self.nnz = int(a.data.size)
        rows, cols, b = _entries(a)  # A's blocks (BSR's), else its entries, in values order
        if a.format == "bsr":  # the block graph is the matrix's own block structure
            block = b
            nb = dim // block
            lower = rows > cols
            brow, bcol = rows[lower], cols[lower]
        else:
            nb = dim // block
            br, bc = rows // block, cols // block
            lower = br > bc
            if block == 1:  # canonical: every pair once already
                brow, bcol = br[lower], bc[lower]
            else:
                key = np.unique(bc[lower] * nb + br[lower])  # each block pair once
                brow, bcol = key % nb, key // nb
            del br, bc
        del lower
        new_block = fill_reducing_order(nb, brow, bcol)
        del brow, bcol
        self._new_pos = (block * new_block[:, None]
                         + np.arange(block, dtype=np.int64)[None, :]).ravel()
        self._old_at = np.empty(dim, np.int64)
        self._old_at[self._new_pos] = np.arange(dim)
        # the permuted lower triangle, column by column, and where each of its values is in A
        indptr = np.empty(dim + 1, np.int64)
        indices = np.empty(rows.size * b * b, np.int64)
        self._source = np.empty(rows.size * b * b, np.int64)
        pos = new_block if b == block else self._new_pos  # of A's blocks, or its entries
        missing = int(permuted_lower(rows, cols, b, pos, indptr, indices, self._source))
        if missing >= 0:
            raise ValueError(f"SparseSPD needs every diagonal entry stored (row "
                             f"{int(self._old_at[b * missing])} has none)")
        nnz = int(indptr[dim])
        indices, self._source = indices[:nnz], self._source[:nnz]
        self._values = np.asarray(a.data, np.float64).ravel().copy()
        pattern = CscPattern.from_arrays(indptr, indices)
        del rows, cols
        self._diag = pattern.diag_index
        self._factorizer = make_factorizer(pattern, "auto", share) if dim else None

    @property
    def backend(self) -> str:
        """The factorizer's name (``"cholmod"`` or ``"splu"``)."""
        return "" if self._factorizer is None else str(self._factorizer.name)

    def factor(self, shift: FloatArray | float = 0.0, check: bool = False,
               values: FloatArray | None = None) -> None:
        """Factor ``A + diag(shift)`` (``shift``: a scalar or one entry per unknown).

        ``values``: new stored entries of A, in the order of ``A.data.ravel()`` of the matrix
        given at construction (any sparse format, canonical: sorted indices, no duplicates;
        BSR: its blocks are the unknowns' blocks).

        Raises
        ------
        NotPositiveDefinite
            A pivot is not positive: the shifted matrix is not positive definite.
        SolverError
            With ``check``: the matrix is singular to rounding (a tiny pivot).
        """
        if self._factorizer is None:
            return
        src = self._values if values is None else np.asarray(values, np.float64)
        vals = src[self._source]
        vals[self._diag] += np.broadcast_to(np.asarray(shift, np.float64), (self.dim,))[
            self._old_at]
        self._factorizer.factor(vals)
        if check:
            self._factorizer.check()

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``(A + diag(shift))^-1 rhs`` with the last factorization (rhs: (dim,) or (dim, k))."""
        if self._factorizer is None:
            return np.zeros_like(rhs, dtype=np.float64)
        x = self._factorizer.solve_factored(np.asarray(rhs, np.float64)[self._old_at])
        return np.asarray(np.asarray(x).reshape(rhs.shape)[self._new_pos], np.float64)


def solve_spd(a: sp.spmatrix, rhs: FloatArray, block: int = 1) -> FloatArray:
    """Solve ``A x = rhs`` once for a sparse SPD ``A`` (rhs: (dim,) or (dim, k)).

    The unknowns come in blocks of ``block`` (a pose's 3 or 6 entries): they are permuted by a
    fill-reducing ordering of the block graph (:class:`SparseSPD`), then factored by CHOLMOD
    when cvxopt is available (else SuperLU), one factorization for every right-hand side.

    Raises
    ------
    SolverError
        ``A`` is not positive definite, or singular to rounding.
    """
    csr = sp.csr_matrix(a, copy=True)
    csr.sum_duplicates()
    csr.sort_indices()
    spd = SparseSPD(csr, block)
    if spd.dim == 0:
        return np.zeros_like(rhs, dtype=np.float64)
    spd.factor(check=True)
    return spd.solve(rhs)
