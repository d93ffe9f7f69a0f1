"""The ``hybridpgo`` command line: every command in-process through ``main([...])``, the error
boundary, and one subprocess smoke test of the installed console script
(docs/contributing.md#tests, docs/contributing.md#cli)."""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from tolerances import FLOAT64_IDENTITY

from hybridpgo import energy, read_graph
from hybridpgo.cli._common import LazyChoices, output_format
from hybridpgo.cli._parser import build_parser
from hybridpgo.initialization import InitKind
from hybridpgo.io import FORMATS, WRITE_FORMATS
from hybridpgo.solvers import METHODS, TREES
from hybridpgo.solvers.hybrid import STEP_KINDS
from hybridpgo.tree import TreeKind

COMMANDS = ("info", "optimize", "convert", "plot", "demo", "generate", "noisify", "evaluate",
            "batch", "warmup")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_json(capsys: pytest.CaptureFixture[str], *argv: object) -> dict:
    code, out, err = run_cli(capsys, *argv, "--json")
    assert code == 0, err
    return json.loads(out)


@pytest.fixture
def small(data_dir: Path) -> Path:
    return data_dir / "smallGrid3D.g2o"


@pytest.fixture
def bad_g2o(tmp_path: Path) -> Path:
    """A g2o file whose line 3 lacks the measurement and information numbers."""
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
                    "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                    "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0 0\n")
    return path


# =========================================================================== parser and help
def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(capsys, "--help")
    assert code == 0
    for cmd in COMMANDS:
        assert cmd in out


@pytest.mark.parametrize("cmd", COMMANDS)
def test_every_command_has_help(capsys: pytest.CaptureFixture[str], cmd: str) -> None:
    code, out, _ = run_cli(capsys, cmd, "--help")
    assert code == 0
    assert out.startswith(f"usage: hybridpgo {cmd}")


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from hybridpgo import __version__

    code, out, _ = run_cli(capsys, "--version")
    assert code == 0
    assert out.strip() == f"hybridpgo {__version__}"


def test_no_command_prints_help_and_fails(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(capsys)
    assert code == 2
    assert "COMMAND" in err


def _choices(cmd: str, dest: str) -> list[str]:
    """The choices of option ``dest`` of (sub)command ``cmd``, e.g. "generate city"."""
    parser = build_parser()
    for name in cmd.split():
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
    action = next(a for a in parser._actions if a.dest == dest)
    return list(action.choices)  # type: ignore[arg-type]


def test_choices_are_the_library_lists() -> None:
    """``choices=`` come from the lists the library validates against, not copies."""
    from hybridpgo.generate import GRID_PRESETS, PRESETS

    assert _choices("optimize", "format") == list(FORMATS)
    assert _choices("optimize", "out_format") == list(WRITE_FORMATS)
    assert _choices("optimize", "solver") == list(METHODS)
    assert _choices("optimize", "step") == list(STEP_KINDS)
    assert _choices("optimize", "tree") == list(TREES)
    assert [k.value for k in TreeKind] == list(TREES)
    assert _choices("optimize", "init") == [k.value for k in InitKind]
    assert _choices("generate city", "preset") == sorted(PRESETS)
    assert _choices("generate grid", "preset") == list(GRID_PRESETS)


def test_help_shows_the_solvers_real_defaults(capsys: pytest.CaptureFixture[str]) -> None:
    from hybridpgo.solvers import GaussNewtonConfig, HybridConfig

    code, out, _ = run_cli(capsys, "optimize", "--help")
    assert code == 0
    text = " ".join(out.split())  # undo argparse's line wrapping
    hy, gn = HybridConfig(), GaussNewtonConfig()
    for phrase in (f"sweeps over all constraints (default {hy.sweeps})",
                   f"per sweep (default {hy.tau_decay:g})",
                   f"relaxed together (default {hy.gps_batch_size})",
                   f"exact solver (default {gn.max_iterations})"):
        assert phrase in text


def test_lazy_choices_accept_anything_when_the_module_is_missing() -> None:
    def missing() -> list[str]:
        raise ImportError("no such module")

    lazy = LazyChoices(missing)
    assert "anything" in lazy
    assert list(lazy) == []
    present = LazyChoices(lambda: ["a", "b"])
    assert "a" in present and "c" not in present and len(present) == 2


@pytest.mark.parametrize("argv, message", [
    (["--sweeps", "-1"], "--sweeps: must be an integer in 0..1000000"),
    (["--tau-decay", "1.5"], "--tau-decay: must be a number in (0, 1]"),
    (["--tau0", "0"], "--tau0: must be a number in (0, 2)"),
    (["--damping", "nan"], "--damping: must be a number >= 0"),
    (["--gps-batch-size", "0"], "--gps-batch-size: must be an integer >= 1"),
    (["--dmax", "1"], "--dmax: must be an integer >= 2"),
    (["--dmax", "-3"], "--dmax: must be an integer >= 2"),
    (["--dmax", "2.5"], "--dmax: must be an integer >= 2"),
    (["--step", "cholesky"], "invalid choice: 'cholesky'"),
    (["--solver", "g2o"], "invalid choice: 'g2o'"),
])
def test_bad_option_values_are_usage_errors(capsys: pytest.CaptureFixture[str], tiny: Path,
                                            tmp_path: Path, argv: list[str],
                                            message: str) -> None:
    out = tmp_path / "out.g2o"
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, *argv)
    assert code == 2
    assert message in err
    assert not out.exists()


