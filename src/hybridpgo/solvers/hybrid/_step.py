"""The hybrid Hessian step of one constraint (paper III-C, III-D, III-H; DESIGN.md §4).

𝔅(H) is the block diagonal of ``H = sum_c J_c^T J_c``; every constraint remembers the blocks it
last added (eq. 24), so relaxing c updates 𝔅(H) in O(d).  The step solves

    (J_c^T J_c + B_c) x_c = J_c^T r_c,      B_c = 𝔅(H) - 𝔅(J_c^T J_c)      (eq. 25/28)

either in Woodbury form (O(d), default) or by the paper's Givens triangularization (O(d^2)).
:func:`cap_and_apply` is the one place where a step is scaled by the temperature, capped at
pi/8 (III-H) and applied; single and batch updates both use it.
"""

from __future__ import annotations

import math

import numpy as np

from ..._cost import retract_into
from ..._numba import kernel
from ._dense import chol_inplace, chol_solve_cols, regularized_factor, solve_lt
from ._linearize import linearize
from .problem import Problem, State, StepKind, Update, Workspace, domain

#: Largest rotation (rad) any node may turn in one step (paper III-H).
MAX_ROTATION = math.pi / 8.0


@kernel
def accumulate_blocks(prob: Problem, state: State, c: int, kr: int, jac: np.ndarray,
                      mu: float, lfac: np.ndarray, bc: np.ndarray, factor: bool = True) -> None:
    """Eq. 23/24: B_c = 𝔅(H) - 𝔅(J_c^T J_c)_old; 𝔅(H) += new - old; factor the damped B_c
    into ``lfac`` (unless ``factor`` is False: interpolated solving factors its own blocks)."""
    s, d = domain(prob, c)
    bdiag = state.bdiag
    contrib = state.contrib
    for k in range(d):
        i = prob.path_node[s + k]
        scale = 0.0
        e = s + k
        # J^T J is symmetric: compute the upper triangle, mirror every store (the blocks stay
        # exactly symmetric, so B_c needs no symmetrization before its factorization)
        for p in range(6):
            for q in range(p, 6):
                acc = 0.0
                for t in range(kr):
                    acc += jac[k, t, p] * jac[k, t, q]
                old = contrib[e, p, q]
                b_old = bdiag[i, p, q]
                v = b_old + (acc - old)
                bdiag[i, p, q] = v
                bdiag[i, q, p] = v
                contrib[e, p, q] = acc
                contrib[e, q, p] = acc
                bc[p, q] = b_old - old
                bc[q, p] = b_old - old
            scale += contrib[e, p, p]
        if factor:
            regularized_factor(bc, scale, mu, lfac[k])


@kernel
def woodbury_solve(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray,
                   y: np.ndarray, x: np.ndarray) -> None:
    """x = B^-1 J^T (I + J B^-1 J^T)^-1 r with B = blockdiag(L_k L_k^T): O(d) (DESIGN §4).

    With W_k = L_k^-1 J_k^T (forward substitution), S = I + sum_k W_k^T W_k and
    x_k = L_k^-T W_k S^-1 r.  ``y`` holds the W_k.
    """
    smat = np.zeros((6, 6))
    for i in range(kr):
        smat[i, i] = 1.0
    for k in range(d):
        lk = lfac[k]
        for i in range(6):
            inv = 1.0 / lk[i, i]
            for q in range(kr):
                acc = jac[k, q, i]
                for m in range(i):
                    acc -= lk[i, m] * y[k, m, q]
                y[k, i, q] = acc * inv
        for p in range(kr):
            for q in range(p, kr):
                acc = 0.0
                for i in range(6):
                    acc += y[k, i, p] * y[k, i, q]
                smat[p, q] += acc
    for p in range(kr):
        for q in range(p):
            smat[p, q] = smat[q, p]
    if not chol_inplace(smat, kr):
        for k in range(d):
            x[k, :] = np.nan
        return
    zz = np.empty((6, 1))
    for i in range(kr):
        zz[i, 0] = r[i]
    chol_solve_cols(smat, kr, zz, 1)
    v = np.empty(6)
    for k in range(d):
        lk = lfac[k]
        for i in range(6):
            acc = 0.0
            for q in range(kr):
                acc += y[k, i, q] * zz[q, 0]
            v[i] = acc
        solve_lt(lk, v, x[k])


