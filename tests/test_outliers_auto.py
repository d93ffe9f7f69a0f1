"""``robust="auto"`` (hybridpgo.solvers.robust): the outlier test, the re-solve and what they
report; the outlier generators (patterns, false GPS fixes) and their command-line options."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
from tolerances import FLOAT64_IDENTITY, ONLINE_REFINED, SPARSE_VS_DENSE_GN

from hybridpgo.energy import energy
from hybridpgo.generate import (
    OUTLIER_PATTERNS,
    add_gps_outliers,
    add_pattern_outliers,
    generate_city,
    generate_grid,
    scale_city,
    write_gps_outliers,
)
from hybridpgo.graph import PoseGraph
from hybridpgo.io import read_graph, write_graph
from hybridpgo.solvers import AutoConfig, GaussNewtonConfig, HybridConfig, config_for, optimize
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.hybrid import solve_hybrid
from hybridpgo.solvers.robust import (
    LEVEL,
    THRESHOLD_SIGMAS,
    _keep_solvable,
    check_consistency,
    exact_resolver,
    odometry_tree,
    resolve,
)

if TYPE_CHECKING:
    from hybridpgo.online import OnlineConfig, OnlineSolver
    from hybridpgo.solvers.config import RobustName
    from hybridpgo.solvers.result import SolveResult

#: Least squares converged to 1e-12 from two starts reach the same poses to this (metres).
SAME_OPTIMUM_M = 1e-6


def _grid(seed: int = 0, n: int = 400) -> object:
    return generate_grid("m3500", seed=seed, num_poses=n)


def _lm(graph: PoseGraph, start: tuple[np.ndarray, np.ndarray]) -> SolveResult:
    return solve_exact(graph, *start, GaussNewtonConfig(max_iterations=300,
                                                       energy_tolerance=1e-12))


def _rejected(res: object, graph: PoseGraph) -> tuple[np.ndarray, np.ndarray]:
    rows = res.stats["outliers"]["rejected_constraints"]  # type: ignore[attr-defined]
    edges = np.zeros(graph.num_edges, bool)
    gps = np.zeros(graph.num_gps, bool)
    for r in rows:
        (edges if r["kind"] == "edge" else gps)[r["index"]] = True
    return edges, gps


# --------------------------------------------------------------------------- the test
def test_the_test_is_blind_to_the_information_scale_of_an_overconfident_file() -> None:
    """A clean graph passes, and passes identically with its information 100x overconfident
    (same optimum, every χ² x100: the estimated scale absorbs it)."""
    made = _grid()
    g = made.graph
    ref = _lm(g, (made.truth_rotations, made.truth_translations))
    v = check_consistency(g, ref.rotations, ref.translations)
    assert not v.inconsistent
    assert 0.5 < v.scale < 2.0  # correct information: about 1
    assert v.sigmas.max() < THRESHOLD_SIGMAS
    loud = dataclasses.replace(g, edge_information=g.edge_information * 100.0)
    w = check_consistency(loud, ref.rotations, ref.translations)
    assert w.scale == pytest.approx(100.0 * v.scale, rel=1e-9)
    np.testing.assert_allclose(w.sigmas, v.sigmas, rtol=1e-9, atol=0)
    assert not w.inconsistent


def test_a_hugely_overconfident_clean_file_is_re_solved_and_kept() -> None:
    """Information 1000x overconfident: the scale is beyond the level (the test cannot tell
    that from a folded map), the re-solve runs, rejects nothing, and least squares is kept."""
    made = _grid()
    g = made.graph
    loud = dataclasses.replace(g, edge_information=g.edge_information * 1e3)
    ls = _lm(loud, (made.truth_rotations, made.truth_translations))
    v = check_consistency(loud, ls.rotations, ls.translations)
    assert v.misfit and not v.outliers.any()
    res = resolve(loud, ls, exact_resolver(GaussNewtonConfig()))
    assert res.rotations is ls.rotations and res.translations is ls.translations
    o = res.stats["outliers"]
    assert o["inconsistent"] and o["rejected"] == 0 and o["rounds"] >= 1


def test_an_underconfident_file_is_tested_against_its_stated_information() -> None:
    """Information 1000x too small: the scale is 1e-3, the sigmas are the stated ones (never
    inflated by dividing by a scale below 1), so the clean graph passes."""
    made = _grid()
    g = made.graph
    ref = _lm(g, (made.truth_rotations, made.truth_translations))
    quiet = dataclasses.replace(g, edge_information=g.edge_information * 1e-3)
    v = check_consistency(quiet, ref.rotations, ref.translations)
    assert v.scale < 1e-2
    assert not v.inconsistent
    assert v.sigmas.max() < THRESHOLD_SIGMAS / 10


def test_a_tree_cannot_be_tested() -> None:
    made = _grid(n=60)
    g = made.graph
    tree = odometry_tree(g)
    chain = dataclasses.replace(g, edge_nodes=g.edge_nodes[tree],
                                edge_rotations=g.edge_rotations[tree],
                                edge_translations=g.edge_translations[tree],
                                edge_information=g.edge_information[tree])
    v = check_consistency(chain, g.rotations, g.translations)
    assert math.isnan(v.scale) and not v.inconsistent


def test_many_false_closures_fold_the_map_and_the_scale_gives_them_away() -> None:
    """With 100 false closures on 400 poses the least-squares optimum hides them (no single
    error stands out) but its scale is far beyond the level."""
    made = _grid()
    g, _ = add_pattern_outliers(made.graph, made.truth_translations, 100, "random", seed=3)
    ls = _lm(g, (g.rotations, g.translations))
    v = check_consistency(g, ls.rotations, ls.translations)
    assert v.scale > LEVEL and v.misfit and v.inconsistent


# --------------------------------------------------------------------------- the re-solve
def test_clean_graph_is_unchanged_by_the_default() -> None:
    """The default pipeline (robust='auto') returns least squares' result bit for bit."""
    made = _grid(seed=2)
    a = optimize(made.graph)
    b = optimize(made.graph, robust="none")
    np.testing.assert_array_equal(a.rotations, b.rotations)
    np.testing.assert_array_equal(a.translations, b.translations)
    np.testing.assert_array_equal(a.energy_history, b.energy_history)
    o = a.stats["outliers"]
    assert not o["inconsistent"] and o["rejected"] == 0 and o["rejected_constraints"] == []
    assert "outliers" not in b.stats