# =========================================================================== info
def test_info_text(capsys: pytest.CaptureFixture[str], tiny: Path) -> None:
    code, out, err = run_cli(capsys, "info", tiny)
    assert code == 0, err
    assert "poses           9" in out
    assert "11: 8 between consecutive ids, 3 loop closures; 3 not in the tree" in out
    assert "energy (file)" in out and "energy (tree)" in out


def test_info_json_matches_the_library(capsys: pytest.CaptureFixture[str], small: Path) -> None:
    from hybridpgo.initialization import initial_locals
    from hybridpgo.tree import build_tree, global_poses

    info = run_json(capsys, "info", small)
    g = read_graph(small)
    tree = build_tree(g, "bfs")
    lengths = tree.path_lengths()
    assert info["format"] == "g2o" and info["dimension"] == "3D"
    assert info["poses"] == g.num_nodes == 125
    assert info["relative_edges"] == g.num_edges == 297
    assert info["odometry_edges"] + info["loop_edges"] == g.num_edges
    assert info["non_tree_edges"] == g.num_edges - (g.num_nodes - 1)
    assert info["gps"] == 0 and info["has_vertices"] is True
    assert info["tree"]["max_depth"] == tree.max_depth
    assert info["tree"]["path_length_max"] == int(lengths.max())
    assert info["tree"]["path_length_mean"] == pytest.approx(float(lengths.mean()),
                                                             rel=FLOAT64_IDENTITY)
    assert info["energy_file"] == pytest.approx(energy(g), rel=FLOAT64_IDENTITY)
    e_tree = energy(g, *global_poses(tree, *initial_locals(g, tree, "tree")))
    assert info["energy_tree_init"] == pytest.approx(e_tree, rel=FLOAT64_IDENTITY)
    assert info["energy_tree_init_per_constraint"] == pytest.approx(e_tree / 297,
                                                                    rel=FLOAT64_IDENTITY)


def test_info_mst_tree(capsys: pytest.CaptureFixture[str], small: Path) -> None:
    info = run_json(capsys, "info", small, "--tree", "mst")
    assert info["tree"]["kind"] == "mst"


def test_info_toro_2d_with_equiv(capsys: pytest.CaptureFixture[str], data_dir: Path) -> None:
    with pytest.warns(UserWarning, match="EQUIV"):
        info = run_json(capsys, "info", data_dir / "w100_toro.graph")
    assert info["format"] == "toro" and info["dimension"] == "2D"
    assert info["poses"] == 60  # 100 vertices, 40 merged by EQUIV


def test_info_of_an_isam_file_has_no_file_energy(capsys: pytest.CaptureFixture[str], tiny: Path,
                                                 tmp_path: Path) -> None:
    isam = tmp_path / "tiny.txt"
    assert run_cli(capsys, "convert", tiny, isam)[0] == 0
    info = run_json(capsys, "info", isam)
    assert info["format"] == "isam" and info["has_vertices"] is False
    assert info["energy_file"] is None
    assert info["energy_tree_init"] > 0


