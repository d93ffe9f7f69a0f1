"""Replaying a pose graph as a robot would have produced it (docs/mathematics.md#frames).

Frames come in increasing pose id: frame k brings pose k with every relative constraint
between k and an earlier pose (its odometry first, then the loop closures) and every GPS
reading on k.  :func:`replay_online` feeds them to :class:`~hybridpgo.online.OnlineSolver`
and :func:`replay_isam2` to GTSAM's ISAM2 (the optional ``gtsam`` extra), timing one update
per frame; :func:`prefix_optima` computes the batch optimum of the prefixes the accuracy is
measured against.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

try:
    import resource
except ImportError:  # not on Windows: page faults unknown there
    resource = None  # type: ignore[assignment]

from ..energy import energy
from ..errors import GraphError, SolverError
from ..graph import FloatArray, PoseGraph

IntArray = npt.NDArray[np.int64]
#: ``on_frame(k, solver, latency_s)`` of :func:`replay_online`: frame k (from 1) is done.
FrameCallback = Callable[[int, Any, float], None]


@dataclass(frozen=True)
class Stream:
    """The frames of a graph (docs/mathematics.md#frames), as index arrays into the graph's
    constraints."""

    graph: PoseGraph
    order: IntArray
    """(N,) dense pose indices in increasing id: frame k brings pose ``order[k]``."""
    odometry: IntArray
    """(N,) the edge that brings each frame's pose (-1 for the first frame)."""
    edge_ptr: IntArray
    """(N+1,) CSR over frames of :attr:`edges`."""
    edges: IntArray
    """Edges of each frame: its odometry first, then its loop closures (by edge index)."""
    gps_ptr: IntArray
    """(N+1,) CSR over frames of :attr:`gps`."""
    gps: IntArray
    """GPS readings of each frame."""
    frame_of: IntArray = field(repr=False)
    """(N,) frame of each dense pose index."""

    @property
    def num_frames(self) -> int:
        return int(self.order.shape[0])

    def odometry_from(self, k: int) -> tuple[int, FloatArray, FloatArray, FloatArray]:
        """Frame ``k``'s odometry (``k >= 1``) as a constraint from the earlier pose to the
        frame's pose: ``(earlier pose's dense index, rotation, translation, information)``,
        inverted (:func:`_inverse_edge`) when the graph stores it the other way round."""
        g = self.graph
        c = int(self.odometry[k])
        a, b = (int(v) for v in g.edge_nodes[c])
        zr, zt, info = g.edge_rotations[c], g.edge_translations[c], g.edge_information[c]
        if b != int(self.order[k]):  # stored as (k, earlier)
            zr, zt, info = _inverse_edge(zr, zt, info)
            a = b
        return a, zr, zt, info

    def prefix(self, frames: int, rotations: FloatArray | None = None,
               translations: FloatArray | None = None) -> PoseGraph:
        """The graph of the first ``frames`` frames (poses, their edges and GPS), at the given
        poses of those frames' poses (default: the graph's own)."""
        g = self.graph
        keep = self.order[:frames]
        remap = np.full(g.num_nodes, -1, np.int64)
        remap[keep] = np.arange(frames)
        e = np.sort(self.edges[: self.edge_ptr[frames]])
        s = np.sort(self.gps[: self.gps_ptr[frames]])
        rot = g.rotations[keep] if rotations is None else rotations
        trans = g.translations[keep] if translations is None else translations
        return PoseGraph(
            node_ids=g.node_ids[keep], rotations=rot, translations=trans,
            edge_nodes=remap[g.edge_nodes[e]].astype(np.int32), edge_rotations=g.edge_rotations[e],
            edge_translations=g.edge_translations[e], edge_information=g.edge_information[e],
            gps_nodes=remap[g.gps_nodes[s]].astype(np.int32), gps_positions=g.gps_positions[s],
            gps_information=g.gps_information[s], is_2d=g.is_2d,
        )  # fmt: skip


def make_stream(graph: PoseGraph) -> Stream:
    """Split ``graph`` into frames (docs/mathematics.md#frames).

    A pose's odometry is its edge to the latest earlier pose (normally the previous one).

    Raises
    ------
    GraphError
        A pose after the first has no relative constraint to an earlier pose, so it cannot
        join the map when it arrives.
    """
    n = graph.num_nodes
    order = np.argsort(graph.node_ids, kind="stable")
    frame_of = np.empty(n, np.int64)
    frame_of[order] = np.arange(n)
    fa = frame_of[graph.edge_nodes[:, 0]]
    fb = frame_of[graph.edge_nodes[:, 1]]
    hi = np.maximum(fa, fb)
    lo = np.minimum(fa, fb)
    # the odometry of frame k: its edge to the latest earlier frame (first in file order)
    srt = np.lexsort((np.arange(hi.shape[0]), -lo, hi))
    first = np.ones(srt.shape[0], bool)
    first[1:] = hi[srt[1:]] != hi[srt[:-1]]
    odo = np.full(n, -1, np.int64)
    odo[hi[srt[first]]] = srt[first]
    self_loop = lo == hi
    if np.any(self_loop):
        c = int(np.nonzero(self_loop)[0][0])
        raise GraphError(f"edge {c} joins pose id {int(graph.node_ids[graph.edge_nodes[c, 0]])} "
                         "to itself")
    missing = np.nonzero(odo[1:] < 0)[0]
    if missing.size:
        pid = int(graph.node_ids[order[missing[0] + 1]])
        raise GraphError(f"pose id {pid} has no constraint to an earlier pose, so it cannot "
                         "join the map when it arrives (frames come in increasing pose id)")
    is_odo = np.zeros(hi.shape[0], bool)
    is_odo[odo[1:]] = True
    # edges by frame: odometry first, then the rest in file order
    e_order = np.lexsort((np.arange(hi.shape[0]), ~is_odo, hi))
    edge_ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(hi, minlength=n), out=edge_ptr[1:])
    fg = frame_of[graph.gps_nodes]
    g_order = np.argsort(fg, kind="stable")
    gps_ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(fg, minlength=n), out=gps_ptr[1:])
    return Stream(graph, order, odo, edge_ptr, e_order.astype(np.int64), gps_ptr,
                  g_order.astype(np.int64), frame_of)


