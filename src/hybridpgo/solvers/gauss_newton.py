"""The exact solver: sparse Gauss-Newton / Levenberg-Marquardt, analyzed once.

:class:`ExactSolver` holds everything about a graph that does not depend on the poses: the
gauge, the sparsity pattern of the normal equations, the fill-reducing ordering and the
symbolic factorization (:mod:`._normal`).  :meth:`ExactSolver.solve` then runs LM (or GN) from
any start as often as asked, each time only assembling and factoring numerically; the default
pipeline polishes every start with one such object, and :mod:`hybridpgo.covariance` factors H
at a solution with it (:meth:`ExactSolver.factor`).  :func:`solve_exact` is the one-call form.

Linear algebra (:mod:`hybridpgo.linalg`): the variables are permuted by a fill-reducing ordering
of the 6x6 *block* graph (AMD, 36x smaller than H); then CHOLMOD through cvxopt (supernodal,
symbolic analysis once, numeric factorization each iteration) or, with
``linear_solver="splu"``, SciPy's SuperLU in symmetric mode with diagonal pivots.  With
``"auto"``, a 3D system whose factor stays sparse (city-like graphs: few loop closures) is
factored by the block Cholesky of :mod:`hybridpgo.linalg._block_cholesky` instead
(:data:`BLOCK_MAX_FILL`): faster there, and the only backend that keeps a 1M-pose polish
within 4 GB.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import _cost
from ..errors import SolverError
from ..graph import FloatArray, PoseGraph
from ..linalg import BlockCholesky, NotPositiveDefinite, cholmod_available, make_factorizer
from . import _gn_kernels as _k
from ._normal import (
    ALL_DOFS,
    Pattern,
    System,
    analyze,
    assemble,
    check_gauge,
    energies_at,
    full_system,
    initial_poses,
    is_planar,
    planar_system,
)
from ._normal import NormalEquations as NormalEquations
from ._normal import default_fixed_nodes as default_fixed_nodes
from ._normal import ensure_compiled as ensure_compiled
from ._normal import gn_step as gn_step
from ._normal import normal_equations as normal_equations
from .config import GaussNewtonConfig, Progress, ProgressCallback
from .result import SolveResult, Status

#: ``iterate(Progress, rotations, translations)``: the current global poses after every
#: iteration, right after the progress callback (for recorders such as ``optimize --rerun``;
#: the arrays may be the solver's own: copy what you keep, never modify them).
IterateCallback = Callable[[Progress, FloatArray, FloatArray], None]

__all__ = ["ExactSolver", "IterateCallback", "NormalEquations", "default_fixed_nodes",
           "ensure_compiled", "gn_step", "normal_equations", "solve_exact"]

#: LM: after an accepted step mu is multiplied by max(MAX_DECREASE, 1 - (2 rho - 1)^3)
#: (Nielsen's rule with GTSAM's factor 10 in place of Nielsen's 3).  Measured with
#: initial_damping 1e-8, iterations to convergence: bound 1/3: sphere2500 8, M3500 8, garage 8,
#: intel 4, M3500_isam 5; bound 1/10: 8, 5, 6, 4, 5.
MAX_DECREASE = 0.1
#: LM gives up (STALLED) when the damping factor mu exceeds this: no step lowers the energy.
MAX_DAMPING = 1e16
#: LM damping matrix: diag(H) clipped below at this fraction of its largest entry, so that the
#: damped system stays SPD where a direction carries (almost) no information.
DIAG_FLOOR = 1e-12
#: ``linear_solver="auto"``: the block Cholesky when its factor has at most this many 6x6 blocks
#: per block column (diagonal included); else CHOLMOD, whose BLAS supernodes win on high fill.
#: Measured (factor + solve): 100k-pose city 2-3 blocks per column, block 0.37 s vs CHOLMOD
#: 1.08 s; sphere2500 17, block 0.27 s vs CHOLMOD 0.18 s.
BLOCK_MAX_FILL = 6
#: An accepted step ends the solve early (converged) when E falls superlinearly: its decrease
#: is at most this fraction of the one before, and that fraction is no larger than the step
#: before's (``_Convergence``).  That saves the step that would only confirm convergence,
#: measured at the default tolerances: intel, M3500_isam and M3500_toro converge in 3
#: iterations instead of 4, garage in 5 instead of 6; sphere2500 and torus3D, whose fractions
#: rise again near the end, take 5 either way.
SUPERLINEAR_RATE = 0.01
#: ... and the geometric tail at that fraction is this many times below the tolerance: a
#: fraction can rise again where the fall turns linear (sphere2500_isam: 5e-5, then 4e-4;
#: the tail at 5e-5 was 7.5x below what remained, which a margin of 1 left 1.2e-10 of E above
#: the optimum at the tolerance 1e-10).
SUPERLINEAR_MARGIN = 10.0


@dataclass
class _Backend:
    """One factorization of the analyzed pattern: the system it factors (all of H, or its
    planar rows and columns), the factorizer with its symbolic analysis, and the buffers the
    assembly writes into.

    Memory (per stored entry of the lower triangle of H, "nnz"; 1M-pose city: 57 M): the values
    are assembled straight into the factorizer's own buffer (CHOLMOD: the cvxopt matrix it
    copies into the factored matrix), damped in place on the diagonal and restored; no other
    copy of H exists (the planar system is assembled as such: a quarter of the entries).
    The row indices live only in CHOLMOD's matrix after the analysis.
    """

    system: System
    solver: Any
    data: FloatArray
    """Values of the lower triangle of the system (the factorizer's buffer where it has one):
    the assembly writes them in place."""

    @classmethod
    def create(cls, pat: Pattern, planar: bool, linear_solver: str, allow_block: bool
               ) -> _Backend:
        solver: Any = None
        if not planar and allow_block and linear_solver == "auto":
            block = BlockCholesky(pat.num_vars, pat.block_ptr, pat.block_row, pat.indptr)
            if not cholmod_available() or block.factor_blocks <= BLOCK_MAX_FILL * max(
                    pat.num_vars, 1):
                solver = block
        if solver is not None:  # the block factorization reads the values in place
            system = System(pat.indptr, np.zeros(0, np.int64), None, ALL_DOFS, pat.dim)
        else:
            system = planar_system(pat) if planar else full_system(pat)
            # the certificate's Newton system has this pattern (shared_patterns)
            solver = make_factorizer(system, linear_solver, share=True)
        if solver.name == "cholmod":  # CHOLMOD holds the pattern: drop our copy of the rows
            system = dataclasses.replace(system, indices=np.zeros(0, np.int64))
        buffer = solver.values_buffer()
        data = buffer if buffer is not None else np.empty(system.nnz)
        return cls(system, solver, data)


class ExactSolver:
    """The exact sparse GN/LM solver of one graph, analyzed once (module docstring).

    Parameters
    ----------
    graph : PoseGraph
    config : GaussNewtonConfig, optional
        Method, stopping criteria, damping, linear solver, robust kernel.

    Raises
    ------
    GraphError
        A connected part has no fixed pose and no GPS constraint.
    """

    def __init__(self, graph: PoseGraph, config: GaussNewtonConfig | None = None) -> None:
        self.graph = graph
        self.config = cfg = config or GaussNewtonConfig()
        self.compile_seconds = ensure_compiled()
        t0 = time.perf_counter()
        self.fixed = default_fixed_nodes(graph)
        check_gauge(graph, self.fixed)
        self.pattern = analyze(graph, self.fixed, reorder=True)
        self.robust = (_cost.robust_kind(cfg.kernel, cfg.robust_delta), float(cfg.robust_delta))
        """(kernel code, delta) of the robust kernel (docs/conventions.md); least squares for
        ``robust="auto"``, whose outlier test runs in :func:`solve_exact`."""
        self._backends: dict[tuple[bool, bool], _Backend] = {}
        self.analyze_seconds = time.perf_counter() - t0
        """Seconds of the analysis so far (the gauge, the pattern, each factorization's
        symbolic analysis, created when a solve first needs it)."""

    def _backend(self, planar: bool, allow_block: bool = True) -> _Backend:
        key = (planar, allow_block)
        if key not in self._backends:
            t0 = time.perf_counter()
            self._backends[key] = _Backend.create(self.pattern, planar,
                                                  self.config.linear_solver, allow_block)
            self.analyze_seconds += time.perf_counter() - t0
        return self._backends[key]

    # ----------------------------------------------------------------- covariances
    def factor(self, rotations: FloatArray | None = None,
               translations: FloatArray | None = None, *, block: bool = False) -> Any:
        """Assemble H (plain least squares) at the poses and factor it; returns the factorizer
        (``inverse_blocks``, ``solve_factored``) with the full 6-dof system of the free nodes,
        variables in the order of :attr:`pattern` (``var_of_node``): the configured backend's,
        or with ``block`` the 6x6 block Cholesky (:class:`hybridpgo.linalg.BlockCholesky`,
        whose ``inverse_diagonal_blocks`` is selected inversion), a new factor each call.

        Raises
        ------
        SolverError
            H is singular to rounding, or the linearization is not finite.
        """
        rot, trans = initial_poses(self.graph, rotations, translations)
        pat = self.pattern
        if block:
            solver: Any = BlockCholesky(pat.num_vars, pat.block_ptr, pat.block_row, pat.indptr)
            data = np.empty(pat.nnz)
        else:
            backend = self._backend(False, allow_block=False)
            solver, data = backend.solver, backend.data
        grad = np.empty(pat.dim)
        assemble(self.graph, pat, rot, trans, data, grad)
        solver.factor(data)
        solver.check()
        return solver

    # ----------------------------------------------------------------- solving
    def solve(self, rotations: FloatArray | None = None, translations: FloatArray | None = None,
              *, progress: ProgressCallback | None = None,
              iterate: IterateCallback | None = None,
              max_iterations: int | None = None) -> SolveResult:
        """Minimize E from the given start (default: the graph's estimate).

        Parameters
        ----------
        rotations, translations : (N, 3, 3), (N, 3) float64, optional
            Initial R_world_node, t_world_node.
        progress : callable, optional
            ``progress(Progress("exact", iteration, max_iterations, energy))`` after every
            iteration (iteration 0: the start).
        iterate : callable, optional
            ``iterate(Progress, rotations, translations)`` with the current poses, at the same
            points as ``progress`` (:data:`IterateCallback`).
        max_iterations : int, optional
            Overrides ``config.max_iterations`` for this solve.

        Returns
        -------
        SolveResult
            ``method`` is ``"exact"``; ``stats["algorithm"]`` is ``"lm"`` or ``"gn"``.
            ``energy_history[k]`` is E after iteration k (unchanged after a rejected LM trial);
            with a robust kernel it is E_rho, and ``stats["plain_energy_history"]`` the plain E.
            ``stats``: accepted and rejected steps, step halvings, linear solver, final damping,
            nnz of H.  ``timings["analyze"]`` is the analysis this solve paid for (0 when an
            earlier solve of this object did it).

        Raises
        ------
        SolverError
            Non-finite initial poses or linearization; a singular system (GN without a gauge);
            a non-finite unguarded GN step.  Never returns non-finite poses.
        """
        t_start = time.perf_counter()
        analyzed = self.analyze_seconds
        rot, trans = initial_poses(self.graph, rotations, translations)
        run = _Run(self, rot, trans)
        t_analyze = self.analyze_seconds - analyzed
        limit = self.config.max_iterations if max_iterations is None else max_iterations
        return _iterate(run, limit, t_start, t_analyze, progress, iterate)


class _Run:
    """One solve of an :class:`ExactSolver`: the current and trial poses, the gradient."""

    def __init__(self, owner: ExactSolver, rot: FloatArray, trans: FloatArray) -> None:
        self.graph = owner.graph
        self.cfg = owner.config
        self.pat = owner.pattern
        self.robust = owner.robust
        self.planar = is_planar(owner.graph, rot, trans)
        backend = owner._backend(self.planar)
        self.system = backend.system
        self.solver = backend.solver
        self.data = backend.data
        self.rot, self.trans = rot, trans
        self.new_rot, self.new_trans = np.empty_like(rot), np.empty_like(trans)
        self.grad = np.empty(self.pat.dim)
        self.seconds = {"assemble": 0.0, "factorize": 0.0, "energy": 0.0}
        self.plain = 0.0
        """The plain E at the current poses (the last assembly's, or the last trial's)."""
        self.new_plain = 0.0
        """The plain E at the trial poses."""

    def assemble(self) -> float:
        """H and g at the current poses; returns E (E_rho) there, the plain E in ``plain``."""
        t0 = time.perf_counter()
        e, self.plain = assemble(self.graph, self.pat, self.rot, self.trans, self.data,
                                 self.grad, self.robust, self.system)
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
        values = self.data
        g_sys = system.restrict(self.grad)
        damping = np.zeros(0)
        if self.cfg.method == "lm":
            diag_index = system.diag_index
            diag = values[diag_index]  # a copy: restored after the factorization
            damping = np.maximum(diag, DIAG_FLOOR * diag.max())
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
        e_new, self.new_plain = energies_at(self.graph, self.new_rot, self.new_trans,
                                            self.robust, self.planar)
        tries = 0
        if self.cfg.method == "gn" and self.cfg.step_guard:
            while not (e_new <= e_cur) and tries < self.cfg.max_step_halvings:
                scale *= 0.5
                tries += 1
                _k.retract(self.rot, self.trans, step, self.pat.var_of_node, scale,
                           self.new_rot, self.new_trans)
                e_new, self.new_plain = energies_at(self.graph, self.new_rot,
                                                    self.new_trans, self.robust, self.planar)
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
        # the gain ratio rho >= 0 enters as min(rho, 1): every rho >= 1 gives the bound
        # MAX_DECREASE, and (2 rho - 1)^3 of a rho near 1e300 would overflow
        rho = min((e_cur - e_new) / predicted, 1.0) if predicted > 0 else 0.0
        return take, mu * max(MAX_DECREASE, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
    return take, mu * nu, nu * 2.0


def _gn_accept(cfg: GaussNewtonConfig, e_cur: float, e_new: float, iteration: int) -> bool:
    """GN: with the step guard, accept when E did not rise; without it, always (finite E)."""
    if cfg.step_guard:
        return bool(np.isfinite(e_new) and e_new <= e_cur)
    if not np.isfinite(e_new):
        raise SolverError(f"iteration {iteration}: the Gauss-Newton step gives a "
                          "non-finite energy (use method='lm' or step_guard=True)")
    return True


class _Trace:
    """The energies and times of one solve, and the callbacks that see them."""

    def __init__(self, run: _Run, t_start: float, limit: int,
                 progress: ProgressCallback | None, iterate: IterateCallback | None) -> None:
        self.run, self.t_start, self.limit = run, t_start, limit
        self.progress, self.iterate = progress, iterate
        self.history: list[float] = []
        self.plain: list[float] = []
        self.times: list[float] = []

    def record(self, iteration: int, e_cur: float, report: bool = True) -> None:
        self.history.append(e_cur)
        self.plain.append(self.run.plain)
        self.times.append(time.perf_counter() - self.t_start)
        if not report:
            return
        if self.progress is not None:
            self.progress(Progress("exact", iteration, self.limit, e_cur))
        if self.iterate is not None:
            self.iterate(Progress("exact", iteration, self.limit, e_cur), self.run.rot,
                         self.run.trans)


def _newton_like(cfg: GaussNewtonConfig, mu_step: float, mu_after: float,
                 scale: float) -> bool:
    """Whether an accepted step was a full Newton-like one, the only kind whose fall can show
    superlinear convergence (:class:`_Convergence`): GN's step not halved; LM's damping at
    most its start when the step was solved and after it (a gain ratio that raises ``mu``
    is no Newton step)."""
    if cfg.method == "gn":
        return scale == 1.0
    return mu_step <= cfg.initial_damping and mu_after <= cfg.initial_damping


class _Convergence:
    """The energy test of convergence, fed the energies before and after each accepted step.

    Converged when what the next steps would add, if E kept falling at the last step's rate
    (the geometric tail ``drop r / (1 - r)``, r = this decrease over the one before), is at
    most ``tolerance E``, and either this step's own decrease is too, or E falls superlinearly
    (r at most :data:`SUPERLINEAR_RATE` and no larger than the step before's, the step a full
    Newton-like one) and the tail is :data:`SUPERLINEAR_MARGIN` times below the tolerance.
    Large-residual graphs converge linearly, each step changing E by less than the tolerance
    while far more of it remains: the tail catches that.  In a superlinear fall the tail is an
    estimate of what remains (7.5 times too small where the fall turned linear, see
    :data:`SUPERLINEAR_MARGIN`), and with the margin the step that would only confirm
    convergence is not taken."""

    def __init__(self, tolerance: float) -> None:
        self.tolerance = tolerance
        self.last_drop = np.inf  # the last accepted step's decrease of E
        self.last_rate = np.inf  # its fraction of the one before (inf: no two steps yet)

    def accepted(self, e_prev: float, e_new: float, newton: bool) -> bool:
        """Record an accepted step from ``e_prev`` to ``e_new`` (above ``e_prev`` only for
        unguarded Gauss-Newton); True when converged.  ``newton``: the step was a full
        Newton-like one (GN not halved; LM damped at most at its start, before and after the
        step), the only kind that can show a superlinear fall."""
        drop = e_prev - e_new
        last = self.last_drop
        rate = drop / last if 0.0 < drop < last else 0.0 if drop <= 0.0 else 1.0
        superlinear = (newton and drop > 0.0 and np.isfinite(self.last_rate)
                       and rate <= min(SUPERLINEAR_RATE, self.last_rate))
        self.last_rate = rate if np.isfinite(last) else np.inf
        self.last_drop = drop
        ahead = abs(drop) * rate / (1.0 - rate) if rate < 1.0 else np.inf
        tol = self.tolerance * e_prev
        return e_new == 0.0 or (ahead <= tol and abs(drop) <= tol) or (
            superlinear and ahead * SUPERLINEAR_MARGIN <= tol)


def _iterate(run: _Run, limit: int, t_start: float, t_analyze: float,
             progress: ProgressCallback | None,
             iterate: IterateCallback | None) -> SolveResult:
    """The LM / GN iterations of one solve (:meth:`ExactSolver.solve`)."""
    cfg = run.cfg
    trace = _Trace(run, t_start, limit, progress, iterate)
    e_cur = run.assemble()
    trace.record(0, e_cur)
    mu = cfg.initial_damping
    nu = 2.0
    accepted = rejected = halvings = 0
    undamped = False  # LM: the convergence test has restarted from the initial damping
    stop = _Convergence(cfg.energy_tolerance)
    status = Status.MAX_ITERATIONS
    iteration = 0
    if run.pat.num_vars == 0 or e_cur == 0.0:
        status = Status.CONVERGED
    while status is Status.MAX_ITERATIONS and iteration < limit:
        iteration += 1
        mu_step = mu
        solved = run.solve(mu, iteration)
        if solved is None:  # LM: H + mu D not numerically SPD -> more damping, as a rejection
            rejected += 1
            mu, nu = mu * nu, nu * 2.0
            if mu > MAX_DAMPING:
                status = Status.STALLED
            trace.record(iteration, e_cur, report=False)
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
            # E at the new poses is the trial's (the assembly's same sum, in the same order):
            # a step that converges needs no assembly there
            small = stop.accepted(e_prev, e_new, _newton_like(cfg, mu_step, mu, scale))
            # a small change under heavy damping can be slow progress (ill-conditioned graphs:
            # linear convergence at mu ~ 1e-3): once, go on from the initial damping; where
            # the optimum is reached the next step confirms it
            restart = small and cfg.method == "lm" and mu > cfg.initial_damping and not undamped
            if small and not restart:
                e_cur, run.plain = e_new, run.new_plain
                status = Status.CONVERGED
            else:
                e_cur = run.assemble()
                if restart:
                    mu, nu, undamped = cfg.initial_damping, 2.0, True
                elif step_small and scale == 1.0:
                    status = Status.CONVERGED
        else:
            rejected += 1
            if changed or step_small:  # E or the poses no longer change measurably
                status = Status.CONVERGED
            elif cfg.method == "gn" or mu > MAX_DAMPING:
                status = Status.STALLED
        trace.record(iteration, e_cur)

    t_total = time.perf_counter() - t_start
    robust_stats: dict[str, Any] = {}
    if run.robust[0] != _cost.ROBUST_NONE:
        robust_stats = {"robust": cfg.robust, "robust_scale": cfg.robust_delta,
                        "plain_energy": trace.plain[-1], "plain_energy_history": trace.plain}
    return SolveResult(
        rotations=run.rot, translations=run.trans, status=status, iterations=iteration,
        energy_history=np.asarray(trace.history), times=np.asarray(trace.times),
        method="exact", num_constraints=run.graph.num_constraints,
        timings={"compile": 0.0, "analyze": t_analyze, "solve": t_total - t_analyze,
                 "total": t_total, **run.seconds},
        stats={"algorithm": cfg.method, "accepted_steps": accepted, "rejected_steps": rejected,
               "step_halvings": halvings, "linear_solver": run.solver.name,
               "final_damping": mu if cfg.method == "lm" else 0.0,
               "num_variables": run.system.dim,
               "hessian_nnz": 2 * run.system.nnz - run.system.dim, "planar": run.planar,
               **robust_stats},
    )


def solve_exact(graph: PoseGraph, rotations: FloatArray | None = None,
                translations: FloatArray | None = None,
                config: GaussNewtonConfig | None = None, *,
                progress: ProgressCallback | None = None,
                iterate: IterateCallback | None = None) -> SolveResult:
    """Minimize E with sparse Gauss-Newton or Levenberg-Marquardt: ``ExactSolver(graph,
    config).solve(rotations, translations)`` (see :meth:`ExactSolver.solve`), with the
    analysis and compilation counted in the result's ``timings``.  ``config.robust="auto"``:
    that solve in least squares, then the outlier test and re-solve of
    :mod:`hybridpgo.solvers.robust`.

    Raises
    ------
    GraphError
        A connected part has no fixed pose and no GPS constraint.
    SolverError
        Non-finite initial poses or linearization; a singular system (GN without a gauge); a
        non-finite unguarded GN step.  Never returns non-finite poses.
    """
    if config is not None and config.robust == "auto":  # least squares, then the outlier test
        from .robust import solve_exact_auto

        return solve_exact_auto(graph, rotations, translations, config, progress=progress,
                                iterate=iterate)
    t0 = time.perf_counter()
    initial_poses(graph, rotations, translations)  # bad poses before the analysis
    solver = ExactSolver(graph, config)
    t_analyze = time.perf_counter() - t0 - solver.compile_seconds
    result = solver.solve(rotations, translations, progress=progress, iterate=iterate)
    timings = dict(result.timings, compile=solver.compile_seconds)
    timings["analyze"] += t_analyze
    timings["total"] += t_analyze
    return dataclasses.replace(result, timings=timings,
                               times=np.asarray(result.times) + t_analyze)