def test_skip_unknown(capsys: pytest.CaptureFixture[str], tiny: Path, tmp_path: Path) -> None:
    path = tmp_path / "extra.g2o"
    path.write_text(tiny.read_text() + "ROBOTLASER1 0 1 2 3\n")
    code, _, err = run_cli(capsys, "info", path)
    assert code == 2
    assert "extra.g2o:" in err and "ROBOTLASER1" in err
    with pytest.warns(UserWarning, match="skipped 1 line"):
        info = run_json(capsys, "info", path, "--skip-unknown")
    assert info["poses"] == 9


# =========================================================================== optimize
def test_optimize_hybrid_writes_the_result(capsys: pytest.CaptureFixture[str], small: Path,
                                           tmp_path: Path) -> None:
    out = tmp_path / "out.g2o"
    code, text, err = run_cli(capsys, "optimize", small, "-o", out, "--solver", "hybrid")
    assert code == 0, err
    for label in ("energy before", "energy after", "per constraint", "analyze", "solve"):
        assert label in text
    # not a terminal: no progress drawn (tests/test_progress.py: --progress forces it)
    assert "\r" not in err and "10/10" not in err
    g0 = read_graph(small)
    g1 = read_graph(out)
    assert g1.num_nodes == g0.num_nodes and g1.num_edges == g0.num_edges
    np.testing.assert_array_equal(g1.edge_translations, g0.edge_translations)
    assert energy(g1) < energy(g0)


def test_optimize_json_matches_the_written_file(capsys: pytest.CaptureFixture[str], tiny: Path,
                                                tmp_path: Path) -> None:
    from hybridpgo.solvers import optimize

    out = tmp_path / "out.g2o"
    s = run_json(capsys, "optimize", tiny, "-o", out, "--solver", "exact")
    assert s["solver"] == "exact" and s["init"] == "file"  # exact defaults to the file's vertices
    assert s["result"]["status"] == "converged"
    assert s["output"] == {"path": str(out), "format": "g2o"}
    e_file = energy(read_graph(out))
    assert s["energy_after"] == pytest.approx(e_file, rel=FLOAT64_IDENTITY)
    ref = optimize(read_graph(tiny), "exact")
    assert s["energy_after"] == pytest.approx(ref.final_energy, rel=FLOAT64_IDENTITY)
    assert s["energy_after_per_constraint"] == pytest.approx(e_file / 11, rel=FLOAT64_IDENTITY)


def test_optimize_every_hybrid_option(capsys: pytest.CaptureFixture[str], small: Path,
                                      tmp_path: Path) -> None:
    out = tmp_path / "out.graph"
    s = run_json(capsys, "optimize", small, "-o", out, "--solver", "hybrid", "--init", "file",
                 "--sweeps", "3", "--tau0", "0.5", "--tau-decay", "0.9", "--damping", "1e-5",
                 "--step", "givens", "--tree", "mst", "--gps-batch-size", "7",
                 "--tolerance", "1e-3", "--polish", "--max-iterations", "2", "-q")
    r = s["result"]
    assert s["init"] == "file"
    assert s["output"]["format"] == "toro"  # from the extension
    assert r["method"] == "hybrid+polish" and r["step"] == "givens"
    assert 1 <= r["sweeps"] <= 3
    assert r["final_tau"] == pytest.approx(0.5 * 0.9 ** r["sweeps"], rel=FLOAT64_IDENTITY)
    assert r["polish_iterations"] <= 2
    assert "energy_after_sweeps" in s
    assert read_graph(out).source_format == "toro"


def test_optimize_every_exact_option(capsys: pytest.CaptureFixture[str], small: Path,
                                     tmp_path: Path) -> None:
    out = tmp_path / "out.g2o"
    s = run_json(capsys, "optimize", small, "-o", out, "--solver", "exact", "--init", "tree",
                 "--tree", "mst", "--max-iterations", "3", "--tolerance", "1e-8",
                 "--out-format", "g2o", "--format", "g2o", "--quiet")
    assert s["init"] == "tree"
    assert s["result"]["iterations"] <= 3
    assert capsys.readouterr().err == ""


def test_quiet_hides_progress(capsys: pytest.CaptureFixture[str], tiny: Path,
                              tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "--quiet")
    assert code == 0
    assert err == ""


