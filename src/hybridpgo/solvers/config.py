"""Solver options: frozen dataclasses validated once in ``__post_init__``
(docs/contributing.md#solver-api).

Every field's docstring states its exact meaning.  Invalid values raise ``ValueError`` naming
the field, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, get_args

from .._robust import ROBUST_DEFAULT_SCALE as ROBUST_DEFAULT_SCALE
from .._robust import ROBUST_NAMES as ROBUST_NAMES
from .._robust import default_robust_scale, robust_kind

if TYPE_CHECKING:
    from ..graph import PoseGraph

StepName = Literal["woodbury", "givens"]
TreeName = Literal["bfs", "mst", "gps"]
InitName = Literal["tree", "file", "chordal"]
#: ``"auto"`` (least squares, then :mod:`hybridpgo.solvers.robust`'s outlier test and re-solve)
#: and the robust kernels (docs/conventions.md#robust-kernels), whose names are
#: ``_cost.ROBUST_NAMES`` (tested).
RobustName = Literal["auto", "none", "huber", "cauchy", "geman_mcclure"]
#: Every value ``robust`` accepts: ``"auto"``, then the kernels.
ROBUST_CHOICES: tuple[str, ...] = get_args(RobustName)
#: The names a user may give for each choice (derived once from the Literal types).
STEP_NAMES: tuple[str, ...] = get_args(StepName)
TREE_NAMES: tuple[str, ...] = get_args(TreeName)
INIT_NAMES: tuple[str, ...] = get_args(InitName)


class Progress(NamedTuple):
    """What every solver reports after each iteration (one callback shape for all solvers)."""

    phase: str
    """``"sweeps"`` (hybrid), ``"polish"`` (exact LM after the sweeps), ``"exact"``, or
    ``"start"`` (the default pipeline computed a start: iteration 0, its energy)."""
    iteration: int
    """Iterations (sweeps) done in this phase; 0 is the phase's starting point."""
    total: int
    """The phase's iteration limit."""
    energy: float
    """E at this point."""
    tau: float | None = None
    """The temperature of the next sweep (hybrid only)."""
    detail: str = ""
    """What the phase works on: the start (``"chordal"``, ``"tree"``, ``"file"``) whose sweeps
    or polish these are, for the default pipeline (:class:`AutoConfig`); else empty."""


#: Progress callback: ``progress(Progress(...))`` after every iteration.
ProgressCallback = Callable[[Progress], None]

#: Sparse linear solvers of the exact solver (``"auto"``: CHOLMOD via cvxopt if importable, else
#: SuperLU; see :mod:`hybridpgo.linalg`).
LINEAR_SOLVERS = ("auto", "cholmod", "splu")



