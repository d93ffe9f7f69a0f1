"""Hostile use of the command line.

Every test here reproduced a defect first: a traceback (exit 1) on finite input, a file left
behind or an input destroyed after an error, an output problem found only after the solve.
"""

from __future__ import annotations

import io
import os
import re
import stat
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_helpers import run_cli

from hybridpgo import read_graph
from hybridpgo.io import read_tum

V2 = ("VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0", "VERTEX_SE2 2 2 0.1 0")
E2 = ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1", "EDGE_SE2 1 2 1 0.1 0 1 0 0 1 0 1",
      "EDGE_SE2 0 2 2 0 0 1 0 0 1 0 1")


def write(path: Path, *lines: str) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def g2d(tmp_path: Path) -> Path:
    return write(tmp_path / "g.g2o", *V2, *E2)


@pytest.fixture
def unwritable_dir(tmp_path: Path) -> Path:
    """A directory where no file can be created (even by root: /proc)."""
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o500)
        return d
    d = Path("/proc")
    try:
        (d / "hybridpgo-probe").write_text("x")
    except OSError:
        return d
    pytest.skip("no unwritable directory available")  # pragma: no cover


@pytest.fixture
def no_solve(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if a solver runs: output problems must be found before the solve."""
    import hybridpgo.solvers

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the solver ran before the output was checked")

    monkeypatch.setattr(hybridpgo.solvers, "optimize", refuse)


def assert_error(code: int, err: str, *phrases: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("hybridpgo: error: "), err
    for p in phrases:
        assert p in lines[-1], err


# =========================================================================== tracebacks
def test_isam_overflowing_square_root(capsys: pytest.CaptureFixture[str],
                                      tmp_path: Path) -> None:
    p = write(tmp_path / "big.txt", "ODOMETRY 0 1 1 0 0 1e200 0 0 1e200 0 1e200")
    code, _, err = run_cli(capsys, "info", p)
    assert_error(code, err, "big.txt:1: information matrix is too large")


def test_convert_never_writes_what_it_cannot_read_back(capsys: pytest.CaptureFixture[str],
                                                       tmp_path: Path) -> None:
    p = write(tmp_path / "huge.g2o", *V2[:2], "EDGE_SE2 0 1 1 0 0 1e308 0 0 1e308 0 1e308")
    out = tmp_path / "huge.txt"
    code, _, err = run_cli(capsys, "convert", p, out)
    assert_error(code, err, "huge.g2o:3: ", "too large")
    assert not out.exists()


def test_convert_reads_back_in_memory_before_writing(capsys: pytest.CaptureFixture[str],
                                                     tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    # a writer bug that produced unreadable text must not reach the disk
    import hybridpgo.io as hio

    real = hio.graph_lines

    def broken(*args: object, **kwargs: object) -> list[str]:
        lines = real(*args, **kwargs)  # type: ignore[arg-type]
        return [*lines[:-1], lines[-1] + " 7"]

    monkeypatch.setattr(hio, "graph_lines", broken)
    src = write(tmp_path / "g.g2o", *V2, *E2)
    out = tmp_path / "o.graph"
    code, _, err = run_cli(capsys, "convert", src, out)
    assert_error(code, err, "could not be read back", "o.graph:6: EDGE2 needs 11 numbers")
    assert not out.exists()


def test_chordal_init_with_huge_information(capsys: pytest.CaptureFixture[str],
                                            tmp_path: Path, no_solve: None) -> None:
    p = write(tmp_path / "huge.g2o", *V2, "EDGE_SE2 0 1 1 0 0 1e308 0 0 1e308 0 1e308", *E2[1:])
    code, _, err = run_cli(capsys, "optimize", p, "-o", tmp_path / "o.g2o", "--init", "chordal")
    assert_error(code, err, "huge.g2o:4: ", "too large")


def test_plot_dpi_is_bounded(capsys: pytest.CaptureFixture[str], g2d: Path,
                             tmp_path: Path) -> None:
    out = tmp_path / "p.png"
    code, _, err = run_cli(capsys, "plot", g2d, "-o", out, "--dpi", "100000")
    assert code == 2 and "--dpi: must be an integer in 1..600" in err
    assert not out.exists()
    pytest.importorskip("matplotlib")
    from hybridpgo.cli._options import MAX_DPI
    from hybridpgo.errors import HybridPGOError
    from hybridpgo.plot import MAX_DPI as PLOT_MAX_DPI
    from hybridpgo.plot import graph_figure, save_figure

    assert MAX_DPI == PLOT_MAX_DPI
    g = read_graph(g2d)
    fig = graph_figure(g, [(g.rotations, g.translations)])
    with pytest.raises(HybridPGOError, match=r"dpi must be in 1\.\.600"):
        save_figure(fig, out, dpi=100000)
    assert not out.exists()


def test_interrupt_during_start_up(capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import hybridpgo.cli._parser as parser

    def interrupted() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(parser, "build_parser", interrupted)
    code, _, err = run_cli(capsys, "info", "x.g2o")
    assert code == 130
    assert "interrupted" in err and "Traceback" not in err


# =========================================================================== outputs
@pytest.mark.parametrize("cmd", ["optimize", "convert", "noisify"])
def test_output_equal_to_the_input_is_refused(capsys: pytest.CaptureFixture[str],
                                              tmp_path: Path, cmd: str, no_solve: None) -> None:
    src = write(tmp_path / "g.g2o", *V2, *E2)
    before = src.read_bytes()
    link = tmp_path / "link.g2o"
    link.symlink_to(src)
    for out in (src, Path(f"{tmp_path}/./g.g2o"), link):
        argv = [cmd, src, out] if cmd == "convert" else [cmd, src, "-o", out]
        code, _, err = run_cli(capsys, *argv)
        assert_error(code, err, "is the input", "refusing to overwrite it")
        assert src.read_bytes() == before


def test_evaluate_tum_must_not_overwrite_inputs(capsys: pytest.CaptureFixture[str],
                                                tmp_path: Path) -> None:
    est = write(tmp_path / "e.g2o", *V2, *E2)
    gt = write(tmp_path / "x_gt.tum", "0 0 0 0 0 0 0 1", "1 1 0 0 0 0 0 1", "2 2 0 0 0 0 0 1")
    saved = est.read_bytes(), gt.read_bytes()
    code, _, err = run_cli(capsys, "evaluate", est, "--ground-truth", gt, "--tum", est)
    assert_error(code, err, "is the input")
    # --tum x.tum writes x_gt.tum: the ground truth itself
    code, _, err = run_cli(capsys, "evaluate", est, "--ground-truth", gt, "--tum",
                           tmp_path / "x.tum")
    assert_error(code, err, "x_gt.tum", "is the input")
    assert not (tmp_path / "x.tum").exists()
    assert (est.read_bytes(), gt.read_bytes()) == saved


def test_evaluate_tum_writes_all_or_nothing(capsys: pytest.CaptureFixture[str],
                                            tmp_path: Path) -> None:
    est = write(tmp_path / "e.g2o", *V2, *E2)
    (tmp_path / "t_gt.tum").mkdir()  # the second output cannot be written
    code, _, err = run_cli(capsys, "evaluate", est, "--ground-truth", est, "--tum",
                           tmp_path / "t.tum")
    assert_error(code, err, "t_gt.tum", "is a directory")
    assert not (tmp_path / "t.tum").exists()


def test_optimize_plot_into_unwritable_dir_writes_nothing(capsys: pytest.CaptureFixture[str],
                                                          g2d: Path, tmp_path: Path,
                                                          unwritable_dir: Path,
                                                          no_solve: None) -> None:
    out = tmp_path / "ok.g2o"
    code, _, err = run_cli(capsys, "optimize", g2d, "-o", out, "--plot", unwritable_dir / "p")
    assert_error(code, err, str(unwritable_dir / "p_before.png"), "cannot write")
    assert not out.exists()


@pytest.mark.parametrize("kind", ["directory", "empty", "unwritable", "missing dir"])
def test_optimize_output_checked_before_the_solve(capsys: pytest.CaptureFixture[str],
                                                  g2d: Path, tmp_path: Path, kind: str,
                                                  unwritable_dir: Path, no_solve: None) -> None:
    out = {"directory": tmp_path, "empty": "", "unwritable": unwritable_dir / "o.g2o",
           "missing dir": tmp_path / "nope" / "o.g2o"}[kind]
    phrase = {"directory": "is a directory", "empty": "empty", "unwritable": "cannot write",
              "missing dir": "does not exist"}[kind]
    code, _, err = run_cli(capsys, "optimize", g2d, "-o", out)
    assert_error(code, err, phrase)


def test_two_outputs_to_one_file_are_refused(capsys: pytest.CaptureFixture[str], g2d: Path,
                                             tmp_path: Path, no_solve: None) -> None:
    code, _, err = run_cli(capsys, "optimize", g2d, "-o", tmp_path / "p_after.png",
                           "--plot", tmp_path / "p")
    assert_error(code, err, "p_after.png", "written twice")


def test_output_through_a_symlink(capsys: pytest.CaptureFixture[str], g2d: Path,
                                  tmp_path: Path) -> None:
    target = tmp_path / "real.graph"
    link = tmp_path / "link.graph"
    link.symlink_to(target)
    code, _, err = run_cli(capsys, "convert", g2d, link, "--out-format", "toro")
    assert code == 0, err
    assert link.is_symlink() and target.read_text().startswith("VERTEX2 0")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
def test_output_into_a_fifo(capsys: pytest.CaptureFixture[str], g2d: Path,
                            tmp_path: Path) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    code, _, err = run_cli(capsys, "convert", g2d, fifo, "--out-format", "g2o")
    reader.join(timeout=10)
    assert code == 0, err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert got[0].decode().startswith("VERTEX_SE2 0")


# =========================================================================== non-SPD information
def _nspd(tmp_path: Path) -> Path:
    return write(tmp_path / "nspd.g2o", *V2, "EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1", *E2)


def test_non_spd_error_names_the_cli_option(capsys: pytest.CaptureFixture[str],
                                            tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "info", _nspd(tmp_path))
    assert_error(code, err, "nspd.g2o:4: ", "1 of 4 EDGE_SE2 lines",
                 "pass --fix-information nearest or --fix-information skip")


@pytest.mark.parametrize("policy, edges", [("nearest", 4), ("skip", 3)])
def test_fix_information_option(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                policy: str, edges: int) -> None:
    import json

    with pytest.warns(UserWarning, match="1 of 4 EDGE_SE2 lines"):
        code, out, err = run_cli(capsys, "info", _nspd(tmp_path), "--fix-information", policy,
                                 "--json")
    assert code == 0, err
    assert json.loads(out)["relative_edges"] == edges


@pytest.mark.parametrize("cmd", ["info", "optimize", "convert", "plot", "noisify", "evaluate"])
def test_every_reading_command_has_fix_information(capsys: pytest.CaptureFixture[str],
                                                   cmd: str) -> None:
    code, out, _ = run_cli(capsys, cmd, "--help")
    assert code == 0 and "--fix-information {nearest,skip}" in out


def test_skip_unknown_message_names_the_flag(capsys: pytest.CaptureFixture[str],
                                             tmp_path: Path) -> None:
    p = write(tmp_path / "u.g2o", *V2, "VERTEX_XY 7 1 2", *E2)
    code, _, err = run_cli(capsys, "info", p)
    assert_error(code, err, "u.g2o:4: ", "(pass --skip-unknown to skip")
    assert "skip_unknown=True" not in err


# =========================================================================== TUM, stdin/stdout
def test_convert_to_tum(capsys: pytest.CaptureFixture[str], tiny: Path, tmp_path: Path) -> None:
    out = tmp_path / "x.tum"
    with pytest.warns(UserWarning, match="the TUM format holds poses only"):
        code, _, err = run_cli(capsys, "convert", tiny, out)
    assert code == 0, err
    stamps, _, trans = read_tum(out)
    g = read_graph(tiny)
    np.testing.assert_array_equal(stamps, g.node_ids)
    np.testing.assert_array_equal(trans, g.translations)
    with pytest.warns(UserWarning, match="poses only"):
        code, _, err = run_cli(capsys, "convert", tiny, tmp_path / "y.txt", "--out-format", "tum")
    assert code == 0, err
    assert (tmp_path / "y.txt").read_bytes() == out.read_bytes()


def test_dash_is_stdin_and_stdout(capsys: pytest.CaptureFixture[str], g2d: Path,
                                  monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(g2d.read_bytes())))
    code, out, err = run_cli(capsys, "convert", "-", "-", "--out-format", "toro")
    assert code == 0, err
    assert out.startswith("VERTEX2 0 ")  # only the graph on stdout ...
    assert "wrote -" in err  # ... the report on stderr
    back = tmp_path / "back.graph"
    back.write_text(out)
    assert read_graph(back).num_edges == 3
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(g2d.read_bytes())))
    code, out, err = run_cli(capsys, "info", "-")
    assert code == 0, err
    assert "poses           3" in out


def test_two_stdin_inputs_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(capsys, "evaluate", "-", "--ground-truth", "-")
    assert_error(code, err, "standard input")


def test_optimize_to_stdout_keeps_the_summary_off_it(capsys: pytest.CaptureFixture[str],
                                                     g2d: Path) -> None:
    code, out, err = run_cli(capsys, "optimize", g2d, "-o", "-", "--solver", "exact", "-q")
    assert code == 0, err
    assert out.startswith("VERTEX_SE2 0 ") and "energy after" in err


# =========================================================================== --fix, evaluate
def test_optimize_fix_holds_that_pose(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    src = write(tmp_path / "g.g2o", *V2, *E2)
    out = tmp_path / "o.g2o"
    code, _, err = run_cli(capsys, "optimize", src, "-o", out, "--solver", "exact", "--fix", "2",
                           "-q")
    assert code == 0, err
    g0, g1 = read_graph(src), read_graph(out)
    np.testing.assert_array_equal(g1.translations[2], g0.translations[2])
    np.testing.assert_array_equal(g1.rotations[2], g0.rotations[2])
    np.testing.assert_array_equal(g1.node_ids[g1.fixed_nodes], [2])  # written as a FIX line
    code, _, err = run_cli(capsys, "optimize", src, "-o", out, "--fix", "9")
    assert_error(code, err, "--fix 9", "no pose with id 9")


def test_evaluate_warns_about_different_pose_sets(capsys: pytest.CaptureFixture[str],
                                                  tmp_path: Path) -> None:
    import json

    est = write(tmp_path / "e.g2o", *V2, *E2)
    gt = write(tmp_path / "gt.tum", "0 0 0 0 0 0 0 1", "1 1 0 0 0 0 0 1", "5 2 0 0 0 0 0 1")
    with pytest.warns(UserWarning, match=r"compared on the 2 poses both have; 1 estimated "
                      r"pose\(s\) have no ground truth \(ids 2\); 1 ground-truth pose\(s\) are "
                      r"not in the estimate \(ids 5\)"):
        code, out, err = run_cli(capsys, "evaluate", est, "--ground-truth", gt, "--json")
    assert code == 0, err
    assert json.loads(out)["num_poses"] == 2


def test_output_to_dev_stdout(capsys: pytest.CaptureFixture[str], g2d: Path) -> None:
    # /dev/stdout is standard output, like "-" (was: resolved to /proc/self/fd/1 and renamed
    # over, or opened a second time and truncated)
    code, out, err = run_cli(capsys, "convert", g2d, "/dev/stdout", "--out-format", "g2o")
    assert code == 0, err
    assert out.startswith("VERTEX_SE2 0 ") and "wrote /dev/stdout" in err


def test_start_up_imports_nothing_heavy_before_the_error_boundary() -> None:
    """A Ctrl-C during ``import hybridpgo`` (Numba: ~0.5 s) printed a traceback: the package and
    the CLI module must import nothing heavy, so main()'s boundary is entered within ~0.1 s."""
    import subprocess

    code = ("import sys, hybridpgo.cli, hybridpgo; "
            "heavy = [m for m in ('numba', 'scipy', 'numpy', 'matplotlib') if m in sys.modules]; "
            "assert not heavy, heavy; "
            "assert callable(hybridpgo.energy)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr


# =========================================================================== numbers at the limits
#: Information of one EDGE3 whose last diagonal entry is 1e75 (TORO upper triangle, 21 values).
_INFO_BIG = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1e75"
_INFO_ONE = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"


@pytest.fixture
def gain_overflow(tmp_path: Path) -> Path:
    """Three EDGE3 lines into pose 4: LM's gain ratio is ~1e300 and (2 rho - 1)^3 overflowed."""
    return write(tmp_path / "gain.graph", f"EDGE3 0 4 0 0 -3.1 3 0 0 {_INFO_BIG}",
                 f"EDGE3 0 4 0 0 0.5 1 -3.1 1 {_INFO_ONE}", f"EDGE3 1 4 1 0 100 1 0 0 {_INFO_ONE}")


def test_lm_damping_update_with_a_huge_gain_ratio(capsys: pytest.CaptureFixture[str],
                                                  gain_overflow: Path, tmp_path: Path) -> None:
    out = tmp_path / "o.graph"
    code, _, err = run_cli(capsys, "optimize", gain_overflow, "-o", out, "-q")
    assert code == 0, err
    assert read_graph(out).num_nodes == 3
    # H is singular to rounding at the solution (information 1e75 beside 1): no covariance
    code, _, err = run_cli(capsys, "optimize", gain_overflow, "-o", out, "-q",
                           "--covariance", tmp_path / "c.npz")
    assert_error(code, err, "gain.graph: ", "covariances are not defined")


@pytest.mark.gtsam
def test_isam2_indeterminate_system_is_an_error(capsys: pytest.CaptureFixture[str],
                                                tmp_path: Path) -> None:
    pytest.importorskip("gtsam")
    p = write(tmp_path / "far.g2o", *V2, "EDGE_SE2 0 1 1e200 0 0 1 0 0 1 0 1",
              "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1")
    code, _, err = run_cli(capsys, "replay", p, "--compare", "isam2", "--every", "0",
                           "--extra-frames", "0")
    assert_error(code, err, "far.g2o: ", "isam2 stopped at frame 3", "Indeterminate")


def test_replay_budget_beyond_the_clock(capsys: pytest.CaptureFixture[str], g2d: Path) -> None:
    code, _, err = run_cli(capsys, "replay", g2d, "--budget-ms", "1e15", "--every", "0",
                           "--extra-frames", "1")
    assert code == 0, err


def test_evaluate_coordinates_whose_squares_overflow(capsys: pytest.CaptureFixture[str],
                                                     tmp_path: Path) -> None:
    """An SVD of non-finite numbers ran for minutes and ignored Ctrl-C."""
    p = write(tmp_path / "e.g2o", "VERTEX_SE2 0 1e200 0 0", "VERTEX_SE2 1 1 0 0",
              "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1")
    code, _, err = run_cli(capsys, "evaluate", p, "--ground-truth", p)
    assert_error(code, err, "e.g2o", "pose 0", "1e+200")


def test_plot_coordinates_beyond_what_can_be_drawn(capsys: pytest.CaptureFixture[str],
                                                   tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    p = write(tmp_path / "far.g2o", "VERTEX_SE2 0 1e308 0 0", "VERTEX_SE2 1 -1e308 0 0",
              "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1")
    out = tmp_path / "far.png"
    code, _, err = run_cli(capsys, "plot", p, "-o", out)
    assert_error(code, err, "far.g2o: ", "cannot draw")
    assert not out.exists()


_SE3_EDGE = "1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"


def test_plot_3d_map_far_from_the_origin(capsys: pytest.CaptureFixture[str],
                                         tmp_path: Path) -> None:
    """A 3D map whose span is small but which lies at 1.8e308 m: matplotlib's axis limits
    would overflow, so it is refused like a map that spans too much."""
    pytest.importorskip("matplotlib")
    x = "1.7976931348623157e308"
    p = write(tmp_path / "far3.g2o", *(f"VERTEX_SE3:QUAT {i} {x} 0 {z} 0 0 0 1"
                                       for i, z in enumerate(("0", "0", "1e-310"))),
              f"EDGE_SE3:QUAT 0 1 {_SE3_EDGE}", f"EDGE_SE3:QUAT 1 2 {_SE3_EDGE}")
    out = tmp_path / "far3.png"
    code, _, err = run_cli(capsys, "plot", p, "-o", out)
    assert_error(code, err, "far3.g2o: ", "cannot draw")
    assert not out.exists()


def test_plot_3d_map_with_subnormal_heights(capsys: pytest.CaptureFixture[str],
                                            tmp_path: Path) -> None:
    """Heights that vary by a subnormal amount: the map is drawn flat (no infinite height
    exaggeration, no NumPy warning, which the suite turns into an error)."""
    pytest.importorskip("matplotlib")
    p = write(tmp_path / "flat3.g2o", *(f"VERTEX_SE3:QUAT {i} {i} 0 {z} 0 0 0 1"
                                        for i, z in enumerate(("0", "0", "1e-310"))),
              f"EDGE_SE3:QUAT 0 1 {_SE3_EDGE}", f"EDGE_SE3:QUAT 1 2 {_SE3_EDGE}")
    out = tmp_path / "flat3.png"
    code, _, err = run_cli(capsys, "plot", p, "-o", out)
    assert code == 0, err
    assert out.stat().st_size > 0


def test_nearest_information_of_subnormal_entries(capsys: pytest.CaptureFixture[str],
                                                  tmp_path: Path) -> None:
    p = write(tmp_path / "tiny.g2o", *V2[:2], "EDGE_SE2 0 1 1 0 0 1e-320 1e-320 0 1e-320 0 1e-320")
    with pytest.warns(UserWarning, match="projected") as record:
        code, _, err = run_cli(capsys, "info", p, "--fix-information", "nearest")
    assert code == 0, err
    assert len(record) == 1, [str(w.message) for w in record]


# =========================================================================== standard streams
class _FullStream(io.StringIO):
    """Standard output on a full disk (``> /dev/full``)."""

    def write(self, s: str) -> int:
        raise OSError(28, "No space left on device")

    def flush(self) -> None:
        raise OSError(28, "No space left on device")


@pytest.mark.parametrize("argv", [["info"], ["info", "--json"],
                                  ["convert", "-", "-", "--out-format", "g2o"]])
def test_standard_output_on_a_full_disk(capsys: pytest.CaptureFixture[str], g2d: Path,
                                        monkeypatch: pytest.MonkeyPatch,
                                        argv: list[str]) -> None:
    if "-" in argv:
        monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(g2d.read_bytes())))
        argv = [argv[0], "-", *argv[2:]]
    else:
        argv = [*argv, str(g2d)]
    monkeypatch.setattr(sys, "stdout", _FullStream())
    code, _, err = run_cli(capsys, *argv)
    assert_error(code, err, "standard output", "No space left on device")


def test_closed_standard_input(capsys: pytest.CaptureFixture[str],
                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "stdin", None)  # as Python starts with "<&-"
    code, _, err = run_cli(capsys, "info", "-")
    assert_error(code, err, "<stdin>", "standard input is closed")


def test_output_that_standard_input_reads_is_refused(capsys: pytest.CaptureFixture[str],
                                                     g2d: Path, monkeypatch: pytest.MonkeyPatch,
                                                     no_solve: None) -> None:
    before = g2d.read_bytes()
    with open(g2d, "rb") as fh:
        monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(fh))
        code, _, err = run_cli(capsys, "optimize", "-", "-o", g2d)
    assert_error(code, err, "standard input", "refusing to overwrite it")
    assert g2d.read_bytes() == before


