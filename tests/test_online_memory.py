"""Page faults out of the online mode's updates: a new path's pool pages are written when it is
laid, and the heap the compiled kernels allocate from stays resident (glibc); the requeued
constraints leave the frame room for its first new constraint.

Faults are counted with ``getrusage(RUSAGE_THREAD)`` (Linux); no test reads the clock.
"""

from __future__ import annotations

import platform
import resource
import sys

import numpy as np
import pytest

from hybridpgo._numba import cycles_per_second
from hybridpgo.online import OnlineConfig, OnlineSolver, _heap
from hybridpgo.online._frame import NO_DEADLINE, READ_LEVEL_S
from hybridpgo.solvers.hybrid import _admission as adm
from hybridpgo.solvers.hybrid import _slices

LINUX = sys.platform.startswith("linux") and hasattr(resource, "RUSAGE_THREAD")
GLIBC = LINUX and platform.libc_ver()[0] == "glibc"


def _faults() -> int:
    return int(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt)


def _chain_with_loop(n: int) -> OnlineSolver:
    """``n`` poses of odometry along a line, then a loop closure from the last to the first
    in a frame of its own: its path is the whole chain.  Everything laid, nothing relaxed."""
    s = OnlineSolver(OnlineConfig(background_refine=False))
    s.add_pose(0)
    step = (np.eye(3), np.array([1.0, 0.0, 0.0]))
    for i in range(1, n):
        s.add_pose(i, i - 1, step, np.eye(6))
    s._integrate()
    s.add_constraint(n - 1, 0, (np.eye(3), np.array([n - 1.0, 0.0, 0.0])), np.eye(6))
    s._integrate()
    return s


@pytest.mark.skipif(not LINUX, reason="page faults counted per thread on Linux only")
def test_a_new_path_is_written_when_laid_not_in_its_first_update() -> None:
    s = _chain_with_loop(3000)
    st = s.store
    c = st.m_laid - 1
    lo, hi = int(st.ptr[c]), int(st.ptr[c + 1])
    assert hi - lo >= 2999  # the loop's path: the whole chain
    assert not st.contrib[lo:hi].any()  # no contribution before its first update
    f0 = _faults()
    st.contrib[lo:hi] = 0.0  # what its first update does to these pages (one per 14 nodes)
    assert _faults() - f0 < 8  # about 210 without: every page was already written


_KEPT_HEAP = """
import ctypes, resource, sys
from hybridpgo.online import _heap

def faults():
    return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt

assert _heap.keep_resident(16)
assert not _heap.keep_resident(0)
libc = ctypes.CDLL("libc.so.6")
libc.malloc.argtypes, libc.malloc.restype = [ctypes.c_size_t], ctypes.c_void_p
libc.free.argtypes, libc.free.restype = [ctypes.c_void_p], None
size = 8 << 20
f0 = faults()
for _ in range(3):  # a kernel's temporaries of 8 MiB, three frames in a row
    p = libc.malloc(size)
    assert p
    ctypes.memset(p, 1, size)
    libc.free(p)
print(faults() - f0)
"""


@pytest.mark.skipif(not GLIBC, reason="the heap's settings are glibc's")
def test_a_kept_heap_serves_large_blocks_without_page_faults() -> None:
    """In a process of its own: the settings are the whole process's, made once, and what a
    test process allocated before (the heap grown past the reserve, its new top not written
    yet) would decide the count."""
    import subprocess

    out = subprocess.run([sys.executable, "-c", _KEPT_HEAP], capture_output=True, text=True,
                         timeout=120, check=True)
    assert int(out.stdout.split()[-1]) < 32  # 4 096 here with malloc's defaults (fresh maps)


def test_requeued_updates_leave_room_for_the_first_new_constraint() -> None:
    """The requeued constraints' deadline is the frame's less the predicted cost of the first
    new constraint's least work: its single update, or one slice of a longer one."""
    s = _chain_with_loop(300)
    st = s.store
    deadline = np.uint64(10**15)
    q = st.pending()
    assert q.size
    first = int(q[0])  # the first odometry edge: one node
    d = int(st.ptr[first + 1] - st.ptr[first])
    assert d == 1
    assert s._keep_for_new(deadline) == deadline - np.uint64(int(adm.predict(st.model, 1,
                                                                               False)))
    st.pop(int(q.size) - 1)  # only the loop closure is left, 299 nodes: one slice's worth
    c = int(st.pending()[0])
    assert int(st.ptr[c + 1] - st.ptr[c]) == 299
    keep = int(adm.predict(st.model, _slices.SLICE, False))
    assert keep < int(adm.predict(st.model, 299, False))
    assert s._keep_for_new(deadline) == deadline - np.uint64(keep)
    assert s._keep_for_new(NO_DEADLINE) == NO_DEADLINE
    st.pop(1)
    assert s._keep_for_new(deadline) == deadline  # nothing new: all of it