def check_int(name: str, value: object, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def check_robust(name: str, scale: float | None, delta: float) -> None:
    """``robust`` and ``robust_scale``: ``"auto"`` takes no scale, a kernel a delta > 0."""
    if name == "auto":
        if scale is not None:
            raise ValueError(f"robust_scale applies to a named kernel, not to robust='auto', "
                             f"got {scale!r}")
        return
    if name not in ROBUST_CHOICES:
        raise ValueError(f"robust must be one of {', '.join(ROBUST_CHOICES)}, got {name!r}")
    robust_kind(name, delta)


def check_float(name: str, value: object, *, positive: bool) -> None:
    if (isinstance(value, bool) or not isinstance(value, (int, float))
            or not math.isfinite(value) or (value <= 0 if positive else value < 0)):
        kind = "a finite number > 0" if positive else "a finite number >= 0"
        raise ValueError(f"{name} must be {kind}, got {value!r}")


class RobustOptions:
    """What every solver's config derives from its ``robust`` and ``robust_scale`` fields."""

    robust: str
    robust_scale: float | None

    @property
    def robust_delta(self) -> float:
        """The robust kernel's delta: ``robust_scale``, or the kernel's default."""
        return default_robust_scale(self.robust, self.robust_scale)

    @property
    def kernel(self) -> str:
        """The kernel of the solver's own iterations: ``robust``, ``"none"`` for ``"auto"``
        (least squares first, the outlier test after)."""
        return "none" if self.robust == "auto" else self.robust


@dataclass(frozen=True)
class GaussNewtonConfig(RobustOptions):
    """Options of the exact solver :func:`hybridpgo.solvers.gauss_newton.solve_exact`
    (docs/mathematics.md#exact-solver).

    The energy is ``E = sum_c e_c^T Omega_c e_c`` (no 1/2).  The solver stops at the first of:
    the energy criterion, the step criterion, or ``max_iterations``.
    """

    method: Literal["gn", "lm"] = "lm"
    """``"lm"``: Levenberg-Marquardt (Nielsen's damping update, damping ``mu * diag(H)``, a step is
    accepted only when it lowers the energy, so E never increases).  ``"gn"``: Gauss-Newton."""
    max_iterations: int = 100
    """Stop after this many iterations.  An iteration is one linear solve: a rejected LM trial
    counts, and so does a GN step together with its halvings."""
    energy_tolerance: float = 1e-10
    """Stop (converged) when, after an accepted step, the geometric tail at the last two steps'
    rate (what the next steps would add if E kept falling at that rate) and the step's own
    change ``|dE|`` are both below ``energy_tolerance * E``; or, when E falls superlinearly
    (a full Newton-like step whose rate is at most 0.01 and no larger than the step before's),
    when the tail alone is ten times below it; or when E reaches exactly 0.  LM that converges
    while damped above ``initial_damping`` goes on once from there."""
    step_tolerance: float = 1e-12
    """Stop (converged) when the accepted step satisfies
    ``max_i |delta_i|_inf < step_tolerance * (1 + max_i |t_i|_inf)`` (delta in (rho, phi) units:
    translation units and radians)."""
    initial_damping: float = 1e-8
    """LM only: the initial ``mu`` of the damped system ``(H + mu * diag(H)) delta = -g``.

    Small on purpose: pose-graph Hessians are so ill-conditioned (long chains) that even
    ``mu = 1e-4`` relative to diag(H) slows LM down 2-5x against Gauss-Newton (measured:
    M3500 26 iterations with 1e-4, 12 with 1e-6, 5 with 1e-8 - as many as GN).  A step that
    raises E is rejected and mu grows quickly (x2, x4, x8, ...), so a small start costs little
    far from the optimum."""
    step_guard: bool = True
    """GN only: when a full step raises the energy, halve it until it does not (up to
    ``max_step_halvings`` times; then stop as STALLED).  ``False``: plain Gauss-Newton, every step
    is taken.  (docs/mathematics.md#lm-damping: unguarded GN from outside the basin diverges.)"""
    max_step_halvings: int = 30
    """GN with ``step_guard``: at most this many halvings of one step."""
    linear_solver: Literal["auto", "cholmod", "splu"] = "auto"
    """Sparse factorization of the normal equations, on a fill-reducing (AMD) ordering of the
    block graph computed once per solve: ``"cholmod"`` (SuiteSparse CHOLMOD through cvxopt, a
    runtime dependency: supernodal Cholesky, symbolic analysis once per solve, numeric
    factorization per iteration), ``"splu"`` (SciPy's SuperLU in symmetric mode with diagonal
    pivots: an LU, 2-5x slower), or ``"auto"`` (CHOLMOD when cvxopt is importable, else
    SuperLU; except that a 3D system whose factor stays sparse, as on city-like graphs, uses
    the block Cholesky of :mod:`hybridpgo.linalg._block_cholesky`: 3x faster than CHOLMOD
    there and ~4x less memory, which keeps a 1M-pose polish within 4 GB)."""
    robust: RobustName = "none"
    """Robust kernel (see ``HybridConfig.robust``); the LM acceptance test uses E_rho.
    ``"auto"``: least squares, then the outlier test and re-solve of
    :mod:`hybridpgo.solvers.robust` (the default of :func:`hybridpgo.optimize` and the command
    line; this building block's default is plain least squares)."""
    robust_scale: float | None = None
    """The kernel's delta (> 0) in whitened units (sqrt of χ²): Huber is quadratic for
    ``s <= delta^2``.  GTSAM's ``mEstimator.*(k)`` with ``k = delta`` is the same kernel.
    None: the kernel's default (:data:`ROBUST_DEFAULT_SCALE`); the value used is
    :attr:`robust_delta`."""

    def __post_init__(self) -> None:
        if self.method not in ("gn", "lm"):
            raise ValueError(f"method must be 'gn' or 'lm', got {self.method!r}")
        check_int("max_iterations", self.max_iterations, 0)
        check_float("energy_tolerance", self.energy_tolerance, positive=False)
        check_float("step_tolerance", self.step_tolerance, positive=False)
        check_float("initial_damping", self.initial_damping, positive=True)
        if not isinstance(self.step_guard, bool):
            raise ValueError(f"step_guard must be True or False, got {self.step_guard!r}")
        check_int("max_step_halvings", self.max_step_halvings, 0)
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, "
                             f"got {self.linear_solver!r}")
        check_robust(self.robust, self.robust_scale, self.robust_delta)


