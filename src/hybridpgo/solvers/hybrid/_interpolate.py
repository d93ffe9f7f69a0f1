"""Interpolated solving (paper III-E, eq. 31-34; DESIGN.md §6).

A constraint whose domain has more than ``D_max`` nodes is solved for a subset ``S_c`` of at most
``D_max`` nodes, kept uniformly along each side of its path (the endpoints always kept).  For a
kept node b whose parent is omitted, the chain of tree links between b and its closest kept
ancestor a (or the constraint's root) is merged into one constraint β: measurement
``p_β = Π p_i`` (eq. 32), stiffness ``S_β = Σ R_{b,i} S_i R_{b,i}^T`` (eq. 33, expressed in b's
frame, where our errors live), and b's block of B is temporarily ``B - J_α^T J_α + J_β^T J_β``
(eq. 31).  The reduced system (eq. 34) is solved like a full update (Woodbury or Givens).  Each
kept node's pose change is then spread over its chain the way TORO does (TORO.md, last section):
the rotation about the single axis of b's rotation change, in the cumulative-weight profile,
first; the translation linearly on the re-bent chain after.  The weights are
``1 / min diag`` of each node's rotational and translational 3x3 block of 𝔅(H).
𝔅(H) itself is still updated over the whole domain (eq. 24), which needs the O(d)
linearization; only the solve is reduced.
"""

from __future__ import annotations

import math

import numpy as np

from ..._cost import SCRATCH, jr_inv_matrix, residual_and_jr_inv, retract_into
from ..._numba import kernel
from ...geometry._kernels import so3_log_into
from ._dense import regularized_factor
from ._linearize import (
    linearize,
    mul_pose_into,
)
from ._step import accumulate_blocks, solve_single, step_temperature
from .problem import Problem, State, Update, Workspace, domain


