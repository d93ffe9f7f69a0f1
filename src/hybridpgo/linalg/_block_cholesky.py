"""Block sparse Cholesky of the exact solver's 6x6-block normal equations (large graphs).

CHOLMOD through cvxopt needs, per stored scalar entry of the lower triangle of H ("nnz"): its own
copy of the matrix (16 bytes: values and 64-bit row indices), the symbolic factor (~10), and at
each numeric factorization a packed copy and a transposed one (16 + 16, transient), on top of
the factor (~19 on a city graph) and the caller's values (8): ~100 bytes per entry at the peak,
6 GB for a 1M-pose city (57 M entries), over a 4 GB memory target.

This factorization works on the 6x6 *blocks* instead, straight from the values the assembly
kernel writes (the lower-triangle layout of :mod:`._gn_kernels`, no copy): its row structure is
one 32-bit index per block (1/36 of a scalar pattern), the factor ``L`` is stored as dense 6x6
blocks (the diagonal ones full), and nothing else of size nnz exists: ~8 bytes per entry for
the values plus ~2x that for ``L`` on a city graph.

Algorithm (the variables are already in fill-reducing order: AMD on the block graph):

* symbolic, once: the block structure of each column of ``L`` is the union of ``A``'s and of its
  elimination-tree children's (minus the child itself); ``parent[j]`` is the smallest row below
  the diagonal of column ``j``;
* numeric, per iteration: left-looking by block columns.  Column ``j`` is loaded from ``A``,
  updated by every earlier column ``k`` with a block in row ``j`` (found by the classic linked
  lists of columns waiting at their next row), then its diagonal block is factored (dense 6x6
  Cholesky) and its other blocks are solved against it;
* solve: block forward and back substitution.

Everything is a Numba kernel over NumPy arrays (no Python loop per column).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from .._numba import kernel
from ..errors import SolverError
from ..graph import FloatArray
from ._factor import Factorizer, check_pivots, not_positive_definite

Int64Array = npt.NDArray[np.int64]


# --------------------------------------------------------------------------- symbolic
@kernel
def _symbolic(nv: int, a_ptr: np.ndarray, a_row: np.ndarray, l_ptr: np.ndarray,
              parent: np.ndarray) -> np.ndarray:
    """Block structure of L (rows below the diagonal of each column, increasing).

    ``a_ptr``/``a_row``: A's lower off-diagonal blocks per block column (rows increasing).
    Fills ``l_ptr`` (nv+1,) and ``parent`` (nv,), returns the rows (int32).
    """
    mark = np.full(nv, -1, np.int64)
    child_head = np.full(nv, -1, np.int64)
    child_next = np.full(nv, -1, np.int64)
    cap = max(2 * a_row.shape[0], 16)
    rows = np.empty(cap, np.int32)
    buf = np.empty(nv, np.int64)
    l_ptr[0] = 0
    for j in range(nv):
        cnt = 0
        mark[j] = j
        for q in range(a_ptr[j], a_ptr[j + 1]):
            r = a_row[q]
            if mark[r] != j:
                mark[r] = j
                buf[cnt] = r
                cnt += 1
        c = child_head[j]
        while c >= 0:
            for q in range(l_ptr[c], l_ptr[c + 1]):
                r = rows[q]
                if mark[r] != j:
                    mark[r] = j
                    buf[cnt] = r
                    cnt += 1
            c = child_next[c]
        srt = np.sort(buf[:cnt])
        start = l_ptr[j]
        if start + cnt > rows.shape[0]:
            bigger = np.empty(max(2 * rows.shape[0], start + cnt), np.int32)
            bigger[:start] = rows[:start]
            rows = bigger
        for q in range(cnt):
            rows[start + q] = srt[q]
        l_ptr[j + 1] = start + cnt
        if cnt:
            p = srt[0]
            parent[j] = p
            child_next[j] = child_head[p]
            child_head[p] = j
        else:
            parent[j] = -1
    return rows[: l_ptr[nv]].copy()


# --------------------------------------------------------------------------- numeric
@kernel
def _numeric(nv: int, a_ptr: np.ndarray, a_row: np.ndarray, indptr: np.ndarray,
             values: np.ndarray,
             l_ptr: np.ndarray, l_row: np.ndarray, diag: np.ndarray, off: np.ndarray,
             pivots: np.ndarray) -> int:
    """Left-looking block Cholesky: ``diag[j]`` (6, 6) lower factor of column j's diagonal
    block, ``off[q]`` (6, 6) the block of row ``l_row[q]``.  Returns -1, or the first scalar
    column whose pivot is not positive (then the factor is incomplete).

    ``values`` in the scalar lower-triangle layout of :mod:`._gn_kernels` (``indptr``;
    A's off-diagonal blocks of column j are its first ``a_ptr[j+1] - a_ptr[j]`` rows, a subset
    of L's in the same order).  ``pivots`` (6 nv,): squared diagonal of L per scalar column.
    """
    pos = np.full(nv, -1, np.int64)  # position of a row's block within the current column
    link_head = np.full(nv, -1, np.int64)  # columns k waiting at row j
    link_next = np.full(nv, -1, np.int64)
    next_q = np.zeros(nv, np.int64)  # each column's next block to be applied
    acc = np.empty((6, 6))
    for j in range(nv):
        lo = l_ptr[j]
        hi = l_ptr[j + 1]
        for q in range(lo, hi):
            pos[l_row[q]] = q
            off[q, :, :] = 0.0
        # load A's column j: diagonal block (full) and its off-diagonal blocks
        d = diag[j]
        for qq in range(6):
            col = indptr[6 * j + qq]
            for p in range(qq, 6):
                v = values[col + p - qq]
                d[p, qq] = v
                d[qq, p] = v
        for k in range(a_ptr[j], a_ptr[j + 1]):
            tq = pos[a_row[k]]
            kk = k - a_ptr[j]
            for qq in range(6):
                base = indptr[6 * j + qq] + 6 - qq + 6 * kk
                for p in range(6):
                    off[tq, p, qq] = values[base + p]
        # updates from earlier columns
        k = link_head[j]
        while k >= 0:
            nk = link_next[k]
            p0 = next_q[k]  # position of row j in column k
            lj = off[p0]
            # diagonal: d -= lj lj^T
            for a in range(6):
                for b in range(a + 1):
                    s = 0.0
                    for t in range(6):
                        s += lj[a, t] * lj[b, t]
                    d[a, b] -= s
            for q in range(p0 + 1, l_ptr[k + 1]):
                r = l_row[q]
                tq = pos[r]
                lr = off[q]
                for a in range(6):
                    for b in range(6):
                        s = 0.0
                        for t in range(6):
                            s += lr[a, t] * lj[b, t]
                        acc[a, b] = s
                for a in range(6):
                    for b in range(6):
                        off[tq, a, b] -= acc[a, b]
            # column k moves on to its next row
            if p0 + 1 < l_ptr[k + 1]:
                next_q[k] = p0 + 1
                r = l_row[p0 + 1]
                link_next[k] = link_head[r]
                link_head[r] = k
            k = nk
        link_head[j] = -1
        # dense Cholesky of the diagonal block (lower), in place
        for c in range(6):
            s = d[c, c]
            for t in range(c):
                s -= d[c, t] * d[c, t]
            if not (s > 0.0):
                return 6 * j + c
            pivots[6 * j + c] = s
            lc = math.sqrt(s)
            d[c, c] = lc
            for r in range(c + 1, 6):
                s2 = d[r, c]
                for t in range(c):
                    s2 -= d[r, t] * d[c, t]
                d[r, c] = s2 / lc
        for c in range(6):
            for r in range(c):
                d[r, c] = 0.0
        # off-diagonal blocks: X = B L_d^-T  (solve X L_d^T = B row by row)
        for q in range(lo, hi):
            x = off[q]
            for a in range(6):
                for c in range(6):
                    s = x[a, c]
                    for t in range(c):
                        s -= x[a, t] * d[c, t]
                    x[a, c] = s / d[c, c]
        if lo < hi:
            next_q[j] = lo
            r = l_row[lo]
            link_next[j] = link_head[r]
            link_head[r] = j
        for q in range(lo, hi):
            pos[l_row[q]] = -1
    return -1


@kernel
def _solve(nv: int, l_ptr: np.ndarray, l_row: np.ndarray, diag: np.ndarray, off: np.ndarray,
           b: np.ndarray) -> None:
    """``b := A^-1 b`` with ``A = L L^T`` (forward, then back substitution by blocks)."""
    for j in range(nv):
        d = diag[j]
        for c in range(6):
            s = b[6 * j + c]
            for t in range(c):
                s -= d[c, t] * b[6 * j + t]
            b[6 * j + c] = s / d[c, c]
        for q in range(l_ptr[j], l_ptr[j + 1]):
            r = l_row[q]
            lq = off[q]
            for a in range(6):
                s = 0.0
                for t in range(6):
                    s += lq[a, t] * b[6 * j + t]
                b[6 * r + a] -= s
    for j in range(nv - 1, -1, -1):
        for q in range(l_ptr[j], l_ptr[j + 1]):
            r = l_row[q]
            lq = off[q]
            for t in range(6):
                s = 0.0
                for a in range(6):
                    s += lq[a, t] * b[6 * r + a]
                b[6 * j + t] -= s
        d = diag[j]
        for c in range(5, -1, -1):
            s = b[6 * j + c]
            for t in range(c + 1, 6):
                s -= d[t, c] * b[6 * j + t]
            b[6 * j + c] = s / d[c, c]


# --------------------------------------------------------------------------- the factorizer
class BlockCholesky(Factorizer):
    """Analyze once (block structure of L), factor per iteration, solve: a
    :class:`~._factor.Factorizer`, plus the diagonal blocks of the inverse by selected
    inversion (:meth:`inverse_diagonal_blocks`)."""

    name = "block"

    def __init__(self, num_vars: int, a_ptr: Int64Array, a_row: Int64Array,
                 indptr: Int64Array) -> None:
        self._nv = nv = int(num_vars)
        self._a_ptr = np.ascontiguousarray(a_ptr, np.int64)
        self._a_row = np.ascontiguousarray(a_row, np.int64)
        self._indptr = indptr
        self._l_ptr = np.empty(nv + 1, np.int64)
        parent = np.empty(nv, np.int64)
        self._l_row: npt.NDArray[np.int32] = _symbolic(nv, self._a_ptr, self._a_row,
                                                       self._l_ptr, parent)
        self._diag = np.zeros((nv, 6, 6))
        self._off = np.zeros((self._l_row.shape[0], 6, 6))
        self._pivots = np.zeros(6 * nv)
        self._diagonal: FloatArray | None = None

    @property
    def factor_blocks(self) -> int:
        """Stored 6x6 blocks of L (diagonal ones included)."""
        return self._nv + int(self._l_row.shape[0])

    def values_buffer(self) -> FloatArray | None:
        """None: the factorization reads the caller's values in place."""
        return None

    def factor(self, values: FloatArray) -> None:
        """Numeric factorization of A with the given values (the lower-triangle layout)."""
        self._diagonal = None  # no usable factor until this one succeeds
        col = _numeric(self._nv, self._a_ptr, self._a_row, self._indptr, values, self._l_ptr,
                       self._l_row, self._diag, self._off, self._pivots)
        if col >= 0:
            raise not_positive_definite(f"non-positive pivot in column {col}")
        self._diagonal = values[self._indptr[:-1]]

    def check(self) -> None:
        """Raise SolverError when the last factored matrix is singular to rounding."""
        assert self._diagonal is not None
        check_pivots(self._pivots, self._diagonal)

    def inverse_diagonal_blocks(self, *, overwrite: bool = False) -> FloatArray:
        """(nv, 6, 6) diagonal blocks of ``A^-1`` from the last factorization, by selected
        inversion (:mod:`._selinv`: about twice the factorization's time).

        ``overwrite=True`` computes them in the factor's own memory (no second factor-sized
        array); the factorization is then consumed: factor again before the next solve.
        """
        from ._selinv import inverse_diagonal_blocks

        if self._diagonal is None:
            raise SolverError("no factorization to invert: call factor() first")
        out = inverse_diagonal_blocks(self._l_ptr, self._l_row, self._diag, self._off,
                                      overwrite=overwrite)
        if overwrite:
            self._diagonal = None
        return out

    def solve_factored(self, rhs: FloatArray) -> FloatArray:
        """``A^-1 rhs`` with the last factorization (rhs: (dim,))."""
        if self._diagonal is None:
            raise SolverError("no factorization to solve with: call factor() first")
        if rhs.ndim != 1:
            raise SolverError("the block factorization solves one right-hand side at a time")
        out = np.array(rhs, np.float64)
        _solve(self._nv, self._l_ptr, self._l_row, self._diag, self._off, out)
        return out

    def is_empty(self) -> bool:
        return self._nv == 0