def test_a_frame_keeps_the_time_to_read_its_newest_pose() -> None:
    """The frame's deadline is kept from the reading of its newest pose after it: O(its tree
    depth), READ_LEVEL_S per level; the deeper the pose, the more is kept."""
    s = _chain_with_loop(300)
    st = s.store
    deadline = np.uint64(10**15)
    depth = int(st.depth[st.placed])
    assert depth >= 150  # a chain: the newest pose lies deep in the tree
    keep = int(depth * READ_LEVEL_S * cycles_per_second())
    assert keep > 0
    assert s._keep_for_read(deadline) == deadline - np.uint64(keep)
    assert s._keep_for_read(NO_DEADLINE) == NO_DEADLINE
    s.add_pose(300, 299, (np.eye(3), np.array([1.0, 0.0, 0.0])), np.eye(6))
    s._integrate()
    assert int(st.depth[st.placed]) == depth + 1  # the new pose is the one read
    assert s._keep_for_read(deadline) < deadline - np.uint64(keep)
    assert s._keep_for_read(np.uint64(1)) == 0  # never below the clock's zero


@pytest.mark.parametrize("bad", [-1, True, 1.5, _heap.MAX_RESERVE_MB + 1, 10**12])
def test_a_heap_reserve_out_of_range_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match="heap_reserve_mb"):
        OnlineConfig(heap_reserve_mb=bad)  # type: ignore[arg-type]


def _huge_pages_always() -> bool:
    """Transparent huge pages for every anonymous map: a first write faults 2 MiB at once."""
    try:
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as fh:
            return "[always]" in fh.read()
    except OSError:
        return False


@pytest.mark.skipif(not LINUX or _huge_pages_always(),
                    reason="page faults counted per thread on Linux, in small pages")
@pytest.mark.parametrize("ahead", [True, False])
def test_the_path_pool_is_written_ahead_of_a_long_path(ahead: bool) -> None:
    """Frames write the path pool ahead of the laid paths in their spare time (one chunk per
    frame: ``update`` without a deadline writes one), so a long loop closure's path lays
    without faulting its pages; with only the frame's one chunk ahead it faults the rest."""
    from hybridpgo.online.store import PREFAULT_AHEAD_BYTES, PREFAULT_CHUNK_BYTES

    n = 3000
    s = OnlineSolver(OnlineConfig(background_refine=False))
    s.add_pose(0)
    step = (np.eye(3), np.array([1.0, 0.0, 0.0]))
    for i in range(1, n):
        s.add_pose(i, i - 1, step, np.eye(6))
    st = s.store
    row = st.contrib[0].nbytes
    s.update(None, 0)
    used = int(st.ptr[st.m_laid])
    assert st._ahead[0] == used + PREFAULT_CHUNK_BYTES // row  # one chunk per frame
    if ahead:
        while st.prefault():
            pass
        assert st._ahead[0] == used + PREFAULT_AHEAD_BYTES // row
        assert st._ahead[1] == st.cap_pe  # no GPS reading: nothing ahead of their paths
        assert not st.contrib[used: st._ahead[0]].any()
        assert not st.path_node[used: st._ahead[0]].any()
    s.add_constraint(n - 1, 0, (np.eye(3), np.array([n - 1.0, 0.0, 0.0])), np.eye(6))
    f0 = _faults()
    st.lay_paths()
    faults = _faults() - f0
    assert int(st.ptr[st.m_laid]) - used >= n - 1  # the loop's path: the whole chain
    if ahead:
        assert faults < 16
    else:
        assert faults > 150  # 3 000 entries of 288 bytes past the first chunk: ~195 pages


def test_writing_the_pool_ahead_leaves_the_laid_paths_as_they_are() -> None:
    """Laid paths of edges and GPS readings (relaxed: their contributions are not zero), the
    pool grown past a small reservation: writing ahead changes none of their entries, and
    nothing past them but zeros."""
    s = OnlineSolver(OnlineConfig(background_refine=False, reserve_poses=64))
    s.add_pose(0)
    rng = np.random.default_rng(3)
    for i in range(1, 400):
        s.add_pose(i, i - 1, (np.eye(3), np.array([1.0, 0.1, 0.0])), np.eye(6))
        if i % 50 == 0:
            s.add_constraint(i, i - 40, (np.eye(3), np.array([40.0, 4.0, 0.0])), np.eye(6))
        if i % 25 == 0:
            s.add_gps(i, np.array([float(i), 0.1 * i, 0.0]) + rng.normal(0, 0.1, 3),
                      np.eye(3))
        s.update(None, 2)
    st = s.store
    e1, g0, g1 = int(st.ptr[st.m_laid]), st.cap_pe, int(st.ptr[st.cap_m + st.g_laid])
    assert st.contrib[:e1].any() and st.contrib[g0:g1].any() and g1 > g0
    laid = {name: (getattr(st, name)[:e1].copy(), getattr(st, name)[g0:g1].copy())
            for name in ("path_node", "path_sign", "contrib")}
    while st.prefault():
        pass
    assert st._ahead[0] > e1 and st._ahead[1] > g1
    for name, (edges, gps) in laid.items():
        arr = getattr(st, name)
        np.testing.assert_array_equal(arr[:e1], edges)
        np.testing.assert_array_equal(arr[g0:g1], gps)
        assert not arr[e1: st._ahead[0]].any() and not arr[g1: st._ahead[1]].any()