def _inverse_edge(rot: FloatArray, trans: FloatArray, info: FloatArray
                  ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The same constraint stored the other way round: ``Z^-1`` with
    ``Omega' = Ad(Z^-1)^T Omega Ad(Z^-1)`` (since ``e' = -Ad(Z) e`` exactly, E is unchanged)."""
    ri = rot.T
    ti = -ri @ trans
    ad = np.zeros((6, 6))
    ad[:3, :3] = ri
    ad[3:, 3:] = ri
    tx = np.array([[0, -ti[2], ti[1]], [ti[2], 0, -ti[0]], [-ti[1], ti[0], 0]])
    ad[:3, 3:] = tx @ ri
    info2 = ad.T @ info @ ad
    return ri, ti, 0.5 * (info2 + info2.T)


def feed_frame(solver: Any, stream: Stream, k: int) -> None:
    """Give frame k's pose, edges and GPS readings to an :class:`OnlineSolver`."""
    g = stream.graph
    ids = g.node_ids
    p = int(stream.order[k])
    e0, e1 = int(stream.edge_ptr[k]), int(stream.edge_ptr[k + 1])
    if k == 0:
        solver.add_pose(int(ids[p]))
    else:
        a, zr, zt, info = stream.odometry_from(k)
        solver.add_pose(int(ids[p]), int(ids[a]), (zr, zt), info)
        e0 += 1
    for c in stream.edges[e0:e1].tolist():
        a, b = g.edge_nodes[c]
        solver.add_constraint(int(ids[a]), int(ids[b]), (g.edge_rotations[c],
                              g.edge_translations[c]), g.edge_information[c])
    for s in stream.gps[stream.gps_ptr[k]: stream.gps_ptr[k + 1]].tolist():
        solver.add_gps(int(ids[g.gps_nodes[s]]), g.gps_positions[s], g.gps_information[s])


