"""A TORO-style baseline (Grisetti et al.'s tree-based network optimizer), written from the rule
in ``shared/TORO.md`` (TORO's own code was not read).

TORO relaxes one constraint at a time in a tree parametrization, like the hybrid solver, but
corrects rotation and translation *separately*: the rotational residual is spread over the path
as rotations about one global axis, then the translational residual (on the re-bent path) as
pure translations.  A translation error is never turned into a rotation, which is what produces
the "dog-leg" distortion the paper fixes (paper Fig. 2, Fig. 3e/f).

Summary of the rule (TORO.md):

* **Tree** (``ToroConfig.tree``): ``"toro"`` (default, TORO's): each pose's parent is its
  smallest-id neighbour, from the smallest-id pose (see :func:`build_toro_tree` for graphs where
  a pose has no smaller-id neighbour); ``"bfs"``: the hybrid solver's breadth-first tree
  (:func:`hybridpgo.tree.build_tree`).  Initial guess: tree-edge measurements composed down from
  the root (``init="tree"``), or the file's vertices (``init="file"``).
* **Order**: constraints by increasing depth of their top node (lowest common ancestor); ties in
  file order (relative edges, then GPS readings).
* **Preconditioner**, once: ``rho_e`` / ``tau_e`` = smallest diagonal entry of the rotation /
  translation block of ``Omega_e``; ``M_n.rot += rho_e``, ``M_n.trans += tau_e`` for every node
  of e's path except the top (GPS readings included, with rho = 0); ``gamma_R = min rho_e``,
  ``gamma_T = min tau_e`` over the relative edges (GPS readings are not in TORO's gamma: see
  ``ToroState.create``).  Node weights ``1/M_n``.
* **Per constraint**, sweep counter ``k`` (2 in the first sweep, then 3, 4, ...), path length
  ``l`` (path nodes other than the top): rotation residual ``R_v1 R_e R_v2^-1 = Rot(a, theta)``,
  gain ``f_R = min(1, sqrt(l) rho_e / (gamma_R k))``, each path node turns by
  ``Rot(a, theta f_R (C(n) - C(top)))`` on the left (C: cumulative normalized rotational weight
  from v1), local translations kept; then ``t_R = (T_v1 T_e).t - t_v2``, gain
  ``f_T = min(1, l tau_e / (gamma_T k))``, v1-wing nodes move by ``-f_T t_R (cumulative weight
  from the top)``, v2-wing nodes by ``+f_T t_R (...)``.

GPS (extension, ``ToroConfig.gps=True``, the default): TORO has no unary constraints.  Here a
fixed *earth* node (index N, identity pose) roots the tree; each connected part of the pose graph
hangs from it below its smallest-id pose with a GPS reading (the tree link takes that reading's
position), and every GPS reading is a constraint earth -> pose whose path is the pose and all its
ancestors.  Relaxing one moves the path nodes by the translation-only distribution of step 2 and
changes no rotation: exactly the dog-leg the paper shows.  With ``gps=False`` a graph with GPS
constraints is refused, as the original TORO would.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .._numba import cycles_per_second
from ..energy import energy
from ..errors import GraphError, SolverError
from ..graph import FloatArray, PoseGraph
from . import _toro_kernels as _tk
from .config import Progress, ProgressCallback
from .result import SolveResult, Status

# Numba dispatchers carry no useful static types (as in hybrid.py).
tk: Any = _tk

I32 = npt.NDArray[np.int32]

TREES = ("toro", "bfs")
INITS = ("tree", "file")
WEIGHTS = ("documented", "swapped")



@dataclass(frozen=True)
class ToroConfig:
    """Options of :func:`solve_toro`; every field is checked in ``__post_init__``."""

    iterations: int = 100
    """Number of sweeps over all constraints (TORO's default: 100).  Sweep s uses the counter
    ``k = s + 1`` in the gains (TORO.md: k starts at 2)."""
    tree: str = "toro"
    """``"toro"``: each pose's parent is its smallest-id neighbour (TORO's default, shallow when
    loop closures reach old poses); ``"bfs"``: the hybrid solver's breadth-first tree."""
    init: str = "tree"
    """``"tree"``: compose the tree edges' measurements down from the root (TORO); ``"file"``:
    the file's vertex estimates."""
    weights: str = "documented"
    """Node weights of the distribution.  ``"documented"`` (default, TORO's stated intent): the
    rotation is spread with ``1/M_n.rot`` and the translation with ``1/M_n.trans``;
    ``"swapped"``: as TORO's code does it (rotation with ``1/M_n.trans`` and vice versa)."""
    energy_tolerance: float = 0.0
    """Stop (converged) when a sweep lowers the energy by less than this fraction of it,
    ``(E_prev - E) / E_prev < energy_tolerance`` with ``E <= E_prev``; 0: run all iterations."""
    gps: bool = True
    """Accept GPS (position-only) constraints through the earth-rooted extension (module
    docstring); it shows the dog-leg.  ``False``: a graph with GPS constraints raises
    :class:`~hybridpgo.errors.GraphError`, as TORO cannot represent them."""

    def __post_init__(self) -> None:
        it = self.iterations
        if isinstance(it, bool) or not isinstance(it, int) or it < 0:
            raise ValueError(f"iterations must be an integer >= 0, got {it!r}")
        for name, allowed in (("tree", TREES), ("init", INITS), ("weights", WEIGHTS)):
            value = getattr(self, name)
            if value not in allowed:
                raise ValueError(
                    f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}"
                )
        tol = self.energy_tolerance
        if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (0.0 <= tol < 1e300):
            raise ValueError(f"energy_tolerance must be a finite number >= 0, got {tol!r}")
        if not isinstance(self.gps, bool):
            raise ValueError(f"gps must be True or False, got {self.gps!r}")


