"""Options of the online mode (:class:`OnlineConfig`), checked once."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ..solvers.config import (
    STEP_NAMES,
    HybridConfig,
    RobustName,
    RobustOptions,
    StepName,
    check_float,
    check_int,
    check_robust,
)
from ._heap import MAX_RESERVE_MB

OnlineTree = Literal["oldest", "odometry"]
ONLINE_TREES: tuple[str, ...] = ("oldest", "odometry")


@dataclass(frozen=True)
class OnlineConfig(RobustOptions):
    """Options of :class:`OnlineSolver` (checked once here)."""

    damping: float = HybridConfig.damping
    """mu: relative damping of the blocks of B_c, as :attr:`HybridConfig.damping` (whose
    default it shares)."""
    step: StepName = HybridConfig.step
    """Single-constraint solve: ``"woodbury"`` (O(d)) or ``"givens"`` (the paper's O(d^2))."""
    gps_batch_size: int = HybridConfig.gps_batch_size
    """GPS readings relaxed together in one batch (III-G)."""
    robust: RobustName = "auto"
    """Robust kernel on every constraint, relative and GPS, as :attr:`HybridConfig.robust`
    (the updates and the worker's exact solves use it).  ``"auto"`` (the default, as in every
    solver): the updates and the worker's solves are least squares; the worker screens its
    answers with the outlier test of :mod:`hybridpgo.solvers.robust` and, when it fails, runs
    the robust re-solve; the constraints it rejects are left alone by the updates from the
    answer's adoption on (:meth:`OnlineSolver.outliers`; docs/mathematics.md, "Outliers
    online").  :meth:`OnlineSolver.refine` tests and re-solves likewise (without a worker,
    the only place the test runs).  ``"none"``: least squares only."""
    robust_scale: float | None = HybridConfig.robust_scale
    """The kernel's delta; None: the kernel's default, as everywhere
    (:attr:`robust_delta`)."""
    tree: OnlineTree = "oldest"
    """Parent of a new pose: ``"oldest"`` (the oldest pose it is constrained to in its frame)
    or ``"odometry"`` (its odometry parent)."""
    tau_new: float = 1.0
    """Temperature of the first update of a new constraint."""
    tau_old: float = 0.3
    """Temperature of spare-time updates of older constraints (measured on M3500_isam at 5 ms
    per frame: final energy 1.18x the optimum with 0.3, 1.25x with 1.0, 1.50x with 0.1)."""
    recent: int = 32
    """The newest relative constraints (those acting near the robot) are spare-time candidates
    in every frame."""
    window: int = 256
    """Spare-time candidates per frame taken cyclically from all the constraints."""
    reserve_poses: int | None = None
    """Capacity reserved at construction for this many poses (edges: twice as many, path
    entries: 16 per pose, GPS readings and their path entries: 1 and 16 per 16 poses).  None:
    2^20 poses where the arrays can be reserved as address space only (Linux: pages are
    allocated when first written, see :mod:`._reserve`), else 1024.  Beyond it an array
    doubles when full: amortized O(1) per frame, but the frame that doubles pays for copying
    it (milliseconds at 10^4 poses)."""
    heap_reserve_mb: int = 64
    """MiB of the process's heap written once and kept resident, with ``malloc``'s blocks up to
    32 MiB served from the heap (glibc only; the first solver of a process that asks sets it,
    :mod:`._heap`): the compiled kernels' temporaries then land on pages already there, and
    no update pays page faults its predicted cost does not hold (valencia: a batch of 1 742
    entries took 888 faults and 6.4 ms where 2.6 ms were predicted).  These are settings of
    the whole process; 0 leaves ``malloc`` as it is.  At most :data:`~._heap.MAX_RESERVE_MB`."""
    gps_link: bool = True
    """A new pose with a GPS reading in its frame hangs from the earth (its tree link is the
    reading), as GPS readings do in the whole-graph tree (III-G).  The tree's depth is then
    bounded by the spacing of the readings rather than growing with the drive, so GPS domains
    stay one node long: no GPS frame pays for a path to the start (valencia_gps: 180 ms frames
    where the path pool doubled).  The pose's odometry carries the path through the earth to
    the previous subtree.  Cost: the subtrees are held to each other by stiff odometry only,
    which the hybrid steps relax slowly (valencia_gps, first 1000 frames, no budget: 34x the
    optimum against 1.3x with False)."""
    junctions: bool = True
    """Relax the constraints that join a pose to the map in its frame (its odometry, its loop
    closures to earlier poses and its GPS readings, when their stiffness differs by more than
    ``JUNCTION_RATIO``) together as one batch, every time any of them is relaxed.  With the
    ``"oldest"`` tree a revisiting pose hangs from a soft loop closure while its stiff
    odometry carries the long path around the loop; relaxed one at a time, the two only trade
    the loop's error through the junction pose, at a rate of about (loop information) /
    (odometry information) per update (valencia: 1e-3 in rotation, so the estimate stayed
    100-1000x above the optimum).  The batch solves them jointly."""
    loop_batch: int = 32
    """Constraints in the batch of a loop closure's neighbours (0: none).  A new relative
    constraint whose path is long (a loop closure) is relaxed by one update that moves the
    subtrees of its path's nodes; the older constraints through those nodes enter its hybrid
    Hessian only by their diagonal blocks, and when the update hands them more χ² than it
    removed, the frame relaxes the new constraints with the neighbours of largest χ²
    together, as one batch that holds each of them exactly (III-G), when it fits the budget.
    valencia_gps, one loop closure after another, the worker's answer adopted before each:
    the frame of the loop at 1.2-4x the prefix optimum with 0, 1.01-1.14x with 32.  The
    batch costs O(entries + (6 loop_batch)^3)."""
    local_size: int = 0
    """Local solve (III-G): relax the newest ``local_size`` relative constraints together as
    one batch in every frame (0: off).  Bounded: the batch costs O(entries + (6 local_size)^3)."""

    background_refine: bool = True
    """Staying accurate: a worker *process* keeps an incremental exact solver of everything
    shipped to it (:mod:`.worker`) and each of its answers (the optimum of the map it holds) is
    adopted in the next :meth:`OnlineSolver.update`.  The frames pay only for shipping the new
    data and one copy of the map's local transforms per answer; the worker takes a CPU core of
    its own.  Results then depend on timing (see ``background_join``).  On by default: without
    it the estimate is what the bounded single-constraint updates make of the map (M3500_isam,
    5 ms per frame: 1.23x the prefix optimum at the worst checkpoint, against 1.01x with an
    incremental exact solver adopted).  ``background_refine=False`` (CLI:
    ``replay --no-background-refine``) runs without a process: deterministic, one core."""
    background_join: int = 0
    """With ``background_refine``: 0 adopts whatever result is ready (asynchronous, results
    depend on timing); K > 0 is the deterministic mode: every K-th update ships the map and
    asks for its optimum, and the update K frames later waits for that answer (however long
    the solve takes) and adopts it, so runs are reproducible as long as the worker's requests
    stay within its time bounds (a request stops at 1 s, and one of 0.25 s has LM measured:
    past those, what an answer holds depends on the machine's speed; a request with new data
    makes one update cycle)."""
    background_tail_only: bool = False
    """With ``background_refine``: once a result has been adopted, spare-time updates go only
    to the constraints added after its snapshot (the adopted optimum is not perturbed by the
    single-constraint steps, whose fixed point is not the optimum).  Off by default: a new
    loop closure in the tail needs the older constraints to settle around it too, which
    only spare-time updates of all constraints do (M3500_isam, 5 ms, ``background_join=100``:
    worst checkpoint 1.13x the prefix optimum with False, 1.48x with True).  See
    ``background_hold`` for the end of a stream."""
    background_hold: bool = True
    """With ``background_refine``: while the adopted optimum is also the optimum of everything
    added since, no spare-time updates are made, so it is kept as it is (the single steps'
    fixed point is not the optimum: M3500_isam, 100 frames after the end,
    ``background_join=100``: 1.002x with hold, drifting to 1.03x without).  That is the case
    when every constraint added after the result's snapshot is the tree link of a pose added
    after it and the only constraint through that pose (the robot drove on with odometry or
    GPS-linked poses and closed no loop: the new poses are placed exactly, nothing else moves),
    in particular when nothing was added (the robot stands still or the stream ended).  Nor
    are they made, asynchronously (``background_join=0``) and without
    ``background_tail_only``, while a long loop closure added after the result's snapshot
    waits for the worker's answer that holds it (:data:`~hybridpgo.online._link.LONG_LOOP`
    path nodes, for at most :data:`~hybridpgo.online._link.LONG_LOOP_WAIT` frames): after
    such a closure the single steps of the older constraints push the map away from the
    optimum.  Nor, likewise, in an :meth:`~OnlineSolver.update` with nothing new to ship to
    the worker while the request outstanding holds everything added (the robot stopped or
    the stream ended: the answer on its way is the optimum of the whole map, and the single
    steps meanwhile only push the map away from it), for at most as many frames and seconds;
    :meth:`~OnlineSolver.idle` keeps its spare time (it also adopts the answer when it
    comes).  The checks are O(constraints added since the result's snapshot) per frame."""
    background_rebase: bool = True
    """With ``background_refine``: when a result is adopted, the constraints added after its
    snapshot are queued to be relaxed again as new ones (on top of the optimum, in arrival
    order), so what the frames had made of them is redone rather than left inconsistent."""
    background_iterations: int = 20
    """Most LM iterations of one background solve (an unconverged solve is continued)."""


    def __post_init__(self) -> None:
        check_float("damping", self.damping, positive=False)
        if self.step not in STEP_NAMES:
            raise ValueError(f"step must be one of {', '.join(STEP_NAMES)}, got {self.step!r}")
        check_robust(self.robust, self.robust_scale, self.robust_delta)
        check_int("gps_batch_size", self.gps_batch_size, 1)
        if self.tree not in ONLINE_TREES:
            raise ValueError(f"tree must be one of {', '.join(ONLINE_TREES)}, got {self.tree!r}")
        check_float("tau_new", self.tau_new, positive=True)
        check_float("tau_old", self.tau_old, positive=True)
        check_int("recent", self.recent, 0)
        check_int("window", self.window, 0)
        check_int("local_size", self.local_size, 0)
        check_int("loop_batch", self.loop_batch, 0)
        if self.loop_batch > 64:
            raise ValueError(f"loop_batch must be at most 64 (its dense system is "
                             f"(6 loop_batch)^2), got {self.loop_batch}")
        if self.reserve_poses is not None:
            check_int("reserve_poses", self.reserve_poses, 1)
        check_int("heap_reserve_mb", self.heap_reserve_mb, 0)
        if self.heap_reserve_mb > MAX_RESERVE_MB:
            raise ValueError(f"heap_reserve_mb must be at most {MAX_RESERVE_MB} (MiB written "
                             f"once and kept), got {self.heap_reserve_mb}")
        check_int("background_join", self.background_join, 0)
        check_int("background_iterations", self.background_iterations, 1)
        if self.local_size > 64:
            raise ValueError(f"local_size must be at most 64 (its dense system is "
                             f"(6 local_size)^2), got {self.local_size}")
