"""The normal equations of the exact solver: gauge, sparsity pattern, assembly.

Ordinary global parametrization with right perturbations ``X_i <- X_i Exp(delta_i)``, tangent
order (rho, phi), energy ``E = sum_c e_c^T Omega_c e_c`` (no 1/2; docs/conventions.md).  The
normal equations ``H delta = -g`` with ``H = J^T Omega J``, ``g = J^T Omega e`` are assembled by one
Numba kernel (:func:`._gn_kernels.assemble_normal_equations`) straight into the values of a CSC
matrix whose sparsity pattern and fill-reducing ordering are computed once (:func:`analyze`).

Gauge: the nodes named by ``FIX`` lines (``graph.fixed_nodes``) are held constant.  Without any,
the first pose (dense index 0) is fixed, unless the graph has position-only (GPS) constraints:
then the earth frame is the gauge and no pose is fixed.

Lifted 2D graphs at planar poses solve only the (x, y, yaw) unknowns (:func:`planar_system`):
the other three are decoupled and their step is exactly zero (M3500: 133 -> 38 ms per
iteration).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .. import _cost
from ..errors import GraphError, SolverError
from ..graph import IN_PLANE, FloatArray, PoseGraph, planar_data, planar_motions
from ..linalg import fill_reducing_order, make_factorizer
from . import _gn_kernels as _k

Int64Array = npt.NDArray[np.int64]

# --------------------------------------------------------------------------- gauge
def default_fixed_nodes(graph: PoseGraph) -> npt.NDArray[np.int32]:
    """Dense indices of the nodes the exact solver holds constant (the gauge, see module doc)."""
    if graph.fixed_nodes.size:
        return np.unique(graph.fixed_nodes).astype(np.int32)
    if graph.num_gps:
        return np.zeros(0, np.int32)
    return np.zeros(1, np.int32)


def check_gauge(graph: PoseGraph, fixed: npt.NDArray[np.int32]) -> None:
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
class Pattern:
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


def analyze(graph: PoseGraph, fixed: npt.NDArray[np.int32], reorder: bool) -> Pattern:
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
        var[free] = fill_reducing_order(nv, np.concatenate([va, vb]), np.concatenate([vb, va]))
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
    indptr = block_indptr(block_ptr, 6)
    return Pattern(var_of_node=var, num_vars=nv, indptr=indptr, block_ptr=block_ptr,
                    block_row=np.ascontiguousarray(uniq % max(nv, 1)), edge_off=edge_off)


def lower_to_full(values: FloatArray, indices: Int64Array, indptr: Int64Array,
                   dim: int) -> sp.csc_matrix:
    """The symmetric matrix (both triangles) whose lower triangle is given."""
    low = sp.csc_matrix((values, indices, indptr), shape=(dim, dim))
    full = (low + low.T - sp.diags(low.diagonal())).tocsc()
    full.sort_indices()
    return full


# Lifted-2D graphs (docs/conventions.md): at planar poses with planar measurements and
# block-separable information, H and g do not couple the tangent entries x, y, yaw
# (graph.IN_PLANE) with z, roll, pitch (every Jacobian keeps the parity of in-plane vs
# out-of-plane components) and g is 0 there, so the step's out-of-plane part is exactly 0:
# only the (x, y, yaw) system is solved.


#: The tangent entries a pose keeps in the whole system, and in the planar one.
ALL_DOFS = np.arange(6, dtype=np.int64)
PLANAR_DOFS = np.ascontiguousarray(IN_PLANE, dtype=np.int64)


@dataclass(frozen=True, slots=True)
class System:
    """The symmetric system actually factored: all of H, or its (x, y, yaw) rows/columns.

    Stored as its lower triangle in CSC form, rows increasing in each column (so the diagonal
    entry comes first): the layout of :class:`hybridpgo.linalg.SymmetricPattern`, by blocks of
    ``len(tangent)`` (:mod:`._gn_kernels`), which the assembly writes straight into.
    """

    indptr: Int64Array  # CSC pattern of the lower triangle of the (dim, dim) system matrix
    indices: Int64Array  # empty once the factorizer has taken them (CHOLMOD keeps its own)
    dofs: Int64Array | None  # positions of the system's unknowns in the full vector; None: all
    tangent: Int64Array  # the tangent entries (of 6) each pose keeps, increasing
    dim: int

    @property
    def diag_index(self) -> Int64Array:
        return self.indptr[:-1]

    @property
    def nnz(self) -> int:
        return int(self.indptr[-1])

    def restrict(self, vec: FloatArray) -> FloatArray:
        return vec if self.dofs is None else vec[self.dofs]

    def expand(self, sub: FloatArray, dim: int) -> FloatArray:
        if self.dofs is None:
            return sub
        out = np.zeros(dim)
        out[self.dofs] = sub
        return out


def block_indptr(block_ptr: Int64Array, nd: int) -> Int64Array:
    """Column pointers of the lower triangle by (nd, nd) blocks: column ``nd j + q`` holds the
    diagonal block's rows q..nd-1, then nd rows per lower block of block column j."""
    q = np.arange(nd, dtype=np.int64)
    counts = (nd - q)[None, :] + nd * np.diff(block_ptr)[:, None]
    indptr = np.zeros(nd * (block_ptr.shape[0] - 1) + 1, np.int64)
    np.cumsum(counts.ravel(), out=indptr[1:])
    return indptr


