"""The admission policy of a budgeted relaxation loop (the online mode's frames).

A sweep of the whole-graph solver stops at a deadline on the cycle counter.  Under a time
budget per frame the online mode needs more: an update is *admitted* only when its predicted
cost fits before the deadline, constraints that joined a pose in one frame are relaxed together
(junction groups), and every constraint's χ² before its update is recorded as the priority of
later frames.  This module holds what that policy decides with:

* the cost model: cycles of an update's base, per domain node of a single update and per
  domain entry of a batch (:func:`predict`, learnt by :func:`learn` from the cycle counts of
  earlier updates), and the bound on a dense capacitance factorization;
* :class:`Admission`, the arrays the loop of :mod:`._sweep` reads and writes under the policy;
* :func:`gps_chi2` / :func:`edge_chi2`: a constraint's χ² at the current estimate, from its path;
* :func:`candidates` (the bounded set of spare-time updates, largest χ² first) and
  :func:`local_batch` (a batch update of chosen constraints, admitted by the same model);
* :func:`crossing` and :func:`edge_chi2s`: the relative constraints whose paths share a node with
  a given one's (those its update moves) and their χ², for the batch of a loop's neighbours.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from ..._cost import residual_and_jr_inv, whiten_residual
from ..._numba import cycle_counter, kernel
from ..._tree_kernels import global_pose
from ._batch import batch_relax_exact
from ._linearize import endpoints, num_a_side, path_products
from .problem import BATCH_REJECTED, Count, Problem, State, Workspace, domain, is_gps

#: Entries of the cost model array (cycles): base cost of an update, cost per domain node of a
#: single update, cost per domain entry of a batch update.
MODEL_BASE = 0
MODEL_NODE = 1
MODEL_BATCH = 2
#: Weight of a new sample in the cost model's moving averages.
MODEL_RATE = 1.0 / 32.0
#: Single updates of more domain nodes than this teach the cost per node, and batches of more
#: work than this the cost per batch entry; shorter ones (above 4 nodes: the base's) teach
#: nothing.  Each rate is thus the cost of long updates, whose path products and poses miss the
#: cache (more per node than short domains): short updates, hundreds per frame, would otherwise
#: pull it down to their own, and a long update admitted on it would overrun its frame.  (With
#: every batch teaching, paris2's junction groups of about 1 000 entries or more took 3.5x their
#: prediction at the median and 7x at the 90th percentile: the frames that ended them ran to
#: 6-7 ms of CPU at a 5 ms budget.)
MODEL_SIZE_REF = 32
#: Tree levels above a batch's root that cost as much as one domain entry: the root's global
#: pose is one composition per level, a domain entry a 6x6 block and its path products
#: (paris2's junction groups, least squares over 163 000 batches: a level costs a 24th of a
#: domain entry, so that groups of short constraints deep in the tree, counted level for entry,
#: taught a cost per entry far below a long group's).  Counted at a 16th, a little above.
DEPTH_PER_ENTRY = 16
#: Predictions are the model times this margin (the model is a mean; updates vary around it).
MODEL_MARGIN = 1.5
#: Cycles per floating-point operation assumed for the dense factorization of a batch.
CYCLES_PER_FLOP = 1.0
#: Initial cost model (cycles): base per update, per domain node, per batch entry.
MODEL0 = (4000.0, 800.0, 1500.0)


class Admission(NamedTuple):
    """What a relaxation loop reads and writes under the admission policy.

    Constraint indices are the problem's (relative edges ``0..num_edges-1``, GPS readings
    ``num_edges + g``).
    """

    model: npt.NDArray[np.float64]
    """(3,) the cost model (``MODEL_BASE``, ``MODEL_NODE``, ``MODEL_BATCH``), learnt in place."""
    chi2: npt.NDArray[np.float64]
    """(C,) each constraint's χ² before its last update (written)."""
    group_of: npt.NDArray[np.int64]
    """(C,) the junction group of each constraint, -1 for none."""
    group_ptr: npt.NDArray[np.int64]
    """CSR of the groups' members: ``group_members[group_ptr[k]:group_ptr[k + 1]]``."""
    group_members: npt.NDArray[np.int64]
    """Constraint indices of each group's members."""
    group_stamp: npt.NDArray[np.int64]
    """(K,) the stamp at which each group was last relaxed (written)."""
    depth: npt.NDArray[np.int32]
    """(T,) depth of every tree node (the work of a batch member, :func:`batch_work`)."""
    span: npt.NDArray[np.float64]
    """(1,) cycles of the call's whole budget (inf: none).  A junction group whose batch is
    predicted to take longer is relaxed member by member, by single updates: no frame could
    hold the batch, so under the policy it would never start."""