# ----------------------------------------------------------------------------- the tree
@dataclass(frozen=True)
class ToroTree:
    """A rooted spanning tree and the constraint paths (CSR, as in :mod:`hybridpgo.tree`)."""

    num_poses: int
    """N."""
    has_earth: bool
    """True when node N is the earth (the graph has GPS constraints)."""
    root: int
    """The fixed root (N for the earth)."""
    parent: I32
    """(T,) parent index, -1 for the root; T = N + has_earth."""
    order: I32
    """(T,) nodes with every parent before its children."""
    depth: I32
    """(T,) depth below the root."""
    link_edge: I32
    """(T,) relative edge joining the node to its parent (first in file order), or -1."""
    link_gps: I32
    """(T,) GPS reading joining the node to the earth (first in file order), or -1."""
    path_ptr: npt.NDArray[np.int64]
    """(C+1,) CSR offsets; constraints are the M relative edges, then the G GPS readings."""
    path_node: I32
    """(nnz,) path nodes: a up to the top (sign -1), then b up to the top (sign +1)."""
    path_sign: npt.NDArray[np.int8]
    """(nnz,) -1 on the a (v1) wing, +1 on the b (v2) wing and for GPS."""
    top: I32
    """(C,) the top (lowest common ancestor) of every constraint; the earth for GPS."""
    sweep_order: I32
    """(C,) constraints by increasing depth of their top (stable)."""

    @property
    def num_tree_nodes(self) -> int:
        return int(self.parent.shape[0])

    @property
    def num_constraints(self) -> int:
        return int(self.path_ptr.shape[0] - 1)

    def path_lengths(self) -> npt.NDArray[np.int64]:
        """(C,) path length l of every constraint (nodes other than the top)."""
        return np.diff(self.path_ptr)