@pytest.mark.parametrize("pattern", OUTLIER_PATTERNS)
def test_false_closures_are_rejected_and_the_result_is_the_clean_optimum(pattern: str) -> None:
    """Exactly the false closures are rejected, and the result is the least-squares optimum
    of the rest: the clean graph's optimum (the oracle: LM on the clean graph from the truth)."""
    made = _grid(seed=1)
    g0 = made.graph
    g, out = add_pattern_outliers(g0, made.truth_translations, 20, pattern, seed=4)
    res = optimize(g)
    edges, gps = _rejected(res, g)
    np.testing.assert_array_equal(edges, out.mask(g.num_edges))
    assert not gps.any()
    ref = _lm(g0, (made.truth_rotations, made.truth_translations))
    assert energy(g0, res.rotations, res.translations) == pytest.approx(
        ref.final_energy, rel=SPARSE_VS_DENSE_GN)
    assert res.final_energy == pytest.approx(energy(g0, res.rotations, res.translations),
                                             rel=FLOAT64_IDENTITY)
    err = np.abs(res.translations - res.translations[0]
                 - (ref.translations - ref.translations[0])).max()
    assert err < SAME_OPTIMUM_M
    o = res.stats["outliers"]
    assert o["inconsistent"] and o["rejected"] == 20
    assert all(r["sigmas"] > THRESHOLD_SIGMAS for r in o["rejected_constraints"])


def test_false_gps_fixes_are_rejected() -> None:
    made = generate_city(None, seed=1, num_poses=600, gps_every=5)
    g, gout = add_gps_outliers(made.graph, 4, seed=2)
    res = optimize(g)
    edges, gps = _rejected(res, g)
    assert not edges.any()
    np.testing.assert_array_equal(gps, gout.mask(g.num_gps))
    keep = ~gout.mask(g.num_gps)
    clean = dataclasses.replace(g, gps_nodes=g.gps_nodes[keep],
                                gps_positions=g.gps_positions[keep],
                                gps_information=g.gps_information[keep])
    ref = _lm(clean, (res.rotations, res.translations))
    assert res.final_energy == pytest.approx(ref.final_energy, rel=SPARSE_VS_DENSE_GN)


