"""Saved online states: a crafted or damaged file is refused with one FormatError (never a
crash, a hang or a stray exception), a valid one continues exactly; saving follows the output
rules of every file the package writes."""

from __future__ import annotations

import io
import json
import os
import stat
import zipfile
from pathlib import Path

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo.errors import FormatError, GraphError
from hybridpgo.online import OnlineConfig, OnlineSolver
from hybridpgo.online.replay import feed_frame, make_stream


def _solver(n: int = 10, gps: int = 3, seed: int = 0) -> OnlineSolver:
    g, _, _ = random_graph(np.random.default_rng(seed), n=n + 6, extra=8, gps=gps, noise=0.02)
    s = OnlineSolver(OnlineConfig(reserve_poses=64, background_refine=False))
    st = make_stream(g)
    for k in range(n):
        feed_frame(s, st, k)
        s.update(None, 12)
    feed_frame(s, st, n)  # a frame not integrated yet: a queue and an unplaced pose
    return s


def _write(path: Path, members: dict[str, np.ndarray]) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, **members)  # type: ignore[arg-type]


def _exercise(s: OnlineSolver) -> None:
    """What a robot does after a load: add a pose, update, read poses."""
    ids = s.pose_ids()
    new = int(ids.max()) + 1
    s.add_pose(new, int(ids[-1]), (np.eye(3), np.array([1.0, 0.0, 0.0])), np.eye(6))
    s.update(None, 20)
    s.update(0.01)
    rot, trans = s.estimate()
    assert np.all(np.isfinite(rot)) and np.all(np.isfinite(trans))
    s.pose(new)
    s.energy()


def _continues_alike(s: OnlineSolver, t: OnlineSolver) -> None:
    """After the same update, ``s`` and ``t`` hold the same state."""
    for solver in (s, t):
        solver.update(None, 12)
    a, b = s.state_arrays(), t.state_arrays()
    for k in a:  # the cost model learns from the clock: not reproducible
        assert k == "model" or np.array_equal(a[k], b[k]), k


def test_a_saved_state_loads_and_continues_like_the_original(tmp_path: Path) -> None:
    s = _solver()
    path = tmp_path / "state.npz"
    s.save(path)
    t = OnlineSolver.load(path)
    a, b = s.state_arrays(), t.state_arrays()
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    _continues_alike(s, t)


