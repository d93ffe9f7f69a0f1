"""The command line's user-tool outputs: ``info --residuals`` and the worst constraints,
``optimize --covariance`` and ``optimize --rerun``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from tolerances import COVARIANCE_ROUTES, FLOAT64_IDENTITY, SPARSE_VS_DENSE_GN

from hybridpgo.energy import residuals
from hybridpgo.io import read_graph
from hybridpgo.solvers.gauss_newton import normal_equations


# =========================================================================== info --residuals
def test_info_residuals_csv_matches_the_api(capsys: pytest.CaptureFixture[str], tiny: Path,
                                            tmp_path: Path) -> None:
    out_csv = tmp_path / "res.csv"
    code, out, err = run_cli(capsys, "info", tiny, "--residuals", out_csv, "--json")
    assert code == 0, err
    info = json.loads(out)
    graph = read_graph(tiny)
    res = residuals(graph)
    with out_csv.open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == graph.num_edges + graph.num_gps
    edges = [r for r in rows if r["kind"] == "edge"]
    assert [int(r["index"]) for r in edges] == list(range(graph.num_edges))
    np.testing.assert_array_equal([[int(r["id_a"]), int(r["id_b"])] for r in edges],
                                  res.edge_ids)
    # repr floats: the CSV round-trips the API's numbers exactly
    np.testing.assert_array_equal([float(r["chi2"]) for r in edges], res.edge_chi2)
    cols = ["e_tx", "e_ty", "e_tz", "e_rx", "e_ry", "e_rz"]
    np.testing.assert_array_equal([[float(r[c]) for c in cols] for r in edges], res.edge_error)
    np.testing.assert_array_equal([[float(r[f"w{k}"]) for k in range(1, 7)] for r in edges],
                                  res.edge_whitened)
    # the worst five, largest first, and the energy they come from
    order = np.argsort(-res.edge_chi2, kind="stable")[:5]
    assert [w["index"] for w in info["worst"]] == order.tolist()
    assert [w["chi2"] for w in info["worst"]] == res.edge_chi2[order].tolist()
    assert info["residuals_at"] == "file"
    assert sum(float(r["chi2"]) for r in rows) == pytest.approx(info["energy_file"],
                                                                rel=FLOAT64_IDENTITY)


def test_info_lists_the_worst_constraints(capsys: pytest.CaptureFixture[str],
                                          tiny: Path) -> None:
    code, out, err = run_cli(capsys, "info", tiny)
    assert code == 0, err
    res = residuals(read_graph(tiny))
    worst = int(np.argmax(res.edge_chi2))
    a, b = res.edge_ids[worst]
    first = out.split("worst chi2")[1].splitlines()[0]
    edge_lines = [k for k, text in enumerate(tiny.read_text().splitlines(), 1)
                  if text.startswith("EDGE")]
    assert f"edge {worst} ({a} -> {b}, line {edge_lines[worst]})  (at the file vertices)" in first


def test_graph_keeps_the_file_line_of_each_constraint(tmp_path: Path) -> None:
    path = tmp_path / "g.g2o"
    info = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"
    bad = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 -1"  # not SPD: dropped by 'skip'
    path.write_text("# a comment\nVERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
                    "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\nVERTEX_SE3:QUAT 2 2 0 0 0 0 0 1\n"
                    f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {info}\n\n"
                    f"EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 {bad}\n"
                    f"EDGE_SE3:QUAT 0 2 2 0 0 0 0 0 1 {info}\n"
                    "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n"
                    "EDGE_SE3_XYZ_PRIOR 2 0 2 0 0 1 0 0 1 0 1\n")
    with pytest.warns(UserWarning, match="line 7"):
        graph = read_graph(path, fix_information="skip")
    assert graph.edge_lines is not None and graph.edge_lines.tolist() == [5, 8]
    assert graph.gps_lines is not None and graph.gps_lines.tolist() == [10]
    moved = graph.with_poses(graph.rotations, graph.translations + 1.0)
    assert moved.edge_lines is not None and moved.edge_lines.tolist() == [5, 8]
    from hybridpgo.graph import PoseGraph

    built = PoseGraph(node_ids=graph.node_ids, rotations=graph.rotations,
                      translations=graph.translations, edge_nodes=graph.edge_nodes,
                      edge_rotations=graph.edge_rotations,
                      edge_translations=graph.edge_translations,
                      edge_information=graph.edge_information, edge_lines=[1, 2, 3])
    assert built.edge_lines is None  # not one per edge: dropped, never misattributed


def test_info_residuals_with_gps_to_stdout(capsys: pytest.CaptureFixture[str],
                                           tmp_path: Path) -> None:
    path = tmp_path / "gps.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                    "EDGE_SE3:QUAT 0 1 1.1 0 0 0 0 0 1 " + "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 "
                    "1 0 1\n"
                    "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n"
                    "EDGE_SE3_XYZ_PRIOR 1 0 1 0.5 0 4 0 0 4 0 4\n"
                    "EDGE_SE3_XYZ_PRIOR 0 0 0 0 0 1 0 0 1 0 1\n")
    code, out, err = run_cli(capsys, "info", path, "--residuals", "-")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("kind,index,id_a,id_b,chi2,")
    gps = [line.split(",") for line in lines if line.startswith("gps,")]
    assert [g[1:4] for g in gps] == [["0", "1", ""], ["1", "0", ""]]
    # pose 1 at (1, 0, 0), measured at (1, 0.5, 0) with information 4: e = (0, -0.5, 0)
    assert float(gps[0][4]) == pytest.approx(4 * 0.25, rel=FLOAT64_IDENTITY)
    assert [float(x) for x in gps[0][5:8]] == [0.0, -0.5, 0.0] and gps[0][8:11] == [""] * 3
    assert "worst chi2" in err  # the report went to stderr, the CSV to stdout


def test_info_residuals_of_a_file_without_vertices(capsys: pytest.CaptureFixture[str],
                                                  tiny: Path, tmp_path: Path) -> None:
    from hybridpgo.initialization import initial_locals
    from hybridpgo.tree import build_tree, global_poses

    isam = tmp_path / "tiny.txt"
    assert run_cli(capsys, "convert", tiny, isam)[0] == 0
    code, out, err = run_cli(capsys, "info", isam, "--json")
    assert code == 0, err
    info = json.loads(out)
    graph = read_graph(isam)
    tree = build_tree(graph, "bfs")
    res = residuals(graph, *global_poses(tree, *initial_locals(graph, tree, "tree")))
    assert info["residuals_at"] == "tree"
    assert info["worst"][0]["chi2"] == float(res.edge_chi2.max())


def test_info_residuals_may_not_overwrite_the_input(capsys: pytest.CaptureFixture[str],
                                                    tiny: Path) -> None:
    code, _, err = run_cli(capsys, "info", tiny, "--residuals", tiny)
    assert code == 2 and "--residuals" in err and "input" in err


# =========================================================================== --covariance
def _dense_cov(graph: object, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    ne = normal_equations(graph, rot, trans)  # type: ignore[arg-type]
    inv = np.linalg.inv(ne.hessian.toarray())
    out = np.zeros((len(rot), 6, 6))
    for k, n in enumerate(ne.free_nodes):
        out[n] = inv[6 * k:6 * k + 6, 6 * k:6 * k + 6]
    return out


def test_optimize_covariance_all_poses(capsys: pytest.CaptureFixture[str], tiny: Path,
                                       tmp_path: Path) -> None:
    out, npz = tmp_path / "o.g2o", tmp_path / "cov.npz"
    code, stdout, err = run_cli(capsys, "optimize", tiny, "-o", out, "--solver", "exact",
                                "--covariance", npz, "--json", "-q")
    assert code == 0, err
    assert json.loads(stdout)["covariance"] == {"path": str(npz), "poses": 9}
    data = np.load(npz)
    assert sorted(data.files) == ["cov", "fixed_ids", "ids", "tangent"]
    graph = read_graph(tiny)
    np.testing.assert_array_equal(data["ids"], graph.node_ids)
    np.testing.assert_array_equal(data["fixed_ids"], [graph.node_ids[0]])
    assert data["tangent"].tolist() == ["tx", "ty", "tz", "rx", "ry", "rz"]
    solved = read_graph(out)  # the written poses (repr precision)
    expected = _dense_cov(graph, solved.rotations, solved.translations)
    np.testing.assert_allclose(data["cov"], expected, rtol=0,
                               atol=SPARSE_VS_DENSE_GN * np.abs(expected).max())
    np.testing.assert_array_equal(data["cov"][0], 0.0)  # the gauge pose


def test_optimize_covariance_selected_poses(capsys: pytest.CaptureFixture[str], tiny: Path,
                                            tmp_path: Path) -> None:
    npz = tmp_path / "cov.npz"
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "-q",
                           "--covariance", npz, "--covariance-poses", "7,2..4,3")
    assert code == 0, err
    data = np.load(npz)
    np.testing.assert_array_equal(data["ids"], [7, 2, 3, 4])
    full = tmp_path / "all.npz"
    assert run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o2.g2o", "-q", "--covariance",
                   full, "--covariance-poses", "all")[0] == 0
    np.testing.assert_array_equal(np.load(full)["cov"][[7, 2, 3, 4]], data["cov"])


def test_optimize_covariance_every_pose_of_a_larger_graph(capsys: pytest.CaptureFixture[str],
                                                          tmp_path: Path) -> None:
    """Without --covariance-poses every pose is written, whatever the size (2 500 poses)."""
    from hybridpgo.covariance import marginal_covariances
    from hybridpgo.generate import generate_city
    from hybridpgo.io import write_graph

    src, out, npz = tmp_path / "c.g2o", tmp_path / "o.g2o", tmp_path / "cov.npz"
    write_graph(generate_city(seed=3, num_poses=2500).graph, src)
    code, stdout, err = run_cli(capsys, "optimize", src, "-o", out, "--solver", "exact",
                                "--covariance", npz, "--json", "-q")
    assert code == 0, err
    assert json.loads(stdout)["covariance"] == {"path": str(npz), "poses": 2500}
    solved = read_graph(out)
    sel = np.array([1, 700, 2499])  # the per-pose CHOLMOD route, an independent factorization
    expected = marginal_covariances(solved, None, None, sel, linear_solver="splu")
    np.testing.assert_allclose(np.load(npz)["cov"][sel], expected, rtol=0,
                               atol=COVARIANCE_ROUTES * np.abs(expected).max())


@pytest.mark.parametrize(("argv", "message"), [
    (["--covariance-poses", "3,99"], "--covariance-poses 99: "),
    (["--covariance-poses", "1..x"], "ranges like 0,5,10..20, got '1..x'"),
    (["--covariance-poses", "5..2"], "bad range '5..2'"),
])
def test_optimize_covariance_bad_poses(capsys: pytest.CaptureFixture[str], tiny: Path,
                                       tmp_path: Path, argv: list[str], message: str) -> None:
    out, npz = tmp_path / "o.g2o", tmp_path / "cov.npz"
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, "--covariance", npz, *argv)
    assert code == 2 and message in err, err
    assert not out.exists() and not npz.exists()


def test_optimize_covariance_checks(capsys: pytest.CaptureFixture[str], tiny: Path,
                                    tmp_path: Path) -> None:
    out = tmp_path / "o.g2o"
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, "--covariance-poses", "1")
    assert code == 2 and "--covariance-poses: give --covariance NPZ too" in err
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, "--covariance", tiny)
    assert code == 2 and "--covariance is the input file" in err
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, "--covariance", "-")
    assert code == 2 and "cannot go to standard output" in err
    assert not out.exists()


# =========================================================================== --rerun
def _recorded(path: Path) -> dict[str, int]:
    """Rows per entity path of a .rrd file (temporal data only)."""
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static or "iteration" not in chunk.timeline_names:
            continue
        counts[chunk.entity_path] = counts.get(chunk.entity_path, 0) + chunk.num_rows
    return counts


@pytest.mark.parametrize("solver", ["hybrid", "exact"])
def test_optimize_rerun_records_every_iteration(capsys: pytest.CaptureFixture[str], tiny: Path,
                                                tmp_path: Path, solver: str) -> None:
    pytest.importorskip("rerun")
    rrd = tmp_path / "run.rrd"
    extra = ["--sweeps", "3", "--polish"] if solver == "hybrid" else []
    code, out, err = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "--solver",
                             solver, "--rerun", rrd, "--json", "-q", *extra)
    assert code == 0, err
    summary = json.loads(out)
    r = summary["result"]
    # iteration 0 of each phase, then one frame per sweep / polish or exact iteration
    expected = (3 + 1 + r["polish_iterations"] + 1 if solver == "hybrid"
                else r["iterations"] + 1)
    assert summary["rerun"] == {"path": str(rrd), "iterations": expected}
    counts = _recorded(rrd)
    for entity in ("/graph/poses", "/graph/trajectory", "/graph/residuals", "/energy/total",
                   "/residuals/chi2_max", "/log"):
        assert counts.get(entity) == expected, (entity, counts)
    assert not any(p.name.startswith(".hybridpgo-") for p in tmp_path.iterdir())


def test_optimize_rerun_records_every_start_of_the_default_pipeline(
        capsys: pytest.CaptureFixture[str], tiny: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from hybridpgo.solvers.auto import solve_auto

    frames: list[str] = []
    solve_auto(read_graph(tiny), iterate=lambda p, r, t: frames.append(p.phase))
    assert {"start", "polish"} <= set(frames)
    rrd = tmp_path / "run.rrd"
    code, out, err = run_cli(capsys, "optimize", tiny, "-o", tmp_path / "o.g2o", "--rerun", rrd,
                             "--json", "-q")
    assert code == 0, err
    assert json.loads(out)["rerun"] == {"path": str(rrd), "iterations": len(frames)}
    counts = _recorded(rrd)
    assert counts.get("/graph/poses") == counts.get("/log") == len(frames)


def test_optimize_rerun_refusals(capsys: pytest.CaptureFixture[str], tiny: Path,
                                 tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out, rrd = tmp_path / "o.g2o", tmp_path / "run.rrd"
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, "--solver", "toro",
                           "--rerun", rrd)
    assert code == 2 and "--rerun records --solver auto, hybrid or exact, not --solver toro" in err
    monkeypatch.setattr("hybridpgo.recording.rerun_available", lambda: False)
    code, _, err = run_cli(capsys, "optimize", tiny, "-o", out, "--solver", "exact",
                           "--rerun", rrd)
    assert code == 2
    assert err.strip().splitlines()[-1] == ("hybridpgo: error: --rerun needs rerun-sdk, which "
                                            "is not installed: pip install hybridpgo[rerun]")
    assert not out.exists() and not rrd.exists()
    assert list(tmp_path.iterdir()) == []