def test_every_solver_gives_robust_auto_the_same_meaning() -> None:
    """The exact solver and the hybrid solver (with its polish) reject the same closures as
    the default pipeline."""
    made = _grid(seed=3)
    g, out = add_pattern_outliers(made.graph, made.truth_translations, 15, "local", seed=5)
    want = out.mask(g.num_edges)
    exact = solve_exact(g, config=GaussNewtonConfig(robust="auto"))
    np.testing.assert_array_equal(_rejected(exact, g)[0], want)
    hybrid = solve_hybrid(g, HybridConfig(robust="auto", sweeps=5, polish=True))
    np.testing.assert_array_equal(_rejected(hybrid, g)[0], want)
    assert energy(made.graph, exact.rotations, exact.translations) == pytest.approx(
        energy(made.graph, hybrid.rotations, hybrid.translations), rel=1e-8)


def _online(graph: PoseGraph, config: OnlineConfig,
            first: tuple[np.ndarray, np.ndarray] | None = None) -> OnlineSolver:
    """The online solver fed ``graph`` frame by frame, 4 updates per frame (``first``: the
    first pose's initial pose, default identity)."""
    from hybridpgo.online import OnlineSolver
    from hybridpgo.online.replay import feed_frame, make_stream

    s = OnlineSolver(config)
    st = make_stream(graph)
    for k in range(st.num_frames):
        if k == 0 and first is not None:
            s.add_pose(int(graph.node_ids[st.order[0]]), None, first)
        else:
            feed_frame(s, st, k)
        s.update(None, 4)
    return s


@pytest.mark.parametrize("robust", ["auto", "none"])
def test_online_refine_gives_robust_auto_the_same_meaning(robust: RobustName) -> None:
    """The online mode's whole-map solve (``OnlineSolver.refine``) under the default
    ``robust="auto"`` ends at the clean graph's optimum, as the batch solvers do; with
    ``"none"`` the false closures fold it.  The stream is a 2D graph's: its least-squares
    optimum is a fold whose scale is beyond the level counted over 3 degrees of freedom per
    constraint, as the batch solvers count them, but not over 6 (the map's 3D form)."""
    from hybridpgo.online import OnlineConfig

    made = _grid(seed=3, n=200)
    g0 = made.graph
    g, _ = add_pattern_outliers(g0, made.truth_translations, 10, "random", seed=5)
    s = _online(g, OnlineConfig(robust=robust))  # the default configuration, worker included
    s.refine(100)
    s.close()
    out = s.to_graph()
    np.testing.assert_array_equal(out.node_ids, g0.node_ids)
    ref = _lm(g0, (made.truth_rotations, made.truth_translations))
    e = energy(g0, out.rotations, out.translations)
    if robust == "auto":
        assert e == pytest.approx(ref.final_energy, rel=SPARSE_VS_DENSE_GN)
    else:
        assert e > 10.0 * ref.final_energy


def _arrival(graph: PoseGraph, edges: np.ndarray) -> np.ndarray:
    """The stream's arrival indices of the graph's edges ``edges`` (sorted)."""
    from hybridpgo.online.replay import make_stream

    order = make_stream(graph).edges
    where = np.empty_like(order)
    where[order] = np.arange(order.shape[0])
    return np.sort(where[edges])


@pytest.mark.parametrize("robust", ["auto", "none"])
def test_the_online_worker_rejects_false_closures_as_they_arrive(robust: RobustName) -> None:
    """The default online solver (worker included; deterministic with ``background_join``):
    each answer of the worker is tested, the false loop closures are rejected as they arrive
    (the frames stop relaxing them), and the end of the stream is the clean graph's optimum;
    with ``"none"`` the closures fold the map."""
    from hybridpgo.online import OnlineConfig

    made = _grid(seed=3, n=200)
    g0 = made.graph
    g, out = add_pattern_outliers(g0, made.truth_translations, 10, "random", seed=5)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    start = np.array([30.0, -20.0, 0.0])
    s = _online(g, OnlineConfig(robust=robust, background_join=25), (turn, start))
    assert s.join_refine(timeout=120.0)
    edges, gps = s.outliers()
    s.close()
    o = s.to_graph()
    ref = _lm(g0, (made.truth_rotations, made.truth_translations))
    e = energy(g0, o.rotations, o.translations)
    if robust == "auto":
        np.testing.assert_array_equal(edges, _arrival(g, np.flatnonzero(out.mask(g.num_edges))))
        assert gps.size == 0
        assert e == pytest.approx(ref.final_energy, rel=ONLINE_REFINED)
        assert s.energy() == pytest.approx(e, rel=FLOAT64_IDENTITY)  # rejected: left out
        # the gauge: the first pose stays where the stream started it (the re-solve's answer
        # is moved back rigidly)
        np.testing.assert_allclose(o.translations[0], start, atol=SAME_OPTIMUM_M)
        np.testing.assert_allclose(o.rotations[0], turn, atol=SAME_OPTIMUM_M)
    else:
        assert edges.size == 0
        assert e > 10.0 * ref.final_energy