def test_rejected_constraints_survive_save_and_load(tmp_path: Path) -> None:
    """The constraints rejected as outliers and the requeued ones are saved; the loaded solver
    has them rejected (no whitening, no contributions) and queued again, and continues exactly
    like the original."""
    s = _solver()
    st = s.store
    s.store.set_rejected(np.array([3, 7]), np.array([0]), (st.m_laid, st.g_laid))
    st.requeue = np.array([1, 2, 4], np.int64)  # relaxed before, queued again
    path = tmp_path / "state.npz"
    s.save(path)
    t = OnlineSolver.load(path)
    for a, b in zip(s.outliers(), t.outliers(), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(t.outliers()[0], [3, 7])
    np.testing.assert_array_equal(t.store.requeue, [1, 2, 4])
    assert not t.store.edge_lt[[3, 7]].any() and not t.store.gps_lt[0].any()
    _continues_alike(s, t)


def test_a_state_of_version_2_loads_with_nothing_rejected(tmp_path: Path) -> None:
    s = _solver()
    members = s.state_arrays()
    del members["rejected"]
    meta = json.loads(bytes(members["meta"]).decode())
    meta["version"] = 2
    members["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    path = tmp_path / "v2.npz"
    _write(path, members)
    t = OnlineSolver.load(path)
    assert t.store.num_rejected == 0
    _exercise(t)


@pytest.mark.parametrize("key", ["rejected", "requeue"])
@pytest.mark.parametrize("names", [[10**9], [-10**9], [2, 2], [-1, -1]])
def test_a_crafted_rejected_list_or_requeue_is_refused(tmp_path: Path, key: str,
                                                      names: list[int]) -> None:
    s = _solver()
    members = s.state_arrays()
    members[key] = np.array(names, np.int64)
    path = tmp_path / "crafted.npz"
    _write(path, members)
    with pytest.raises(FormatError, match=r"crafted\.npz"):
        OnlineSolver.load(path)


# --------------------------------------------------------------------------- reproducers
@pytest.mark.parametrize("key, value", [
    ("parent", 10**9), ("parent", -5), ("edge_ab", 10**9), ("edge_ab", -1), ("gps_node", 10**9),
    ("odom", 10**9), ("queue", 10**9), ("queue", -10**9), ("group_members", 10**9),
    ("group_ptr", 10**9), ("group_stamp", 10**12), ("model", -1.0), ("model", np.nan),
    ("chi2_e", -1.0), ("rot", np.inf), ("edge_info", np.nan), ("bdiag", np.inf),
])
def test_a_crafted_index_or_value_is_refused(tmp_path: Path, key: str, value: float) -> None:
    """A saved 10-pose state with one member set out of range (the parent array at 10^9 made
    the process die with SIGSEGV in the first update after loading) is refused."""
    s = _solver()
    members = s.state_arrays()
    if members[key].size == 0:
        pytest.skip(f"{key} is empty in this state")
    arr = members[key].astype(np.float64 if isinstance(value, float) else members[key].dtype)
    arr.reshape(-1)[-1] = value
    members[key] = arr.astype(members[key].dtype) if members[key].dtype.kind == "f" else arr
    path = tmp_path / "crafted.npz"
    _write(path, members)
    with pytest.raises(FormatError, match=r"crafted\.npz"):
        OnlineSolver.load(path)


@pytest.mark.parametrize("meta_change", [
    {"n": 10**12}, {"placed": -1}, {"ngroups": 10**6}, {"config": [1, 2]},
    {"config": {"tau_new": -1}}, {"config": {"unknown": 1}}, {"version": 1},
    {"format": "numpy"}, {"frame": "x"},
])
def test_a_crafted_meta_is_refused(tmp_path: Path, meta_change: dict[str, object]) -> None:
    s = _solver()
    members = s.state_arrays()
    meta = json.loads(bytes(members["meta"]).decode())
    meta.update(meta_change)
    members["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    path = tmp_path / "crafted.npz"
    _write(path, members)
    with pytest.raises(FormatError, match=r"crafted\.npz"):
        OnlineSolver.load(path)


def test_meta_that_is_not_an_object_and_members_that_are_not_arrays(tmp_path: Path) -> None:
    s = _solver()
    members = s.state_arrays()
    for meta in (b"[1, 2, 3]", b"\xff\xfe", b"{", b'"text"'):
        members["meta"] = np.frombuffer(meta, np.uint8)
        path = tmp_path / "m.npz"
        _write(path, members)
        with pytest.raises(FormatError, match=r"m\.npz: .*meta"):
            OnlineSolver.load(path)
    members = s.state_arrays()
    members["parent"] = np.array(["a", "b"])  # not a number
    path = tmp_path / "s.npz"
    _write(path, members)
    with pytest.raises(FormatError, match=r"s\.npz"):
        OnlineSolver.load(path)


def test_an_object_array_is_refused_without_unpickling(tmp_path: Path) -> None:
    s = _solver()
    members = s.state_arrays()
    buf = io.BytesIO()
    np.save(buf, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    path = tmp_path / "pickle.npz"
    _write(path, members)
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr("extra.npy", buf.getvalue())
    with pytest.raises(FormatError, match="unexpected member 'extra'"):
        OnlineSolver.load(path)
    members_path = tmp_path / "pickle2.npz"
    with zipfile.ZipFile(members_path, "w") as zf:
        for k, v in members.items():
            b = io.BytesIO()
            np.save(b, v if k != "model" else np.array([{"x": 1}], dtype=object),
                    allow_pickle=True)
            zf.writestr(k + ".npy", b.getvalue())
    with pytest.raises(FormatError, match="'model' is not a readable array"):
        OnlineSolver.load(members_path)


def test_a_header_that_declares_a_huge_array_is_refused_before_reading(tmp_path: Path) -> None:
    s = _solver()
    members = s.state_arrays()
    del members["rot"]
    path = tmp_path / "huge.npz"
    _write(path, members)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (10**12,)})
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr("rot.npy", np.lib.format.magic(1, 0) + header.getvalue() + b"\0" * 64)
    with pytest.raises(FormatError, match=r"huge\.npz"):
        OnlineSolver.load(path)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "missing"])
def test_damaged_files_are_refused(tmp_path: Path, damage: str) -> None:
    s = _solver()
    path = tmp_path / "state.npz"
    s.save(path)
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 3])
    elif damage == "garbage":
        path.write_bytes(bytes(range(256)) * 40)
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        path = tmp_path / "nothing.npz"
    with pytest.raises(FormatError, match=path.name.replace(".", r"\.")):
        OnlineSolver.load(path)


