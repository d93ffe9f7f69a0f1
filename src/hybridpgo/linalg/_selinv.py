"""Selected inversion: the diagonal blocks of ``A^-1`` from a sparse Cholesky factor of A.

Given ``A = L L^T`` with L block lower triangular (square diagonal blocks ``L_jj`` of size b,
off-diagonal blocks ``L_sj`` at the rows ``s in S_j`` of block column j), the inverse
``Z = A^-1`` satisfies ``Z L = L^-T``, an upper triangular matrix whose diagonal blocks are
``L_jj^-T``.  Reading block column j of that identity at the rows j and ``S_j`` (Takahashi's
recurrences; Rue's algorithm for Gaussian Markov random fields) gives, with
``W_j = L_{S_j j} L_jj^-1``:

* ``Z_{S_j j} = -Z_{S_j S_j} W_j``
* ``Z_jj = L_jj^-T L_jj^-1 - Z_{S_j j}^T W_j``

Every block of ``Z_{S_j S_j}`` lies in the pattern of L (the rows of one column of a Cholesky
factor are pairwise joined by fill: ``s_a > s_b`` in ``S_j`` means ``L_{s_a s_b}`` is a stored
block), and it belongs to a later column than j.  So one sweep from the last block column to
the first computes Z on L's pattern only, never the dense inverse: about twice the flops of the
numeric factorization, and memory for one more factor (none when it overwrites the factor).

The kernel works on any block size b (``diag.shape[1]``): 6 for the exact solver's pose
blocks (:class:`._block_cholesky.BlockCholesky`), 1 for a scalar CSC factor.  Used by
:func:`hybridpgo.covariance.marginal_covariances` for the marginal covariance of every pose.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .._numba import kernel
from ..errors import SolverError
from ..graph import FloatArray

__all__ = ["inverse_diagonal_blocks"]


@kernel
def _lower_inverse(d: np.ndarray, out: np.ndarray) -> None:
    """``out = d^-1`` for a lower triangular (b, b) ``d`` with a nonzero diagonal."""
    b = d.shape[0]
    for c in range(b):
        for r in range(b):
            out[r, c] = 0.0
    for c in range(b):
        out[c, c] = 1.0 / d[c, c]
        for r in range(c + 1, b):
            s = 0.0
            for t in range(c, r):
                s += d[r, t] * out[t, c]
            out[r, c] = -s / d[r, r]


@kernel
def _takahashi(l_ptr: np.ndarray, l_row: np.ndarray, diag: np.ndarray, off: np.ndarray,
               zdiag: np.ndarray, zoff: np.ndarray) -> int:
    """Z = (L L^T)^-1 on L's block pattern (module docstring).

    ``diag`` (n, b, b): ``L_jj`` (lower triangular); ``off`` (nnz, b, b): the block of row
    ``l_row[q]`` for ``q`` in ``l_ptr[j] .. l_ptr[j+1]`` (rows increasing in each column).
    Writes ``zdiag`` (n, b, b) and ``zoff`` (nnz, b, b) in the same layout; they may be
    ``diag`` and ``off`` themselves (column j is read before it is written, and only later
    columns' Z are read).  Returns -1, or a column j whose rows are not all found in the
    columns they should be in (a pattern that is not a Cholesky factor's).
    """
    n = diag.shape[0]
    b = diag.shape[1]
    most = 0
    for j in range(n):
        most = max(most, l_ptr[j + 1] - l_ptr[j])
    w = np.empty((most, b, b))
    acc = np.empty((most, b, b))
    linv = np.empty((b, b))
    for j in range(n - 1, -1, -1):
        lo = l_ptr[j]
        m = l_ptr[j + 1] - lo
        _lower_inverse(diag[j], linv)
        for a in range(m):  # W_a = L_{s_a j} L_jj^-1 (linv lower triangular)
            la = off[lo + a]
            for r in range(b):
                for c in range(b):
                    s = 0.0
                    for t in range(c, b):
                        s += la[r, t] * linv[t, c]
                    w[a, r, c] = s
        for a in range(m):  # acc_a = sum_b Z_{s_a s_b} W_b: first the diagonal blocks
            za = zdiag[l_row[lo + a]]
            for r in range(b):
                for c in range(b):
                    s = 0.0
                    for t in range(b):
                        s += za[r, t] * w[a, t, c]
                    acc[a, r, c] = s
        for bb in range(m):  # then the pairs s_a > s_b, found in column s_b (a merge walk)
            sb = l_row[lo + bb]
            p = l_ptr[sb]
            end = l_ptr[sb + 1]
            for a in range(bb + 1, m):
                sa = l_row[lo + a]
                while p < end and l_row[p] < sa:
                    p += 1
                if p == end or l_row[p] != sa:
                    return j
                zab = zoff[p]  # Z_{s_a s_b}; Z_{s_b s_a} is its transpose
                for r in range(b):
                    for c in range(b):
                        s1 = 0.0
                        s2 = 0.0
                        for t in range(b):
                            s1 += zab[r, t] * w[bb, t, c]
                            s2 += zab[t, r] * w[a, t, c]
                        acc[a, r, c] += s1
                        acc[bb, r, c] += s2
        zj = zdiag[j]  # Z_jj = L_jj^-T L_jj^-1 + sum_a acc_a^T W_a (symmetric: upper, mirror)
        for r in range(b):
            for c in range(r, b):
                s = 0.0
                for t in range(c, b):
                    s += linv[t, r] * linv[t, c]
                for a in range(m):
                    for t in range(b):
                        s += acc[a, t, r] * w[a, t, c]
                zj[r, c] = s
        for r in range(b):
            for c in range(r):
                zj[r, c] = zj[c, r]
        for a in range(m):  # Z_{s_a j} = -acc_a
            za = zoff[lo + a]
            for r in range(b):
                for c in range(b):
                    za[r, c] = -acc[a, r, c]
    return -1


def inverse_diagonal_blocks(l_ptr: npt.ArrayLike, l_row: npt.ArrayLike, diag: FloatArray,
                            off: FloatArray, *, overwrite: bool = False) -> FloatArray:
    """The diagonal blocks ``(A^-1)_jj`` of ``A = L L^T`` (selected inversion, module doc).

    Parameters
    ----------
    l_ptr : array_like of int, shape (n + 1,)
        Block column pointers of L's off-diagonal blocks.
    l_row : array_like of int, shape (nnz,)
        Their block rows, increasing within each column, all below the diagonal.
    diag : (n, b, b) float64
        The lower triangular diagonal blocks ``L_jj`` (positive diagonal).
    off : (nnz, b, b) float64
        The off-diagonal blocks, in the order of ``l_row``.
    overwrite : bool
        Compute in place: ``diag`` becomes the result and ``off`` the off-diagonal blocks of
        ``A^-1`` on L's pattern (no memory beyond a few blocks); else both are left unchanged.

    Returns
    -------
    (n, b, b) float64
        ``(A^-1)_jj`` in L's block order (the factor's permutation, if any, is the caller's).

    Raises
    ------
    SolverError
        The pattern is not closed under fill (not the pattern of a Cholesky factor).
    """
    ptr = np.ascontiguousarray(l_ptr, np.int64)
    rows = np.ascontiguousarray(l_row)
    if not (diag.ndim == 3 and off.ndim == 3 and diag.shape[1] == diag.shape[2]
            and off.shape[1:] == diag.shape[1:] and ptr.shape == (diag.shape[0] + 1,)
            and rows.shape == (off.shape[0],) and ptr[-1] == off.shape[0]):
        raise ValueError(f"need l_ptr (n+1,), l_row (nnz,), diag (n, b, b), off (nnz, b, b); "
                         f"got {ptr.shape}, {rows.shape}, {diag.shape}, {off.shape}")
    zdiag, zoff = (diag, off) if overwrite else (np.empty_like(diag), np.empty_like(off))
    status = _takahashi(ptr, rows, diag, off, zdiag, zoff)
    if status >= 0:
        raise SolverError(f"selected inversion: block column {status}'s rows are not all in "
                          "the factor's pattern (not a Cholesky factor's structure)")
    return zdiag
