"""The online mode's frame budget: the whole frame's work counts, what does not fit is carried
over (never dropped), and the cost model admits long updates on the cost of long updates.

No test reads the clock's values: budgets are either spent already (a deadline in the past) or
absent, and the cost model is a pure function of the samples it is given.
"""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo.online import OnlineConfig, OnlineSolver
from hybridpgo.online.replay import feed_frame, make_stream
from hybridpgo.solvers.hybrid import _admission as adm


def _graph(seed: int = 0, n: int = 60, extra: int = 30):  # type: ignore[no-untyped-def]
    g, _, _ = random_graph(np.random.default_rng(seed), n=n, extra=extra, noise=0.02)
    return g


def _spend_frame(s: OnlineSolver) -> None:
    """As if this frame's add_* calls had used a whole day of cycles (every budget is spent)."""
    s._input_cycles = 1 << 62


def test_add_calls_are_charged_to_their_frame() -> None:
    g = _graph()
    st = make_stream(g)
    s = OnlineSolver()
    assert s._input_cycles == 0
    feed_frame(s, st, 0)
    feed_frame(s, st, 1)
    assert s._input_cycles > 0  # the add_* calls' cycles, waiting for their frame's update
    s.update(5e-3)
    assert s._input_cycles == 0  # charged to that update, not to the next frame
    feed_frame(s, st, 2)
    s.update(None)  # an unbudgeted frame also takes the charge (and ignores it)
    assert s._input_cycles == 0


def test_spent_frame_carries_its_work_over_and_drops_nothing() -> None:
    """A frame whose add_* calls used its budget relaxes only the first new constraint (the
    one unit a frame always makes); the rest waits in the queue and later frames relax every
    constraint, in arrival order."""
    g = _graph(seed=3)
    st = make_stream(g)
    s = OnlineSolver()
    for k in range(st.num_frames):
        feed_frame(s, st, k)
    total = s.backlog
    assert total == g.num_edges
    _spend_frame(s)
    r = s.update(5e-3)
    assert (r.new, r.backlog, r.old) == (1, total - 1, 0)
    queued = s.store.pending().copy()
    assert np.array_equal(queued, np.arange(1, total))  # carried over in arrival order
    frames = 0
    while s.backlog:
        _spend_frame(s)
        r = s.update(5e-3)
        assert r.new == 1 and r.old == 0  # never more than the admitted unit
        frames += 1
    assert frames == total - 1  # one per frame: nothing dropped, nothing skipped
    # every constraint was relaxed: its update's cycles are recorded
    assert np.all(s.store.cycles[: s.num_edges] > 0)


@pytest.mark.parametrize(("batch", "large", "large_cost", "small", "small_cost"), [
    (False, 3000, 4000.0, 8, 800.0),  # single updates: a cache-missing long path
    (True, 1250, 1700.0, 12, 150.0),  # batches: GPS pairs, junction groups of short paths
])
def test_large_updates_are_predicted_from_large_updates(batch: bool, large: int,
                                                        large_cost: float, small: int,
                                                        small_cost: float) -> None:
    """Hundreds of short updates (or small batches) per frame do not pull the cost per node
    (per batch entry) below what a long update (a large batch) costs: its prediction covers
    its measured cost; batches never teach the base."""
    model = np.array(adm.MODEL0)
    for _ in range(40):
        adm.learn(model, large, model[adm.MODEL_BASE] + large * large_cost, batch)
        for _ in range(300):
            adm.learn(model, small, model[adm.MODEL_BASE] + small * small_cost, batch)
    assert adm.predict(model, large, batch) >= model[adm.MODEL_BASE] + large * large_cost
    if batch:
        assert model[adm.MODEL_BASE] == adm.MODEL0[adm.MODEL_BASE]


def test_add_calls_do_not_copy_the_map() -> None:
    """add_* writes in place: with the default reservation no array of the map moves while it
    grows (a frame never pays for copying the map)."""
    g = _graph(seed=5, n=400, extra=100)
    st = make_stream(g)
    s = OnlineSolver()
    feed_frame(s, st, 0)
    s.update(None)
    store = s.store
    names = ("parent", "rot", "edge_rot", "edge_info", "path_node", "contrib", "ptr", "chi2")
    before = {k: getattr(store, k).__array_interface__["data"][0] for k in names}
    for k in range(1, st.num_frames):
        feed_frame(s, st, k)
        s.update(None, 4)
    after = {k: getattr(store, k).__array_interface__["data"][0] for k in names}
    assert before == after


