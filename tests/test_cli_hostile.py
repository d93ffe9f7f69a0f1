"""Hostile use of the command line.

Every test here reproduced a defect first: a traceback (exit 1) on finite input, a file left
behind or an input destroyed after an error, an output problem found only after the solve.
"""

from __future__ import annotations

import io
import os
import stat
import sys
import threading
from pathlib import Path

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
    from hybridpgo.cli._parser import MAX_DPI
    from hybridpgo.errors import HybridPGOError
    from hybridpgo.plot import MAX_DPI as PLOT_MAX_DPI
    from hybridpgo.plot import graph_figure, save_figure

    assert MAX_DPI == PLOT_MAX_DPI
    g = read_graph(g2d)
    fig = graph_figure(g, [(g.rotations, g.translations)])
    with pytest.raises(HybridPGOError, match=r"dpi must be in 1\.\.600"):
        save_figure(fig, out, dpi=100000)
    assert not out.exists()


def test_two_fix_lines_name_the_file(capsys: pytest.CaptureFixture[str],
                                     tmp_path: Path) -> None:
    p = write(tmp_path / "fix.g2o", *V2, "FIX 0", "FIX 1", *E2)
    code, _, err = run_cli(capsys, "info", p)
    assert_error(code, err, "fix.g2o: ", "fixes 2 poses")


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