def checkpoint_frames(num_frames: int, every: int) -> list[int]:
    """Frame counts at which accuracy is measured: every ``every`` frames and the last."""
    out = list(range(every, num_frames, every))
    if not out or out[-1] != num_frames:
        out.append(num_frames)
    return out


def prefix_optima(stream: Stream, frames: Sequence[int], max_iterations: int = 100,
                  progress: Callable[[int, float], None] | None = None,
                  robust: Literal["none", "auto"] = "none") -> dict[int, float]:
    """Batch optimum (exact LM) of each prefix; each warm-starts from the previous optimum,
    the new poses composed from their odometry (independent of any online solver).
    ``robust="auto"``: each prefix is solved as the exact solver's default would, the
    outlier test and re-solve included, and its optimum is the energy of the constraints
    kept (what :meth:`~hybridpgo.online.OnlineSolver.energy` counts)."""
    from ..solvers.config import GaussNewtonConfig
    from ..solvers.gauss_newton import solve_exact

    out: dict[int, float] = {}
    rot = np.empty((0, 3, 3))
    trans = np.empty((0, 3))
    for f in frames:
        r = np.empty((f, 3, 3))
        t = np.empty((f, 3))
        k0 = rot.shape[0]
        r[:k0] = rot
        t[:k0] = trans
        for k in range(k0, f):
            if k == 0:
                r[0] = np.eye(3)
                t[0] = 0.0
                continue
            a, zr, zt, _ = stream.odometry_from(k)
            ka = int(stream.frame_of[a])
            r[k] = r[ka] @ zr
            t[k] = r[ka] @ zt + t[ka]
        pg = stream.prefix(f, r, t)
        res = solve_exact(pg, r, t, GaussNewtonConfig(max_iterations=max_iterations,
                                                      robust=robust))
        rot, trans = res.rotations, res.translations
        out[f] = float(res.final_energy)
        if progress:
            progress(f, out[f])
    return out


#: Energies below this count as this much in :func:`energy_ratio`.  A prefix with no loop closure
#: (odometry only; valencia's first 2 000 frames) has the optimum 0 up to rounding (1e-25 to
#: 1e-17), and the ratio of two rounding errors (measured up to 1e5) says nothing; any constraint
#: that is not satisfied exactly contributes far more than this (a chi^2 of 1e-6 is a thousandth
#: of a standard deviation).
ENERGY_FLOOR = 1e-6


def energy_ratio(energy: float, optimum: float) -> float:
    """``energy / optimum`` with both raised to :data:`ENERGY_FLOOR` (see there)."""
    return max(energy, ENERGY_FLOOR) / max(optimum, ENERGY_FLOOR)


@dataclass
class ReplayResult:
    """Per-frame measurements of one replay."""

    name: str
    latency_s: FloatArray
    """(F,) wall time of each frame's whole work: giving the solver its data (``add_*``), its
    update and reading the current pose."""
    cpu_s: FloatArray
    """(F,) the main thread's CPU time of the same (not inflated by preemption or by the
    background worker: the "steady" latency)."""
    checkpoints: dict[int, float]
    """Energy of the estimate over the prefix, at each checkpoint frame count."""
    extra_energy: list[float] = dataclasses.field(default_factory=list)
    """After the last frame: the energy after each extra frame (no new data, same budget)."""
    extra_latency_s: list[float] = dataclasses.field(default_factory=list)
    info: dict[str, Any] = dataclasses.field(default_factory=dict)

    def summary(self, optima: dict[int, float] | None = None) -> dict[str, Any]:
        lat = self.latency_s * 1e3
        out: dict[str, Any] = {
            "frames": int(lat.shape[0]),
            "latency_ms_mean": float(lat.mean()),
            "latency_ms_p99": float(np.quantile(lat, 0.99)),
            "latency_ms_max": float(lat.max()),
            "latency_ms_steady_max": float(self.cpu_s.max() * 1e3),
            "final_energy": self.checkpoints[max(self.checkpoints)],
        }
        if optima:
            ratios = {f: energy_ratio(e, optima[f]) for f, e in self.checkpoints.items()
                      if f in optima}
            out["energy_ratio"] = ratios
            out["energy_ratio_max"] = max(ratios.values())
            last = max(ratios)
            out["final_ratio"] = ratios[last]
            if self.extra_energy:
                ex = [energy_ratio(e, optima[last]) for e in self.extra_energy]
                out["extra_ratio"] = ex
                hit = [i + 1 for i, r in enumerate(ex) if r <= 1.01]
                out["extra_frames_to_1pct"] = hit[0] if hit else None
                out["extra_latency_ms_max"] = float(np.max(self.extra_latency_s) * 1e3)
        return out