def test_random_damage_never_escapes_the_error_contract(tmp_path: Path) -> None:
    """Fuzz: one member of a valid state changed at random, many times; each load either
    refuses the file with a FormatError or gives a solver that keeps working."""
    rng = np.random.default_rng(7)
    base = _solver(n=12, gps=4, seed=3).state_arrays()
    keys = [k for k in base if k != "meta" and base[k].size]
    specials = [0, -1, 1, 2, 7, -(2**31), 2**31 - 1, 2**62, np.nan, np.inf, -np.inf, 1e308,
                -1e-300, 0.5]
    loaded = refused = 0
    for trial in range(300):
        members = {k: v.copy() for k, v in base.items()}
        key = keys[rng.integers(len(keys))]
        arr = members[key]
        flat = arr.reshape(-1)
        for _ in range(int(rng.integers(1, 4))):
            value = specials[rng.integers(len(specials))]
            pos = int(rng.integers(flat.size))
            if arr.dtype.kind == "f":
                flat[pos] = value
            elif (np.isfinite(value) and float(value).is_integer()
                  and np.iinfo(arr.dtype).min <= value <= np.iinfo(arr.dtype).max):
                flat[pos] = int(value)
            else:
                flat[pos] = -1
        path = tmp_path / f"fuzz{trial}.npz"
        _write(path, members)
        try:
            s = OnlineSolver.load(path)
        except FormatError as exc:
            assert path.name in str(exc)
            refused += 1
            continue
        _exercise(s)
        loaded += 1
    assert refused > 0 and loaded > 0  # both branches were exercised


# --------------------------------------------------------------------------- saving
def test_save_writes_through_a_link_and_refuses_what_it_cannot_replace(tmp_path: Path) -> None:
    s = _solver()
    real = tmp_path / "real.npz"
    link = tmp_path / "link.npz"
    real.write_bytes(b"old")
    link.symlink_to(real)
    s.save(link)
    assert link.is_symlink() and OnlineSolver.load(real).num_poses == s.num_poses
    (tmp_path / "dir.npz").mkdir()
    with pytest.raises(FormatError, match=r"dir\.npz: cannot write the file: it is a directory"):
        s.save(tmp_path / "dir.npz")
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    with pytest.raises(FormatError, match=r"fifo\.npz: cannot write the file: it is a FIFO"):
        s.save(fifo)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still the FIFO
    with pytest.raises(FormatError, match="it is a device"):
        s.save("/dev/null")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.npz", "fifo.npz", "link.npz",
                                                          "real.npz"]


# --------------------------------------------------------------------------- bad calls
@pytest.mark.parametrize("budget", [0.0, -1.0, float("nan"), float("inf"), "5", True])
def test_a_bad_budget_is_refused_and_changes_nothing(budget: object) -> None:
    s = _solver()
    before = s.state_arrays()
    with pytest.raises(ValueError, match="budget_s must be a finite number > 0"):
        s.update(budget)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="budget_s must be a finite number > 0"):
        s.idle(budget)  # type: ignore[arg-type]
    after = s.state_arrays()
    for k in before:
        assert np.array_equal(before[k], after[k]), k


def test_a_huge_budget_is_a_long_frame_not_an_overflow() -> None:
    s = _solver()
    s.update(1e15)
    s.update(1e12)
    assert np.isfinite(s.energy())