#: Most sweeps one run may ask for (a sweep visits every constraint once; the paper runs 10).
MAX_SWEEPS = 1_000_000
#: The temperature must stay below this: a step scaled by tau >= 2 overshoots a quadratic
#: model's minimum by at least as much as it corrects (over-relaxation), so the sweeps diverge
#: (measured: intel with tau0 = 2.5 went from E = 501 to 2e11).
MAX_TAU = 2.0


@dataclass(frozen=True)
class HybridConfig(RobustOptions):
    """Options of the hybrid solver (paper Algorithm 1); every field is checked once here."""

    sweeps: int = 10
    """Maximum number of sweeps over all constraints (the paper's experiments use 10), at most
    ``MAX_SWEEPS``."""
    tau0: float = 1.0
    """Initial temperature tau (paper III-H), in (0, 2) (``MAX_TAU``)."""
    tau_decay: float = 0.99
    """tau is multiplied by this after each sweep (paper III-H)."""
    damping: float = 1e-6
    """mu: each block of B_c gets ``mu * trace(B)/6`` added to its diagonal
    (docs/mathematics.md#hybrid-step)."""
    step: StepName = "woodbury"
    """``"woodbury"`` (O(d), default) or ``"givens"`` (the paper's O(d^2) triangularization)."""
    tree: TreeName = "bfs"
    """``"bfs"`` (paper), ``"mst"`` (maximum-stiffness spanning tree) or ``"gps"`` (every GPS
    pose a child of the earth: GPS domains of one pose, a fraction of the per-path blocks on
    large GPS graphs, but measured slower to converge; experimental)."""
    init: InitName = "tree"
    """``"tree"`` (concatenate tree-edge measurements, paper), ``"file"`` (the file's vertices)
    or ``"chordal"`` (chordal rotation relaxation, then positions)."""
    energy_tolerance: float = 0.0
    """Stop when a sweep lowers the energy by less than this fraction (0: run all sweeps)."""
    gps_batch_size: int = 40
    """GPS constraints are relaxed together in batches of this size (paper: 30-50)."""
    dmax: int | None = None
    """Interpolated solving (paper III-E): a single update solves for at most this many nodes of
    its domain (>= 2: each side's endpoint) and distributes the rest (TORO's way); None solves
    the whole domain."""
    polish: bool = False
    """Finish with the exact Levenberg-Marquardt solver."""
    polish_iterations: int = 100
    """Iteration limit of the polish."""
    robust: RobustName = "none"
    """Robust kernel on every constraint's χ² ``s = e^T Omega e`` (relative and GPS;
    docs/conventions.md#robust-kernels): ``"none"`` (least squares), ``"huber"``,
    ``"cauchy"`` or ``"geman_mcclure"`` (g2o's conventions).  The solver minimizes
    ``E_rho = sum_c rho(s_c)`` by iterative reweighting: each step whitens with
    ``sqrt(w_c) L^T``, ``w_c = rho'(s_c)`` at the current poses.  ``energy_history`` is then
    E_rho and ``stats["plain_energy_history"]`` the plain E.  The polish uses the same kernel.
    ``"auto"``: least squares, then the outlier test and re-solve of
    :mod:`hybridpgo.solvers.robust` (:func:`solve_hybrid`; a
    :class:`~hybridpgo.solvers.hybrid.HybridSolver` stepped by hand runs least squares)."""
    robust_scale: float | None = None
    """The kernel's delta (> 0) in whitened units (sqrt of χ²); None: the kernel's default
    (:data:`ROBUST_DEFAULT_SCALE`).  The value used is :attr:`robust_delta`."""

    correction: Literal["none", "pcg"] = "none"
    """``"pcg"``: after every sweep one global truncated Gauss-Newton step:
    ``correction_iterations`` iterations of conjugate gradients on the exact normal equations of
    the tree parametrization (the batch of every constraint, III-F) preconditioned by 𝔅(H),
    taken only if it lowers the energy (:mod:`hybridpgo.solvers.hybrid._correction`).
    ``"none"``: the paper's sweeps."""
    correction_iterations: int = 30
    """CG iterations of one ``correction="pcg"`` step (>= 1)."""
    monotone: bool = False
    """With ``correction="pcg"``: a sweep that raises the energy is undone (the correction
    still follows), so every iteration lowers E and a stationary point is a fixed point of the
    iterations (the paper's sweeps near the optimum raise E: it is not one of theirs)."""

    def __post_init__(self) -> None:
        if self.correction not in ("none", "pcg"):
            raise ValueError(f"correction must be 'none' or 'pcg', got {self.correction!r}")
        check_int("correction_iterations", self.correction_iterations, 1)
        if not isinstance(self.monotone, bool):
            raise ValueError(f"monotone must be True or False, got {self.monotone!r}")
        if self.monotone and self.correction == "none":
            raise ValueError("monotone=True needs correction='pcg' (an undone sweep alone would "
                             "repeat itself)")
        check_int("sweeps", self.sweeps, 0)
        if self.sweeps > MAX_SWEEPS:
            raise ValueError(f"sweeps must be at most {MAX_SWEEPS}, got {self.sweeps!r}")
        check_float("tau0", self.tau0, positive=True)
        if not self.tau0 < MAX_TAU:
            raise ValueError(f"tau0 must be below {MAX_TAU:g} (a larger temperature "
                             f"over-relaxes and the sweeps diverge), got {self.tau0!r}")
        if not (isinstance(self.tau_decay, (int, float)) and 0 < self.tau_decay <= 1):
            raise ValueError(f"tau_decay must be in (0, 1], got {self.tau_decay!r}")
        check_float("damping", self.damping, positive=False)
        for name, value, allowed in (("step", self.step, STEP_NAMES),
                                     ("tree", self.tree, TREE_NAMES),
                                     ("init", self.init, INIT_NAMES)):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {value!r}")
        check_int("gps_batch_size", self.gps_batch_size, 1)
        if self.dmax is not None:
            check_int("dmax", self.dmax, 2)  # one node per side of the path at least
        check_float("energy_tolerance", self.energy_tolerance, positive=False)
        if not isinstance(self.polish, bool):
            raise ValueError(f"polish must be True or False, got {self.polish!r}")
        check_int("polish_iterations", self.polish_iterations, 0)
        check_robust(self.robust, self.robust_scale, self.robust_delta)


