"""A single update of a relative constraint in slices, resumable between calls.

The single update (:data:`~._step.RELAX`) of a constraint whose path is thousands of nodes long
takes milliseconds, longer than a frame's budget.  Here the same arithmetic runs in slices of
at most :data:`SLICE` domain nodes, each phase a pass over the domain:

1. **setup**: the path products, ``e0``, ``r`` and ``a = L^T Jr^-1(e0)``
   (:func:`~._linearize.relative_setup`, the whole domain in one slice);
2. **linearize**: the Jacobian blocks, 𝔅(H) and the damped factors of ``B_c``
   (:func:`~._linearize.relative_blocks`, :func:`~._step.accumulate_path`);
3. **gather**: Woodbury's first pass (:func:`~._step.woodbury_gather`), then the 6x6
   capacitance solve;
4. **spread**: Woodbury's second pass (:func:`~._step.woodbury_spread`), then the step's
   temperature (:func:`~._step.step_temperature`);
5. **apply**: ``T_i <- T_i Exp(t x_i)`` (:func:`~._step.retract_nodes`).

Run without a pause, the slices give the single update's result bit for bit (same products in
the same order).  Between calls other updates may change the poses and 𝔅(H) the slices read:
the step is then that of the linearization where the update started, applied to the current
poses, like any delayed step of a stochastic method.  𝔅(H) stays consistent throughout: each
domain entry's contribution is swapped for its new value in one place.

The update's progress lives in two small arrays (:func:`new_state`) and a
:class:`~.problem.Workspace` of its own, so other updates can run between its slices.
"""

from __future__ import annotations

import numpy as np

from ..._numba import cycle_counter, kernel
from ._linearize import relative_blocks, relative_setup
from ._step import (
    accumulate_path,
    retract_nodes,
    step_temperature,
    woodbury_factor,
    woodbury_gather,
    woodbury_spread,
    woodbury_start,
)
from .problem import EYE, ZERO, Problem, State, Update, Workspace, domain

#: Domain nodes per slice (about 0.1 ms of a linearization slice on this machine's cores).
SLICE = 64

# fields of the integer state
C, S, D, NA, PHASE, CURSOR, STATUS = range(7)
NUM_INT = 7
# fields of the float state: the step's temperature factor, the longest slice (cycles)
TEMP, SLICE_MAX = range(2)
NUM_FLOAT = 2
# phases
SETUP, LINEARIZE, GATHER, SPREAD, APPLY, DONE = range(6)


def new_state() -> tuple[np.ndarray, np.ndarray]:
    """The (integer, float) progress arrays of a sliced update; :func:`begin` fills them."""
    return np.zeros(NUM_INT, np.int64), np.zeros(NUM_FLOAT)


@kernel
def begin(prob: Problem, c: int, lu: np.ndarray, lf: np.ndarray) -> None:
    """Start relaxing relative constraint c in slices (nothing is computed yet)."""
    s, d = domain(prob, c)
    lu[C] = c
    lu[S] = s
    lu[D] = d
    lu[NA] = 0
    lu[PHASE] = SETUP if d > 0 else DONE
    lu[CURSOR] = 0
    lu[STATUS] = Update.APPLIED
    lf[TEMP] = 0.0
    lf[SLICE_MAX] = 0.0


@kernel
def valid(prob: Problem, lu: np.ndarray) -> bool:
    """True while the constraint's domain is the one the update started with."""
    s, d = domain(prob, lu[C])
    return bool(s == lu[S] and d == lu[D])


@kernel
def _slice(prob: Problem, state: State, wk: Workspace, lu: np.ndarray, lf: np.ndarray,
           tau: float, mu: float) -> None:
    """One slice of the current phase (module docstring)."""
    c, s, d, na = lu[C], lu[S], lu[D], lu[NA]
    phase = lu[PHASE]
    k0 = lu[CURSOR]
    k1 = min(d, k0 + SLICE)
    if phase == SETUP:
        lu[NA] = relative_setup(prob.path_node, prob.path_sign, s, d, prob.edge_rot[c],
                                prob.edge_trans[c], prob.edge_lt[c], prob.robust_kind,
                                prob.robust_scale, state.rot, state.trans, wk.path_rot,
                                wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a)
        lu[PHASE] = LINEARIZE
        lu[CURSOR] = 0
        return
    if phase == LINEARIZE:
        rb = wk.iws[EYE]
        tb = wk.iws[ZERO][0]
        if na < d:
            rb = wk.path_rot[na]
            tb = wk.path_trans[na]
        n = k1 - k0
        relative_blocks(prob.path_sign, s + k0, n, rb, tb, wk.path_rot[k0:k1],
                        wk.path_trans[k0:k1], wk.a, wk.ws, wk.jac[k0:k1])
        accumulate_path(prob.path_node, s + k0, n, 6, wk.jac[k0:k1], state.bdiag,
                        state.contrib, mu, wk.lfac[k0:k1], wk.bc, True)
        if k1 == d:
            woodbury_start(6, wk.bc)
            lu[PHASE] = GATHER
            k1 = 0
    elif phase == GATHER:
        woodbury_gather(k0, k1, 6, wk.jac, wk.lfac, wk.w, wk.bc)
        if k1 == d:
            if woodbury_factor(6, wk.bc, wk.r, wk.sv):
                lu[PHASE] = SPREAD
            else:  # not positive definite: nothing applied
                lu[STATUS] = Update.REJECTED
                lu[PHASE] = DONE
            k1 = 0
    elif phase == SPREAD:
        woodbury_spread(k0, k1, 6, wk.lfac, wk.w, wk.x, wk.sv)
        if k1 == d:
            t, status = step_temperature(wk.x, d, tau)
            lf[TEMP] = t
            lu[STATUS] = status
            lu[PHASE] = DONE if status == Update.REJECTED else APPLY
            k1 = 0
    elif phase == APPLY:
        retract_nodes(prob.path_node, s + k0, k1 - k0, wk.x[k0:k1], lf[TEMP], state.rot,
                      state.trans, wk.ws)
        if k1 == d:
            lu[PHASE] = DONE
            k1 = 0
    lu[CURSOR] = k1


@kernel
def advance(prob: Problem, state: State, wk: Workspace, lu: np.ndarray, lf: np.ndarray,
            tau: float, mu: float, deadline: np.uint64) -> bool:
    """Run slices until the update is done (True) or the next slice, predicted to take as
    long as the longest slice after the setup so far, would end after ``deadline`` (False).
    At least one slice runs per call.  ``wk`` must hold the constraint's domain."""
    ran = False
    while lu[PHASE] != DONE:
        if ran and float(cycle_counter()) + lf[SLICE_MAX] > float(deadline):
            return False
        setup = lu[PHASE] == SETUP
        t0 = cycle_counter()
        _slice(prob, state, wk, lu, lf, tau, mu)
        dc = float(cycle_counter() - t0)
        if not setup and dc > lf[SLICE_MAX]:
            lf[SLICE_MAX] = dc
        ran = True
    return True