#: Seconds :func:`replay_online` waits for the background worker to start before the stream.
BACKGROUND_START_TIMEOUT_S = 60.0


def replay_online(stream: Stream, config: Any = None, budget_s: float | None = 5e-3, *,
                  checkpoints: Sequence[int] = (), extra_frames: int = 0,
                  refine_every: int = 0, refine_offset: int = 0,
                  progress: Callable[[int, float], None] | None = None,
                  on_frame: FrameCallback | None = None,
                  rate_hz: float | None = None) -> ReplayResult:
    """Stream ``stream`` into an :class:`OnlineSolver`, one :meth:`update` per frame.

    A frame's latency is all of its work: giving the solver the frame's pose, edges and GPS
    readings (``add_*``), its ``update`` and the estimate of the pose it brought (what the
    robot reads); the energy over the prefix is evaluated at ``checkpoints`` outside the timing.
    Frames come back to back (the worst case), or with ``rate_hz`` at that rate (a lidar: 10):
    the time between a frame's work and the next frame's arrival goes to
    :meth:`OnlineSolver.idle` (and to the worker, in its own process), outside the latency.
    With ``refine_every = K``, frames ``k`` with ``k % K == refine_offset`` (counting from 1)
    also run :meth:`OnlineSolver.refine` (the whole-map exact solve), inside their latency.
    ``on_frame(k, solver, latency_s)`` is called after every frame ``k`` (counting from 1, the
    extra frames continuing the count), outside the timing (e.g. to record the run).
    With ``background_refine``, the stream starts once the worker is up
    (:meth:`OnlineSolver.wait_background_ready`, as a robot starts its back end before it
    drives); the wait is ``info["background_start_s"]``.
    """
    from .solver import OnlineSolver

    solver = OnlineSolver(config)
    try:
        t0 = time.perf_counter()
        if solver.config.background_refine:  # started before the drive, as on a robot
            solver.wait_background_ready(BACKGROUND_START_TIMEOUT_S)
        start_s = time.perf_counter() - t0
        if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be a finite number > 0, got {rate_hz!r}")
        result = _replay_online(solver, stream, budget_s, checkpoints, extra_frames,
                                refine_every, refine_offset, progress, on_frame, rate_hz)
    finally:
        solver.close()
    if solver.config.background_refine:
        result.info["background_start_s"] = start_s
    return result


#: Frames reported in ``ReplayResult.info["worst_frames"]``.
WORST_FRAMES = 5