def test_optimize_isam_input_writes_g2o(capsys: pytest.CaptureFixture[str], tiny: Path,
                                        tmp_path: Path) -> None:
    isam = tmp_path / "tiny.txt"
    assert run_cli(capsys, "convert", tiny, isam)[0] == 0
    out = tmp_path / "opt.txt"  # .txt does not select iSAM: it would lose the poses
    s = run_json(capsys, "optimize", isam, "-o", out, "-q")
    assert s["output"]["format"] == "g2o"
    assert read_graph(out).has_estimates
    code, _, err = run_cli(capsys, "optimize", isam, "-o", tmp_path / "x", "--init", "file")
    assert code == 2 and "--init file needs vertex estimates" in err
    code, _, err = run_cli(capsys, "optimize", isam, "-o", tmp_path / "x", "--out-format",
                           "isam")
    assert code == 2 and "iSAM format has no vertex lines" in err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("argv, message", [
    (["--solver", "exact", "--sweeps", "3"], "--sweeps: only for the hybrid solver"),
    (["--solver", "exact", "--step", "givens", "--polish"], "--step, --polish: only for the"),
    (["--solver", "hybrid", "--max-iterations", "3"],
     "--max-iterations limits the exact solver or the polish"),
])
def test_options_for_the_other_solver_are_refused(capsys: pytest.CaptureFixture[str],
                                                  tiny: Path, tmp_path: Path, argv: list[str],
                                                  message: str) -> None:
    out = tmp_path / "o.g2o"
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, *argv)
    assert code == 2
    assert message in err
    assert not out.exists()


def test_optimize_plot_writes_three_pngs(capsys: pytest.CaptureFixture[str], tiny: Path,
                                         tmp_path: Path) -> None:
    prefix = tmp_path / "run"
    s = run_json(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "--plot", prefix, "-q")
    expected = [f"{prefix}_before.png", f"{prefix}_after.png", f"{prefix}_energy.png"]
    assert s["plots"] == expected
    for path in expected:
        assert Path(path).read_bytes()[:8] == PNG_MAGIC
    assert sorted(os.listdir(tmp_path)) == ["o.g2o", "run_after.png", "run_before.png",
                                            "run_energy.png"]


def test_optimize_into_a_missing_directory_fails_before_solving(
        capsys: pytest.CaptureFixture[str], tiny: Path, tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "nope" / "o.g2o")
    assert code == 2
    assert "does not exist" in err
    assert "hybrid [" not in err  # refused before the solver ran


# =========================================================================== error boundary
def test_bad_file_exits_2_naming_file_and_line(capsys: pytest.CaptureFixture[str],
                                               bad_g2o: Path, tmp_path: Path) -> None:
    out = tmp_path / "out.g2o"
    code, stdout, err = run_cli(capsys, "optimize", bad_g2o, "-o", out)
    assert code == 2
    assert stdout == ""
    assert err.startswith(f"hybridpgo: error: {bad_g2o}:3: EDGE_SE3:QUAT needs")
    assert "Traceback" not in err
    assert not out.exists()
    assert sorted(os.listdir(tmp_path)) == ["bad.g2o"]  # no temporary file left either


@pytest.mark.parametrize("cmd", ["info", "plot", "convert", "noisify", "evaluate"])
def test_every_reader_reports_file_and_line(capsys: pytest.CaptureFixture[str], bad_g2o: Path,
                                            tmp_path: Path, cmd: str) -> None:
    out = tmp_path / "out.g2o"
    extra = {"info": [], "plot": ["-o", out], "convert": [out], "noisify": ["-o", out],
             "evaluate": ["--ground-truth", bad_g2o]}[cmd]
    code, _, err = run_cli(capsys, cmd, bad_g2o, *extra)
    assert code == 2
    assert f"{bad_g2o}:3:" in err
    assert not out.exists()


def test_missing_file(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "info", tmp_path / "none.g2o")
    assert code == 2
    assert "none.g2o: cannot read the file" in err


def test_debug_shows_the_traceback(capsys: pytest.CaptureFixture[str], bad_g2o: Path) -> None:
    for argv in (["--debug", "info", bad_g2o], ["info", bad_g2o, "--debug"]):
        code, _, err = run_cli(capsys, *argv)
        assert code == 2
        assert "Traceback" in err and "FormatError" in err
        assert "hybridpgo: error:" in err


