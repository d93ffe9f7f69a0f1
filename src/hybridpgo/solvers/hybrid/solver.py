"""The hybrid solver object: built once, then run or stepped many times (paper Algorithm 1).

:class:`HybridSolver` grows the pose tree and the constraint paths (III-A), initializes the
local transforms, whitens the information and builds 𝔅(H) once; then :meth:`~HybridSolver.run`
performs sweeps with the temperature schedule (III-H) and :meth:`~HybridSolver.step` relaxes a
chosen list of constraints within a time budget (the online mode stands on it).
:func:`solve_hybrid` is the one-call form, with the optional exact polish.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt

from ..._cost import robust_kind
from ..._memory import mapped_zeros
from ..._numba import cycles_per_second, read_cycles
from ..._warmup import tiny_graph
from ...energy import energy, robust_energy
from ...errors import SolverError
from ...graph import FloatArray, PoseGraph
from ...initialization import initial_locals
from ...tree import LINK_EDGE, LINK_GPS, PoseTree, build_tree, global_poses
from ..config import HybridConfig, Progress, ProgressCallback
from ..result import SolveResult, Status
from . import _batch, _correction, _init_blocks, _linearize, _step, _sweep
from .problem import NUM_COUNTS, Count, Problem, State, StepKind, new_workspace

if TYPE_CHECKING:
    from ..gauss_newton import IterateCallback

#: Step names of :class:`HybridConfig` -> kernel codes.
STEP_KINDS = {"woodbury": StepKind.WOODBURY, "givens": StepKind.GIVENS}
_U64_MAX = np.iinfo(np.uint64).max


class StepReport(NamedTuple):
    """What :meth:`HybridSolver.step` did."""

    done: int
    """Constraints processed (fewer than asked when the budget ran out)."""
    capped: int
    """Updates whose rotation was capped at pi/8."""
    rejected: int
    """Updates rejected as non-finite (nothing applied)."""
    seconds: float
    """Wall time of the call."""


def _whitening(information: FloatArray, k: int) -> FloatArray:
    """``L^T`` (upper triangular) of every information matrix, ``Omega = L L^T``
    (docs/conventions.md).

    A diagonal matrix (most generated and many file informations) gets ``sqrt`` of its
    diagonal, which is what the Cholesky factorization computes for it; the others are
    factored by LAPACK (at 1M edges this saves about 3 s of batched Cholesky).
    """
    m = information.shape[0]
    if m == 0:
        return np.zeros((0, k, k))
    diag = information.reshape(m, k * k)[:, :: k + 1]
    if np.count_nonzero(information) != np.count_nonzero(diag) or not np.all(diag > 0.0):
        out = np.ascontiguousarray(np.swapaxes(np.linalg.cholesky(information), 1, 2))
        return out  # (not positive definite: LAPACK's error)
    lt = np.zeros((m, k, k))
    lt.reshape(m, k * k)[:, :: k + 1] = np.sqrt(diag)
    return lt


def _link_constraints(tree: PoseTree, num_edges: int) -> npt.NDArray[np.int64]:
    """The constraint index of every node's tree link (-1 for the root)."""
    out = np.full(tree.num_tree_nodes, -1, np.int64)
    edge = tree.link_kind == LINK_EDGE
    gps = tree.link_kind == LINK_GPS
    out[edge] = tree.link_index[edge]
    out[gps] = num_edges + tree.link_index[gps].astype(np.int64)
    return out