# --------------------------------------------------------------------------- cost model
@kernel
def predict(model: np.ndarray, d: int, batch: bool) -> float:
    """Predicted cycles of an update over ``d`` domain nodes (a batch: ``d`` entries)."""
    per = model[MODEL_BATCH] if batch else model[MODEL_NODE]
    return float(MODEL_MARGIN * (model[MODEL_BASE] + per * d))


@kernel
def capacitance_cost(nb: int) -> float:
    """Predicted cycles of the dense factorization of a batch's (6 nb)^2 capacitance matrix
    ((6 nb)^3 / 3 flops)."""
    return MODEL_MARGIN * CYCLES_PER_FLOP * 72.0 * nb * nb * nb


@kernel
def learn(model: np.ndarray, d: int, dc: float, batch: bool) -> None:
    """Moving averages of the base cost (small domains) and of the cost per domain node or
    batch entry (long updates and large batches, ``MODEL_SIZE_REF``)."""
    if d <= 4 and not batch:
        cur = model[MODEL_BASE]
        model[MODEL_BASE] = cur + MODEL_RATE * (min(dc, 4.0 * cur) - cur)
        return
    if d <= MODEL_SIZE_REF:
        return
    k = MODEL_BATCH if batch else MODEL_NODE
    sample = max(dc - model[MODEL_BASE], 0.0) / d
    cur = model[k]
    model[k] = cur + MODEL_RATE * (min(sample, 4.0 * cur) - cur)


@kernel
def batch_work(prob: Problem, depth: np.ndarray, c: int) -> int:
    """Work of constraint c in a batch update, in domain-node units: its domain plus the depth
    of its root (the batch computes the root's global pose, O(depth)) over
    :data:`DEPTH_PER_ENTRY`."""
    s, d = domain(prob, c)
    if d == 0:
        return 0
    na = num_a_side(prob, c)
    top = prob.path_node[s + na - 1] if na > 0 else prob.path_node[s + d - 1]
    return int(d + depth[prob.parent[top]] // DEPTH_PER_ENTRY)


# --------------------------------------------------------------------------- priorities
@kernel
def gps_chi2(prob: Problem, state: State, c: int, ro: np.ndarray, to: np.ndarray) -> float:
    """χ² of GPS reading c at the current estimate (O(depth of its pose))."""
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
def edge_chi2(prob: Problem, state: State, c: int, wk: Workspace) -> float:
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


@kernel
def chi2_of(prob: Problem, state: State, c: int, wk: Workspace, ro: np.ndarray,
            to: np.ndarray) -> float:
    """χ² of constraint c (either kind) at the current estimate."""
    if is_gps(prob, c):
        return gps_chi2(prob, state, c, ro, to)
    return edge_chi2(prob, state, c, wk)


@kernel
def crossing(prob: Problem, m: int, c: int, rejected: np.ndarray, mark: np.ndarray,
             out: np.ndarray) -> int:
    """The relative constraints among ``0..m-1``, c and those in ``rejected`` left out,
    whose paths hold a node of c's path: the constraints whose residuals an update of c
    changes (it moves the subtrees of its path's nodes).  O(path entries of the m
    constraints).  ``mark`` (one flag per tree node) is False on entry and on exit.  Writes
    them to ``out`` in index order and returns how many."""
    s, d = domain(prob, c)
    for k in range(s, s + d):
        mark[prob.path_node[k]] = True
    n = 0
    for e in range(m):
        if e == c or rejected[e]:
            continue
        for k in range(prob.path_ptr[e], prob.path_ptr[e + 1]):
            if mark[prob.path_node[k]]:
                out[n] = e
                n += 1
                break
    for k in range(s, s + d):
        mark[prob.path_node[k]] = False
    return n


@kernel
def edge_chi2s(prob: Problem, state: State, cs: np.ndarray, wk: Workspace,
               out: np.ndarray) -> float:
    """:func:`edge_chi2` of every relative constraint in ``cs`` into ``out``; their sum."""
    total = 0.0
    for q in range(cs.shape[0]):
        out[q] = edge_chi2(prob, state, cs[q], wk)
        total += out[q]
    return total


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
    pred = predict(model, ne, True) + capacitance_cost(nb)
    if float(cycle_counter()) + pred > float(deadline):
        counts[Count.SKIPPED] += 1
        return 0
    t0 = cycle_counter()
    nu = batch_relax_exact(prob, state, cs, nb, tau, mu, slot, xb, nodes, 0, False)
    learn(model, max(ne, 1), float(cycle_counter() - t0), True)
    counts[Count.BATCHES] += 1
    if nu == BATCH_REJECTED:
        counts[Count.REJECTED] += nb
    return nu
