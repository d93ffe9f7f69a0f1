"""``hybridpgo generate city|grid`` and ``noisify`` on the command line: outputs, outliers
files, help, and the defects found by an audit (each test reproduced its defect before the fix)."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

from hybridpgo import energy, read_graph
from hybridpgo.errors import FormatError
from hybridpgo.generate import GridParams
from hybridpgo.generate import grid as grid_module

#: Options that keep the CLI runs small (milliseconds each).
SMALL_GRID = ("--poses", "300")
SMALL_CITY = ("--poses", "1500")


def _files(directory: Path) -> list[str]:
    """Every entry of ``directory``, hidden (temporary) files included."""
    return sorted(p.name for p in directory.iterdir())


# =========================================================================== defects
def test_unwritable_ground_truth_fails_before_writing_the_graph(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Defect: the graph was written, then the ground truth failed, leaving the graph behind."""
    gt = tmp_path / "missing" / "gt.g2o"
    code, out, err = run_cli(capsys, "generate", "city", *SMALL_CITY, "-o", tmp_path / "g.g2o",
                             "--ground-truth", gt)
    assert _files(tmp_path) == []  # the defect: g.g2o was left behind
    assert code == 2 and out == ""
    assert err.startswith(f"hybridpgo: error: {gt}: cannot write --ground-truth: directory")
    assert "does not exist" in err


