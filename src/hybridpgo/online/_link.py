"""The frames' side of the background worker: what was shipped, asked for and adopted.

:class:`WorkerLink` ships every pose, constraint and GPS reading of a :class:`~.store.MapStore`
to the worker process of :mod:`.worker` once it is integrated, asks for the optimum of what was
shipped, and adopts each answer into the store by one copy of the local transforms of the poses
it covers (the poses added after its snapshot keep their local transforms, so they move along
with their tree parents).  It also decides when the adopted optimum is still the optimum of
everything added since (:meth:`WorkerLink.holds`).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .store import MapStore
from .worker import GPS_GAUGE, BackgroundRefiner, Refined


def adopt_result(store: MapStore, res: Refined, rebase: bool) -> bool:
    """Replace the local transforms of the result's poses (one copy, O(n)); the poses added
    after its snapshot keep theirs (they move along with their tree parents).  With ``rebase``,
    the constraints laid after the snapshot that were relaxed before are queued to be relaxed
    again first, in arrival order, on top of the optimum (``store.requeue``: each started only
    when it fits the frame; those still waiting for their first update keep their place in
    the queue of new ones).  False (nothing done) for a result of poses not placed."""
    n = res.n
    if n > store.placed:  # cannot happen: only placed poses are shipped
        return False
    store.rot[1: n + 1] = res.rotations
    store.trans[1: n + 1] = res.translations
    if res.rejected is not None:  # robust="auto": the worker's verdict on what it holds
        store.set_rejected(*res.rejected, res.holds_all)
    if rebase:
        tail = np.concatenate([np.arange(res.m, store.m_laid, dtype=np.int64),
                               store.cap_m + np.arange(res.g, store.g_laid, dtype=np.int64)])
        store.requeue = tail[~np.isin(tail, store.pending())]
    return True


#: Asynchronously, an answer whose snapshot misses more than this many constraints laid since
#: is not adopted.  Adopting rewinds the poses it covers to the optimum of an old prefix and
#: queues the constraints since to be relaxed again, frame by frame; with a tail of thousands
#: the map is worse for it than the frames had made it (paris2 back to back, answers 5 000
#: frames late: 14x the optimum at the end, 2.3x without the worker, 1.48x with this limit).
MAX_TAIL = 1000
#: A loop closure whose path has at least this many nodes is long: while one laid after the
#: adopted answer's snapshot waits for an answer that holds it, the frames make no
#: spare-time updates (:meth:`WorkerLink.awaits_loop`; asynchronous mode, without
#: ``background_tail_only``).  After such a closure the frames' single steps of the older
#: constraints push the map away from the optimum rather than settle it: valencia streamed
#: back to back, its loop at frame 8 497 (2 936 poses around, a path of 1 069 tree nodes)
#: relaxed to 3.5x the prefix optimum, then 5.1x after the next frame's spare-time updates,
#: and 1.14x once the worker's answer came four frames later.  Shorter closures keep the
#: spare-time updates, which settle the constraints around them (grid10k, longest path 382
#: nodes, with updates of the tail only: worst checkpoint 1.035-1.041x against
#: 1.011-1.034x; paris2's longest path is 958 nodes).  The odometry edge of a pose linked to
#: the earth (GPS) has a path through the earth, as long as the two poses' depths: on a map
#: with readings 1 000 or more poses apart such edges hold spare time too (not measured).
LONG_LOOP = 1000
#: Frames, and seconds, at most that spare-time updates wait for the answer that holds a long
#: closure, or in frames that add nothing for the answer that holds everything
#: (:meth:`WorkerLink.awaits_all`; the worker far behind, or its answers refused): then they go
#: on as usual.
LONG_LOOP_WAIT = 50
LONG_LOOP_WAIT_S = 1.0


def _within_wait(since: tuple[int, float], frame: int, now: float) -> bool:
    """Whether a wait that began at ``since`` (frame, :func:`time.perf_counter` time) is
    within :data:`LONG_LOOP_WAIT` frames and :data:`LONG_LOOP_WAIT_S` seconds at ``frame``,
    ``now``."""
    return frame - since[0] < LONG_LOOP_WAIT and now - since[1] < LONG_LOOP_WAIT_S


#: Requests whose round trips :meth:`WorkerLink.settle` takes the median of (the worker's
#: time per request has a long tail: M3500_isam back to back, median 3.7 ms, mean 8.2 ms).
ANSWER_WINDOW = 16
#: Weight of the newest adoption's time in their moving average.
ADOPT_RATE = 0.3
#: An adoption's time before any was measured (seconds).
ADOPT_S0 = 5e-4
#: A frame waits for an answer only until this many times an adoption's average time, and
#: :data:`WAKE_S` more, before its deadline, so that the adoption fits in the frame.
ADOPT_MARGIN = 2.0
#: Seconds kept for the frame's thread to run again once the answer wakes it (the worker
#: holds the other core, and the answer's receiving thread the GIL for a moment).
WAKE_S = 5e-4


class WorkerLink:
    """Bookkeeping of one solver's background worker (module docstring).

    Parameters
    ----------
    iterations : int
        Most LM iterations of one background solve.
    robust : str
        ``"none"`` or ``"NAME:DELTA"``: the robust kernel of the worker's solves.
    """

    def __init__(self, iterations: int, robust: str = "none") -> None:
        self.refiner = BackgroundRefiner(iterations, robust)
        self.sent = (0, 0, 0)
        """Poses placed, edges and GPS readings laid that were shipped."""
        self.join_req = -1
        """The outstanding request (-1: none)."""
        self.adopted = 0
        #: the newest long loop closure found waiting (-1: none), and the frame and time
        #: its wait began (:meth:`awaits_loop`)
        self._loop_edge = -1
        self._loop_since = (0, 0.0)
        self.loop_floor = 0
        """Edges laid before this are never counted as waiting (a restored map's)."""
        self.refined = (0, 0)
        """Edges and GPS readings covered by the adopted optimum."""
        # holds(): tree nodes <= tail[0] are the adopted result's; the constraints after it
        # checked up to (tail[1], tail[2]) keep it the optimum while tail_ok
        self.tail = (0, 0, 0)
        self.tail_ok = False
        self.adopt_s_max = 0.0
        self.lag_max = 0
        self.stale = 0
        """Answers not adopted: their estimate missed more than :data:`MAX_TAIL` constraints."""
        self.other_gauge = 0
        """Answers not adopted: solved with the first pose held while the frames' map has GPS
        readings (fewer than :data:`~.worker.GPS_GAUGE`)."""
        self._ship_frames: dict[int, int] = {}
        self.rescreens = 0
        """The newest answer's count of screenings that ran the robust re-solve."""
        self.fallback = ""
        """The newest answer's word on why the worker left its incremental solver ("": it
        has not)."""
        self.resets = 0
        """The newest answer's count of the worker's failed incremental solves."""
        self.with_lm = False
        """The newest answer's word that the worker's map is solved by LM, measured faster."""
        self.answer_s = np.nan
        """Median wall time from a request that brings new data to its answer's arrival,
        over the last :data:`ANSWER_WINDOW` such requests (NaN: none measured yet)."""
        self._trips = np.full(ANSWER_WINDOW, np.nan)
        self._ntrips = 0
        self.adopt_s = ADOPT_S0
        """Moving average of an adoption's wall time."""
        self.settled = 0
        """Answers adopted inside the frame that requested them (:meth:`settle`)."""
        self._req_at = 0.0  # when the outstanding request was made
        #: the map's (placed, laid, GPS laid) found awaited last, and the frame and time its
        #: wait began (:meth:`awaits_all`)
        self._all_state = (-1, -1, -1)
        self._all_since = (0, 0.0)
        self._req_new = False  # whether it brought new data
        self._req_sent = (-1, -1, -1)  # self.sent at the last request

    def close(self) -> None:
        self.refiner.close()

    # ----------------------------------------------------------------- frames
    def step(self, store: MapStore, frame: int, join: int, rebase: bool) -> None:
        """Adopt a ready result and ask again (``join`` K > 0: only every K-th frame,
        waiting for the answer to the previous request).

        Asynchronous (``join`` 0), the frame's new data goes every frame, while a request is
        outstanding too (the worker queues it for its next solve): each frame encodes only its
        own poses and constraints, never the backlog of the frames a long solve took.  With
        ``join`` K the data goes with each request, so that what a request covers does not
        depend on timing."""
        ref = self.refiner
        if join == 0:  # asynchronous: one request at a time, adopted when its answer is there
            shipped = self.ship(store, frame)
            # the answer, or while waiting for the next, one that came after the last taken
            # (the worker's screening after an answer re-solved the map: worker.screen_after)
            res = self._take()
            if res is not None and self.fresh(store, res):
                self.adopt(store, res, frame, rebase)
            if self.join_req >= 0:  # still waiting
                if shipped and not self._req_new:
                    # the worker is polishing an unchanged map: the new data stops the
                    # polish, and this request, answered instead, covers it
                    self.request(store, frame)
                return
            self.request(store, frame)
        elif frame % join == 0:
            if self.join_req >= 0:
                res = ref.wait(self.join_req)
                if res is not None:
                    self.adopt(store, res, frame, rebase)
            # screened before the answer, so that what an answer holds does not depend on
            # when the worker's screening ends
            self.request(store, frame, defer=False)

    def fresh(self, store: MapStore, res: Refined) -> bool:
        """True when at most :data:`MAX_TAIL` constraints laid are missing from the answer's
        estimate (laid after its snapshot, or shipped but not yet integrated by a solve
        stopped by its cap); else it is counted in ``stale`` and not adopted."""
        hm, hg = res.holds_all
        tail = store.m_laid - hm + store.g_laid - hg
        if tail <= MAX_TAIL:
            return True
        self.stale += 1
        return False

    def request(self, store: MapStore, frame: int, thorough: bool = False,
                defer: bool = True) -> None:
        """Ship the new data and ask for the optimum of everything shipped (``thorough``,
        ``defer``: :meth:`~.worker.BackgroundRefiner.request`)."""
        self.ship(store, frame)
        self.join_req = self.refiner.request(thorough, defer)
        self._req_at = time.perf_counter()
        self._req_new = self.sent != self._req_sent
        self._req_sent = self.sent

    def _take(self) -> Refined | None:
        """The newest answer not taken yet (None: none, or the worker failed); no request is
        outstanding once the outstanding one was answered.  A request that brought new data
        times the round trip to its first answer (:attr:`answer_s`)."""
        answered = self.join_req >= 0 and self.refiner.answered(self.join_req)  # then take
        res = self.refiner.take()
        if (res is not None and res.req == self.join_req and self._req_new
                and res.status != "screened"):
            self._trips[self._ntrips % ANSWER_WINDOW] = res.received - self._req_at
            self._ntrips += 1
            self.answer_s = float(np.nanmedian(self._trips))
        if answered:
            self.join_req = -1
        return res

    def settle(self, store: MapStore, frame: int, rebase: bool, deadline: float) -> bool:
        """Wait for the outstanding request's answer and adopt it while the frame's time
        lasts (asynchronous mode, after the frame's new constraints were relaxed).  The wait
        is made only when the answer is expected (:attr:`answer_s` after the request) early
        enough to be adopted (:attr:`adopt_s`) before ``deadline`` (a
        :func:`time.perf_counter` time); an answer that misses constraints laid since its
        snapshot is adopted, and a new request made and waited for likewise.  True when an
        answer holding every constraint laid was adopted: the map is then the optimum of
        everything added, and no request is left outstanding (the next frame's data comes
        with the next one; a request without new data would make the worker polish)."""
        ref = self.refiner
        while self.join_req >= 0:
            now = time.perf_counter()
            until = deadline - ADOPT_MARGIN * self.adopt_s - WAKE_S
            if not ref.answered(self.join_req):
                expected = self._req_at + (self.answer_s if self._req_new else np.inf)
                if not (expected <= until and now < until):
                    return False
                if not ref.wait_answered(self.join_req, until - now):
                    return False
            res = self._take()
            if res is None or not self.fresh(store, res):
                return False
            if not self.adopt(store, res, frame, rebase):
                return False
            if res.holds_all == (store.m_laid, store.g_laid) and res.n == store.placed:
                self.settled += 1
                return True
            self.request(store, frame)
        return False

    def ship(self, store: MapStore, frame: int) -> bool:
        """Send the poses placed, edges and GPS readings laid since the last call (O(new));
        False when there was nothing new."""
        sn, sm, sg = self.sent
        n, m, g = store.placed, store.m_laid, store.g_laid
        if (sn, sm, sg) == (n, m, g):
            return False
        self.refiner.ship({"type": "data"}, {
            "parent": store.parent[sn + 1: n + 1], "rot": store.rot[sn + 1: n + 1],
            "trans": store.trans[sn + 1: n + 1],
            "edge_ab": store.edge_ab[sm:m], "edge_rot": store.edge_rot[sm:m],
            "edge_trans": store.edge_trans[sm:m], "edge_info": store.edge_info[sm:m],
            "gps_node": store.gps_node[sg:g], "gps_pos": store.gps_pos[sg:g],
            "gps_info": store.gps_info[sg:g],
        })  # fmt: skip
        self.sent = (n, m, g)
        self._ship_frames[n] = frame
        return True

    def adopt(self, store: MapStore, res: Refined, frame: int, rebase: bool) -> bool:
        """:func:`adopt_result`, and the bookkeeping of :meth:`holds` and :meth:`stats`; False
        when the answer is not adopted.

        An answer that holds GPS readings but fewer than :data:`~.worker.GPS_GAUGE` is not
        adopted: the worker held the first pose where the stream started, while from the first
        reading the frames let the readings move the whole map (into the readings' frame,
        which may lie kilometres away): the two maps are in different gauges."""
        t0 = time.perf_counter()
        n = res.n
        if 0 < res.g < GPS_GAUGE:
            self.other_gauge += 1
            return False
        if not adopt_result(store, res, rebase):
            return False
        self.refined = res.holds_all
        self.rescreens = res.rescreens
        self.fallback = res.fallback
        self.resets, self.with_lm = res.resets, res.with_lm
        self.tail, self.tail_ok = (n, *res.holds_all), True
        self.adopted += 1
        took = time.perf_counter() - t0
        self.adopt_s_max = max(self.adopt_s_max, took)
        self.adopt_s += ADOPT_RATE * (took - self.adopt_s)
        shipped = self._ship_frames.get(n)
        if shipped is not None:
            self.lag_max = max(self.lag_max, frame - shipped)
        for key in [k for k in self._ship_frames if k < n]:
            del self._ship_frames[key]
        return True

    def holds(self, store: MapStore) -> bool:
        """True while the adopted optimum is also the optimum of everything added since: each
        constraint laid after its snapshot is a path of one node, added after it, with no other
        path through it (a new pose on its odometry or GPS link).  O(constraints since the
        last call)."""
        if not self.tail_ok:
            return False
        tail_n, tail_m, tail_g = self.tail
        ptr, node, count = store.ptr, store.path_node, store.path_count
        cm = store.cap_m
        for c in (*range(tail_m, store.m_laid), *range(cm + tail_g, cm + store.g_laid)):
            lo = int(ptr[c])
            if int(ptr[c + 1]) - lo != 1:
                self.tail_ok = False
                return False
            u = int(node[lo])
            if u <= tail_n or int(count[u]) != 1:
                self.tail_ok = False
                return False
        self.tail = (tail_n, store.m_laid, store.g_laid)
        return True

    def awaits_loop(self, store: MapStore, frame: int) -> bool:
        """True while a loop closure of at least :data:`LONG_LOOP` path nodes, laid after the
        adopted answer's snapshot (and after :attr:`loop_floor`) and not rejected, waits for
        an answer that holds it: for at most :data:`LONG_LOOP_WAIT` frames and
        :data:`LONG_LOOP_WAIT_S` seconds from the first call that found the newest such
        closure waiting, and while the worker is alive, its newest message was no error and
        the link to it works (:attr:`~.worker.BackgroundRefiner.failing`; a closure's wait
        runs on while it does not).  O(constraints laid since the snapshot)."""
        if not self.refiner.alive or self.refiner.failing:
            return False
        fm, laid = max(self.refined[0], self.loop_floor), store.m_laid
        newest = -1
        if laid > fm:
            ptr = store.ptr
            lens = ptr[fm + 1: laid + 1] - ptr[fm:laid]
            if store.num_rejected:  # the frames leave a rejected closure alone
                lens = np.where(store.rejected[fm:laid], 0, lens)
            long = np.flatnonzero(lens >= LONG_LOOP)
            newest = fm + int(long[-1]) if long.size else -1
        if newest < 0:
            self._loop_edge = -1
            return False
        now = time.perf_counter()
        if newest != self._loop_edge:  # a closure not seen waiting before: its wait begins
            self._loop_edge, self._loop_since = newest, (frame, now)
        return _within_wait(self._loop_since, frame, now)

    def awaits_all(self, store: MapStore, frame: int) -> bool:
        """True while the outstanding request holds everything placed and laid (its answer
        is the optimum of the whole map as it stands), for at most :data:`LONG_LOOP_WAIT`
        frames and :data:`LONG_LOOP_WAIT_S` seconds from the first call that found the map
        as it stands awaited (requests made again meanwhile, their answers refused, do not
        lengthen the wait), and while the worker is alive, its newest message was no error
        and the link to it works.  O(1)."""
        if self.join_req < 0 or not self.refiner.alive or self.refiner.failing:
            return False
        state = (store.placed, store.m_laid, store.g_laid)
        if self._req_sent != state:
            return False
        now = time.perf_counter()
        if state != self._all_state:  # the map as it stands, found awaited: its wait begins
            self._all_state, self._all_since = state, (frame, now)
        return _within_wait(self._all_since, frame, now)

    def join(self, store: MapStore, frame: int, timeout: float | None,
             rebase: bool) -> bool:
        """Ship everything, wait for the optimum of it and adopt it (True when it came); with
        ``robust="auto"`` every constraint is tested, as a whole-graph solve tests them."""
        self.request(store, frame, thorough=True)
        req = self.join_req
        res = self.refiner.wait(req, timeout)
        return (res is not None and self.adopt(store, res, frame, rebase)
                and res.req >= req)

    def stats(self) -> dict[str, Any]:
        return {"results_adopted": self.adopted, "results_stale": self.stale,
                "results_other_gauge": self.other_gauge, "rescreens": self.rescreens,
                "adopt_ms_max": self.adopt_s_max * 1e3,
                "lag_frames_max": self.lag_max, "results_received": self.refiner.results,
                "results_settled": self.settled,
                "worker_fallback": self.fallback, "worker_resets": self.resets,
                "worker_with_lm": self.with_lm,
                "error": self.refiner.error}
