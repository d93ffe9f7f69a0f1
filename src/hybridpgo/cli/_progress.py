"""Progress display of the command line: bars with rate and ETA, and spinners for phases.

Built on `rich <https://rich.readthedocs.io>`_: its live display redraws from a background
thread (10 times a second), so the spinner and the elapsed time keep moving while the main thread
is inside a long call (Numba compilation, one sweep of a large graph, a sparse factorization),
which a redraw-on-update bar (tqdm, or the hand-made bar this replaces) cannot do.

* Progress goes to stderr and only when stderr is a terminal; ``--progress`` (:func:`configure`)
  forces it on for any stream (a log file then gets the terminal control sequences).
  ``enabled=False`` (``--quiet``) turns it off everywhere.
* Bars and phases share one live display: a :func:`phase` started while a bar runs (or the
  other way round) becomes one more row of it.  Rows vanish when they end; a bar then leaves its
  final line, a phase that took at least :data:`PHASE_REPORT_S` a line with its duration.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import IO, TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID

__all__ = ["COMPILE_NOTICE", "PHASE_REPORT_S", "ProgressBar", "configure", "is_live", "phase"]

#: A phase that took at least this long leaves a line with its duration (seconds).
PHASE_REPORT_S = 1.0
#: Off a terminal: the line printed when Numba starts compiling inside a phase.
COMPILE_NOTICE = ("hybridpgo: compiling kernels (first run only; about a minute or two on a "
                  "slow machine, cached for later runs)...")

_force = False
#: The live display every bar and phase draws into, and how many rows use it.
_display: dict[str, Any] = {"progress": None, "users": 0}


def configure(*, force: bool) -> None:
    """``force=True`` (``--progress``): show progress even when stderr is not a terminal."""
    global _force
    _force = bool(force)


def is_live(stream: IO[str] | None = None, enabled: bool = True) -> bool:
    """Whether progress is drawn on ``stream`` (default stderr)."""
    if not enabled:
        return False
    if _force:
        return True
    isatty = getattr(stream or sys.stderr, "isatty", None)
    try:
        return bool(isatty is not None and isatty())
    except ValueError:  # a closed stream
        return False


def _acquire(stream: IO[str]) -> Progress:
    """The shared live display (started on first use)."""
    progress: Progress | None = _display["progress"]
    if progress is None:
        from ._progress_rich import make_progress

        progress = make_progress(stream)
        progress.start()
        _display["progress"] = progress
    _display["users"] += 1
    return progress


def _release(progress: Progress) -> None:
    _display["users"] -= 1
    if _display["users"] <= 0:
        _display["progress"] = None
        _display["users"] = 0
        progress.stop()


class ProgressBar:
    """A progress bar on stderr: ``label [####....] k/total  E/c ...  tau ...  rate  elapsed  ETA``.

    Drawn only when stderr is a terminal (or ``--progress`` forced it); ``enabled=False``
    (``--quiet``) draws nothing.  The elapsed time keeps running between updates, so a long
    sweep or the polish after the last sweep is never a frozen screen.  :meth:`close` leaves the
    final line.

    Parameters
    ----------
    label : str
        Name of the task (``hybrid``, ``exact LM``, ``batch``).
    total : int
        Number of iterations expected (``update`` with ``k == total`` completes the bar).
    num_constraints : int
        The graph's constraint count: energies are shown per constraint.
    enabled : bool
    stream : text stream, optional
        Default ``sys.stderr``.
    unit : str, optional
        Name of one iteration in the rate (``sweep``, ``it``, ``job``); default ``sweep`` for a
        label starting with ``hybrid``, else ``it``.
    """

    def __init__(self, label: str, total: int, num_constraints: int, *, enabled: bool = True,
                 stream: IO[str] | None = None, unit: str | None = None) -> None:
        self.label = label
        self.total = max(int(total), 0)
        self.num_constraints = max(int(num_constraints), 1)
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.unit = unit or ("sweep" if label.startswith("hybrid") else "it")
        self.live = is_live(self.stream, enabled)
        self._progress: Progress | None = None
        self._task: TaskID | None = None
        self._first: tuple[int, float] | None = None
        if self.live:
            self._progress = _acquire(self.stream)
            self._task = self._progress.add_task(label, total=self.total, stats="", note="",
                                                 unit=self.unit)

    def update(self, k: int, energy: float | None, tau: float | None = None,
               note: str = "") -> None:
        """Record progress: iteration ``k`` of ``total`` reached ``energy`` (None: not shown)."""
        if self._progress is None or self._task is None:
            return
        parts = []
        if energy is not None:
            parts.append(f"E/c {energy / self.num_constraints:.4g}")
        if tau is not None:
            parts.append(f"tau {tau:.3f}")
        k = min(max(k, 0), self.total)
        now = time.monotonic()  # the rate and ETA columns (_progress_rich) read these
        if self._first is None:
            self._first = (k, now)
        self._progress.update(self._task, completed=k, stats="  ".join(parts), note=note,
                              k_first=self._first[0], t_first=self._first[1], k_last=k,
                              t_last=now)

    def close(self, note: str = "") -> None:
        """Finish the bar, leaving its final line (plus ``note``)."""
        progress, task = self._progress, self._task
        if progress is None or task is None:
            return
        self._progress = self._task = None
        fields: dict[str, Any] = {"done": True}
        if note:
            fields["note"] = note
        progress.update(task, **fields)
        final = progress.make_tasks_table([t for t in progress.tasks if t.id == task])
        progress.remove_task(task)
        progress.console.print(final)
        _release(progress)

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _compile_status() -> Any:
    """``hybridpgo._numba.compile_status()`` if a kernel module was imported (importing Numba
    just to learn that nothing compiled would slow light commands down)."""
    numba_side = sys.modules.get("hybridpgo._numba")
    if numba_side is None:
        from types import SimpleNamespace

        return SimpleNamespace(compiled=0, current=None, seconds=0.0)
    return numba_side.compile_status()


@contextmanager
def phase(text: str, *, enabled: bool = True, stream: IO[str] | None = None) -> Iterator[None]:
    """A spinner with elapsed time while the ``with`` block runs, e.g.
    ``with phase("compiling kernels (first run only)"): ...``.

    Off a terminal (unless forced) or with ``enabled=False`` it draws nothing.  On a terminal, a
    phase of at least :data:`PHASE_REPORT_S` leaves the line ``text: 12.3 s``.

    Numba compiling inside the block (a cold cache: the first run, or after an upgrade) is
    shown: on a terminal the row says how many kernels are compiled and which one is compiling
    now; off a terminal (``enabled`` still True) one line announces it when it starts and one
    says how long it took.  Loading kernels from the cache shows nothing more.
    """
    out = stream or sys.stderr
    base = _compile_status()
    if not is_live(out, enabled):
        numba_side = sys.modules.get("hybridpgo._numba")
        if not enabled or numba_side is None:  # no kernel module imported: nothing to watch
            yield
            return

        def announce() -> None:
            print(COMPILE_NOTICE, file=out, flush=True)

        with numba_side.on_first_compile(announce):
            yield
        done = _compile_status()
        if done.compiled > base.compiled:
            print(f"hybridpgo: compiled {done.compiled - base.compiled} kernels in "
                  f"{done.seconds - base.seconds:.1f} s (cached for later runs)", file=out,
                  flush=True)
        return

    def note() -> str:
        now = _compile_status()
        if now.compiled == base.compiled and now.current is None:
            return ""
        current = f", now {now.current}" if now.current else ""
        return f"numba: {now.compiled - base.compiled} kernels compiled{current}"

    progress = _acquire(out)
    task = progress.add_task(text, total=None, stats="", note=note, unit="")
    t0 = time.perf_counter()
    try:
        yield
    finally:
        elapsed = time.perf_counter() - t0
        progress.remove_task(task)
        if elapsed >= PHASE_REPORT_S:
            from rich.text import Text

            n = _compile_status().compiled - base.compiled
            extra = f" ({n} kernels compiled, cached for later runs)" if n else ""
            progress.console.print(Text(f"{text}: {elapsed:.1f} s{extra}"))
        _release(progress)