def build_toro_tree(graph: PoseGraph, kind: str = "toro") -> ToroTree:
    """Grow the tree and the constraint paths.

    ``kind="toro"``: nodes are visited by increasing index from the root, each taking as parent
    its smallest-index visited neighbour (:func:`_toro_kernels.smallest_id_tree`).  When every
    pose but the root has a smaller-id neighbour this is exactly TORO's rule "the parent is the
    smallest-id node with an edge into it".  The root is the smallest-id pose (or the pose a FIX
    line names); with GPS it is the earth, whose index is the largest, so a pose hangs from the
    earth only where no pose reaches it first (one GPS link per connected part).
    ``kind="bfs"``: the parents of :func:`hybridpgo.tree.build_tree` (breadth-first).

    Raises
    ------
    GraphError
        The graph is not connected (with GPS: a part has no GPS reading), or it fixes more than
        one pose.
    """
    if kind not in TREES:
        raise ValueError(f"tree must be one of {', '.join(map(repr, TREES))}, got {kind!r}")
    n, m, g = graph.num_nodes, graph.num_edges, graph.num_gps
    has_earth = g > 0
    t_nodes = n + int(has_earth)
    a = graph.edge_nodes[:, 0].astype(np.int64)
    b = graph.edge_nodes[:, 1].astype(np.int64)
    if has_earth:
        root = n
    else:
        if graph.fixed_nodes.size > 1:
            raise GraphError(
                f"the graph fixes {graph.fixed_nodes.size} poses (FIX lines); the TORO tree holds "
                "exactly one pose fixed, its root: keep one FIX line, or use the exact solver"
            )
        root = int(graph.fixed_nodes[0]) if graph.fixed_nodes.size else 0

    if kind == "toro":
        ea = np.concatenate([a, np.full(g, n, np.int64)])
        eb = np.concatenate([b, graph.gps_nodes.astype(np.int64)])
        src = np.concatenate([ea, eb])
        dst = np.concatenate([eb, ea])
        srt = np.lexsort((dst, src))  # CSR adjacency, neighbours sorted
        indptr = np.zeros(t_nodes + 1, np.int64)
        np.cumsum(np.bincount(src, minlength=t_nodes), out=indptr[1:])
        parent = np.empty(t_nodes, np.int32)
        order = np.empty(t_nodes, np.int32)
        visited = tk.smallest_id_tree(indptr, np.ascontiguousarray(dst[srt]), root, parent, order)
        if visited != t_nodes:
            graph.check_connected()
            raise GraphError("the graph is not connected")  # pragma: no cover
    else:
        from ..tree import build_tree

        bt = build_tree(graph, "bfs")
        parent = np.array(bt.parent, np.int32)
        order = np.array(bt.order, np.int32)
        root = bt.root

    # which constraint links each node to its parent (the first in file order)
    link_edge = np.full(t_nodes, -1, np.int32)
    link_gps = np.full(t_nodes, -1, np.int32)
    child = np.nonzero(parent >= 0)[0]
    if has_earth:
        gchild = child[parent[child] == n]
        child = child[parent[child] != n]
        first = np.full(n, -1, np.int64)
        first[graph.gps_nodes[::-1]] = np.arange(g - 1, -1, -1)
        link_gps[gchild] = first[gchild]
    if child.size:
        key_e = np.minimum(a, b) * t_nodes + np.maximum(a, b)
        srt = np.argsort(key_e, kind="stable")
        p = parent[child].astype(np.int64)
        key_c = np.minimum(p, child) * t_nodes + np.maximum(p, child)
        e_idx = srt[np.searchsorted(key_e[srt], key_c)]
        if not np.all(key_e[e_idx] == key_c):  # pragma: no cover - internal invariant
            raise AssertionError("a tree link has no edge")
        link_edge[child] = e_idx

    depth = np.zeros(t_nodes, np.int32)
    tk.depths(order, parent, depth)
    c_nodes = np.empty((m + g, 2), np.int32)
    c_nodes[:m] = graph.edge_nodes
    c_nodes[m:, 0] = n
    c_nodes[m:, 1] = graph.gps_nodes
    lengths = np.zeros(m + g, np.int64)
    top = np.zeros(m + g, np.int32)
    tk.path_lengths(c_nodes, parent, depth, lengths, top)
    ptr = np.zeros(m + g + 1, np.int64)
    np.cumsum(lengths, out=ptr[1:])
    path_node = np.empty(int(ptr[-1]), np.int32)
    path_sign = np.empty(int(ptr[-1]), np.int8)
    tk.fill_paths(c_nodes, parent, top, ptr, path_node, path_sign)
    sweep_order = np.argsort(depth[top], kind="stable").astype(np.int32)
    arrays: dict[str, Any] = dict(
        parent=parent, order=order, depth=depth, link_edge=link_edge, link_gps=link_gps,
        path_ptr=ptr, path_node=path_node, path_sign=path_sign, top=top,
        sweep_order=sweep_order,
    )
    for v in arrays.values():
        v.flags.writeable = False
    return ToroTree(num_poses=n, has_earth=has_earth, root=root, **arrays)


