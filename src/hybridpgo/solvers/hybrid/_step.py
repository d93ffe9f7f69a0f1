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
from ._dense import chol_inplace, regularized_factor
from ._linearize import linearize, relative_linearization
from .problem import Problem, State, StepKind, Update, Workspace, domain, is_gps

#: Largest rotation (rad) any node may turn in one step (paper III-H).
MAX_ROTATION = math.pi / 8.0


@kernel
def accumulate_path(path_node: np.ndarray, s: int, d: int, kr: int, jac: np.ndarray,
                    bdiag: np.ndarray, contrib: np.ndarray, mu: float, lfac: np.ndarray,
                    bc: np.ndarray, factor: bool) -> None:
    """:func:`accumulate_blocks` for the domain ``path_node[s:s + d]`` with the arrays passed
    one by one (what the update kernels call: fewer arrays, fewer reference-count pairs)."""
    for k in range(d):
        i = path_node[s + k]
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
                if factor:
                    bc[p, q] = b_old - old
                    bc[q, p] = b_old - old
            scale += contrib[e, p, p]
        if factor:
            regularized_factor(bc, scale, mu, lfac[k])


@kernel
def accumulate_blocks(prob: Problem, state: State, c: int, kr: int, jac: np.ndarray,
                      mu: float, lfac: np.ndarray, bc: np.ndarray, factor: bool = True) -> None:
    """Eq. 23/24: B_c = 𝔅(H) - 𝔅(J_c^T J_c)_old; 𝔅(H) += new - old; factor the damped B_c
    into ``lfac`` (unless ``factor`` is False: interpolated solving factors its own blocks)."""
    s, d = domain(prob, c)
    accumulate_path(prob.path_node, s, d, kr, jac, state.bdiag, state.contrib, mu, lfac, bc,
                    factor)


@kernel
def woodbury_solve(d: int, kr: int, jac: np.ndarray, lfac: np.ndarray, r: np.ndarray,
                   y: np.ndarray, x: np.ndarray, smat: np.ndarray, sv: np.ndarray) -> None:
    """x = B^-1 J^T (I + J B^-1 J^T)^-1 r with B = blockdiag(L_k L_k^T): O(d) (DESIGN §4).

    With W_k = L_k^-1 J_k^T (forward substitution), S = I + sum_k W_k^T W_k and
    x_k = L_k^-T W_k S^-1 r.  ``y`` holds the W_k; ``smat`` (6, 6) and ``sv`` (2, 6) scratch.
    """
    for p in range(6):
        for q in range(6):
            smat[p, q] = 0.0
    for i in range(kr):
        smat[i, i] = 1.0
    for k in range(d):
        for i in range(6):
            inv = 1.0 / lfac[k, i, i]
            for q in range(kr):
                acc = jac[k, q, i]
                for m in range(i):
                    acc -= lfac[k, i, m] * y[k, m, q]
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
            for i in range(6):
                x[k, i] = np.nan
        return
    # S z = r, column by column as chol_solve_cols does (z in sv[0])
    for i in range(kr):
        acc = r[i]
        for m in range(i):
            acc -= smat[i, m] * sv[0, m]
        sv[0, i] = acc / smat[i, i]
    for i in range(kr - 1, -1, -1):
        acc = sv[0, i]
        for m in range(i + 1, kr):
            acc -= smat[m, i] * sv[0, m]
        sv[0, i] = acc / smat[i, i]
    for k in range(d):
        for i in range(6):
            acc = 0.0
            for q in range(kr):
                acc += y[k, i, q] * sv[0, q]
            sv[1, i] = acc
        for i in range(5, -1, -1):  # L_k^T x_k = v (as solve_lt)
            acc = sv[1, i]
            for m in range(i + 1, 6):
                acc -= lfac[k, m, i] * x[k, m]
            x[k, i] = acc / lfac[k, i, i]


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
def apply_step(nodes: np.ndarray, start: int, n: int, x: np.ndarray, tau: float,
               rot: np.ndarray, trans: np.ndarray, ws: np.ndarray) -> int:
    """:func:`cap_and_apply` with the state's arrays passed one by one."""
    t, status = step_temperature(x, n, tau)
    if status == Update.REJECTED:
        return status
    er = ws[0]
    tmp = ws[1]
    for k in range(n):
        i = nodes[start + k]
        retract_into(rot[i], trans[i], x[k], t, rot[i], trans[i], er, tmp)
    return status


@kernel
def cap_and_apply(nodes: np.ndarray, start: int, n: int, x: np.ndarray, tau: float,
                  state: State, ws: np.ndarray) -> int:
    """Apply ``T_i <- T_i Exp(t x_k)`` to ``i = nodes[start + k]``, k < n, with the factor t of
    :func:`step_temperature`.  Returns APPLIED, CAPPED, or REJECTED (nothing applied)."""
    return apply_step(nodes, start, n, x, tau, state.rot, state.trans, ws)


@kernel
def solve_single(d: int, kr: int, step_kind: int, wk: Workspace) -> None:
    """The step ``wk.x`` of eq. 25 from ``wk.jac``, ``wk.lfac``, ``wk.r`` (Woodbury or Givens;
    ``wk.bc`` is overwritten)."""
    if step_kind == StepKind.GIVENS:
        givens_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.x)
    else:
        woodbury_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.w, wk.x, wk.bc, wk.sv)


@kernel
def relax(prob: Problem, state: State, wk: Workspace, c: int, tau: float, mu: float,
          step_kind: int, apply: bool) -> int:
    """Relax constraint c (paper eq. 25): linearize, update 𝔅(H), solve, apply ``tau x``.

    With ``apply=False`` only 𝔅(H) and c's contributions are updated.  Returns an ``Update``.
    The callees get single arrays, not the NamedTuples (see :func:`relative_linearization`).
    """
    s, d = domain(prob, c)
    if d == 0:
        return Update.APPLIED
    if is_gps(prob, c):
        kr = linearize(prob, c, state.rot, state.trans, wk, wk.jac)[0]
    else:
        kr = 6
        relative_linearization(prob.path_node, prob.path_sign, s, d, prob.edge_rot[c],
                               prob.edge_trans[c], prob.edge_lt[c], prob.robust_kind,
                               prob.robust_scale, state.rot, state.trans, wk.path_rot,
                               wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a, wk.jac)
    accumulate_path(prob.path_node, s, d, kr, wk.jac, state.bdiag, state.contrib, mu, wk.lfac,
                    wk.bc, True)
    if not apply:
        return Update.APPLIED
    if step_kind == StepKind.GIVENS:
        givens_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.x)
    else:
        woodbury_solve(d, kr, wk.jac, wk.lfac, wk.r, wk.w, wk.x, wk.bc, wk.sv)
    return apply_step(prob.path_node, s, d, wk.x, tau, state.rot, state.trans, wk.ws)