def test_frames_leave_nothing_for_the_garbage_collector() -> None:
    """A frame's work (add_*, update, pose) leaves no object the collector tracks: a full
    collection walks every tracked object, so a map that left some per pose or constraint
    would make the collections of a long stream longer and longer (tens of ms at 40 000
    poses), in whichever frame they fall."""
    import gc

    g = _graph(seed=4, n=400, extra=300)
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    for k in range(100):  # warm-up: buffers, caches and compiled dispatchers settle
        feed_frame(s, st, k)
        s.update(None, 8)
    gc.collect()
    before = len(gc.get_objects())
    for k in range(100, st.num_frames):
        feed_frame(s, st, k)
        s.update(None, 8)
        s.pose(int(g.node_ids[st.order[k]]))
    gc.collect()
    grown = len(gc.get_objects()) - before
    assert grown < 50, f"{grown} tracked objects after {st.num_frames - 100} frames"
    assert not gc.is_tracked(s.store.pair_last)  # integer keys and values only


@pytest.mark.parametrize("enabled", [True, False])
def test_no_garbage_collection_starts_inside_a_frame(enabled: bool) -> None:
    """With the collector's threshold at 1, any tracked allocation starts a collection: none
    starts while add_*, update or pose runs (a collection walks the whole process's objects,
    the application's too), the ones that fell due run at allocations outside, and the
    collector is left on or off as the caller had it."""
    import gc
    import sys

    import hybridpgo.online.solver as solver_module

    g = _graph(seed=5, n=80, extra=40)
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    feed_frame(s, st, 0)
    s.update(None)  # the process's first solver compiles and freezes before the counts
    started: list[bool] = []

    def on_collection(phase: str, info: dict[str, int]) -> None:
        if phase == "start":  # is a method of the solver on the stack?
            f = sys._getframe(1)
            while f is not None and f.f_code.co_filename != solver_module.__file__:
                f = f.f_back
            started.append(f is not None)

    thresholds = gc.get_threshold()
    was = gc.isenabled()
    gc.callbacks.append(on_collection)
    try:
        gc.set_threshold(1, 1, 1)
        (gc.enable if enabled else gc.disable)()
        for k in range(1, st.num_frames):
            feed_frame(s, st, k)
            s.update(None, 4)
            s.pose(int(g.node_ids[st.order[k]]))
            assert gc.isenabled() == enabled
    finally:
        gc.callbacks.remove(on_collection)
        gc.set_threshold(*thresholds)
        (gc.enable if was else gc.disable)()
    assert not any(started), f"{sum(started)} collections started inside the solver"
    assert (len(started) > 0) == enabled  # the collections ran, outside the solver



def _until_group(st):  # type: ignore[no-untyped-def]
    """A solver fed frame by frame (each relaxed in full) until a frame forms a junction
    group; that frame is integrated but not updated.  Returns the solver and the group's
    members."""
    s = OnlineSolver(OnlineConfig(background_refine=False))
    store = s.store
    k = 0
    while True:
        ng = store.ngroups
        feed_frame(s, st, k)
        k += 1
        s._integrate()
        if store.ngroups > ng:
            break
        s.update(None)
    lo, hi = int(store.group_ptr[ng]), int(store.group_ptr[ng + 1])
    members = np.sort(store.group_members[lo:hi])
    assert members.size >= 2 and s.backlog == members.size  # the frame brings the group
    return s, members


def _city_stream():  # type: ignore[no-untyped-def]
    from hybridpgo.generate import generate_city

    return make_stream(generate_city(None, seed=1, num_poses=600, nx=4, ny=4,
                                     block_size_m=60.0, p_loop=0.1).graph)


def test_a_forced_junction_group_that_does_not_fit_goes_member_by_member() -> None:
    """The first new constraint of a frame is started whatever its cost, but when its junction
    group's batch does not fit, it is relaxed alone (a single update, in slices over several
    frames when its path is long); each further member comes first likewise, and none is
    dropped.  With time, the group is one batch (its members share the batch's cycle
    count)."""
    st = _city_stream()
    runs = {}
    for spent in (True, False):
        s, members = _until_group(st)
        relaxed = []
        while s.backlog and len(relaxed) < 1000:
            if spent:
                _spend_frame(s)
            r = s.update(5e-3 if spent else None)
            relaxed.append(int(np.count_nonzero(s.store.cycles[members])))
            if not spent:
                break
            assert r.new == relaxed[-1] - (relaxed[-2] if len(relaxed) > 1 else 0) <= 1
        runs[spent] = (members, relaxed, s.store.cycles[members].copy(), s.backlog)
    members, relaxed, cycles, backlog = runs[True]
    # one member at a time, in as many frames as its update takes
    assert sorted(set(relaxed)) == list(range(relaxed[0], members.size + 1))
    assert relaxed[0] <= 1 and backlog == 0
    assert np.unique(cycles).size == members.size  # single updates: each its own count
    members, relaxed, cycles, backlog = runs[False]
    assert relaxed == [members.size] and backlog == 0
    assert np.unique(cycles).size == 1  # one batch: its count shared by the members


