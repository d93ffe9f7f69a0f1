"""Compile on two cores: a helper process fills Numba's cache while this one compiles.

A cold first run spends most of its time compiling kernels, one after the other, on one core.
The hybrid sweep alone takes about half of it and must come first; the
kernels a solve needs *after* the sweeps (global poses, energies, the exact solver's polish)
can be compiled meanwhile by a second process into the same on-disk cache:

* :func:`start` launches ``python -m hybridpgo._precompile GROUP...`` (no shell) when the
  cache is cold (:func:`_cold`: the first group's kernels are not cached) and parallel
  compilation is on (:func:`enabled`).  The helper compiles each group's kernels by running
  the package's own functions on a three-pose graph, so the argument types are the real ones.
* Numba's dispatcher looks in the on-disk cache before it compiles a signature, so when this
  process reaches a kernel the helper has saved, it loads it (about 0.05 s) instead of
  compiling it.  The helper reports on its stdout each kernel it starts and each one it has
  compiled and saved; if this process needs a kernel the helper is compiling right now, it
  waits for it (:class:`hybridpgo._numba.CompileHooks`; at most :data:`WAIT_S` seconds per
  kernel) instead of compiling it a second time.
* Failure modes: Numba writes every index and data file to a temporary name and renames it
  (``os.replace``), so a half-written file is never read; an index entry whose data file is
  missing is a miss; an entry saved under another signature is a miss
  (``_numba._checked_cache``).  If the helper fails, is killed or hangs, this process compiles
  what is missing itself, as without a helper.  The helper exits when this process's end of
  its stdin pipe closes (this process ended, even by SIGKILL) and is terminated at exit
  (:func:`stop`, registered with :mod:`atexit`).

``HYBRIDPGO_PARALLEL_COMPILE=0`` turns it off, ``=1`` on; by default it is on when a core is
idle (CPUs minus the 1-minute load average >= :data:`IDLE_CORES`), except under pytest
(``PYTEST_CURRENT_TEST``), in CI (``CI``) and with ``NUMBA_DISABLE_JIT``.
"""

from __future__ import annotations

import atexit
import importlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import IO, Any

from . import _numba

__all__ = ["GROUPS", "Helper", "enabled", "start", "stop"]

#: Longest wait (seconds) for one kernel the helper is compiling, before compiling it here.
WAIT_S = 60.0
ENV = "HYBRIDPGO_PARALLEL_COMPILE"
#: By default a helper starts only if this many cores are idle (CPUs - 1-minute load average).
IDLE_CORES = 1.0


# --------------------------------------------------------------------------- the groups
def _tiny_graph() -> Any:
    """Three poses, three constraints, no GPS: the graph ``ensure_compiled`` solves."""
    from ._warmup import tiny_graph

    return tiny_graph()


def _finish() -> None:
    """What a hybrid solve compiles right after its sweep: global poses from local transforms,
    per-constraint energies."""
    import numpy as np

    from .energy import energy
    from .initialization import initial_locals
    from .tree import build_tree, global_poses

    graph = _tiny_graph()
    tree = build_tree(graph)
    rot, trans = initial_locals(graph, tree, "tree")  # no kernel: local transforms from edges
    grot, gtr = global_poses(tree, np.array(rot, np.float64, order="C"),
                             np.array(trans, np.float64, order="C"))
    energy(graph, grot, gtr)


def _starts() -> None:
    """Local transforms from global poses (the ``file`` start; the ``chordal`` one also compiles
    the chordal initialization)."""
    from .initialization import initial_locals
    from .tree import build_tree

    graph = _tiny_graph()
    tree = build_tree(graph)
    initial_locals(graph, tree, "file")
    initial_locals(graph, tree, "chordal")


def _exact() -> None:
    """The exact solver (the default pipeline's polish, ``--polish``, ``--solver exact``)."""
    from .solvers.gauss_newton import ensure_compiled

    ensure_compiled()


def _exact_solve() -> None:
    """An exact solve, which adds the block Cholesky of small sparse systems (a large graph's
    polish may use CHOLMOD instead)."""
    from .solvers.gauss_newton import solve_exact

    solve_exact(_tiny_graph())


def _sweep() -> None:
    """The hybrid sweep without GPS (the default pipeline's sweeps when its early try, a
    certified start, fails)."""
    from .solvers.hybrid.solver import ensure_compiled as ensure_hybrid

    ensure_hybrid()


