"""The exact solver: sparse Gauss-Newton / Levenberg-Marquardt (DESIGN.md §7).

Ordinary global parametrization with right perturbations ``X_i <- X_i Exp(delta_i)``, tangent
order (rho, phi), energy ``E = sum_c e_c^T Omega_c e_c`` (no 1/2, DESIGN §1).  The normal
equations ``H delta = -g`` with ``H = J^T Omega J``, ``g = J^T Omega e`` are assembled by one Numba
kernel straight into the values of a CSC matrix whose sparsity pattern (and fill-reducing
ordering) is computed once per solve ("analyze once, solve many times", STYLE.md §2).

Gauge (STYLE.md §6): the nodes named by ``FIX`` lines (``graph.fixed_nodes``) are held constant.
Without any, the first pose (dense index 0) is fixed, unless the graph has position-only (GPS)
constraints: then the earth frame is the gauge and no pose is fixed.

Linear algebra (:mod:`._linear`): the variables are permuted once per solve by a fill-reducing
ordering of the 6x6 *block* graph (AMD, 36x smaller than H); then CHOLMOD through cvxopt
(supernodal, symbolic analysis once, numeric factorization each iteration) or, with
``linear_solver="splu"``, SciPy's SuperLU in symmetric mode with diagonal pivots.  With
``"auto"``, a 3D system whose factor stays sparse (city-like graphs: few loop closures) is
factored by the block Cholesky of :mod:`._block_cholesky` instead (``_BLOCK_MAX_FILL``):
faster there, and the only backend that keeps a 1M-pose polish within 4 GB.

Lifted 2D graphs (DESIGN §1) at planar poses solve only the (x, y, yaw) unknowns: the other three
are decoupled and their step is exactly zero (see ``_PLANAR_DOFS``); M3500: 133 -> 38 ms per
iteration.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .. import _cost
from ..errors import GraphError, SolverError
from ..graph import FloatArray, PoseGraph
from . import _gn_kernels as _k
from ._block_cholesky import BlockCholesky
from ._linear import NotPositiveDefinite, _fill_reducing_order, _make_factorizer
from ._linear import _cholmod_available as _cholmod_available  # re-exported for the tests
from .config import GaussNewtonConfig, Progress, ProgressCallback
from .result import SolveResult, Status

#: ``iterate(Progress, rotations, translations)``: the current global poses after every
#: iteration, right after the progress callback (for recorders such as ``optimize --rerun``;
#: the arrays may be the solver's own: copy what you keep, never modify them).
IterateCallback = Callable[[Progress, FloatArray, FloatArray], None]

__all__ = ["NormalEquations", "default_fixed_nodes", "gn_step", "normal_equations", "solve_exact"]

Int64Array = npt.NDArray[np.int64]

#: LM: after an accepted step mu is multiplied by max(_MAX_DECREASE, 1 - (2 rho - 1)^3)
#: (Nielsen's rule with GTSAM's factor 10 in place of Nielsen's 3).  Measured with
#: initial_damping 1e-8, iterations to convergence (benchmarks/exact_targets.py): bound 1/3:
#: sphere2500 8, M3500 8, garage 8, intel 4, M3500_isam 5; bound 1/10: 8, 5, 6, 4, 5.
_MAX_DECREASE = 0.1
#: LM gives up (STALLED) when the damping factor mu exceeds this: no step lowers the energy.
_MAX_DAMPING = 1e16
#: LM damping matrix: diag(H) clipped below at this fraction of its largest entry, so that the
#: damped system stays SPD where a direction carries (almost) no information.
_DIAG_FLOOR = 1e-12
#: ``linear_solver="auto"``: the block Cholesky (:mod:`._block_cholesky`) when its factor has at
#: most this many 6x6 blocks per block column (diagonal included); else CHOLMOD, whose BLAS
#: supernodes win on high fill.  Measured (factor + solve): 100k-pose city 2-3 blocks per
#: column, block 0.37 s vs CHOLMOD 1.08 s; sphere2500 17, block 0.27 s vs CHOLMOD 0.18 s.
_BLOCK_MAX_FILL = 6


# --------------------------------------------------------------------------- gauge
def default_fixed_nodes(graph: PoseGraph) -> npt.NDArray[np.int32]:
    """Dense indices of the nodes the exact solver holds constant (the gauge, see module doc)."""
    if graph.fixed_nodes.size:
        return np.unique(graph.fixed_nodes).astype(np.int32)
    if graph.num_gps:
        return np.zeros(0, np.int32)
    return np.zeros(1, np.int32)


def _check_gauge(graph: PoseGraph, fixed: npt.NDArray[np.int32]) -> None:
    """Every connected part needs a fixed node or a GPS constraint; else H is singular."""
    labels = graph.connected_components()
    anchored = np.zeros(int(labels.max()) + 1, bool)
    anchored[labels[fixed]] = True
    anchored[labels[graph.gps_nodes]] = True
    if not anchored.all():
        part = int(np.argmin(anchored))
        members = graph.node_ids[labels == part]
        raise GraphError(
            f"the graph is not connected and a part of {members.size} pose(s) (e.g. id "
            f"{int(members[0])}) has neither a fixed pose nor a GPS constraint, so its position "
            "is undetermined; link it to the rest or fix one of its poses"
        )


# --------------------------------------------------------------------------- analyze
@dataclass(frozen=True, slots=True)
class _Pattern:
    """Sparsity pattern of the lower triangle of H and where each constraint's blocks go
    (computed once; layout in :mod:`._gn_kernels`)."""

    var_of_node: Int64Array  # (N,) variable (block column) of each node, -1 when fixed
    num_vars: int
    indptr: Int64Array  # (6 nv + 1,) scalar column pointers of the lower triangle
    block_ptr: Int64Array  # (nv + 1,) lower off-diagonal blocks of each block column
    block_row: Int64Array  # their block rows (increasing within a column)
    edge_off: Int64Array  # (M,) position of each edge's lower block in its column, -1: fixed

    @property
    def dim(self) -> int:
        return 6 * self.num_vars

    @property
    def nnz(self) -> int:
        """Stored entries (the lower triangle, diagonal included)."""
        return int(self.indptr[-1])

    @property
    def diag_index(self) -> Int64Array:
        """(dim,) position of H[k, k] in the values: the first entry of each column."""
        return self.indptr[:-1]

    def lower_indices(self) -> Int64Array:
        """Row index of every stored entry (built on demand: the solver itself never needs
        them after the factorization's symbolic analysis)."""
        indices = np.empty(self.nnz, np.int64)
        _k.lower_pattern_indices(self.block_ptr, self.block_row, self.indptr, indices)
        return indices


def _analyze(graph: PoseGraph, fixed: npt.NDArray[np.int32], reorder: bool) -> _Pattern:
    n = graph.num_nodes
    is_fixed = np.zeros(n, bool)
    is_fixed[fixed] = True
    free = np.flatnonzero(~is_fixed)
    nv = int(free.size)
    var = np.full(n, -1, np.int64)
    var[free] = np.arange(nv)
    ends = graph.edge_nodes
    if reorder:
        va, vb = var[ends[:, 0]], var[ends[:, 1]]
        var[free] = _fill_reducing_order(nv, np.concatenate([va, vb]), np.concatenate([vb, va]))
        del va, vb
    va, vb = var[ends[:, 0]], var[ends[:, 1]]
    both = (va >= 0) & (vb >= 0) & (va != vb)
    lo = np.minimum(va, vb)[both]
    hi = np.maximum(va, vb)[both]
    del va, vb
    uniq, inv = np.unique(lo * max(nv, 1) + hi, return_inverse=True)
    del lo, hi
    bcol = uniq // max(nv, 1)
    nblocks = np.bincount(bcol, minlength=nv).astype(np.int64)
    block_ptr = np.zeros(nv + 1, np.int64)
    np.cumsum(nblocks, out=block_ptr[1:])
    edge_off = np.full(graph.num_edges, -1, np.int64)
    edge_off[both] = inv - block_ptr[bcol[inv]]
    q6 = np.arange(6, dtype=np.int64)
    counts = (6 - q6)[None, :] + 6 * nblocks[:, None]  # column 6j+q: diagonal rows q..5, blocks
    indptr = np.zeros(6 * nv + 1, np.int64)
    np.cumsum(counts.ravel(), out=indptr[1:])
    return _Pattern(var_of_node=var, num_vars=nv, indptr=indptr, block_ptr=block_ptr,
                    block_row=np.ascontiguousarray(uniq % max(nv, 1)), edge_off=edge_off)


def _lower_to_full(values: FloatArray, indices: Int64Array, indptr: Int64Array,
                   dim: int) -> sp.csc_matrix:
    """The symmetric matrix (both triangles) whose lower triangle is given."""
    low = sp.csc_matrix((values, indices, indptr), shape=(dim, dim))
    full = (low + low.T - sp.diags(low.diagonal())).tocsc()
    full.sort_indices()
    return full


#: Lifted-2D graphs (DESIGN §1): the tangent entries x, y, yaw.  At planar poses with planar
#: measurements and block-separable information, H and g do not couple them with z, roll,
#: pitch (every Jacobian keeps the parity of in-plane vs out-of-plane components) and g is 0
#: there, so the step's out-of-plane part is exactly 0: only the (x, y, yaw) system is solved.
_PLANAR_DOFS = np.array([0, 1, 5])
_OUT_OF_PLANE_DOFS = np.array([2, 3, 4])


@dataclass(frozen=True, slots=True)
class _System:
    """The symmetric system actually factored: all of H, or its (x, y, yaw) rows/columns.

    Stored as its lower triangle in CSC form, rows increasing in each column (so the diagonal
    entry comes first): the layout of :class:`._linear.SymmetricPattern`.
    """

    indptr: Int64Array  # CSC pattern of the lower triangle of the (dim, dim) system matrix
    indices: Int64Array  # empty once the factorizer has taken them (CHOLMOD keeps its own)
    dofs: Int64Array | None  # positions of the system's unknowns in the full vector; None: all
    value_map: Int64Array | None  # system values = data[value_map]; None: data itself
    dim: int

    @property
    def diag_index(self) -> Int64Array:
        return self.indptr[:-1]

    @property
    def nnz(self) -> int:
        return int(self.indptr[-1])

    def values(self, data: FloatArray, out: FloatArray | None) -> FloatArray:
        """The system's values: ``data`` itself, or its entries gathered (into ``out``)."""
        if self.value_map is None:
            return data
        return np.take(data, self.value_map, out=out)

    def restrict(self, vec: FloatArray) -> FloatArray:
        return vec if self.dofs is None else vec[self.dofs]

    def expand(self, sub: FloatArray, dim: int) -> FloatArray:
        if self.dofs is None:
            return sub
        out = np.zeros(dim)
        out[self.dofs] = sub
        return out


def _full_system(pat: _Pattern) -> _System:
    return _System(pat.indptr, pat.lower_indices(), None, None, pat.dim)


def _planar_system(pat: _Pattern) -> _System:
    """The (x, y, yaw) rows and columns of H, with a value map computed once."""
    keep = (6 * np.arange(pat.num_vars)[:, None] + _PLANAR_DOFS[None, :]).ravel()
    ids = sp.csc_matrix((np.arange(1, pat.nnz + 1, dtype=np.float64), pat.lower_indices(),
                         pat.indptr), shape=(pat.dim, pat.dim))
    sub = ids[keep][:, keep].tocsc()
    sub.sort_indices()
    value_map = sub.data.astype(np.int64) - 1
    indptr = sub.indptr.astype(np.int64)
    indices = sub.indices.astype(np.int64)
    # every diagonal entry is in the pattern, first in its column (a lower triangle)
    assert np.array_equal(indices[indptr[:-1]], np.arange(keep.shape[0]))
    return _System(indptr, indices, keep, value_map, int(keep.shape[0]))


def _is_planar(graph: PoseGraph, rot: FloatArray, trans: FloatArray) -> bool:
    """True when the (x, y, yaw) reduction is exact (see ``_PLANAR_DOFS``)."""
    if not graph.is_2d or graph.num_gps or graph.num_edges == 0:
        return False
    e3 = np.array([0.0, 0.0, 1.0])
    for r, t in ((rot, trans), (graph.edge_rotations, graph.edge_translations)):
        if not (np.all(r[:, 2, :] == e3) and np.all(r[:, :, 2] == e3) and np.all(t[:, 2] == 0.0)):
            return False
    info = graph.edge_information
    return bool(np.all(info[:, _PLANAR_DOFS[:, None], _OUT_OF_PLANE_DOFS[None, :]] == 0.0))


# --------------------------------------------------------------------------- linearize
def _assemble(graph: PoseGraph, pat: _Pattern, rot: FloatArray, trans: FloatArray,
              data: FloatArray, grad: FloatArray, robust: tuple[int, float] = (0, 1.0)
              ) -> tuple[float, float]:
    """H and g into ``data``, ``grad``; returns ``(E_rho, E)`` (equal without a kernel)."""
    status, e, plain = _k.assemble_normal_equations(
        rot, trans, graph.edge_nodes, graph.edge_rotations, graph.edge_translations,
        graph.edge_information, pat.edge_off, graph.gps_nodes, graph.gps_positions,
        graph.gps_information, pat.var_of_node, pat.indptr, data, grad, robust[0], robust[1],
    )
    if status >= 0:
        where = _describe_constraint(graph, status)
        raise SolverError(f"the linearization is not finite at {where}")
    return float(e), float(plain)


def _energy(graph: PoseGraph, rot: FloatArray, trans: FloatArray,
            robust: tuple[int, float] = (0, 1.0)) -> float:
    """E (E_rho with a robust kernel) at trial poses (may be inf/nan: the callers reject such
    steps)."""
    if robust[0] != _cost.ROBUST_NONE:
        return float(_cost.robust_total_energy(
            rot, trans, graph.edge_nodes, graph.edge_rotations, graph.edge_translations,
            graph.edge_information, graph.gps_nodes, graph.gps_positions,
            graph.gps_information, robust[0], robust[1])[0])
    return float(_cost.total_energy(rot, trans, graph.edge_nodes, graph.edge_rotations,
                                 graph.edge_translations, graph.edge_information,
                                 graph.gps_nodes, graph.gps_positions, graph.gps_information))


def _describe_constraint(graph: PoseGraph, c: int) -> str:
    if c < graph.num_edges:
        a, b = (int(graph.node_ids[i]) for i in graph.edge_nodes[c])
        return f"relative constraint {c} (between ids {a} and {b})"
    g = c - graph.num_edges
    return f"GPS constraint {g} (on id {int(graph.node_ids[graph.gps_nodes[g]])})"


@dataclass(frozen=True)
class NormalEquations:
    """The Gauss-Newton system ``H delta = -g`` at given poses (free nodes in increasing index).

    Block k (rows/columns ``6k .. 6k+5``) belongs to node ``free_nodes[k]``; tangent (rho, phi).
    """

    hessian: sp.csc_matrix
    """(6F, 6F) H = J^T Omega J (robust: sum_c w_c J_c^T Omega_c J_c)."""
    gradient: FloatArray
    """(6F,) g = J^T Omega e (half the gradient of E, which has no 1/2; robust: of E_rho)."""
    free_nodes: npt.NDArray[np.int64]
    """(F,) dense indices of the nodes that are variables."""
    energy: float
    """E at the linearization point (robust: E_rho)."""


def normal_equations(graph: PoseGraph, rotations: FloatArray | None = None,
                     translations: FloatArray | None = None,
                     fixed: npt.ArrayLike | None = None, *, robust: str = "none",
                     robust_scale: float = 1.0) -> NormalEquations:
    """Assemble the Gauss-Newton normal equations (free nodes in natural order).

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64, optional
        Linearization point (default: the graph's estimate).
    fixed : array_like of int, optional
        Dense indices held constant (default: :func:`default_fixed_nodes`).
    robust, robust_scale : str, float
        Robust kernel and its delta (DESIGN §10; as in :class:`GaussNewtonConfig`): each
        relative constraint's terms are weighted by ``w_c = rho'(s_c)`` (IRLS).
    """
    kind = _cost.robust_kind(robust, robust_scale)
    rot, trans = _initial_poses(graph, rotations, translations)
    fx = _fixed_array(graph, fixed)
    pat = _analyze(graph, fx, reorder=False)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    e, _plain = _assemble(graph, pat, rot, trans, data, grad, (kind, float(robust_scale)))
    h = _lower_to_full(data, pat.lower_indices(), pat.indptr, pat.dim)
    return NormalEquations(h, grad, np.flatnonzero(pat.var_of_node >= 0), e)


def gn_step(graph: PoseGraph, rotations: FloatArray | None = None,
            translations: FloatArray | None = None,
            fixed: npt.ArrayLike | None = None) -> FloatArray:
    """The exact Gauss-Newton step ``delta = -H^-1 g`` as an (N, 6) array (zero on fixed nodes).

    Apply it as ``X_i <- X_i Exp(delta_i)``; tangent order (rho, phi).

    Raises
    ------
    SolverError
        When H is singular (gauge not fixed) or the step is not finite.
    """
    rot, trans = _initial_poses(graph, rotations, translations)
    fx = _fixed_array(graph, fixed)
    pat = _analyze(graph, fx, reorder=True)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    _assemble(graph, pat, rot, trans, data, grad)
    step = _make_factorizer(_full_system(pat), "auto").solve(data, -grad, check=True)
    out = np.zeros((graph.num_nodes, 6))
    free = pat.var_of_node >= 0
    out[free] = step.reshape(-1, 6)[pat.var_of_node[free]]
    return out


# --------------------------------------------------------------------------- helpers
def _initial_poses(graph: PoseGraph, rotations: FloatArray | None,
                   translations: FloatArray | None) -> tuple[FloatArray, FloatArray]:
    rot = np.array(graph.rotations if rotations is None else rotations, np.float64, order="C")
    trans = np.array(graph.translations if translations is None else translations, np.float64,
                     order="C")
    n = graph.num_nodes
    if rot.shape != (n, 3, 3) or trans.shape != (n, 3):
        raise ValueError(f"poses must have shapes ({n}, 3, 3) and ({n}, 3), "
                         f"got {rot.shape} and {trans.shape}")
    for name, arr in (("rotations", rot), ("translations", trans)):
        bad = ~np.isfinite(arr.reshape(n, -1)).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise SolverError(f"initial {name}[{i}] (id {int(graph.node_ids[i])}) is not finite")
    return rot, trans


def _fixed_array(graph: PoseGraph, fixed: npt.ArrayLike | None) -> npt.NDArray[np.int32]:
    if fixed is None:
        return default_fixed_nodes(graph)
    fx = np.unique(np.asarray(fixed, dtype=np.int64).reshape(-1))
    if fx.size and (fx[0] < 0 or fx[-1] >= graph.num_nodes):
        raise ValueError(f"fixed node indices must lie in 0..{graph.num_nodes - 1}")
    return fx.astype(np.int32)


_compiled = False


def _ensure_compiled() -> float:
    """Compile (or load from cache) the kernels on a two-node graph; return the seconds spent."""
    global _compiled
    if _compiled:
        return 0.0
    t0 = time.perf_counter()
    eye = np.eye(3)[None].repeat(2, axis=0)
    g = PoseGraph(node_ids=np.arange(2), rotations=eye, translations=np.zeros((2, 3)),
                  edge_nodes=np.array([[0, 1]]), edge_rotations=eye[:1],
                  edge_translations=np.ones((1, 3)), edge_information=np.eye(6)[None],
                  gps_nodes=np.array([1]), gps_positions=np.ones((1, 3)),
                  gps_information=np.eye(3)[None])
    pat = _analyze(g, np.zeros(0, np.int32), reorder=False)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    rot = np.array(g.rotations)  # writable, like the solver's state (Numba types differ)
    trans = np.array(g.translations)
    _assemble(g, pat, rot, trans, data, grad)
    pat.lower_indices()
    out_r = np.empty((2, 3, 3))
    out_t = np.empty((2, 3))
    _k.retract(rot, trans, grad, pat.var_of_node, 1.0, out_r, out_t)
    _energy(g, out_r, out_t)
    _energy(g, out_r, out_t, (_cost.ROBUST_HUBER, 1.0))
    _compiled = True
    return time.perf_counter() - t0


# --------------------------------------------------------------------------- the solver
@dataclass
class _Run:
    """One exact solve after its analysis: pattern, factorizer, buffers, current poses.

    Memory (per stored entry of the lower triangle of H, "nnz"; 1M-pose city: 57 M): the values
    are assembled straight into the factorizer's own buffer (CHOLMOD: the cvxopt matrix it
    copies into the factored matrix), damped in place on the diagonal and restored; no other
    copy of H exists.  The row indices live only in CHOLMOD's matrix after the analysis.
    """

    graph: PoseGraph
    cfg: GaussNewtonConfig
    pat: _Pattern
    system: _System
    solver: Any
    rot: FloatArray
    trans: FloatArray
    data: FloatArray
    """Values of the lower triangle of H (the factorizer's buffer for the full system)."""
    sys_values: FloatArray | None
    """The reduced (planar) system's values (the factorizer's buffer), None for the full one."""
    grad: FloatArray
    new_rot: FloatArray
    new_trans: FloatArray
    planar: bool
    seconds: dict[str, float]
    robust: tuple[int, float]
    """(kernel code, delta) of the robust kernel (DESIGN §10)."""
    plain: float = 0.0
    """The plain E at the last assembly."""

    @classmethod
    def analyze(cls, graph: PoseGraph, rotations: FloatArray | None,
                translations: FloatArray | None, cfg: GaussNewtonConfig) -> _Run:
        """Check the start and the gauge, compute the pattern, ordering and symbolic
        factorization once."""
        rot, trans = _initial_poses(graph, rotations, translations)
        fixed = default_fixed_nodes(graph)
        _check_gauge(graph, fixed)
        pat = _analyze(graph, fixed, reorder=True)
        planar = _is_planar(graph, rot, trans)
        solver: Any = None
        if not planar and cfg.linear_solver == "auto":
            block = BlockCholesky(pat.num_vars, pat.block_ptr, pat.block_row, pat.indptr)
            if not _cholmod_available() or block.factor_blocks <= _BLOCK_MAX_FILL * max(
                    pat.num_vars, 1):
                solver = block
        if solver is not None:  # the block factorization reads the values in place
            system = _System(pat.indptr, np.zeros(0, np.int64), None, None, pat.dim)
        else:
            system = _planar_system(pat) if planar else _full_system(pat)
            solver = _make_factorizer(system, cfg.linear_solver)
        if solver.name == "cholmod":  # CHOLMOD holds the pattern: drop our copy of the rows
            system = dataclasses.replace(system, indices=np.zeros(0, np.int64))
        buffer = solver.values_buffer()
        sys_values = None
        if planar:
            data = np.empty(pat.nnz)
            sys_values = buffer if buffer is not None else np.empty(system.nnz)
        else:
            data = buffer if buffer is not None else np.empty(pat.nnz)
        return cls(graph, cfg, pat, system, solver, rot, trans, data, sys_values,
                   np.empty(pat.dim), np.empty_like(rot), np.empty_like(trans), planar,
                   {"assemble": 0.0, "factorize": 0.0, "energy": 0.0},
                   (_cost.robust_kind(cfg.robust, cfg.robust_delta), float(cfg.robust_delta)))

    def assemble(self) -> float:
        """H and g at the current poses; returns E (E_rho) there, the plain E in ``plain``."""
        t0 = time.perf_counter()
        e, self.plain = _assemble(self.graph, self.pat, self.rot, self.trans, self.data,
                                  self.grad, self.robust)
        self.seconds["assemble"] += time.perf_counter() - t0
        return e

    def solve(self, mu: float,
              iteration: int) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """The step: ``(H + mu D) delta = -g`` (LM) or ``H delta = -g`` (GN).

        Returns ``(damping, step_sys, step)``: the LM damping diagonal D (GN: empty), the step
        over the system's unknowns and over all of them.  LM returns None when the damped system
        is numerically not positive definite (H is only PSD: a robust kernel can weight every
        constraint of a pose to ~0, and a small ``mu D`` then drowns in rounding); the caller
        raises ``mu`` as for a rejected step.  H's values are unchanged on return.
        """
        t0 = time.perf_counter()
        system = self.system
        values = system.values(self.data, self.sys_values)
        g_sys = system.restrict(self.grad)
        damping = np.zeros(0)
        if self.cfg.method == "lm":
            diag_index = system.diag_index
            diag = values[diag_index]  # a copy: restored after the factorization
            damping = np.maximum(diag, _DIAG_FLOOR * diag.max())
            values[diag_index] = diag + mu * damping
            try:
                step_sys = self.solver.solve(values, -g_sys)
            except NotPositiveDefinite:
                self.seconds["factorize"] += time.perf_counter() - t0
                return None
            finally:
                values[diag_index] = diag
        else:
            step_sys = self.solver.solve(values, -g_sys, check=True)
        step = system.expand(step_sys, self.pat.dim)
        self.seconds["factorize"] += time.perf_counter() - t0
        if not np.all(np.isfinite(step)):
            if self.cfg.method == "lm":  # H + mu D is SPD: only overflow can cause this
                raise SolverError(f"iteration {iteration}: the LM step is not finite "
                                  f"(mu = {mu:.3g})")
            raise SolverError(f"iteration {iteration}: the Gauss-Newton step is not finite; "
                              "H is singular or ill-conditioned (use method='lm')")
        return damping, step_sys, step

    def trial(self, step: FloatArray, e_cur: float) -> tuple[float, float, int]:
        """Energy at the retracted poses (into ``new_rot/new_trans``); GN with its step guard
        halves the step until E does not rise.  Returns ``(e_new, scale, halvings)``."""
        t0 = time.perf_counter()
        scale = 1.0
        _k.retract(self.rot, self.trans, step, self.pat.var_of_node, scale, self.new_rot,
                   self.new_trans)
        e_new = _energy(self.graph, self.new_rot, self.new_trans, self.robust)
        tries = 0
        if self.cfg.method == "gn" and self.cfg.step_guard:
            while not (e_new <= e_cur) and tries < self.cfg.max_step_halvings:
                scale *= 0.5
                tries += 1
                _k.retract(self.rot, self.trans, step, self.pat.var_of_node, scale,
                           self.new_rot, self.new_trans)
                e_new = _energy(self.graph, self.new_rot, self.new_trans, self.robust)
        self.seconds["energy"] += time.perf_counter() - t0
        return e_new, scale, tries

    def accept(self) -> None:
        """Make the trial poses current."""
        self.rot, self.new_rot = self.new_rot, self.rot
        self.trans, self.new_trans = self.new_trans, self.trans


def _lm_damping(run: _Run, damping: FloatArray, step_sys: FloatArray, e_cur: float,
                e_new: float, mu: float, nu: float) -> tuple[bool, float, float]:
    """LM: accept when E did not rise; update mu by the gain ratio (Nielsen).

    The predicted decrease of the quadratic model ``E + 2 g.d + d.H.d`` (E has no 1/2) is
    ``-2 g.d - d.H.d = -g.d + mu d.D.d``, since ``(H + mu D) d = -g``: no product with H.
    Returns ``(take, mu, nu)``.
    """
    g_sys = run.system.restrict(run.grad)
    predicted = -float(g_sys @ step_sys) + mu * float(step_sys @ (damping * step_sys))
    take = bool(np.isfinite(e_new) and e_new <= e_cur)
    if take:
        rho = (e_cur - e_new) / predicted if predicted > 0 else 0.0
        return take, mu * max(_MAX_DECREASE, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
    return take, mu * nu, nu * 2.0


def _gn_accept(cfg: GaussNewtonConfig, e_cur: float, e_new: float, iteration: int) -> bool:
    """GN: with the step guard, accept when E did not rise; without it, always (finite E)."""
    if cfg.step_guard:
        return bool(np.isfinite(e_new) and e_new <= e_cur)
    if not np.isfinite(e_new):
        raise SolverError(f"iteration {iteration}: the Gauss-Newton step gives a "
                          "non-finite energy (use method='lm' or step_guard=True)")
    return True


def solve_exact(graph: PoseGraph, rotations: FloatArray | None = None,
                translations: FloatArray | None = None,
                config: GaussNewtonConfig | None = None, *,
                progress: ProgressCallback | None = None,
                iterate: IterateCallback | None = None) -> SolveResult:
    """Minimize E with sparse Gauss-Newton or Levenberg-Marquardt (DESIGN §7).

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64, optional
        Initial R_world_node, t_world_node (default: the graph's estimate).
    config : GaussNewtonConfig, optional
        Method, stopping criteria, damping, linear solver.
    progress : callable, optional
        ``progress(Progress("exact", iteration, max_iterations, energy))`` after every
        iteration (iteration 0: the start).
    iterate : callable, optional
        ``iterate(Progress, rotations, translations)`` with the current poses, at the same
        points as ``progress`` (:data:`IterateCallback`).

    Returns
    -------
    SolveResult
        ``method`` is ``"exact"``; ``stats["algorithm"]`` is ``"lm"`` or ``"gn"``.
        ``energy_history[k]`` is E after iteration k (unchanged after a rejected LM trial);
        with a robust kernel it is E_rho, and ``stats["plain_energy_history"]`` the plain E.
        ``stats``: accepted and rejected steps, step halvings, linear solver, final damping,
        nnz of H.

    Raises
    ------
    GraphError
        A connected part has no fixed pose and no GPS constraint.
    SolverError
        Non-finite initial poses or linearization; a singular system (GN without a gauge); a
        non-finite unguarded GN step.  Never returns non-finite poses.
    """
    cfg = GaussNewtonConfig() if config is None else config
    if cfg.robust == "auto":  # least squares, then the outlier test (solvers/robust.py)
        from .robust import solve_exact_auto

        return solve_exact_auto(graph, rotations, translations, cfg, progress=progress,
                                iterate=iterate)
    compile_s = _ensure_compiled()
    t_start = time.perf_counter()
    run = _Run.analyze(graph, rotations, translations, cfg)
    t_analyze = time.perf_counter() - t_start

    e_cur = run.assemble()
    history = [e_cur]
    plain_history = [run.plain]
    times = [time.perf_counter() - t_start]
    if progress is not None:
        progress(Progress("exact", 0, cfg.max_iterations, e_cur))
    if iterate is not None:
        iterate(Progress("exact", 0, cfg.max_iterations, e_cur), run.rot, run.trans)
    mu = cfg.initial_damping
    nu = 2.0
    accepted = rejected = halvings = 0
    status = Status.MAX_ITERATIONS
    iteration = 0
    if run.pat.num_vars == 0 or e_cur == 0.0:
        status = Status.CONVERGED
    while status is Status.MAX_ITERATIONS and iteration < cfg.max_iterations:
        iteration += 1
        solved = run.solve(mu, iteration)
        if solved is None:  # LM: H + mu D not numerically SPD -> more damping, as a rejection
            rejected += 1
            mu, nu = mu * nu, nu * 2.0
            if mu > _MAX_DAMPING:
                status = Status.STALLED
            history.append(e_cur)
            plain_history.append(run.plain)
            times.append(time.perf_counter() - t_start)
            continue
        damping, step_sys, step = solved
        step_small = float(np.max(np.abs(step))) < cfg.step_tolerance * (
            1.0 + float(np.max(np.abs(run.trans))))
        e_new, scale, tries = run.trial(step, e_cur)
        halvings += tries
        if cfg.method == "lm":
            take, mu, nu = _lm_damping(run, damping, step_sys, e_cur, e_new, mu, nu)
        else:
            take = _gn_accept(cfg, e_cur, e_new, iteration)
        changed = bool(np.isfinite(e_new)) and abs(e_new - e_cur) <= cfg.energy_tolerance * e_cur
        if take:
            accepted += 1
            run.accept()
            e_prev = e_cur
            e_cur = run.assemble()
            if e_cur == 0.0 or abs(e_prev - e_cur) <= cfg.energy_tolerance * e_prev:
                status = Status.CONVERGED
            elif step_small and scale == 1.0:
                status = Status.CONVERGED
        else:
            rejected += 1
            if changed or step_small:  # E or the poses no longer change measurably
                status = Status.CONVERGED
            elif cfg.method == "gn" or mu > _MAX_DAMPING:
                status = Status.STALLED
        history.append(e_cur)
        plain_history.append(run.plain)
        times.append(time.perf_counter() - t_start)
        if progress is not None:
            progress(Progress("exact", iteration, cfg.max_iterations, e_cur))
        if iterate is not None:
            iterate(Progress("exact", iteration, cfg.max_iterations, e_cur), run.rot, run.trans)

    t_total = time.perf_counter() - t_start
    robust_stats: dict[str, Any] = {}
    if run.robust[0] != _cost.ROBUST_NONE:
        robust_stats = {"robust": cfg.robust, "robust_scale": cfg.robust_delta,
                        "plain_energy": plain_history[-1],
                        "plain_energy_history": plain_history}
    return SolveResult(
        rotations=run.rot, translations=run.trans, status=status, iterations=iteration,
        energy_history=np.asarray(history), times=np.asarray(times), method="exact",
        num_constraints=graph.num_constraints,
        timings={"compile": compile_s, "analyze": t_analyze, "solve": t_total - t_analyze,
                 "total": t_total, **run.seconds},
        stats={"algorithm": cfg.method, "accepted_steps": accepted, "rejected_steps": rejected,
               "step_halvings": halvings, "linear_solver": run.solver.name,
               "final_damping": mu if cfg.method == "lm" else 0.0,
               "num_variables": run.system.dim,
               "hessian_nnz": 2 * run.system.nnz - run.system.dim, "planar": run.planar,
               **robust_stats},
    )