def test_a_thorough_screening_finishes_a_capped_solve(monkeypatch: pytest.MonkeyPatch) -> None:
    """The worker's map (in this process) of a stream with false closures, its incremental
    solve stopped by the time cap at every request: an ordinary answer holds too little to be
    screened; the thorough one (``join_refine``) finishes the solve by LM and rejects exactly
    the false closures."""
    from test_online import _worker_map

    from hybridpgo.online import OnlineConfig, worker

    made = _grid(seed=3, n=200)
    g, out = add_pattern_outliers(made.graph, made.truth_translations, 10, "random", seed=5)
    s = _online(g, OnlineConfig(background_refine=False, robust="none"))
    monkeypatch.setattr(worker, "SOLVE_CAP_S", 0.0)
    mp = _worker_map(s, ("auto", None))
    arrays, meta = mp.solve(20)
    assert meta["m_held"] < meta["m"] and arrays["rejected_m"].size == 0
    arrays, meta = mp.solve(20, thorough=True)
    assert meta["thorough"] and meta["m_held"] == meta["m"]
    np.testing.assert_array_equal(arrays["rejected_m"],
                                  _arrival(g, np.flatnonzero(out.mask(g.num_edges))))


@pytest.mark.parametrize("preset", ["m3500", "grid3d"])
def test_online_refine_of_a_clean_map_is_least_squares(preset: str) -> None:
    """Without outliers ``refine()`` under ``"auto"`` leaves the poses ``"none"`` does, bit for
    bit (the test passes the least-squares optimum unchanged), on a planar map (solved and
    tested as 2D) and a 3D one."""
    from hybridpgo.graph import planar_data
    from hybridpgo.online import OnlineConfig

    made = generate_grid(preset, seed=4, num_poses=120)
    poses = {}
    robust: RobustName
    for robust in ("auto", "none"):  # no worker: the same estimate before both solves
        s = _online(made.graph, OnlineConfig(background_refine=False, robust=robust))
        assert planar_data(s.to_graph()) == (preset == "m3500")
        s.refine(100)
        poses[robust] = s.estimate()
    ref = _lm(made.graph, (made.truth_rotations, made.truth_translations))
    e = energy(made.graph, *poses["auto"])
    assert e == pytest.approx(ref.final_energy, rel=ONLINE_REFINED)
    for a, b in zip(poses["auto"], poses["none"], strict=True):
        np.testing.assert_array_equal(a, b)


def test_rejecting_keeps_the_graph_connected_and_anchored() -> None:
    """A rejected bridge is kept (least inconsistent first); so is a part's last GPS reading."""
    made = _grid(n=40)
    g = made.graph
    keep = np.ones(g.num_edges, bool)
    bridge = int(np.flatnonzero((g.edge_nodes[:, 0] == 19) & (g.edge_nodes[:, 1] == 20))[0])
    cut = (np.minimum(g.edge_nodes[:, 0], g.edge_nodes[:, 1]) < 20) & (
        np.maximum(g.edge_nodes[:, 0], g.edge_nodes[:, 1]) >= 20)
    keep[cut] = False
    sigmas = np.full(g.num_edges, 50.0)
    sigmas[bridge] = 8.0  # the least inconsistent of the crossing edges
    _keep_solvable(g, keep, np.zeros(0, bool), sigmas, np.zeros(0))
    assert keep[bridge] and keep.sum() == g.num_edges - cut.sum() + 1


def test_odometry_tree_prefers_consecutive_ids_in_file_order() -> None:
    made = _grid(n=50)
    g = made.graph
    dup = dataclasses.replace(  # a false duplicate of odometry edge (9, 10), after the real one
        g, edge_nodes=np.concatenate([g.edge_nodes, [[9, 10]]]),
        edge_rotations=np.concatenate([g.edge_rotations, np.eye(3)[None]]),
        edge_translations=np.concatenate([g.edge_translations, [[5.0, 0, 0]]]),
        edge_information=np.concatenate([g.edge_information, g.edge_information[:1]]))
    tree = odometry_tree(dup)
    ends = dup.edge_nodes[tree]
    assert tree.size == g.num_nodes - 1
    assert np.all(np.abs(ends[:, 1] - ends[:, 0]) == 1)
    assert dup.num_edges - 1 not in tree


