"""The online mode's exact solve of the whole map, in a worker process.

:class:`~.solver.OnlineSolver` with ``OnlineConfig(background_refine=True)`` ships every pose,
constraint and GPS reading to a worker process as they are integrated; the worker keeps its own
copy of the map in an incremental exact solver
(:class:`~hybridpgo.online.incremental.IncrementalExact`, kept for the life of the worker: each
request re-eliminates only the part of the factor the new data and the moved poses touch) and
answers with its optimum of everything shipped (the poses added since the last answer start
composed onto their parents with the tree-local transforms the online solver gave them).  With a
robust kernel, which the incremental solver does not have, each request runs the exact
Levenberg-Marquardt solve (:func:`~hybridpgo.solvers.gauss_newton.solve_exact`) of the whole
map instead, warm-started from its previous optimum.  With ``robust="auto"`` the solves are
least squares and each answer is screened for outliers (:meth:`_Map._screen`): when the outlier
test of :mod:`hybridpgo.solvers.robust` fails, the robust re-solve of the whole map decides
which constraints are rejected, the incremental solver starts again without them, and every
answer names them (the frames stop relaxing them).  Each result comes
back as *tree-local* transforms (each pose relative to its parent in the online solver's tree,
which never changes once a pose is placed), so the next :meth:`~.solver.OnlineSolver.update`
adopts it by one copy of ``(n, 3, 3)`` and ``(n, 3)`` arrays, and the poses added after the
snapshot move along with their parents.

Why a process and not a thread: the solver runs long stretches of Python between its Numba
kernels, all with the GIL held, and so do CHOLMOD (cvxopt) and AMD (cvxopt) for the whole
factorization (their extension modules never release it: no ``PyEval_SaveThread`` import), and so
does every stretch of Python between the Numba kernels.  Measured on M3500_isam with a 5 ms budget
per frame: a thread running the exact solve beside the frames raised the frame latency max to
44.6 ms with CHOLMOD and 25.6 ms with SuperLU (which releases the GIL but still needs AMD), against
9.7 ms without it.  A process shares no GIL; the frames only pay for shipping the new data
(O(new)) and for adopting a result (one memcpy of the map's local transforms).

Protocol (both directions, binary on the worker's stdin and stdout): an 8-byte little-endian
length of a JSON header, the header (``{"type": ..., "arrays": [[name, dtype, shape], ...],
...}``) and the arrays' raw bytes in order. Main -> worker: ``data`` (new tree nodes with their
parent and local transform, new edges, new GPS readings), ``solve`` (answer request ``req``
with the optimum of everything shipped so far; ``thorough``: solved to the optimum, polish
included, and every constraint screened, those rejected before included), EOF to stop.
Worker -> main: ``ready`` once its kernels are loaded (:meth:`BackgroundRefiner.wait_ready`), then
``result`` (``n`` tree nodes below the earth, their local transforms, ``m`` and ``g`` the edges
and GPS readings shipped, ``m_held`` and ``g_held`` those the estimate holds, ``rejected_m``
and ``rejected_g`` the rejected ones among those held, the iterations, energy and status) or
``error``. With ``robust="auto"`` a request may have a second ``result`` (status
``"screened"``): the outlier test due with its answer runs after that answer was sent
(:meth:`_Map.screen_after`), and a re-solve that rejected constraints answers it again.
An incremental solve stopped by :data:`SOLVE_CAP_S` answers with the last completed
update cycle's estimate, which holds fewer constraints than were shipped: the frames count the
missing ones in the answer's age (:data:`~._link.MAX_TAIL`).

The worker solves only on request.  The asynchronous mode keeps one request outstanding and
makes the next as soon as the answer is adopted, so which prefix each answer covers depends on
timing; the synchronous mode (``OnlineConfig.background_join = K``) requests every K frames and
waits K frames later, so runs are reproducible while the requests stay within the worker's
time bounds (:data:`MORE_CYCLES_S`, :data:`SOLVE_CAP_S`, :data:`SLOW_INCREMENTAL_S`).
"""

from __future__ import annotations

import gc
import json
import os
import queue
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import IO, Any

import numpy as np

from .._tree_kernels import globals_from_locals
from ..errors import HybridPGOError

#: The worker process's program: this module imported as part of its package (``-m`` would run
#: it a second time as ``__main__`` beside the package's copy, with a warning).
_ENTRY = ("import sys; from hybridpgo.online.worker import _worker; "
          "sys.exit(_worker(int(sys.argv[1]), sys.argv[2]))")
#: Failed incremental solves after which the worker's map stays with LM.
MAX_RESETS = 3
#: Niceness added to the worker process (the frames get the CPU first on a busy machine).
WORKER_NICE = 5
#: The worker's environment: one thread for BLAS (CHOLMOD's supernodes), OpenMP and Numba.  The
#: worker is one core's job beside the frames; a second BLAS thread competing with the frames
#: for the other core made every solve 4-10x slower (M3500_isam, warm LM solve of the whole map
#: while the frames run: 0.31-0.45 s with OpenBLAS's default of a thread per core, 0.08-0.11 s
#: with one; 0.045 s with the frames idle).
WORKER_THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                  "NUMBA_NUM_THREADS": "1"}
#: The worker's switch interval (seconds): its reader thread gets the GIL this soon after a
#: message arrives while a solve runs, so that new data stops a polish promptly
#: (:data:`POLISH_SLICE_S`); the interpreter's default is 5 ms.
WORKER_SWITCH_S = 1e-4
#: Seconds :meth:`BackgroundRefiner.close` waits for the worker to exit before killing it.
STOP_TIMEOUT_S = 5.0
_HEADER = struct.Struct("<Q")
#: Capacity asked for the pipe of the worker's answers (bytes; Linux's default limit for an
#: unprivileged process is 1 MiB, its default capacity 64 KiB).
PIPE_BYTES = 1 << 20
#: Largest JSON header accepted (a corrupted stream otherwise asks for huge buffers).
_MAX_HEADER = 1 << 20

Arrays = dict[str, np.ndarray]


# --------------------------------------------------------------------------- framing
def _parts(meta: dict[str, Any], arrays: Arrays) -> list[Any]:
    """A message as buffers: header length and JSON header (with the arrays' layout), then
    each array's bytes (the arrays themselves, C-contiguous: no copy)."""
    parts = [np.ascontiguousarray(a) for a in arrays.values()]
    head = dict(meta, arrays=[[k, a.dtype.str, list(a.shape)]
                              for k, a in zip(arrays, parts, strict=True)])
    hb = json.dumps(head).encode()
    return [_HEADER.pack(len(hb)) + hb, *(a.data.cast("B") for a in parts if a.nbytes)]


def encode(meta: dict[str, Any], arrays: Arrays) -> bytes:
    """One message (:func:`_parts`) as bytes: a copy of the arrays taken now."""
    return b"".join(_parts(meta, arrays))


def write_all(fh: IO[bytes], data: bytes) -> None:
    """Write all of ``data`` to a raw (unbuffered) file, which may accept less per call."""
    view = memoryview(data)
    while view:
        k = fh.write(view)
        if k is None:  # pragma: no cover - only non-blocking files return None
            raise OSError("write would block")
        view = view[k:]


def write_message(fh: IO[bytes], meta: dict[str, Any], arrays: Arrays) -> None:
    """Write one message (:func:`encode`'s bytes) straight from the arrays: a C-contiguous
    array is not copied (an answer on 15 000 poses: 1.4 MB).  The arrays must not change
    until it returns."""
    for part in _parts(meta, arrays):
        write_all(fh, part)