class HybridSolver:
    """The hybrid Hessian solver of one graph, analyzed once.

    Parameters
    ----------
    graph : PoseGraph
    config : HybridConfig, optional
    tree : PoseTree, optional
        A tree built earlier by :func:`hybridpgo.tree.build_tree` (else grown from
        ``config.tree``).
    locals0 : (rot (T,3,3), trans (T,3)), optional
        Initial local transforms (else from ``config.init``).
    """

    def __init__(self, graph: PoseGraph, config: HybridConfig | None = None, *,
                 tree: PoseTree | None = None,
                 locals0: tuple[FloatArray, FloatArray] | None = None) -> None:
        self.config = cfg = config or HybridConfig()
        self.compile_seconds = ensure_compiled(graph.num_gps > 0, bool(cfg.dmax),
                                               cfg.step == "givens")
        t0 = time.perf_counter()
        self.graph = graph
        self.tree = tree = tree if tree is not None else build_tree(graph, cfg.tree)
        rot0, trans0 = locals0 if locals0 is not None else initial_locals(graph, tree, cfg.init)
        self.problem = Problem(
            graph.num_edges, tree.path_ptr, tree.path_node, tree.path_sign,
            graph.edge_rotations, graph.edge_translations, _whitening(graph.edge_information, 6),
            graph.gps_positions, _whitening(graph.gps_information, 3),
            np.bincount(tree.path_node, minlength=tree.num_tree_nodes).astype(np.int64),
            tree.parent, _link_constraints(tree, graph.num_edges), tree.link_forward,
            robust_kind(cfg.kernel, cfg.robust_delta), float(cfg.robust_delta),
        )  # fmt: skip
        self.state = State(  # copies: the sweeps change them in place
            np.array(rot0, np.float64, order="C"), np.array(trans0, np.float64, order="C"),
            # 𝔅(H) and the constraints' blocks (GBs at 1M poses): on demand-zero pages without
            # huge pages, whose first write can stall in the kernel's compaction (_memory)
            mapped_zeros((tree.num_tree_nodes, 6, 6))[0],
            mapped_zeros((int(tree.path_ptr[-1]), 6, 6))[0],
        )
        lengths = tree.path_lengths()
        self.dmax = max(int(lengths.max()) if lengths.size else 1, 1)
        nc = tree.num_constraints
        self.scratch = _sweep.new_scratch(tree.num_tree_nodes, nc, self.dmax, cfg.dmax or 0,
                                          cfg.gps_batch_size)
        """Buffers of the relaxation loop, reused by every sweep and step."""
        compiled = self.compile_seconds
        self.rebuild_blocks()
        compiled = self.compile_seconds - compiled  # the first large graph's init kernel
        self._topology: _correction.Topology | None = None
        self.tau = cfg.tau0
        """The temperature of the next sweep."""
        self.sweeps_done = 0
        self.analyze_seconds = time.perf_counter() - t0 - compiled

    # ----------------------------------------------------------------- state
    @property
    def num_constraints(self) -> int:
        return self.tree.num_constraints

    def rebuild_blocks(self) -> None:
        """Recompute 𝔅(H) and all contributions from scratch at the current poses.

        With at least :data:`INIT_KERNEL_ENTRIES` path entries by their own kernel
        (:mod:`._init_blocks`), otherwise by the solve's sweep kernel with ``apply=False``
        (bit-identical blocks; nothing more to compile).
        """
        if self.problem.path_node.shape[0] >= INIT_KERNEL_ENTRIES:
            self.compile_seconds += _compile_init_kernel()
            _init_blocks.init_blocks(self.problem, self.state, self.dmax)
        else:
            _sweep.init_blocks(self.problem, self.state, self.scratch,
                               self.problem.gps_pos.shape[0] > 0, bool(self.config.dmax),
                               self.config.step == "givens")

    def poses(self) -> tuple[FloatArray, FloatArray]:
        """Global poses ``(R (N,3,3), t (N,3))`` of the current estimate."""
        return global_poses(self.tree, self.state.rot, self.state.trans)

    def energy(self) -> float:
        """E of the current estimate (E_rho with a robust kernel,
        docs/conventions.md#robust-kernels)."""
        return self.energies()[0]

    def energies(self) -> tuple[float, float]:
        """``(E_rho, E)`` of the current estimate (equal without a robust kernel)."""
        return self._energies_of(*self.poses())

    def _energies_of(self, rot: FloatArray, trans: FloatArray) -> tuple[float, float]:
        """:meth:`energies` at the global poses ``rot, trans`` (computed once by the caller)."""
        if self.problem.robust_kind == 0:
            e = energy(self.graph, rot, trans)
            return e, e
        return robust_energy(self.graph, rot, trans, self.config.kernel,
                             self.config.robust_delta)

    # ----------------------------------------------------------------- updates
    def _sweep(self, order: npt.NDArray[Any], tau: float, deadline: int,
               counts: npt.NDArray[np.int64]) -> int:
        """One relaxation loop over ``order``; returns the first rejected constraint or -1."""
        cfg = self.config
        counts[Count.FIRST_REJECTED] = 0
        _sweep.sweep(self.problem, self.state, self.scratch, order, tau, cfg.damping,
                     STEP_KINDS[cfg.step], cfg.gps_batch_size, cfg.dmax or 0,
                     np.uint64(deadline), counts)
        return int(counts[Count.FIRST_REJECTED]) - 1

    def step(self, constraints: npt.ArrayLike, budget_s: float | None = None,
             tau: float | None = None) -> StepReport:
        """Relax ``constraints`` in the given order (GPS readings batched, Algorithm 1).

        Parameters
        ----------
        constraints : array_like of int
            Constraint indices (relative edges ``0..M-1``, then GPS ``M..``).
        budget_s : float, optional
            Start no further constraint once this many seconds have passed (the update in
            progress finishes).  At least one constraint is always processed.
        tau : float, optional
            Temperature of these updates (default: the solver's current ``tau``).
        """
        t0 = time.perf_counter()
        order = self._checked(constraints).astype(np.int32)
        deadline = _U64_MAX
        if budget_s is not None:
            deadline = int(read_cycles()) + int(budget_s * cycles_per_second())
        counts = np.zeros(NUM_COUNTS, np.int64)
        self._sweep(order, self.tau if tau is None else tau, min(deadline, _U64_MAX), counts)
        return StepReport(int(counts[Count.DONE]), int(counts[Count.CAPPED]),
                          int(counts[Count.REJECTED]), time.perf_counter() - t0)

    def _checked(self, constraints: npt.ArrayLike, unique: bool = False) -> npt.NDArray[np.int64]:
        """Constraint indices as int64, each in range (and distinct when ``unique``): the kernels
        do not check bounds."""
        cs = np.ascontiguousarray(constraints, dtype=np.int64).reshape(-1)
        if cs.size and (cs.min() < 0 or cs.max() >= self.num_constraints):
            raise ValueError(f"constraint indices must lie in 0..{self.num_constraints - 1}")
        if unique and np.unique(cs).size != cs.size:
            raise ValueError("a batch may not list a constraint twice")
        return cs

    def batch_step(self, constraints: npt.ArrayLike, tau: float = 0.0,
                   damping: float | None = None) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """Hybrid step of a batch of constraints (paper eq. 35-37) over their domains' union.

        Returns ``(nodes, x)``: the union's tree nodes and their (6,) steps.  With ``tau > 0``
        the step is also applied (scaled by tau, capped at pi/8); 𝔅(H) is updated either way.
        ``damping`` overrides ``config.damping`` (0 with every constraint: the Gauss-Newton step).
        """
        cs = self._checked(constraints, unique=True)
        nt = self.tree.num_tree_nodes
        x = np.zeros((nt, 6))
        nodes = np.zeros(nt, np.int64)
        state = self.state
        if tau <= 0.0:  # compute only: apply to a scratch copy of the poses
            state = State(state.rot.copy(), state.trans.copy(), state.bdiag, state.contrib)
        slot = np.full(nt, -1, np.int64)
        mu = self.config.damping if damping is None else damping
        nu = _batch.batch_relax_exact(self.problem, state, cs, cs.shape[0], max(tau, 1e-300),
                                      mu, slot, x, nodes)
        if nu < 0:
            raise SolverError("the batch step was not finite")
        return nodes[:nu].copy(), x[:nu].copy()

    def probe(self, c: int, step: str | None = None
              ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Linearize constraint c and update 𝔅(H) as a sweep would; return its step unapplied.

        Returns ``(jac (d,6,6), r (6,), x (d,6))``: whitened Jacobian blocks, residual, step.
        """
        c = int(self._checked([c])[0])
        d = int(self.tree.path_ptr[c + 1] - self.tree.path_ptr[c])
        wk = new_workspace(max(d, 1))
        kr, _na = _linearize.linearize(self.problem, c, self.state.rot, self.state.trans, wk,
                                       wk.jac)
        _step.accumulate_blocks(self.problem, self.state, c, kr, wk.jac, self.config.damping,
                                wk.lfac, wk.bc)
        _step.solve_single(d, kr, STEP_KINDS[step or self.config.step], wk)
        return wk.jac[:d].copy(), wk.r.copy(), wk.x[:d].copy()

    @property
    def topology(self) -> _correction.Topology:
        """Tree arrays of :meth:`correct` (built on first use: most runs never correct)."""
        if self._topology is None:
            self._topology = _correction.topology(self.graph, self.tree)
        return self._topology

    def correct(self, iterations: int | None = None,
                energy_before: float | None = None) -> _correction.Report:
        """One global correction (:mod:`._correction`): a truncated Gauss-Newton step by
        ``iterations`` (default ``config.correction_iterations``) CG iterations preconditioned
        by 𝔅(H), taken only if it lowers the energy.  The sweeps' 𝔅(H) is left as it was (each
        constraint's contribution is refreshed when it is next relaxed, eq. 24)."""
        cfg = self.config
        return _correction.correct(
            self.problem, self.state, self.topology,
            cfg.correction_iterations if iterations is None else iterations, cfg.damping,
            self.energy, energy_before)

    # ----------------------------------------------------------------- sweeps
    def run(self, sweeps: int | None = None,
            progress: ProgressCallback | None = None,
            iterate: IterateCallback | None = None) -> SolveResult:
        """Run sweeps (default: ``config.sweeps``) from the current state, no polish.

        Stops early when ``config.energy_tolerance`` is met.  The temperature continues from
        earlier calls.  ``stats`` holds per-constraint update times and step counts.
        ``iterate(Progress, rotations, translations)``, if given, receives the global poses
        wherever ``progress`` is called.
        """
        cfg = self.config
        n_sweeps = cfg.sweeps if sweeps is None else sweeps
        tree = self.tree
        nc = tree.num_constraints
        freq = cycles_per_second()
        steady = np.full(nc, _U64_MAX, np.uint64)
        batch_steady = np.full(nc, _U64_MAX, np.uint64)
        counts = np.zeros(NUM_COUNTS, np.int64)
        sum_cycles = 0.0
        p999 = 0.0
        # once per evaluation: the energies and the result share them
        poses: tuple[FloatArray, FloatArray] | None
        poses = self.poses()
        e0, e0_plain = self._energies_of(*poses)
        history = [e0]
        plain = [e0_plain] if self.problem.robust_kind else []
        times = [0.0]
        if progress:
            progress(Progress("sweeps", 0, n_sweeps, history[0], self.tau))
        if iterate:
            iterate(Progress("sweeps", 0, n_sweeps, history[0], self.tau), *poses)
        status = Status.MAX_ITERATIONS
        solve_time = 0.0
        first_bad = -1
        done = 0
        corrections: list[float] = []
        undone = 0
        for k in range(n_sweeps):
            poses = None  # not kept through the sweep (96 MB at 1M poses)
            t0 = time.perf_counter()
            saved = (self.state.rot.copy(), self.state.trans.copy()) if cfg.monotone else None
            bad = self._sweep(tree.sweep_order, self.tau, _U64_MAX, counts)
            if cfg.correction != "none":
                e_swept = None
                if saved is not None:
                    e_swept = self.energy()
                    if e_swept > history[-1]:  # undo a sweep that raised E (config.monotone)
                        self.state.rot[:], self.state.trans[:] = saved
                        e_swept = history[-1]
                        undone += 1
                corrections.append(self.correct(energy_before=e_swept).scale)
            solve_time += time.perf_counter() - t0
            done += 1
            self.sweeps_done += 1
            if bad >= 0 and first_bad < 0:
                first_bad = bad
            sum_cycles += float(self.scratch.cycles.sum())
            np.minimum(steady, self.scratch.cycles, out=steady)
            np.minimum(batch_steady, self.scratch.batch_cycles, out=batch_steady)
            if nc:
                p999 = max(p999, float(np.quantile(self.scratch.cycles, 0.999)))
            poses = self.poses()
            e, e_plain = self._energies_of(*poses)
            history.append(e)
            plain += [e_plain] if plain else []
            times.append(solve_time)
            self.tau *= cfg.tau_decay
            if progress:
                progress(Progress("sweeps", k + 1, n_sweeps, e, self.tau))
            if iterate:
                iterate(Progress("sweeps", k + 1, n_sweeps, e, self.tau), *poses)
            if not np.isfinite(e):
                raise SolverError(f"the energy became non-finite in sweep {k + 1}")
            if (cfg.energy_tolerance > 0 and history[-2] > 0
                    and (history[-2] - e) / history[-2] < cfg.energy_tolerance
                    and e <= history[-2]):
                status = Status.CONVERGED
                break
        if nc and counts[Count.REJECTED] >= nc * max(done, 1):
            raise SolverError(f"every update was non-finite (first: constraint {first_bad})")
        rot, trans = poses if poses is not None else self.poses()  # the last evaluation's
        if iterate:  # the callback saw these arrays: the result gets its own
            rot, trans = rot.copy(), trans.copy()
        n_updates = max(done * nc, 1)
        finite_batches = batch_steady[batch_steady < _U64_MAX]
        stats: dict[str, Any] = {
            "sweeps": done,
            "final_tau": self.tau,
            "us_per_constraint_mean": sum_cycles / n_updates / freq * 1e6,
            "us_per_constraint_max": float(counts[Count.MAX_CYCLES]) / freq * 1e6,
            "us_per_constraint_p999": p999 / freq * 1e6,
            "us_per_constraint_max_steady": (
                float(steady.max()) / freq * 1e6 if done and nc else 0.0),
            "gps_batches": int(counts[Count.BATCHES]),
            "ms_per_gps_batch_max_steady": float(finite_batches.max(initial=0)) / freq * 1e3,
            "capped_steps": int(counts[Count.CAPPED]),
            "rejected_steps": int(counts[Count.REJECTED]),
            "first_rejected_constraint": first_bad,
            "tree_max_depth": tree.max_depth,
            "path_length_max": int(tree.path_lengths().max()) if nc else 0,
            "path_length_mean": float(tree.path_lengths().mean()) if nc else 0.0,
            "step": cfg.step,
        }
        if cfg.correction != "none":
            stats.update(correction=cfg.correction, correction_scales=corrections,
                         sweeps_undone=undone)
        if plain:
            stats.update(robust=cfg.robust, robust_scale=cfg.robust_delta,
                         plain_energy=plain[-1], plain_energy_history=plain)
        return SolveResult(
            rotations=rot, translations=trans, status=status, iterations=done,
            energy_history=np.asarray(history), times=np.asarray(times), method="hybrid",
            num_constraints=self.graph.num_constraints,
            timings={"compile": self.compile_seconds, "analyze": self.analyze_seconds,
                     "solve": solve_time},
            stats=stats,
        )


def solve_hybrid(graph: PoseGraph, config: HybridConfig | None = None, *,
                 tree: PoseTree | None = None, progress: ProgressCallback | None = None,
                 locals0: tuple[FloatArray, FloatArray] | None = None,
                 iterate: IterateCallback | None = None) -> SolveResult:
    """Optimize ``graph`` with the hybrid Hessian method (sweeps, then the optional polish).

    Parameters
    ----------
    graph : PoseGraph
    config : HybridConfig, optional
    tree : PoseTree, optional
        A tree built earlier by :func:`hybridpgo.tree.build_tree` (analyze once, solve many).
    progress : callable, optional
        ``progress(Progress)`` after every sweep and polish iteration.
    locals0 : (rot, trans), optional
        Initial local transforms of the tree nodes (else from ``config.init``).
    iterate : callable, optional
        ``iterate(Progress, rotations, translations)``: the global poses at the same points
        as ``progress`` (phase ``"sweeps"``, then ``"polish"``).

    Raises
    ------
    SolverError
        When every update of a sweep was rejected as non-finite.
    """
    cfg = config or HybridConfig()
    if cfg.robust == "auto":  # least squares, then the outlier test (solvers/robust.py)
        from ..robust import solve_hybrid_auto

        return solve_hybrid_auto(graph, cfg, tree=tree, progress=progress, locals0=locals0,
                                 iterate=iterate)
    result = HybridSolver(graph, cfg, tree=tree, locals0=locals0).run(progress=progress,
                                                                       iterate=iterate)
    if not cfg.polish:
        return result
    from ..config import GaussNewtonConfig
    from ..gauss_newton import solve_exact

    t0 = time.perf_counter()
    polished = solve_exact(graph, result.rotations, result.translations,
                           GaussNewtonConfig(method="lm", max_iterations=cfg.polish_iterations,
                                             robust=cfg.robust, robust_scale=cfg.robust_scale),
                           progress=None if progress is None else
                           (lambda p: progress(p._replace(phase="polish"))),
                           iterate=None if iterate is None else
                           (lambda p, r, t: iterate(p._replace(phase="polish"), r, t)))
    offset = result.times[-1]
    stats = dict(result.stats, polish_iterations=polished.iterations,
                 polish_status=polished.status.value)
    if "plain_energy_history" in stats:
        stats.update(plain_energy=polished.stats["plain_energy"], plain_energy_history=(
            stats["plain_energy_history"] + polished.stats["plain_energy_history"][1:]))
    return dataclasses.replace(
        result, rotations=polished.rotations, translations=polished.translations,
        status=polished.status, method="hybrid+polish",
        energy_history=np.concatenate([result.energy_history, polished.energy_history[1:]]),
        times=np.concatenate([result.times, offset + np.asarray(polished.times[1:])]),
        timings=dict(result.timings, polish=time.perf_counter() - t0), stats=stats,
    )


#: The sweep variants ``(gps, interpolate, givens)`` compiled (or loaded) in this process.
_COMPILED: set[tuple[bool, bool, bool]] = set()

#: 𝔅(H) is built by its own kernel (:mod:`._init_blocks`: no damped factorization per node, no
#: solve; 1M-pose city: 2.8 s of CPU against 5.0 s by the sweep kernel with ``apply=False``) on
#: problems with at least this many constraint-path entries.  Below, the solve's sweep kernel
#: builds it: the own kernel costs as much compilation as a sweep variant (~10 s of CPU on a
#: cold cache), more than it saves there.
INIT_KERNEL_ENTRIES = 1_000_000
_INIT_COMPILED: list[bool] = []


def _compile_init_kernel() -> float:
    """Compile (or load) :func:`._init_blocks.init_blocks`; the seconds spent (0 once done)."""
    if _INIT_COMPILED:
        return 0.0
    _INIT_COMPILED.append(True)  # first: the tiny solver below builds its blocks too
    t0 = time.perf_counter()
    eye = np.tile(np.eye(3), (2, 1, 1))
    tiny = PoseGraph(
        node_ids=np.arange(2), rotations=eye, translations=np.zeros((2, 3)),
        edge_nodes=np.array([[0, 1]], np.int32), edge_rotations=eye[:1],
        edge_translations=np.ones((1, 3)), edge_information=np.eye(6)[None],
    )
    try:
        solver = HybridSolver(tiny, HybridConfig(sweeps=1, init="tree"))
        _init_blocks.init_blocks(solver.problem, solver.state, solver.dmax)
    except BaseException:
        _INIT_COMPILED.clear()
        raise
    return time.perf_counter() - t0


def ensure_compiled(gps: bool = False, interpolate: bool = False,
                    givens: bool = False) -> float:
    """Compile (or load from Numba's cache) the kernels a solve uses; returns the seconds spent.

    Runs a three-pose graph once per process and variant, so a caller's ``analyze`` and
    ``solve`` times are not inflated by compilation (docs/contributing.md#solver-api).  Only what
    is asked is
    compiled: the sweep variant of ``(gps, interpolate, givens)`` (which also builds 𝔅(H)
    below :data:`INIT_KERNEL_ENTRIES`); the GPS batches (III-G) with ``gps``, interpolated
    solving (III-E) with ``interpolate``, the Givens solve instead of Woodbury's with
    ``givens`` -- each about as long to compile as the plain solver, so a graph without GPS
    never waits for them.
    """
    wanted = {(bool(gps), bool(interpolate), bool(givens))}
    todo = sorted(wanted - _COMPILED)
    if not todo:
        return 0.0
    _COMPILED.update(todo)  # first: the tiny solves below construct solvers too
    t0 = time.perf_counter()
    try:
        for with_gps, with_interp, with_givens in todo:
            HybridSolver(tiny_graph(gps=with_gps),
                         HybridConfig(sweeps=1, init="tree", dmax=2 if with_interp else None,
                                      step="givens" if with_givens else "woodbury")).run()
    except BaseException:
        _COMPILED.difference_update(todo)
        raise
    return time.perf_counter() - t0