#: The starts :class:`AutoConfig` tries by default, in this order (``"file"`` only when the
#: file has vertices).
AUTO_INITS: tuple[InitName, ...] = ("chordal", "tree", "file")
#: Most sweeps the default pipeline runs from one start (``AutoConfig.sweeps.sweeps``).
AUTO_MAX_SWEEPS = 30
#: Iteration limit of each of the default pipeline's polishes
#: (``AutoConfig.polish.max_iterations``).
AUTO_POLISH_ITERATIONS = 200


def _auto_sweeps() -> HybridConfig:
    return HybridConfig(sweeps=AUTO_MAX_SWEEPS, robust="auto")


def _auto_polish() -> GaussNewtonConfig:
    return GaussNewtonConfig(method="lm", max_iterations=AUTO_POLISH_ITERATIONS, robust="auto")


@dataclass(frozen=True)
class AutoConfig:
    """Options of the default pipeline :func:`hybridpgo.solvers.auto.solve_auto`.

    First (``certify_first``, where SE-Sync's certificate applies) the first start of
    ``inits`` alone: certified, LM from its certified start is the answer.  Otherwise, for
    every start in ``inits`` (``"file"`` skipped when the file has no vertices): hybrid
    sweeps (options ``sweeps``) while they pay (each sweep must lower the energy by at least
    ``sweep_tolerance``, relative; the best poses seen are kept, so a sweep that raises E is
    undone), then the ``finalists`` starts with the lowest energy are polished with
    Levenberg-Marquardt (options ``polish``) to convergence (a runner-up within
    ``finalist_budget``) and the lowest final energy wins.  The result's ``stats`` say which
    start won, how many sweeps and polish iterations it took, and every candidate's energies.

    The sweeps and the polish are configured by the two solvers' own option objects, so their
    defaults are those of :class:`HybridConfig` and :class:`GaussNewtonConfig`; both must use
    the same robust kernel.  :meth:`from_options` builds one from flat keyword options (the
    command line's names).
    """

    sweeps: HybridConfig = field(default_factory=_auto_sweeps)
    """The sweeps from each start: ``sweeps.sweeps`` is the most sweeps from one start (0: no
    sweeps, LM straight from the start; default :data:`AUTO_MAX_SWEEPS`), the other fields the
    temperature, damping, step, tree (also of the tree and chordal starts), GPS batches,
    ``D_max`` and robust kernel.  ``init``, ``polish`` and ``energy_tolerance`` are not used:
    the pipeline chooses the starts (``inits``), stops sweeping by ``sweep_tolerance`` and
    polishes itself."""
    polish: GaussNewtonConfig = field(default_factory=_auto_polish)
    """The Levenberg-Marquardt polish of each finalist (default: at most
    :data:`AUTO_POLISH_ITERATIONS` iterations, converged when an accepted step changes E by
    less than ``polish.energy_tolerance``)."""
    inits: tuple[InitName, ...] = AUTO_INITS
    """Candidate starts, in order of preference on ties: ``"chordal"`` (chordal rotation
    relaxation, then positions), ``"tree"`` (the paper's concatenation of tree-edge
    measurements), ``"file"`` (the file's vertices).  At least one, no repeats."""
    finalists: int | None = None
    """How many candidates are polished, in rank order (the starts after their sweeps, lowest
    energy first; then, with ``polish_unswept``, the swept starts as they were); the lowest
    polished energy wins.  None: every candidate; 1: only the best start after its sweeps."""
    polish_unswept: bool = True
    """Also polish each start whose sweeps were kept from its own poses: sweeps that pay can
    still carry a start out of the global optimum's basin (measured on a noisified M3500:
    LM from the file's vertices reaches the optimum, after 19 sweeps it ends 3% above)."""
    finalist_budget: float = 2.0
    """Cost guard: a finalist after the first polished one gets at most ``finalist_budget``
    times the best polish's iterations (at least 20) and is polished on to convergence only if
    it is then below the best; else it is reported as cut (``polish_cut_at_budget``)."""
    sweep_tolerance: float = 0.05
    """Stop sweeping from a start when a sweep lowers E by less than this fraction (or raises
    it).  Sweeps pay far from the optimum (a tree start: E falls 10-100x in a few sweeps) and
    stop paying near it (the optimum is not a fixed point of the sweeps)."""
    certify: bool = True
    """Certify the first polished start (:func:`hybridpgo.certificate.certify`: Newton's
    method on SE-Sync's objective from its rotations, the certificate of that objective's
    global minimum, and LM from the certified start back to the same energy).  Certified: no
    other finalist is polished and the relaxation check is skipped.  Not certified: the other
    finalists are polished as with ``False`` and the winner is certified (a winner at the
    first finalist's energy keeps the first finalist's verdict; ``stats["certificate"]["start"]``
    names the finalist certified).  Applies where
    SE-Sync's model describes the graph (no robust kernel, at most one FIX node and none
    with GPS, connected) and not under the large-graph policy.
    ``stats["certificate"]`` says what was certified, or why not.  False: every finalist is
    polished, no certificate."""
    certify_first: bool = True
    """Before any sweep, try the first start of ``inits`` that applies (``"chordal"`` by
    default) alone: Newton's method on SE-Sync's objective refines its rotations, the
    certificate tests that objective's global minimum there, and when it holds, LM from the
    certified start is the answer (no sweeps, no other start: ``stats["start"]`` is
    ``"certified start"``).  When the certificate fails or does not apply, the pipeline runs
    as with ``False`` (sweeps, finalists, ``certify``) and ``stats["certificate"]["early"]``
    says what the early try found.  Needs ``certify``; not under the large-graph policy."""
    relaxation: bool = True
    """Planar graphs (2D, no GPS, no robust kernel, at most one FIX node; not under the
    large-graph policy): after the polish, run the rank-2 relaxation of the chordal cost
    (SE-Sync's, complex form: :func:`hybridpgo.initialization.planar_relaxation_start`) from the
    winner's poses.  If its rounded rotations differ from the winner's by more than
    ``relaxation_angle`` somewhere, the winner sits in another basin than the relaxation's
    minimum: that start is polished too (full budget) and the lower energy wins; else nothing
    more runs.  Measured (benchmarks/auto.py): the check moves <= 0.01 rad on the graphs the
    pipeline already solves (relaxation ~1-4 s on 3 500 poses) and 2.3-3.1 rad on m3500c and
    m3500b + 10 deg of yaw noise, where the relaxation's polish reaches the optimum (1.15 ->
    1.0000, 1.015 -> 1.0000, 1.041 -> 1.0000 of LM from the ground truth)."""
    relaxation_iterations: int = 300
    """Most Riemannian conjugate-gradient iterations of the relaxation."""
    relaxation_angle: float = 0.1
    """Radians: the relaxation's start is polished when some rotation differs from the
    winner's by more than this (the two are then in different basins)."""
    large_poses: int | None = 200_000
    """Graphs with at least this many poses get the *large-graph policy* (None: never), since
    every start, sweep and polish costs seconds to minutes there (a 1M-pose city: one sweep
    20-40 s, one LM iteration ~10 s): only the first applicable start of ``large_inits``, at
    most ``large_max_sweeps`` sweeps, one polish (``finalists=1``, no ``polish_unswept``, no
    certificate, no early try).  The result's ``stats["policy"]`` and its ``reason`` say which
    policy ran."""
    large_inits: tuple[InitName, ...] = ("chordal", "file", "tree")
    """Starts of the large-graph policy, in order of preference: the first that applies (and
    can be computed) is the only one swept and polished."""
    large_max_sweeps: int = 0
    """Most sweeps from the start under the large-graph policy.  0 (default): none, and no
    hybrid solver is built (its per-path 6x6 blocks alone take 1 GB at 1M poses without GPS,
    ~6 GB with GPS).  Measured on a 100k-pose city (benchmarks/scale.py): from the chordal start
    the first sweep raises E (it is undone) and LM converges in 12 iterations either way; from
    the tree start 13 sweeps (26 s) leave LM 14 iterations where it needs 12 without them."""

    def __post_init__(self) -> None:
        if not isinstance(self.sweeps, HybridConfig):
            raise ValueError(f"sweeps must be a HybridConfig, got {self.sweeps!r}")
        if not isinstance(self.polish, GaussNewtonConfig):
            raise ValueError(f"polish must be a GaussNewtonConfig, got {self.polish!r}")
        if self.sweeps.polish:
            raise ValueError("sweeps.polish must be False: the pipeline polishes itself "
                             "(configure it with polish=GaussNewtonConfig(...))")
        if self.polish.method != "lm":
            raise ValueError("the pipeline polishes with Levenberg-Marquardt: polish.method "
                             f"must be 'lm', got {self.polish.method!r}")
        if (self.sweeps.kernel, self.sweeps.robust_delta) != (self.polish.kernel,
                                                             self.polish.robust_delta):
            raise ValueError(
                f"the sweeps and the polish must use the same robust kernel, got "
                f"{self.sweeps.robust}:{self.sweeps.robust_delta:g} and "
                f"{self.polish.robust}:{self.polish.robust_delta:g}")
        if self.large_poses is not None:
            check_int("large_poses", self.large_poses, 2)
        for name, value in (("inits", self.inits), ("large_inits", self.large_inits)):
            if (not isinstance(value, tuple) or not value
                    or any(i not in INIT_NAMES for i in value) or len(set(value)) != len(value)):
                raise ValueError(f"{name} must be a non-empty tuple of distinct names from "
                                 f"{', '.join(INIT_NAMES)}, got {value!r}")
        check_int("large_max_sweeps", self.large_max_sweeps, 0)
        if self.large_max_sweeps > MAX_SWEEPS:
            raise ValueError(f"large_max_sweeps must be at most {MAX_SWEEPS}, got "
                             f"{self.large_max_sweeps!r}")
        if self.finalists is not None:
            check_int("finalists", self.finalists, 1)
        if not isinstance(self.polish_unswept, bool):
            raise ValueError(f"polish_unswept must be True or False, got {self.polish_unswept!r}")
        check_float("finalist_budget", self.finalist_budget, positive=True)
        check_float("sweep_tolerance", self.sweep_tolerance, positive=False)
        if not isinstance(self.certify, bool):
            raise ValueError(f"certify must be True or False, got {self.certify!r}")
        if not isinstance(self.certify_first, bool):
            raise ValueError(f"certify_first must be True or False, got {self.certify_first!r}")
        if not isinstance(self.relaxation, bool):
            raise ValueError(f"relaxation must be True or False, got {self.relaxation!r}")
        check_int("relaxation_iterations", self.relaxation_iterations, 1)
        check_float("relaxation_angle", self.relaxation_angle, positive=True)

    @property
    def robust(self) -> RobustName:
        """The robust kernel of the sweeps and the polish (the same by construction).

        ``"auto"`` (the default, when either nested config says ``"auto"``): the pipeline
        solves least squares, then tests every constraint and, when the graph is inconsistent
        (false loop closures, false GPS fixes), re-solves without the outliers
        (:mod:`hybridpgo.solvers.robust`; ``stats["outliers"]`` lists them).  ``"none"`` in
        both: least squares only.  A kernel name: that kernel in the sweeps and the polish
        (``HybridConfig.robust``)."""
        if "auto" in (self.sweeps.robust, self.polish.robust):
            return "auto"
        return self.sweeps.robust

    @property
    def robust_delta(self) -> float:
        """The robust kernel's delta (the same in the sweeps and the polish)."""
        return self.sweeps.robust_delta

    def is_large(self, num_poses: int) -> bool:
        """True when a graph of ``num_poses`` poses gets the large-graph policy."""
        return self.large_poses is not None and num_poses >= self.large_poses

    def hybrid_config(self, init: str, sweeps: int) -> HybridConfig:
        """The options of one start's sweeps (no polish: the pipeline polishes itself)."""
        return dataclasses.replace(self.sweeps, init=init,  # type: ignore[arg-type]
                                   sweeps=sweeps)  # init: checked by HybridConfig

    @classmethod
    def from_options(cls, **options: Any) -> AutoConfig:
        """An AutoConfig from flat keyword options, the command line's names: ``sweeps`` (most
        sweeps per start), ``max_iterations`` and ``energy_tolerance`` (of each polish),
        ``linear_solver`` and ``initial_damping`` (the polish's), ``robust`` and
        ``robust_scale`` (both), ``init`` (the only start to try), any other field of
        :class:`HybridConfig` (the sweeps') or of AutoConfig itself.  A positive ``sweeps``
        turns ``certify_first`` off unless it is given too: sweeps asked for are run.

        Raises
        ------
        TypeError
            An option that is not one of the default pipeline's.
        ValueError
            A value that is not allowed (the field's own message).
        """
        opts = dict(options)
        if isinstance(opts.get("polish"), bool):
            raise TypeError("polish: not an option of the default pipeline, which always "
                            "polishes; polish=True is for the paper's method alone: "
                            "optimize(graph, 'hybrid', polish=True)")
        if "init" in opts:
            opts["inits"] = opts.pop("init")
        inits = opts.get("inits")
        if isinstance(inits, (list, str)):  # one name (a CLI --init, a batch grid) or a list
            opts["inits"] = (inits,) if isinstance(inits, str) else tuple(inits)
        sweeps: dict[str, Any] = {}
        polish: dict[str, Any] = {}
        for key in ("robust", "robust_scale"):
            if key in opts:
                sweeps[key] = polish[key] = opts.pop(key)
        for key in ("max_iterations", "energy_tolerance", "linear_solver", "initial_damping"):
            if key in opts:
                polish[key] = opts.pop(key)
        own = set(cls.__dataclass_fields__)
        for key in list(opts):
            if key in _HYBRID_SWEEP_FIELDS and key not in own:
                sweeps[key] = opts.pop(key)
        if "sweeps" in opts and not isinstance(opts["sweeps"], HybridConfig):
            sweeps["sweeps"] = opts.pop("sweeps")
            if sweeps["sweeps"] and "certify_first" not in opts:  # asked for sweeps: they run
                opts["certify_first"] = False
        unknown = sorted(set(opts) - own)
        if unknown:
            raise TypeError(f"{', '.join(unknown)}: not an option of the default pipeline "
                            "(AutoConfig); for the paper's method alone name it: "
                            "optimize(graph, 'hybrid', ...)")
        base = cls()
        if sweeps:
            opts["sweeps"] = dataclasses.replace(opts.get("sweeps", base.sweeps), **sweeps)
        if polish:
            opts["polish"] = dataclasses.replace(opts.get("polish", base.polish), **polish)
        return cls(**opts)


#: HybridConfig fields the default pipeline's flat options pass to its sweeps (``init``,
#: ``polish``, ``polish_iterations`` and ``energy_tolerance`` are the pipeline's own business).
_HYBRID_SWEEP_FIELDS = frozenset(HybridConfig.__dataclass_fields__) - {
    "init", "polish", "polish_iterations", "energy_tolerance", "sweeps"}


def default_init(graph: PoseGraph, method: str) -> InitName:
    """The starting point a solver uses when none is given (the one place that decides).

    The exact solver starts from the file's vertices when the file has them (what g2o and GTSAM
    do); the hybrid solver, and any solver on a file without vertices, from the tree (paper).
    """
    if method == "exact" and graph.has_estimates:
        return "file"
    return "tree"
