"""The hybrid Hessian solver (paper Algorithm 1; DESIGN.md §2-§4).

``solve_hybrid`` grows the pose tree, initializes the local transforms, builds 𝔅(H) and then
runs sweeps of per-constraint stochastic updates, entirely in compiled code, with the paper's
temperature schedule.  An optional exact polish finishes at the nearest optimum.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from .._numba import cycle_counter, kernel
from ..energy import energy
from ..errors import SolverError
from ..graph import FloatArray, PoseGraph
from ..tree import InitKind, PoseTree, TreeKind, build_tree, global_poses, initial_locals
from . import _hybrid_kernels as _hk
from .result import SolveResult, Status

# Numba dispatchers carry no useful static types; the kernels are called through an untyped
# alias so that mypy checks the Python around them, not the tuples passed in.
hk: Any = _hk

STEP_KINDS = {"woodbury": hk.STEP_WOODBURY, "givens": hk.STEP_GIVENS}

ProgressFn = Callable[[int, float, float], None]
"""``progress(sweep, energy, tau)``, called after every sweep (sweep 0 = initial state)."""


@dataclass(frozen=True)
class HybridConfig:
    """Options of the hybrid solver; every field is checked in ``__post_init__``."""

    sweeps: int = 10
    """Maximum number of sweeps over all constraints (the paper's experiments use 10)."""
    tau0: float = 1.0
    """Initial temperature tau (paper III-H)."""
    tau_decay: float = 0.99
    """tau is multiplied by this after each sweep (paper III-H)."""
    damping: float = 1e-6
    """mu: each block of B_c gets mu * trace(B)/6 added to its diagonal (DESIGN §4)."""
    step: str = "woodbury"
    """'woodbury' (O(d), default) or 'givens' (the paper's O(d^2) triangularization)."""
    tree: str = "bfs"
    """'bfs' (paper) or 'mst' (maximum-stiffness spanning tree)."""
    init: str = "tree"
    """'tree' (concatenate tree-edge measurements, paper) or 'file' (the file's vertices)."""
    energy_tolerance: float = 0.0
    """Stop when a sweep lowers the energy by less than this fraction (0: run all sweeps)."""
    gps_batch_size: int = 40
    """GPS constraints are relaxed together in batches of this size (paper: 30-50)."""
    polish: bool = False
    """Finish with the exact Levenberg-Marquardt solver."""
    polish_iterations: int = 100
    """Iteration limit of the polish."""

    def __post_init__(self) -> None:
        if not (isinstance(self.sweeps, int) and self.sweeps >= 0):
            raise ValueError(f"sweeps must be a non-negative integer, got {self.sweeps!r}")
        if not (self.tau0 > 0 and np.isfinite(self.tau0)):
            raise ValueError(f"tau0 must be positive, got {self.tau0!r}")
        if not (0 < self.tau_decay <= 1):
            raise ValueError(f"tau_decay must be in (0, 1], got {self.tau_decay!r}")
        if not (self.damping >= 0 and np.isfinite(self.damping)):
            raise ValueError(f"damping must be >= 0, got {self.damping!r}")
        if self.step not in STEP_KINDS:
            raise ValueError(f"step must be one of {sorted(STEP_KINDS)}, got {self.step!r}")
        TreeKind(self.tree)
        InitKind(self.init)
        if not (isinstance(self.gps_batch_size, int) and self.gps_batch_size >= 1):
            raise ValueError(
                f"gps_batch_size must be a positive integer, got {self.gps_batch_size!r}"
            )
        if not (self.energy_tolerance >= 0):
            raise ValueError("energy_tolerance must be >= 0")
        if not (isinstance(self.polish_iterations, int) and self.polish_iterations >= 0):
            raise ValueError("polish_iterations must be a non-negative integer")


@kernel
def _read_cycles() -> int:
    return cycle_counter()  # type: ignore[no-any-return]


@functools.cache
def cycles_per_second() -> float:
    """Frequency of the cycle counter, calibrated once against ``time.perf_counter``."""
    _read_cycles()
    c0, t0 = _read_cycles(), time.perf_counter()
    time.sleep(0.05)
    c1, t1 = _read_cycles(), time.perf_counter()
    return float(c1 - c0) / (t1 - t0)


def _ensure_compiled() -> float:
    """Compile (or load from Numba's cache) every kernel a solve uses; returns the seconds spent.

    Runs a three-pose graph with a GPS reading once per process, so a caller's ``analyze`` and
    ``solve`` times are not inflated by compilation (STYLE.md §6).
    """
    if getattr(hk.sweep, "signatures", None) and getattr(hk.init_blocks, "signatures", None):
        return 0.0
    t0 = time.perf_counter()
    eye = np.tile(np.eye(3), (3, 1, 1))
    tiny = PoseGraph(
        node_ids=np.arange(3),
        rotations=eye,
        translations=np.eye(3),
        edge_nodes=np.array([[0, 1], [1, 2], [0, 2]], np.int32),
        edge_rotations=eye,
        edge_translations=np.ones((3, 3)),
        edge_information=np.tile(np.eye(6), (3, 1, 1)),
        gps_nodes=np.array([2], np.int32),
        gps_positions=np.ones((1, 3)),
        gps_information=np.eye(3)[None],
    )
    for g in (
        tiny,
        dataclasses.replace(
            tiny,
            gps_nodes=np.zeros(0, np.int32),
            gps_positions=np.zeros((0, 3)),
            gps_information=np.zeros((0, 3, 3)),
        ),
    ):
        _solve(g, HybridConfig(sweeps=1, init="tree"), None, None, None, compile_s=0.0)
    return time.perf_counter() - t0


@dataclass
class HybridState:
    """Mutable solver state (struct-of-arrays) shared by the sweep kernels."""

    graph: PoseGraph
    tree: PoseTree
    rot: FloatArray
    trans: FloatArray
    edge_lt: FloatArray
    gps_lt: FloatArray
    bdiag: FloatArray
    contrib: FloatArray
    dmax: int
    path_count: npt.NDArray[np.int64]
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def create(
        cls, graph: PoseGraph, tree: PoseTree, rot: FloatArray, trans: FloatArray
    ) -> HybridState:
        # Omega = L L^T; the whitened error is L^T e (DESIGN §1)
        edge_lt = np.ascontiguousarray(
            np.swapaxes(np.linalg.cholesky(graph.edge_information), 1, 2)
        )
        if graph.num_gps:
            gps_lt = np.ascontiguousarray(
                np.swapaxes(np.linalg.cholesky(graph.gps_information), 1, 2)
            )
        else:
            gps_lt = np.zeros((0, 3, 3))
        lengths = tree.path_lengths()
        dmax = max(int(lengths.max()) if lengths.size else 1, 1)
        state = cls(
            graph=graph,
            tree=tree,
            rot=np.ascontiguousarray(rot, np.float64),
            trans=np.ascontiguousarray(trans, np.float64),
            edge_lt=edge_lt,
            gps_lt=gps_lt,
            bdiag=np.zeros((tree.num_tree_nodes, 6, 6)),
            contrib=np.zeros((int(tree.path_ptr[-1]), 6, 6)),
            dmax=dmax,
            path_count=np.bincount(tree.path_node, minlength=tree.num_tree_nodes).astype(np.int64),
        )
        state.rebuild_blocks()
        return state

    def problem(self) -> tuple[Any, ...]:
        """The read-only arrays every kernel takes as ``prob`` (see ``_hybrid_kernels``)."""
        g, t = self.graph, self.tree
        return (
            g.num_edges, t.path_ptr, t.path_node, t.path_sign, g.edge_rotations,
            g.edge_translations, self.edge_lt, g.gps_positions, self.gps_lt, self.path_count,
            t.parent,
        )  # fmt: skip

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The mutable state every kernel takes as ``state``: locals, 𝔅(H), contributions."""
        return self.rot, self.trans, self.bdiag, self.contrib

    def rebuild_blocks(self) -> None:
        """Recompute 𝔅(H) and all contributions from scratch at the current poses."""
        hk.init_blocks(self.problem(), self.arrays(), self.dmax)

    def batch_step(
        self, constraints: npt.ArrayLike, damping: float = 1e-6, tau: float = 0.0
    ) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """Hybrid step of a batch of constraints (paper eq. 35-37) over their domains' union.

        Returns ``(nodes, x)``: the union's tree nodes and their (6,) steps.  With ``tau > 0``
        the step is also applied (scaled by tau, capped at pi/8) and 𝔅(H) updated.
        """
        cs = np.ascontiguousarray(constraints, dtype=np.int64)
        nt = self.tree.num_tree_nodes
        x = np.zeros((nt, 6))
        nodes = np.zeros(nt, np.int64)
        nu = hk.batch_step(cs, damping, self.problem(), self.arrays(), tau, x, nodes)
        if nu < 0:
            raise SolverError("the batch step was not finite")
        return nodes[:nu].copy(), x[:nu].copy()

    def sweep(self, tau: float, damping: float, step_kind: int, gps_batch_size: int,
              cycles: npt.NDArray[np.uint64], batch_cycles: npt.NDArray[np.uint64],
              counts: npt.NDArray[np.int64]) -> int:
        """One pass of Algorithm 1 over the constraints in tree order (see ``hk.sweep``).

        Returns the first constraint whose step was rejected as non-finite, or -1.
        """
        return int(hk.sweep(self.tree.sweep_order, tau, damping, step_kind, gps_batch_size,
                            self.problem(), self.arrays(), self.dmax, cycles, batch_cycles,
                            counts))

    def poses(self) -> tuple[FloatArray, FloatArray]:
        return global_poses(self.tree, self.rot, self.trans)

    def energy(self) -> float:
        r, t = self.poses()
        return energy(self.graph, r, t)


def solve_hybrid(
    graph: PoseGraph,
    config: HybridConfig | None = None,
    *,
    tree: PoseTree | None = None,
    progress: ProgressFn | None = None,
    initial_locals_override: tuple[FloatArray, FloatArray] | None = None,
) -> SolveResult:
    """Optimize ``graph`` with the hybrid Hessian method.

    Parameters
    ----------
    graph : PoseGraph
    config : HybridConfig, optional
    tree : PoseTree, optional
        A tree built earlier by :func:`hybridpgo.tree.build_tree` (analyze once, solve many).
    progress : callable, optional
        ``progress(sweep, energy, tau)`` after every sweep.

    Returns
    -------
    SolveResult
        ``stats`` holds per-constraint update times (``us_per_constraint_mean``,
        ``us_per_constraint_max``), capped and rejected step counts, and tree statistics.

    Raises
    ------
    SolverError
        When every update of a sweep was rejected as non-finite.
    """
    cfg = config or HybridConfig()
    compile_s = _ensure_compiled()
    return _solve(graph, cfg, tree, progress, initial_locals_override, compile_s)


def _solve(
    graph: PoseGraph,
    cfg: HybridConfig,
    tree: PoseTree | None,
    progress: ProgressFn | None,
    initial_locals_override: tuple[FloatArray, FloatArray] | None,
    compile_s: float,
) -> SolveResult:
    t_start = time.perf_counter()
    if tree is None:
        tree = build_tree(graph, cfg.tree)
    if initial_locals_override is not None:
        rot0, trans0 = initial_locals_override
    else:
        rot0, trans0 = initial_locals(graph, tree, cfg.init)
    state = HybridState.create(graph, tree, rot0, trans0)
    t_analyze = time.perf_counter() - t_start

    freq = cycles_per_second()
    step_kind = STEP_KINDS[cfg.step]
    nc = tree.num_constraints
    cycles = np.zeros(nc, np.uint64)
    batch_cycles = np.zeros(nc, np.uint64)
    batch_steady = np.full(nc, np.iinfo(np.uint64).max, np.uint64)
    counts = np.zeros(4, np.int64)
    sum_cycles = 0.0
    # per constraint, its cheapest update over the sweeps: the cost of the update itself, free of
    # the scheduler's interruptions that inflate single measurements on a busy machine
    steady = np.full(nc, np.iinfo(np.uint64).max, np.uint64)
    p999 = 0.0
    e0 = state.energy()
    history = [e0]
    times = [0.0]
    if progress:
        progress(0, e0, cfg.tau0)
    tau = cfg.tau0
    status = Status.MAX_ITERATIONS
    solve_time = 0.0
    first_bad = -1
    sweeps_done = 0
    for k in range(cfg.sweeps):
        t0 = time.perf_counter()
        bad = state.sweep(tau, cfg.damping, step_kind, cfg.gps_batch_size, cycles, batch_cycles,
                          counts)
        solve_time += time.perf_counter() - t0
        sweeps_done += 1
        if bad >= 0 and first_bad < 0:
            first_bad = int(bad)
        sum_cycles += float(cycles.sum())
        np.minimum(steady, cycles, out=steady)
        np.minimum(batch_steady, batch_cycles, out=batch_steady)
        if nc:
            p999 = max(p999, float(np.quantile(cycles, 0.999)))
        e = state.energy()
        history.append(e)
        times.append(solve_time)
        tau *= cfg.tau_decay
        if progress:
            progress(k + 1, e, tau)
        if not np.isfinite(e):
            raise SolverError(f"the energy became non-finite in sweep {k + 1}")
        if (
            cfg.energy_tolerance > 0
            and history[-2] > 0
            and (history[-2] - e) / history[-2] < cfg.energy_tolerance
            and e <= history[-2]
        ):
            status = Status.CONVERGED
            break
    if nc and counts[1] >= nc * max(sweeps_done, 1):
        raise SolverError(f"every update was non-finite (first: constraint {first_bad})")
    rot, trans = state.poses()
    timings = {"compile": compile_s, "analyze": t_analyze, "solve": solve_time}
    n_updates = max(sweeps_done * nc, 1)
    stats: dict[str, Any] = {
        "sweeps": sweeps_done,
        "final_tau": tau,
        "us_per_constraint_mean": sum_cycles / n_updates / freq * 1e6,
        "us_per_constraint_max": float(counts[2]) / freq * 1e6,
        "us_per_constraint_p999": p999 / freq * 1e6,
        "us_per_constraint_max_steady": (
            float(steady.max()) / freq * 1e6 if sweeps_done and nc else 0.0
        ),
        "gps_batches": int(counts[3]),
        "ms_per_gps_batch_max_steady": (
            float(batch_steady[batch_steady < np.iinfo(np.uint64).max].max(initial=0)) / freq * 1e3
        ),
        "capped_steps": int(counts[0]),
        "rejected_steps": int(counts[1]),
        "first_rejected_constraint": first_bad,
        "tree_max_depth": tree.max_depth,
        "path_length_max": int(tree.path_lengths().max()) if nc else 0,
        "path_length_mean": float(tree.path_lengths().mean()) if nc else 0.0,
        "step": cfg.step,
    }
    method = "hybrid"
    if cfg.polish:
        from .config import GaussNewtonConfig
        from .gauss_newton import solve_exact

        t0 = time.perf_counter()
        polished = solve_exact(
            graph, rot, trans, GaussNewtonConfig(method="lm", max_iterations=cfg.polish_iterations)
        )
        timings["polish"] = time.perf_counter() - t0
        rot, trans = polished.rotations, polished.translations
        offset = times[-1]
        history.extend(polished.energy_history[1:].tolist())
        times.extend((offset + np.asarray(polished.times[1:])).tolist())
        stats["polish_iterations"] = polished.iterations
        stats["polish_status"] = polished.status.value
        status = polished.status
        method = "hybrid+polish"
    return SolveResult(
        rotations=rot,
        translations=trans,
        status=status,
        iterations=sweeps_done,
        energy_history=np.asarray(history),
        times=np.asarray(times),
        method=method,
        num_constraints=graph.num_constraints,
        timings=timings,
        stats=stats,
    )