# =========================================================================== names and signals
@pytest.mark.parametrize("cmd", ["optimize", "convert"])
def test_output_name_at_the_length_limit(capsys: pytest.CaptureFixture[str], g2d: Path,
                                         tmp_path: Path, cmd: str) -> None:
    d = tmp_path / "out"
    d.mkdir()
    out = d / ("o" * (os.pathconf(d, "PC_NAME_MAX") - 4) + ".g2o")
    argv = [cmd, g2d, out] if cmd == "convert" else [cmd, g2d, "-o", out, "-q"]
    code, _, err = run_cli(capsys, *argv)
    assert code == 0, err
    assert [p.name for p in d.iterdir()] == [out.name]
    assert read_graph(out).num_nodes == 3


def test_sigterm_during_a_write_cleans_up(capsys: pytest.CaptureFixture[str], g2d: Path,
                                          tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM once the temporary output file exists: it is removed, exit 143."""
    import signal

    import hybridpgo._output as output

    real = output.temp_file
    made: list[str] = []

    def terminated_after_creating(target: str, **kwargs: Any) -> tuple[int, str]:
        fd, tmp = real(target, **kwargs)
        made.append(tmp)
        os.kill(os.getpid(), signal.SIGTERM)
        return fd, tmp

    before = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "o.g2o"
    code, _, err = run_cli(capsys, "optimize", g2d, "-o", out, "-q")  # the pre-check's probe
    assert code == 0, err
    monkeypatch.setattr(output, "temp_file", terminated_after_creating)
    code, _, err = run_cli(capsys, "convert", g2d, out, "--out-format", "toro")
    assert code == 143, err
    assert "terminated" in err and "Traceback" not in err
    assert made and not any(os.path.exists(t) for t in made)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.g2o", "o.g2o"]
    assert out.read_text().startswith("VERTEX_SE2")  # the old output is untouched
    assert signal.getsignal(signal.SIGTERM) == before  # restored after main()


# =========================================================================== messages
def test_format_detection_shortens_an_unknown_tag(capsys: pytest.CaptureFixture[str],
                                                  tmp_path: Path) -> None:
    p = write(tmp_path / "junk.txt", "x" * 1_000_000 + " 1 2 3")
    code, _, err = run_cli(capsys, "info", p)
    assert_error(code, err, "junk.txt:1: ", "cannot detect the file format", "(1000000 characters)")
    assert len(err) < 1000


def test_residuals_that_overflow_are_refused(capsys: pytest.CaptureFixture[str],
                                             tmp_path: Path) -> None:
    p = write(tmp_path / "far.g2o", "VERTEX_SE2 0 1e200 0 0", "VERTEX_SE2 1 1 0 0",
              "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1")
    out = tmp_path / "r.csv"
    code, _, err = run_cli(capsys, "info", p, "--residuals", out)
    assert_error(code, err, "far.g2o:3: ", "overflow")
    assert not out.exists()


def test_solver_errors_name_the_file_and_a_reason(capsys: pytest.CaptureFixture[str],
                                                  tmp_path: Path) -> None:
    # every start's energy overflows: each start must say so, and the file must be named
    p = write(tmp_path / "far.g2o", "VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0",
              "EDGE_SE2 0 1 1e200 0 0 1 0 0 1 0 1", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1")
    code, _, err = run_cli(capsys, "optimize", p, "-o", tmp_path / "o.g2o", "-q")
    assert_error(code, err, "far.g2o: ")
    assert not re.search(r": ;|: $", err.strip()), err


def test_info_accepts_several_fix_lines(capsys: pytest.CaptureFixture[str],
                                        tmp_path: Path) -> None:
    import json

    p = write(tmp_path / "fix.g2o", *V2, "FIX 0", "FIX 1", *E2)
    code, out, err = run_cli(capsys, "info", p, "--json")
    assert code == 0, err
    assert json.loads(out)["fixed"] == 2


def test_a_byte_order_mark_is_skipped(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    p = tmp_path / "bom.g2o"
    p.write_bytes(b"\xef\xbb\xbf" + "\n".join([*V2, *E2]).encode() + b"\n")
    code, _, err = run_cli(capsys, "info", p)
    assert code == 0, err
    assert read_graph(p).num_edges == 3


# =========================================================================== found by fuzz_cli
def test_information_cholesky_cannot_factor_is_refused_at_its_line(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """iSAM square-root information with an entry of 1e29: R^T R passes "smallest eigenvalue
    > 0" by rounding, and every whitening's Cholesky factorization then failed (traceback)."""
    p = write(tmp_path / "sqrt.txt", "ODOMETRY 1 2 2.93682 -1.33422 -1.85652 0.956784019582386 "
              "0 0 0.956784019582386 111111111111111111111111111111 0.956784")
    for cmd in (["info", p], ["optimize", p, "-o", tmp_path / "o.g2o", "-q"]):
        code, _, err = run_cli(capsys, *cmd)
        assert_error(code, err, "sqrt.txt:1: ", "Cholesky factorization fails")
    with pytest.warns(UserWarning, match="projected"):
        code, _, err = run_cli(capsys, "info", p, "--fix-information", "nearest")
    assert code == 0, err


def test_toro_weights_of_subnormal_information(capsys: pytest.CaptureFixture[str],
                                               tmp_path: Path) -> None:
    """A yaw information of 5e-324: 1 / the node's weight overflowed (NumPy warning)."""
    p = write(tmp_path / "sub.graph", "VERTEX2 0 0 0 0", "VERTEX2 1 1 0 0", "VERTEX2 2 2 0 0",
              "EDGE2 0 1 1 0 0 1 0 1 1 0 0", "EDGE2 1 2 1 0 0 1 0 1 5e-324 0 0")
    code, _, err = run_cli(capsys, "optimize", p, "--solver", "toro", "-o",
                           tmp_path / "o.graph", "-q")
    assert code == 0, err


def test_planar_relaxation_that_overflows_fails_quietly(capsys: pytest.CaptureFixture[str],
                                                        tmp_path: Path) -> None:
    """A measurement of 1e154: the relaxation's quadratic overflowed (NumPy warnings); it is
    the relaxation's failure, reported in the summary, and the pipeline goes on."""
    import json

    p = write(tmp_path / "far.g2o", *V2, "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1",
              "EDGE_SE2 1 2 1e154 0 0 1 0 0 1 0 1", "EDGE_SE2 0 2 2 0 0 1 0 0 1 0 1")
    code, out, err = run_cli(capsys, "optimize", p, "-o", tmp_path / "o.g2o", "--json")
    assert code == 0, err
    assert "overflows float64" in json.dumps(json.loads(out))
