"""A TORO-style baseline (Grisetti et al.'s tree-based network optimizer), written from its
published update rule (docs/mathematics.md#toro; TORO's own code was not read).

TORO relaxes one constraint at a time in a tree parametrization, like the hybrid solver, but
corrects rotation and translation *separately*: the rotational residual is spread over the path
as rotations about one global axis, then the translational residual (on the re-bent path) as
pure translations.  A translation error is never turned into a rotation, which is what produces
the "dog-leg" distortion the paper fixes (paper Fig. 2, Fig. 3e/f).

Summary of the rule (docs/mathematics.md#toro):

* **Tree** (``ToroConfig.tree``): ``"toro"`` (default, TORO's): each pose's parent is its
  smallest-id neighbour, from the smallest-id pose (:data:`hybridpgo.tree.TreeKind.TORO` says
  what happens where a pose has no smaller-id neighbour); ``"bfs"``: the hybrid solver's
  breadth-first tree.  Both are grown by :func:`hybridpgo.tree.build_tree`.  Initial guess:
  tree-edge measurements composed down from the root (``init="tree"``), or the file's vertices
  (``init="file"``).
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
from .._warmup import tiny_graph
from ..energy import energy
from ..errors import GraphError, SolverError
from ..graph import FloatArray, PoseGraph
from ..initialization import initial_locals
from ..tree import PoseTree, build_tree, global_poses
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
    ``k = s + 1`` in the gains (k starts at 2)."""
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


# ----------------------------------------------------------------------------- the solver state
@dataclass
class ToroState:
    """Mutable solver state: the tree, the preconditioned weights and the local transforms."""

    graph: PoseGraph
    tree: PoseTree
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
    def create(cls, graph: PoseGraph, tree: PoseTree, rot: FloatArray, trans: FloatArray,
               weights: str = "documented") -> ToroState:
        """Compute the preconditioner (once before the first sweep)."""
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
        inv_r = np.divide(1.0, m_rot, out=np.zeros(t_nodes), where=m_rot > 0)
        inv_t = np.divide(1.0, m_trans, out=np.zeros(t_nodes), where=m_trans > 0)
        w_rot, w_trans = (inv_r, inv_t) if weights == "documented" else (inv_t, inv_r)
        meas_trans = np.concatenate([graph.edge_translations, graph.gps_positions])
        return cls(graph=graph, tree=tree, rot=np.array(rot, np.float64, order="C"),
                   trans=np.array(trans, np.float64, order="C"), rho=rho, tau=tau,
                   gamma_r=gamma_r, gamma_t=gamma_t, m_rot=m_rot, m_trans=m_trans,
                   w_rot=w_rot, w_trans=w_trans, meas_trans=meas_trans)

    def problem(self) -> tuple[Any, ...]:
        """The read-only arrays the kernels take as ``prob`` (see ``_toro_kernels``)."""
        g, t = self.graph, self.tree
        return (g.num_edges, t.path_ptr, t.path_node, t.path_sign, t.constraint_root,
                g.edge_rotations,
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
        return global_poses(self.tree, self.rot, self.trans)

    def energy(self) -> float:
        return energy(self.graph, *self.poses())


# ----------------------------------------------------------------------------- timing
def ensure_compiled() -> float:
    """Compile (or load from Numba's cache) every kernel once; returns the seconds spent."""
    if getattr(tk.sweep, "signatures", None):
        return 0.0
    t0 = time.perf_counter()
    _solve(tiny_graph(gps=True), ToroConfig(iterations=1), None, compile_s=0.0)
    cycles_per_second()
    return time.perf_counter() - t0


# ----------------------------------------------------------------------------- the solver
def solve_toro(
    graph: PoseGraph, config: ToroConfig | None = None, progress: ProgressCallback | None = None
) -> SolveResult:
    """Optimize ``graph`` with the TORO-style baseline (module docstring, docs/mathematics.md#toro).

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
    compile_s = ensure_compiled()
    return _solve(graph, cfg, progress, compile_s)


def _solve(graph: PoseGraph, cfg: ToroConfig, progress: ProgressCallback | None,
           compile_s: float) -> SolveResult:
    t_start = time.perf_counter()
    tree = build_tree(graph, cfg.tree)
    rot0, trans0 = initial_locals(graph, tree, cfg.init)
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
        bad = state.sweep(float(it + 1), cycles)  # the counter k starts at 2
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
