"""Small dense linear algebra of the hybrid steps: Cholesky and the damped factor of 𝔅 blocks.

Fixed-size loops over caller-provided arrays (docs/contributing.md#kernels); divisions are hoisted
because they
dominate the cost of 6x6 factorizations.
"""

from __future__ import annotations

import math

import numpy as np

from ..._numba import kernel

#: A block of B_c is damped by ``mu * trace(B)/6 + TINY * scale``
#: (docs/mathematics.md#hybrid-step); ``scale`` is the
#: trace of the constraint's own block, so a node that only constraint c touches still gets a
#: finite, well-scaled step.
TINY = 1e-9
#: The damping is raised tenfold at most this many times until the block factors.
MAX_DAMPING_ESCALATIONS = 60


@kernel
def chol_inplace(a: np.ndarray, n: int) -> bool:
    """Lower Cholesky factor of the leading n x n block of ``a``, in place. False if not SPD."""
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if not (s > 0.0):
            return False
        d = math.sqrt(s)
        a[j, j] = d
        inv_d = 1.0 / d  # one division per column (divisions dominate 6x6 factorizations)
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s * inv_d
        for i in range(j):
            a[i, j] = 0.0
    return True


@kernel
def chol_solve_cols(lo: np.ndarray, n: int, b: np.ndarray, ncols: int) -> None:
    """Solve (L L^T) X = B in place for the first ``ncols`` columns of ``b`` (n rows)."""
    for c in range(ncols):
        for i in range(n):
            s = b[i, c]
            for k in range(i):
                s -= lo[i, k] * b[k, c]
            b[i, c] = s / lo[i, i]
        for i in range(n - 1, -1, -1):
            s = b[i, c]
            for k in range(i + 1, n):
                s -= lo[k, i] * b[k, c]
            b[i, c] = s / lo[i, i]


@kernel
def solve_lt(lo: np.ndarray, v: np.ndarray, x: np.ndarray) -> None:
    """Solve ``L^T x = v`` for a (6, 6) lower factor L (back substitution)."""
    for i in range(5, -1, -1):
        acc = v[i]
        for m in range(i + 1, 6):
            acc -= lo[m, i] * x[m]
        x[i] = acc / lo[i, i]


@kernel
def regularized_factor(bc: np.ndarray, scale: float, mu: float, out: np.ndarray) -> int:
    """``out`` = lower Cholesky factor of sym(bc) + (mu tr(bc)/6 + TINY scale) I
    (docs/mathematics.md#hybrid-step).

    Rounding in ``bdiag - old`` can leave ``bc`` slightly indefinite; the damping is raised
    tenfold until the factorization succeeds.  Returns the number of escalations (0: the first
    damping worked; ``MAX_DAMPING_ESCALATIONS``: it never did, ``out`` is not a factor).
    """
    tr = 0.0
    for i in range(6):
        tr += bc[i, i]
    if tr < 0.0:
        tr = 0.0
    damp = mu * tr / 6.0 + TINY * scale
    if not (damp > 0.0):
        damp = 1e-300
    for k in range(MAX_DAMPING_ESCALATIONS):
        for i in range(6):
            for j in range(i + 1):  # the factorization reads the lower triangle only
                out[i, j] = 0.5 * (bc[i, j] + bc[j, i])
            out[i, i] += damp
        if chol_inplace(out, 6):
            return k
        damp *= 10.0
        if damp < 1e-12 * (tr + scale):
            damp = 1e-12 * (tr + scale)
    return MAX_DAMPING_ESCALATIONS
