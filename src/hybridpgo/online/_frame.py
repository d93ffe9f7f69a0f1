"""A frame's time: the budget's checks and bounds, the clock that charges ``add_*`` calls to
their frame, and :class:`FrameReport`, what one :meth:`OnlineSolver.update` did."""

from __future__ import annotations

import functools
import gc
from collections.abc import Callable
from typing import Any, NamedTuple, TypeVar

import numpy as np

from .._numba import read_cycles

#: Seconds of every budget kept for the work after the last update (estimate, bookkeeping).
RESERVE_S = 2e-4
#: Seconds per tree level kept of a frame's budget for reading its newest pose
#: (:meth:`OnlineSolver.pose` composes the local transforms from the root, O(tree depth)).
#: Measured on valencia streamed with a 5 ms budget: 46-79 ns per level at depths of
#: 2 500-4 800 (0.13-0.35 ms), up to 0.44 ms after the budget's last update.
READ_LEVEL_S = 1e-7
#: The longest budget a frame may have (a day): longer ones would overflow the cycle counter.
MAX_BUDGET_S = 86_400.0
NO_DEADLINE = np.uint64(np.iinfo(np.uint64).max)


class FrameReport(NamedTuple):
    """What one :meth:`OnlineSolver.update` did."""

    new: int
    """New constraints relaxed for the first time."""
    backlog: int
    """New constraints still waiting (the budget ran out before them)."""
    old: int
    """Spare-time updates of older constraints."""
    local_nodes: int
    """Poses moved by the local solve and the batch of a loop closure's neighbours (0: neither
    ran or fitted)."""
    capped: int
    """Updates whose rotation was capped at pi/8."""
    rejected: int
    """Updates rejected as non-finite (nothing applied)."""
    skipped: int
    """Candidate updates skipped because their predicted cost did not fit."""
    seconds: float
    """Wall time of the call."""


_F = TypeVar("_F", bound=Callable[..., Any])


def uncollected(method: _F) -> _F:
    """A method of a frame's work (``add_*``, :meth:`OnlineSolver.update`,
    :meth:`OnlineSolver.pose`), run with Python's automatic garbage collection held off and
    then restored as it was.

    A collection starts in whichever allocation crosses the collector's threshold, and a full
    one walks every tracked object of the process, the application's too, in time in
    proportion (about 0.2 s for the 4 * 10^5 objects the compiled kernels leave, which the
    process's first solver freezes), so inside a frame it would break the budget.  Held off,
    the collection that falls due comes at the next allocation outside the solver: in the
    application's own code, or in :meth:`OnlineSolver.idle`, which the time between frames
    pays.  Nothing is skipped: the collector's counts keep growing while it is held.  A
    caller that turned automatic collection off keeps it off.  The switch is the process's:
    other threads' collections wait for the end of the call too."""

    @functools.wraps(method)
    def uncollected(self: Any, *args: Any, **kwargs: Any) -> Any:
        if not gc.isenabled():
            return method(self, *args, **kwargs)
        gc.disable()
        try:
            return method(self, *args, **kwargs)
        finally:
            gc.enable()

    return uncollected  # type: ignore[return-value]


def charged(method: _F) -> _F:
    """An ``add_*`` method whose cycles count against the next :meth:`OnlineSolver.update`'s
    budget (they are part of that frame's work), run without garbage collection
    (:func:`uncollected`)."""

    @functools.wraps(method)
    def charged(self: Any, *args: Any, **kwargs: Any) -> Any:
        c0 = int(read_cycles())
        try:
            return method(self, *args, **kwargs)
        finally:
            self._input_cycles += int(read_cycles()) - c0

    return uncollected(charged)  # type: ignore[return-value]


def check_budget(budget_s: object) -> float:
    if (isinstance(budget_s, bool) or not isinstance(budget_s, (int, float, np.floating))
            or not np.isfinite(budget_s) or budget_s <= 0):
        raise ValueError(f"budget_s must be a finite number > 0 (seconds) or None, got "
                         f"{budget_s!r}")
    return min(float(budget_s), MAX_BUDGET_S)