# --------------------------------------------------------------------------- options
def test_robust_option_values() -> None:
    assert AutoConfig().robust == "auto"
    assert GaussNewtonConfig().robust == "none" and HybridConfig().robust == "none"
    assert config_for("exact").robust == "auto"  # type: ignore[union-attr]
    assert config_for("hybrid").robust == "auto"  # type: ignore[union-attr]
    assert config_for("exact", robust="cauchy").robust == "cauchy"  # type: ignore[union-attr]
    with pytest.raises(ValueError, match="robust_scale applies to a named kernel"):
        GaussNewtonConfig(robust="auto", robust_scale=2.0)
    assert HybridConfig(robust="auto").kernel == "none"
    assert GaussNewtonConfig(robust="huber").kernel == "huber"


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _cli(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    from hybridpgo.cli import main

    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_lists_the_rejected_constraints(capsys: pytest.CaptureFixture[str],
                                            tmp_path: Path) -> None:
    made = generate_city(None, seed=1, num_poses=600, gps_every=5)
    g, out = add_pattern_outliers(made.graph, made.truth_translations, 6, "random", seed=1)
    g, gout = add_gps_outliers(g, 2, seed=1)
    src = tmp_path / "in.g2o"
    write_graph(g, src)
    res_path = tmp_path / "out.g2o"
    rej_path = tmp_path / "rejected.csv"
    code, text, err = _cli(capsys, "optimize", src, "-o", res_path, "--rejected-out", rej_path,
                           "--json", "-q")
    assert code == 0, err
    summary = json.loads(text)
    rows = summary["result"]["outliers"]["rejected_constraints"]
    assert sorted(r["index"] for r in rows if r["kind"] == "edge") == out.edges.tolist()
    assert sorted(r["index"] for r in rows if r["kind"] == "gps") == gout.readings.tolist()
    lines = src.read_text().splitlines()
    for r in rows:  # the line named is the constraint's own, with its file ids
        fields = lines[r["line"] - 1].split()
        ids = [int(fields[1]), int(fields[2])] if r["kind"] == "edge" else [int(fields[1])]
        assert ids == [r["id_a"], r["id_b"]][:len(ids)]
    table = _csv_rows(rej_path)
    assert [(t["kind"], int(t["index"]), t["line"]) for t in table] == [
        (r["kind"], r["index"], str(r["line"])) for r in rows]
    code, text, err = _cli(capsys, "optimize", src, "-o", res_path, "-q")
    assert code == 0, err
    assert "outliers" in text and "8 rejected (6 relative, 2 GPS)" in text


# --------------------------------------------------------------------------- generators
def test_pattern_outliers_follow_the_patterns() -> None:
    made = _grid(n=500)
    g0 = made.graph
    for pattern in OUTLIER_PATTERNS:
        g, out = add_pattern_outliers(g0, made.truth_translations, 25, pattern, seed=9)
        assert g.num_edges == g0.num_edges + 25 and out.num_outliers == 25
        ends = g.edge_nodes[out.edges].astype(np.int64)
        gap = ends[:, 1] - ends[:, 0]
        assert np.all(gap >= 2)
        if pattern.startswith("local"):
            assert np.all(gap <= 20)
        zt = g.edge_translations[out.edges]
        if pattern.endswith("grouped"):  # groups of 10 consecutive pairs, one measurement
            _, group, sizes = np.unique(zt, axis=0, return_inverse=True, return_counts=True)
            assert sorted(sizes.tolist()) == [5, 10, 10]
            for k in range(sizes.size):
                e = ends[group.ravel() == k]
                e = e[np.argsort(e[:, 0])]
                np.testing.assert_array_equal(np.diff(e, axis=0),
                                              np.ones((e.shape[0] - 1, 2), np.int64))
        else:  # one measurement each
            assert np.unique(zt, axis=0).shape[0] == 25
        assert np.all(np.abs(zt[:, 2]) == 0.0)  # a planar graph gets planar measurements


def test_gps_outliers_jump_tens_of_metres(tmp_path: Path) -> None:
    made = generate_city(None, seed=1, num_poses=600, gps_every=5)
    g, out = add_gps_outliers(made.graph, 7, seed=3)
    assert out.num_outliers == 7 and np.unique(out.readings).size == 7
    jump = g.gps_positions - made.graph.gps_positions
    moved = np.flatnonzero(np.abs(jump).sum(axis=1) > 0)
    np.testing.assert_array_equal(moved, out.readings)
    length = np.linalg.norm(jump[moved], axis=1)
    assert np.all((length >= 20.0) & (length <= 60.0))
    assert np.all(jump[moved, 2] == 0.0)
    path = tmp_path / "gps.csv"
    write_gps_outliers(path, g, out)
    rows = _csv_rows(path)
    assert [int(r["gps_index"]) for r in rows] == out.readings.tolist()
    assert [int(r["id"]) for r in rows] == g.node_ids[g.gps_nodes[out.readings]].tolist()
    with pytest.raises(ValueError, match=r"num_outliers must be in 0\.\.120"):
        add_gps_outliers(made.graph, 121)


def test_cli_generate_gps_outliers_and_patterns(capsys: pytest.CaptureFixture[str],
                                                tmp_path: Path) -> None:
    out = tmp_path / "c.g2o"
    code, _, err = _cli(capsys, "generate", "city", "--poses", "500", "--gps-every", "5",
                           "--gps-outliers", "3", "--outliers", "12", "--outlier-pattern",
                           "random-grouped", "-o", out)
    assert code == 0, err
    assert len(_csv_rows(tmp_path / "c.gps_outliers.csv")) == 3
    g = read_graph(out)
    made = generate_city(None, seed=0, gps_every=5, gps_outliers=3, num_outliers=12,
                         outlier_pattern="random-grouped", **scale_city(None, 500))
    np.testing.assert_array_equal(g.gps_positions, made.graph.gps_positions)
    kinds = {r["kind"] for r in _csv_rows(tmp_path / "c.outliers.csv")}
    assert kinds == {"aliased_random_grouped"}
    code, _, err = _cli(capsys, "generate", "grid", "--outliers", "5", "--outlier-pattern",
                        "local", "--near-miss-fraction", "0.3", "-o", tmp_path / "g.g2o")
    assert code == 2 and "--near-miss-fraction: only for --outlier-pattern mixed" in err


def test_planar_data_in_3d_form_are_tested_as_planar() -> None:
    """A planar graph written in 3D form (``is_2d`` False) gets the 2D file's verdict: its
    out-of-plane errors are exactly 0 at the optimum, so counting them as degrees of freedom
    would halve the scale and hide the 10 false loop closures (scale 174 against 347)."""
    made = _grid(seed=3, n=200)
    g0 = made.graph
    g, _ = add_pattern_outliers(g0, made.truth_translations, 10, "random", seed=5)
    lifted = dataclasses.replace(g, is_2d=False)
    res = solve_exact(lifted, None, None, GaussNewtonConfig(max_iterations=100, robust="auto"))
    assert res.stats["outliers"]["rejected"] == 10
    ref = _lm(g0, (made.truth_rotations, made.truth_translations))
    e = energy(g0, res.rotations, res.translations)
    assert e == pytest.approx(ref.final_energy, rel=SPARSE_VS_DENSE_GN)


def test_gps_scale_counts_the_degrees_of_freedom_of_the_readings() -> None:
    """The GPS scale is the median χ² over the median of χ²(d): d = 3, or 2 for planar data
    (readings at z = 0 have no height error); both medians are χ²'s own."""
    from scipy.stats import chi2

    from hybridpgo.solvers import robust

    assert robust._CHI2_3_MEDIAN == pytest.approx(chi2(3).median(), rel=FLOAT64_IDENTITY)
    assert robust._CHI2_2_MEDIAN == pytest.approx(chi2(2).median(), rel=FLOAT64_IDENTITY)
    rng = np.random.default_rng(7)
    for dof in (2, 3):
        s = 4.0 * rng.chisquare(dof, 200_000)  # errors twice the stated sigma
        # the sample median of 2e5 draws is within 1% of the true one (> 10 standard errors)
        assert robust._gps_scale(s, dof) == pytest.approx(4.0, rel=0.01)
        assert abs(robust._gps_scale(s, 5 - dof) - 4.0) > 0.4  # the other d is far off
    made = _grid(seed=3, n=40)
    assert robust._gps_dof(made.graph) == 2 and robust._gps_dof(
        dataclasses.replace(made.graph, edge_translations=made.graph.edge_translations + 0.1)
    ) == 3
