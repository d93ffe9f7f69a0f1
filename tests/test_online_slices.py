"""A long single update in slices: the same result as the single update, spread over frames
whose budget it cannot fit, never dropped, given up only to be started again.

No test reads the clock's values: a budget is either spent already (a deadline in the past:
one slice per call) or absent, and the cost model is set so that a long update never fits.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hybridpgo.online import OnlineConfig, OnlineSolver
from hybridpgo.online.solver import MIN_SLICED
from hybridpgo.solvers.hybrid import _admission as adm
from hybridpgo.solvers.hybrid import _slices
from hybridpgo.solvers.hybrid._step import relax
from hybridpgo.solvers.hybrid.problem import State, StepKind, new_workspace


def _corridor(n: int, seed: int = 0, background: bool = False,
              step: str = "woodbury") -> OnlineSolver:
    """A solver fed ``n`` poses of noisy odometry along a circle, each frame relaxed in full,
    then one loop closure from the last pose to the first, laid and queued (not relaxed)."""
    rng = np.random.default_rng(seed)
    s = OnlineSolver(OnlineConfig(background_refine=background, step=step))
    s.add_pose(0)
    ang = 2 * np.pi / n
    step_r = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0],
                       [0, 0, 1.0]])
    step_t = np.array([1.0, 0.0, 0.0])
    for i in range(1, n):
        noise = rng.normal(0, 0.02, 3)
        s.add_pose(i, i - 1, (step_r, step_t + noise), np.eye(6))
        s.update(None)
    s.add_constraint(n - 1, 0, (step_r, step_t), np.eye(6) * 4.0)
    s._integrate()  # its path laid, as the next update would
    return s


def _never_fits(s: OnlineSolver) -> None:
    """A cost model under which no update of more than a few nodes fits any frame."""
    s.store.model[adm.MODEL_NODE] = 1e12


def _state_copy(s: OnlineSolver) -> tuple[np.ndarray, ...]:
    st = s.store
    return st.rot.copy(), st.trans.copy(), st.bdiag.copy(), st.contrib.copy()


def test_slices_run_through_are_the_single_update_bit_for_bit() -> None:
    """The slices, one per call, give the single update's poses, 𝔅(H) and contributions
    exactly (the same products in the same order), whatever the step's outcome."""
    s = _corridor(400)
    st = s.store
    c = int(st.pending()[0])
    prob, _, _ = st.views()
    d = int(st.ptr[c + 1] - st.ptr[c])
    assert d >= MIN_SLICED
    single = State(*_state_copy(s))
    relax(prob, single, new_workspace(d), c, 1.0, s.config.damping,
          int(StepKind.WOODBURY), True)
    sliced = State(*_state_copy(s))
    lu, lf = _slices.new_state()
    _slices.begin(prob, c, lu, lf)
    wk = new_workspace(d)
    calls = 0
    while not _slices.advance(prob, sliced, wk, lu, lf, 1.0, s.config.damping, np.uint64(0)):
        calls += 1
    # one slice per call: the setup, then four passes of ceil(d / SLICE) slices
    assert calls + 1 == 1 + 4 * -(-d // _slices.SLICE)
    assert lu[_slices.STATUS] == 0  # APPLIED: the step was taken in full
    for a, b in zip(single, sliced, strict=True):
        assert np.array_equal(a, b)
    assert not np.array_equal(sliced.rot, st.rot)  # the update moved the poses


def test_a_long_new_constraint_is_relaxed_in_slices_across_frames() -> None:
    """A frame whose budget cannot hold the first new constraint's single update runs slices
    of it instead (one per frame with the budget spent), keeps it first in the queue until it
    is done, and ends in the state the single update gives."""
    s = _corridor(400)
    twin = _corridor(400)
    rep = twin.update(None, max_updates=1)
    assert rep.new == 1 and twin.backlog == 0
    _never_fits(s)
    c = int(s.store.pending()[0])
    frames = 0
    while s.backlog:
        s._input_cycles = 1 << 62  # the frame's budget spent by its add_* calls
        rep = s.update(5e-3)
        frames += 1
        if s.backlog:
            assert rep.new == 0 and int(s.store.pending()[0]) == c
            assert s.stats()["sliced_updates"]["under_way"]
    assert rep.new == 1 and frames > 4
    assert s.stats()["sliced_updates"] == {"done": 1, "given_up": 0, "under_way": False}
    for a, b in zip(_state_copy(s), _state_copy(twin), strict=True):
        assert np.array_equal(a, b)


def test_constraints_behind_an_update_in_slices_keep_their_order() -> None:
    """While the first constraint is relaxed in slices, those behind it are relaxed when they
    fit and leave the queue; the sliced one stays first until it is done."""
    s = _corridor(300)
    s.add_pose(300, 299, (np.eye(3), np.array([1.0, 0.0, 0.0])), np.eye(6))
    s.add_pose(301, 300, (np.eye(3), np.array([1.0, 0.0, 0.0])), np.eye(6))
    _never_fits(s)
    q0 = s.store.pending().copy()
    s._input_cycles = 1 << 62
    s.update(5e-3)
    assert s.stats()["sliced_updates"]["under_way"]
    assert np.array_equal(s.store.pending(), q0)  # nothing fits: the queue is unchanged
    s.store.model[adm.MODEL_NODE] = 0.0  # short updates fit again; the sliced one goes on
    rep = s.update(1.0)
    assert s.backlog == 0 and rep.new == 3  # the sliced one, then the two behind it
    assert s.stats()["sliced_updates"]["done"] >= 1


def test_spare_time_relaxes_long_older_constraints_in_slices() -> None:
    """Spare time runs the long older constraints in slices (here the loop closure, relaxed
    once already), one at a time, and none when the frame has no time left."""
    s = _corridor(300)
    s.update(None)
    assert s.backlog == 0 and s.stats()["sliced_updates"]["done"] == 0
    _never_fits(s)  # no short update fits: only the slices, timed, run
    s._input_cycles = 1 << 62
    rep = s.update(5e-3)
    assert rep.old == 0 and s.stats()["sliced_updates"]["done"] == 0
    rep = s.update(1.0)
    assert rep.old == 1 and s.backlog == 0
    assert s.stats()["sliced_updates"] == {"done": 1, "given_up": 0, "under_way": False}


def test_an_adopted_answer_gives_up_the_update_in_slices_and_starts_it_again() -> None:
    """An answer adopted from the worker replaces the poses the slices' step was computed at:
    the update is given up and its constraint, still first in the queue, is relaxed afresh."""
    s = _corridor(300, background=True)
    try:
        _never_fits(s)
        link = s._link
        assert link is not None
        link.step = lambda *a, **k: None  # type: ignore[method-assign]  # no real adoption
        link.settle = lambda *a, **k: False  # type: ignore[method-assign]
        c = int(s.store.pending()[0])
        s._input_cycles = 1 << 62
        s.update(5e-3)
        assert s.stats()["sliced_updates"]["under_way"]
        link.adopted += 1  # as adopt() does
        s._input_cycles = 1 << 62
        s.update(5e-3)
        sl = s.stats()["sliced_updates"]
        assert sl["given_up"] == 1 and sl["under_way"] and int(s.store.pending()[0]) == c
        while s.backlog:
            s._input_cycles = 1 << 62
            s.update(5e-3)
        assert s.stats()["sliced_updates"]["done"] == 1
    finally:
        s.close()


@pytest.mark.parametrize("step", ["givens", "woodbury"])
def test_only_long_woodbury_updates_are_sliced(step: str) -> None:
    """Givens' O(d^2) solve has no slices (the update is started whole, as the first new
    constraint of a frame always is); nor has a short update."""
    s = _corridor(300, step=step)
    _never_fits(s)
    s._input_cycles = 1 << 62
    rep = s.update(5e-3)
    assert s.stats()["sliced_updates"]["under_way"] == (step == "woodbury")
    assert rep.new == (step == "givens")
    short = OnlineSolver(OnlineConfig(background_refine=False, step=step))
    short.add_pose(0)
    for i in range(1, 20):
        short.add_pose(i, i - 1, (np.eye(3), np.array([1.0, 0.0, 0.0])), np.eye(6))
    _never_fits(short)
    short._input_cycles = 1 << 62
    rep = short.update(5e-3)
    assert rep.new == 1 and not short.stats()["sliced_updates"]["under_way"]


def test_a_saved_state_keeps_the_constraint_an_update_in_slices_was_relaxing(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Saving in the middle of an update in slices keeps its constraint queued: the loaded
    solver relaxes it afresh."""
    s = _corridor(300)
    _never_fits(s)
    c = int(s.store.pending()[0])
    s._input_cycles = 1 << 62
    s.update(5e-3)
    assert s.stats()["sliced_updates"]["under_way"]
    s.save(tmp_path / "state.npz")
    t = OnlineSolver.load(tmp_path / "state.npz")
    assert t.backlog == 1 and int(t.store.pending()[0]) == c
    assert not t.stats()["sliced_updates"]["under_way"]
    t.update(None)
    assert t.backlog == 0


def test_an_update_in_slices_overtaken_by_its_groups_batch_is_given_up() -> None:
    """When the junction group's batch relaxes the constraint an update in slices is on, the
    slices stop (their step would correct the same residual twice) and the constraint leaves
    the queue, relaxed."""
    s = _corridor(300)
    _never_fits(s)
    s._input_cycles = 1 << 62
    s.update(5e-3)
    sl = s._sliced
    assert sl is not None and sl.new
    st = s.store
    # as if the constraint were in group 0 and that group's batch ran in a later frame
    s._sliced = dataclasses.replace(sl, group=0, stamp=int(st.group_stamp[0]))
    st.group_stamp[0] += 1
    s._input_cycles = 1 << 62
    rep = s.update(5e-3)
    assert rep.new == 1 and s.backlog == 0
    assert s.stats()["sliced_updates"] == {"done": 0, "given_up": 1, "under_way": False}


def test_a_shorter_update_is_sliced_only_when_it_does_not_fit() -> None:
    """Between one slice's nodes and :data:`MIN_SLICED`, the first new constraint runs in
    slices when its single update is predicted not to fit (the loop would start it whatever
    its cost), and whole when it fits."""
    n = (_slices.SLICE + MIN_SLICED) // 2
    late = _corridor(n)
    c = int(late.store.pending()[0])
    d = int(late.store.ptr[c + 1] - late.store.ptr[c])
    assert _slices.SLICE <= d < MIN_SLICED
    _never_fits(late)
    late._input_cycles = 1 << 62
    rep = late.update(5e-3)
    assert late.stats()["sliced_updates"]["under_way"] and rep.new == 0
    in_time = _corridor(n)
    in_time.store.model[adm.MODEL_NODE] = 0.0
    rep = in_time.update(1.0)
    assert rep.new == 1 and in_time.stats()["sliced_updates"] == {
        "done": 0, "given_up": 0, "under_way": False}
