"""Sparse symmetric linear algebra: fill-reducing orderings, factorizations, SPD solves.

The exact solver, the chordal and relaxation starts and the covariances factor symmetric
positive definite matrices given as the values of a fixed pattern of their lower triangle
(analyze once, factor many times).  Backends: CHOLMOD (through cvxopt), SciPy's SuperLU, and
the block Cholesky of :mod:`._block_cholesky` for sparse factors of 6x6 blocks.
"""

from ._block_cholesky import BlockCholesky as BlockCholesky
from ._factor import CscPattern as CscPattern
from ._factor import NotPositiveDefinite as NotPositiveDefinite
from ._factor import SparseSPD as SparseSPD
from ._factor import SymmetricPattern as SymmetricPattern
from ._factor import check_pivots as check_pivots
from ._factor import cholmod_available as cholmod_available
from ._factor import fill_reducing_order as fill_reducing_order
from ._factor import make_factorizer as make_factorizer
from ._factor import not_positive_definite as not_positive_definite
from ._factor import shared_patterns as shared_patterns
from ._factor import solve_spd as solve_spd

__all__ = [
    "BlockCholesky",
    "CscPattern",
    "NotPositiveDefinite",
    "SparseSPD",
    "SymmetricPattern",
    "check_pivots",
    "cholmod_available",
    "fill_reducing_order",
    "make_factorizer",
    "not_positive_definite",
    "shared_patterns",
    "solve_spd",
]