def toro_initial_locals(
    graph: PoseGraph, tree: ToroTree, init: str = "tree"
) -> tuple[FloatArray, FloatArray]:
    """Initial local transforms ``(rot (T,3,3), trans (T,3))`` of every tree node.

    ``"tree"``: each node's local transform is its tree edge's measurement (inverted when the
    edge points from child to parent); a child of the earth gets its GPS reading's position and
    its rotation from the file (identity when the file has none); the root pose keeps its file
    pose.  ``"file"``: ``T_i = X_parent^-1 X_i`` from the file's vertices.  The earth is the
    identity.
    """
    if init not in INITS:
        raise ValueError(f"init must be one of {', '.join(map(repr, INITS))}, got {init!r}")
    if init == "file" and not graph.has_estimates:
        raise GraphError(
            "init='file' needs vertex estimates, but the file has none "
            "(iSAM files list only constraints): use init='tree'"
        )
    n = graph.num_nodes
    t_nodes = tree.num_tree_nodes
    grot = np.tile(np.eye(3), (t_nodes, 1, 1))
    gtr = np.zeros((t_nodes, 3))
    grot[:n] = graph.rotations
    gtr[:n] = graph.translations
    parent = tree.parent
    if init == "file":
        rot = np.array(grot)
        trans = np.array(gtr)
        child = np.nonzero(parent >= 0)[0]
        p = parent[child]
        rot[child] = np.einsum("kji,kjl->kil", grot[p], grot[child])
        trans[child] = np.einsum("kji,kj->ki", grot[p], gtr[child] - gtr[p])
        return rot, trans
    rot = np.tile(np.eye(3), (t_nodes, 1, 1))
    trans = np.zeros((t_nodes, 3))
    e = tree.link_edge >= 0
    ei = tree.link_edge[e]
    fwd = graph.edge_nodes[ei, 0] == parent[e]
    zr = graph.edge_rotations[ei]
    zt = graph.edge_translations[ei]
    # forward link (parent, child): T = Z; reversed (child, parent): T = Z^-1
    rot[e] = np.where(fwd[:, None, None], zr, np.swapaxes(zr, 1, 2))
    trans[e] = np.where(fwd[:, None], zt, -np.einsum("kji,kj->ki", zr, zt))
    gl = tree.link_gps >= 0
    trans[gl] = graph.gps_positions[tree.link_gps[gl]]
    rot[gl] = grot[gl]
    if not tree.has_earth:
        rot[tree.root] = grot[tree.root]
        trans[tree.root] = gtr[tree.root]
    return rot, trans