def widen_pipe(fd: int) -> None:
    """Give the pipe ``fd`` :data:`PIPE_BYTES` of capacity where the system lets us (Linux;
    elsewhere, or above the system's limit, it keeps its own): an answer the pipe holds whole
    is written at once, and the frames' receiving thread takes it in few reads."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not a POSIX system
        return
    op = getattr(fcntl, "F_SETPIPE_SZ", None)
    if op is None:  # pragma: no cover - not Linux
        return
    try:
        fcntl.fcntl(fd, op, PIPE_BYTES)
    except OSError:  # pragma: no cover - not a pipe, above /proc/sys/fs/pipe-max-size, or
        pass  # past the user's quota of pipe memory: the pipe keeps its capacity


def _read_exact(fh: IO[bytes], buf: memoryview) -> bool:
    """Fill ``buf`` from ``fh`` (raw, may return short reads); False at a clean EOF."""
    got = 0
    while got < len(buf):
        k = fh.readinto(buf[got:])  # type: ignore[attr-defined]
        if not k:
            if got == 0:
                return False
            raise EOFError("truncated message")
        got += k
    return True


def read_message(fh: IO[bytes]) -> tuple[dict[str, Any], Arrays] | None:
    """The next message from ``fh``, or None at EOF.  Arrays are read straight into fresh
    NumPy buffers (no copy with the GIL held beyond each ``read`` call)."""
    hbuf = bytearray(_HEADER.size)
    if not _read_exact(fh, memoryview(hbuf)):
        return None
    (size,) = _HEADER.unpack(hbuf)
    if size > _MAX_HEADER:
        raise ValueError(f"message header of {size} bytes")
    head = bytearray(size)
    if not _read_exact(fh, memoryview(head)):
        raise EOFError("truncated message")
    meta: dict[str, Any] = json.loads(head.decode())
    arrays: Arrays = {}
    for name, dtype, shape in meta.pop("arrays"):
        arr = np.empty(shape, np.dtype(dtype))
        if arr.nbytes and not _read_exact(fh, arr.reshape(-1).view(np.uint8).data):
            raise EOFError("truncated message")
        arrays[name] = arr
    return meta, arrays


# --------------------------------------------------------------------------- main side
@dataclass
class Refined:
    """A result of the worker: the local transforms of tree nodes ``1..n``."""

    n: int
    """Tree nodes below the earth covered (= poses of the prefix)."""
    m: int
    """Edges shipped to the worker when it answered (the first ``m`` laid)."""
    g: int
    """GPS readings shipped, likewise."""
    req: int
    """The highest solve request answered (-1: none)."""
    rotations: np.ndarray
    """(n, 3, 3) local rotations of tree nodes 1..n."""
    translations: np.ndarray
    """(n, 3) local translations."""
    energy: float
    iterations: int
    status: str
    seconds: float
    """Wall time of the worker's solve."""
    held: tuple[int, int] | None = None
    """Edges and GPS readings the estimate holds: fewer than shipped when the incremental
    solve was stopped by its cap (None: all of them)."""
    rejected: tuple[np.ndarray, np.ndarray] | None = None
    """``robust="auto"``: the edges and GPS readings among those held that the worker's
    outlier test rejected (arrival order; None: no verdict)."""
    rescreens: int = 0
    """``robust="auto"``: the worker's screenings so far that found its map inconsistent
    (each ran the robust re-solve)."""
    fallback: str = ""
    """Why the worker's map has left the incremental solver ("" while it has not: a
    failed incremental solve, or LM being the faster on this map)."""
    resets: int = 0
    """Failed incremental solves of the worker's map so far (each answered by LM, then a new
    incremental solver started)."""
    with_lm: bool = False
    """The worker's map is solved by LM because LM was measured the faster on it."""
    received: float = 0.0
    """When the answer reached this process (:func:`time.perf_counter`)."""

    @property
    def holds_all(self) -> tuple[int, int]:
        """(edges, GPS readings) the estimate holds."""
        return (self.m, self.g) if self.held is None else self.held