def full_system(pat: Pattern) -> System:
    return System(pat.indptr, pat.lower_indices(), None, ALL_DOFS, pat.dim)


def planar_system(pat: Pattern) -> System:
    """The (x, y, yaw) rows and columns of H, in the layout of H by (3, 3) blocks."""
    keep = (6 * np.arange(pat.num_vars)[:, None] + PLANAR_DOFS[None, :]).ravel()
    indptr = block_indptr(pat.block_ptr, 3)
    indices = np.empty(int(indptr[-1]), np.int64)
    _k.lower_pattern_indices(pat.block_ptr, pat.block_row, indptr, indices)
    return System(indptr, indices, keep, PLANAR_DOFS, int(keep.shape[0]))


def is_planar(graph: PoseGraph, rot: FloatArray, trans: FloatArray) -> bool:
    """True when the (x, y, yaw) reduction is exact (the note above :func:`planar_system`):
    a 2D graph without GPS whose data (:func:`~hybridpgo.graph.planar_data`) and poses are
    planar."""
    if not graph.is_2d or graph.num_gps or not planar_data(graph):
        return False
    return planar_motions(rot, trans)


# --------------------------------------------------------------------------- linearize
def assemble(graph: PoseGraph, pat: Pattern, rot: FloatArray, trans: FloatArray,
              data: FloatArray, grad: FloatArray, robust: tuple[int, float] = (0, 1.0),
              system: System | None = None) -> tuple[float, float]:
    """H (``system``'s rows and columns of it; default all) and g into ``data``, ``grad``;
    returns ``(E_rho, E)`` (equal without a kernel)."""
    indptr, tangent = (pat.indptr, ALL_DOFS) if system is None else (system.indptr,
                                                                      system.tangent)
    status, e, plain = _k.assemble_normal_equations(
        rot, trans, graph.edge_nodes, graph.edge_rotations, graph.edge_translations,
        graph.edge_information, pat.edge_off, graph.gps_nodes, graph.gps_positions,
        graph.gps_information, pat.var_of_node, indptr, data, grad, robust[0], robust[1],
        tuple(int(d) for d in tangent),  # a tuple: one compiled variant per system size
    )
    if status >= 0:
        where = describe_constraint(graph, status)
        raise SolverError(f"the linearization is not finite at {where}")
    return float(e), float(plain)


def energies_at(graph: PoseGraph, rot: FloatArray, trans: FloatArray,
                robust: tuple[int, float] = (0, 1.0), planar: bool = False
                ) -> tuple[float, float]:
    """``(E_rho, E)`` at trial poses (equal without a robust kernel; may be inf/nan: the
    callers reject such steps), each the same sum, in the same order, as :func:`assemble`'s.
    ``planar``: the poses and data are planar (:func:`is_planar`); the errors are SE(2)'s, as
    the planar system's assembly computes them."""
    if robust[0] != _cost.ROBUST_NONE or planar:
        e_rho, e = _cost.robust_total_energy(
            rot, trans, graph.edge_nodes, graph.edge_rotations, graph.edge_translations,
            graph.edge_information, graph.gps_nodes, graph.gps_positions,
            graph.gps_information, robust[0], robust[1], planar)
        return float(e_rho), float(e)
    e = float(_cost.total_energy(rot, trans, graph.edge_nodes, graph.edge_rotations,
                                 graph.edge_translations, graph.edge_information,
                                 graph.gps_nodes, graph.gps_positions, graph.gps_information))
    return e, e