# ----------------------------------------------------------------------------- the solver state
@dataclass
class ToroState:
    """Mutable solver state: the tree, the preconditioned weights and the local transforms."""

    graph: PoseGraph
    tree: ToroTree
    rot: FloatArray
    """(T, 3, 3) local rotations R_parent_node, updated in place."""
    trans: FloatArray
    """(T, 3) local translations, updated in place."""
    rho: FloatArray
    """(C,) smallest rotational information diagonal of each constraint (0 for GPS)."""
    tau: FloatArray
    """(C,) smallest translational information diagonal of each constraint."""
    gamma_r: float
    """min rho over the relative edges."""
    gamma_t: float
    """min tau over the relative edges (over the GPS readings when there are no edges)."""
    m_rot: FloatArray
    """(T,) M_n.rot: the sum of rho over the constraints whose path holds n (top excluded)."""
    m_trans: FloatArray
    """(T,) M_n.trans: the same with tau."""
    w_rot: FloatArray
    """(T,) weights of the rotational distribution (1/M, 0 where M = 0)."""
    w_trans: FloatArray
    """(T,) weights of the translational distribution."""
    meas_trans: FloatArray
    """(C, 3) measured translations, then the GPS positions."""

    @classmethod
    def create(cls, graph: PoseGraph, tree: ToroTree, rot: FloatArray, trans: FloatArray,
               weights: str = "documented") -> ToroState:
        """Compute the preconditioner (TORO.md, once before the first sweep)."""
        if weights not in WEIGHTS:
            raise ValueError(f"weights must be one of {', '.join(map(repr, WEIGHTS))}, "
                             f"got {weights!r}")
        info = graph.edge_information
        diag = np.diagonal(info, axis1=1, axis2=2)  # (M, 6) over (rho, phi)
        rho_rel = diag[:, 3:].min(axis=1) if graph.num_edges else np.zeros(0)
        tau_rel = diag[:, :3].min(axis=1) if graph.num_edges else np.zeros(0)
        tau_gps = (np.diagonal(graph.gps_information, axis1=1, axis2=2).min(axis=1)
                   if graph.num_gps else np.zeros(0))
        rho = np.concatenate([rho_rel, np.zeros(graph.num_gps)])
        tau = np.concatenate([tau_rel, tau_gps])
        lengths = tree.path_lengths()
        t_nodes = tree.num_tree_nodes
        m_rot: FloatArray = np.bincount(
            tree.path_node, weights=np.repeat(rho, lengths), minlength=t_nodes
        ).astype(np.float64)
        m_trans: FloatArray = np.bincount(
            tree.path_node, weights=np.repeat(tau, lengths), minlength=t_nodes
        ).astype(np.float64)
        gamma_r = float(rho_rel.min()) if rho_rel.size else 1.0
        # gamma over the relative edges only: with the (much weaker) GPS readings included,
        # every relative gain f_T saturates at 1 for thousands of sweeps and TORO stops
        # converging (measured, valencia w/ GPS, 100 sweeps: 279 per constraint vs 30.7)
        gamma_t = (float(tau_rel.min()) if tau_rel.size
                   else float(tau_gps.min()) if tau_gps.size else 1.0)
        # a subnormal weight (information of 1e-320) has no finite inverse: as no weight
        tiny = np.finfo(np.float64).tiny
        inv_r = np.divide(1.0, m_rot, out=np.zeros(t_nodes), where=m_rot >= tiny)
        inv_t = np.divide(1.0, m_trans, out=np.zeros(t_nodes), where=m_trans >= tiny)
        w_rot, w_trans = (inv_r, inv_t) if weights == "documented" else (inv_t, inv_r)
        meas_trans = np.concatenate([graph.edge_translations, graph.gps_positions])
        return cls(graph=graph, tree=tree, rot=np.array(rot, np.float64, order="C"),
                   trans=np.array(trans, np.float64, order="C"), rho=rho, tau=tau,
                   gamma_r=gamma_r, gamma_t=gamma_t, m_rot=m_rot, m_trans=m_trans,
                   w_rot=w_rot, w_trans=w_trans, meas_trans=meas_trans)

    def problem(self) -> tuple[Any, ...]:
        """The read-only arrays the kernels take as ``prob`` (see ``_toro_kernels``)."""
        g, t = self.graph, self.tree
        return (g.num_edges, t.path_ptr, t.path_node, t.path_sign, t.top, g.edge_rotations,
                self.meas_trans, self.rho, self.tau, self.gamma_r, self.gamma_t, self.w_rot,
                self.w_trans)

    def workspace(self) -> tuple[Any, ...]:
        d = max(int(self.tree.path_lengths().max(initial=0)), 1)
        return (np.zeros((d, 3, 3)), np.zeros((d, 3)), np.zeros((3, 3)), np.eye(3), np.zeros(3))

    def relax(self, c: int, k: float) -> int:
        """Relax constraint ``c`` once with sweep counter ``k``; returns 1 if not finite."""
        return int(tk.update_constraint(int(c), float(k), self.problem(),
                                        (self.rot, self.trans), self.workspace()))

    def sweep(self, k: float, cycles: npt.NDArray[np.uint64]) -> int:
        """One pass over the constraints in tree order; returns -1 or the first bad one."""
        return int(tk.sweep(self.tree.sweep_order, float(k), self.problem(),
                            (self.rot, self.trans), self.workspace(), cycles))

    def poses(self) -> tuple[FloatArray, FloatArray]:
        """Global poses ``(R (N,3,3), t (N,3))`` of the N poses."""
        t_nodes = self.tree.num_tree_nodes
        grot = np.empty((t_nodes, 3, 3))
        gtr = np.empty((t_nodes, 3))
        tk.globals_from_locals(self.tree.order, self.tree.parent, self.rot, self.trans, grot, gtr)
        n = self.tree.num_poses
        return grot[:n].copy(), gtr[:n].copy()

    def energy(self) -> float:
        return energy(self.graph, *self.poses())


# ----------------------------------------------------------------------------- timing
def _ensure_compiled() -> float:
    """Compile (or load from Numba's cache) every kernel once; returns the seconds spent."""
    if getattr(tk.sweep, "signatures", None):
        return 0.0
    t0 = time.perf_counter()
    eye = np.tile(np.eye(3), (3, 1, 1))
    tiny = PoseGraph(
        node_ids=np.arange(3), rotations=eye, translations=np.eye(3),
        edge_nodes=np.array([[0, 1], [1, 2], [0, 2]], np.int32), edge_rotations=eye,
        edge_translations=np.ones((3, 3)), edge_information=np.tile(np.eye(6), (3, 1, 1)),
        gps_nodes=np.array([2], np.int32), gps_positions=np.ones((1, 3)),
        gps_information=np.eye(3)[None],
    )
    _solve(tiny, ToroConfig(iterations=1), None, compile_s=0.0)
    cycles_per_second()
    return time.perf_counter() - t0