class _MachineClock:
    """What the machine took from the frames' thread, where Linux tells it: the time the
    thread waited for a CPU (its ``schedstat``'s run delay, nanoseconds) and the time the host
    took from this virtual machine's CPUs (``steal`` in ``/proc/stat``: all CPUs together, in
    clock ticks of usually 10 ms, so a frame of a few ms may show a tick the host took from the
    other CPU).  Where the guest kernel does not subtract steal from a thread's run time, a
    host that stops a virtual CPU makes the thread's CPU time look longer; where it does, the
    steal lengthens only the wall time.  Also what the process did that the solver does not
    decide: the time spent in Python's garbage collections (any thread's; the solver holds
    automatic collection off in its frames, :func:`~._frame.uncollected`) and the thread's page
    faults (``getrusage``; first writes to fresh memory, which a virtual machine's host may
    back slowly).  Read outside the frames' timing; :meth:`read` gives ``(waited_s, stolen_s,
    collected_s, faults)`` so far, NaN where the system does not tell (no such file, or one
    that cannot be read or parsed)."""

    #: The thread's scheduler statistics (``/proc/self/task/TID/schedstat`` on kernels
    #: before 3.17, :meth:`__init__`) and the system's CPU times.
    PATHS = ("/proc/thread-self/schedstat", "/proc/stat")

    def __init__(self) -> None:
        import threading
        import weakref

        sched, stat = self.PATHS
        if sched.startswith("/proc/thread-self/") and not os.path.exists("/proc/thread-self"):
            sched = f"/proc/self/task/{threading.get_native_id()}/schedstat"
        self._fds: list[int | None] = []
        for path in (sched, stat):
            try:
                self._fds.append(os.open(path, os.O_RDONLY))
            except OSError:
                self._fds.append(None)
        # descriptors, not file objects: closed when the clock goes, also after an error
        # inside a replay, without a ResourceWarning (with the collection callback, below)
        try:
            self._tick = 1.0 / float(os.sysconf("SC_CLK_TCK"))
        except (AttributeError, ValueError, OSError):
            self._tick = 0.01
        # seconds in collections so far, and when the current one started (a closure over
        # the list, not a method: gc.callbacks would keep the clock alive)
        collected = self._collected = [0.0, 0.0]

        def on_collection(phase: str, info: dict[str, int]) -> None:
            if phase == "start":
                collected[1] = time.perf_counter()
            else:
                collected[0] += time.perf_counter() - collected[1]

        gc.callbacks.append(on_collection)
        self._close = weakref.finalize(self, _close_all, list(self._fds), on_collection)

    @staticmethod
    def _faults() -> float:
        who = getattr(resource, "RUSAGE_THREAD", None)  # Linux
        if who is None:
            return float("nan")
        try:
            use = resource.getrusage(who)
        except (OSError, ValueError):
            return float("nan")
        return float(use.ru_minflt + use.ru_majflt)

    def read(self) -> tuple[float, float, float, float]:
        sched, stat = self._fds
        waited = stolen = float("nan")
        if sched is not None:
            try:
                waited = int(os.pread(sched, 256, 0).split()[1]) * 1e-9
            except (OSError, ValueError, IndexError):
                pass
        if stat is not None:
            try:
                line = os.pread(stat, 256, 0).split(b"\n", 1)[0].split()
                if line[0] == b"cpu" and len(line) > 8:
                    stolen = int(line[8]) * self._tick
            except (OSError, ValueError, IndexError):
                pass
        return waited, stolen, self._collected[0], self._faults()

    def close(self) -> None:
        self._close()


def _close_all(fds: list[int | None], callback: Any = None) -> None:
    if callback in gc.callbacks:
        gc.callbacks.remove(callback)
    for fd in fds:
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass


