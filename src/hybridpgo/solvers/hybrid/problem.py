"""Named data of the hybrid solver: what the kernels read, what they change, what they report.

Kernels take these NamedTuples (Numba compiles attribute access to a field load), so no kernel
unpacks an anonymous tuple by position.  Constraints are indexed ``0..M-1`` (relative edges) then
``M..M+G-1`` (GPS); :func:`is_gps` is the one place that tells them apart.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from ..._cost import SCRATCH
from ..._numba import kernel

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class Problem(NamedTuple):
    """Read-only arrays of one hybrid problem (built once by :class:`HybridSolver`)."""

    num_edges: int
    """M: constraints ``c < M`` are relative edges, ``c >= M`` are GPS readings ``c - M``."""
    path_ptr: npt.NDArray[np.int64]
    """(C+1,) CSR offsets of the constraint domains (tree paths, docs/mathematics.md#pose-tree)."""
    path_node: npt.NDArray[np.int32]
    """(nnz,) domain nodes: the a side from a upwards, then the b side from b upwards."""
    path_sign: npt.NDArray[np.int8]
    """(nnz,) -1 on the a side, +1 on the b side and for GPS."""
    edge_rot: FloatArray
    """(M, 3, 3) measured rotation of each relative edge."""
    edge_trans: FloatArray
    """(M, 3) measured translation of each relative edge."""
    edge_lt: FloatArray
    """(M, 6, 6) ``L^T`` (upper triangular) with ``Omega = L L^T``: the whitening."""
    gps_pos: FloatArray
    """(G, 3) GPS positions in the earth frame."""
    gps_lt: FloatArray
    """(G, 3, 3) ``L^T`` of each GPS information."""
    path_count: npt.NDArray[np.int64]
    """(T,) how many constraint domains contain each tree node."""
    parent: npt.NDArray[np.int32]
    """(T,) parent of each tree node, -1 for the root."""
    link_constraint: npt.NDArray[np.int64]
    """(T,) the constraint linking each node to its parent (a relative edge, or ``M + g`` for
    a GPS link to the earth), -1 for the root (interpolated solving merges these links)."""
    link_forward: npt.NDArray[np.bool_]
    """(T,) True when the linking edge is stored as (parent, child)."""
    robust_kind: int = 0
    """Robust kernel code (:data:`hybridpgo._cost.ROBUST_NAMES`; 0: none,
    docs/conventions.md#robust-kernels)."""
    robust_scale: float = 1.0
    """The robust kernel's delta."""


class State(NamedTuple):
    """Mutable arrays the updates change in place."""

    rot: FloatArray
    """(T, 3, 3) local rotations ``R_parent^-1 R_i``."""
    trans: FloatArray
    """(T, 3) local translations."""
    bdiag: FloatArray
    """(T, 6, 6) 𝔅(H), the block diagonal of ``H = sum_c J_c^T J_c`` (paper eq. 23)."""
    contrib: FloatArray
    """(nnz, 6, 6) the block ``J_c^kT J_c^k`` each constraint last added to 𝔅(H) (eq. 24)."""


class Workspace(NamedTuple):
    """Scratch buffers of single updates, for domains of up to ``capacity`` nodes."""

    path_rot: FloatArray
    """(d, 3, 3) path products: rotation of each domain node in the constraint root's frame."""
    path_trans: FloatArray
    """(d, 3) path products: translation of each domain node in the root's frame."""
    jac: FloatArray
    """(d, 6, 6) whitened Jacobian blocks ``J_c^k`` (rows beyond the constraint's are zero)."""
    lfac: FloatArray
    """(d, 6, 6) lower Cholesky factors of the damped blocks of ``B_c``."""
    w: FloatArray
    """(d, 6, 6) Woodbury's ``W_k = L_k^-1 J_k^T``."""
    x: FloatArray
    """(d, 6) the step of each domain node."""
    r: FloatArray
    """(6,) whitened residual ``-L^T e0``."""
    e: FloatArray
    """(6,) the constraint's error ``e0``."""
    jri: FloatArray
    """(6, 6) ``Jr^-1(e0)``."""
    a: FloatArray
    """(6, 6) ``L^T Jr^-1(e0)``, the whitened Jacobian with respect to ``X_b``."""
    bc: FloatArray
    """(6, 6) one block of ``B_c`` before damping."""
    ws: FloatArray
    """(12, 3, 3) scratch of the cost layer."""
    chain_rot: FloatArray
    """(d + 1, 3, 3) rotations along a merged chain (interpolated solving, III-E)."""
    chain_w: FloatArray
    """(d + 1, 2) cumulative rotational / translational distribution weights along a chain."""
    iws: FloatArray
    """(16, 3, 3) scratch of interpolated solving; ``iws[EYE]`` is the identity and
    ``iws[ZERO]`` zero, constant (never written after :func:`new_workspace`)."""
    iws6: FloatArray
    """(4, 6, 6) scratch of interpolated solving."""
    sv: FloatArray
    """(2, 6) vectors of the Woodbury solve."""


#: Constant slots of ``Workspace.iws``: the (3, 3) identity and a (3, 3) zero.
EYE = 14
ZERO = 15


@kernel
def new_workspace(capacity: int) -> Workspace:
    """A workspace for domains of up to ``capacity`` nodes."""
    iws = np.empty((16, 3, 3))
    iws[ZERO] = 0.0
    iws[EYE] = 0.0
    for i in range(3):
        iws[EYE, i, i] = 1.0
    return Workspace(
        np.empty((capacity, 3, 3)),
        np.empty((capacity, 3)),
        np.zeros((capacity, 6, 6)),
        np.empty((capacity, 6, 6)),
        np.empty((capacity, 6, 6)),
        np.empty((capacity, 6)),
        np.empty(6),
        np.empty(6),
        np.empty((6, 6)),
        np.empty((6, 6)),
        np.empty((6, 6)),
        np.empty((SCRATCH, 3, 3)),
        np.empty((capacity + 1, 3, 3)),
        np.empty((capacity + 1, 2)),
        iws,
        np.empty((4, 6, 6)),
        np.empty((2, 6)),
    )


@kernel
def is_gps(prob: Problem, c: int) -> bool:
    """True when constraint c is a GPS reading (index ``c - num_edges``)."""
    return c >= prob.num_edges


@kernel
def domain(prob: Problem, c: int) -> tuple[int, int]:
    """``(start, d)``: constraint c's domain is ``path_node[start:start + d]``."""
    s = prob.path_ptr[c]
    return s, prob.path_ptr[c + 1] - s


class Update(enum.IntEnum):
    """Outcome of one single-constraint update."""

    APPLIED = 0
    CAPPED = 1
    """Applied with a smaller temperature: the largest rotation was capped at pi/8 (III-H)."""
    REJECTED = 2
    """The step was not finite: nothing was applied."""


#: A batch update returns its number of union nodes, or this when the step was rejected.
BATCH_REJECTED = -1


class Count(enum.IntEnum):
    """Positions in the ``counts`` array a sweep accumulates into."""

    CAPPED = 0
    REJECTED = 1
    MAX_CYCLES = 2
    """The largest cycle count of one update (single or batch)."""
    BATCHES = 3
    DONE = 4
    """Constraints processed (less than asked when a deadline stopped the sweep)."""
    SKIPPED = 5
    """Updates not admitted because their predicted cost did not fit (admission policy)."""
    FIRST_REJECTED = 6
    """1 + the first constraint whose update was rejected (0: none)."""


NUM_COUNTS = len(Count)


class StepKind(enum.IntEnum):
    """How the single-constraint system (paper eq. 25) is solved."""

    WOODBURY = 0
    """O(d): ``x = B^-1 J^T (I + J B^-1 J^T)^-1 r`` (docs/mathematics.md#hybrid-step, default)."""
    GIVENS = 1
    """O(d^2): the paper's Givens triangularization (eq. 29-30)."""
