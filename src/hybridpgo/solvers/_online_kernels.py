"""Kernels of the online mode (DESIGN.md §11): growing paths, budgeted relaxation, estimates.

The online solver keeps the arrays of :class:`~.hybrid.problem.Problem` and
:class:`~.hybrid.problem.State` at a capacity that doubles, and relaxes constraints with the
single-constraint step (:func:`~.hybrid._step.relax`) and the batch step
(:mod:`~.hybrid._batch`) of the whole-graph solver.  What is new here:

* :func:`path_lengths` / :func:`fill_paths`: a new constraint's domain (DESIGN §2) by a walk to
  the lowest common ancestor on the depth array, O(d);
* :func:`relax_list`: Algorithm 1's loop over a list of constraints that stops before an update
  whose *predicted* cost would pass the deadline (a cost model per domain node, learnt from the
  cycle counts of earlier updates), records every constraint's χ² before its update (the
  priority of later frames), and reuses caller-owned buffers (no O(T) allocation per frame);
* :func:`local_batch`: the batch update of a set of constraints (III-F/G) that always takes the
  segmented Woodbury solve, whose cost is bounded by the set (never the dense normal
  equations over the union of the domains);
* :func:`candidates`: the bounded candidate set of spare-time updates, ordered by χ².
"""

from __future__ import annotations

import numpy as np

from .._cost import residual_and_jr_inv, whiten_residual
from .._numba import cycle_counter, kernel
from .._tree_kernels import global_pose
from .hybrid._batch import batch_relax_exact
from .hybrid._linearize import endpoints, num_a_side, path_products
from .hybrid._step import relax
from .hybrid.problem import (
    BATCH_REJECTED,
    Problem,
    State,
    Update,
    Workspace,
    domain,
    is_gps,
)

#: Entries of the cost model array (cycles): base cost of an update, cost per domain node of a
#: single update, cost per domain entry of a batch update.
MODEL_BASE = 0
MODEL_NODE = 1
MODEL_BATCH = 2
#: Weight of a new sample in the cost model's moving averages.
MODEL_RATE = 1.0 / 32.0
#: Predictions are the model times this margin (the model is a mean; updates vary around it).
MODEL_MARGIN = 1.5
#: Cycles per floating-point operation assumed for the dense factorization of a local batch.
CYCLES_PER_FLOP = 1.0

#: Positions in the ``counts`` array of :func:`relax_list`.
C_DONE = 0
C_CAPPED = 1
C_REJECTED = 2
C_BATCHES = 3
C_SKIPPED = 4
NUM_C = 5


@kernel
def _gps_chi2(prob: Problem, state: State, c: int, ro: np.ndarray, to: np.ndarray) -> float:
    g = c - prob.num_edges
    node = prob.path_node[prob.path_ptr[c]]  # a GPS domain starts at its pose
    global_pose(node, prob.parent, state.rot, state.trans, ro, to)
    lt = prob.gps_lt[g]
    s = 0.0
    for p in range(3):
        acc = 0.0
        for q in range(p, 3):
            acc += lt[p, q] * (to[q] - prob.gps_pos[g, q])
        s += acc * acc
    return s


@kernel
def _edge_chi2(prob: Problem, state: State, c: int, wk: Workspace) -> float:
    """χ² of relative constraint c at the current estimate, from its path only (O(d))."""
    d = domain(prob, c)[1]
    na = path_products(prob, c, state.rot, state.trans, wk.path_rot, wk.path_trans)
    ra, ta, rb, tb = endpoints(wk.path_rot, wk.path_trans, na, d)
    residual_and_jr_inv(prob.edge_rot[c], prob.edge_trans[c], ra, ta, rb, tb, wk.e, wk.ws)
    whiten_residual(prob.edge_lt[c], wk.e, 6, wk.r)
    acc = 0.0
    for i in range(6):
        acc += wk.r[i] * wk.r[i]
    return acc


# --------------------------------------------------------------------------- cost model
@kernel
def _predict(model: np.ndarray, d: int, batch: bool) -> float:
    per = model[MODEL_BATCH] if batch else model[MODEL_NODE]
    return float(MODEL_MARGIN * (model[MODEL_BASE] + per * d))


@kernel
def _kid(prob: Problem, canonical: int) -> int:
    """Kernel constraint index of a canonical id (edge e >= 0, GPS reading g as -(g+1))."""
    return canonical if canonical >= 0 else prob.num_edges - canonical - 1


@kernel
def batch_work(prob: Problem, depth: np.ndarray, c: int) -> int:
    """Work of constraint c in a batch update, in domain-node units: its domain plus the depth
    of its root (the batch computes the root's global pose, O(depth))."""
    s, d = domain(prob, c)
    if d == 0:
        return 0
    na = num_a_side(prob, c)
    top = prob.path_node[s + na - 1] if na > 0 else prob.path_node[s + d - 1]
    return int(d + depth[prob.parent[top]])