def _replay_online(solver: Any, stream: Stream, budget_s: float | None,
                   checkpoints: Sequence[int], extra_frames: int, refine_every: int,
                   refine_offset: int, progress: Callable[[int, float], None] | None,
                   on_frame: FrameCallback | None = None,
                   rate_hz: float | None = None) -> ReplayResult:
    nf = stream.num_frames
    lat = np.empty(nf)
    cpu = np.empty(nf)
    # what each frame's update did (FrameReport's counts), in an array: a list of one object
    # per frame would lengthen every full garbage collection as the stream goes on
    done = np.zeros((nf, len(_REPORT_FIELDS)), np.int64)
    # per frame: waited for a CPU, taken by the host, garbage collections (s), page faults
    machine = np.full((nf, 4), np.nan)
    clock = _MachineClock()
    marks = set(checkpoints)
    energies: dict[int, float] = {}
    ids = stream.graph.node_ids
    period = None if rate_hz is None else 1.0 / rate_hz
    clock0 = time.perf_counter()
    idle_s = 0.0
    for k in range(nf):
        if period is not None:  # the frame arrives at its time; the back end had the wait
            arrival = clock0 + k * period
            now = time.perf_counter()
            if arrival - now > 1e-4:
                t_idle = time.perf_counter()
                solver.idle(arrival - now)
                idle_s += time.perf_counter() - t_idle
                rest = arrival - time.perf_counter()
                if rest > 0:
                    time.sleep(rest)
        pid = int(ids[stream.order[k]])
        m0 = clock.read()
        c0 = time.thread_time()
        t0 = time.perf_counter()
        feed_frame(solver, stream, k)
        rep = solver.update(budget_s)
        if refine_every and (k + 1) % refine_every == refine_offset:
            solver.refine()
        solver.pose(pid)
        lat[k] = time.perf_counter() - t0
        cpu[k] = time.thread_time() - c0
        m1 = clock.read()
        machine[k] = np.subtract(m1, m0)
        done[k] = [getattr(rep, f) for f in _REPORT_FIELDS]
        if on_frame is not None:
            on_frame(k + 1, solver, float(lat[k]))
        if k + 1 in marks:
            energies[k + 1] = solver.energy()
            if progress:
                progress(k + 1, energies[k + 1])
    energies[nf] = solver.energy()
    extra_e: list[float] = []
    extra_l: list[float] = []
    last = int(ids[stream.order[nf - 1]])
    for j in range(extra_frames):
        if period is not None:
            solver.idle(period)
        t0 = time.perf_counter()
        solver.update(budget_s)
        solver.pose(last)
        extra_l.append(time.perf_counter() - t0)
        if on_frame is not None:
            on_frame(nf + j + 1, solver, extra_l[-1])
        extra_e.append(solver.energy())
    name = f"hybridpgo+refine/{refine_every}" if refine_every else "hybridpgo"
    if solver.config.background_refine:
        name += "+background"
    worst = np.argsort(-cpu, kind="stable")[:WORST_FRAMES]
    info = {**solver.stats(), "compile_s": solver.compile_seconds,
            "worst_frames": [_frame_note(stream, int(k), lat, cpu, done[k], machine[k])
                             for k in worst]}
    clock.close()
    if period is not None:
        info.update(rate_hz=rate_hz, idle_s=idle_s)
    return ReplayResult(name, lat, cpu, energies, extra_e, extra_l, info)


#: The counts of :class:`~hybridpgo.online.FrameReport` a replay keeps per frame.
_REPORT_FIELDS = ("new", "old", "backlog", "local_nodes", "skipped")


def _frame_note(stream: Stream, k: int, lat: FloatArray, cpu: FloatArray,
                done: npt.NDArray[np.int64], machine: FloatArray) -> dict[str, Any]:
    """What frame k brought and what its update did (one of the worst frames; ``done``: its
    :data:`_REPORT_FIELDS`), and what the machine took meanwhile (``machine``: the thread's
    wait for a CPU, the host's steal and the garbage collections, seconds, and the thread's
    page faults, :class:`_MachineClock`; None where the system does not tell)."""
    waited, stolen, collected = (float(v) * 1e3 if np.isfinite(v) else None
                                 for v in machine[:3])
    faults = int(machine[3]) if np.isfinite(machine[3]) else None
    return {"frame": k + 1, "cpu_ms": float(cpu[k] * 1e3), "wall_ms": float(lat[k] * 1e3),
            "edges": int(stream.edge_ptr[k + 1] - stream.edge_ptr[k]),
            "gps": int(stream.gps_ptr[k + 1] - stream.gps_ptr[k]),
            **{f: int(v) for f, v in zip(_REPORT_FIELDS, done, strict=True)},
            "waited_ms": waited, "stolen_ms": stolen, "collected_ms": collected,
            "faults": faults}