class BackgroundRefiner:
    """The main process's end: a worker process, a sender and a receiver thread.

    :meth:`ship` never blocks (the sender thread writes); :meth:`take` returns the newest result
    without waiting; :meth:`wait` blocks for the answer to a request.  :meth:`close` stops
    everything and is idempotent.
    """

    def __init__(self, max_iterations: int, robust: str = "none") -> None:
        """Start the worker (``robust``: ``NAME:DELTA`` of the robust kernel, ``none`` or
        ``auto``)."""
        # the folder that holds the package (this file is <root>/hybridpgo/online/worker.py)
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        env.update(WORKER_THREADS)
        self._proc: subprocess.Popen[bytes] | None = subprocess.Popen(
            [sys.executable, "-c", _ENTRY, str(max_iterations), robust],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0, env=env)
        self._outbox: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._cond = threading.Condition()
        self._latest: Refined | None = None
        self._answered = -1
        self.error: str | None = None
        """The last error the worker reported (or why it stopped); None until there is one.
        It stays when results come after it (:attr:`failing` says whether the newest message
        was an error)."""
        self.failing = False
        """Whether the worker's newest message was an error, or the link to it failed (it
        stopped, its output could not be read, or it could not be written to): a result
        received after an error message sets it back to False; a failed link stays failed."""
        self._broken = False  # the link failed (_fail): failing for good
        self.results = 0
        """Results received."""
        self._alive = True
        self._req = -1
        self._ready = False
        self._sender = threading.Thread(target=self._send_loop, name="hybridpgo-refine-send",
                                        daemon=True)
        self._receiver = threading.Thread(target=self._recv_loop,
                                          name="hybridpgo-refine-recv", daemon=True)
        self._sender.start()
        self._receiver.start()

    # ----------------------------------------------------------------- threads
    def _send_loop(self) -> None:
        proc = self._proc
        assert proc is not None and proc.stdin is not None
        try:
            while True:
                msg = self._outbox.get()
                if msg is None:
                    break
                write_all(proc.stdin, msg)
        except (BrokenPipeError, OSError, ValueError) as exc:
            self._fail(f"the worker stopped reading ({exc})")
        finally:
            try:
                proc.stdin.close()
            except OSError:
                pass

    def _recv_loop(self) -> None:
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        try:
            while True:
                msg = read_message(proc.stdout)
                if msg is None:
                    break
                meta, arrays = msg
                with self._cond:
                    if meta["type"] == "ready":
                        self._ready = True
                    elif meta["type"] == "result":
                        self._latest = Refined(
                            int(meta["n"]), int(meta["m"]), int(meta["g"]), int(meta["req"]),
                            arrays["rot"], arrays["trans"], float(meta["energy"]),
                            int(meta["iterations"]), str(meta["status"]),
                            float(meta["seconds"]),
                            (int(meta["m_held"]), int(meta["g_held"])),
                            (arrays["rejected_m"], arrays["rejected_g"]),
                            int(meta["rescreens"]), str(meta.get("fallback", "")),
                            int(meta.get("resets", 0)), bool(meta.get("with_lm", False)),
                            time.perf_counter())
                        self.results += 1
                        self.failing = self._broken
                        self._answered = max(self._answered, int(meta["req"]))
                    else:
                        self.error = str(meta.get("message", meta))
                        self.failing = True
                        self._answered = max(self._answered, int(meta.get("req", -1)))
                    self._cond.notify_all()
        except (OSError, ValueError, EOFError, KeyError) as exc:
            self._fail(f"bad message from the worker ({exc})")
        finally:
            with self._cond:
                self._alive = False
                if self.error is None and self._proc is not None:
                    self.error = "the worker exited"
                self.failing = True
                self._cond.notify_all()

    def _fail(self, message: str) -> None:
        with self._cond:
            self.error = message
            self.failing = self._broken = True
            self._cond.notify_all()

    # ----------------------------------------------------------------- API
    @property
    def alive(self) -> bool:
        return self._alive

    @property
    def pid(self) -> int | None:
        """The worker process's id (None once closed)."""
        return None if self._proc is None else self._proc.pid

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Block until the worker has loaded its kernels (True), died or ``timeout`` passed."""
        with self._cond:
            self._cond.wait_for(lambda: self._ready or not self._alive, timeout)
            return self._ready

    def ship(self, meta: dict[str, Any], arrays: Arrays) -> None:
        """Queue a message for the worker (the sender thread writes it)."""
        if self._alive:
            self._outbox.put(encode(meta, arrays))

    def request(self, thorough: bool = False, defer: bool = True) -> int:
        """Ask for the optimum of everything shipped so far; the request's id.  ``thorough``
        (``robust="auto"``): test every constraint, those rejected before included
        (:meth:`_Map.solve`); ``defer`` False: an outlier test due with the answer runs before
        it is sent, not after (:meth:`_Map.screen_after`)."""
        self._req += 1
        self.ship({"type": "solve", "req": self._req, "thorough": thorough, "defer": defer},
                  {})
        return self._req

    def answered(self, req: int) -> bool:
        """True once request ``req`` has been answered (or the worker is gone)."""
        with self._cond:
            return self._answered >= req or not self._alive

    def wait_answered(self, req: int, timeout: float | None = None) -> bool:
        """Block until request ``req`` is answered (or the worker died, or ``timeout``
        seconds passed); :meth:`answered` then.  Takes nothing."""
        with self._cond:
            self._cond.wait_for(lambda: self._answered >= req or not self._alive, timeout)
            return self._answered >= req or not self._alive

    def take(self) -> Refined | None:
        """The newest result not taken yet, or None (never waits)."""
        with self._cond:
            out, self._latest = self._latest, None
        return out

    def wait(self, req: int, timeout: float | None = None) -> Refined | None:
        """Block until request ``req`` is answered (or the worker died, or ``timeout``);
        then the newest result not taken yet."""
        self.wait_answered(req, timeout)
        return self.take()

    def close(self) -> None:
        """Stop the worker (EOF on its input, then kill after a timeout) and the threads."""
        proc = self._proc
        if proc is None:
            return
        self._proc = None
        self._outbox.put(None)
        self._sender.join(STOP_TIMEOUT_S)
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        self._receiver.join(STOP_TIMEOUT_S)
        for fh in (proc.stdin, proc.stdout):
            if fh is not None:
                try:
                    fh.close()
                except OSError:
                    pass
        with self._cond:
            self._alive = False
            self._cond.notify_all()


# --------------------------------------------------------------------------- worker side
#: GPS readings from which the worker's solves take the earth as the gauge (before: the first
#: pose is held).  The frames free the first pose from the first reading, so an answer with
#: fewer readings (but some) is in another gauge and is not adopted
#: (:meth:`~._link.WorkerLink.adopt`).
GPS_GAUGE = 3
#: The worker's back substitution leaves a column's subtree alone when the column's solution
#: moved by at most this (metres or radians, inf-norm): rounding, not a change.  A frame that
#: brings a pose and its odometry changes no other pose's step, but recomputing the root's
#: columns moves their solution by rounding, and with no threshold the whole map below them is
#: recomputed in every cycle: paris2 fed frame by frame into an incremental solver with the
#: worker's options, 13.7 ms per odometry-only request at 16 000-20 000 poses (16 600 columns
#: recomputed), 0.33 ms (3 columns) with this threshold; the estimates of the two within 3e-12
#: m and their energies within 5e-15 (relative) at every 500th frame of valencia and of
#: paris2's first 12 000.
ROUNDING_WILDFIRE = 1e-12
#: Options of the worker's incremental solver: a pose's linearization point moves once its step
#: exceeds 0.1 (m or rad), and the idle polish (``IncrementalConfig.polish_rho``) then takes
#: every pose still moving to the optimum.  Measured on M3500_isam with an incremental solver
#: fed every frame and its estimate adopted by the frames: worst checkpoint 1.002-1.007x the
#: prefix optimum (valencia: 1.011x), against 1.233x (valencia: 121.8x) without a worker.
#: The back substitution stops only below columns whose solution moved by rounding
#: (:data:`ROUNDING_WILDFIRE`).  Stopped below columns that moved by at most 1e-4, it left
#: steps of columns it skipped stale: after
#: a long loop closure, cycles that relinearized one pose each while E oscillated between 2x
#: and 10x the optimum (valencia streamed back to back: one request of 512 cycles, 0.2-0.35 s,
#: against 8 with the whole solution; paris2's first 15 000 frames replayed into a worker's
#: map: 48 s of solves, requests of up to 186 cycles and 74 answered by LM, against 34 s, at
#: most 7 cycles and 4).
#: The polish runs only for a request that brings no new data (the stream paused or ended):
#: while data arrives, each request stops once no pose's step exceeds 0.1, which keeps the
#: answers within 1e-3 of the prefix optimum at a third of the cost (M3500_isam fed frame by
#: frame, a request per frame: 3.1 ms per request on average, worst 1.0008x the prefix
#: optimum at 250-frame checkpoints, against 11.3 ms and 1.00000x with the polish in every
#: request; valencia 0.68 against 2.2 ms).
#: Every re-eliminated set is ordered by AMD (``reorder_max``): the worker has no frame
#: deadline, and a large set kept in its old order fills in without bound.  Measured on
#: paris2 fed in chunks of 50 frames: with the default limit (4 096 variables) the factor's
#: pool reached 4.2 M blocks and a solve 0.74 s on average by frame 7 549 (and asked for
#: 36 GiB further on); with every set reordered, 0.13-0.5 M blocks and 0.06-0.36 s up to
#: frame 17 549.
INCREMENTAL = {"relinearize_rho": 0.1, "relinearize_phi": 0.1, "wildfire": ROUNDING_WILDFIRE,
               "gps_gauge": GPS_GAUGE, "reorder_max": 1 << 62}
#: The outlier test of the screening (``robust="auto"``) takes at most this share of the
#: worker's time: an answer is tested only when the time since the last test ended is at least
#: ``1 / SCREEN_SHARE - 1`` times what that test took (valencia streamed back to back: 0.3-3 ms
#: at 8 000-15 000 poses, where an answer to a loop closure takes 6-10 ms).  The re-solve a
#: failed test runs is counted only when it rejects nothing (a false alarm); when it finds
#: outliers it is the work they need.  A thorough request is always screened.
SCREEN_SHARE = 0.2
#: Seconds of one request's incremental solve at most (an unfinished solve resumes at the next
#: request; the answer is the last completed update cycle's estimate, the poses it does not
#: cover yet composed onto their parents).  M3500_isam streamed back to back on a loaded 2-core
#: machine: most answers take 1-3 ms, the longest (some 200 frames of new data at once) 2 s.
SOLVE_CAP_S = 1.0
#: A request that brings new data starts no further update cycle once this many seconds
#: passed since its first began: its answer goes back, and the relinearization left is done
#: by the next request's first cycle together with that request's new data.  0: one cycle
#: per request with new data, as iSAM2 makes one per update.  The first cycle after a loop
#: closure is a Gauss-Newton step of the whole map from its last linearization, which takes
#: the estimate most of the way, in a fraction of the time of all the cycles (valencia's
#: 2 936-pose loop at frame 8 497: one cycle 9.2 ms and 1.0001x the prefix optimum, both
#: cycles 18.1 ms; paris2 at 32 000 poses: 0.25-0.5 s per cycle, 2-3 cycles per request).
#: valencia streamed back to back, two runs each: the checkpoint 3 frames after that loop
#: 1.0001x and 3.66x with one cycle (the answer came before the checkpoint, or just after
#: it), 3.56x and 3.55x with cycles up to 50 ms; the checkpoint at 6 500 1.011-1.012x
#: against 1.04-1.06x.  paris2, one run each: worst checkpoint 1.019x against 1.044x;
#: M3500_isam 1.0005-1.0006x against 1.0005-1.004x; grid10k 1.076x against 1.048x (its
#: cycles take longer than 50 ms from some 5 000 poses on, where the two are the same, and
#: its worst checkpoint moves by more than that between runs).  A request stopped this way
#: is not timed for the choice between the incremental solver and LM (:func:`prefer_lm`),
#: which compares LM's solve of the whole map with requests that did all their work
#: (grid10k streamed back to back with the one-cycle requests timed: the map stayed with the
#: incremental solver, whose cycles grew past the 1 s cap, and ended 1.39x the optimum 10
#: frames after the stream; a warm LM solve of that map takes about 0.3 s).
MORE_CYCLES_S = 0.0
#: Seconds of one slice of the polish of a request without new data, between which the
#: worker looks for new messages: new data stops the polish (its request is answered with the
#: new data's solve instead), so that an idle map's polish (valencia: up to 0.15 s) never
#: holds back the answer to the next frame's data by more than a slice and the rest of the
#: update cycle in progress.
POLISH_SLICE_S = 2e-3
#: A polish (a request without new data) answers once this many seconds have passed and an
#: update cycle completed, and the next such request goes on with it: the first cycles of a
#: polish relinearize what moved and bring most of its gain (grid10k at the end of its stream:
#: five cycles in 0.7 s, the first one alone at 1.0002x the optimum).
POLISH_ANSWER_S = 0.05
#: An incremental request that takes this long (seconds) has the next request solved by LM
#: instead, which measures LM's time on the map (:meth:`_Map.solve`).  Once LM was measured
#: and found slower, a request is slow only when it took as long as LM would need to be
#: preferred (:func:`prefer_lm`), LM's time scaled by the map's growth since: each measurement
#: costs an LM solve and a new incremental solver (a factorization of the whole map).  paris2
#: streamed back to back with this threshold fixed: from 19 000 poses on every incremental
#: request (0.3-0.6 s, some 80 frames of data) was slow, and one request in five was a
#: measuring LM solve (1.1-4.4 s, each slower than the requests) followed by a whole
#: factorization (0.9 s): 117 of the worker's 180 s in requests over 0.25 s, the answers up
#: to 670 frames behind the frames.
SLOW_INCREMENTAL_S = 0.25
#: The map stays with LM once LM's solve took less than this share of the recent incremental
#: requests' time (their moving average, :data:`INCREMENTAL_RATE`).  The incremental factor is
#: a left-looking supernodal block Cholesky (3x3 blocks while the map is planar, else
#: 6x6): on a lattice-like map, where each
#: update re-eliminates most of the map and the fill is large, a warm LM solve (CHOLMOD, the
#: planar system where the map is planar) is the faster of the two (grid10k streamed back to
#: back: incremental requests of 0.6-2.6 s, 1 s capped answers that held too few constraints
#: to be adopted, 1.17x the optimum 400 frames after the stream's end; a warm LM solve of the
#: whole map 0.4-0.5 s).
LM_PREFERRED_SHARE = 0.5
#: An incremental answer whose E exceeds the E it started from by more than this (relative)
#: goes on with the polish until it converges or :data:`SOLVE_CAP_S`; still above it, it is
#: refused and LM answers the request.  The incremental step is not an exact Gauss-Newton
#: step (a pose is relinearized only past 0.1), so an answer a hair above its start is
#: expected: paris2 streamed back to back had rises below 1e-6 at four requests (at 1e-9
#: each was refused, the fourth sent the map to LM for good: 1.5 s per request against
#: 0.06-0.36 s), paris2 with GPS rises of 6e-6 and 1.3e-5 (at 1e-6 each was refused and
#: answered by a 2.4 s LM solve).  A map the step has thrown off rises by far more.
RISE_RTOL = 1e-4
#: Weight of the newest incremental request's time in their moving average.
INCREMENTAL_RATE = 0.5
#: The first requests of an incremental solver are not timed: the first after a new solver
#: factors the whole map, and the worker's first ones may load kernels (M3500_isam: a 0.47 s
#: first request); nor are requests on maps of fewer poses than :data:`LM_MIN_POSES`, where
#: LM is fast only because the map is small.
INCREMENTAL_WARMUP = 3
LM_MIN_POSES = 1000
#: A map with LM goes back to an incremental solver once an LM solve takes longer than this
#: share of the incremental requests' moving average measured before it chose LM (LM's cost
#: grows with the map; an incremental request's with the part of it a request re-eliminates).
LM_RETURN_SHARE = 1.0
#: Poses of the map :func:`warm_up` solves: more than the smallest set the incremental solver
#: orders by AMD (``incremental._AMD_MIN``), so that the ordering's kernels load too.
WARM_UP_POSES = 10


def prefer_lm(incremental_s: float, lm_s: float, with_lm: bool = False) -> bool:
    """Whether the map should be solved by LM.  From the incremental solver: LM took less
    than :data:`LM_PREFERRED_SHARE` of the incremental requests' moving average; with LM
    already: it takes at most :data:`LM_RETURN_SHARE` of it (between the two, the map stays
    where it is).  Both times measured on this map; a NaN (not measured) keeps it where it
    is."""
    if with_lm:
        return not lm_s > LM_RETURN_SHARE * incremental_s
    return bool(lm_s < LM_PREFERRED_SHARE * incremental_s)


class _Map:
    """The worker's copy of the map: tree nodes ``1..n`` (0 = the earth) with their parents.

    With no robust kernel the map lives in an
    :class:`~hybridpgo.online.incremental.IncrementalExact` kept for the life of the worker
    (pose ``i`` = tree node ``i + 1``): each request integrates what was shipped since and
    updates only the part of the factor it changes.  With a robust kernel (which
    :class:`~hybridpgo.online.incremental.IncrementalExact` does not have) each request runs
    the exact Levenberg-Marquardt solve
    (:func:`~hybridpgo.solvers.gauss_newton.solve_exact`) over the whole map, warm-started from
    the previous optimum.  When an incremental solve fails (an error of the factorization, or
    an energy above the one it started from by more than :data:`RISE_RTOL` even after the
    polish) LM answers that request from the last good
    estimate and a new incremental solver starts there; after :data:`MAX_RESETS` failures the
    map stays with LM (``fallback`` says why, ``resets`` how often).  An incremental request
    that takes :data:`SLOW_INCREMENTAL_S` (past the solver's first :data:`INCREMENTAL_WARMUP`
    requests, on a map of :data:`LM_MIN_POSES` poses or more) has the next one solved by LM,
    which measures LM on this map: when LM took less than :data:`LM_PREFERRED_SHARE` of the
    incremental requests' time the map stays with LM (:func:`prefer_lm`) until an LM solve
    takes longer than those requests did (:data:`LM_RETURN_SHARE`), else a new incremental
    solver starts at LM's optimum.  The request that brings the
    :data:`GPS_GAUGE`-th GPS reading is solved by LM too (the gauge moves from the first pose
    to the earth), and the incremental solver starts again at its optimum; a request with
    fewer readings (but some) is answered unsolved, since its answer is not adopted.
    """

    def __init__(self, robust: tuple[str, float | None] = ("none", None)) -> None:
        from .incremental import IncrementalConfig, IncrementalExact

        self.robust = robust
        #: ``robust="auto"``: least squares, each answer screened for outliers (:meth:`_screen`)
        self.auto = robust[0] == "auto"
        self.n = self.m = self.g = 0
        self.parent = np.full(1, -1, np.int32)  # tree nodes, 0 = the earth
        self.inc = (IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
                    if robust[0] in ("none", "auto") else None)
        #: the constraints solved (False: rejected as outliers by the screening)
        self.keep_m = np.ones(0, np.bool_)
        self.keep_g = np.ones(0, np.bool_)
        #: screenings that found the map inconsistent (each ran the robust re-solve)
        self.rescreens = 0
        #: when the last screening ended and how long it took (perf_counter seconds)
        self._screened_at = -np.inf
        self._screen_cost = 0.0
        #: a screening that fell due at the last answer, run once that answer is sent
        #: (:meth:`screen_after`; ``defer_screening`` False: before it, in :meth:`solve`)
        self._screen_later = False
        self.defer_screening = True
        #: why the last incremental solve failed ("" when none has)
        self.fallback = ""
        #: failed incremental solves so far (each answered by LM, then the solver started again)
        self.resets = 0
        #: moving average of the incremental requests' seconds, and the last LM solve's (NaN:
        #: not measured yet); the next request is solved by LM to measure it (:meth:`solve`)
        self.inc_seconds = np.nan
        self.lm_seconds = np.nan
        self._measure_lm = False
        #: an incremental request this long (seconds) has the next one measure LM, once the
        #: solver answered this many and the map holds this many poses
        self.slow_s = SLOW_INCREMENTAL_S
        #: a request with new data starts no cycle past this many seconds (:meth:`_cycles`)
        self.more_cycles_s = MORE_CYCLES_S
        #: an incremental request stops after this many seconds (:data:`SOLVE_CAP_S`)
        self.cap_s = SOLVE_CAP_S
        self.warmup = INCREMENTAL_WARMUP
        self.min_poses = LM_MIN_POSES
        #: the last measuring LM solve's (or with LM, the last LM solve's) seconds and poses
        #: (:meth:`_slow`; 0 poses: none yet)
        self._lm_timed = (np.nan, 0)
        #: requests answered by the current incremental solver
        self._inc_answers = 0
        #: (poses, edges, GPS readings) of the map at the last request solved, and whether
        #: its answer held every constraint of it (a solve that stopped at its cap, or whose
        #: cycle began before the last data came, holds fewer)
        self._solved = (-1, -1, -1)
        self._solved_all = False
        #: the last committed evaluation of E (:meth:`_evaluate`): the poses of its first
        #: ``_ev_n`` nodes, and the χ² of its first ``_ev_m`` edges and ``_ev_g`` readings
        self._ev_n = self._ev_m = self._ev_g = 0
        self._ev_rot = np.zeros((0, 3, 3))
        self._ev_tr = np.zeros((0, 3))
        self._ce_m = np.zeros(0)
        self._ce_g = np.zeros(0)
        #: the map is solved by LM because LM was measured faster (:func:`prefer_lm`)
        self.with_lm = False
        #: whether the gauge is the earth (:data:`GPS_GAUGE` readings; before: the first pose)
        self.earth = False
        # the LM path's copy: global poses of tree nodes (the estimate) and the measurements
        self.grot = np.eye(3)[None].copy()
        self.gtr = np.zeros((1, 3))
        # the local transforms of the tree nodes as shipped (read for the nodes being added)
        self.lrot = np.eye(3)[None].copy()
        self.ltr = np.zeros((1, 3))
        self.edge_ab = np.zeros((0, 2), np.int32)
        self.edge_rot = np.zeros((0, 3, 3))
        self.edge_trans = np.zeros((0, 3))
        self.edge_info = np.zeros((0, 6, 6))
        self.gps_node = np.zeros(0, np.int32)
        self.gps_pos = np.zeros((0, 3))
        self.gps_info = np.zeros((0, 3, 3))

    @staticmethod
    def _append(arr: np.ndarray, used: int, new: np.ndarray) -> np.ndarray:
        need = used + new.shape[0]
        if need > arr.shape[0]:
            grown = np.zeros((max(need, 2 * arr.shape[0]), *arr.shape[1:]), arr.dtype)
            grown[:used] = arr[:used]
            arr = grown
        arr[used:need] = new
        return arr

    def add(self, d: Arrays) -> None:
        self._screen_later = False  # a screening due with the last answer is of another map
        k = d["parent"].shape[0]
        t0 = self.n + 1
        self.parent = self._append(self.parent, t0, d["parent"].astype(np.int32))
        ke, kg = d["edge_ab"].shape[0], d["gps_node"].shape[0]
        if self.inc is not None:
            # local transforms onto the parents' estimates (the earth's children: global)
            self.inc.add_poses(d["rot"], d["trans"], self.parent[t0: t0 + k] - 1)
            self.inc.add_edges(d["edge_ab"][:, 0], d["edge_ab"][:, 1], d["edge_rot"],
                               d["edge_trans"], d["edge_info"])
            self.inc.add_gps(d["gps_node"], d["gps_pos"], d["gps_info"])
        # the LM path's copy, kept in both modes so that a failed incremental solve can fall
        # back to it
        self.lrot = self._append(self.lrot, t0, d["rot"])
        self.ltr = self._append(self.ltr, t0, d["trans"])
        self.grot = self._append(self.grot, t0, d["rot"])
        self.gtr = self._append(self.gtr, t0, d["trans"])
        # local -> global onto the parents' estimates, parents first (a parent is older)
        globals_from_locals(np.arange(t0, t0 + k, dtype=np.int32), self.parent, self.lrot,
                            self.ltr, self.grot, self.gtr)
        self.n += k
        for name in ("edge_ab", "edge_rot", "edge_trans", "edge_info"):
            setattr(self, name, self._append(getattr(self, name), self.m, d[name]))
        self.keep_m = self._append(self.keep_m, self.m, np.ones(ke, np.bool_))
        self.m += ke
        for name in ("gps_node", "gps_pos", "gps_info"):
            setattr(self, name, self._append(getattr(self, name), self.g, d[name]))
        self.keep_g = self._append(self.keep_g, self.g, np.ones(kg, np.bool_))
        self.g += kg

    @staticmethod
    def _held(keep: np.ndarray, k: int) -> int:
        """The constraints of the map (all, rejected ones included) up to the ``k``-th one
        solved: the incremental solver holds the solved ones only, in order."""
        kept = np.flatnonzero(keep)
        return keep.shape[0] if k >= kept.shape[0] else int(kept[k - 1]) + 1 if k else 0

    def _kept(self) -> tuple[Any, Any]:
        """Indices of the edges and GPS readings solved (slices while none is rejected)."""
        m, g = self.m, self.g
        km, kg = self.keep_m[:m], self.keep_g[:g]
        return (slice(0, m) if km.all() else np.flatnonzero(km),
                slice(0, g) if kg.all() else np.flatnonzero(kg))

    def solve(self, max_iterations: int, thorough: bool = False,
              interrupted: Callable[[], bool] | None = None
              ) -> tuple[Arrays, dict[str, Any]]:
        """The optimum of the map from the current estimate; the locals of nodes 1..n.

        Incremental: update cycles until nothing is left to do (or :data:`SOLVE_CAP_S`, or
        for a request with new data, the first cycle to end past :data:`MORE_CYCLES_S`:
        :meth:`_cycles`); ``iterations`` counts them; an answer whose E rose above
        :data:`RISE_RTOL` goes on with the polish before it fails; the polish
        (:data:`INCREMENTAL`) runs when the request brings no new data or is ``thorough``.
        A polish that is not thorough runs in slices of :data:`POLISH_SLICE_S` and stops once
        ``interrupted()`` (a new message came): its status is then ``"interrupted"``, and the
        estimate is the last completed cycle's (the worker does not send it: the message's
        request is answered next).  LM (robust
        kernel): at most ``max_iterations``.
        ``robust="auto"``: when an outlier test is due (:data:`SCREEN_SHARE`), the answer is
        screened (:meth:`_screen`) after it was sent (:meth:`screen_after`), or before it when
        ``defer_screening`` is False or the request is ``thorough`` (every constraint tested,
        those rejected before included, as a whole-graph solve tests them)."""
        n, m, g = self.n, self.m, self.g
        t0 = time.perf_counter()
        energy, iterations, status = 0.0, 0, "converged"
        failed = False
        held = (m, g)
        if not self.earth and 0 < g < GPS_GAUGE:
            # 1 or 2 GPS readings: the frames let them move the whole map while this map
            # holds its first pose, so no answer is adopted (WorkerLink.adopt) and none is
            # solved; the estimate goes back as it is.  Solving it cost the next answer: an
            # undamped solve of the first pose held against readings far away ran to
            # SOLVE_CAP_S (valencia_gps back to back: 1 s at pose 106, the next answer, the
            # first adopted, 600 frames later)
            return self._answer(held, self._energy(), 0, "not solved",
                                time.perf_counter() - t0, self.inc is not None, False)
        # GPS_GAUGE readings: the gauge becomes the earth.  The estimate was solved with the
        # first pose held where the stream started; the readings' frame may lie far from it,
        # and an undamped Gauss-Newton step that far need not lower E: this request is solved
        # by LM (damped), and the incremental solver starts again at its optimum
        switch = not self.earth and g >= GPS_GAUGE
        self.earth = self.earth or switch
        # an incremental request took SLOW_INCREMENTAL_S: this one is solved by LM, which
        # measures LM on this map; the map then stays with the faster of the two (prefer_lm)
        measure = self._measure_lm and self.inc is not None and not switch
        self._measure_lm = False
        if self.inc is not None and not (switch or measure):
            e_start = self._energy()
            bound = e_start * (1.0 + RISE_RTOL) + 1e-12  # the answer's E at most (RISE_RTOL)
            try:
                cycles = int(self.inc.stats["cycles"])
                # the polish only for a request that brings nothing new, or a thorough one
                # (OnlineSolver.join_refine: the optimum of everything); see INCREMENTAL.  A
                # map whose last answer did not hold all of it gets an update cycle first
                # (the polish would answer only at its end: grid10k at the end of its
                # stream, the last 39 loop closures 0.7 s later)
                polish = thorough or ((n, m, g) == self._solved and self._solved_all)
                end = t0 + self.cap_s
                if polish and not thorough and interrupted is not None:
                    status = self._polish(interrupted)
                elif polish:
                    if not self.inc.solve(self.cap_s, polish=True):
                        status = "max_time"
                else:
                    status = self._cycles(end)
                rot, trans = self.inc.estimate()
                energy, change = self._evaluate(rot, trans)
                if not energy <= bound and status != "max_time":
                    # the step raised E: the solve goes on, the polish included (every pose
                    # that moved relinearized), until it converges or the cap
                    if not self.inc.solve(max(end - time.perf_counter(), 0.0), polish=True):
                        status = "max_time"
                    rot, trans = self.inc.estimate()
                    energy, change = self._evaluate(rot, trans)
                iterations = int(self.inc.stats["cycles"]) - cycles
                # the estimate is the last completed update cycle's: the constraints laid
                # after the ones it integrated are not in it (a solve stopped by the cap)
                _, m_est, g_est = self.inc.covered
                if not energy <= bound:  # NaN fails too
                    raise ArithmeticError(f"the incremental solve raised E from {e_start:.6g} "
                                          f"to {energy:.6g}")
                self.grot = self._append(self.grot, 1, rot)
                self.gtr = self._append(self.gtr, 1, trans)
                self._commit(change)
                held = (self._held(self.keep_m[:m], m_est), self._held(self.keep_g[:g], g_est))
                took = time.perf_counter() - t0
                self._inc_answers += 1
                # a request stopped after its first cycles (MORE_CYCLES_S) did part of its
                # work: its time is no sample of what a request costs against LM
                if (self._inc_answers > self.warmup and n >= self.min_poses
                        and status != "cycles"):
                    self.inc_seconds = (took if not np.isfinite(self.inc_seconds) else
                                        self.inc_seconds + INCREMENTAL_RATE
                                        * (took - self.inc_seconds))
                    self._measure_lm = took >= self._slow(n)
            except (HybridPGOError, ValueError, ArithmeticError, MemoryError,
                    np.linalg.LinAlgError) as exc:
                # e.g. an undamped step from a poor estimate: LM (damped) solves this request
                # from the last good estimate, and the incremental solver starts again there
                self.fallback = f"{type(exc).__name__}: {exc}"
                self.resets += 1
                failed = True
        # a thorough screening needs the optimum of everything shipped: an incremental solve
        # stopped by its cap (false closures slow it down) is finished by LM
        finish = (thorough and self.auto and self.inc is not None and not (failed or switch)
                  and (held != (m, g) or status != "converged"))
        if (self.inc is None or failed or switch or finish or measure) and n >= 2:
            t_lm = time.perf_counter()
            energy, iterations, status = self._solve_lm(max_iterations)
            self.lm_seconds = time.perf_counter() - t_lm
            if measure or self.with_lm:  # a warm LM solve of the map as it stands
                self._lm_timed = (self.lm_seconds, n)
            held = (m, g)
        # screened at every answer that holds everything shipped, converged or not (false
        # closures slow the least-squares solve down: M3500 with 100 of them, streamed, hit
        # the time cap at most answers); a false alarm costs a re-solve that rejects nothing
        due = (time.perf_counter() - self._screened_at
               >= self._screen_cost * (1.0 / SCREEN_SHARE - 1.0))
        check = (self.auto and n >= 2 and held == (m, g) and (due or thorough)
                 and status != "interrupted")
        # a thorough request's answer is the screened one; any other is sent first and
        # screened after (screen_after)
        self._screen_later = check and not thorough and self.defer_screening
        screened = check and not self._screen_later and self._screen(thorough)
        if screened:
            energy = self._energy()
        self._solved, self._solved_all = (n, m, g), held == (m, g)
        returned = False  # solved by LM, which sent the map back to an incremental solver
        if measure and prefer_lm(self.inc_seconds, self.lm_seconds):
            self.inc, self.with_lm = None, True
            self.fallback = (f"LM is faster on this map: {self.lm_seconds:.3g} s against "
                             f"{self.inc_seconds:.3g} s per incremental request")
        elif (self.with_lm and not (failed or switch)
              and not prefer_lm(self.inc_seconds, self.lm_seconds, with_lm=True)):
            # LM has grown slower than the incremental requests were: back to an incremental
            # solver, timed again after its warm-up
            self.inc, self.with_lm, self.fallback = self._incremental_here(), False, ""
            self.inc_seconds = np.nan
            returned = True
        elif failed:
            self._reseed()
        elif (switch or screened or finish or measure) and self.inc is not None:
            self.inc = self._incremental_here()
        incremental = self.inc is not None and not (failed or switch or screened or finish
                                                    or measure or returned)
        return self._answer(held, energy, iterations, status, time.perf_counter() - t0,
                            incremental, self.auto and thorough and held == (m, g))

    def screen_after(self) -> tuple[Arrays, dict[str, Any]] | None:
        """The screening that fell due at the last answer (``robust="auto"``, not thorough:
        :meth:`solve`), run once that answer was sent, so that the test does not hold the
        answer back (valencia streamed back to back: the answer to a 2 936-pose loop closure
        took 10 ms with the test after it, 20 ms with it before).  When the test fails and
        the robust re-solve changes the estimate or the rejected set, the answer of the
        re-solved map (its rejected constraints named; the frames adopt it like any
        answer); else None.  Until then the frames hold the least-squares answer, the fit a
        whole-graph solve makes before its outlier test."""
        if not self._screen_later:
            return None
        self._screen_later = False
        t0 = time.perf_counter()
        if not self._screen(False):
            return None
        energy = self._energy()
        if self.inc is not None:  # the re-solved estimate: a new incremental solver there
            self.inc = self._incremental_here()
        return self._answer((self.m, self.g), energy, 0, "screened", time.perf_counter() - t0,
                            False, False)

    def _slow(self, n: int) -> float:
        """Seconds from which an incremental request on a map of ``n`` poses has the next
        one measure LM: :attr:`slow_s`, or once LM was measured, the time a request must take
        for LM to be preferred at LM's last measured time scaled by the map's growth
        (:data:`SLOW_INCREMENTAL_S`), whichever is longer.  The LM solves of a failed
        incremental solve or of the gauge switch are not measurements: they start from a
        poor estimate, or on a small map whose fixed costs would scale into a threshold no
        request reaches."""
        seconds, poses = self._lm_timed
        if not (poses and np.isfinite(seconds)):
            return self.slow_s
        lm_now = seconds * n / poses
        return max(self.slow_s, lm_now / LM_PREFERRED_SHARE)

    def _cycles(self, end: float) -> str:
        """The update cycles of a request that brings new data: one after the other until
        no pose's step exceeds the relinearization thresholds (``"converged"``), until
        ``end`` (perf_counter seconds; ``"max_time"``), or until a cycle ends past
        :attr:`more_cycles_s` (:data:`MORE_CYCLES_S`) since the first began (``"cycles"``:
        the relinearization left goes into the next request's first cycle, with its new
        data).  A cycle that leaves nothing to relinearize is ``"converged"`` either way.
        The look after the last cycle begins nothing
        (:attr:`~hybridpgo.online.incremental.IncrementalExact.settled`): a cycle begun to
        look would hold only the data there by then, and the next request would finish it
        and answer without its own data (grid10k streamed back to back: after every loop
        closure that moved poses past the thresholds, each answer held the previous
        request's data, one frame older than it could)."""
        assert self.inc is not None
        t0 = time.perf_counter()
        while True:
            done = int(self.inc.stats["cycles"])
            if self.inc.solve(max(end - time.perf_counter(), 0.0), max_cycles=1,
                              polish=False):
                return "converged"
            now = time.perf_counter()
            if now >= end or int(self.inc.stats["cycles"]) == done:  # stopped inside a cycle
                return "max_time"
            if now - t0 >= self.more_cycles_s:  # a look that begins no cycle
                return "converged" if self.inc.settled else "cycles"

    def _polish(self, interrupted: Callable[[], bool]) -> str:
        """The incremental solve with the polish, in slices of :data:`POLISH_SLICE_S`, until
        converged (``"converged"``), ``interrupted()`` (``"interrupted"``),
        :attr:`cap_s` (:data:`SOLVE_CAP_S`; ``"max_time"``), or a slice that ends
        :data:`POLISH_ANSWER_S` after the start with an update cycle completed since
        (``"polishing"``: answered, and the next request without new data goes on)."""
        assert self.inc is not None
        t0 = time.perf_counter()
        end = t0 + self.cap_s
        cycles = int(self.inc.stats["cycles"])
        while not self.inc.solve(POLISH_SLICE_S, polish=True):
            if interrupted():
                return "interrupted"
            now = time.perf_counter()
            if now >= end:
                return "max_time"
            if now - t0 >= POLISH_ANSWER_S and int(self.inc.stats["cycles"]) > cycles:
                return "polishing"
        return "converged"

    def _answer(self, held: tuple[int, int], energy: float, iterations: int, status: str,
                seconds: float, incremental: bool, thorough: bool
                ) -> tuple[Arrays, dict[str, Any]]:
        """A request's answer: the estimate's local transforms of nodes 1..n and its meta."""
        from ..tree import locals_from_globals

        n = self.n
        lrot = np.empty((n + 1, 3, 3))
        ltr = np.empty((n + 1, 3))
        locals_from_globals(self.parent[: n + 1], self.grot[: n + 1], self.gtr[: n + 1],
                            lrot, ltr)
        meta = {"type": "result", "n": n, "m": self.m, "g": self.g, "m_held": held[0],
                "g_held": held[1], "energy": energy, "iterations": iterations,
                "status": status, "seconds": seconds, "incremental": incremental,
                "fallback": self.fallback, "resets": self.resets, "with_lm": self.with_lm,
                "rescreens": self.rescreens, "thorough": thorough}
        return {"rot": lrot[1:], "trans": ltr[1:],
                "rejected_m": np.flatnonzero(~self.keep_m[: held[0]]),
                "rejected_g": np.flatnonzero(~self.keep_g[: held[1]])}, meta

    def _graph(self, kept: bool) -> Any:
        """The map as a :class:`~hybridpgo.graph.PoseGraph` at the current estimate: the
        constraints solved (``kept``) or all of them; the first pose held until the gauge is
        the earth; ``is_2d`` when the data are planar and there is no GPS reading
        (:func:`~hybridpgo.graph.planar_data`: LM takes the (x, y, yaw) system when the
        estimate is planar too; the outlier test counts 3 degrees of freedom per relative
        constraint for planar data in any case)."""
        import dataclasses

        from ..graph import PoseGraph, planar_data

        n, m, g = self.n, self.m, self.g
        e, k = self._kept() if kept else (slice(0, m), slice(0, g))
        graph = PoseGraph(
            node_ids=np.arange(n, dtype=np.int64), rotations=self.grot[1: n + 1],
            translations=self.gtr[1: n + 1], edge_nodes=self.edge_ab[e],
            edge_rotations=self.edge_rot[e], edge_translations=self.edge_trans[e],
            edge_information=self.edge_info[e], gps_nodes=self.gps_node[k],
            gps_positions=self.gps_pos[k], gps_information=self.gps_info[k],
            fixed_nodes=np.zeros(0 if self.earth else 1, np.int32))  # fmt: skip
        planar = g == 0 and planar_data(graph)  # the planar reduction has no GPS terms
        return dataclasses.replace(graph, is_2d=True) if planar else graph

    def _screen(self, thorough: bool = False) -> bool:
        """``robust="auto"``: the outlier test of the solved constraints at the estimate (their
        least-squares optimum, or the way to it); when it finds them inconsistent, the robust
        re-solve of the whole map (every constraint shipped, those rejected before included)
        replaces the estimate and the rejected set (:mod:`hybridpgo.solvers.robust`).  True
        when the re-solve changed the estimate.  Before the gauge is the earth, the first
        pose stays where the estimate held it (the graph fixes it, and the re-solve's start
        chains the odometry from it).

        ``thorough`` tests every constraint, those rejected before too, so the re-solve runs
        whenever one is rejected: its verdict is then the one a whole-graph solve of the map
        gives.  A false closure that arrives near the end of the drive is one the test of
        the solved constraints can miss: the poses since the last loop bend to absorb it at
        their least-squares optimum (little redundancy), until later loops contradict it.

        An answer is screened only when the last test is long enough ago
        (:data:`SCREEN_SHARE`)."""
        from ..graph import planar_arrays
        from ..solvers.config import GaussNewtonConfig
        from ..solvers.result import SolveResult, Status
        from ..solvers.robust import consistency_of, exact_resolver, resolve

        n, m, g = self.n, self.m, self.g
        rot, trans = self.grot[1: n + 1], self.gtr[1: n + 1]
        t0 = time.perf_counter()
        # check_consistency's test on the χ² this map keeps (evaluated again only where a
        # pose moved), without a PoseGraph: the frames' add_* checked every datum of the map,
        # and a PoseGraph checks them all again when built (streamed valencia at 8 000-15 000
        # poses: screenings of 9-11 ms with one, 0.3-3 ms without)
        self._energy()  # the kept χ² at the current poses (_ce_m, _ce_g)
        em, eg = self._ce_m, self._ce_g
        e, k = (slice(0, m), slice(0, g)) if thorough else self._kept()
        planar = planar_arrays(self.edge_rot[:m][e], self.edge_trans[:m][e],
                               self.edge_info[:m][e], self.gps_pos[:g][k], self.gps_info[:g][k])
        verdict = consistency_of(em[e], eg[k], n, planar, planar)
        self._screened_at = time.perf_counter()
        self._screen_cost = self._screened_at - t0  # the test's (a re-solve is needed work)
        if not verdict.inconsistent:
            return False
        self.rescreens += 1
        graph = self._graph(False)
        start = SolveResult(rot.copy(), trans.copy(), Status.CONVERGED, 0,
                            np.array([self._energy()]), np.zeros(1), "worker", m + g)
        # the re-solve's solves with the exact solver's defaults, as a whole-graph solve's
        res = resolve(graph, start, exact_resolver(GaussNewtonConfig()))
        rows = res.stats["outliers"]["rejected_constraints"]
        if not rows and self.keep_m[:m].all() and self.keep_g[:g].all():
            # a false alarm: nothing rejected, the estimate is the input's; its re-solve is
            # counted as the test's cost (a repeated false alarm must not take the worker)
            self._screened_at = time.perf_counter()
            self._screen_cost = self._screened_at - t0
            return False
        self.keep_m[:m] = True
        self.keep_g[:g] = True
        for row in rows:
            (self.keep_m if row["kind"] == "edge" else self.keep_g)[row["index"]] = False
        # the gauge is kept: the first pose is fixed in every solve of the re-solve
        self.grot[1: n + 1] = res.rotations
        self.gtr[1: n + 1] = res.translations
        return True

    def _energy(self) -> float:
        """E of the constraints solved at the current estimate of the whole map."""
        n = self.n
        energy, change = self._evaluate(self.grot[1: n + 1], self.gtr[1: n + 1])
        self._commit(change)
        return energy

    def _evaluate(self, rot: np.ndarray, trans: np.ndarray) -> tuple[float, Any]:
        """E of the constraints solved at the poses ``rot``, ``trans`` of nodes 1..n, and
        the per-constraint energies for :meth:`_commit`.  Only the constraints that are new
        since the last committed evaluation or that have an end whose pose differs from it
        are evaluated (:func:`~._incremental_kernels.refresh_energies`): O(n + m) comparisons
        and sums, and χ² for those constraints only (an answer moves few poses unless a loop
        closed)."""
        from ._incremental_kernels import differing_poses, refresh_energies

        n, m, g = self.n, self.m, self.g
        k = self._ev_n
        moved = np.ones(n, np.bool_)
        differing_poses(rot, trans, self._ev_rot, self._ev_tr, moved[:k])
        # the committed energies; the new constraints' entries are written
        em = np.empty(m)
        em[: self._ev_m] = self._ce_m[: self._ev_m]
        eg = np.empty(g)
        eg[: self._ev_g] = self._ce_g[: self._ev_g]
        refresh_energies(rot, trans, moved, self.edge_ab[:m], self.edge_rot[:m],
                         self.edge_trans[:m], self.edge_info[:m], self.gps_node[:g],
                         self.gps_pos[:g], self.gps_info[:g], self._ev_m, self._ev_g, em, eg)
        energy = float(em[self.keep_m[:m]].sum() + eg[self.keep_g[:g]].sum())
        return energy, (rot, trans, np.flatnonzero(moved), em, eg)

    def _commit(self, change: Any) -> None:
        """Keep an evaluation of :meth:`_evaluate` as the reference of the next."""
        rot, trans, moved, em, eg = change
        n = rot.shape[0]
        self._ev_rot = self._append(self._ev_rot, self._ev_n, np.zeros((n - self._ev_n, 3, 3)))
        self._ev_tr = self._append(self._ev_tr, self._ev_n, np.zeros((n - self._ev_n, 3)))
        self._ev_rot[moved] = rot[moved]
        self._ev_tr[moved] = trans[moved]
        self._ce_m, self._ce_g = em, eg
        self._ev_n, self._ev_m, self._ev_g = n, em.shape[0], eg.shape[0]

    def _reseed(self) -> None:
        """A new incremental solver holding the whole map at the current estimate (after an
        incremental solve failed and LM solved the request), or none after
        :data:`MAX_RESETS` failures (LM from then on)."""
        self.inc = None if self.resets > MAX_RESETS else self._incremental_here()

    def _incremental_here(self) -> Any:
        """An :class:`~hybridpgo.online.incremental.IncrementalExact` holding the whole map
        at the current estimate."""
        from .incremental import IncrementalConfig, IncrementalExact

        n = self.n
        e, k = self._kept()
        self._inc_answers = 0
        inc = IncrementalExact(IncrementalConfig(**INCREMENTAL))  # type: ignore[arg-type]
        inc.add_poses(self.grot[1: n + 1], self.gtr[1: n + 1])  # global poses
        ab = self.edge_ab[e]
        inc.add_edges(ab[:, 0], ab[:, 1], self.edge_rot[e], self.edge_trans[e],
                      self.edge_info[e])
        inc.add_gps(self.gps_node[k], self.gps_pos[k], self.gps_info[k])
        return inc

    def _solve_lm(self, max_iterations: int) -> tuple[float, int, str]:
        """Exact LM over the constraints solved (robust kernel ``self.robust``; least
        squares with ``"auto"``) from the current estimate."""
        from ..solvers.config import GaussNewtonConfig
        from ..solvers.gauss_newton import solve_exact

        n = self.n
        # the gauge: the first pose until GPS_GAUGE readings can hold the map (_graph); its
        # is_2d (no GPS) lets solve_exact use the (x, y, yaw) system when the map is exactly
        # planar (it checks every pose, measurement and information exactly, else solves in
        # 3D): half the unknowns (M3500_isam, a warm solve: 0.10-0.14 s against 0.23-0.25 s)
        graph = self._graph(True)
        kernel = "none" if self.auto else self.robust[0]
        res = solve_exact(graph, None, None, GaussNewtonConfig(
            max_iterations=max_iterations, robust=kernel,  # type: ignore[arg-type]
            robust_scale=None if self.auto else self.robust[1]))
        self.grot[1: n + 1] = res.rotations
        self.gtr[1: n + 1] = res.translations
        return float(res.final_energy), int(res.iterations), res.status.value


def warm_up(robust: tuple[str, float | None]) -> _Map:
    """Answer requests of a tiny map through every path a request can take, so that each
    kernel is loaded from Numba's cache (or compiled into it) before the worker says it is
    ready: the incremental solve (a set of :data:`WARM_UP_POSES` new poses, which the solver
    orders by AMD, and the cycles after it, which relinearize), LM in the plane (``is_2d``),
    the gauge switch to three GPS readings (LM in 3D, a new incremental solver), the
    compaction of the factor's pool, and with ``robust="auto"`` the outlier test and the
    robust re-solve of a map with a false closure.
    A kernel first needed in the middle of a stream holds the answers back while it loads or
    compiles (from a cold cache, seconds per kernel).  The requests here have no time cap
    and run every cycle (:attr:`_Map.cap_s`, :attr:`_Map.more_cycles_s`): on a cold cache
    the first cycle's compilation takes longer than :data:`SOLVE_CAP_S`, and a cycle stopped
    there would leave the kernels of its later phases for the first requests of the stream.
    Returns the tiny map."""
    from ..geometry.so3 import exp as so3_exp

    k = WARM_UP_POSES
    turn = so3_exp(np.array([0.0, 0.0, 2.0 * np.pi / k]))
    step = np.array([1.0, 0.0, 0.0])
    # a regular k-gon driven with a turn of 2 pi / k per side, closed: every measurement is
    # (turn, step); the first pose hangs from the earth at the origin
    rot = np.concatenate([np.eye(3)[None], np.tile(turn, (k - 1, 1, 1))])
    trans = np.concatenate([np.zeros((1, 3)), np.tile(step, (k - 1, 1))])
    ring = np.arange(k, dtype=np.int32)
    mp = _Map(robust)
    mp.cap_s = mp.more_cycles_s = np.inf
    mp.add({"parent": ring, "rot": rot, "trans": trans,
            "edge_ab": np.stack([ring, np.roll(ring, -1)], axis=1),
            "edge_rot": np.tile(turn, (k, 1, 1)), "edge_trans": np.tile(step, (k, 1)),
            "edge_info": np.tile(np.eye(6), (k, 1, 1)), "gps_node": np.zeros(0, np.int32),
            "gps_pos": np.zeros((0, 3)), "gps_info": np.zeros((0, 3, 3))})
    mp.solve(5)  # incremental (a robust kernel: LM)
    mp.screen_after()  # "auto": the outlier test, after the answer as in a stream
    mp._measure_lm = True
    mp.solve(5)  # LM on the planar map, then a new incremental solver at its optimum
    # three GPS readings at the first three poses: the gauge switch; with "auto" also a
    # false closure across the polygon (its rotation right, its translation 40 m off) for
    # the test to reject
    bad = int(mp.auto)
    half = k // 2
    mp.add({"parent": np.zeros(0, np.int32), "rot": np.zeros((0, 3, 3)),
            "trans": np.zeros((0, 3)),
            "edge_ab": np.array([[0, half]] * bad, np.int32).reshape(-1, 2),
            "edge_rot": np.tile(np.linalg.matrix_power(turn, half), (bad, 1, 1)),
            "edge_trans": np.tile([40.0, 0.0, 0.0], (bad, 1)),
            "edge_info": np.tile(np.eye(6), (bad, 1, 1)),
            "gps_node": np.arange(GPS_GAUGE, dtype=np.int32),
            "gps_pos": mp.gtr[1: GPS_GAUGE + 1].copy(),
            "gps_info": np.tile(np.eye(3), (GPS_GAUGE, 1, 1))})
    mp.solve(5, thorough=True)  # LM in 3D with GPS; "auto": the test, the robust re-solve
    mp.solve(5)  # the incremental solver on the earth's gauge
    if mp.inc is not None:  # the pool compacted in place, as when it grows
        mp.inc._compact(mp.inc._pool_cap)
    return mp


def _error(req: int, exc: Exception) -> bytes:
    """The ``error`` message answering request ``req``."""
    return encode({"type": "error", "req": req, "message": f"{type(exc).__name__}: {exc}"}, {})


def _worker(max_iterations: int, robust_spec: str = "none") -> int:
    """The worker process: read messages on stdin, answer on stdout (see the module doc)."""
    inp = os.fdopen(os.dup(0), "rb", buffering=0)
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)  # stray prints go to stderr, never into the protocol
    widen_pipe(out.fileno())
    sys.setswitchinterval(WORKER_SWITCH_S)
    try:
        os.nice(WORKER_NICE)
    except OSError:  # pragma: no cover - not permitted on this system
        pass
    inbox: list[tuple[dict[str, Any], Arrays] | None] = []
    cond = threading.Condition()

    def reader() -> None:
        try:
            while True:
                msg = read_message(inp)
                with cond:
                    inbox.append(msg)
                    cond.notify()
                if msg is None:
                    return
        except (OSError, ValueError, EOFError):
            with cond:
                inbox.append(None)
                cond.notify()

    threading.Thread(target=reader, daemon=True).start()
    name, _, scale = robust_spec.partition(":")
    robust = (name, float(scale) if scale else None)
    warm_up(robust)  # every kernel a request may need, before the worker says it is ready
    # the objects alive now (the loaded kernels among them) live as long as the worker: out
    # of the collector's reach, so that no request pays for walking them (as in the frames'
    # process, solver._ensure_online_compiled)
    gc.collect()
    gc.freeze()
    try:
        write_all(out, encode({"type": "ready"}, {}))
    except (BrokenPipeError, OSError):
        return 0
    mp = _Map(robust)
    pending = -1  # highest request received
    answered = -1
    thorough = False  # a pending request asks for every constraint to be tested
    stop = False
    while not stop:
        with cond:
            while not inbox and pending <= answered:
                cond.wait()
            batch = inbox[:]
            inbox.clear()
        for msg in batch:
            if msg is None or msg[0]["type"] == "stop":
                stop = True
                break
            meta, arrays = msg
            if meta["type"] == "data":
                mp.add(arrays)
            elif meta["type"] == "solve":
                pending = max(pending, int(meta["req"]))
                thorough = thorough or bool(meta.get("thorough", False))
                mp.defer_screening = bool(meta.get("defer", True))
        if stop:
            break
        if pending <= answered:
            continue
        try:
            arrays, meta = mp.solve(max_iterations, thorough, lambda: bool(inbox))
            if meta["status"] == "interrupted":  # a polish cut short by a new message
                continue
            # a thorough screening not done yet (robust="auto") stays asked for the next answer
            thorough = thorough and mp.auto and not meta["thorough"]
        except Exception as exc:  # report it; the frames go on without refinement
            write_all(out, _error(pending, exc))
            answered = pending
            continue
        meta["req"] = pending
        answered = pending
        try:
            write_message(out, meta, arrays)
        except (BrokenPipeError, OSError):
            break
        # the screening due at this answer, after it: a re-solve that changed the map
        # answers the same request again
        try:
            later = mp.screen_after()
        except Exception as exc:  # report it; the frames go on without refinement
            later = None
            try:
                write_all(out, _error(pending, exc))
            except (BrokenPipeError, OSError):
                break
        if later is not None:
            try:
                write_message(out, {**later[1], "req": pending}, later[0])
            except (BrokenPipeError, OSError):
                break
    return 0


if __name__ == "__main__":  # pragma: no cover - run as a subprocess
    sys.exit(_worker(int(sys.argv[1]), sys.argv[2] if len(sys.argv) > 2 else "none"))