def _toro() -> None:
    """The TORO baseline (``--solver toro``, ``hybridpgo warmup``)."""
    from .solvers.toro import ensure_compiled as ensure_toro

    ensure_toro()


#: Kernel groups a helper can compile: name -> (function, kernels that tell cold from warm).
GROUPS: dict[str, tuple[Callable[[], None], tuple[str, ...]]] = {
    "finish": (_finish, ("hybridpgo._tree_kernels:globals_from_locals",
                         "hybridpgo._cost:constraint_energies")),
    "starts": (_starts, ("hybridpgo._tree_kernels:locals_from_globals",)),
    "exact": (_exact, ("hybridpgo.solvers._gn_kernels:assemble_normal_equations",
                       "hybridpgo.solvers._gn_kernels:retract",
                       "hybridpgo._cost:total_energy")),
    "exact-solve": (_exact_solve, ("hybridpgo.linalg._block_cholesky:_numeric",)),
    "toro": (_toro, ("hybridpgo.solvers._toro_kernels:sweep",)),
    "sweep": (_sweep, ("hybridpgo.solvers.hybrid._step:woodbury_solve",)),
}


def _resolve(ref: str) -> Any:
    module, _, attr = ref.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def _group(name: str) -> tuple[Callable[[], None], tuple[str, ...]]:
    """A named group, or ``module:function`` (a function that compiles what it calls; it is
    its own cold/warm probe only if it is a kernel: tests use this)."""
    if name in GROUPS:
        return GROUPS[name]
    fn = _resolve(name)
    return fn, ((name,) if hasattr(fn, "_cache") else ())