def energy_at(graph: PoseGraph, rot: FloatArray, trans: FloatArray,
              robust: tuple[int, float] = (0, 1.0), planar: bool = False) -> float:
    """E (E_rho with a robust kernel) at trial poses: :func:`energies_at`'s first."""
    return energies_at(graph, rot, trans, robust, planar)[0]


def describe_constraint(graph: PoseGraph, c: int) -> str:
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
        Robust kernel and its delta (docs/conventions.md#robust-kernels; as in
        :class:`GaussNewtonConfig`): each
        relative constraint's terms are weighted by ``w_c = rho'(s_c)`` (IRLS).
    """
    kind = _cost.robust_kind(robust, robust_scale)
    rot, trans = initial_poses(graph, rotations, translations)
    fx = fixed_array(graph, fixed)
    pat = analyze(graph, fx, reorder=False)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    e, _plain = assemble(graph, pat, rot, trans, data, grad, (kind, float(robust_scale)))
    h = lower_to_full(data, pat.lower_indices(), pat.indptr, pat.dim)
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
    rot, trans = initial_poses(graph, rotations, translations)
    fx = fixed_array(graph, fixed)
    pat = analyze(graph, fx, reorder=True)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    assemble(graph, pat, rot, trans, data, grad)
    step = make_factorizer(full_system(pat), "auto").solve(data, -grad, check=True)
    out = np.zeros((graph.num_nodes, 6))
    free = pat.var_of_node >= 0
    out[free] = step.reshape(-1, 6)[pat.var_of_node[free]]
    return out



# --------------------------------------------------------------------------- helpers
def initial_poses(graph: PoseGraph, rotations: FloatArray | None,
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


def fixed_array(graph: PoseGraph, fixed: npt.ArrayLike | None) -> npt.NDArray[np.int32]:
    if fixed is None:
        return default_fixed_nodes(graph)
    fx = np.unique(np.asarray(fixed, dtype=np.int64).reshape(-1))
    if fx.size and (fx[0] < 0 or fx[-1] >= graph.num_nodes):
        raise ValueError(f"fixed node indices must lie in 0..{graph.num_nodes - 1}")
    return fx.astype(np.int32)


_COMPILED = [False]


def ensure_compiled() -> float:
    """Compile (or load from cache) the kernels on a two-node graph; return the seconds spent."""
    if _COMPILED[0]:
        return 0.0
    t0 = time.perf_counter()
    eye = np.eye(3)[None].repeat(2, axis=0)
    g = PoseGraph(node_ids=np.arange(2), rotations=eye, translations=np.zeros((2, 3)),
                  edge_nodes=np.array([[0, 1]]), edge_rotations=eye[:1],
                  edge_translations=np.ones((1, 3)), edge_information=np.eye(6)[None],
                  gps_nodes=np.array([1]), gps_positions=np.ones((1, 3)),
                  gps_information=np.eye(3)[None])
    pat = analyze(g, np.zeros(0, np.int32), reorder=False)
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    rot = np.array(g.rotations)  # writable, like the solver's state (Numba types differ)
    trans = np.array(g.translations)
    assemble(g, pat, rot, trans, data, grad)
    planar = planar_system(pat)  # the planar system's variant of the assembly too
    assemble(g, pat, rot, trans, np.empty(planar.nnz), grad, (0, 1.0), planar)
    out_r = np.empty((2, 3, 3))
    out_t = np.empty((2, 3))
    _k.retract(rot, trans, grad, pat.var_of_node, 1.0, out_r, out_t)
    energy_at(g, out_r, out_t)
    energy_at(g, out_r, out_t, (_cost.ROBUST_HUBER, 1.0))
    energy_at(g, out_r, out_t, (0, 1.0), True)
    _COMPILED[0] = True
    return time.perf_counter() - t0


