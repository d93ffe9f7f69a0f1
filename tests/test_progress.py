"""The progress display of the command line (``hybridpgo.cli._progress``, rich underneath)."""

from __future__ import annotations

import io
import re
import threading
import time

import pytest

from hybridpgo.cli import _progress
from hybridpgo.cli._common import ProgressBar, phase

#: Terminal control sequences (colours, cursor moves) that rich writes between frames.
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


class Terminal(io.StringIO):
    """A stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


def text(stream: io.StringIO) -> str:
    """What was written, without control sequences, one frame per line."""
    return ANSI.sub("", stream.getvalue()).replace("\r", "\n")


def final_lines(stream: io.StringIO) -> list[str]:
    """The lines a finished bar leaves (the live frames are erased on a real terminal)."""
    return [line for line in text(stream).splitlines() if line.startswith(("✓", "+"))]


@pytest.fixture(autouse=True)
def _not_forced() -> None:
    _progress.configure(force=False)


def test_bar_on_a_terminal_shows_count_energy_tau_rate_and_eta() -> None:
    stream = Terminal()
    bar = ProgressBar("hybrid", 3, 10, stream=stream)
    for k, e in enumerate([100.0, 50.0, 20.0, 10.0]):
        bar.update(k, e, tau=0.99**k)
        time.sleep(0.15)  # > one refresh (10 per second): frames with an ETA get drawn
        if k == 1:
            frame = text(stream)
            assert "1/3" in frame and "ETA 0:00:0" in frame and "s/sweep" in frame
    bar.close("done")
    [final] = final_lines(stream)
    assert "hybrid" in final and "3/3" in final and "E/c 1 " in final
    assert "tau 0.970" in final and final.rstrip().endswith("done")
    assert re.search(r"\d sweep/s|s/sweep", final)
    assert "ETA" not in final  # finished rows show no ETA
    assert _progress._display["progress"] is None  # the live display is gone


def test_elapsed_time_runs_between_updates() -> None:
    """The display redraws from its own thread: a long sweep is not a frozen screen."""
    stream = Terminal()
    bar = ProgressBar("hybrid", 5, 10, stream=stream)
    bar.update(0, 10.0)
    time.sleep(1.25)  # no update: a blocked main thread
    assert "0:00:01" in text(stream)
    bar.close()


def test_nothing_off_a_terminal_unless_forced() -> None:
    stream = io.StringIO()
    bar = ProgressBar("exact LM", 5, 2, stream=stream)
    for k in range(4):
        bar.update(k, 10.0 - k)
    bar.close("done")
    with phase("compiling", stream=stream):
        pass
    assert stream.getvalue() == ""
    _progress.configure(force=True)
    bar = ProgressBar("exact LM", 5, 2, stream=stream)
    bar.update(5, 1.0)
    bar.close()
    [final] = final_lines(stream)
    assert "5/5" in final and "-- s/it" in final  # one update: no rate yet


def test_disabled_bar_and_phase_draw_nothing_even_forced() -> None:
    _progress.configure(force=True)
    stream = Terminal()
    bar = ProgressBar("x", 5, 2, enabled=False, stream=stream)
    bar.update(1, 1.0)
    bar.close()
    with phase("compiling", enabled=False, stream=stream):
        pass
    assert stream.getvalue() == ""


def test_phase_shows_a_spinner_and_reports_a_long_phase(monkeypatch: pytest.MonkeyPatch
                                                        ) -> None:
    stream = Terminal()
    with phase("compiling kernels (first run only)", stream=stream):
        time.sleep(0.25)
        assert "compiling kernels (first run only)" in text(stream)
    # shorter than PHASE_REPORT_S: no line is left
    assert not text(stream).rstrip().endswith(" s")
    monkeypatch.setattr(_progress, "PHASE_REPORT_S", 0.0)
    stream = Terminal()
    with phase("reading big.g2o", stream=stream):
        pass
    assert re.search(r"reading big\.g2o: 0\.0 s\n", text(stream))


def test_phase_inside_a_bar_shares_its_display() -> None:
    """rich allows one live display: a phase during a bar is one more row of it."""
    stream = Terminal()
    bar = ProgressBar("hybrid", 2, 1, stream=stream)
    bar.update(2, 4.0)
    with phase("polishing (exact LM)", stream=stream):
        assert _progress._display["users"] == 2
        time.sleep(0.15)
    bar.close()
    with phase("writing", stream=stream):  # and the other way round
        inner = ProgressBar("exact LM", 3, 1, stream=stream)
        inner.update(3, 1.0)
        inner.close()
    assert _progress._display["progress"] is None
    assert "polishing (exact LM)" in text(stream) and "3/3" in text(stream)
    for thread in threading.enumerate():  # rich's refresh thread ends with the display
        if type(thread).__name__ == "_RefreshThread":
            thread.join(timeout=1.0)
            assert not thread.is_alive()


def test_a_failing_block_still_ends_the_phase() -> None:
    stream = Terminal()
    with pytest.raises(RuntimeError), phase("solving", stream=stream):
        raise RuntimeError("boom")
    assert _progress._display["progress"] is None


def _fresh_kernel() -> object:
    """A new (uncached) Numba function: calling it compiles."""
    import numba

    def twice(x: float) -> float:
        return 2.0 * x

    return numba.njit(cache=False)(twice)


def test_compilation_inside_a_phase_is_announced_off_a_terminal() -> None:
    import hybridpgo._numba  # noqa: F401  (a kernel module is imported: compiles are watched)

    stream = io.StringIO()
    with phase("solving", stream=stream):
        pass  # nothing compiles: nothing printed
    assert stream.getvalue() == ""
    fn = _fresh_kernel()
    with phase("solving", stream=stream):
        assert fn(2.0) == 4.0  # type: ignore[operator]
    lines = stream.getvalue().splitlines()
    assert lines[0] == _progress.COMPILE_NOTICE
    assert re.fullmatch(r"hybridpgo: compiled [1-9]\d* kernels in \d+\.\d s \(cached for later "
                        r"runs\)", lines[1])
    assert len(lines) == 2
    stream = io.StringIO()
    with phase("solving", stream=stream, enabled=False):  # --quiet: nothing
        assert _fresh_kernel()(1.0) == 2.0  # type: ignore[operator]
    assert stream.getvalue() == ""


def test_compilation_inside_a_phase_is_counted_on_a_terminal(monkeypatch: pytest.MonkeyPatch
                                                             ) -> None:
    import hybridpgo._numba  # noqa: F401

    monkeypatch.setattr(_progress, "PHASE_REPORT_S", 0.0)
    stream = Terminal()
    fn = _fresh_kernel()
    with phase("compiling kernels (first run only)", stream=stream):
        assert fn(1.0) == 2.0  # type: ignore[operator]
    assert re.search(r"compiling kernels \(first run only\): \d+\.\d s \([1-9]\d* kernels "
                     r"compiled, cached for later runs\)", " ".join(text(stream).split()))