def test_unexpected_exception_is_a_bug_with_traceback(capsys: pytest.CaptureFixture[str],
                                                      monkeypatch: pytest.MonkeyPatch,
                                                      tiny: Path) -> None:
    import hybridpgo.cli.info

    def broken(args: object) -> int:
        raise RuntimeError("boom")

    monkeypatch.setattr(hybridpgo.cli.info, "run", broken)
    code, _, err = run_cli(capsys, "info", tiny)
    assert code == 1
    assert "Traceback" in err and "RuntimeError: boom" in err


def test_keyboard_interrupt_exits_130(capsys: pytest.CaptureFixture[str],
                                      monkeypatch: pytest.MonkeyPatch, tiny: Path) -> None:
    import hybridpgo.cli.info

    def interrupted(args: object) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(hybridpgo.cli.info, "run", interrupted)
    code, _, err = run_cli(capsys, "info", tiny)
    assert code == 130
    assert "interrupted" in err and "Traceback" not in err


def test_closed_stdout_pipe_exits_quietly(capsys: pytest.CaptureFixture[str],
                                          monkeypatch: pytest.MonkeyPatch, tiny: Path) -> None:
    import hybridpgo.cli.info

    def reader_gone(args: object) -> int:
        raise BrokenPipeError

    monkeypatch.setattr(hybridpgo.cli.info, "run", reader_gone)
    code, _, err = run_cli(capsys, "info", tiny)
    assert code == 141
    assert err == ""


# =========================================================================== progress bar
# (the bar itself: tests/test_progress.py)
def test_progress_flag_draws_off_a_terminal(capsys: pytest.CaptureFixture[str], tiny: Path,
                                            tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "--progress",
                           "--solver", "hybrid", "--sweeps", "3")
    assert code == 0
    assert "hybrid" in err and "3/3" in err and "E/c" in err
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "--progress",
                           "-q")
    assert code == 0 and err == ""  # --quiet wins


# =========================================================================== convert
def test_convert_round_trip(capsys: pytest.CaptureFixture[str], tiny: Path,
                            tmp_path: Path) -> None:
    toro = tmp_path / "t.graph"
    back = tmp_path / "t.g2o"
    code, out, err = run_cli(capsys, "convert", tiny, toro)
    assert code == 0, err
    assert f"wrote {toro} (toro)" in out
    assert run_cli(capsys, "convert", toro, back)[0] == 0
    a, b = read_graph(tiny), read_graph(back)
    assert (a.source_format, read_graph(toro).source_format, b.source_format) == \
        ("g2o", "toro", "g2o")
    np.testing.assert_array_equal(a.node_ids, b.node_ids)
    np.testing.assert_array_equal(a.edge_nodes, b.edge_nodes)
    np.testing.assert_allclose(b.rotations, a.rotations, rtol=0, atol=FLOAT64_IDENTITY)
    np.testing.assert_allclose(b.edge_rotations, a.edge_rotations, rtol=0,
                               atol=FLOAT64_IDENTITY)
    np.testing.assert_array_equal(b.translations, a.translations)
    np.testing.assert_array_equal(b.edge_translations, a.edge_translations)
    np.testing.assert_array_equal(b.edge_information, a.edge_information)


def test_convert_format_choice(capsys: pytest.CaptureFixture[str], tiny: Path,
                               tmp_path: Path) -> None:
    out = tmp_path / "noext"
    assert run_cli(capsys, "convert", tiny, out)[0] == 0  # no extension: the input's format
    assert read_graph(out).source_format == "g2o"
    assert run_cli(capsys, "convert", tiny, out, "--out-format", "toro")[0] == 0
    assert read_graph(out).source_format == "toro"
    isam = tmp_path / "x.txt"
    assert run_cli(capsys, "convert", tiny, isam, "--format", "g2o")[0] == 0
    assert read_graph(isam).source_format == "isam"


def test_output_format_rules(tiny: Path) -> None:
    g = read_graph(tiny)
    assert output_format("a.graph", None, g, allow_isam=True) == "toro"
    assert output_format("a.G2O", None, g, allow_isam=True) == "g2o"
    assert output_format("a.txt", None, g, allow_isam=True) == "isam"
    assert output_format("a.txt", None, g, allow_isam=False) == "g2o"
    assert output_format("a.out", None, g, allow_isam=True) == "g2o"
    assert output_format("a.g2o", "toro", g, allow_isam=False) == "toro"


