"""The hybrid Hessian solver (Grimes, Anguelov & LeCun, IROS 2010), one file per paper section.

=========================  ===================================================================
module                     paper
=========================  ===================================================================
``problem``                named data: :class:`Problem`, :class:`State`, :class:`Workspace`
``_dense``                 small dense Cholesky, the damped factor of a block of B (III-D)
``_linearize``             III-B: path products, whitened Jacobian blocks (eq. 17-22)
``_step``                  III-C/D/H: 𝔅(H) (eq. 23/24), damping, Woodbury, Givens (eq. 25-30),
                           the pi/8 cap and the retraction
``_interpolate``           III-E: interpolated solving (D_max): kept nodes, reduced system
``_merge``                 III-E: a chain of omitted nodes merged into one constraint (eq. 31-33)
``_distribute``            III-E: a kept node's change spread over its chain (TORO's way)
``_batch``                 III-F/G: batch updates (eq. 35-37), GPS batches
``_batch_union``           III-F: the union of a batch's domains, its entries and segments
``_batch_solve``           III-F: the batch's solve, dense or Woodbury over segments (eq. 37)
``_batch_reduced``         III-E/G: a batch solved for its kept nodes (interpolated batches)
``_sweep``                 Algorithm 1: sweeps in root-depth order, GPS buffering
``solver``                 :class:`HybridSolver` (built once, run or stepped), :func:`solve_hybrid`
=========================  ===================================================================
"""

from __future__ import annotations

from ..._numba import cycles_per_second as cycles_per_second
from ..config import HybridConfig as HybridConfig
from .problem import StepKind as StepKind
from .solver import STEP_KINDS as STEP_KINDS
from .solver import HybridSolver as HybridSolver
from .solver import StepReport as StepReport
from .solver import solve_hybrid as solve_hybrid

__all__ = ["STEP_KINDS", "HybridConfig", "HybridSolver", "StepKind", "StepReport",
           "cycles_per_second", "solve_hybrid"]