@kernel
def _capacitance_cost(nb: int) -> float:
    """Predicted cycles of the dense factorization of a batch's (6 nb)^2 capacitance matrix
    ((6 nb)^3 / 3 flops)."""
    return MODEL_MARGIN * CYCLES_PER_FLOP * 72.0 * nb * nb * nb


@kernel
def _learn(model: np.ndarray, d: int, dc: float, batch: bool) -> None:
    """Moving averages of the base cost (small domains) and of the cost per domain node."""
    if d <= 4 and not batch:
        sample = dc
        cur = model[MODEL_BASE]
        model[MODEL_BASE] = cur + MODEL_RATE * (min(sample, 4.0 * cur) - cur)
        return
    k = MODEL_BATCH if batch else MODEL_NODE
    sample = max(dc - model[MODEL_BASE], 0.0) / d
    cur = model[k]
    model[k] = cur + MODEL_RATE * (min(sample, 4.0 * cur) - cur)


# --------------------------------------------------------------------------- relaxation
@kernel
def _flush(prob: Problem, state: State, buf: np.ndarray, nbuf: int, tau: float, mu: float,
           slot: np.ndarray, xb: np.ndarray, nodes: np.ndarray, model: np.ndarray,
           counts: np.ndarray) -> bool:
    """Relax the buffered GPS readings as one batch (III-G); True when it was rejected."""
    t0 = cycle_counter()
    nu = batch_relax_exact(prob, state, buf, nbuf, tau, mu, slot, xb, nodes, 0, False)
    dc = float(cycle_counter() - t0)
    ne = 0
    for q in range(nbuf):
        ne += domain(prob, buf[q])[1]
    _learn(model, max(ne, 1), dc, True)
    counts[C_BATCHES] += 1
    if nu == BATCH_REJECTED:
        counts[C_REJECTED] += nbuf
        return True
    return False


@kernel
def relax_list(prob: Problem, state: State, wk: Workspace, order: np.ndarray, tau: float,
               mu: float, step_kind: int, gps_batch_size: int, deadline: np.uint64,
               max_updates: int, force_first: bool, skip: bool, chi2: np.ndarray,
               last: np.ndarray, stamp: int, model: np.ndarray, slot: np.ndarray,
               xb: np.ndarray, nodes: np.ndarray, counts: np.ndarray, grp_of: np.ndarray,
               grp_of_g: np.ndarray, grp_ptr: np.ndarray, grp_edges: np.ndarray,
               grp_stamp: np.ndarray, depth: np.ndarray) -> int:
    """Relax the constraints of ``order`` in turn (paper Algorithm 1, GPS batched).

    A constraint of a junction group (``grp_of[c]`` for an edge, ``grp_of_g[g]`` for a GPS
    reading, >= 0: the constraints that joined a pose to the map in its frame, canonical ids
    ``grp_edges[grp_ptr[k]:grp_ptr[k+1]]``) is relaxed together with the rest of its group as
    one batch, once per ``stamp`` (``grp_stamp``); its other members are then passed over.

    An update is started only when ``cycle_counter() + predicted cost <= deadline`` (the first
    one regardless when ``force_first``) and fewer than ``max_updates`` were started.  When an
    update does not fit: ``skip`` moves on to the next (cheaper ones may fit), otherwise the
    list stops there.  ``chi2[c]`` receives c's χ² before its update, ``last[c] = stamp``.
    Returns the number of leading entries of ``order`` processed (all of them with ``skip``).
    """
    ro = np.empty((3, 3))
    to = np.empty(3)
    buf = np.empty(max(gps_batch_size, 1), np.int64)
    nbuf = 0
    buf_cost = 0.0
    started = 0
    n_order = order.shape[0]
    stop_at = n_order
    for idx in range(n_order + 1):
        c = order[idx] if idx < n_order else -1
        gps = False
        grp = -1
        nb = 1
        d = 0
        if c >= 0:
            gps = is_gps(prob, c)
            grp = grp_of_g[c - prob.num_edges] if gps else grp_of[c]
            if grp >= 0 and grp_stamp[grp] == stamp:
                continue  # relaxed with its group in this frame
            d = domain(prob, c)[1]
            if grp >= 0:
                d = 0
                nb = grp_ptr[grp + 1] - grp_ptr[grp]
                for j in range(grp_ptr[grp], grp_ptr[grp + 1]):
                    d += batch_work(prob, depth, _kid(prob, grp_edges[j]))
            if started >= max_updates:
                c = -1
                stop_at = idx
            else:
                if grp >= 0:
                    pred = _predict(model, d, True) + _capacitance_cost(nb)
                else:
                    pred = _predict(model, d, gps) + (buf_cost if gps else 0.0)
                late = float(cycle_counter()) + pred > float(deadline)
                if late and not (force_first and started == 0):
                    counts[C_SKIPPED] += 1
                    if skip:
                        continue
                    c = -1
                    stop_at = idx
        if nbuf > 0 and (c < 0 or not gps or grp >= 0 or nbuf >= gps_batch_size):
            _flush(prob, state, buf, nbuf, tau, mu, slot, xb, nodes, model, counts)
            nbuf = 0
            buf_cost = 0.0
        if c < 0:
            break
        started += 1
        counts[C_DONE] += 1
        last[c] = stamp
        if grp >= 0:
            grp_stamp[grp] = stamp
            gbuf = np.empty(nb, np.int64)
            for j in range(nb):
                cj = _kid(prob, grp_edges[grp_ptr[grp] + j])
                gbuf[j] = cj
                if is_gps(prob, cj):
                    chi2[cj] = _gps_chi2(prob, state, cj, ro, to)
                else:
                    chi2[cj] = _edge_chi2(prob, state, cj, wk)
                last[cj] = stamp
            t0 = cycle_counter()
            nu = batch_relax_exact(prob, state, gbuf, nb, tau, mu, slot, xb, nodes, 0, False)
            _learn(model, max(d, 1), float(cycle_counter() - t0), True)
            counts[C_BATCHES] += 1
            if nu == BATCH_REJECTED:
                counts[C_REJECTED] += 1
            continue
        if gps:
            chi2[c] = _gps_chi2(prob, state, c, ro, to)
            buf[nbuf] = c
            nbuf += 1
            buf_cost += _predict(model, d, True)
            continue
        t0 = cycle_counter()
        st = relax(prob, state, wk, c, tau, mu, step_kind, True)
        dc = float(cycle_counter() - t0)
        s = 0.0
        for i in range(6):
            s += wk.r[i] * wk.r[i]
        chi2[c] = s
        _learn(model, d, dc, False)
        if st == Update.CAPPED:
            counts[C_CAPPED] += 1
        elif st == Update.REJECTED:
            counts[C_REJECTED] += 1
    return int(stop_at)