# --------------------------------------------------------------------------- iSAM2
def _rot_z(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _import_gtsam() -> Any:
    import importlib

    try:
        return importlib.import_module("gtsam")
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("the iSAM2 comparison needs GTSAM: pip install 'hybridpgo[gtsam]'"
                          ) from exc


def _gtsam_pose(graph: PoseGraph, rot: FloatArray, trans: FloatArray) -> Any:
    gtsam = _import_gtsam()
    if graph.is_2d:
        return gtsam.Pose2(trans[0], trans[1], float(math.atan2(rot[1, 0], rot[0, 0])))
    return gtsam.Pose3(gtsam.Rot3(rot), trans)


def replay_isam2(stream: Stream, *, checkpoints: Sequence[int] = (), extra_frames: int = 0,
                 relinearize_skip: int = 1, factorization: str = "QR",
                 max_seconds: float | None = None,
                 progress: Callable[[int, float], None] | None = None) -> ReplayResult:
    """The same stream through GTSAM's ISAM2, one ``update`` per frame.

    Factors are built from *our* information (docs/conventions.md: the tangent order permuted to
    GTSAM's
    (rotation, translation)), so ``2 * error`` is our energy.  The first pose gets a tight prior
    when the graph has no GPS (the gauge our solver also fixes); with GPS it gets a weak prior
    (1e3 m, 1e3 rad), because GTSAM needs a gauge before the readings define one.  A frame's
    latency is ``update`` plus ``calculateEstimate`` of the frame's pose.  ``extra_frames``:
    after the stream, updates without new factors (each one more Gauss-Newton iteration on the
    variables iSAM2 relinearizes), with the energy after each.  ``factorization``: "QR" by
    default, since "CHOLESKY" (GTSAM's default) reports an indeterminate system on the
    generated cities (roll/pitch information 8e6 beside 2e3 on translation: valencia, frame
    2893).  ``max_seconds``: stop feeding frames once the updates have taken this long in
    all (the result then covers the frames reached; ``info["frames_reached"]``).
    """
    gtsam = _import_gtsam()
    g = stream.graph
    planar = g.is_2d
    if planar and g.num_gps:
        raise GraphError("GPS readings on a 2D graph")
    perm = np.r_[3:6, 0:3]
    idx2 = np.array([0, 1, 5])
    params = gtsam.ISAM2Params()
    params.relinearizeSkip = relinearize_skip
    params.setFactorization(factorization)
    isam = gtsam.ISAM2(params)
    nf = stream.num_frames
    lat = np.empty(nf)
    cpu = np.empty(nf)
    marks = set(checkpoints)
    energies: dict[int, float] = {}
    # our energy of the estimate over the prefix, via our own cost layer
    est_rot = np.zeros((g.num_nodes, 3, 3))
    est_trans = np.zeros((g.num_nodes, 3))
    calc = isam.calculateEstimatePose2 if planar else isam.calculateEstimatePose3

    def model(info: FloatArray) -> Any:
        if planar:
            return gtsam.noiseModel.Gaussian.Information(info[np.ix_(idx2, idx2)])
        return gtsam.noiseModel.Gaussian.Information(info[np.ix_(perm, perm)])

    def between(a: int, b: int, rot: FloatArray, trans: FloatArray, info: FloatArray) -> Any:
        z = _gtsam_pose(g, rot, trans)
        cls = gtsam.BetweenFactorPose2 if planar else gtsam.BetweenFactorPose3
        return cls(a, b, z, model(info))

    guess: dict[int, tuple[FloatArray, FloatArray]] = {}
    spent = 0.0
    reached = nf
    for k in range(nf):
        if max_seconds is not None and spent > max_seconds:
            reached = k
            break
        p = int(stream.order[k])
        factors = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if k == 0:
            r0, t0_ = np.eye(3), np.zeros(3)
            sigma = 1e3 if g.num_gps else 1e-6
            dim = 3 if planar else 6
            prior = gtsam.PriorFactorPose2 if planar else gtsam.PriorFactorPose3
            factors.add(prior(p, _gtsam_pose(g, r0, t0_),
                              gtsam.noiseModel.Isotropic.Sigma(dim, sigma)))
        else:
            c = int(stream.odometry[k])
            a, b = (int(v) for v in g.edge_nodes[c])
            zr, zt = g.edge_rotations[c], g.edge_translations[c]
            other = a if b == p else b
            ra, ta = guess[other]
            if b == p:
                r0, t0_ = ra @ zr, ra @ zt + ta
            else:
                r0, t0_ = ra @ zr.T, ra @ (-zr.T @ zt) + ta
        values.insert(p, _gtsam_pose(g, r0, t0_))
        for c in stream.edges[stream.edge_ptr[k]: stream.edge_ptr[k + 1]].tolist():
            a, b = (int(v) for v in g.edge_nodes[c])
            factors.add(between(a, b, g.edge_rotations[c], g.edge_translations[c],
                                g.edge_information[c]))
        for s in stream.gps[stream.gps_ptr[k]: stream.gps_ptr[k + 1]].tolist():
            factors.add(gtsam.GPSFactor(p, g.gps_positions[s],
                                        gtsam.noiseModel.Gaussian.Information(
                                            g.gps_information[s])))
        c0 = time.process_time()
        t0 = time.perf_counter()
        try:
            isam.update(factors, values)
            est = calc(p)
        except RuntimeError as exc:  # GTSAM's exceptions (an indeterminate system, ...)
            raise SolverError(f"isam2 stopped at frame {k + 1}: GTSAM: "
                              f"{_first_sentence(exc)}") from exc
        lat[k] = time.perf_counter() - t0
        cpu[k] = time.process_time() - c0
        spent += lat[k]
        if planar:
            th = est.theta()
            guess[p] = (_rot_z(th), np.array([est.x(), est.y(), 0.0]))
        else:
            guess[p] = (est.rotation().matrix(), np.asarray(est.translation()))
        if k + 1 in marks or k + 1 == nf:
            energies[k + 1] = _isam2_energy(stream, isam, k + 1, est_rot, est_trans)
            if progress:
                progress(k + 1, energies[k + 1])
    extra_e: list[float] = []
    extra_l: list[float] = []
    if reached < nf:
        lat, cpu = lat[:reached], cpu[:reached]
        energies.setdefault(reached, _isam2_energy(stream, isam, reached, est_rot, est_trans))
        extra_frames = 0
    last = int(stream.order[reached - 1])
    for j in range(extra_frames):
        t0 = time.perf_counter()
        try:
            isam.update()
            calc(last)
        except RuntimeError as exc:
            raise SolverError(f"isam2 stopped at extra frame {j + 1}: GTSAM: "
                              f"{_first_sentence(exc)}") from exc
        extra_l.append(time.perf_counter() - t0)
        extra_e.append(_isam2_energy(stream, isam, nf, est_rot, est_trans))
    name = "isam2" if reached == nf else f"isam2 (stopped at frame {reached})"
    return ReplayResult(name, lat, cpu, energies, extra_e, extra_l,
                        {"relinearize_skip": relinearize_skip, "factorization": factorization,
                         "frames_reached": reached, "seconds_in_updates": spent})


def _first_sentence(exc: BaseException) -> str:
    """The first sentence of a (GTSAM) exception's message, on one line."""
    text = " ".join(str(exc).split())
    end = text.find(". ")
    return (text[:end + 1] if end >= 0 else text) or type(exc).__name__


def _isam2_energy(stream: Stream, isam: Any, frames: int, est_rot: FloatArray,
                  est_trans: FloatArray) -> float:
    """Our energy of iSAM2's full estimate over the prefix of ``frames`` frames."""
    planar = stream.graph.is_2d
    vals = isam.calculateEstimate()
    keep = stream.order[:frames]
    for q in keep.tolist():
        if planar:
            ps = vals.atPose2(q)
            est_rot[q] = _rot_z(ps.theta())
            est_trans[q] = (ps.x(), ps.y(), 0.0)
        else:
            ps = vals.atPose3(q)
            est_rot[q] = ps.rotation().matrix()
            est_trans[q] = ps.translation()
    return energy(stream.prefix(frames, est_rot[keep], est_trans[keep]))