# =========================================================================== plot
def test_plot_writes_a_png(capsys: pytest.CaptureFixture[str], tiny: Path,
                           tmp_path: Path) -> None:
    fig = tmp_path / "fig.png"
    code, out, err = run_cli(capsys, "plot", tiny, "-o", fig)
    assert code == 0, err
    assert out.strip() == f"wrote {fig}"
    assert fig.read_bytes()[:8] == PNG_MAGIC


def test_plot_before_and_after(capsys: pytest.CaptureFixture[str], tiny: Path,
                               tmp_path: Path) -> None:
    opt = tmp_path / "opt.g2o"
    assert run_cli(capsys, "optimize", tiny, "-o", opt, "-q")[0] == 0
    fig = tmp_path / "cmp.svg"
    code, _, err = run_cli(capsys, "plot", tiny, "--optimized", opt, "-o", fig, "--dpi", "50",
                           "--no-residuals", "--format", "g2o")
    assert code == 0, err
    assert b"<svg" in fig.read_bytes()[:500]


def test_plot_refuses_a_different_graph(capsys: pytest.CaptureFixture[str], tiny: Path,
                                        small: Path, tmp_path: Path) -> None:
    fig = tmp_path / "fig.png"
    code, _, err = run_cli(capsys, "plot", tiny, "--optimized", small, "-o", fig)
    assert code == 2
    assert "pose ids differ" in err
    assert not fig.exists()


def test_plot_bad_extension(capsys: pytest.CaptureFixture[str], tiny: Path,
                            tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "plot", tiny, "-o", tmp_path / "fig.docx")
    assert code == 2
    assert "cannot write a figure as .docx" in err
    assert os.listdir(tmp_path) == []


# =========================================================================== demo
def test_warmup(capsys: pytest.CaptureFixture[str]) -> None:
    """Compiles (or loads) the kernels and says which; --quiet prints nothing."""
    code, out, err = run_cli(capsys, "warmup", "--solver", "exact")
    assert code == 0 and out == ""
    assert re.search(r"hybridpgo warmup: exact: (compiled \d+ kernels|all kernels were already "
                     r"compiled \(loaded from the cache\)) in \d+\.\d s", err)
    assert run_cli(capsys, "warmup", "--solver", "exact", "-q") == (0, "", "")


