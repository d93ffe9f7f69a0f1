"""The online mode: a real-time back end fed pose by pose (paper I, III-E/G, IV).

:class:`OnlineSolver` takes poses with their odometry, loop closures and GPS readings as they
arrive, and :meth:`~OnlineSolver.update` relaxes them within a time budget per frame
(docs/mathematics.md, "Online streams").  The map lives in a :class:`~.store.MapStore` whose
arrays grow without copies; the updates are the whole-graph solver's relaxation loop
(:mod:`hybridpgo.solvers.hybrid._sweep`) under its admission policy:

* **update(budget)** integrates what arrived (places the new poses in the tree, lays the new
  constraints' paths), relaxes the new constraints first (odometry, then loop closures, GPS
  batched, junction groups as one batch), optionally solves the newest constraints together as
  one batch (the local solve, III-G: the far poses are held by their 𝔅(H) blocks), and spends
  the rest of the budget on older constraints, largest last χ² first among a bounded candidate
  set (the newest constraints, which act near the robot, and a window that cycles through
  all).  An update is started only when its predicted cost fits before the deadline.
* **The frame's budget** covers its ``add_*`` calls too (their cycles are charged to the next
  update); what does not fit stays queued for the next frames, in arrival order.  Only the
  first new constraint of a frame is started whatever its cost (alone, by a single update,
  when its junction group's batch does not fit; in slices over as many frames as it takes,
  when that single update is long and does not fit either: :mod:`~..solvers.hybrid._slices`,
  :meth:`~OnlineSolver._begin_sliced`), and a group whose batch no frame could hold
  is relaxed member by member wherever it comes; constraints queued again
  after an adopted answer (relaxed before) start only when they fit.  Building the
  first solver of a process freezes the objects alive then (:func:`gc.freeze`), so no
  garbage collection walks the compiled kernels, and a frame's work (``add_*``,
  :meth:`~OnlineSolver.update`, :meth:`~OnlineSolver.pose`) runs with automatic garbage
  collection held off (:func:`~._frame.uncollected`): a collection that falls due meanwhile
  runs at the next allocation outside the solver (the application's, or :meth:`idle`'s).
* **Staying accurate** (``OnlineConfig.background_refine``, on by default): a worker process
  keeps the whole map at its optimum with an incremental exact solver and each answer is
  adopted in one copy (:mod:`._link`, :mod:`.worker`).  After relaxing its new constraints, a
  frame with a budget waits for the answer to its own data when the worker's recent round
  trips say it can come and be adopted before the deadline
  (:meth:`~._link.WorkerLink.settle`); the map is then the optimum of everything added.
* **Outliers** (``OnlineConfig.robust="auto"``, the default): the worker screens its answers
  for false loop closures and GPS fixes; the constraints it rejects get zero whitening and no
  share of 𝔅(H) in the frames (:meth:`~.store.MapStore.set_rejected`, :meth:`outliers`).

Constraints are numbered in arrival order at the API (relative edges and GPS readings each
from 0); inside, the store's one index (edges, then GPS readings at the edge capacity).
"""

from __future__ import annotations

import dataclasses
import gc
import os
import time
import weakref
from typing import Any

import numpy as np
import numpy.typing as npt

from .. import _cost
from .._numba import cycles_per_second, read_cycles
from ..errors import FormatError, GraphError
from ..graph import FloatArray, PoseGraph, planar_data
from ..solvers.config import check_int
from ..solvers.hybrid import _admission as adm
from ..solvers.hybrid import _slices
from ..solvers.hybrid._sweep import group_cost, loop_kernel, run_loop
from ..solvers.hybrid.problem import NUM_COUNTS, Count, StepKind, Update
from ..solvers.hybrid.solver import STEP_KINDS, ensure_compiled
from . import _heap
from ._frame import MAX_BUDGET_S as MAX_BUDGET_S
from ._frame import (
    NO_DEADLINE,
    READ_LEVEL_S,
    RESERVE_S,
    FrameReport,
    charged,
    check_budget,
    uncollected,
)
from ._link import WorkerLink
from ._validate import as_pose, check_id, whitening
from .config import OnlineConfig
from .store import MapStore

#: Requeued constraints a frame drops at most when they do not fit
#: (:meth:`OnlineSolver._requeued`).
MAX_DROPS = 4
#: A single update of the first new constraint runs in slices from this many domain nodes
#: whatever the cost model predicts (its rare long paths miss the cache more than the model's
#: average); from one slice's nodes (:data:`~..solvers.hybrid._slices.SLICE`) when it is
#: predicted not to fit before the deadline (the loop would start it whatever its cost).
#: Spare time slices the long ones only.
MIN_SLICED = 4 * _slices.SLICE
#: A new relative constraint whose path has at least this many nodes (a loop closure: the
#: revisiting pose's odometry carries the path around the loop) has its neighbours measured
#: (:meth:`OnlineSolver._loop_neighbours`).
LOOP_MIN_PATH = 4
#: The batch of a loop's neighbours runs when they gained more χ² than this share of what the
#: new constraints lost.  Measured on twelve of valencia_gps's loops, each frame starting
#: from the worker's optimum: 0.51-11 in the five frames whose updates raised the map to
#: 1.1-4x the prefix optimum; 0.17-0.66 in six of the seven that left it within 1.03x, 7.4 in
#: the seventh (where the batch runs in such a frame, it moved E by -0.011 to +0.011 of the
#: optimum).
LOOP_SHARE = 0.5
#: Cycles per path entry of the scan for a loop's neighbours (a bound: 0.8-0.9 ns measured
#: on valencia and paris2).
SCAN_CYCLES = 8.0
#: Cycles per path entry of a neighbour's χ² (a bound: 190 ns measured on valencia).
CHI2_CYCLES = 1000.0


#: Seconds a frame must have left before its deadline to write ahead into the path pool
#: (:meth:`~.store.MapStore.prefault`: 16-18 page faults, 0.03 ms on an idle host; in one
#: benchmark frame on a busy one, 255 faults took about 7 ms).
PREFAULT_CYCLES_S = 1e-3


def _late(deadline: np.uint64, cycles: float) -> bool:
    """Would ``cycles`` more of work end past the deadline (never without one)?"""
    return deadline != NO_DEADLINE and float(read_cycles()) + cycles > float(deadline)


