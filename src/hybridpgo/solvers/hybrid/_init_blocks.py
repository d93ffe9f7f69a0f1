"""𝔅(H) from scratch (paper eq. 23): every constraint's blocks ``J_c^kT J_c^k``, no step.

The sweep relaxes constraint c against ``B_c = 𝔅(H) - 𝔅(J_c^T J_c)_old`` (eq. 24), so 𝔅(H)
and every constraint's contribution must exist before the first update.  Building them needs
only each constraint's linearization and ``J_c^kT J_c^k`` per domain node: no damped ``B_c``
factorization per node and no solve, which a sweep with ``apply=False`` would also do (that
was about as long as a sweep).  The arithmetic of every stored number is the sweep's
(:func:`~._step.accumulate_path` with no old contribution), so 𝔅(H) is bit-identical to the
one the sweep kernel would build in the same constraint order.
"""

from __future__ import annotations

from ..._numba import kernel
from ._linearize import linearize, relative_linearization
from ._step import accumulate_path
from .problem import Problem, State, domain, is_gps, new_workspace


@kernel
def init_blocks(prob: Problem, state: State, dmax: int) -> None:
    """Set ``state.bdiag`` to 𝔅(H) and ``state.contrib`` to every constraint's blocks at the
    current poses (constraints in index order; every row of ``contrib`` is written, so it may
    come uninitialized).  ``dmax``: the largest domain (workspace capacity)."""
    wk = new_workspace(max(dmax, 1))
    jac = wk.jac
    bdiag = state.bdiag
    contrib = state.contrib
    path_node = prob.path_node
    bdiag[:] = 0.0
    for c in range(prob.path_ptr.shape[0] - 1):
        s, d = domain(prob, c)
        if d == 0:
            continue
        if is_gps(prob, c):
            kr = linearize(prob, c, state.rot, state.trans, wk, jac)[0]
        else:  # as relax() does: the arrays one by one (no NamedTuple per call,
        # docs/contributing.md#data)
            kr = 6
            relative_linearization(path_node, prob.path_sign, s, d, prob.edge_rot[c],
                                   prob.edge_trans[c], prob.edge_lt[c], prob.robust_kind,
                                   prob.robust_scale, state.rot, state.trans, wk.path_rot,
                                   wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a, jac)
        contrib[s:s + d] = 0.0  # no old contribution: 𝔅(H) += acc - 0.0, which is acc
        accumulate_path(path_node, s, d, kr, jac, bdiag, contrib, 0.0, wk.lfac, wk.bc, False)