# ----------------------------------------------------------------------------- the solver
def solve_toro(
    graph: PoseGraph, config: ToroConfig | None = None, progress: ProgressCallback | None = None
) -> SolveResult:
    """Optimize ``graph`` with the TORO-style baseline (module docstring, shared/TORO.md).

    Parameters
    ----------
    graph : PoseGraph
    config : ToroConfig, optional
    progress : callable, optional
        ``progress(Progress("toro", iteration, iterations, energy))`` after every iteration
        (iteration 0: the start).

    Returns
    -------
    SolveResult
        ``method="toro"``; ``stats`` holds per-constraint update times
        (``us_per_constraint_mean``, ``us_per_constraint_max`` over every update,
        ``us_per_constraint_max_steady``: the largest over constraints of each constraint's
        cheapest update, free of scheduler interruptions), tree and path statistics.

    Raises
    ------
    GraphError
        GPS constraints with ``config.gps=False``; a disconnected graph (with GPS: a part
        without a GPS reading); more than one FIX line; ``init="file"`` without vertices.
    SolverError
        The energy became non-finite.
    """
    cfg = config or ToroConfig()
    if graph.num_gps and not cfg.gps:
        raise GraphError(
            f"TORO cannot represent position-only (GPS) constraints and the graph has "
            f"{graph.num_gps}: remove them, or accept them with the earth-rooted extension "
            "(ToroConfig(gps=True)), which suffers dog-legs"
        )
    compile_s = _ensure_compiled()
    return _solve(graph, cfg, progress, compile_s)


def _solve(graph: PoseGraph, cfg: ToroConfig, progress: ProgressCallback | None,
           compile_s: float) -> SolveResult:
    t_start = time.perf_counter()
    tree = build_toro_tree(graph, cfg.tree)
    rot0, trans0 = toro_initial_locals(graph, tree, cfg.init)
    state = ToroState.create(graph, tree, rot0, trans0, cfg.weights)
    t_analyze = time.perf_counter() - t_start

    nc = tree.num_constraints
    cycles = np.zeros(nc, np.uint64)
    steady = np.full(nc, np.iinfo(np.uint64).max, np.uint64)
    sum_cycles = 0.0
    max_cycles = 0
    e0 = state.energy()
    history = [e0]
    times = [0.0]
    if progress:
        progress(Progress("toro", 0, cfg.iterations, e0))
    status = Status.MAX_ITERATIONS
    solve_time = 0.0
    first_bad = -1
    done = 0
    for it in range(1, cfg.iterations + 1):
        t0 = time.perf_counter()
        bad = state.sweep(float(it + 1), cycles)  # TORO.md: the counter k starts at 2
        solve_time += time.perf_counter() - t0
        done = it
        if bad >= 0 and first_bad < 0:
            first_bad = bad
        sum_cycles += float(cycles.sum())
        max_cycles = max(max_cycles, int(cycles.max(initial=0)))
        np.minimum(steady, cycles, out=steady)
        e = state.energy()
        history.append(e)
        times.append(solve_time)
        if progress:
            progress(Progress("toro", it, cfg.iterations, e))
        if not np.isfinite(e):
            raise SolverError(f"the energy became non-finite in iteration {it}")
        prev = history[-2]
        if cfg.energy_tolerance > 0 and prev > 0 and e <= prev and (
                (prev - e) / prev < cfg.energy_tolerance):
            status = Status.CONVERGED
            break
    freq = cycles_per_second()
    rot, trans = state.poses()
    lengths = tree.path_lengths()
    stats: dict[str, Any] = {
        "sweeps": done,
        "us_per_constraint_mean": sum_cycles / max(done * nc, 1) / freq * 1e6,
        "us_per_constraint_max": max_cycles / freq * 1e6,
        "us_per_constraint_max_steady": (float(steady.max()) / freq * 1e6
                                         if done and nc else 0.0),
        "skipped_updates_first": first_bad,
        "tree": cfg.tree,
        "weights": cfg.weights,
        "tree_max_depth": int(tree.depth.max()),
        "path_length_max": int(lengths.max(initial=0)),
        "path_length_mean": float(lengths.mean()) if nc else 0.0,
        "gamma_r": state.gamma_r,
        "gamma_t": state.gamma_t,
    }
    return SolveResult(
        rotations=rot, translations=trans, status=status, iterations=done,
        energy_history=np.asarray(history), times=np.asarray(times), method="toro",
        num_constraints=graph.num_constraints,
        timings={"compile": compile_s, "analyze": t_analyze, "solve": solve_time}, stats=stats,
    )