@kernel
def givens_solve(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray,
                 x: np.ndarray) -> None:
    """The paper's solve (eq. 29-30): Givens-triangularize [J; Gamma] x = [r; 0], O(d^2).

    Gamma is block diagonal with upper-triangular blocks Gamma_k = L_k^T (Gamma^T Gamma = B).
    Each J row is rotated into the Gamma rows column by column; the Gamma rows fill in to the
    right, giving a dense upper-triangular R, then R x = b is back-substituted.
    """
    n = 6 * d
    rr = np.zeros((n, n))
    rhs = np.zeros(n)
    for k in range(d):
        for i in range(6):
            for j in range(i, 6):
                rr[6 * k + i, 6 * k + j] = lfac[k, j, i]
    w = np.zeros((kr, n))
    wr = np.zeros(kr)
    for q in range(kr):
        wr[q] = r[q]
        for k in range(d):
            for i in range(6):
                w[q, 6 * k + i] = jac[k, q, i]
    for col in range(n):
        for q in range(kr):
            b = w[q, col]
            if b == 0.0:
                continue
            a = rr[col, col]
            h = math.hypot(a, b)
            cs = a / h
            sn = b / h
            for j in range(col, n):
                u = rr[col, j]
                v = w[q, j]
                rr[col, j] = cs * u + sn * v
                w[q, j] = -sn * u + cs * v
            u = rhs[col]
            v = wr[q]
            rhs[col] = cs * u + sn * v
            wr[q] = -sn * u + cs * v
    for i in range(n - 1, -1, -1):
        acc = rhs[i]
        for j in range(i + 1, n):
            acc -= rr[i, j] * rhs[j]
        rhs[i] = acc / rr[i, i]
    for k in range(d):
        for i in range(6):
            x[k, i] = rhs[6 * k + i]


@kernel
def step_temperature(x: np.ndarray, n: int, tau: float) -> tuple[float, int]:
    """The factor t a step ``x[:n]`` is applied with (paper III-H) and the outcome.

    ``t = tau``, or smaller so that the largest rotation of ``t x`` is exactly pi/8 (CAPPED);
    REJECTED when the step is not finite.
    """
    biggest = 0.0
    for k in range(n):
        for i in range(6):
            if not math.isfinite(x[k, i]):
                return 0.0, Update.REJECTED
        ang = math.sqrt(x[k, 3] ** 2 + x[k, 4] ** 2 + x[k, 5] ** 2)
        if ang > biggest:
            biggest = ang
    if tau * biggest > MAX_ROTATION:
        return MAX_ROTATION / biggest, Update.CAPPED
    return tau, Update.APPLIED


@kernel
def cap_and_apply(nodes: np.ndarray, start: int, n: int, x: np.ndarray, tau: float,
                  state: State, ws: np.ndarray) -> int:
    """Apply ``T_i <- T_i Exp(t x_k)`` to ``i = nodes[start + k]``, k < n, with the factor t of
    :func:`step_temperature`.  Returns APPLIED, CAPPED, or REJECTED (nothing applied)."""
    t, status = step_temperature(x, n, tau)
    if status == Update.REJECTED:
        return status
    rot = state.rot
    trans = state.trans
    for k in range(n):
        i = nodes[start + k]
        retract_into(rot[i], trans[i], x[k], t, rot[i], trans[i], ws[0], ws[1])
    return status


@kernel
def solve_single(d: int, kr: int, step_kind: int, wk: Workspace) -> None:
    """The step ``wk.x`` of eq. 25 from ``wk.jac``, ``wk.lfac``, ``wk.r`` (Woodbury or Givens)."""
    if step_kind == StepKind.GIVENS:
        givens_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.x)
    else:
        woodbury_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.w, wk.x)


@kernel
def relax(prob: Problem, state: State, wk: Workspace, c: int, tau: float, mu: float,
          step_kind: int, apply: bool) -> int:
    """Relax constraint c (paper eq. 25): linearize, update 𝔅(H), solve, apply ``tau x``.

    With ``apply=False`` only 𝔅(H) and c's contributions are updated.  Returns an ``Update``.
    """
    s, d = domain(prob, c)
    if d == 0:
        return Update.APPLIED
    kr, _na = linearize(prob, c, state.rot, state.trans, wk, wk.jac)
    accumulate_blocks(prob, state, c, kr, wk.jac, mu, wk.lfac, wk.bc)
    if not apply:
        return Update.APPLIED
    solve_single(d, kr, step_kind, wk)
    return cap_and_apply(prob.path_node, s, d, wk.x, tau, state, wk.ws)