def test_a_junction_group_no_budget_can_hold_goes_member_by_member() -> None:
    """A group whose batch is predicted to take longer than the call's whole budget
    (``Admission.span``) is relaxed by single updates of its members even with no deadline:
    under the policy its batch would never start."""
    from hybridpgo.online._frame import NO_DEADLINE
    from hybridpgo.solvers.hybrid._sweep import loop_kernel, run_loop
    from hybridpgo.solvers.hybrid.problem import NUM_COUNTS
    from hybridpgo.solvers.hybrid.solver import STEP_KINDS

    st = _city_stream()
    for span, distinct in ((0.0, None), (np.inf, 1)):
        s, members = _until_group(st)
        store, cfg = s.store, s.config
        prob, state, pol = store.views()
        store.span[0] = span
        counts = np.zeros(NUM_COUNTS, np.int64)
        done = run_loop(loop_kernel(True, False, False, True), prob, state, store.scratch(None),
                        members, cfg.tau_new, cfg.damping, int(STEP_KINDS[cfg.step]),
                        cfg.gps_batch_size, 0, NO_DEADLINE, counts, True, pol, 1, 1 << 62)
        cycles = store.cycles[members]
        assert done == members.size and np.all(cycles > 0)
        assert np.unique(cycles).size == (members.size if distinct is None else distinct)


def test_nothing_is_examined_past_the_deadline() -> None:
    """Past the deadline no update fits: a loop that skips what does not fit stops at once
    (the rest counted as skipped, none examined), and the spare-time pass is not made (its
    window of candidates stays where it was); nothing moves."""
    from hybridpgo.online._frame import NO_DEADLINE
    from hybridpgo.solvers.hybrid._sweep import loop_kernel, run_loop
    from hybridpgo.solvers.hybrid.problem import NUM_COUNTS, Count
    from hybridpgo.solvers.hybrid.solver import STEP_KINDS

    g = _graph(seed=6, n=400, extra=300)
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    for k in range(st.num_frames):
        feed_frame(s, st, k)
        s.update(None)
    store, cfg = s.store, s.config
    cand = np.arange(store.m_laid, dtype=np.int64)
    rot0, cursor0 = store.rot.copy(), s._cursor
    for deadline, stop in ((np.uint64(1), 0), (NO_DEADLINE, cand.size)):
        prob, state, pol = store.views()
        counts = np.zeros(NUM_COUNTS, np.int64)
        k = run_loop(loop_kernel(True, False, False, True), prob, state, store.scratch(None),
                     cand, cfg.tau_old, cfg.damping, int(STEP_KINDS[cfg.step]),
                     cfg.gps_batch_size, 0, deadline, counts, True, pol, 7, 1 << 62,
                     force_first=False, skip=True)
        assert k == stop
        if stop == 0:
            assert counts[Count.SKIPPED] == cand.size and counts[Count.DONE] == 0
            assert np.array_equal(store.rot, rot0)
    rot1 = store.rot.copy()
    counts = np.zeros(NUM_COUNTS, np.int64)
    assert s._spare_time(np.uint64(1), counts, 1 << 62, 99) == 0
    assert s._cursor == cursor0 and not counts.any()
    assert np.array_equal(store.rot, rot1)
    s._spare_time(NO_DEADLINE, counts, 1 << 62, 100)  # with time, the window moves on
    assert s._cursor != cursor0


def test_a_long_group_member_is_sliced_unless_its_batch_fits_with_a_slice_to_spare() -> None:
    """The frame's first new constraint, a long member of a junction group, is left to the
    loop's batch only when the batch fits with one slice's predicted cost to spare (the loop
    decides a moment later; a batch that no longer fits then has the member relaxed alone by
    one single update, unsliced).  The cost model makes a slice cost seconds, a batch
    nothing, so the decision does not depend on the time the test takes."""
    from hybridpgo._numba import read_cycles
    from hybridpgo.online._frame import NO_DEADLINE
    from hybridpgo.solvers.hybrid import _slices
    from hybridpgo.solvers.hybrid._sweep import group_cost

    st = _city_stream()
    decided = []
    for spare in (0.5, 2.0):
        s, members = _until_group(st)
        store = s.store
        lengths = store.ptr[members + 1] - store.ptr[members]
        long = int(members[int(np.argmax(lengths))])
        assert int(lengths.max()) >= _slices.SLICE and long < store.cap_m
        store.set_queue(np.concatenate([[long], store.pending()[store.pending() != long]]))
        store.model[adm.MODEL_NODE] = 1e8  # a slice: about 10^10 cycles
        store.model[adm.MODEL_BATCH] = 1.0
        store.span[0] = np.inf
        prob, _, pol = store.views()
        slice_cost = adm.predict(store.model, _slices.SLICE, False)
        batch = group_cost(prob, pol, int(store.group_of[long]))
        assert batch < 1e-3 * slice_cost
        deadline = np.uint64(int(read_cycles()) + int(batch + spare * slice_cost))
        decided.append(s._begin_sliced(deadline))
        assert s._begin_sliced(NO_DEADLINE) is False
    assert decided == [True, False]