def test_a_failure_while_writing_leaves_every_output_untouched(
        capsys: pytest.CaptureFixture[str], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """All or nothing: when a later output fails, the earlier ones are not renamed into place
    (an existing file keeps its content) and no temporary file is left."""
    import hybridpgo.generate

    def broken(path: object, *args: object, **kwargs: object) -> None:
        raise FormatError("cannot write the file: disk full", str(path))

    monkeypatch.setattr(hybridpgo.generate, "write_ground_truth", broken)
    graph = tmp_path / "g.g2o"
    graph.write_text("old graph\n")
    code, _, err = run_cli(capsys, "generate", "grid", *SMALL_GRID, "-o", graph,
                           "--ground-truth", tmp_path / "gt.g2o")
    assert code == 2 and "disk full" in err
    assert graph.read_text() == "old graph\n"
    assert _files(tmp_path) == ["g.g2o"]


@pytest.mark.parametrize("second", ["same", "dot-slash", "outliers-out"])
def test_two_outputs_naming_one_file_are_refused(capsys: pytest.CaptureFixture[str],
                                                 tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 second: str) -> None:
    """Defect: ``-o X --ground-truth X`` silently overwrote the graph with the ground truth."""
    monkeypatch.chdir(tmp_path)
    Path("x.g2o").write_text("keep me\n")
    extra = {"same": ["--ground-truth", "x.g2o"],
             "dot-slash": ["--ground-truth", "./x.g2o"],
             "outliers-out": ["--outliers", "2", "--outliers-out", "x.g2o"]}[second]
    code, out, err = run_cli(capsys, "generate", "city", *SMALL_CITY, "-o", "x.g2o", *extra)
    assert code == 2 and out == ""
    assert re.match(r"hybridpgo: error: \S*x\.g2o: -o/--output and --\S+ name the same file", err)
    assert Path("x.g2o").read_text() == "keep me\n"
    assert _files(tmp_path) == ["x.g2o"]


def test_gps_every_zero_means_no_gps(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Defect: ``--gps-every 0`` was a usage error instead of "no GPS"."""
    path = tmp_path / "c.g2o"
    code, _, err = run_cli(capsys, "generate", "city", *SMALL_CITY, "--gps-every", "0", "-o",
                           path)
    assert code == 0, err
    assert read_graph(path).num_gps == 0
    assert "EDGE_SE3_XYZ_PRIOR" not in path.read_text()
    code, _, err = run_cli(capsys, "generate", "city", *SMALL_CITY, "--gps-every", "-1", "-o",
                           path)
    assert code == 2 and "--gps-every" in err


def test_generate_city_help_shows_the_city_options(capsys: pytest.CaptureFixture[str]) -> None:
    """Defect: ``generate city --help`` showed the generic ``generate`` help."""
    code, out, _ = run_cli(capsys, "generate", "city", "--help")
    assert code == 0 and out.startswith("usage: hybridpgo generate city")
    for option in ("--preset", "--poses", "--gps-every", "--outliers", "--outliers-out",
                   "--near-miss-fraction", "--ground-truth", "--seed"):
        assert option in out
    assert "--rot-sigma" not in out
    code, out, _ = run_cli(capsys, "generate", "grid", "--help")
    assert code == 0 and out.startswith("usage: hybridpgo generate grid")
    for option in ("--preset", "--poses", "--3d", "--rot-sigma", "--trans-sigma", "--p-loop",
                   "--loop-radius", "--street-spacing", "--outliers", "--ground-truth"):
        assert option in out
    code, out, _ = run_cli(capsys, "generate", "--help")
    assert code == 0 and "city" in out and "grid" in out
    code, _, err = run_cli(capsys, "generate")
    assert code == 2 and "KIND" in err


def test_grid_help_states_the_library_defaults(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(capsys, "generate", "grid", "--help")
    assert code == 0
    text = " ".join(out.split())
    p = GridParams()
    for phrase in (f"default {p.num_poses}", f"{p.rot_sigma_rad:.4f} for m3500",
                   f"(default {p.trans_sigma_m:.4f})", f"(default {p.p_loop:g};",
                   f"(default {p.loop_radius_m:g})", f"{grid_module._SIDE_2D:g} sqrt(N) in 2D",
                   f"{grid_module._SIDE_3D:g} N^(1/3) in 3D",
                   f"exp(-d^2 / (2 x {p.loop_scale_m:g}^2)) within {p.loop_radius_m:g} m"):
        assert phrase in text, phrase


def test_noisify_refuses_to_overwrite_its_input(capsys: pytest.CaptureFixture[str],
                                                tmp_path: Path) -> None:
    """Defect: ``noisify X -o X`` replaced its input."""
    path = tmp_path / "g.g2o"
    assert run_cli(capsys, "generate", "grid", *SMALL_GRID, "-o", path)[0] == 0
    before = path.read_bytes()
    code, _, err = run_cli(capsys, "noisify", path, "-o", path)
    assert code == 2 and "is the input file" in err
    assert path.read_bytes() == before


def test_toro_output_with_gps_is_refused_before_any_work(capsys: pytest.CaptureFixture[str],
                                                         tmp_path: Path) -> None:
    code, _, err = run_cli(capsys, "generate", "city", "--gps-every", "10", "-o",
                           tmp_path / "c.graph")
    assert code == 2 and "TORO files cannot hold GPS" in err
    assert _files(tmp_path) == []


# =========================================================================== grid
def test_generate_grid_writes_se2_and_its_ground_truth(capsys: pytest.CaptureFixture[str],
                                                       tmp_path: Path) -> None:
    out_file, gt = tmp_path / "m.g2o", tmp_path / "m_gt.g2o"
    code, out, err = run_cli(capsys, "generate", "grid", "--preset", "m3500b", *SMALL_GRID,
                             "--seed", "4", "-o", out_file, "--ground-truth", gt)
    assert code == 0, err
    assert "m3500b, seed 4" in out and "2D, 300 poses" in out
    g, truth = read_graph(out_file), read_graph(gt)
    assert g.is_2d and truth.is_2d
    assert {ln.split()[0] for ln in out_file.read_text().splitlines()} == {"VERTEX_SE2",
                                                                           "EDGE_SE2"}
    # same constraints; the truth's vertices fit them far better than the dead reckoning
    np.testing.assert_array_equal(g.edge_nodes, truth.edge_nodes)
    assert energy(truth) < 0.1 * energy(g)
    # deterministic: a second run writes the same bytes
    again = tmp_path / "again.g2o"
    assert run_cli(capsys, "generate", "grid", "--preset", "m3500b", *SMALL_GRID, "--seed", "4",
                   "-o", again)[0] == 0
    assert again.read_bytes() == out_file.read_bytes()


def test_generate_grid_3d_and_options(capsys: pytest.CaptureFixture[str],
                                      tmp_path: Path) -> None:
    path = tmp_path / "g3.g2o"
    code, _, err = run_cli(capsys, "generate", "grid", "--3d", *SMALL_GRID, "--nx", "4",
                           "--rot-sigma", "0", "--trans-sigma", "0", "--p-loop", "0.5",
                           "--loop-radius", "1", "-o", path, "--ground-truth",
                           tmp_path / "gt.g2o")
    assert code == 0, err
    g = read_graph(path)
    assert not g.is_2d and g.num_nodes == 300
    t = read_graph(tmp_path / "gt.g2o").translations
    assert t.max() <= 4 and np.unique(t[:, 2]).size > 1
    # noise-free: the file's dead reckoning is the truth, every constraint is met
    np.testing.assert_allclose(g.translations, t, atol=1e-9)
    code, _, err = run_cli(capsys, "generate", "grid", "--nz", "3", "-o", path)
    assert code == 2 and "nz is for 3D grids" in err


# =========================================================================== city size, outliers
def test_generate_city_poses_sets_the_size(capsys: pytest.CaptureFixture[str],
                                           tmp_path: Path) -> None:
    path = tmp_path / "c.g2o"
    code, out, err = run_cli(capsys, "generate", "city", "--preset", "paris1", "--poses", "3000",
                             "--gps-every", "100", "-o", path)
    assert code == 0, err
    g = read_graph(path)
    assert g.num_nodes == 3000 and g.num_gps == 30
    assert "paris1, seed 0" in out


@pytest.mark.parametrize("kind", ["city", "grid"])
def test_outliers_file_lists_the_false_edges(capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                             kind: str) -> None:
    size = SMALL_CITY if kind == "city" else SMALL_GRID
    out_file, gt = tmp_path / "g.g2o", tmp_path / "g_gt.g2o"
    code, out, err = run_cli(capsys, "generate", kind, *size, "--outliers", "6", "-o", out_file,
                             "--ground-truth", gt)
    assert code == 0, err
    csv_file = tmp_path / "g_gt.outliers.csv"  # default: next to the ground truth
    assert f"outliers      {csv_file} (6 false loop closures: 3 random, 3 near misses)" in out
    with csv_file.open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6
    g, truth = read_graph(out_file), read_graph(gt)
    index = np.array([int(r["edge_index"]) for r in rows])
    ids = np.array([[int(r["id_a"]), int(r["id_b"])] for r in rows])
    np.testing.assert_array_equal(g.node_ids[g.edge_nodes[index]], ids)
    # the listed edges are the ones the truth does not satisfy
    from hybridpgo.energy import constraint_energies

    e = constraint_energies(truth)[0]
    worst = np.argsort(e)[-6:]
    assert set(worst.tolist()) == set(index.tolist())
    # without a ground truth the list goes next to the graph; or where --outliers-out says
    other = tmp_path / "h.g2o"
    assert run_cli(capsys, "generate", kind, *size, "--outliers", "2", "-o", other)[0] == 0
    assert (tmp_path / "h.outliers.csv").is_file()
    named = tmp_path / "list.csv"
    assert run_cli(capsys, "generate", kind, *size, "--outliers", "2", "--near-miss-fraction",
                   "0", "-o", other, "--outliers-out", named)[0] == 0
    with named.open() as fh:
        assert [r["kind"] for r in csv.DictReader(fh)] == ["random", "random"]