def test_demo(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """The README's main job: M3500, the default pipeline (sweeps + exact polish), graph and
    plots written."""
    out_dir = tmp_path / "demo"
    code, out, err = run_cli(capsys, "demo", "-o", out_dir, "--sweeps", "3")
    assert code == 0, err
    assert sorted(os.listdir(out_dir)) == ["M3500_after.png", "M3500_before.png",
                                           "M3500_energy.png", "M3500_optimized.g2o"]
    g = read_graph(out_dir / "M3500_optimized.g2o")
    assert g.num_nodes == 3500 and g.num_edges == 5598
    # the polish ends at the optimum: 6532.8 = 1.167 per constraint (docs/conventions.md)
    assert energy(g) / g.num_edges == pytest.approx(1.167, abs=5e-4)
    assert "demo output in" in out and "after sweeps" in out


# ================================================================ generate, noisify, evaluate
def test_generate_evaluate(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    pytest.importorskip("hybridpgo.generate")
    pytest.importorskip("hybridpgo.metrics")
    graph, gt = tmp_path / "city.g2o", tmp_path / "gt.g2o"
    code, out, err = run_cli(capsys, "generate", "city", "--gps-every", "50", "--seed", "3",
                             "-o", graph, "--ground-truth", gt)
    assert code == 0, err
    g = read_graph(graph)
    assert g.num_gps == -(-g.num_nodes // 50)
    assert f"graph         {graph}" in out
    # oracle: the ground truth against itself is exact (no alignment with GPS)
    m = run_json(capsys, "evaluate", gt, "--ground-truth", gt)
    assert m["aligned"] is False
    assert m["position_rmse_m"] == 0.0 and m["heading_error_max_deg"] == 0.0
    # dead reckoning drifts; the text report and the TUM export
    tum = tmp_path / "est.tum"
    code, out, err = run_cli(capsys, "evaluate", graph, "--ground-truth", gt, "--tum", tum)
    assert code == 0, err
    assert "RMSE" in out and "no alignment (earth frame)" in out
    from hybridpgo.metrics import read_ground_truth

    _, trans, ids = read_ground_truth(tum)
    np.testing.assert_array_equal(ids, g.node_ids)
    np.testing.assert_allclose(trans, g.translations, rtol=0, atol=FLOAT64_IDENTITY * 1e3)
    _, gt_trans, _ = read_ground_truth(tmp_path / "est_gt.tum")
    np.testing.assert_allclose(gt_trans, read_graph(gt).translations, rtol=0,
                               atol=FLOAT64_IDENTITY * 1e3)
    m = run_json(capsys, "evaluate", graph, "--ground-truth", gt, "--align", "yes")
    assert m["aligned"] is True


def test_generate_is_deterministic(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    pytest.importorskip("hybridpgo.generate")
    paths = []
    for k in range(2):
        p = tmp_path / f"c{k}.g2o"
        code, _, err = run_cli(capsys, "generate", "city", "-o", p, "--ground-truth",
                               tmp_path / f"gt{k}.g2o")
        assert code == 0, err
        paths.append(p)
    assert paths[0].read_bytes() == paths[1].read_bytes()


def test_evaluate_without_vertices_is_refused(capsys: pytest.CaptureFixture[str], tiny: Path,
                                              tmp_path: Path) -> None:
    pytest.importorskip("hybridpgo.metrics")
    isam = tmp_path / "t.txt"
    assert run_cli(capsys, "convert", tiny, isam)[0] == 0
    code, _, err = run_cli(capsys, "evaluate", isam, "--ground-truth", tiny)
    assert code == 2 and "no vertex lines" in err


def test_noisify(capsys: pytest.CaptureFixture[str], small: Path, tmp_path: Path) -> None:
    pytest.importorskip("hybridpgo.generate")
    a, b, c = tmp_path / "a.g2o", tmp_path / "b.g2o", tmp_path / "c.g2o"
    for path, seed in ((a, 1), (b, 1), (c, 2)):
        code, _, err = run_cli(capsys, "noisify", small, "-o", path, "--yaw-sigma-deg", "3",
                               "--seed", seed)
        assert code == 0, err
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
    g0, g1 = read_graph(small), read_graph(a)
    np.testing.assert_array_equal(g1.edge_translations, g0.edge_translations)
    delta = np.swapaxes(g0.edge_rotations, 1, 2) @ g1.edge_rotations  # Rz(angle) per edge
    np.testing.assert_allclose(delta[:, 2, :], np.tile([0.0, 0.0, 1.0], (297, 1)), rtol=0,
                               atol=FLOAT64_IDENTITY)
    angles = np.degrees(np.arctan2(delta[:, 1, 0], delta[:, 0, 0]))
    assert 2.0 < float(np.std(angles)) < 4.0  # N(0, 3 deg) over 297 edges


def test_noisify_keeps_isam(capsys: pytest.CaptureFixture[str], tiny: Path,
                            tmp_path: Path) -> None:
    pytest.importorskip("hybridpgo.generate")
    isam = tmp_path / "t.txt"
    assert run_cli(capsys, "convert", tiny, isam)[0] == 0
    out = tmp_path / "noisy"
    code, _, err = run_cli(capsys, "noisify", isam, "-o", out, "--yaw-sigma-deg", "0")
    assert code == 0, err
    g0, g1 = read_graph(isam), read_graph(out)
    assert g1.source_format == "isam"
    np.testing.assert_allclose(g1.edge_rotations, g0.edge_rotations, rtol=0,
                               atol=FLOAT64_IDENTITY)


# =========================================================================== console script
def test_console_script(tiny: Path) -> None:
    """The installed ``hybridpgo`` entry point (pip install -e .) in a real subprocess."""
    exe = Path(sysconfig.get_path("scripts")) / "hybridpgo"
    if not exe.exists():  # e.g. a --user install: fall back to PATH next to the interpreter
        exe = Path(sys.executable).parent / "hybridpgo"
    assert exe.exists(), "the console script is not installed: pip install -e ."
    env = {**os.environ, "PYTHONWARNINGS": "error"}
    done = subprocess.run([str(exe), "--help"], capture_output=True, text=True, env=env,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "optimize" in done.stdout
    done = subprocess.run([str(exe), "info", str(tiny), "--json"], capture_output=True,
                          text=True, env=env, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["poses"] == 9
    done = subprocess.run([str(exe), "info", str(tiny) + ".missing"], capture_output=True,
                          text=True, env=env, timeout=120, check=False)
    assert done.returncode == 2
    assert done.stderr.startswith("hybridpgo: error:")


# =========================================================================== --solver toro
@pytest.mark.parametrize(("argv", "message"), [
    (["--polish"], "--polish: not an option of --solver toro"),
    (["--tau0", "0.5"], "--tau0: not an option of --solver toro"),
    (["--dmax", "30"], "--dmax: not an option of --solver toro"),
    (["--max-iterations", "3"], "--max-iterations"),
    (["--init", "chordal"], "--init chordal"),
    (["--tree", "mst"], "--tree mst"),
])
def test_toro_refuses_options_it_does_not_take(capsys: pytest.CaptureFixture[str], tiny: Path,
                                               tmp_path: Path, argv: list[str],
                                               message: str) -> None:
    out = tmp_path / "out.g2o"
    code, _, err = run_cli(capsys, "optimize", str(tiny), "-o", str(out), "--solver", "toro",
                           *argv)
    assert code == 2
    assert message in err
    assert not out.exists()


def test_toro_runs_its_sweeps_as_iterations(capsys: pytest.CaptureFixture[str], tiny: Path,
                                            tmp_path: Path) -> None:
    out = tmp_path / "out.g2o"
    code, text, _ = run_cli(capsys, "optimize", str(tiny), "-o", str(out), "--solver", "toro",
                            "--sweeps", "3", "--json", "--quiet")
    assert code == 0
    summary = json.loads(text)
    assert summary["result"]["method"] == "toro"
    assert summary["result"]["iterations"] == 3
    assert summary["energy_after"] < summary["energy_before"]
    assert out.exists()
    code, _, err = run_cli(capsys, "optimize", str(tiny), "-o", str(out), "--tree", "toro")
    assert code == 2 and "--tree toro: only for --solver toro" in err


# =========================================================================== bounds
def test_sweeps_and_tau0_bounds_match_the_library() -> None:
    from hybridpgo.cli import _options
    from hybridpgo.solvers import config

    assert _options.MAX_SWEEPS == config.MAX_SWEEPS
    assert _options.MAX_TAU == config.MAX_TAU


@pytest.mark.parametrize(("argv", "message"), [
    (["--sweeps", "99999999999999999999"], "--sweeps: must be an integer in 0..1000000"),
    (["--tau0", "2.5"], "--tau0: must be a number in (0, 2)"),
    (["--tau0", "2"], "--tau0: must be a number in (0, 2)"),
])
def test_runaway_sweeps_and_temperatures_are_refused(capsys: pytest.CaptureFixture[str],
                                                     tiny: Path, tmp_path: Path,
                                                     argv: list[str], message: str) -> None:
    out = tmp_path / "out.g2o"
    code, _, err = run_cli(capsys, "optimize", str(tiny), "-o", str(out), *argv)
    assert code == 2 and message in err
    assert not out.exists()


def test_the_parser_and_version_import_no_solver() -> None:
    """``hybridpgo --version`` and ``--help`` build the parser only: no NumPy, SciPy, Numba or
    solver module (the choice lists load when a command's help or a value needs them)."""
    import subprocess
    import sys

    script = ("import sys\n"
              "from hybridpgo.cli import main\n"
              "for argv in (['--version'], ['--help']):\n"
              "    try:\n"
              "        main(argv)\n"
              "    except SystemExit:\n"
              "        pass\n"
              "heavy = sorted(m for m in sys.modules if m.split('.')[0] in "
              "('numpy', 'scipy', 'numba', 'cvxopt') or m.startswith('hybridpgo.solvers.'))\n"
              "print('HEAVY:' + ','.join(h for h in heavy if h != 'hybridpgo.solvers.config'))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True).stdout.strip().splitlines()[-1]
    assert out == "HEAVY:"


def test_optimize_summary_names_the_linear_solver(capsys: pytest.CaptureFixture[str],
                                                  tiny: Path, tmp_path: Path) -> None:
    """The summary says which sparse factorization ran (CHOLMOD is an optional extra)."""
    code, out, _ = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "--solver",
                           "exact")
    s = run_json(capsys, "optimize", tiny, "-o", tmp_path / "p.g2o", "--solver", "exact")
    backend = s["result"]["linear_solver"]
    assert code == 0 and backend
    assert f"linear solver {backend}" in out