# --------------------------------------------------------------------------- batches
@kernel
def local_batch(prob: Problem, state: State, cs: np.ndarray, tau: float, mu: float,
                deadline: np.uint64, model: np.ndarray, slot: np.ndarray, xb: np.ndarray,
                nodes: np.ndarray, counts: np.ndarray, depth: np.ndarray) -> int:
    """The local solve (III-G): relax ``cs`` together when its predicted cost fits.

    Returns the number of union nodes moved, 0 when the batch did not fit the deadline, or
    ``BATCH_REJECTED``.
    """
    nb = cs.shape[0]
    if nb == 0:
        return 0
    ne = 0
    for q in range(nb):
        ne += batch_work(prob, depth, cs[q])
    pred = _predict(model, ne, True) + _capacitance_cost(nb)
    if float(cycle_counter()) + pred > float(deadline):
        counts[C_SKIPPED] += 1
        return 0
    t0 = cycle_counter()
    nu = batch_relax_exact(prob, state, cs, nb, tau, mu, slot, xb, nodes, 0, False)
    _learn(model, max(ne, 1), float(cycle_counter() - t0), True)
    counts[C_BATCHES] += 1
    if nu == BATCH_REJECTED:
        counts[C_REJECTED] += nb
    return nu


# --------------------------------------------------------------------------- priority
@kernel
def candidates(chi2: np.ndarray, first: int, m: int, recent: int, window: int, cursor: int,
               out: np.ndarray) -> int:
    """The spare-time candidates of a frame among constraints ``first..m-1``, largest last χ²
    first (ties: newer first).

    The set is the ``recent`` newest relative constraints (nearest the robot) and ``window``
    constraints from ``first + cursor`` on, cyclically (every constraint is a candidate once
    every ``(m - first) / window`` frames), without repeats.  Writes them to ``out`` and returns
    how many.
    """
    k = 0
    lo = max(m - recent, first)
    for c in range(m - 1, lo - 1, -1):
        out[k] = c
        k += 1
    span = lo - first
    w = min(window, span)  # the window covers the older constraints first..lo-1
    for j in range(w):
        out[k] = first + (cursor + j) % span
        k += 1
    keys = np.empty(k)
    for j in range(k):
        keys[j] = -chi2[out[j]]
    perm = np.argsort(keys, kind="mergesort")  # stable: among equal keys the newer first
    tmp = out[:k].copy()
    for j in range(k):
        out[j] = tmp[perm[j]]
    return k