# --------------------------------------------------------------------------- this process
def _idle_cores() -> float:
    """CPUs this process may use minus the 1-minute load average (cheap, lagging)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        cpus = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # pragma: no cover - Windows
        load = 0.0
    return cpus - load


def enabled() -> bool:
    """Whether :func:`start` may launch a helper (module docstring): ``=1`` always; by default
    only with a core to spare (measured on a 2-core machine at load 4-7: a helper made a cold
    run slower, its duplicated compile work competing for busy cores)."""
    value = os.environ.get(ENV, "").strip().lower()
    if value in ("0", "false", "no", "off"):
        return False
    if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"):
        return False
    if value in ("1", "true", "yes", "on"):
        return True
    if (os.environ.get("PYTEST_CURRENT_TEST")
            or os.environ.get("CI", "").strip().lower() not in ("", "0", "false")):
        return False
    return _idle_cores() >= IDLE_CORES


def _cold(groups: Sequence[str]) -> bool:
    """Whether the cache is cold: the first group's probe kernels are not cached.  Only the
    first group's: every solve compiles those itself, so they are cached after any run, while
    a later group may never be needed by the main process (``optimize intel.g2o`` never
    factors with the block Cholesky of ``exact-solve``) and its helper may have been ended with
    the main process before it got there; probing it would start a helper on every warm run."""
    return any(not _numba.is_cached(_resolve(ref)) for ref in _group(groups[0])[1])


class Helper:
    """A running helper process and what it has reported (:func:`start` makes one)."""

    def __init__(self, proc: subprocess.Popen[bytes], groups: Sequence[str]) -> None:
        self.proc = proc
        self.groups = tuple(groups)
        self.started: set[str] = set()
        self.done: set[str] = set()
        self.finished = False
        """The helper's stdout closed: it ended (or will report nothing more)."""
        self.ok = False
        """The helper reported that it compiled every group."""
        self.waited = 0.0
        """Seconds this process spent waiting for kernels the helper was compiling."""
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, name="hybridpgo-precompile",
                                        daemon=True)
        self._reader.start()

    def _read(self) -> None:
        out = self.proc.stdout
        assert out is not None
        log_path = os.environ.get("HYBRIDPGO_PRECOMPILE_LOG")  # diagnostics: timed reports
        t0 = time.perf_counter()
        try:
            for raw in out:
                line = raw.decode("utf-8", "replace").strip()
                if log_path:
                    with open(log_path, "a") as log:
                        log.write(f"{time.perf_counter() - t0:8.2f} helper {line}\n")
                what, _, name = line.partition(" ")
                with self._cond:
                    if what == "start":
                        self.started.add(name)
                    elif what == "done":
                        self.done.add(name)
                    elif what == "end":
                        self.ok = True
                    self._cond.notify_all()
        except (OSError, ValueError):  # pragma: no cover - pipe closed under us
            pass
        finally:
            with self._cond:
                self.finished = True
                self._cond.notify_all()

    def compiling(self, name: str) -> bool:
        """Whether the helper is compiling ``name`` now."""
        with self._cond:
            return not self.finished and name in self.started and name not in self.done

    def wait_for(self, name: str, timeout: float = WAIT_S) -> bool:
        """Wait while the helper compiles ``name``; True if it reported it compiled and saved."""
        t0 = time.perf_counter()
        deadline = t0 + timeout
        with self._cond:
            while not self.finished and name in self.started and name not in self.done:
                left = deadline - time.perf_counter()
                if left <= 0:
                    break
                self._cond.wait(min(left, 0.5))
            self.waited += time.perf_counter() - t0
            log_path = os.environ.get("HYBRIDPGO_PRECOMPILE_LOG")
            if log_path:
                with open(log_path, "a") as log:
                    log.write(f"main waited {time.perf_counter() - t0:.2f} s for {name}\n")
            return name in self.done

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the helper to end; True if it compiled every group."""
        self._reader.join(timeout)
        try:
            self.proc.wait(timeout=5.0 if timeout is None else max(timeout, 0.1))
        except subprocess.TimeoutExpired:
            return False
        return self.ok and self.proc.returncode == 0

    def stop(self) -> None:
        """End the helper now (what it saved stays in the cache); idempotent."""
        proc = self.proc
        if proc.stdin is not None:
            try:
                proc.stdin.close()  # the helper exits when its stdin closes
            except OSError:  # pragma: no cover
                pass
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:  # pragma: no cover - ignores SIGTERM
                proc.kill()
                proc.wait()
        if proc.stdout is not None:
            self._reader.join(2.0)
            try:
                proc.stdout.close()
            except OSError:  # pragma: no cover
                pass


_HELPER: Helper | None = None
_LOCK = threading.Lock()


def _before(name: str) -> None:
    helper = _HELPER
    if helper is not None and helper.compiling(name):
        helper.wait_for(name)


def start(groups: Sequence[str], *, force: bool = False) -> Helper | None:
    """Start a helper compiling ``groups`` (names of :data:`GROUPS`, or ``module:function``)
    unless parallel compilation is off, the cache is warm for them, or a helper runs already;
    ``force``: even if it is off or warm (tests).  Returns the helper, or None."""
    global _HELPER
    groups = list(groups)
    if not groups:
        return None
    with _LOCK:
        if _HELPER is not None and _HELPER.proc.poll() is None:
            return None
        if not force and not (enabled() and _cold(groups)):
            return None
        pkg_parent = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        path = os.environ.get("PYTHONPATH")
        env = dict(os.environ, PYTHONPATH=pkg_parent + (os.pathsep + path if path else ""))
        env[ENV] = "0"  # no helper of the helper
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "hybridpgo._precompile", *groups],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                env=env, close_fds=True)
        except OSError:
            return None
        _HELPER = Helper(proc, groups)
        _numba.CompileHooks.before = _before
        return _HELPER


def stop() -> None:
    """End the helper, if any (also at exit)."""
    global _HELPER
    with _LOCK:
        helper, _HELPER = _HELPER, None
        if _numba.CompileHooks.before is _before:
            _numba.CompileHooks.before = None
    if helper is not None:
        helper.stop()


atexit.register(stop)


# --------------------------------------------------------------------------- the helper
def _watch_parent(stdin: IO[bytes]) -> None:
    """End this helper when the parent's end of the stdin pipe closes (the parent ended)."""
    try:
        while stdin.read(4096):
            pass
    except (OSError, ValueError):
        pass
    os._exit(0)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m hybridpgo._precompile GROUP...``: compile the groups, report on stdout."""
    names = list(sys.argv[1:] if argv is None else argv)
    lock = threading.Lock()

    def say(line: str) -> None:
        with lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    threading.Thread(target=_watch_parent, args=(sys.stdin.buffer,), daemon=True).start()
    _numba.CompileHooks.before = lambda name: say(f"start {name}")
    _numba.CompileHooks.after = lambda name: say(f"done {name}")
    try:
        for name in names:
            _group(name)[0]()
    except BaseException as exc:  # the parent compiles what is missing
        say(f"failed {type(exc).__name__}")
        return 1
    say("end")
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)  # not sys.exit: the thread reading stdin would block the shutdown