# --------------------------------------------------------------------------- S_c
@kernel
def kept_positions(d: int, na: int, d_max: int, keep: np.ndarray) -> int:
    """Domain positions kept when solving for at most ``d_max`` of the d nodes.

    Each side (a side: positions ``0..na-1``, b side: ``na..d-1``, both listed from the
    endpoint upwards) gets a share of ``d_max`` proportional to its length (at least one node
    when it is not empty); within a side the kept nodes are spread uniformly from the endpoint
    to the top.  Returns the number kept, written in increasing position order.
    """
    nb = d - na
    ka = 0
    if na > 0:
        ka = max(1, min(na, (d_max * na + d // 2) // d))
        if nb > 0:
            ka = min(ka, d_max - 1)
    kb = min(nb, d_max - ka)
    n = 0
    for lo, length, k in ((0, na, ka), (na, nb, kb)):
        if k <= 0:
            continue
        if k == 1:
            keep[n] = lo
            n += 1
            continue
        prev = -1
        for j in range(k):
            p = lo + (j * (length - 1) + (k - 1) // 2) // (k - 1)
            if p > prev:
                keep[n] = p
                n += 1
                prev = p
    return n


@kernel
def chain_end(d: int, na: int, keep: np.ndarray, nk: int, j: int) -> int:
    """One past the last position of kept node j's chain: the next kept position on the same
    side (its closest kept ancestor), or the end of the side (the chain reaches the root)."""
    side_end = na if keep[j] < na else d
    if j + 1 < nk and keep[j + 1] < side_end:
        return keep[j + 1]
    return side_end


@kernel
def chain_top(pr: np.ndarray, pt: np.ndarray, d: int, na: int, p: int, end: int,
              eye: np.ndarray, zero: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the chain's top parent a in the constraint root's frame: the kept node at
    position ``end``, or the root itself (``eye``, ``zero``) when the chain reaches the top."""
    if end < (na if p < na else d):
        return pr[end], pt[end]
    return eye, zero


# --------------------------------------------------------------------------- eq. 31-33
@kernel
def _link_information(prob: Problem, node: int, om: np.ndarray) -> None:
    """Information of the tree link of ``node`` (6x6; a GPS link is translation-only)."""
    c = prob.link_constraint[node]
    om[:, :] = 0.0
    if c < prob.num_edges:
        lt = prob.edge_lt[c]
        n = 6
    else:
        lt = prob.gps_lt[c - prob.num_edges]
        n = 3
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for q in range(n):
                acc += lt[q, i] * lt[q, j]  # Omega = L L^T = (L^T)^T (L^T)
            om[i, j] = acc


@kernel
def _link_measurement(prob: Problem, state: State, node: int, zr: np.ndarray,
                      zt: np.ndarray) -> None:
    """The desired local transform of ``node``'s tree link, oriented parent -> child.

    A GPS link (a child of the earth) prescribes only a position: its rotation is the current
    local rotation.
    """
    c = prob.link_constraint[node]
    if c >= prob.num_edges:
        zr[:, :] = state.rot[node]
        zt[:] = prob.gps_pos[c - prob.num_edges]
        return
    r = prob.edge_rot[c]
    t = prob.edge_trans[c]
    if prob.link_forward[node]:
        zr[:, :] = r
        zt[:] = t
        return
    for i in range(3):
        zt[i] = -(r[0, i] * t[0] + r[1, i] * t[1] + r[2, i] * t[2])
        for j in range(3):
            zr[i, j] = r[j, i]


@kernel
def merged_constraint(prob: Problem, state: State, nodes: np.ndarray, k: int,
                      zr: np.ndarray, zt: np.ndarray, s_beta: np.ndarray) -> None:
    """The constraint β replacing the chain ``nodes[k-1] -> ... -> nodes[0]`` (top to b).

    ``(zr, zt) = p_β``, the product of the links' desired transforms from the chain's top
    parent a down to b (eq. 32); ``s_beta`` the stiffness Σ R_{b,i} S_i R_{b,i}^T in b's frame
    (eq. 33), ``R_{b,i}`` the desired rotation from link i's error frame to b (an error lives
    in the child's frame for a forward link, in the parent's for a reversed one).
    """
    r_acc = np.eye(3)
    t_acc = np.zeros(3)
    lr = np.empty((3, 3))
    lt_ = np.empty(3)
    tr = np.empty((3, 3))
    tt = np.empty(3)
    # rotations of the link frames from the top: rot_from_top[i] = R_{a, node i}
    for i in range(k - 1, -1, -1):
        _link_measurement(prob, state, nodes[i], lr, lt_)
        mul_pose_into(r_acc, t_acc, lr, lt_, tr, tt)
        r_acc[:, :] = tr
        t_acc[:] = tt
    zr[:, :] = r_acc
    zt[:] = t_acc
    # second pass: R_{a,frame_i}, then R_{b,frame_i} = R_{a,b}^T R_{a,frame_i}
    s_beta[:, :] = 0.0
    r_top = np.eye(3)  # R_{a, parent of node i}
    om = np.empty((6, 6))
    rot6 = np.zeros((6, 6))
    tmp = np.empty((6, 6))
    for i in range(k - 1, -1, -1):
        node = nodes[i]
        _link_measurement(prob, state, node, lr, lt_)
        r_child = r_top @ lr
        # a forward link's error lives in the child's frame; a reversed link's in the
        # parent's; a GPS link's in the earth's (= the top's parent, r_top = I there)
        gps_link = prob.link_constraint[node] >= prob.num_edges
        frame = r_child if (prob.link_forward[node] and not gps_link) else r_top
        r_bf = r_acc.T @ frame
        for p in range(3):
            for q in range(3):
                rot6[p, q] = r_bf[p, q]
                rot6[3 + p, 3 + q] = r_bf[p, q]
        _link_information(prob, node, om)
        tmp[:, :] = rot6 @ om
        s_beta += tmp @ rot6.T
        r_top = r_child


@kernel
def merged_blocks(prob: Problem, state: State, c: int, d: int, keep: np.ndarray, nk: int,
                  na: int, pr: np.ndarray, pt: np.ndarray, bc: np.ndarray) -> None:
    """Eq. 31 on the kept nodes' blocks ``bc[j]`` (B_c restricted to S_c): for every kept node
    whose parent is omitted, ``- J_α^T J_α + J_β^T J_β``."""
    s = prob.path_ptr[c]
    nodes = np.empty(d, np.int64)
    zr = np.empty((3, 3))
    zt = np.empty(3)
    s_beta = np.empty((6, 6))
    ws = np.empty((SCRATCH, 3, 3))
    e = np.empty(6)
    jri = np.empty((6, 6))
    eye = np.eye(3)
    zero = np.zeros(3)
    for j in range(nk):
        p = keep[j]
        end = chain_end(d, na, keep, nk, j)
        k = end - p
        if k <= 1:
            continue  # b's parent is kept: β = α
        b = prob.path_node[s + p]
        alpha = prob.link_constraint[b]
        old = state.contrib[prob.path_ptr[alpha]]  # α's domain is {b}
        for i in range(k):
            nodes[i] = prob.path_node[s + p + i]
        merged_constraint(prob, state, nodes, k, zr, zt, s_beta)
        # current merged transform T_{a,b} = P_a^-1 P_b (a: the chain's top parent)
        ra, ta = chain_top(pr, pt, d, na, p, end, eye, zero)
        # J_β = L_β^T Jr^-1(e_β), e_β = Log(p_β^-1 T_{a,b}); J_β^T J_β = Jr^-T S_β Jr^-1
        residual_and_jr_inv(zr, zt, ra, ta, pr[p], pt[p], e, ws)
        jr_inv_matrix(ws, jri)
        jtj = jri.T @ s_beta @ jri
        for q1 in range(6):
            for q2 in range(6):
                bc[j, q1, q2] += 0.5 * (jtj[q1, q2] + jtj[q2, q1]) - old[q1, q2]


@kernel
def reduced_factors(prob: Problem, state: State, c: int, d: int, na: int, kr: int,
                    wk: Workspace, keep: np.ndarray, nk: int, mu: float,
                    sub: Workspace) -> None:
    """B̃ (eq. 31) on the kept nodes, damped and factored into ``sub.lfac``; ``sub.jac`` gets
    the kept nodes' Jacobian blocks.  Must run right after ``accumulate_blocks`` (which updated
    𝔅(H) and c's contributions): ``B_c = 𝔅(H) - contribution of c`` at each kept node."""
    s = prob.path_ptr[c]
    jac = wk.jac
    bc = np.empty((nk, 6, 6))
    for j in range(nk):
        p = keep[j]
        i = prob.path_node[s + p]
        bc[j] = state.bdiag[i] - state.contrib[s + p]
        sub.jac[j] = jac[p]
    merged_blocks(prob, state, c, d, keep, nk, na, wk.path_rot, wk.path_trans, bc)
    for j in range(nk):
        scale = 0.0
        for q in range(6):
            acc = 0.0
            for t in range(kr):
                acc += jac[keep[j], t, q] * jac[keep[j], t, q]
            scale += acc
        regularized_factor(bc[j], scale, mu, sub.lfac[j])


# --------------------------------------------------------------------------- distribution
@kernel
def _rotation_exp(phi: np.ndarray, f: float, out: np.ndarray) -> None:
    """``out = Exp(f phi)`` (Rodrigues)."""
    x, y, z = f * phi[0], f * phi[1], f * phi[2]
    th = math.sqrt(x * x + y * y + z * z)
    if th < 1e-12:
        a = 1.0
        b = 0.5
    else:
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / (th * th)
    k = ((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0))
    for i in range(3):
        for j in range(3):
            k2 = 0.0
            for m in range(3):
                k2 += k[i][m] * k[m][j]
            out[i, j] = (1.0 if i == j else 0.0) + a * k[i][j] + b * k2


@kernel
def distribution_weights(bdiag_block: np.ndarray) -> tuple[float, float]:
    """TORO's weights of a node: 1 / the smallest diagonal entry of the rotational and of the
    translational 3x3 block of 𝔅(H) (a tiny floor keeps a free node finite)."""
    wr = min(bdiag_block[3, 3], bdiag_block[4, 4], bdiag_block[5, 5])
    wt = min(bdiag_block[0, 0], bdiag_block[1, 1], bdiag_block[2, 2])
    return 1.0 / max(wr, 1e-300), 1.0 / max(wt, 1e-300)


@kernel
def distribute_chain(state: State, nodes: np.ndarray, k: int, ra: np.ndarray, ta: np.ndarray,
                     rb_new: np.ndarray, tb_new: np.ndarray) -> None:
    """Move the chain ``nodes[k-1] (top) ... nodes[0] (= b)`` so that b reaches its desired
    pose relative to the chain's top parent a, TORO's way (DESIGN §6).

    ``(ra, ta)``, ``(rb_new, tb_new)``: poses of a and b's desired pose in any common frame.
    The locals of the chain nodes are rewritten; everything hanging below rides along.
    """
    rot = state.rot
    trans = state.trans
    # current poses of the chain nodes relative to a: q[j] for j = 1..k (q[0] = identity = a)
    qr = np.empty((k + 1, 3, 3))
    qt = np.empty((k + 1, 3))
    qr[0] = np.eye(3)
    qt[0] = 0.0
    for j in range(1, k + 1):
        i = nodes[k - j]
        mul_pose_into(qr[j - 1], qt[j - 1], rot[i], trans[i], qr[j], qt[j])
    # b's desired pose relative to a
    dr = ra.T @ rb_new
    dt = ra.T @ (tb_new - ta)
    # rotation change of b in a's frame: dR = R'_b R_b^T = Exp(phi)
    delta = dr @ qr[k].T
    phi6 = np.zeros(6)
    so3_log_into(delta, phi6)
    phi = phi6[3:]
    w_rot = np.empty(k + 1)
    w_tr = np.empty(k + 1)
    w_rot[0] = 0.0
    w_tr[0] = 0.0
    for j in range(1, k + 1):
        wr, wt = distribution_weights(state.bdiag[nodes[k - j]])
        w_rot[j] = w_rot[j - 1] + wr
        w_tr[j] = w_tr[j - 1] + wt
    # 1. rotations first: R''_j = Exp(f_j phi) R_j; positions recomputed with the old locals
    nr = np.empty((k + 1, 3, 3))
    nt = np.empty((k + 1, 3))
    nr[0] = np.eye(3)
    nt[0] = 0.0
    rexp = np.empty((3, 3))
    for j in range(1, k + 1):
        _rotation_exp(phi, w_rot[j] / w_rot[k], rexp)
        nr[j] = rexp @ qr[j]
        nt[j] = nt[j - 1] + nr[j - 1] @ trans[nodes[k - j]]
    nr[k] = dr  # the end reaches its desired rotation exactly
    # 2. then translations, linearly along the re-bent chain
    dpos = dt - nt[k]
    for j in range(1, k + 1):
        nt[j] = nt[j] + (w_tr[j] / w_tr[k]) * dpos
    # 3. new locals, each re-orthonormalized (one Newton step towards the polar factor, as
    # the retraction does): products along long chains would otherwise let rounding grow
    for j in range(1, k + 1):
        i = nodes[k - j]
        m = nr[j - 1].T @ nr[j]
        rot[i] = 0.5 * (m @ (3.0 * np.eye(3) - m.T @ m))
        trans[i] = nr[j - 1].T @ (nt[j] - nt[j - 1])


@kernel
def distribute(prob: Problem, state: State, c: int, d: int, na: int, keep: np.ndarray,
               nk: int, x: np.ndarray, t: float, pr: np.ndarray, pt: np.ndarray) -> None:
    """Apply the reduced step ``t x`` (kept node j: ``x[j]``) by distributing each kept node's
    desired pose change over its chain (path products ``pr, pt`` from before the step)."""
    s = prob.path_ptr[c]
    nodes = np.empty(d, np.int64)
    rb = np.empty((3, 3))
    tb = np.empty(3)
    er = np.empty((3, 3))
    tmp = np.empty((3, 3))
    eye = np.eye(3)
    zero = np.zeros(3)
    for j in range(nk):
        p = keep[j]
        end = chain_end(d, na, keep, nk, j)
        k = end - p
        for i in range(k):
            nodes[i] = prob.path_node[s + p + i]
        ra, ta = chain_top(pr, pt, d, na, p, end, eye, zero)
        # b's desired pose (root frame): P_b Exp(t x_b), as a full update would move it
        retract_into(pr[p], pt[p], x[j], t, rb, tb, er, tmp)
        if k == 1:  # nothing omitted: the plain update of b's local transform
            i = nodes[0]
            retract_into(state.rot[i], state.trans[i], x[j], t, state.rot[i], state.trans[i],
                         er, tmp)
        else:
            distribute_chain(state, nodes, k, ra, ta, rb, tb)


# --------------------------------------------------------------------------- the update
@kernel
def relax_interpolated(prob: Problem, state: State, wk: Workspace, sub: Workspace,
                       keep: np.ndarray, c: int, tau: float, mu: float, step_kind: int,
                       d_max: int) -> int:
    """Relax constraint c solving for at most ``d_max`` of its domain nodes (paper III-E).

    ``wk`` must hold the whole domain, ``sub`` and ``keep`` ``d_max`` nodes.  Returns an
    ``Update`` like :func:`~._step.relax`.
    """
    _s, d = domain(prob, c)
    kr, na = linearize(prob, c, state.rot, state.trans, wk, wk.jac)
    accumulate_blocks(prob, state, c, kr, wk.jac, mu, wk.lfac, wk.bc, False)
    nk = kept_positions(d, na, d_max, keep)
    reduced_factors(prob, state, c, d, na, kr, wk, keep, nk, mu, sub)
    for i in range(6):
        sub.r[i] = wk.r[i]
    solve_single(nk, kr, step_kind, sub)
    t, status = step_temperature(sub.x, nk, tau)
    if status == Update.REJECTED:
        return status
    distribute(prob, state, c, d, na, keep, nk, sub.x, t, wk.path_rot, wk.path_trans)
    return status