@dataclasses.dataclass(slots=True)
class _Hood:
    """A new loop closure's neighbours (:meth:`OnlineSolver._loop_neighbours`)."""

    c: int
    """The new relative constraint of the longest path."""
    new: npt.NDArray[np.int64]
    """The frame's new (and queued again) relative constraints."""
    near: npt.NDArray[np.int64]
    """The older constraints whose paths share a node with c's."""
    before: float
    """Their χ² before the frame's updates."""
    new_before: float
    """The new constraints' χ² before their updates."""
    entries: int
    """Path entries of the neighbours and the new constraints (a χ² measurement's work)."""


@dataclasses.dataclass(slots=True)
class _Sliced:
    """An update in slices under way (:mod:`~..solvers.hybrid._slices`)."""

    lu: npt.NDArray[np.int64]
    lf: npt.NDArray[np.float64]
    wk: Any
    adopted: int
    """The worker's adoptions when it began (-1: no worker)."""
    new: bool
    """The first new constraint (else an older one, from spare time)."""
    tau: float
    group: int
    """Its junction group (-1: none) and the group's stamp when it began: a changed stamp
    means its group's batch relaxed it meanwhile."""
    stamp: int
    spent: int = 0
    """Cycles of its slices so far: the update's cycles once done."""


class OnlineSolver:
    """A hybrid-Hessian back end that grows with the map (module docstring).

    Poses are identified by the caller's integer ids.  Constraints are kept in arrival order:
    relative constraints ("edges", the odometry of :meth:`add_pose` included) and GPS readings.
    Every ``add_*`` call validates its input first and changes nothing when it raises.
    """

    def __init__(self, config: OnlineConfig | None = None) -> None:
        self.config = cfg = config or OnlineConfig()
        self.compile_seconds = ensure_compiled() + _ensure_online_compiled()
        if cfg.heap_reserve_mb:
            _heap.keep_resident(cfg.heap_reserve_mb)
        self._index: dict[int, int] = {}
        self.frame = 0
        """Number of :meth:`update` calls so far."""
        robust = (_cost.robust_kind(cfg.kernel, cfg.robust_delta), float(cfg.robust_delta))
        self._store = MapStore(cfg.reserve_poses, robust, cfg.gps_batch_size)
        self._wk: Any = self._store.scratch(None).wk
        self._cursor = 0
        self._gps_cursor = 0
        self._stamp = 0  # one per call of the relaxation loops (junction groups: once each)
        self._input_cycles = 0  # cycles spent in add_* since the last update (its frame's)
        # the update in slices under way (_slices: progress arrays, its workspace, the
        # worker's adoptions when it began), and the counts stats() reports
        self._sliced: _Sliced | None = None
        self._slice_wk: Any = None
        self._sliced_done = self._sliced_cancelled = 0
        self._link: WorkerLink | None = None
        self._finalizer: weakref.finalize[Any, Any] | None = None
        if cfg.background_refine:
            spec = (cfg.robust if cfg.robust in ("auto", "none")
                    else f"{cfg.kernel}:{cfg.robust_delta!r}")
            self._link = WorkerLink(cfg.background_iterations, spec)
            # stops the worker when the solver is collected or at exit, whatever comes first
            self._finalizer = weakref.finalize(self, self._link.close)

    # ----------------------------------------------------------------- life cycle
    def close(self) -> None:
        """Stop the background worker (if any); idempotent.  The solver stays usable, without
        background refinement."""
        if self._finalizer is not None:
            self._finalizer()
        self._link = None
        self._finalizer = None

    def __enter__(self) -> OnlineSolver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- sizes
    @property
    def store(self) -> MapStore:
        """The map's arrays (:class:`~.store.MapStore`: the tree, the paths, 𝔅(H), the
        priorities) for inspection; change them only through this class."""
        return self._store

    @property
    def worker_pid(self) -> int | None:
        """The background worker's process id (None: no worker, or closed)."""
        return None if self._link is None else self._link.refiner.pid

    @property
    def num_poses(self) -> int:
        return self._store.n

    @property
    def num_edges(self) -> int:
        """Relative constraints added (odometry included)."""
        return self._store.m

    @property
    def num_gps(self) -> int:
        return self._store.g

    @property
    def num_constraints(self) -> int:
        return self._store.m + self._store.g

    @property
    def backlog(self) -> int:
        """Constraints added but not yet relaxed once."""
        return self._store.q_tail - self._store.q_head

    def pose_ids(self) -> npt.NDArray[np.int64]:
        """(N,) the pose ids in arrival order (the rows of :meth:`estimate`)."""
        return self._store.ids[: self._store.n].copy()

    # ----------------------------------------------------------------- input
    def _pose_index(self, pose_id: object, what: str) -> int:
        i = check_id(pose_id, what)
        if i not in self._index:
            raise GraphError(f"{what}: unknown pose id {i}")
        return self._index[i]

    @charged
    def add_pose(self, pose_id: int, parent: int | None = None, measurement: object = None,
                 information: object = None) -> None:
        """Add a pose with its odometry ``Z = X_parent^-1 X_pose`` and its (6, 6) information.

        The first pose has no parent: its ``measurement`` (default identity) is its initial pose
        in the earth frame and ``information`` must be None.  ``measurement`` is a (4, 4)
        homogeneous matrix or a pair ``(R (3, 3), t (3,))``; information is over (rho, phi).

        Raises
        ------
        GraphError
            Duplicate id, unknown parent, a second pose without parent, a measurement that is
            not a finite rigid transform, or information that is not SPD.
        """
        i = check_id(pose_id, "add_pose: pose id")
        what = f"add_pose({i})"
        if i in self._index:
            raise GraphError(f"{what}: duplicate pose id {i}")
        st = self._store
        if parent is None:
            if st.n > 0:
                raise GraphError(f"{what}: a pose needs an odometry parent (only the first pose "
                                 "starts the map)")
            if information is not None:
                raise GraphError(f"{what}: the first pose has no odometry, so no information")
            rot, trans = (np.eye(3), np.zeros(3)) if measurement is None else as_pose(
                measurement, f"{what}: initial pose")
            p = st.append_pose(i)
            self._index[i] = p
            st.first_rot, st.first_trans = rot, trans
            return
        a = self._pose_index(parent, f"{what}: parent")
        if measurement is None or information is None:
            raise GraphError(f"{what}: odometry needs a measurement and an information")
        rot, trans = as_pose(measurement, f"{what}: odometry")
        info, lt = whitening(information, 6, f"{what}: odometry")
        p = st.append_pose(i)  # validated: mutate
        self._index[i] = p
        st.odom[p] = st.m
        self._append_edge(a, p, rot, trans, info, lt)

    @charged
    def add_constraint(self, a: int, b: int, measurement: object, information: object) -> None:
        """Add a relative constraint (loop closure) ``Z = X_a^-1 X_b`` between known poses.

        Raises
        ------
        GraphError
            Unknown pose, ``a == b``, a measurement that is not a finite rigid transform,
            information that is not SPD, or the same constraint (endpoints, measurement and
            information) added before.
        """
        what = f"add_constraint({a!r}, {b!r})"
        ia = self._pose_index(a, f"{what}: a")
        ib = self._pose_index(b, f"{what}: b")
        if ia == ib:
            raise GraphError(f"{what}: a constraint needs two different poses")
        rot, trans = as_pose(measurement, f"{what}: measurement")
        info, lt = whitening(information, 6, what)
        st = self._store
        for e in st.edges_between(ia, ib):
            if (np.array_equal(st.edge_rot[e], rot) and np.array_equal(st.edge_trans[e], trans)
                    and np.array_equal(st.edge_info[e], info)):
                raise GraphError(f"{what}: duplicate constraint (edge {e} has the same poses, "
                                 "measurement and information)")
        self._append_edge(ia, ib, rot, trans, info, lt)

    def _append_edge(self, a: int, b: int, rot: FloatArray, trans: FloatArray,
                     info: FloatArray, lt: FloatArray) -> None:
        self._store.push(self._store.append_edge(a, b, rot, trans, info, lt))

    @charged
    def add_gps(self, pose_id: int, xyz: object, information: object) -> None:
        """Add a position reading ``g`` (earth frame, metres) of a known pose, (3, 3) information.

        Raises
        ------
        GraphError
            Unknown pose, a non-finite position, or information that is not SPD.
        """
        what = f"add_gps({pose_id!r})"
        n = self._pose_index(pose_id, what)
        try:
            pos = np.array(xyz, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise GraphError(f"{what}: position is not numeric: {exc}") from exc
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise GraphError(f"{what}: position must be 3 finite numbers, got {xyz!r}")
        info, lt = whitening(information, 3, what)
        self._store.push(self._store.append_gps(n, pos, info, lt))

    # ----------------------------------------------------------------- integration
    def _integrate(self) -> None:
        """Place the new poses in the tree and lay the new constraints' paths (O(new work))."""
        st = self._store
        if st.placed < st.n:
            cfg = self.config
            st.place_poses(cfg.tree, cfg.gps_link, cfg.junctions)
        st.lay_paths()

    # ----------------------------------------------------------------- update
    @uncollected
    def update(self, budget_s: float | None = None, max_updates: int | None = None
               ) -> FrameReport:
        """One frame: integrate what arrived, relax new constraints, then older ones.

        Parameters
        ----------
        budget_s : float, optional
            Time budget of the frame (seconds, > 0): the ``add_*`` calls since the last update
            count against it, and the time to read the newest pose after it (:meth:`pose`,
            O(its tree depth)) is kept from it, so the frame's whole work stays within it.  No
            update is started whose predicted cost would pass it.  None: no time limit.
        max_updates : int, optional
            Start at most this many updates (counted like the budget; with ``budget_s=None``
            the frame's work does not depend on timing, so runs are reproducible).

        With neither limit, every new constraint and every spare-time candidate is relaxed once.
        A frame with 1 ms of its budget left (or without a budget) then writes 64 KiB of its
        store of constraint paths ahead of the paths laid so far, so that the memory of a long
        path laid later is allocated already (docs/mathematics.md, "No page faults in
        updates").

        Raises
        ------
        ValueError
            A budget that is not a finite number > 0, or a negative ``max_updates``; nothing
            is changed.
        """
        t0 = time.perf_counter()
        deadline = self._deadline(budget_s, self._input_cycles)
        self._input_cycles = 0
        if max_updates is not None:
            check_int("max_updates", max_updates, 0)
        limit = (1 << 62) if max_updates is None else max_updates
        self._integrate()
        deadline = self._keep_for_read(deadline)
        quiet = False
        if self._link is not None:
            cfg = self.config
            st = self._store
            # nothing placed or laid since the link last shipped (the robot stands, or the
            # stream ended)
            quiet = self._link.sent == (st.placed, st.m_laid, st.g_laid)
            self._link.step(st, self.frame, cfg.background_join, cfg.background_rebase)
        report = self._work(deadline, limit, time.perf_counter() - t0, first=True, quiet=quiet)
        if deadline == NO_DEADLINE or not _late(deadline,
                                                PREFAULT_CYCLES_S * cycles_per_second()):
            self._store.prefault()  # fresh pages of the path pool, while there is time
        self.frame += 1
        return report._replace(seconds=time.perf_counter() - t0)

    def idle(self, budget_s: float) -> int:
        """Use ``budget_s`` seconds between frames for the back end: adopt the worker's
        results, relax what is still queued, then older constraints, until the time is used or
        nothing is left to do (the adopted optimum holds, ``background_hold``); then write the
        store of constraint paths ahead of the paths laid so far while time is left (as
        :meth:`update` does).  Returns the
        updates made.  A stream at a real rate calls it after each frame's :meth:`update` with
        the time until the next frame; a frame's own work stays bounded by its budget.

        Raises
        ------
        ValueError
            A budget that is not a finite number > 0.
        """
        t0 = time.perf_counter()
        deadline = self._deadline(budget_s)
        self._integrate()
        done = 0
        while np.uint64(read_cycles()) < deadline:
            if self._link is not None and self.config.background_join == 0:
                self._link.step(self._store, self.frame, 0, self.config.background_rebase)
            rep = self._work(deadline, 1 << 62, time.perf_counter() - t0)
            if rep.new + rep.old + rep.local_nodes == 0:
                break
            done += rep.new + rep.old
        while (not _late(deadline, PREFAULT_CYCLES_S * cycles_per_second())
               and self._store.prefault()):
            pass
        return done

    def _deadline(self, budget_s: float | None, spent: int = 0) -> np.uint64:
        """The cycle count at which a call with this budget stops starting updates, ``spent``
        cycles of it being used already; the budget's cycles become the span the admission
        policy lets a batch take (``Admission.span``)."""
        c0 = int(read_cycles()) - spent
        if budget_s is None:
            self._store.span[0] = np.inf
            return NO_DEADLINE
        spare = max(check_budget(budget_s) - RESERVE_S, 0.0)
        self._store.span[0] = spare * cycles_per_second()
        return np.uint64(max(c0 + int(spare * cycles_per_second()), 0))

    def _keep_for_read(self, deadline: np.uint64) -> np.uint64:
        """The deadline less the predicted cost of reading the newest pose after the frame
        (:meth:`pose`: O(its tree depth), :data:`~._frame.READ_LEVEL_S` per level)."""
        st = self._store
        if deadline == NO_DEADLINE or st.placed == 0:
            return deadline
        keep = int(st.depth[st.placed]) * READ_LEVEL_S * cycles_per_second()
        return np.uint64(max(int(deadline) - int(keep), 0))

    def _work(self, deadline: np.uint64, limit: int, elapsed: float, first: bool = False,
              quiet: bool = False) -> FrameReport:
        """Requeued constraints, new constraints in arrival order, the local solve, then spare
        time (one call of the relaxation loop each, under the admission policy; ``first``: the
        frame's own work, :meth:`_requeued`; ``quiet``: the frame added nothing,
        :meth:`_spare_time`)."""
        cfg = self.config
        st = self._store
        counts = np.zeros(NUM_COUNTS, np.int64)
        self._stamp += 1
        stamp = self._stamp
        hood = (self._loop_neighbours(deadline) if cfg.loop_batch and limit > 0
                and self._sliced is None else None)
        n_re = (self._requeued(self._keep_for_new(deadline), counts, limit, stamp, first)
                if st.requeue.size else 0)
        limit -= int(counts[Count.DONE])
        done0 = int(counts[Count.DONE])
        forced = True
        n_sliced = self._check_sliced()
        sl = self._sliced
        if limit > 0 and ((sl is not None and sl.new) or self._begin_sliced(deadline)):
            n_sliced += self._advance_sliced(deadline, counts)
            forced = False  # the frame's progress on the first new constraint
        prob, state, pol = st.views()
        sc = st.scratch(self._wk)
        self._wk = sc.wk
        # a new constraint relaxed in slices stays first in the queue until done
        behind = self._sliced is not None and self._sliced.new
        n_new = run_loop(loop_kernel(True, False, False, True), prob, state, sc,
                         st.pending()[int(behind):], cfg.tau_new, cfg.damping,
                         int(STEP_KINDS[cfg.step]), cfg.gps_batch_size, 0, deadline, counts,
                         True, pol, stamp, limit - (int(counts[Count.DONE]) - done0),
                         force_first=forced, skip=False)
        st.pop(n_new, behind)
        n_new += n_sliced + self._check_sliced()
        limit -= int(counts[Count.DONE]) - done0
        local_nodes = 0
        if hood is not None and limit > 0:
            local_nodes = self._loop_batch(hood, deadline, counts)
            if local_nodes:
                limit -= 1
        if cfg.local_size and limit > 0:
            nodes = self._local_solve(deadline, counts, limit)
            if nodes:
                local_nodes += nodes
                limit -= 1
        link = self._link
        if first and link is not None and cfg.background_join == 0 and deadline != NO_DEADLINE:
            # the worker's answer to this frame's data, when it can come in the frame's time
            until = (time.perf_counter()
                     + (int(deadline) - int(read_cycles())) / cycles_per_second())
            link.settle(st, self.frame, cfg.background_rebase, until)
        old = n_re + self._spare_time(deadline, counts, limit, stamp, quiet)
        return FrameReport(n_new, self.backlog, old, local_nodes, int(counts[Count.CAPPED]),
                           int(counts[Count.REJECTED]), int(counts[Count.SKIPPED]), elapsed)

    def _loop_neighbours(self, deadline: np.uint64) -> _Hood | None:
        """Before a frame's new constraints are relaxed: when one of them (or of the
        constraints queued again after an adopted answer, :meth:`_requeued`) is a relative
        constraint of at least :data:`LOOP_MIN_PATH` path nodes (the longest is taken), its
        neighbours (:func:`~..solvers.hybrid._admission.crossing`: the older relative
        constraints whose residuals its update changes; GPS readings are not measured),
        their χ² and the new constraints' χ² now, for :meth:`_loop_batch`.  None when there
        is none, or when the scan (O(path entries)) or the two measurements would not leave
        the first new constraint its predicted time."""
        st = self._store
        q = np.concatenate([st.requeue, st.pending()])
        rel = q[q < st.cap_m]
        if not rel.size:
            return None
        lens = st.ptr[rel + 1] - st.ptr[rel]
        c = int(rel[int(np.argmax(lens))])
        if int(lens.max()) < LOOP_MIN_PATH:
            return None
        first = adm.predict(st.model, int(lens[0]), False)  # the first new constraint's
        if _late(deadline, first + 2.0 * int(st.ptr[st.m_laid]) * SCAN_CYCLES):
            return None
        prob, state, _ = st.views()
        mark = np.zeros(st.placed + 1, np.bool_)
        out = np.empty(st.m_laid, np.int64)
        k = int(adm.crossing(prob, st.m_laid, c, st.rejected, mark, out))
        near = out[:k]
        near = near[~np.isin(near, rel)]
        # their χ² now and after the frame's updates (O(their path entries) each)
        entries = int(np.sum(st.ptr[near + 1] - st.ptr[near])) + int(np.sum(lens))
        if _late(deadline, first + 2.0 * entries * CHI2_CYCLES):
            return None
        sc = st.scratch(self._wk)
        self._wk = sc.wk
        chi = np.empty(max(near.size, rel.size))
        before = float(adm.edge_chi2s(prob, state, near, sc.wk, chi))
        new_before = float(adm.edge_chi2s(prob, state, rel, sc.wk, chi))
        return _Hood(c, rel, near, before, new_before, entries)

    def _loop_batch(self, hood: _Hood, deadline: np.uint64,
                    counts: npt.NDArray[np.int64]) -> int:
        """After the new constraints were relaxed: when the neighbours of the loop
        (:meth:`_loop_neighbours`) gained more χ² than :data:`LOOP_SHARE` of what the new
        constraints lost (the update pushed the loop's error onto constraints its hybrid
        Hessian holds only by their diagonal blocks 𝔅(H); on valencia_gps such frames raised
        the map from the optimum to 1.1-4x it), the new constraints and the
        :attr:`~.config.OnlineConfig.loop_batch` neighbours of largest χ² are relaxed
        together as one batch (III-G), when it fits before the deadline: the batch holds each
        of them exactly.  The neighbours' measured χ² becomes their spare-time priority.
        Nothing is measured when the measurement's predicted cost no longer fits before the
        deadline (the frame's other new constraints took the time).  Returns the batch's
        union nodes (0: none)."""
        st = self._store
        cfg = self.config
        q = np.concatenate([st.requeue, st.pending()])
        if np.isin(hood.c, q) or self._sliced is not None:
            return 0  # not relaxed in this frame
        if _late(deadline, hood.entries * CHI2_CYCLES):
            return 0  # the frame's other new constraints took the time
        done = hood.new[~np.isin(hood.new, q)]
        prob, state, _ = st.views()
        sc = st.scratch(self._wk)
        self._wk = sc.wk
        chi = np.empty(max(hood.near.size, done.size))
        new_after = float(adm.edge_chi2s(prob, state, done, sc.wk, chi))
        after = float(adm.edge_chi2s(prob, state, hood.near, sc.wk, chi))
        st.chi2[hood.near] = chi[: hood.near.size]
        if not after - hood.before > LOOP_SHARE * (hood.new_before - new_after):
            return 0
        k = max(cfg.loop_batch - done.size, 0)
        worst = hood.near[np.argsort(-chi[: hood.near.size], kind="stable")[:k]]
        cs = np.concatenate([done, worst])
        return max(int(adm.local_batch(prob, state, cs, cfg.tau_new, cfg.damping, deadline,
                                       st.model, st.slot, st.xb, st.nodes_buf, counts,
                                       st.depth)), 0)

    def _keep_for_new(self, deadline: np.uint64) -> np.uint64:
        """The deadline of the requeued constraints: ``deadline`` less the predicted cost of
        the first new constraint's least work (its single update, or one slice of a longer
        one), which the frame does whatever its cost; without it, requeued updates that fill
        the budget leave that work to end the frame late."""
        st = self._store
        q = st.pending()
        if deadline == NO_DEADLINE or not q.size:
            return deadline
        c = int(q[0])
        d = min(int(st.ptr[c + 1] - st.ptr[c]), _slices.SLICE)
        keep = int(adm.predict(st.model, d, c >= st.cap_m))
        return np.uint64(max(int(deadline) - keep, 0))

    def _begin_sliced(self, deadline: np.uint64) -> bool:
        """Start relaxing the first new constraint in slices (:mod:`~..solvers.hybrid._slices`)
        when it is a relative constraint (under the Woodbury step) of at least
        :data:`MIN_SLICED` domain nodes, or of at least one slice's whose single update is
        predicted not to fit, that the loop would relax by a single update: not in a junction
        group, or in one whose batch is predicted not to fit.  The slices are timed, so a long
        update never ends the frame late by more than one slice, whatever the cost model
        predicts for it (its rare long paths miss the cache more than the model's average);
        one that fits is done in the same frame.  True when begun."""
        st = self._store
        q = st.pending()
        if (deadline == NO_DEADLINE or not q.size or q[0] >= st.cap_m
                or STEP_KINDS[self.config.step] != StepKind.WOODBURY):
            return False
        c = int(q[0])
        d = int(st.ptr[c + 1] - st.ptr[c])
        if d < _slices.SLICE or (d < MIN_SLICED and float(read_cycles())
                                 + adm.predict(st.model, d, False) <= float(deadline)):
            return False
        prob, _, pol = st.views()
        grp = int(st.group_of[c])
        if grp >= 0:  # the loop relaxes its junction group as one batch when it fits
            # (with one slice to spare: the loop decides a moment later, and when the batch
            # no longer fits then, it relaxes this member alone by one single update)
            pred = group_cost(prob, pol, grp) + adm.predict(st.model, _slices.SLICE, False)
            if pred <= st.span[0] and float(read_cycles()) + pred <= float(deadline):
                return False
        if self._sliced is not None:  # an older constraint's, from spare time: new ones first
            self._give_up_sliced()
        self._start_sliced(c, d, True)
        return True

    def _start_sliced(self, c: int, d: int, new: bool) -> None:
        """Begin the update in slices of constraint c (``d`` domain nodes; ``new``: the first
        new constraint, else an older one relaxed in spare time)."""
        wk = self._slice_wk
        if wk is None or wk.x.shape[0] < d:
            wk = self._slice_wk = self._store.scratch(None).wk
        st = self._store
        lu, lf = _slices.new_state()
        prob, _, _ = st.views()
        _slices.begin(prob, c, lu, lf)
        grp = int(st.group_of[c])
        self._sliced = _Sliced(lu, lf, wk, -1 if self._link is None else self._link.adopted,
                               new, self.config.tau_new if new else self.config.tau_old, grp,
                               int(st.group_stamp[grp]) if grp >= 0 else -1)

    def _give_up_sliced(self) -> None:
        self._sliced = None
        self._sliced_cancelled += 1

    def _check_sliced(self) -> int:
        """Whether the update in slices can go on; when not, it is given up.  It cannot when
        its junction group's batch relaxed its constraint meanwhile (its own step would correct
        the same residual a second time: a new constraint then leaves the queue, relaxed), when
        the worker's answer was adopted since it began (its step belongs to the poses before),
        or when its constraint's domain changed (a new constraint then stays first in the
        queue, to be relaxed afresh).  Returns the new constraints relaxed by their group's
        batch (0 or 1)."""
        sl = self._sliced
        if sl is None:
            return 0
        st = self._store
        q = st.pending()
        head = sl.new and q.size > 0 and q[0] == sl.lu[_slices.C]
        if sl.group >= 0 and int(st.group_stamp[sl.group]) != sl.stamp:
            self._give_up_sliced()
            if head:
                st.pop(1)
                return 1
            return 0
        prob, _, _ = st.views()
        if not ((self._link is None or self._link.adopted == sl.adopted)
                and (head or not sl.new) and bool(_slices.valid(prob, sl.lu))):
            self._give_up_sliced()
        return 0

    def _advance_sliced(self, deadline: np.uint64, counts: npt.NDArray[np.int64]) -> int:
        """Run the update in slices until ``deadline`` (at least one slice); once done, a new
        constraint leaves the queue.  Returns the constraints done (0 or 1)."""
        sl = self._sliced
        assert sl is not None
        lu, lf, wk = sl.lu, sl.lf, sl.wk
        st = self._store
        prob, state, pol = st.views()
        whole = lu[_slices.PHASE] == _slices.SETUP
        t0 = read_cycles()
        done = _slices.advance(prob, state, wk, lu, lf, sl.tau, self.config.damping, deadline)
        sl.spent += int(read_cycles()) - int(t0)
        if not done:
            return 0
        c = int(lu[_slices.C])
        if whole:  # done in one call: the cost of a single update, for the cost model
            adm.learn(st.model, int(lu[_slices.D]), float(sl.spent), False)
        st.cycles[c] = sl.spent  # its update's cycles, as the loop records a single's
        pol.chi2[c] = float(np.dot(wk.r, wk.r))  # its χ² before the update, as a single's
        status = int(lu[_slices.STATUS])
        if status == Update.CAPPED:
            counts[Count.CAPPED] += 1
        elif status == Update.REJECTED:
            counts[Count.REJECTED] += 1
        counts[Count.DONE] += 1
        if sl.new:
            st.pop(1)
        self._sliced = None
        self._sliced_done += 1
        return 1

    def _requeued(self, deadline: np.uint64, counts: npt.NDArray[np.int64], limit: int,
                  stamp: int, first: bool) -> int:
        """The requeued constraints (relaxed before; ``store.requeue``) in arrival order, each
        started only when its predicted cost fits: unlike a new constraint, none is started
        whatever its cost.  In a frame's own work (``first``: nothing else ran before) one
        that does not fit is dropped, at most :data:`MAX_DROPS` per frame, so that none holds
        the others back; spare time revisits it.  Returns the updates made."""
        st = self._store
        cfg = self.config
        done = drops = 0
        while st.requeue.size and limit > 0:
            prob, state, pol = st.views()
            sc = st.scratch(self._wk)
            self._wk = sc.wk
            d0 = int(counts[Count.DONE])
            k = run_loop(loop_kernel(True, False, False, True), prob, state, sc, st.requeue,
                         cfg.tau_new, cfg.damping, int(STEP_KINDS[cfg.step]),
                         cfg.gps_batch_size, 0, deadline, counts, True, pol, stamp, limit,
                         force_first=False, skip=False)
            made = int(counts[Count.DONE]) - d0
            limit -= made
            done += made
            if (k == 0 and first and drops < MAX_DROPS
                    and np.uint64(read_cycles()) < deadline):  # no room in the frame's budget
                k, drops = 1, drops + 1
                st.requeue = st.requeue[k:]
                continue
            st.requeue = st.requeue[k:]
            break
        return done

    def _local_solve(self, deadline: np.uint64, counts: npt.NDArray[np.int64],
                     limit: int) -> int:
        """The local solve: the newest relative constraints together (III-G)."""
        st = self._store
        cfg = self.config
        if not (st.m_laid and limit > 0 and self.backlog == 0):
            return 0
        prob, state, _ = st.views()
        k = min(cfg.local_size, st.m_laid)
        cs = np.arange(st.m_laid - k, st.m_laid, dtype=np.int64)
        if st.num_rejected:
            cs = cs[~st.rejected[cs]]
        return max(int(adm.local_batch(prob, state, cs, cfg.tau_new, cfg.damping, deadline,
                                       st.model, st.slot, st.xb, st.nodes_buf, counts,
                                       st.depth)), 0)

    def _spare_time(self, deadline: np.uint64, counts: npt.NDArray[np.int64], limit: int,
                    stamp: int, quiet: bool = False) -> int:
        """Older constraints, largest last χ² first, while time remains; the updates made.
        None while ``background_hold`` holds (the adopted optimum holds everything, a long loop
        closure waits for its answer, or in a frame that added nothing (``quiet``) the answer
        to everything is on its way).
        Under a deadline the long relative ones among them (:data:`MIN_SLICED` domain nodes)
        are relaxed in slices, one at a time: the one under way goes on first, and the
        others begin, largest χ² first, once the short ones were admitted or skipped."""
        st = self._store
        cfg = self.config
        link = self._link
        # with an adopted background optimum, only the constraints it did not cover
        fm, fg = link.refined if (link is not None and cfg.background_tail_only) else (0, 0)
        if (not (limit > 0 and self.backlog == 0 and st.m_laid - fm > 1)
                or np.uint64(read_cycles()) >= deadline):  # (past it, nothing would fit)
            return 0
        if cfg.background_hold and link is not None and (
                link.holds(st) or (cfg.background_join == 0 and not cfg.background_tail_only
                                   and (link.awaits_loop(st, self.frame)
                                        or (quiet and link.awaits_all(st, self.frame))))):
            return 0
        done0 = int(counts[Count.DONE])
        went_on = -1
        if self._sliced is not None:  # an older constraint's update in slices goes on first
            went_on = int(self._sliced.lu[_slices.C])
            self._advance_sliced(deadline, counts)
            limit -= int(counts[Count.DONE]) - done0
        cand = np.empty(cfg.recent + cfg.window, np.int64)
        k = int(adm.candidates(st.chi2, fm, st.m_laid, cfg.recent, cfg.window, self._cursor,
                               cand))
        span = max(st.m_laid - cfg.recent - fm, 1)
        self._cursor = (self._cursor + cfg.window) % span
        cand = cand[:k]
        if st.g_laid > fg:  # a cyclic window of GPS readings first, as one batch
            kg = min(cfg.gps_batch_size, st.g_laid - fg)
            gw = fg + (self._gps_cursor + np.arange(kg)) % (st.g_laid - fg)
            self._gps_cursor = int((self._gps_cursor + kg) % (st.g_laid - fg))
            cand = np.concatenate([st.cap_m + gw, cand])
        if st.num_rejected:
            cand = cand[~st.rejected[cand]]
        long = np.empty(0, np.int64)
        if deadline != NO_DEADLINE and STEP_KINDS[cfg.step] == StepKind.WOODBURY:
            # the long relative ones in slices
            rel = cand[cand < st.cap_m]
            long = rel[st.ptr[rel + 1] - st.ptr[rel] >= MIN_SLICED]
            if long.size:
                cand = cand[~np.isin(cand, long)]
        prob, state, pol = st.views()
        sc = st.scratch(self._wk)
        d0 = int(counts[Count.DONE])
        run_loop(loop_kernel(True, False, False, True), prob, state, sc, cand, cfg.tau_old,
                 cfg.damping, int(STEP_KINDS[cfg.step]), cfg.gps_batch_size, 0, deadline,
                 counts, True, pol, stamp, limit, force_first=False, skip=True)
        limit -= int(counts[Count.DONE]) - d0
        for c in long.tolist():  # largest χ² first, while one is done within the deadline
            if self._sliced is not None or limit <= 0 or np.uint64(read_cycles()) >= deadline:
                break
            if c != went_on:
                self._start_sliced(c, int(st.ptr[c + 1] - st.ptr[c]), False)
                limit -= self._advance_sliced(deadline, counts)
        return int(counts[Count.DONE]) - done0

    # ----------------------------------------------------------------- background refine
    def join_refine(self, timeout: float | None = None) -> bool:
        """Ship everything added so far, wait for the worker's optimum of it and adopt it.

        For the end of a stream (or a pause), and for reproducible runs.  Returns True when
        the answer came and was adopted (False: ``timeout`` passed, the worker reported an
        error: :meth:`stats` ``["background"]["error"]``, or the map has GPS readings but
        fewer than :data:`~hybridpgo.online.worker.GPS_GAUGE`, whose answer is in another
        gauge than the frames' map).

        Raises
        ------
        ValueError
            ``background_refine`` is off.
        """
        if self._link is None:
            raise ValueError("join_refine needs OnlineConfig(background_refine=True) and a "
                             "solver that is not closed")
        self._integrate()
        return self._link.join(self._store, self.frame, timeout, self.config.background_rebase)

    def wait_background_ready(self, timeout: float | None = None) -> bool:
        """Block until the background worker has started and loaded its kernels (about 1 s
        after the solver is built: a process start, the imports, and the cached kernels of
        every path a request can take, :func:`~hybridpgo.online.worker.warm_up`).

        The frames never wait for the worker; call this before the robot drives (as the replay
        and its benchmark do) so that the first results are not late by the start-up.  Returns
        True when the worker is ready (False: ``timeout`` passed or the worker failed); False
        without waiting when ``background_refine`` is off or the solver is closed.
        """
        return self._link is not None and self._link.refiner.wait_ready(timeout)

    # ----------------------------------------------------------------- estimates
    @uncollected
    def pose(self, pose_id: int) -> tuple[FloatArray, FloatArray]:
        """Current estimate ``(R (3, 3), t (3,))`` of one pose, O(tree depth)."""
        p = self._pose_index(pose_id, "pose")
        if p >= self._store.placed:
            grot, gtr = self.estimate()
            return grot[p], gtr[p]
        return self._store.pose(p)

    def estimate(self) -> tuple[FloatArray, FloatArray]:
        """Global poses ``(R (N, 3, 3), t (N, 3))`` in arrival order (:meth:`pose_ids`), O(N).

        Poses not yet placed in the tree (added since the last :meth:`update`) are their
        odometry composed onto their parent's estimate.
        """
        return self._store.poses()

    def energy(self) -> float:
        """E of the current estimate over every constraint added so far but those rejected as
        outliers (:meth:`outliers`; docs/conventions.md)."""
        rot, trans = self.estimate()
        st = self._store
        m, g = st.m, st.g
        e: Any = slice(0, m)
        k: Any = slice(0, g)
        if st.num_rejected:
            e = np.flatnonzero(~st.rejected[:m])
            k = np.flatnonzero(~st.rejected[st.cap_m: st.cap_m + g])
        return float(_cost.total_energy(
            rot, trans, st.edge_ab[e], st.edge_rot[e], st.edge_trans[e], st.edge_info[e],
            st.gps_node[k], st.gps_pos[k], st.gps_info[k]))

    def outliers(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """The constraints rejected as outliers (``robust="auto"``): ``(edges, gps)``, each
        an increasing array of indices in arrival order (edges counted with the odometry of
        :meth:`add_pose`).  The worker's outlier test decides them on each answer it adopts,
        :meth:`refine` on its solve; a rejected constraint stays in the map's data
        (:meth:`to_graph`) but no update relaxes it and :meth:`energy` leaves it out.  A later
        verdict may re-admit it."""
        return self._store.rejected_names()

    def to_graph(self) -> PoseGraph:
        """Everything added so far as a :class:`PoseGraph` at the current estimate (ids sorted)."""
        rot, trans = self.estimate()
        st = self._store
        ids = st.ids[: st.n]
        perm = np.argsort(ids, kind="stable")
        rank = np.empty_like(perm)
        rank[perm] = np.arange(perm.shape[0])
        m, g = st.m, st.g
        return PoseGraph(
            node_ids=ids[perm], rotations=rot[perm], translations=trans[perm],
            edge_nodes=rank[st.edge_ab[:m]].astype(np.int32), edge_rotations=st.edge_rot[:m],
            edge_translations=st.edge_trans[:m], edge_information=st.edge_info[:m],
            gps_nodes=rank[st.gps_node[:g]].astype(np.int32), gps_positions=st.gps_pos[:g],
            gps_information=st.gps_info[:g],
        )  # fmt: skip

    def refine(self, max_iterations: int = 10) -> int:
        """Exact Levenberg-Marquardt over the whole map from the current estimate.

        This is the periodic batch solve of the whole map: it costs a sparse factorization per
        iteration (O(N) and more, no time budget), so it is not part of :meth:`update`; call it
        when a frame can afford it (e.g. while the robot stands still).  The gauge is the
        solver's: the first pose without GPS, the earth with it.  With ``robust="auto"`` (the
        default) the least-squares solve of every constraint (those rejected before included)
        is followed by the outlier test and, when it fails, the re-solve without the outliers
        (:mod:`hybridpgo.solvers.robust`); its verdict becomes the rejected set
        (:meth:`outliers`), which the updates leave alone from then on.

        The map is solved as the graph :func:`~hybridpgo.solvers.gauss_newton.solve_exact`
        would get from a file of the same data: when the data are planar
        (:func:`planar_data`, e.g. a stream of a 2D graph) it is marked ``is_2d``, so the
        outlier test counts 3 degrees of freedom per relative constraint, as for a 2D file,
        not 6 of which 3 are exactly 0 (that halves the estimated scale and hides a map folded
        by false loop closures), and the solve uses the (x, y, yaw) system when the estimate
        is exactly planar too.  Returns the iterations done.
        """
        from ..solvers.config import GaussNewtonConfig
        from ..solvers.gauss_newton import solve_exact
        from ..tree import locals_from_globals

        check_int("max_iterations", max_iterations, 1)
        self._integrate()
        st = self._store
        if st.n < 2:
            return 0
        graph = self.to_graph()
        # a planar map is solved and tested as the 2D graph it is (``is_2d``: the outlier
        # test's degrees of freedom, the planar reduction of the solve)
        graph = dataclasses.replace(graph, is_2d=planar_data(graph))
        if not st.g:
            first = int(np.searchsorted(graph.node_ids, st.ids[0]))
            graph = dataclasses.replace(graph, fixed_nodes=np.array([first], np.int32))
        cfg = self.config
        res = solve_exact(graph, None, None, GaussNewtonConfig(
            max_iterations=max_iterations, robust=cfg.robust, robust_scale=cfg.robust_scale))
        report = res.stats.get("outliers")
        if report is not None:  # robust="auto": the verdict over every constraint
            rows = report["rejected_constraints"]
            st.set_rejected(
                np.array([r["index"] for r in rows if r["kind"] == "edge"], np.int64),
                np.array([r["index"] for r in rows if r["kind"] == "gps"], np.int64),
                (st.m, st.g))
        rank = np.searchsorted(graph.node_ids, st.ids[: st.n])
        t = st.n + 1
        grot = np.empty((t, 3, 3))
        gtr = np.zeros((t, 3))
        grot[0] = np.eye(3)
        grot[1:] = res.rotations[rank]
        gtr[1:] = res.translations[rank]
        locals_from_globals(st.parent[:t], grot, gtr, st.rot[:t], st.trans[:t])
        return int(res.iterations)

    def stats(self) -> dict[str, Any]:
        """Sizes of the tree and the paths."""
        st = self._store
        lengths = np.diff(st.ptr[: st.m_laid + 1])
        return {
            "poses": st.n, "edges": st.m, "gps": st.g, "frames": self.frame,
            "tree_max_depth": int(st.depth[: st.placed + 1].max()),
            "path_length_mean": float(lengths.mean()) if lengths.size else 0.0,
            "path_length_max": int(st.dmax), "path_entries": st.path_entries(),
            "gps_links": st.gps_links, "junction_groups": st.ngroups,
            "rejected": st.num_rejected,
            "sliced_updates": {"done": self._sliced_done, "given_up": self._sliced_cancelled,
                               "under_way": self._sliced is not None},
            "model_us": (st.model / cycles_per_second() * 1e6).tolist(),
            **({"background": self._link.stats()} if self._link is not None else {}),
        }  # fmt: skip

    # ----------------------------------------------------------------- save / load
    def state_arrays(self) -> dict[str, np.ndarray]:
        """Every member of the saved state (:mod:`.persist`), as copies: what :meth:`save`
        writes."""
        from .persist import state_arrays

        return state_arrays(self._store, self.config, {
            "frame": self.frame, "cursor": self._cursor, "gps_cursor": self._gps_cursor})

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the whole state to ``path`` (:mod:`.persist`), atomically; :meth:`load` of it,
        then the same calls, gives the same results as not stopping."""
        from .persist import write_state

        write_state(path, self.state_arrays())

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> OnlineSolver:
        """Read a state written by :meth:`save`, validated completely (:mod:`.persist`).

        Raises
        ------
        FormatError
            The file is missing, truncated, corrupted, not an online state or of another
            version, or any of its values breaks an invariant of the solver.
        """
        from ._restore import restore
        from .persist import read_state

        config, meta, members = read_state(path)
        solver = cls(config)
        try:
            restore(solver._store, meta, members)
        except (GraphError, ValueError, IndexError) as exc:
            solver.close()
            raise FormatError(f"not a valid online solver state: {exc}",
                              path=os.fspath(path)) from exc
        except BaseException:
            solver.close()
            raise
        st = solver._store
        solver.frame = int(meta["frame"])
        solver._cursor, solver._gps_cursor = int(meta["cursor"]), int(meta["gps_cursor"])
        solver._index = {int(v): i for i, v in enumerate(st.ids[: st.n])}
        if solver._link is not None:  # the new worker gets the whole map
            solver._link.ship(st, solver.frame)
            solver._link.loop_floor = st.m_laid  # its closures wait for no answer
        return solver


#: Set once the online kernels have been compiled (or loaded from the cache) in this process.
_COMPILED = [False]


def _ensure_online_compiled() -> float:
    """Compile every online kernel once per process on a four-pose stream with GPS, so the
    first frames of a caller are not timed with compilation in them; then move every object
    alive to the garbage collector's permanent generation (:func:`gc.freeze`).  Loading the
    kernels leaves some 4 * 10^5 Python objects that live as long as the process, and a full
    collection walks them all: about 0.2 s, in whichever frame happens to allocate the object
    that triggers it."""
    if _COMPILED[0]:
        return 0.0
    _COMPILED[0] = True
    t0 = time.perf_counter()
    try:
        # (the caller's config decides on the process's heap: heap_reserve_mb)
        s = OnlineSolver(OnlineConfig(local_size=2, reserve_poses=8, heap_reserve_mb=0))
        s.add_pose(0)
        step = (np.eye(3), np.array([1.0, 0.0, 0.0]))
        for i in range(1, 4):
            s.add_pose(i, i - 1, step, np.eye(6))
            s.add_gps(i, [float(i), 0.0, 0.0], np.eye(3))
        s.add_constraint(0, 3, (np.eye(3), np.array([3.0, 0.0, 0.0])), np.eye(6))
        s.update()
        s.update(1.0)
        s.energy()
        s.pose(3)
        # an update in slices (the loop closure again, with no step: tau 0)
        st = s._store
        prob, state, pol = st.views()
        lu, lf = _slices.new_state()
        _slices.begin(prob, 3, lu, lf)
        _slices.valid(prob, lu)
        _slices.advance(prob, state, st.scratch(None).wk, lu, lf, 0.0, s.config.damping,
                        NO_DEADLINE)
        # and what decides to begin one (_begin_sliced, _advance_sliced)
        group_cost(prob, pol, 0)
        adm.predict(st.model, 4, False)
        adm.learn(st.model, 4, 1.0, False)
        # a loop closure's neighbours and their χ² (_loop_neighbours, _loop_batch)
        near = np.empty(st.m_laid, np.int64)
        k = adm.crossing(prob, st.m_laid, 3, st.rejected, np.zeros(st.placed + 1, np.bool_),
                         near)
        adm.edge_chi2s(prob, state, near[:k], st.scratch(None).wk, np.empty(max(k, 1)))
    except BaseException:
        _COMPILED[0] = False
        raise
    gc.collect()
    gc.freeze()
    return time.perf_counter() - t0