def test_bad_input_changes_nothing() -> None:
    s = _solver()
    ids = s.pose_ids()
    before = s.state_arrays()
    nan_pose = (np.eye(3), np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(GraphError, match="not finite"):
        s.add_constraint(int(ids[0]), int(ids[3]), nan_pose, np.eye(6))
    with pytest.raises(GraphError, match="unknown pose id"):
        s.add_constraint(int(ids[0]), 10**9, (np.eye(3), np.ones(3)), np.eye(6))
    with pytest.raises(GraphError, match="duplicate pose id"):
        s.add_pose(int(ids[2]), int(ids[1]), (np.eye(3), np.ones(3)), np.eye(6))
    s.add_constraint(int(ids[0]), int(ids[4]), (np.eye(3), np.ones(3)), np.eye(6))
    mid = s.state_arrays()
    with pytest.raises(GraphError, match="duplicate constraint"):
        s.add_constraint(int(ids[0]), int(ids[4]), (np.eye(3), np.ones(3)), np.eye(6))
    after = s.state_arrays()
    for k in mid:
        assert np.array_equal(mid[k], after[k]), k
    assert before["meta"].tobytes() != mid["meta"].tobytes()  # the good constraint was taken


def test_idle_uses_the_time_between_frames() -> None:
    """idle() between frames relaxes what a tight budget left queued and then older
    constraints; the frames' own work stays as it was."""
    g, _, _ = random_graph(np.random.default_rng(5), n=40, extra=30, noise=0.05)
    st = make_stream(g)
    busy, resting = (OnlineSolver(OnlineConfig(reserve_poses=64, background_refine=False))
                     for _ in range(2))
    for k in range(st.num_frames):
        for s in (busy, resting):
            feed_frame(s, st, k)
            s.update(None, 1)  # one update per frame: a backlog builds up
        resting.idle(0.002)
    assert busy.backlog > 0 and resting.backlog == 0
    assert resting.energy() < busy.energy()


def test_the_duplicate_check_knows_every_parallel_constraint_after_growth_and_load(
        tmp_path: Path) -> None:
    """Three constraints on one pose pair, added while the edge arrays grow (a reserve of 2
    poses) and before and after a save and load: every one of them, the oldest included, is
    refused when added again; a fourth, different one is taken."""
    s = OnlineSolver(OnlineConfig(reserve_poses=2, background_refine=False))
    step = (np.eye(3), np.array([1.0, 0.0, 0.0]))
    s.add_pose(0)
    for i in range(1, 8):
        s.add_pose(i, i - 1, step, np.eye(6))
    loops = [(np.eye(3), np.array([7.0 + 0.1 * k, 0.0, 0.0])) for k in range(4)]
    s.add_constraint(0, 7, loops[0], np.eye(6))
    s.update(None)
    for i in range(8, 40):  # the edge capacity doubles several times
        s.add_pose(i, i - 1, step, np.eye(6))
    s.add_constraint(0, 7, loops[1], np.eye(6))
    s.update(None)
    s.save(tmp_path / "s.npz")
    t = OnlineSolver.load(tmp_path / "s.npz")
    t.add_constraint(0, 7, loops[2], np.eye(6))
    for k in range(3):
        with pytest.raises(GraphError, match="duplicate constraint"):
            t.add_constraint(0, 7, loops[k], np.eye(6))
    t.add_constraint(0, 7, loops[3], np.eye(6))
    t.add_constraint(7, 0, loops[0], np.eye(6))  # the other direction is another pair
    assert t.num_edges == 39 + 5


_ASYM = np.eye(6)
_ASYM[0, 1] = 0.5


@pytest.mark.parametrize(("meas", "info", "message"), [
    ((np.eye(3), np.array([0.0, np.nan, 0.0])), np.eye(6), r"measurement is not finite"),
    ((np.full((3, 3), np.inf), np.ones(3)), np.eye(6), r"measurement is not finite"),
    ((np.diag([1.0, 1.0, -1.0]), np.ones(3)), np.eye(6),
     r"R is not a rotation \(\|R\^T R - I\| = 0, det = -1\)"),
    ((1.001 * np.eye(3), np.ones(3)), np.eye(6),
     r"R is not a rotation \(\|R\^T R - I\| = 0\.002, det = 1\)"),
    ((np.eye(3), np.ones(3)), np.full((6, 6), np.nan), r"information is not finite"),
    ((np.eye(3), np.ones(3)), _ASYM, r"information matrix is not symmetric"),
    ((np.eye(3), np.ones(3)), np.diag([1.0, 1, 1, 1, 1, -1]), r"not positive definite"),
])
def test_each_bad_measurement_or_information_is_named(meas: object, info: np.ndarray,
                                                      message: str) -> None:
    s = _solver()
    ids = s.pose_ids()
    before = s.state_arrays()
    with pytest.raises(GraphError, match=message):
        s.add_constraint(int(ids[0]), int(ids[3]), meas, info)
    after = s.state_arrays()
    assert all(np.array_equal(before[k], after[k]) for k in before)


def test_the_rigid_and_information_checks_agree_with_numpy() -> None:
    """The compiled checks of ``add_*`` against their NumPy twins (random near-rotations,
    arbitrary matrices, and symmetric matrices with one entry nudged)."""
    from hybridpgo.graph import SYMMETRY_RTOL, asymmetric
    from hybridpgo.online._validate import _finite_symmetric, _rigid

    rng = np.random.default_rng(11)
    for _ in range(200):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        rot = np.ascontiguousarray(q + rng.normal(scale=10.0 ** rng.integers(-12, 0),
                                                  size=(3, 3)))
        finite, dev, det = _rigid(rot, np.zeros(3))
        assert finite
        np.testing.assert_allclose(dev, np.abs(rot.T @ rot - np.eye(3)).max(),
                                   rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(det, np.linalg.det(rot), rtol=1e-12, atol=1e-15)
        a = rng.normal(size=(6, 6))
        info = a @ a.T
        i, j = rng.integers(0, 6, 2)
        info[i, j] += rng.choice([0.0, 1e-12, 1e-6]) * np.abs(info).max()
        expect = int(np.abs(info - info.T).max() > SYMMETRY_RTOL * np.abs(info).max()) * 2
        assert _finite_symmetric(info, SYMMETRY_RTOL) == expect
        assert bool(asymmetric(info[None])[0]) is (expect == 2)  # the vectorized twin
