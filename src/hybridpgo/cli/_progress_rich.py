"""The rich columns of the progress display (imported only when something is drawn)."""

from __future__ import annotations

import math
import time
from typing import IO, Any

from rich.console import Console
from rich.progress import BarColumn, Progress, ProgressColumn, SpinnerColumn, TimeElapsedColumn
from rich.table import Column
from rich.text import Text

__all__ = ["make_progress"]


class _Spinner(SpinnerColumn):
    """A spinner; a check mark once the row is done."""

    def __init__(self, done_text: str) -> None:
        super().__init__(table_column=Column(no_wrap=True))
        self.done_text = done_text

    def render(self, task: Any) -> Any:
        if task.fields.get("done"):
            return Text(self.done_text)
        return super().render(task)


class _Field(ProgressColumn):
    """A task's description or one of its fields, as plain text (no markup); a callable field
    is called at every redraw (a phase's note follows Numba's compilation)."""

    def __init__(self, name: str) -> None:
        super().__init__(table_column=Column(no_wrap=True))
        self.name = name

    def render(self, task: Any) -> Text:
        if self.name == "description":
            return Text(str(task.description))
        value = task.fields.get(self.name, "")
        return Text(str(value() if callable(value) else value))


class _Count(ProgressColumn):
    """``k/total`` (nothing for a phase)."""

    def render(self, task: Any) -> Text:
        if task.total is None:
            return Text("")
        return Text(f"{int(task.completed)}/{int(task.total)}")


def _rate(task: Any) -> float | None:
    """Iterations per second since the first update (which comes after compilation and setup,
    so they do not count), or None before a second data point."""
    k0, t0 = task.fields.get("k_first"), task.fields.get("t_first")
    k1, t1 = task.fields.get("k_last"), task.fields.get("t_last")
    if k0 is None or k1 is None or k1 <= k0 or t1 <= t0:
        return None
    return float(k1 - k0) / float(t1 - t0)


class _Rate(ProgressColumn):
    """``4.2 sweep/s``, or ``2.31 s/sweep`` when slower than one a second."""

    def render(self, task: Any) -> Text:
        unit = task.fields.get("unit", "")
        if task.total is None or not unit:
            return Text("")
        speed = _rate(task)
        if not speed:
            return Text(f"-- s/{unit}")
        if speed < 1.0:
            return Text(f"{1.0 / speed:.3g} s/{unit}")
        return Text(f"{speed:.3g} {unit}/s")


class _Eta(ProgressColumn):
    """``ETA 0:01:23`` while the row runs: the remaining iterations at the rate above, counting
    down between updates."""

    def render(self, task: Any) -> Text:
        if task.total is None or task.fields.get("done"):
            return Text("")
        speed = _rate(task)
        if not speed:
            return Text("ETA -:--:--")
        since = time.monotonic() - float(task.fields["t_last"])
        remaining = max((task.total - task.completed) / speed - since, 0.0)
        if not math.isfinite(remaining):
            return Text("ETA -:--:--")
        s = round(remaining)
        return Text(f"ETA {s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}")


def make_progress(stream: IO[str]) -> Progress:
    """A transient live display on ``stream`` (drawn as a terminal: the caller decided)."""
    console = Console(file=stream, force_terminal=True, highlight=False, markup=False,
                      emoji=False)
    done = "✓" if (console.encoding or "").lower().startswith("utf") else "+"
    nowrap = {"table_column": Column(no_wrap=True)}
    return Progress(_Spinner(done), _Field("description"), BarColumn(bar_width=20),
                    _Count(**nowrap), _Field("stats"), _Rate(**nowrap),
                    TimeElapsedColumn(**nowrap), _Eta(**nowrap), _Field("note"),
                    console=console, transient=True, redirect_stdout=False,
                    redirect_stderr=True)
