"""The online mode's map: arrays that grow with the stream, and the pose tree inside them.

:class:`MapStore` keeps everything the hybrid kernels read (:class:`~..solvers.hybrid.problem.
Problem`, :class:`~..solvers.hybrid.problem.State`) for a map that grows pose by pose:

* **Tree nodes**: node 0 is the earth (the fixed root); pose ``p`` (arrival order) is node
  ``p + 1``.  The first pose hangs from the earth by a *free* link (no constraint): before any
  GPS reading no domain contains it and it stays where it started (the gauge); from the first
  GPS reading on, every GPS domain contains it, so GPS can move and turn the whole map without
  re-rooting.  A new pose whose frame brings a GPS reading hangs from the earth by it
  (``OnlineConfig.gps_link``); any other new pose hangs from the *oldest* pose it is
  constrained to in its frame (its odometry parent unless a loop closure reaches an older pose;
  ``OnlineConfig.tree = "odometry"``: always its odometry parent), so revisits hang from the
  first visit and the tree stays shallow (M3500: 32 110 path entries against 742 356 for the
  odometry chain).
* **Constraints** have one index inside: relative edges ``0..cap_m-1`` then GPS readings
  ``cap_m + g`` (the problem's layout; ``cap_m`` is the edge capacity).  The solver translates
  to arrival order at its API.
* **Paths** are laid when a constraint is first integrated, by a walk to the lowest common
  ancestor (:mod:`hybridpgo._tree_kernels`), O(d), into a pool whose edge part and GPS part
  grow separately.
* **Rejected constraints** (outliers found by the outlier test, ``robust="auto"``) stay in the
  arrays with their data, but their whitening is zero and their contributions to 𝔅(H) are
  taken out, so no update moves a pose for them; :meth:`MapStore.set_rejected` rejects and
  re-admits.
* **Junction groups**: the constraints that joined a pose to the map in its frame, when their
  stiffness differs by more than :data:`JUNCTION_RATIO`, are relaxed together as one batch.

Capacity is reserved up front (:mod:`._reserve`: address space only, on Linux where
:func:`hybridpgo._memory.can_overcommit`), so a frame never copies the map; elsewhere the
capacity starts at 1 024 poses, and beyond it an array doubles.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import _tree_kernels as tk
from ..solvers.hybrid._admission import MODEL0, Admission
from ..solvers.hybrid._sweep import Scratch
from ..solvers.hybrid.problem import Problem, State, new_workspace
from ._reserve import capacity, grown, reserved_zeros

#: A junction group is formed when the stiffest of its constraints has more than this many
#: times the translational information of the softest (cities: loop closures and GPS are
#: 25-10^4 times softer than the odometry; M3500: 1, no groups, which measured better there:
#: 1.17x against 1.25x the optimum at the end).
JUNCTION_RATIO = 10.0
#: Poses reserved when the arrays can be reserved as address space only (else 1024).
RESERVE_POSES = 1 << 20

#: Domain nodes the first workspace holds (about 1.1 kB each, written when the solver is
#: built): a longer path grows it, in the frame that lays the path (valencia's longest path
#: has 2 368 nodes; a new workspace faulted in by its first update took 3.6 ms of that frame).
WORKSPACE_NODES = 4096

#: Problem.link_* placeholders: the online mode has no interpolated solving, no kernel reads them.
_NO_LINKS = np.empty(0, np.int64)
_NO_FORWARD = np.empty(0, np.bool_)

#: Arrays per tree node, per edge, per GPS reading, per path entry: (name, trailing shape,
#: dtype).  Every array is reserved at its capacity and written element by element.
_Spec = tuple[tuple[str, tuple[int, ...], Any], ...]
_NODE_ARRAYS: _Spec = (
    ("parent", (), np.int32), ("depth", (), np.int32), ("rot", (3, 3), np.float64),
    ("trans", (3,), np.float64), ("bdiag", (6, 6), np.float64), ("path_count", (), np.int64),
    ("slot", (), np.int64), ("xb", (6,), np.float64), ("nodes_buf", (), np.int64),
    ("ids", (), np.int64), ("odom", (), np.int64), ("group_stamp", (), np.int64),
    ("group_ptr", (), np.int64))
_EDGE_ARRAYS: _Spec = (("edge_ab", (2,), np.int32), ("edge_rot", (3, 3), np.float64),
                ("edge_trans", (3,), np.float64), ("edge_info", (6, 6), np.float64),
                ("edge_lt", (6, 6), np.float64), ("edge_prev", (), np.int64))
_GPS_ARRAYS: _Spec = (("gps_node", (), np.int32), ("gps_pos", (3,), np.float64),
               ("gps_info", (3, 3), np.float64), ("gps_lt", (3, 3), np.float64))
_POOL_ARRAYS: _Spec = (("path_node", (), np.int32), ("path_sign", (), np.int8),
                ("contrib", (6, 6), np.float64))
#: Bytes of ``contrib`` (288 per path entry; the pool's other arrays add 5) kept written ahead
#: of each region's laid paths by :meth:`MapStore.prefault`, in the frames' spare time: a page
#: of reserved memory is allocated when first written, and a long loop closure's path would
#: otherwise fault all of its fresh pages inside the frame that lays it (valencia, frame
#: 7 784: a 3 264-entry path, 233-255 page faults, 3.2-9.0 ms of CPU).
PREFAULT_AHEAD_BYTES = 4 << 20
#: Bytes of ``contrib`` one call of :meth:`MapStore.prefault` writes (16 pages, and a page or
#: two of the pool's other arrays).
PREFAULT_CHUNK_BYTES = 64 << 10
#: Arrays per constraint (edges, then GPS readings at ``cap_m``).
_CONSTRAINT_ARRAYS: _Spec = (
    ("ptr", (), np.int64), ("chi2", (), np.float64), ("group_of", (), np.int64),
    ("cycles", (), np.uint64), ("batch_cycles", (), np.uint64), ("rejected", (), np.bool_))


class MapStore:
    """The growing arrays of the online mode's map (module docstring).

    Counters: ``n`` poses added, ``placed`` of them in the tree; ``m`` edges added, ``m_laid``
    with their paths; likewise ``g`` and ``g_laid`` for GPS readings; ``ngroups`` junction
    groups.  Capacities: ``cap_n`` tree nodes, ``cap_m`` edges, ``cap_g`` GPS readings,
    ``cap_pe`` / ``cap_pg`` path entries of edges / GPS readings.
    """

    parent: np.ndarray
    depth: np.ndarray
    rot: np.ndarray
    trans: np.ndarray
    bdiag: np.ndarray
    path_count: np.ndarray
    slot: np.ndarray
    xb: np.ndarray
    nodes_buf: np.ndarray
    ids: np.ndarray
    odom: np.ndarray
    group_stamp: np.ndarray
    group_ptr: np.ndarray
    edge_ab: np.ndarray
    edge_rot: np.ndarray
    edge_trans: np.ndarray
    edge_info: np.ndarray
    edge_lt: np.ndarray
    edge_prev: np.ndarray
    gps_node: np.ndarray
    gps_pos: np.ndarray
    gps_info: np.ndarray
    gps_lt: np.ndarray
    path_node: np.ndarray
    path_sign: np.ndarray
    contrib: np.ndarray
    ptr: np.ndarray
    chi2: np.ndarray
    group_of: np.ndarray
    cycles: np.ndarray
    batch_cycles: np.ndarray
    rejected: np.ndarray

    def __init__(self, reserve_poses: int | None, robust: tuple[int, float] = (0, 1.0),
                 gps_batch_size: int = 1) -> None:
        probe, reservable = reserved_zeros((1 << 16,), np.uint8)
        del probe
        r = reserve_poses or (RESERVE_POSES if reservable else 1024)
        self.robust = robust
        self.gps_batch_size = gps_batch_size
        self.n = self.placed = self.m = self.m_laid = self.g = self.g_laid = 0
        self.ngroups = 0
        self.num_rejected = 0
        """Constraints rejected as outliers (:meth:`set_rejected`)."""
        self.gps_links = 0
        """Poses hung from the earth by a GPS reading."""
        self.dmax = 1
        self.model = np.array(MODEL0)
        self.span = np.full(1, np.inf)  # the current call's budget in cycles (Admission.span)
        self.queue = np.zeros(64, np.int64)
        """Constraints waiting for their first update, ``queue[q_head:q_tail]``."""
        self.q_head = self.q_tail = 0
        self.requeue = np.zeros(0, np.int64)
        """Constraints relaxed before and queued again (the constraints laid after an adopted
        answer's snapshot), in arrival order: each is started only when it fits."""
        self.first_rot = np.eye(3)
        self.first_trans = np.zeros(3)
        self.pair_last: dict[int, int] = {}
        """``a * 2**32 + b`` -> the newest edge from pose a to pose b; ``edge_prev[e]`` is the
        one before e with the same poses (-1: none).  Integer keys and values: the garbage
        collector does not track them, so the index costs no frame a longer collection."""
        self.allocate(nodes=r + 2, edges=2 * r + 1, gps=max(r // 16, 8), pool_e=16 * r,
                      pool_g=max(r, 64))
        self.parent[0] = -1  # the earth: tree node 0, the fixed root
        self.rot[0] = np.eye(3)
        self.slot[0] = -1

    # ----------------------------------------------------------------- storage
    def allocate(self, nodes: int, edges: int, gps: int, pool_e: int, pool_g: int) -> None:
        """Reserve every array at these capacities (zero; ``slot`` and the like are written
        as their elements come into use)."""
        self.cap_n, self.cap_m, self.cap_g = nodes, edges, gps
        self.cap_pe, self.cap_pg = pool_e, pool_g
        for name, shape, dtype in _NODE_ARRAYS:
            setattr(self, name, reserved_zeros((nodes, *shape), dtype)[0])
        for name, shape, dtype in _EDGE_ARRAYS:
            setattr(self, name, reserved_zeros((edges, *shape), dtype)[0])
        for name, shape, dtype in _GPS_ARRAYS:
            setattr(self, name, reserved_zeros((gps, *shape), dtype)[0])
        for name, shape, dtype in _POOL_ARRAYS:
            setattr(self, name, reserved_zeros((pool_e + pool_g, *shape), dtype)[0])
        for name, shape, dtype in _CONSTRAINT_ARRAYS:
            setattr(self, name, reserved_zeros((edges + gps + 1, *shape), dtype)[0])
        self.ptr[edges:] = pool_e  # the GPS part of the pool starts after the edges'
        #: the pool entries written ahead (:meth:`prefault`) up to, in the edges' and the GPS
        #: readings' regions
        self._ahead = [0, pool_e]
        self.group_members = reserved_zeros((edges + gps,), np.int64)[0]
        self._views: tuple[Any, ...] | None = None

    def ensure_nodes(self, need: int) -> None:
        """Capacity for ``need`` tree nodes."""
        if need <= self.cap_n:
            return
        cap = capacity(need, self.cap_n)
        for name, _, _ in _NODE_ARRAYS:
            setattr(self, name, grown(getattr(self, name)[: self.n + 1], cap))
        self.cap_n = cap
        self._views = None

    def ensure_constraints(self, edges: int, gps: int) -> None:
        """Capacity for ``edges`` edges (one edge slot always stays free) and ``gps`` GPS
        readings.  When the edge capacity grows, the GPS readings' indices (``cap_m + g``) move:
        every stored index is translated."""
        cap_m = capacity(edges + 1, self.cap_m)
        cap_g = capacity(gps, self.cap_g)
        if cap_m == self.cap_m and cap_g == self.cap_g:
            return
        om = self.cap_m
        for name, _, _ in _EDGE_ARRAYS:
            setattr(self, name, grown(getattr(self, name)[: self.m], cap_m))
        for name, _, _ in _GPS_ARRAYS:
            setattr(self, name, grown(getattr(self, name)[: self.g], cap_g))
        for name, shape, dtype in _CONSTRAINT_ARRAYS:
            old = getattr(self, name)
            new = reserved_zeros((cap_m + cap_g + 1, *shape), dtype)[0]
            if name == "ptr":  # every edge offset (the laid end included), the GPS part after
                new[:om] = old[:om]
                new[cap_m: cap_m + self.g + 1] = old[om: om + self.g + 1]
                new[cap_m + self.g + 1:] = old[om + self.g]
            else:
                new[: self.m] = old[: self.m]
                new[cap_m: cap_m + self.g] = old[om: om + self.g]
            setattr(self, name, new)
        shift = cap_m - om
        k = int(self.group_ptr[self.ngroups])
        for ids in (self.group_members[:k], self.queue[self.q_head: self.q_tail],
                    self.requeue):
            ids[ids >= om] += shift
        self.cap_m, self.cap_g = cap_m, cap_g
        self._views = None

    def ensure_pool(self, need_e: int, need_g: int) -> None:
        """Room for paths of ``need_e`` edge entries and ``need_g`` GPS entries in all."""
        cap_e = capacity(need_e, self.cap_pe)
        cap_g = capacity(need_g, self.cap_pg)
        if cap_e == self.cap_pe and cap_g == self.cap_pg:
            return
        used_e = int(self.ptr[self.m_laid])
        g0 = self.cap_pe
        g1 = int(self.ptr[self.cap_m + self.g_laid])
        for name, shape, dtype in _POOL_ARRAYS:
            old = getattr(self, name)
            new = reserved_zeros((cap_e + cap_g, *shape), dtype)[0]
            new[:used_e] = old[:used_e]
            new[cap_e: cap_e + g1 - g0] = old[g0:g1]
            setattr(self, name, new)
        self.ptr[self.cap_m:] += cap_e - g0
        self.cap_pe, self.cap_pg = cap_e, cap_g
        self._ahead = [used_e, cap_e + g1 - g0]  # new arrays: written up to what was copied
        self._views = None

    def prefault(self) -> bool:
        """Write zeros to the next :data:`PREFAULT_CHUNK_BYTES` of ``contrib`` (and the same
        entries of the pool's other arrays) past the laid paths of the first region (edges,
        then GPS readings once the map has one) that has less than
        :data:`PREFAULT_AHEAD_BYTES` written ahead, so that their pages are allocated now
        rather than in the frame that lays a long path.  The entries past the laid paths are
        zero already: only the pages change.  True when it wrote."""
        row = self.contrib[0].nbytes
        chunk, ahead = PREFAULT_CHUNK_BYTES // row, PREFAULT_AHEAD_BYTES // row
        regions = ((int(self.ptr[self.m_laid]), self.cap_pe),
                   (int(self.ptr[self.cap_m + self.g_laid]), self.cap_pe + self.cap_pg))
        for r, (used, end) in enumerate(regions[: 2 if self.g else 1]):
            lo = max(self._ahead[r], used)
            hi = min(lo + chunk, used + ahead, end)
            if hi > lo:
                for name, _, _ in _POOL_ARRAYS:
                    getattr(self, name)[lo:hi] = 0
                self._ahead[r] = hi
                return True
        return False

    def ensure_group_members(self, members: int) -> None:
        """Room for ``members`` junction-group members in all."""
        if members > self.group_members.shape[0]:
            k = int(self.group_ptr[self.ngroups])
            self.group_members = grown(self.group_members[:k],
                                       capacity(members, self.group_members.shape[0]))
            self._views = None

    def push(self, c: int) -> None:
        """Queue constraint c for its first update."""
        if self.q_tail >= self.queue.shape[0]:  # compact, then grow
            live = self.q_tail - self.q_head
            cap = capacity(live + 1, self.queue.shape[0])
            q = np.zeros(cap, np.int64) if cap > self.queue.shape[0] else self.queue
            q[:live] = self.queue[self.q_head: self.q_tail].copy()
            self.queue, self.q_head, self.q_tail = q, 0, live
        self.queue[self.q_tail] = c
        self.q_tail += 1

    def set_queue(self, cs: np.ndarray) -> None:
        """Replace the queue by ``cs``."""
        self.queue = np.zeros(capacity(cs.shape[0], 64), np.int64)
        self.queue[: cs.shape[0]] = cs
        self.q_head, self.q_tail = 0, int(cs.shape[0])

    def pending(self) -> np.ndarray:
        """The queued constraints (a view)."""
        return self.queue[self.q_head: self.q_tail]

    def arrival_names(self, cs: np.ndarray) -> np.ndarray:
        """Store indices -> arrival-order names (edge ``e`` as ``e``, GPS reading ``g`` as
        ``-(g + 1)``): the names a saved state uses, independent of the reserved capacity."""
        cs = np.asarray(cs, np.int64)
        return np.where(cs < self.cap_m, cs, -(cs - self.cap_m) - 1)

    def store_indices(self, names: np.ndarray) -> np.ndarray:
        """Arrival-order names -> store indices (the inverse of :meth:`arrival_names`)."""
        return np.where(names >= 0, names, self.cap_m - names - 1)

    def pop(self, k: int, behind_first: bool = False) -> None:
        """Drop the first ``k`` queued constraints (``behind_first``: the ``k`` after the
        first, which stays first)."""
        if behind_first and k:
            self.queue[self.q_head + k] = self.queue[self.q_head]
        self.q_head += k
        if self.q_head == self.q_tail:
            self.q_head = self.q_tail = 0

    # ----------------------------------------------------------------- kernel views
    def views(self) -> tuple[Problem, State, Admission]:
        """The problem, state and admission arrays the kernels take (rebuilt after growth)."""
        if self._views is None:
            prob = Problem(
                self.cap_m, self.ptr, self.path_node, self.path_sign, self.edge_rot,
                self.edge_trans, self.edge_lt, self.gps_pos, self.gps_lt, self.path_count,
                self.parent, _NO_LINKS, _NO_FORWARD, self.robust[0], self.robust[1],
            )  # fmt: skip
            state = State(self.rot, self.trans, self.bdiag, self.contrib)
            pol = Admission(self.model, self.chi2, self.group_of, self.group_ptr,
                            self.group_members, self.group_stamp, self.depth, self.span)
            self._views = (prob, state, pol)
        return self._views

    def scratch(self, wk: Any) -> Scratch:
        """The loop's buffers over the store's arrays, with the workspace ``wk`` (a new one,
        its pages written once, when ``wk`` is None or too small for the longest path)."""
        if wk is None or wk.x.shape[0] < self.dmax:
            cap = capacity(self.dmax, WORKSPACE_NODES)
            wk = new_workspace(cap)
            for arr in wk:  # fault the per-node arrays in now, not in their first update
                if arr.shape[0] >= cap:
                    arr.fill(0.0)
        return Scratch(wk, wk, np.empty(1, np.int64), self.slot, self.xb, self.nodes_buf,
                       np.empty(max(self.gps_batch_size, 1), np.int64), self.cycles,
                       self.batch_cycles)

    # ----------------------------------------------------------------- appending
    def append_pose(self, pose_id: int) -> int:
        """A new pose (not yet in the tree); returns its index."""
        n = self.n
        self.ensure_nodes(n + 2)
        self.ids[n] = pose_id
        self.odom[n] = -1
        self.n = n + 1
        return n

    def append_edge(self, a: int, b: int, rot: np.ndarray, trans: np.ndarray,
                    info: np.ndarray, lt: np.ndarray) -> int:
        """A new relative constraint between poses a and b; returns its index."""
        self.ensure_constraints(self.m + 1, self.g)
        e = self.m
        self.edge_ab[e] = (a, b)
        self.edge_rot[e] = rot
        self.edge_trans[e] = trans
        self.edge_info[e] = info
        self.edge_lt[e] = lt
        self.group_of[e] = -1
        key = (a << 32) | b
        self.edge_prev[e] = self.pair_last.get(key, -1)
        self.pair_last[key] = e
        self.m = e + 1
        return e

    def edges_between(self, a: int, b: int) -> list[int]:
        """The edges from pose a to pose b, newest first."""
        out = []
        e = self.pair_last.get((a << 32) | b, -1)
        while e >= 0:
            out.append(e)
            e = int(self.edge_prev[e])
        return out

    def index_pairs(self) -> None:
        """Rebuild :attr:`pair_last` and ``edge_prev`` from ``edge_ab`` (after a restore)."""
        self.pair_last = {}
        for e in range(self.m):
            key = (int(self.edge_ab[e, 0]) << 32) | int(self.edge_ab[e, 1])
            self.edge_prev[e] = self.pair_last.get(key, -1)
            self.pair_last[key] = e

    def append_gps(self, n: int, pos: np.ndarray, info: np.ndarray, lt: np.ndarray) -> int:
        """A new GPS reading of pose n; returns its constraint index ``cap_m + g``."""
        self.ensure_constraints(self.m, self.g + 1)
        g = self.g
        self.gps_node[g] = n
        self.gps_pos[g] = pos
        self.gps_info[g] = info
        self.gps_lt[g] = lt
        c = self.cap_m + g
        self.group_of[c] = -1
        self.g = g + 1
        return c

    # ----------------------------------------------------------------- integration
    def place_poses(self, tree: str, gps_link: bool, junctions: bool) -> None:
        """Hang the poses added since the last call in the tree (module docstring) and form
        their junction groups."""
        parent_of: dict[int, int] = {}
        joining: dict[int, list[int]] = {}  # new pose -> its constraints to earlier poses
        ab = self.edge_ab[self.m_laid: self.m]
        for e, (a, b) in enumerate(ab.tolist(), start=self.m_laid):
            lo, hi = (a, b) if a < b else (b, a)
            if hi >= self.placed:
                joining.setdefault(hi, []).append(e)
                if tree == "oldest" and parent_of.get(hi, hi) > lo:
                    parent_of[hi] = lo
        if gps_link:
            for g, n in enumerate(self.gps_node[self.g_laid: self.g].tolist(),
                                  start=self.g_laid):
                if n >= self.placed:
                    joining.setdefault(n, []).append(self.cap_m + g)
                    parent_of[n] = -1  # the earth
        if junctions:
            for cs in joining.values():
                if len(cs) > 1 and self._stiffness_spread(cs) > JUNCTION_RATIO:
                    self._add_group(cs)
        ro, to = np.empty((3, 3)), np.empty(3)
        for p in range(self.placed, self.n):
            node = p + 1
            if p == 0:
                tp, rot, trans = 0, self.first_rot, self.first_trans
                self.gps_links += parent_of.get(0) == -1  # its link: its GPS reading
            else:
                e = int(self.odom[p])
                a = int(self.edge_ab[e, 0])
                # initial guess: the odometry composed onto the parent's estimate
                tk.global_pose(a + 1, self.parent, self.rot, self.trans, ro, to)
                zr, zt = self.edge_rot[e], self.edge_trans[e]
                gr, gt = ro @ zr, ro @ zt + to
                tp = parent_of.get(p, a) + 1
                if tp == a + 1:
                    rot, trans = zr.copy(), zt.copy()
                elif tp == 0:  # hangs from the earth: the local transform is the global pose
                    rot, trans = gr, gt
                    self.gps_links += 1
                else:
                    tk.global_pose(tp, self.parent, self.rot, self.trans, ro, to)
                    rot, trans = ro.T @ gr, ro.T @ (gt - to)
                if tp != a + 1:
                    # one Newton step towards the polar factor, R (3I - R^T R) / 2: R^T is the
                    # inverse of an orthonormal R only, and an error left here doubles at each
                    # pose hung from an old pose through this one (M3500_isam with no update:
                    # 1e-12 at frame 144, translations of 1e53 by frame 469)
                    rot = 0.5 * rot @ (3.0 * np.eye(3) - rot.T @ rot)
            self.parent[node] = tp
            self.depth[node] = self.depth[tp] + 1
            self.rot[node] = rot
            self.trans[node] = trans
            self.slot[node] = -1
        self.placed = self.n

    def _stiffness_spread(self, cs: list[int]) -> float:
        """Largest over smallest translational information (trace) among constraints ``cs``."""
        tr = [float(np.trace(self.edge_info[c, :3, :3])) if c < self.cap_m
              else float(np.trace(self.gps_info[c - self.cap_m])) for c in cs]
        return max(tr) / min(tr)

    def _add_group(self, cs: list[int]) -> None:
        """A junction group: these constraints are relaxed together."""
        k = self.ngroups
        lo = int(self.group_ptr[k])
        self.ensure_group_members(lo + len(cs))
        self.group_members[lo: lo + len(cs)] = cs
        self.group_of[cs] = k
        self.group_ptr[k + 1] = lo + len(cs)
        self.group_stamp[k] = -1
        self.ngroups = k + 1

    def lay_paths(self) -> None:
        """The paths of the constraints added since the last call (O(their length))."""
        m0, m1, g0, g1 = self.m_laid, self.m, self.g_laid, self.g
        if m0 == m1 and g0 == g1:
            return
        ends = np.empty((m1 - m0 + g1 - g0, 2), np.int32)
        ends[: m1 - m0] = self.edge_ab[m0:m1] + 1
        ends[m1 - m0:, 0] = 0  # GPS: from the earth
        ends[m1 - m0:, 1] = self.gps_node[g0:g1] + 1
        lengths = np.empty(ends.shape[0], np.int64)
        roots = np.empty(ends.shape[0], np.int32)
        tk.path_lengths(ends, self.parent, self.depth, lengths, roots)
        le, lg = lengths[: m1 - m0], lengths[m1 - m0:]
        cm = self.cap_m
        self.ensure_pool(int(self.ptr[m0] + le.sum()),
                         int(self.ptr[cm + g0] - self.cap_pe + lg.sum()))
        cm = self.cap_m
        self.ptr[m0 + 1: m1 + 1] = self.ptr[m0] + np.cumsum(le)
        self.ptr[cm + g0 + 1: cm + g1 + 1] = self.ptr[cm + g0] + np.cumsum(lg)
        starts = np.concatenate([self.ptr[m0:m1], self.ptr[cm + g0: cm + g1]])
        tk.fill_paths(ends, self.parent, roots, starts, self.path_node, self.path_sign)
        for lo, hi in ((int(self.ptr[m0]), int(self.ptr[m1])),
                       (int(self.ptr[cm + g0]), int(self.ptr[cm + g1]))):
            np.add.at(self.path_count, self.path_node[lo:hi], 1)
            # no contributions yet; written now, the pool's new pages fault here, before the
            # frame's admission decisions, not inside the first update (0.5 MB at 1 742 nodes)
            self.contrib[lo:hi] = 0.0
        if lengths.size:
            self.dmax = max(self.dmax, int(lengths.max()))
        self.m_laid, self.g_laid = m1, g1

    # ----------------------------------------------------------------- outliers
    def set_rejected(self, edges: np.ndarray, gps: np.ndarray, judged: tuple[int, int]
                     ) -> tuple[int, int]:
        """Make the rejected constraints among the first ``judged`` (edges, GPS readings, all
        laid) exactly ``edges`` and ``gps`` (arrival order); returns (rejected, re-admitted).

        A newly rejected constraint's whitening becomes zero (its residual and Jacobian
        vanish, so an update of it, alone or in its junction group, moves nothing), its
        contributions to 𝔅(H) are taken out and it leaves the queue.  A re-admitted one gets
        its whitening back from its information and is queued to be relaxed as a new one
        (its contributions return with that update).  O(paths of the constraints changed)."""
        if self.num_rejected == 0 and len(edges) == 0 and len(gps) == 0:
            return 0, 0  # the common case of every adoption: O(1)
        jm, jg = judged
        cm = self.cap_m
        want = np.zeros(jm + jg, np.bool_)
        want[np.asarray(edges, np.int64)] = True
        want[jm + np.asarray(gps, np.int64)] = True
        idx = np.concatenate([np.arange(jm, dtype=np.int64), cm + np.arange(jg, dtype=np.int64)])
        have = self.rejected[idx]
        new = idx[want & ~have]
        back = idx[have & ~want]
        if new.size:
            lo, hi = self.ptr[new], self.ptr[new + 1]
            lens = hi - lo
            ent = np.repeat(lo - np.cumsum(lens) + lens, lens) + np.arange(int(lens.sum()))
            np.subtract.at(self.bdiag, self.path_node[ent], self.contrib[ent])
            self.contrib[ent] = 0.0
            e, g = new[new < cm], new[new >= cm] - cm
            self.edge_lt[e] = 0.0
            self.gps_lt[g] = 0.0
            self.chi2[new] = 0.0
            self.rejected[new] = True
            live = self.pending()
            self.set_queue(live[~self.rejected[live]])
            self.requeue = self.requeue[~self.rejected[self.requeue]]
        if back.size:
            e, g = back[back < cm], back[back >= cm] - cm
            self.edge_lt[e] = np.linalg.cholesky(self.edge_info[e]).transpose(0, 2, 1)
            self.gps_lt[g] = np.linalg.cholesky(self.gps_info[g]).transpose(0, 2, 1)
            self.rejected[back] = False
            for c in back.tolist():
                self.push(c)
        self.num_rejected += int(new.size) - int(back.size)
        return int(new.size), int(back.size)

    def rejected_names(self) -> tuple[np.ndarray, np.ndarray]:
        """The rejected edges and GPS readings (arrival order, increasing)."""
        cm = self.cap_m
        return (np.flatnonzero(self.rejected[: self.m]),
                np.flatnonzero(self.rejected[cm: cm + self.g]))

    # ----------------------------------------------------------------- estimates
    def pose(self, p: int) -> tuple[np.ndarray, np.ndarray]:
        """Global pose of placed pose ``p``, O(tree depth)."""
        ro, to = np.empty((3, 3)), np.empty(3)
        tk.global_pose(p + 1, self.parent, self.rot, self.trans, ro, to)
        return ro, to

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Global poses ``(R (n, 3, 3), t (n, 3))`` in arrival order, O(n); poses not yet
        placed are their odometry composed onto their parent's estimate."""
        t = self.placed + 1
        grot = np.empty((t, 3, 3))
        gtr = np.empty((t, 3))
        tk.globals_from_locals(np.arange(t, dtype=np.int32), self.parent, self.rot, self.trans,
                               grot, gtr)
        rot = np.empty((self.n, 3, 3))
        trans = np.empty((self.n, 3))
        rot[: self.placed] = grot[1:]
        trans[: self.placed] = gtr[1:]
        for p in range(self.placed, self.n):
            if p == 0:
                rot[0], trans[0] = self.first_rot, self.first_trans
                continue
            e = int(self.odom[p])
            a = int(self.edge_ab[e, 0])
            rot[p] = rot[a] @ self.edge_rot[e]
            trans[p] = rot[a] @ self.edge_trans[e] + trans[a]
        return rot, trans

    def path_entries(self) -> int:
        """Path pool entries in use (edges and GPS readings)."""
        return int(self.ptr[self.m_laid]) + int(self.ptr[self.cap_m + self.g_laid]
                                                - self.cap_pe)
