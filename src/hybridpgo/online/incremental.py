"""An incremental exact solver for a growing pose graph, resumable in time slices.

:class:`IncrementalExact` keeps the Gauss-Newton normal equations of the map factored
(``H = L L^T`` by 6x6 blocks, :mod:`._incremental_kernels`) and, when poses and constraints are
appended, re-eliminates only the columns that changed and their ancestors in the elimination
tree, in a fresh fill-reducing order (AMD on the reduced system, with the ends of the new
constraints last so that the next frame's changes stay near the root).  The linearization point
moves only for the poses whose step exceeds a threshold ("fluid relinearization"), and the
solution may be propagated down the tree only where it changes ("wildfire" back substitution,
``IncrementalConfig.wildfire``).
This is the incremental scheme of iSAM2 (Kaess et al., IJRR 2012) written as a left-looking
supernodal block Cholesky on the elimination tree instead of a Bayes tree of cliques.

While every pose and measurement is planar (``IncrementalConfig.planar``) the factor holds only
the (x, y, yaw) part of each block, 3x3: there the out-of-plane error, gradient and step are
exactly 0 and the planar system's step is the full system's (a planar graph lifted to 3D).
The first datum that is not planar moves the solver to the full system, in one update that
linearizes every constraint again and re-eliminates the whole map.

With both thresholds 0 every update is an exact Gauss-Newton step of the whole map, and
repeated :meth:`~IncrementalExact.solve` calls converge to the same optimum as the batch exact
solver (:func:`hybridpgo.solvers.gauss_newton.solve_exact`).

Every piece of work is bounded: :meth:`~IncrementalExact.solve` takes a deadline and returns
when it passes, between two supernodes of the factorization or two columns of the back
substitution; the next call resumes there.  Data appended meanwhile waits for the next update
cycle.  The estimate (:meth:`~IncrementalExact.estimate`) is always the last completed
cycle's.

Gauge: with ``gauge="auto"`` the first pose is held until ``gps_gauge`` position readings exist,
then the earth frame is the gauge (as the online solver's worker does); ``"first"`` always holds
it, ``"none"`` never.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
import numpy.typing as npt

from .. import _cost
from .._numba import cycles_per_second, read_cycles
from ..errors import SolverError
from ..graph import (
    IN_PLANE,
    OUT_OF_PLANE,
    FloatArray,
    asymmetric,
    decoupled_information,
    planar_motions,
)
from ..linalg import fill_reducing_order
from . import _incremental_kernels as ik
from ._incremental_kernels import panel_scratch
from ._reserve import capacity, reserved_only

IntArray = npt.NDArray[np.int64]
_NO_DEADLINE = np.uint64(np.iinfo(np.uint64).max)
#: S smaller than this is ordered without AMD (positions: its old order, new variables last).
_AMD_MIN = 8

_IDLE, _LINEARIZE, _SYMBOLIC, _NUMERIC, _BACK = 0, 1, 2, 3, 4
#: The planar system's coordinates first (x, y, yaw), then z, roll, pitch.
_PLANAR_PERM = np.concatenate([IN_PLANE, OUT_OF_PLANE])
#: Constraints linearized between two deadline checks.
_CHUNK = 256


@dataclass(frozen=True)
class IncrementalConfig:
    """Options of :class:`IncrementalExact`."""

    relinearize_rho: float = 1e-3
    """A pose's linearization point moves to its estimate when the translation part of its
    step exceeds this (inf-norm, metres) ..."""
    relinearize_phi: float = 1e-3
    """... or the rotation part exceeds this (radians).  Both 0: every step relinearizes
    (exact Gauss-Newton)."""
    wildfire: float = 0.0
    """The back substitution stops below a column when neither its solution nor the solution
    of any of its rows moved by more than this (inf-norm); 0: the whole solution is
    recomputed.  At rounding level (the worker's 1e-12) the solution stays exact and a frame
    that brings only a pose and its odometry recomputes a few columns instead of the map.  A
    larger threshold leaves the steps of the columns it skips stale: after a long loop
    closure the cycles that follow may relinearize a pose or two each and take hundreds of
    cycles to converge."""
    gauge: Literal["auto", "first", "none"] = "auto"
    """``"auto"``: the first pose is held until ``gps_gauge`` GPS readings exist; ``"first"``:
    always; ``"none"``: never (GPS must fix the gauge)."""
    gps_gauge: int = 3
    """GPS readings after which ``gauge="auto"`` frees the first pose."""
    reorder: bool = True
    """Order each re-eliminated set by AMD (False: keep its old order, new variables last)."""
    last: Literal["ends", "poses"] = "ends"
    """Variables the new order of a re-eliminated set puts last (nearest the root): the ends
    of the constraints that are new in the update (as iSAM2 does), or only the new poses."""
    reorder_max: int = 4096
    """Sets larger than this keep their old order (AMD is one call that cannot stop at a
    deadline; 4096 variables take about 2 ms)."""
    polish_rho: float = 1e-5
    """When nothing else is left to do, every pose whose step exceeds ``polish_rho`` (metres)
    or ``polish_phi`` (radians) is relinearized, so an idle solver converges to the optimum
    (such poses are listed as their steps are computed: an idle update costs as much as the
    poses that move)."""
    polish_phi: float = 1e-5
    """See ``polish_rho``."""
    planar: bool = True
    """Solve the (x, y, yaw) system while every pose and measurement is planar
    (:func:`~hybridpgo.graph.planar_motions`, no information coupling the plane with z, roll
    or pitch, no GPS reading): there the out-of-plane error, gradient and step are exactly 0
    and the in-plane step is the full system's, at an eighth of the factorization's
    multiplications.  The first datum that is not planar switches to the full system (one
    update re-eliminates the whole map)."""
    max_fill: int = 128
    """The factor's pool holds at most this many blocks per pose and constraint (at least
    :data:`POOL_FLOOR`): an update whose fill-in needs more raises :class:`SolverError` (a poor
    elimination order, e.g. large sets kept in their old order: paris2 asked for 36 GiB).
    The caller can start again or solve in batch."""


def _check_measurements(rot: FloatArray | None, trans: FloatArray, info: FloatArray,
                        what: str) -> None:
    """ValueError naming the first measurement that is not finite or whose information is
    not symmetric positive definite."""
    k = trans.shape[0]
    if k == 0:
        return
    finite = np.isfinite(trans).all(axis=1) & np.isfinite(info).reshape(k, -1).all(axis=1)
    if rot is not None:
        finite &= np.isfinite(rot).reshape(k, -1).all(axis=1)
    if not finite.all():
        raise ValueError(f"{what} {int(np.argmin(finite))} (of those added) is not finite")
    bad = asymmetric(info)
    if not bad.any():
        try:
            np.linalg.cholesky(info)
        except np.linalg.LinAlgError:
            bad = ~np.all(np.linalg.eigvalsh(info) > 0.0, axis=1)
    if bad.any():
        raise ValueError(f"{what} {int(np.argmax(bad))} (of those added): its information is "
                         "not symmetric positive definite")


#: The factor's pool may always hold this many blocks (``IncrementalConfig.max_fill``).
POOL_FLOOR = 1 << 20
#: Blocks of address space reserved for the factor's pool (:mod:`._reserve`: pages are
#: allocated when first written), so that the pool grows and is compacted in place, its pages
#: written a few at a time as it fills, rather than copied into a new array whose live rows
#: are all written at once (paris2 with GPS fed into a solver in chunks of 50 frames: the
#: doubling to 2 M blocks at frame 29 700 takes 48 ms in place, 547 ms as a copy, during
#: which the worker answers nothing).  A pool that outgrows its reservation is copied into a
#: new one (of 4 times its capacity); where no address space can be reserved the pool is
#: plain arrays of its capacity, copied at each growth.
POOL_RESERVE = 1 << 24
#: Rows of address space reserved for each per-pose, per-edge and per-GPS-reading array (at
#: least 4 times its first capacity), so that they grow in place, writing only the new rows'
#: fill, rather than being copied into arrays of twice the size at each doubling, in which the
#: worker answers nothing (paris2 fed in requests of 50 frames, ``2026-12-01-worker-arrays``:
#: the edge arrays' doubling to 65 536 rows 0.39 ms in place, 62 ms copied; the pose arrays'
#: to 65 536 rows 1.7 ms against 4.8 ms).  Beyond it an array is copied into a new
#: reservation of 4 times its capacity (once per fourfold growth); where nothing can be reserved
#: (:func:`hybridpgo._memory.can_overcommit`) it is copied into a plain one at each doubling.
ROWS_RESERVE = 1 << 22


class IncrementalExact:
    """A pose graph that grows by appended arrays, kept at its Gauss-Newton solution by
    bounded incremental updates (module docstring).

    Poses are dense indices ``0, 1, ...`` in the order they are added.
    """

    def __init__(self, config: IncrementalConfig | None = None, capacity: int = 1024) -> None:
        self.config = config or IncrementalConfig()
        cap = max(int(capacity), 4)
        self._n = self._n_in = 0  # poses added / integrated
        # the reservations the pose, edge and GPS arrays are views of (None: plain arrays)
        self._bases: dict[str, np.ndarray | None] = {}
        self._m = self._m_in = 0  # edges
        self._g = self._g_in = 0  # GPS readings
        self._alloc_poses(cap)
        self._alloc_edges(2 * cap)
        self._alloc_gps(max(cap // 16, 8))
        self._pool_cap = 8 * cap
        # the factor's coordinates: tangent coordinates perm[:nd] (module doc: the planar
        # system), its blocks (nd, nd); _planar_lost: a datum that is not planar was added to
        # a planar solver
        self._nd = 3 if self.config.planar else 6
        self._perm = _PLANAR_PERM.copy() if self.config.planar else np.arange(6)
        self._planar_lost = False
        # the pool: _row_var and _row_blk are its first _pool_cap rows, views of the
        # reserved arrays _pool_var and _pool_blk (None: not reserved)
        self._pool_var: npt.NDArray[np.int64] | None = None
        self._pool_blk: npt.NDArray[np.float64] | None = None
        self._row_var, self._row_blk = self._new_pool(self._pool_cap, self._nd)
        # the supernodes of the cycle's S and their panels (ik.supernodes, ik.numeric)
        self._sn_ptr = np.zeros(1, np.int64)
        self._sn_count = 0
        self._sn_mark = np.full(16, -1, np.int64)
        self._pan_off = np.zeros(1, np.int64)
        self._panel = np.zeros(0)
        self._scratch = np.zeros(0)
        self._pool_used = np.zeros(2, np.int64)
        self._work = np.zeros(2, np.int64)
        self._counter = 0  # next elimination position
        self._stamp = 0  # update cycles started
        self._phase = _IDLE
        self._relin_cands = np.zeros(0, np.int64)
        self._first_free = self.config.gauge == "none"
        self._cycle_cover = (0, 0, 0)
        self.covered = (0, 0, 0)
        """(poses, edges, GPS readings) the estimate's last completed update integrated."""
        self.stats: dict[str, Any] = {
            "cycles": 0, "columns": 0, "relinearized": 0, "recomputed": 0, "max_set": 0,
            "applied": 0, "products": 0,
            "seconds": {"start": 0.0, "numeric": 0.0, "back": 0.0}}
        """Totals: update cycles completed, columns re-eliminated, poses relinearized,
        solution entries recomputed; the largest re-eliminated set; earlier columns applied to
        re-eliminated ones and the blocks they multiplied (the factorization's work); seconds
        spent starting
        cycles (integration, linearization, ordering, symbolic), factoring and back
        substituting."""

    # ----------------------------------------------------------------- storage
    # the arrays of the tables below, set by _alloc and _grow
    _ref: npt.NDArray[Any]
    _rel_r: npt.NDArray[Any]
    _rel_t: npt.NDArray[Any]
    _th_r: npt.NDArray[Any]
    _th_t: npt.NDArray[Any]
    _est_r: npt.NDArray[Any]
    _est_t: npt.NDArray[Any]
    _x: npt.NDArray[Any]
    _y: npt.NDArray[Any]
    _diag: npt.NDArray[Any]
    _free: npt.NDArray[Any]
    _position: npt.NDArray[Any]
    _parent: npt.NDArray[Any]
    _ch_head: npt.NDArray[Any]
    _ch_next: npt.NDArray[Any]
    _ch_prev: npt.NDArray[Any]
    _col_start: npt.NDArray[Any]
    _col_len: npt.NDArray[Any]
    _col_cap: npt.NDArray[Any]
    _inc_head: npt.NDArray[Any]
    _gps_head: npt.NDArray[Any]
    _in_s: npt.NDArray[Any]
    _changed: npt.NDArray[Any]
    _mark: npt.NDArray[Any]
    _walk: npt.NDArray[Any]
    _slot: npt.NDArray[Any]
    _sn_of: npt.NDArray[Any]
    _src: npt.NDArray[Any]
    _local: npt.NDArray[Any]
    _stack: npt.NDArray[Any]
    _touched: npt.NDArray[Any]
    _pol_flag: npt.NDArray[Any]
    _pol_list: npt.NDArray[Any]
    _chg_flag: npt.NDArray[Any]
    _chg_list: npt.NDArray[Any]
    _ab: npt.NDArray[Any]
    _zr: npt.NDArray[Any]
    _zt: npt.NDArray[Any]
    _info: npt.NDArray[Any]
    _haa: npt.NDArray[Any]
    _hbb: npt.NDArray[Any]
    _hab: npt.NDArray[Any]
    _ga: npt.NDArray[Any]
    _gb: npt.NDArray[Any]
    _chi: npt.NDArray[Any]
    _inc_next: npt.NDArray[Any]
    _e_stamp: npt.NDArray[Any]
    _gnode: npt.NDArray[Any]
    _gpos: npt.NDArray[Any]
    _ginfo: npt.NDArray[Any]
    _hgg: npt.NDArray[Any]
    _gg: npt.NDArray[Any]
    _gchi: npt.NDArray[Any]
    _gps_next: npt.NDArray[Any]
    _g_stamp: npt.NDArray[Any]
    #: The per-pose, per-edge and per-GPS-reading arrays: name -> (shape of a row, dtype,
    #: fill, rows per pose / edge / reading).
    _POSE_ARRAYS: ClassVar[dict[str, tuple[tuple[int, ...], Any, int, int]]] = {
        "_ref": ((), np.int64, -1, 1), "_rel_r": ((3, 3), np.float64, 0, 1),
        "_rel_t": ((3,), np.float64, 0, 1), "_th_r": ((3, 3), np.float64, 0, 1),
        "_th_t": ((3,), np.float64, 0, 1), "_est_r": ((3, 3), np.float64, 0, 1),
        "_est_t": ((3,), np.float64, 0, 1), "_x": ((6,), np.float64, 0, 1),
        "_y": ((6,), np.float64, 0, 1), "_diag": ((6, 6), np.float64, 0, 1),
        "_free": ((), np.bool_, 0, 1), "_position": ((), np.int64, -1, 1),
        "_parent": ((), np.int64, -1, 1), "_ch_head": ((), np.int64, -1, 1),
        "_ch_next": ((), np.int64, -1, 1), "_ch_prev": ((), np.int64, -1, 1),
        "_col_start": ((), np.int64, 0, 1), "_col_len": ((), np.int64, 0, 1),
        "_col_cap": ((), np.int64, 0, 1), "_inc_head": ((), np.int64, -1, 1),
        "_gps_head": ((), np.int64, -1, 1), "_in_s": ((), np.int64, -1, 1),
        "_changed": ((), np.int64, -1, 1), "_mark": ((), np.int64, -1, 1),
        "_walk": ((), np.int64, -1, 1), "_slot": ((), np.int64, -1, 1),
        "_sn_of": ((), np.int64, 0, 1), "_src": ((), np.int64, 0, 1),
        "_local": ((), np.int64, 0, 1), "_stack": ((), np.int64, 0, 1),
        "_touched": ((), np.int64, 0, 1), "_pol_flag": ((), np.bool_, 0, 1),
        "_pol_list": ((), np.int64, 0, 1), "_chg_flag": ((), np.bool_, 0, 1),
        "_chg_list": ((), np.int64, 0, 1)}
    _EDGE_ARRAYS: ClassVar[dict[str, tuple[tuple[int, ...], Any, int, int]]] = {
        "_ab": ((2,), np.int64, 0, 1), "_zr": ((3, 3), np.float64, 0, 1),
        "_zt": ((3,), np.float64, 0, 1), "_info": ((6, 6), np.float64, 0, 1),
        "_haa": ((6, 6), np.float64, 0, 1), "_hbb": ((6, 6), np.float64, 0, 1),
        "_hab": ((6, 6), np.float64, 0, 1), "_ga": ((6,), np.float64, 0, 1),
        "_gb": ((6,), np.float64, 0, 1), "_chi": ((), np.float64, 0, 1),
        "_inc_next": ((), np.int64, -1, 2), "_e_stamp": ((), np.int64, -1, 1)}
    _GPS_ARRAYS: ClassVar[dict[str, tuple[tuple[int, ...], Any, int, int]]] = {
        "_gnode": ((), np.int64, 0, 1), "_gpos": ((3,), np.float64, 0, 1),
        "_ginfo": ((3, 3), np.float64, 0, 1), "_hgg": ((3, 3), np.float64, 0, 1),
        "_gg": ((3,), np.float64, 0, 1), "_gchi": ((), np.float64, 0, 1),
        "_gps_next": ((), np.int64, -1, 1), "_g_stamp": ((), np.int64, -1, 1)}

    def _alloc(self, arrays: dict[str, tuple[tuple[int, ...], Any, int, int]],
               cap: int) -> None:
        """Each of ``arrays`` with room for ``cap`` poses, edges or readings: the first rows
        of an array of :data:`ROWS_RESERVE` (at least ``4 cap``) reserved as address space,
        kept in ``_bases``, or a plain array where none can be reserved."""
        for name, (row, dtype, fill, per) in arrays.items():
            arr = self._reserve(name, row, dtype, cap * per)
            if fill:
                arr[:] = fill
            setattr(self, name, arr)

    def _reserve(self, name: str, row: tuple[int, ...], dtype: Any, rows: int) -> np.ndarray:
        """Zero array ``name`` of ``rows`` rows: the first rows of a reservation of
        :data:`ROWS_RESERVE` rows (at least ``4 rows``), kept in ``_bases``, or a plain array
        (``_bases[name]`` None) where none can be made."""
        base = reserved_only((max(ROWS_RESERVE, 4 * rows), *row), dtype)
        self._bases[name] = base
        return base[:rows] if base is not None else np.zeros((rows, *row), dtype)

    def _grow(self, arrays: dict[str, tuple[tuple[int, ...], Any, int, int]], old: int,
              cap: int) -> None:
        """Each of ``arrays`` from room for ``old`` to ``cap`` poses, edges or readings: in
        place within its reservation (only the new rows are written, where their fill is
        not 0), else copied into a new reservation as :meth:`_alloc` makes one (a plain
        array where none can be made)."""
        for name, (row, dtype, fill, per) in arrays.items():
            arr = getattr(self, name)
            base = self._bases.get(name)
            if base is not None and cap * per <= base.shape[0]:
                new = base[: cap * per]
            else:  # copied into a new reservation, or a plain array
                new = self._reserve(name, row, dtype, cap * per)
                new[: old * per] = arr[: old * per]
            if fill:
                new[old * per:] = fill
            setattr(self, name, new)

    def _alloc_poses(self, cap: int) -> None:
        self._cap_n = cap
        self._alloc(self._POSE_ARRAYS, cap)
        self._pol_count = np.zeros(1, np.int64)
        self._chg_count = np.zeros(1, np.int64)

    def _grow_poses(self, need: int) -> None:
        if need <= self._cap_n:
            return
        cap = capacity(need, self._cap_n)
        self._grow(self._POSE_ARRAYS, self._cap_n, cap)
        self._cap_n = cap

    def _alloc_edges(self, cap: int) -> None:
        self._cap_m = cap
        self._alloc(self._EDGE_ARRAYS, cap)

    def _grow_edges(self, need: int) -> None:
        if need <= self._cap_m:
            return
        cap = capacity(need, self._cap_m)
        self._grow(self._EDGE_ARRAYS, self._cap_m, cap)
        self._cap_m = cap

    def _alloc_gps(self, cap: int) -> None:
        self._cap_g = cap
        self._alloc(self._GPS_ARRAYS, cap)

    def _grow_gps(self, need: int) -> None:
        if need <= self._cap_g:
            return
        cap = capacity(need, self._cap_g)
        self._grow(self._GPS_ARRAYS, self._cap_g, cap)
        self._cap_g = cap

    def _grow_pool(self, need: int) -> None:
        """Room for ``need`` more rows after a compaction (dead segments dropped); the pool
        doubles unless at least half of it was dead."""
        n = self._n_in
        live = int(self._col_cap[:n].sum())
        used = int(self._pool_used[0])
        cap = self._pool_cap
        if used - live < used // 2:
            cap *= 2
        while cap < live + need:
            cap *= 2
        limit = max(self.config.max_fill * (self._n + self._m + self._g), POOL_FLOOR)
        cap = max(min(cap, limit), self._pool_cap)
        if live + need > limit:
            raise SolverError(f"the incremental factor's fill-in needs {live + need} blocks, "
                              f"more than max_fill={self.config.max_fill} per pose and "
                              f"constraint ({limit})")
        self._compact(cap)

    def _new_pool(self, cap: int, nd: int) -> tuple[npt.NDArray[np.int64],
                                                     npt.NDArray[np.float64]]:
        """Zero pool arrays of ``cap`` rows with (nd, nd) blocks: views of arrays of
        :data:`POOL_RESERVE` rows (at least ``4 cap``) reserved as address space, kept in
        ``_pool_var`` / ``_pool_blk``, or plain zeros of ``cap`` rows where that cannot be
        done (``_pool_var`` None)."""
        rows = max(POOL_RESERVE, 4 * cap)
        var = reserved_only((rows,), np.int64)
        blk = reserved_only((rows, nd, nd)) if var is not None else None
        if var is None or blk is None:
            self._pool_var = self._pool_blk = None
            return np.zeros(cap, np.int64), np.zeros((cap, nd, nd))
        self._pool_var, self._pool_blk = var, blk
        return var[:cap], blk[:cap]

    def __deepcopy__(self, memo: dict[int, Any]) -> IncrementalExact:
        """A copy whose pool and per-pose, per-edge and per-reading arrays are plain arrays
        of their current rows (a view's copy holds the view's rows only; the reservations
        are not copied: their untouched address space would be written)."""
        import copy

        out = self.__class__.__new__(self.__class__)
        memo[id(self)] = out
        for key, value in self.__dict__.items():
            keep = key not in ("_pool_var", "_pool_blk", "_bases")
            setattr(out, key, copy.deepcopy(value, memo) if keep else None)
        out._bases = {}
        return out

    def _compact(self, cap: int) -> None:
        """Lay every column's segment back to back in a pool of ``cap`` rows: in place where
        the reservation holds ``cap`` rows (:func:`~._incremental_kernels.compact_pool`), else
        copied into a new pool."""
        n = self._n_in
        pv, pb = self._pool_var, self._pool_blk
        if pv is not None and pb is not None and cap <= pv.shape[0]:
            order = np.argsort(self._col_start[:n], kind="stable")
            end = ik.compact_pool(order, self._col_start, self._col_cap, self._col_len,
                                  int(self._pool_used[0]), pv, pb)
            self._row_var, self._row_blk = pv[:cap], pb[:cap]
            self._pool_used[0] = end
            self._pool_cap = cap
            return
        caps = self._col_cap[:n]
        lens = self._col_len[:n]
        new_start = np.zeros(n, np.int64)
        if n > 1:
            np.cumsum(caps[:-1], out=new_start[1:])
        total_len = int(lens.sum())
        offs = np.arange(total_len) - np.repeat(np.cumsum(lens) - lens, lens)
        src = np.repeat(self._col_start[:n], lens) + offs
        dst = np.repeat(new_start, lens) + offs
        row_var, row_blk = self._new_pool(cap, self._nd)
        row_var[dst] = self._row_var[src]
        row_blk[dst] = self._row_blk[src]
        self._row_var, self._row_blk = row_var, row_blk
        self._col_start[:n] = new_start
        self._pool_used[0] = int(caps.sum())
        self._pool_cap = cap

    # ----------------------------------------------------------------- input
    @property
    def num_poses(self) -> int:
        return self._n

    @property
    def num_edges(self) -> int:
        return self._m

    @property
    def num_gps(self) -> int:
        return self._g

    def add_poses(self, rotations: FloatArray, translations: FloatArray,
                  parents: npt.ArrayLike | None = None) -> None:
        """Append poses with their initial estimates.

        Parameters
        ----------
        rotations, translations : (k, 3, 3), (k, 3) float64
            Global poses (``parents`` None) or poses relative to each parent's estimate at the
            time the pose joins the solver (its next update): ``X = X_parent Z``.
        parents : (k,) int, optional
            Dense index of each new pose's parent (an earlier pose); -1: global.
        """
        rot = np.ascontiguousarray(rotations, np.float64).reshape(-1, 3, 3)
        trans = np.ascontiguousarray(translations, np.float64).reshape(-1, 3)
        k = rot.shape[0]
        if trans.shape[0] != k:
            raise ValueError("rotations and translations must have the same length")
        ref = (np.full(k, -1, np.int64) if parents is None
               else np.asarray(parents, np.int64).reshape(-1))
        if ref.shape[0] != k:
            raise ValueError("parents must have one entry per pose")
        idx = self._n + np.arange(k)
        if np.any(ref >= idx) or np.any(ref < -1):
            raise ValueError("a parent must be an earlier pose (or -1)")
        if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(trans))):
            raise ValueError("poses must be finite")
        if self._nd == 3 and not planar_motions(rot, trans):
            self._planar_lost = True
        self._grow_poses(self._n + k)
        n = self._n
        self._rel_r[n: n + k] = rot
        self._rel_t[n: n + k] = trans
        self._ref[n: n + k] = ref
        self._n = n + k

    def add_edges(self, a: npt.ArrayLike, b: npt.ArrayLike, rotations: FloatArray,
                  translations: FloatArray, information: FloatArray) -> None:
        """Append relative constraints ``Z = X_a^-1 X_b`` with (6, 6) information over
        (rho, phi) between poses already added."""
        ia = np.asarray(a, np.int64).reshape(-1)
        ib = np.asarray(b, np.int64).reshape(-1)
        k = ia.shape[0]
        rot = np.ascontiguousarray(rotations, np.float64).reshape(k, 3, 3)
        trans = np.ascontiguousarray(translations, np.float64).reshape(k, 3)
        info = np.ascontiguousarray(information, np.float64).reshape(k, 6, 6)
        if ib.shape[0] != k:
            raise ValueError("a and b must have the same length")
        if k and (min(ia.min(), ib.min()) < 0 or max(ia.max(), ib.max()) >= self._n
                  or np.any(ia == ib)):
            raise ValueError("edges must join two different poses already added")
        _check_measurements(rot, trans, info, "edge")
        if self._nd == 3 and not (planar_motions(rot, trans) and decoupled_information(info)):
            self._planar_lost = True
        self._grow_edges(self._m + k)
        m = self._m
        self._ab[m: m + k, 0] = ia
        self._ab[m: m + k, 1] = ib
        self._zr[m: m + k] = rot
        self._zt[m: m + k] = trans
        self._info[m: m + k] = info
        self._m = m + k

    def add_gps(self, nodes: npt.ArrayLike, positions: FloatArray,
                information: FloatArray) -> None:
        """Append position readings ``t_n = g`` (earth frame) with (3, 3) information."""
        nd = np.asarray(nodes, np.int64).reshape(-1)
        k = nd.shape[0]
        pos = np.ascontiguousarray(positions, np.float64).reshape(k, 3)
        info = np.ascontiguousarray(information, np.float64).reshape(k, 3, 3)
        if k and (nd.min() < 0 or nd.max() >= self._n):
            raise ValueError("GPS readings must be on poses already added")
        _check_measurements(None, pos, info, "GPS reading")
        if k and self._nd == 3:
            self._planar_lost = True
        self._grow_gps(self._g + k)
        g = self._g
        self._gnode[g: g + k] = nd
        self._gpos[g: g + k] = pos
        self._ginfo[g: g + k] = info
        self._g = g + k

    # ----------------------------------------------------------------- estimates
    def estimate(self) -> tuple[FloatArray, FloatArray]:
        """Global poses ``(R (n, 3, 3), t (n, 3))`` of every pose added: the last completed
        update's solution; poses not integrated yet are composed onto their parents."""
        n, n_in = self._n, self._n_in
        rot = np.empty((n, 3, 3))
        trans = np.empty((n, 3))
        rot[:n_in] = self._est_r[:n_in]
        trans[:n_in] = self._est_t[:n_in]
        for p in range(n_in, n):  # O(poses added since the last update)
            r = int(self._ref[p])
            if r < 0:
                rot[p], trans[p] = self._rel_r[p], self._rel_t[p]
            else:
                rot[p] = rot[r] @ self._rel_r[p]
                trans[p] = rot[r] @ self._rel_t[p] + trans[r]
        return rot, trans

    def energy(self) -> float:
        """E of :meth:`estimate` over every constraint added."""
        rot, trans = self.estimate()
        m, g = self._m, self._g
        return float(_cost.total_energy(
            rot, trans, self._ab[:m].astype(np.int32), self._zr[:m], self._zt[:m],
            self._info[:m], self._gnode[:g].astype(np.int32), self._gpos[:g],
            self._ginfo[:g]))

    def take_changes(self) -> IntArray:
        """The poses whose estimate changed since the last call: those placed (joined the
        solver) and those moved by a completed update (each once, in no particular order),
        e.g. to ship only those.  O(poses returned)."""
        k = int(self._chg_count[0])
        out = self._chg_list[:k].copy()
        self._chg_flag[out] = False
        self._chg_count[0] = 0
        return out

    @property
    def busy(self) -> bool:
        """True while an update cycle is in progress (a :meth:`solve` stopped inside it)."""
        return self._phase != _IDLE

    @property
    def pending(self) -> bool:
        """True when data was added that no update has integrated yet."""
        return (self._n_in, self._m_in, self._g_in) != (self._n, self._m, self._g)

    @property
    def settled(self) -> bool:
        """True when an update cycle without the polish would find nothing to do: no cycle
        under way, nothing added since the last one, and no pose whose step exceeds the
        relinearization thresholds.  Read-only, O(poses the last cycle moved): unlike a
        :meth:`solve` call, which begins the next cycle when there is one, with the data added
        by then (data added later waits for the cycle after it)."""
        if self.busy or self.pending or (self._planar_lost and self._nd == 3):
            return False
        cands = self._relin_cands
        if not cands.size:
            return True
        step = np.abs(self._x[cands])
        cfg = self.config
        return not bool(np.any((step[:, :3].max(axis=1) > cfg.relinearize_rho)
                               | (step[:, 3:].max(axis=1) > cfg.relinearize_phi)))

    # ----------------------------------------------------------------- solving
    def relinearize_all(self) -> None:
        """Make every pose a relinearization candidate at the next update cycle (those whose
        step exceeds the thresholds move their linearization point).  Poses whose step was
        below the thresholds when last computed are otherwise never looked at again: with the
        thresholds lowered (0: Gauss-Newton), this lets :meth:`solve` reach the batch
        optimum.  O(poses)."""
        self._relin_cands = np.union1d(self._relin_cands, np.arange(self._n_in))

    def solve(self, budget_s: float | None = None, max_cycles: int | None = None,
              polish: bool = True) -> bool:
        """Run update cycles until converged, ``budget_s`` seconds have passed, or
        ``max_cycles`` cycles were completed; resumable.  ``budget_s`` None or inf: no
        deadline.

        Returns True when it found nothing left to do: everything added is integrated and no
        pose's step exceeds the relinearization thresholds (with ``polish``, the polish
        thresholds too: ``IncrementalConfig.polish_rho``; without, the poses listed for the
        polish stay listed for a later call's).
        """
        c0 = int(read_cycles())
        deadline = (_NO_DEADLINE if budget_s is None or budget_s == np.inf
                    else np.uint64(c0 + int(max(budget_s, 0.0) * cycles_per_second())))
        done = 0
        sec = self.stats["seconds"]
        while True:
            t0 = time.perf_counter()
            if self._phase == _IDLE:
                if max_cycles is not None and done >= max_cycles:
                    return False
                if not self._start_cycle(polish):
                    sec["start"] += time.perf_counter() - t0
                    return True
            if self._phase == _LINEARIZE:
                self._run_linearize(deadline)
            if self._phase == _SYMBOLIC:
                self._run_symbolic(deadline)
            sec["start"] += time.perf_counter() - t0
            if self._phase in (_LINEARIZE, _SYMBOLIC):
                return False
            if self._phase == _NUMERIC:
                t0 = time.perf_counter()
                self._run_numeric(deadline)
                sec["numeric"] += time.perf_counter() - t0
                if self._phase == _NUMERIC:
                    return False
            if self._phase == _BACK:
                t0 = time.perf_counter()
                self._run_back(deadline)
                sec["back"] += time.perf_counter() - t0
                if self._phase == _BACK:
                    return False
                done += 1
            if np.uint64(read_cycles()) > deadline:
                return False

    def _start_cycle(self, polish: bool = True) -> bool:
        """Integrate new data, relinearize, choose S and do its symbolic factorization.
        False when there is nothing to do (converged, and polished when ``polish``)."""
        if self._start_cycle_with(self.config.relinearize_rho, self.config.relinearize_phi):
            return True
        cfg = self.config
        k = int(self._pol_count[0])
        if k == 0 or not polish:
            return False
        cands = self._pol_list[:k].copy()
        self._pol_flag[cands] = False
        self._pol_count[0] = 0
        self._relin_cands = cands
        return self._start_cycle_with(cfg.polish_rho, cfg.polish_phi)

    def _start_cycle_with(self, beta_rho: float, beta_phi: float) -> bool:
        cfg = self.config
        n0, n1 = self._n_in, self._n
        m0, m1 = self._m_in, self._m
        g0, g1 = self._g_in, self._g
        stamp = self._stamp + 1
        # the full system from now on: every constraint linearized again and every column
        # re-eliminated (the solver's steps so far have no out-of-plane part)
        full = np.zeros(0, np.int64)
        if self._planar_lost and self._nd == 3:
            rows = self._row_var
            row_var, row_blk = self._new_pool(self._pool_cap, 6)
            row_var[:] = rows  # the pool's structure stays; its blocks grow to 6x6
            self._row_var, self._row_blk = row_var, row_blk
            self._nd, self._perm = 6, np.arange(6)
            full = np.arange(n0)
        # 1. new poses and constraints
        if n1 > n0:
            ik.place_poses(n0, n1, self._ref, self._rel_r, self._rel_t, self._est_r,
                           self._est_t, self._th_r, self._th_t)
            self._free[n0:n1] = True
            if n0 == 0 and not self._first_free:
                self._free[0] = False
            ik.append_moved(np.arange(n0, n1), self._x, -1.0, -1.0, self._chg_flag,
                            self._chg_list, self._chg_count)
        ik.insert_incidences(m0, m1, self._ab, self._inc_head, self._inc_next)
        ik.insert_gps(g0, g1, self._gnode, self._gps_head, self._gps_next)
        self._n_in, self._m_in, self._g_in = n1, m1, g1
        self._cycle_cover = (n1, m1, g1)
        freed = np.zeros(0, np.int64)
        if (not self._first_free and cfg.gauge == "auto" and g1 >= cfg.gps_gauge and n1 > 0):
            self._first_free = True
            self._free[0] = True
            freed = np.zeros(1, np.int64)
        # 2. relinearization
        relin = np.zeros(0, np.int64)
        if self._relin_cands.size:
            out = np.empty(self._relin_cands.size, np.int64)
            k = ik.relinearize(self._relin_cands, beta_rho, beta_phi,
                               self._th_r, self._th_t, self._x, self._est_r, self._est_t, out)
            relin = out[:k]
            self._relin_cands = np.zeros(0, np.int64)
        if (n1 == n0 and m1 == m0 and g1 == g0 and relin.size == 0 and freed.size == 0
                and full.size == 0):
            return False
        self._stamp = stamp
        # 3. the constraints to linearize: the new ones and those of relinearized poses
        e_ids = np.empty(m1, np.int64)  # np.empty: no O(M) work
        g_ids = np.empty(g1, np.int64)
        cnt = np.zeros(2, np.int64)
        e_ids[: m1 - m0] = np.arange(m0, m1)
        g_ids[: g1 - g0] = np.arange(g0, g1)
        self._e_stamp[m0:m1] = stamp
        self._g_stamp[g0:g1] = stamp
        cnt[:] = (m1 - m0, g1 - g0)
        touch = np.concatenate([relin, freed, full])
        ik.incident_factors(touch, self._inc_head, self._inc_next, self._gps_head,
                            self._gps_next, self._e_stamp, self._g_stamp, stamp, e_ids, g_ids,
                            cnt)
        self._e_ids, self._g_ids = e_ids[: cnt[0]], g_ids[: cnt[1]]
        self._touch = touch
        self._news = (n0, n1, m0, m1, g0, g1)
        self._lin_i = 0
        self._phase = _LINEARIZE
        self.stats["relinearized"] += int(relin.size)
        return True

    def _run_linearize(self, deadline: np.uint64) -> None:
        """Linearize the cycle's constraints, a chunk at a time; then choose S."""
        e_ids, g_ids = self._e_ids, self._g_ids
        total = e_ids.shape[0] + g_ids.shape[0]
        while self._lin_i < total:
            i0 = self._lin_i
            i1 = min(i0 + _CHUNK, total)
            ne = e_ids.shape[0]
            if i0 < ne:
                i1 = min(i1, ne)
                bad = ik.linearize_edges(e_ids[i0:i1], self._th_r, self._th_t, self._ab,
                                         self._zr, self._zt, self._info, self._haa, self._hbb,
                                         self._hab, self._ga, self._gb, self._chi)
                if bad >= 0:
                    raise SolverError(f"the linearization of edge {bad} is not finite")
            else:
                bad = ik.linearize_gps(g_ids[i0 - ne: i1 - ne], self._th_r, self._th_t,
                                       self._gnode, self._gpos, self._ginfo, self._hgg,
                                       self._gg, self._gchi)
                if bad >= 0:
                    raise SolverError(f"the linearization of GPS reading {bad} is not finite")
            self._lin_i = i1
            if self._lin_i < total and np.uint64(read_cycles()) > deadline:
                return
        self._choose_set()

    def _choose_set(self) -> None:
        """S (the changed columns and their ancestors), its orphans, its new order; then the
        symbolic phase."""
        n0, n1, m0, m1, g0, g1 = self._news
        stamp = self._stamp
        e_ids, g_ids, touch = self._e_ids, self._g_ids, self._touch
        cands = np.concatenate([self._ab[e_ids].ravel(), self._gnode[g_ids], touch,
                                np.arange(n0, n1)])
        s_buf = np.empty(self._n_in, np.int64)
        ns = ik.ancestor_closure(cands, self._free, self._parent, self._in_s, stamp, s_buf)
        s_vars = s_buf[:ns]
        if ns == 0:  # only constraints between held poses: nothing to factor
            self.stats["cycles"] += 1
            self.covered = self._cycle_cover
            self._phase = _IDLE
            return
        orph_buf = np.empty(self._n_in, np.int64)
        no = ik.find_orphans(s_vars, self._in_s, stamp, self._ch_head, self._ch_next,
                             orph_buf)
        orphans = orph_buf[:no]
        newest = (np.concatenate([self._ab[m0:m1].ravel(), self._gnode[g0:g1],
                                  np.arange(n0, n1)]) if self.config.last == "ends"
                  else np.arange(n0, n1))
        order = self._order(s_vars, orphans, stamp, np.isin(s_vars, newest))
        self._position[order] = self._counter + np.arange(ns)
        self._counter += ns
        ik.detach(s_vars, orphans, self._parent, self._ch_head, self._ch_next, self._ch_prev)
        ik.link_orphans(orphans, self._position, self._col_start, self._col_len,
                        self._row_var, self._parent, self._ch_head, self._ch_next,
                        self._ch_prev)
        self._order_s = order
        self._s_vars = s_vars
        self._i = 0
        self._phase = _SYMBOLIC
        self.stats["columns"] += ns
        self.stats["max_set"] = max(self.stats["max_set"], ns)

    def _run_symbolic(self, deadline: np.uint64) -> None:
        order = self._order_s
        while True:
            r = ik.symbolic(order, self._i, deadline, self._position, self._free, self._in_s,
                            self._stamp, self._ab, self._inc_head, self._inc_next,
                            self._parent, self._ch_head, self._ch_next, self._ch_prev,
                            self._col_start, self._col_len, self._col_cap, self._row_var,
                            self._pool_used, self._mark)
            if r == ik.POOL_FULL:
                self._i = int(self._pool_used[1])
                self._grow_pool(max(2 * order.shape[0], 1024))
                continue
            if r == ik.PAST_DEADLINE:
                self._i = int(self._pool_used[1])
                return
            if r < 0:
                raise SolverError("internal error in the incremental symbolic factorization")
            break
        self._i = 0
        self._prepare_supernodes()
        self._phase = _NUMERIC

    def _prepare_supernodes(self) -> None:
        """S's supernodes (``ik.supernodes``) and room for their panels."""
        order = self._order_s
        ns = order.shape[0]
        self._sn_ptr = np.empty(ns + 1, np.int64)
        self._pan_off = np.empty(ns + 1, np.int64)
        self._sn_count = ik.supernodes(order, self._parent, self._col_len, ik.SUPERNODE_MAX,
                                       self._nd, self._sn_ptr, self._sn_of, self._pan_off)
        if self._sn_mark.shape[0] < self._sn_count:
            self._sn_mark = np.full(2 * self._sn_count, -1, np.int64)
        ptr = self._sn_ptr[: self._sn_count + 1]
        rows = int(np.max(np.diff(ptr) + self._col_len[order[ptr[1:] - 1]]))
        need = panel_scratch(rows * self._nd, ik.SUPERNODE_MAX * self._nd)
        if self._scratch.shape[0] < need:
            self._scratch = np.empty(max(need, self._scratch.shape[0] * 3 // 2))
        size = int(self._pan_off[self._sn_count])
        if self._panel.shape[0] < size:
            # kept for the next cycles (never shrunk): a cycle then allocates, first touches
            # and frees no large array, work that takes memory bandwidth from the frames'
            # process beside the worker
            self._panel = np.empty(max(size, self._panel.shape[0] * 3 // 2))

    def _order(self, s_vars: IntArray, orphans: IntArray, stamp: int,
               last: npt.NDArray[np.bool_]) -> IntArray:
        """S in its new elimination order (see the module docstring)."""
        ns = s_vars.shape[0]
        if not self.config.reorder or ns < _AMD_MIN or ns > self.config.reorder_max:
            pos = self._position[s_vars].astype(np.float64)
            pos[pos < 0] = np.inf  # new variables after the others, in index order
            key = np.lexsort((s_vars, pos, last))
            return s_vars[key]
        self._local[s_vars] = np.arange(ns)
        rows, cols = ik.reduced_pattern(s_vars, orphans, self._in_s, stamp, self._local,
                                        self._free, self._ab, self._inc_head, self._inc_next,
                                        self._col_start, self._col_len, self._row_var)
        new_pos = fill_reducing_order(ns, rows, cols)
        key = np.lexsort((new_pos, last))
        return s_vars[key]

    def _run_numeric(self, deadline: np.uint64) -> None:
        order = self._order_s
        r = ik.numeric(order, self._i, deadline, self._position, self._free, self._ab,
                       self._inc_head, self._inc_next, self._gps_head, self._gps_next,
                       self._haa, self._hbb, self._hab, self._ga, self._gb, self._hgg,
                       self._gg, self._parent, self._col_start, self._col_len, self._row_var,
                       self._row_blk, self._diag, self._y, self._slot, self._walk,
                       self._in_s, self._stamp, self._sn_ptr, self._sn_count, self._sn_of,
                       self._sn_mark, self._pan_off, self._panel, self._src,
                       self._scratch, 0.0,
                       self._nd, self._perm, self._work)
        self.stats["applied"] += int(self._work[0])
        self.stats["products"] += int(self._work[1])
        self._work[:] = 0
        if r == ik.NOT_SPD:
            raise SolverError("the normal equations are not positive definite (a pose is not "
                              "determined by its constraints, or the gauge is not fixed)")
        if r < 0:
            raise SolverError("internal error in the incremental factorization")
        self._i = r
        if r == self._sn_count:
            s = self._s_vars
            roots = s[self._parent[s] < 0]
            self._stack[: roots.shape[0]] = roots
            self._top = np.array([roots.shape[0]], np.int64)
            self._n_touched = np.zeros(1, np.int64)
            self._phase = _BACK

    def _run_back(self, deadline: np.uint64) -> None:
        done = ik.back_substitute(self._stack, self._top, deadline, self._in_s, self._stamp,
                                  self._changed, self.config.wildfire, self._ch_head,
                                  self._ch_next, self._col_start, self._col_len,
                                  self._row_var, self._row_blk, self._diag, self._y, self._x,
                                  self._touched, self._n_touched, self._nd, self._perm)
        if not done:
            return
        touched = self._touched[: int(self._n_touched[0])].copy()
        ik.publish(touched, self._th_r, self._th_t, self._x, self._est_r, self._est_t)
        self._relin_cands = touched
        ik.append_moved(touched, self._x, -1.0, -1.0, self._chg_flag, self._chg_list,
                        self._chg_count)
        cfg = self.config
        if cfg.polish_rho < cfg.relinearize_rho or cfg.polish_phi < cfg.relinearize_phi:
            ik.append_moved(touched, self._x, cfg.polish_rho, cfg.polish_phi, self._pol_flag,
                           self._pol_list, self._pol_count)
        self.stats["recomputed"] += int(touched.shape[0])
        self.stats["cycles"] += 1
        self.covered = self._cycle_cover
        self._phase = _IDLE
