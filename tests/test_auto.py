"""The default pipeline (``--solver auto``, :mod:`hybridpgo.solvers.auto`): it reaches the LM
optimum, its status and stats say what happened, and it is the default of the library and CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from graphs import random_graph
from tolerances import FLOAT64_IDENTITY, OPTIMUM_RELATIVE

import hybridpgo
from hybridpgo import read_graph
from hybridpgo.cli import main
from hybridpgo.energy import energy
from hybridpgo.initialization import initial_locals
from hybridpgo.solvers import AutoConfig, GaussNewtonConfig, HybridConfig, Status, optimize
from hybridpgo.solvers.auto import solve_auto
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.tree import build_tree, global_poses

#: LM that runs to convergence: the reference optimum's solver.
TIGHT_LM = GaussNewtonConfig(max_iterations=300, energy_tolerance=1e-14)


def best_known(graph, truth=None) -> float:
    """Lowest LM energy over the starts truth (when known), file, chordal and tree."""
    starts = [truth] if truth is not None else []
    if graph.has_estimates:
        starts.append((graph.rotations, graph.translations))
    tree = build_tree(graph, "bfs")
    starts += [global_poses(tree, *initial_locals(graph, tree, k)) for k in ("chordal", "tree")]
    return min(solve_exact(graph, r, t, TIGHT_LM).final_energy for r, t in starts)


# ------------------------------------------------------------------------- config
@pytest.mark.parametrize("options, message", [
    ({"inits": ()}, "inits must be a non-empty tuple"),
    ({"inits": ("tree", "tree")}, "inits must be a non-empty tuple of distinct"),
    ({"inits": ("gps",)}, "inits must be a non-empty tuple"),
    ({"finalists": 0}, "finalists must be an integer >= 1"),
    ({"sweeps": -1}, "sweeps must be an integer >= 0"),
    ({"sweep_tolerance": float("nan")}, "sweep_tolerance must be a finite number >= 0"),
    ({"max_iterations": 1.5}, "max_iterations must be an integer >= 0"),
    ({"polish": True}, "polish: not an option of the default pipeline"),
    ({"sweeps": 101, "robust": "huber", "robust_scale": -1.0}, "robust_scale"),
    ({"tau0": 2.0}, "tau0 must be below 2"),
    ({"step": "cholesky"}, "step must be one of woodbury, givens"),
    ({"robust": "tukey"}, "robust must be one of auto, none, huber"),
    ({"large_poses": 1}, "large_poses must be an integer >= 2"),
    ({"large_inits": ()}, "large_inits must be a non-empty tuple"),
    ({"large_inits": ("chordal", "chordal")}, "large_inits must be a non-empty tuple of distinct"),
    ({"large_max_sweeps": -1}, "large_max_sweeps must be an integer >= 0"),
    ({"relaxation": 1}, "relaxation must be True or False"),
    ({"relaxation_iterations": 0}, "relaxation_iterations must be an integer >= 1"),
    ({"relaxation_angle": 0.0}, "relaxation_angle must be a finite number > 0"),
])
def test_auto_config_rejects_bad_values(options, message) -> None:
    with pytest.raises((ValueError, TypeError), match=message.replace("(", r"\(")):
        AutoConfig.from_options(**options)


def test_auto_config_nests_the_sweep_and_polish_configs() -> None:
    cfg = AutoConfig.from_options(tau0=0.5, step="givens", tree="mst", robust="huber",
                                  robust_scale=2.0, max_iterations=7, energy_tolerance=1e-9,
                                  sweeps=4)
    assert cfg == AutoConfig(
        sweeps=HybridConfig(sweeps=4, tau0=0.5, step="givens", tree="mst", robust="huber",
                            robust_scale=2.0),
        polish=GaussNewtonConfig(max_iterations=7, energy_tolerance=1e-9, robust="huber",
                                 robust_scale=2.0),
        certify_first=False)  # sweeps asked for are run
    assert AutoConfig.from_options(sweeps=0).certify_first  # LM from the start: it may certify
    assert AutoConfig.from_options(sweeps=4, certify_first=True).certify_first
    with pytest.raises(ValueError, match="inits must be a non-empty tuple"):
        AutoConfig(inits=["tree"])  # type: ignore[arg-type]  # the constructor takes tuples
    with pytest.raises(ValueError, match="sweeps must be a HybridConfig"):
        AutoConfig(sweeps=30)  # type: ignore[arg-type]
    hy = cfg.hybrid_config("chordal", 3)
    assert (hy.init, hy.sweeps, hy.tau0, hy.step, hy.tree, hy.robust, hy.robust_scale,
            hy.polish) == ("chordal", 3, 0.5, "givens", "mst", "huber", 2.0, False)
    # the nested defaults are the solvers' own: nothing is copied, so nothing can drift
    default = AutoConfig()
    for name in ("tau0", "tau_decay", "damping", "step", "tree", "gps_batch_size", "dmax",
                 "robust_scale"):
        assert getattr(default.sweeps, name) == getattr(HybridConfig(), name), name
    for name in ("method", "energy_tolerance", "initial_damping", "linear_solver",
                 "robust_scale"):
        assert getattr(default.polish, name) == getattr(GaussNewtonConfig(), name), name
    # but the pipeline's robust default is the outlier test, in both nested configs
    assert default.robust == default.sweeps.robust == default.polish.robust == "auto"


def test_auto_config_needs_one_robust_kernel() -> None:
    with pytest.raises(ValueError, match="same robust kernel"):
        AutoConfig(sweeps=HybridConfig(robust="cauchy"), polish=GaussNewtonConfig())
    with pytest.raises(ValueError, match="same robust kernel"):
        AutoConfig(sweeps=HybridConfig(robust="cauchy"),
                   polish=GaussNewtonConfig(robust="cauchy", robust_scale=1.0))


@pytest.mark.parametrize("name", ["huber", "cauchy", "geman_mcclure"])
def test_a_robust_name_means_the_same_scale_under_every_solver(name: str) -> None:
    """``--robust NAME`` without a scale gives the kernel's documented default scale to the
    default pipeline (sweeps and polish), the hybrid solver and the exact solver alike."""
    from hybridpgo._cost import ROBUST_DEFAULT_SCALE
    from hybridpgo.solvers import config_for

    want = ROBUST_DEFAULT_SCALE[name]
    auto = config_for("auto", robust=name)
    assert isinstance(auto, AutoConfig)
    hybrid = config_for("hybrid", robust=name, polish=True)
    exact = config_for("exact", robust=name)
    assert auto.sweeps.robust_delta == auto.polish.robust_delta == want
    assert hybrid.robust_delta == exact.robust_delta == want  # type: ignore[union-attr]
    explicit = config_for("auto", robust=name, robust_scale=want)
    assert isinstance(explicit, AutoConfig)
    assert explicit.sweeps.robust_delta == explicit.polish.robust_delta == want
    from hybridpgo.online import OnlineConfig

    online = OnlineConfig(robust=name)  # type: ignore[arg-type]
    assert online.robust_delta == want and online.kernel == name


@pytest.mark.parametrize("name", ["auto", "none"])
def test_auto_and_none_mean_the_same_under_every_solver(name: str) -> None:
    """``--robust auto`` (the default everywhere) and ``--robust none``: every solver's config
    says the same name, solves its iterations in least squares, and takes no scale."""
    from hybridpgo.online import OnlineConfig
    from hybridpgo.solvers import config_for

    auto = config_for("auto", robust=name)
    assert isinstance(auto, AutoConfig)
    hybrid = config_for("hybrid", robust=name)
    exact = config_for("exact", robust=name)
    online = OnlineConfig(robust=name)  # type: ignore[arg-type]
    assert isinstance(hybrid, HybridConfig) and isinstance(exact, GaussNewtonConfig)
    assert auto.robust == hybrid.robust == exact.robust == online.robust == name
    assert (auto.sweeps.kernel == auto.polish.kernel == hybrid.kernel == exact.kernel
            == online.kernel == "none")
    if name == "auto":  # the default of every solver that has robust kernels
        defaults = (config_for("auto"), config_for("hybrid"), config_for("exact"),
                    OnlineConfig())
        assert [c.robust for c in defaults] == ["auto"] * 4
        for method in ("auto", "hybrid", "exact"):
            with pytest.raises(ValueError, match="robust_scale applies to a named kernel"):
                config_for(method, robust="auto", robust_scale=2.0)
        with pytest.raises(ValueError, match="robust_scale applies to a named kernel"):
            OnlineConfig(robust="auto", robust_scale=2.0)


# ------------------------------------------------------------------------- the optimum
@pytest.mark.parametrize("seed, gps", [(0, 0), (1, 0), (2, 3), (3, 0)])
def test_default_reaches_the_optimum_on_random_graphs(seed: int, gps: int) -> None:
    graph, rot, trans = random_graph(np.random.default_rng(seed), n=30, extra=25, gps=gps,
                                     rot_scale=0.5, noise=0.1)
    result = optimize(graph)  # no method: the default pipeline
    assert result.method == "auto"
    assert result.status is Status.CONVERGED
    ref = best_known(graph, (rot, trans))
    assert result.final_energy <= ref * (1 + OPTIMUM_RELATIVE)
    assert result.final_energy == pytest.approx(energy(graph, result.rotations,
                                                       result.translations),
                                                rel=FLOAT64_IDENTITY)


@pytest.mark.parametrize("name", ["tinyGrid3D.g2o", "smallGrid3D.g2o", "w100_toro.graph"])
def test_default_reaches_the_optimum_on_the_test_files(data_dir: Path, name: str) -> None:
    if name.endswith(".graph"):
        with pytest.warns(UserWarning, match="EQUIV"):
            graph = read_graph(data_dir / name)
    else:
        graph = read_graph(data_dir / name)
    result = hybridpgo.optimize(graph)
    assert result.status is Status.CONVERGED
    assert result.final_energy <= best_known(graph) * (1 + OPTIMUM_RELATIVE)


# ------------------------------------------------------------------------- what it says
def test_status_and_stats_describe_the_run(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    result = solve_auto(graph, AutoConfig(certify=False))  # every start polished
    s = result.stats
    cands = s["candidates"]
    swept = [k for k in ("chordal", "tree", "file") if cands[k]["sweeps"]]
    assert list(cands) == ["chordal", "tree", "file"] + [f"{k}, no sweeps" for k in sorted(
        swept, key=lambda k: cands[k]["initial_energy"])]
    assert s["init"] in cands and s["finalists"][0] == min(
        cands, key=lambda k: cands[k]["energy_after_sweeps"])
    polished = [k for k, c in cands.items() if "final_energy" in c]
    assert sorted(polished) == sorted(s["finalists"]) == sorted(cands)  # default: all
    # the winner is the lowest polished energy, and the result is its trajectory
    kept = [k for k in polished if not cands[k]["polish_cut_at_budget"]]
    assert s["start"] == min(kept, key=lambda k: cands[k]["final_energy"])
    assert s["init"] == s["start"].split(",")[0]
    win = cands[s["start"]]
    assert result.final_energy == win["final_energy"]
    assert result.iterations == s["sweeps"] == win["sweeps"]
    assert result.energy_history[0] == win["initial_energy"]
    assert result.energy_history[result.iterations] == s["energy_after_sweeps"]
    assert len(result.energy_history) == 1 + s["sweeps"] + s["polish_iterations"]
    assert len(result.times) == len(result.energy_history)
    assert s["polish_status"] == result.status.value == "converged"
    # sweeps that raise E are undone and the polish accepts only decreases
    assert np.all(np.diff(result.energy_history) <= 0)
    for c in cands.values():
        assert c["sweeps"] <= c["sweeps_run"] <= AutoConfig().sweeps.sweeps
        assert c["energy_after_sweeps"] <= c["initial_energy"]
    assert s["init"] in s["reason"] and "converged" in s["reason"]
    json.dumps(result.summary())  # every stat is JSON-friendly


def test_no_file_start_without_vertices(tmp_path: Path, data_dir: Path) -> None:
    graph = read_graph(data_dir / "tinyGrid3D.g2o")
    isam = tmp_path / "tiny.txt"
    hybridpgo.write_graph(graph, isam, "isam")
    result = optimize(read_graph(isam), certify_first=False)  # every start that applies
    assert result.stats["skipped_inits"] == ["file"]
    assert [k for k in result.stats["candidates"] if "no sweeps" not in k] == ["chordal", "tree"]


def test_without_sweeps_the_pipeline_is_lm_from_the_start(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    result = optimize(graph, "auto", sweeps=0, init="tree", certify_first=False)
    direct = optimize(graph, "exact", init="tree")
    assert result.stats["init"] == "tree" and result.iterations == 0
    assert list(result.stats["candidates"]) == ["tree"]
    assert result.final_energy == pytest.approx(direct.final_energy, rel=FLOAT64_IDENTITY)
    np.testing.assert_allclose(result.translations, direct.translations, rtol=0,
                               atol=FLOAT64_IDENTITY * 10)


def test_sweeps_stop_when_they_stop_paying(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    cfg = AutoConfig(inits=("tree",), sweep_tolerance=0.2, sweeps=HybridConfig(sweeps=50),
                     certify_first=False)
    c = solve_auto(graph, cfg).stats["candidates"]["tree"]
    hist = optimize(graph, "hybrid", init="tree", sweeps=c["sweeps_run"]).energy_history
    drops = 1 - hist[1:] / hist[:-1]
    # every sweep but the last lowered E by >= 20%; the last by less (or raised it)
    assert np.all(drops[:-1] >= 0.2) and drops[-1] < 0.2
    assert c["sweeps_run"] < 50


def test_one_finalist_polishes_one_start(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    s = optimize(graph, "auto", finalists=1, certify_first=False).stats
    assert [k for k, c in s["candidates"].items() if "final_energy" in c] == [s["init"]]


def test_an_iteration_limit_shows_in_the_status(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    result = optimize(graph, "auto", max_iterations=1, sweeps=0)
    assert result.status is Status.MAX_ITERATIONS
    assert result.stats["polish_status"] == "max_iterations"
    assert "max_iterations" in result.stats["reason"]


# ------------------------------------------------------------------------- the API
def test_hybrid_by_name_is_still_the_papers_method(data_dir: Path) -> None:
    graph = read_graph(data_dir / "tinyGrid3D.g2o")
    result = optimize(graph, "hybrid")
    assert result.method == "hybrid" and result.iterations == 10
    assert "candidates" not in result.stats


def test_hybrid_options_without_a_method_name_the_fix(data_dir: Path) -> None:
    graph = read_graph(data_dir / "tinyGrid3D.g2o")
    with pytest.raises(TypeError, match=r"polish: not an option of the default pipeline.*"
                                        r"optimize\(graph, 'hybrid'"):
        optimize(graph, sweeps=10, polish=True)
    with pytest.raises(TypeError, match=r"finalist: not an option of the default pipeline"):
        optimize(graph, finalist=2)
    # sweeps means what --sweeps means on the command line: the most sweeps per start
    limited = optimize(graph, sweeps=1)
    assert limited.method == "auto"
    assert all(c["sweeps_run"] <= 1 for c in limited.stats["candidates"].values())
    with pytest.raises(ValueError, match="fields of its config"):
        optimize(graph, AutoConfig(), init="tree")


# ------------------------------------------------------------------------- the CLI
def _cli_json(capsys, *argv) -> dict:
    code = main([str(a) for a in argv] + ["--json", "-q"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


def test_cli_default_is_auto_and_matches_the_library(capsys, data_dir: Path,
                                                     tmp_path: Path) -> None:
    src = data_dir / "smallGrid3D.g2o"
    out = tmp_path / "o.g2o"
    s = _cli_json(capsys, "optimize", src, "-o", out)
    r = s["result"]
    lib = optimize(read_graph(src))
    assert s["solver"] == "auto" and r["method"] == "auto" and r["status"] == "converged"
    assert s["init"] == r["init"] == lib.stats["init"]
    assert s["energy_after"] == pytest.approx(lib.final_energy, rel=FLOAT64_IDENTITY)
    assert energy(read_graph(out)) == pytest.approx(lib.final_energy, rel=1e-8)  # 9 digits
    assert s["energy_after_sweeps"] == r["energy_after_sweeps"]
    assert s["reason"] == r["reason"]


def test_cli_auto_options(capsys, data_dir: Path, tmp_path: Path) -> None:
    src = data_dir / "smallGrid3D.g2o"
    s = _cli_json(capsys, "optimize", src, "-o", tmp_path / "o.g2o", "--init", "tree",
                  "--sweeps", "2", "--max-iterations", "3", "--tau0", "0.5")
    r = s["result"]
    assert list(r["candidates"]) in (["tree"], ["tree", "tree, no sweeps"])
    assert s["init"] == "tree"
    assert r["candidates"]["tree"]["sweeps_run"] <= 2 and r["polish_iterations"] <= 3


@pytest.mark.parametrize("argv, message", [
    (["--polish"], "--polish: --solver auto (the default) always polishes"),
    (["--tree", "toro"], "--tree toro: only for --solver toro"),
])
def test_cli_auto_refuses(capsys, data_dir: Path, tmp_path: Path, argv, message) -> None:
    out = tmp_path / "o.g2o"
    code = main(["optimize", str(data_dir / "tinyGrid3D.g2o"), "-o", str(out), *argv])
    _, err = capsys.readouterr()
    assert code == 2 and message in err and not out.exists()


def test_cli_text_summary_names_the_starts(capsys, data_dir: Path, tmp_path: Path) -> None:
    code = main(["optimize", str(data_dir / "tinyGrid3D.g2o"), "-o", str(tmp_path / "o.g2o")])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "(chosen by the pipeline)" in out and "starts " in out and "(polished)" in out
    assert "auto: start chordal" in err


def test_cli_progress_shows_each_phase(capsys, data_dir: Path, tmp_path: Path) -> None:
    code = main(["optimize", str(data_dir / "tinyGrid3D.g2o"), "-o", str(tmp_path / "o.g2o"),
                 "--progress", "--init", "tree", "--sweeps", "2"])
    _, err = capsys.readouterr()
    assert code == 0
    assert "auto: start tree" in err and "tree sweeps" in err and "tree polish (LM)" in err


def test_a_runner_up_polish_stops_at_its_budget(data_dir: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    import hybridpgo.solvers.auto as auto

    graph = read_graph(data_dir / "smallGrid3D.g2o")
    monkeypatch.setattr(auto, "MIN_FINALIST_ITERATIONS", 1)
    cfg = AutoConfig(inits=("tree", "chordal"), sweeps=HybridConfig(sweeps=0),
                     finalist_budget=0.01, certify=False)  # the runner-up is polished
    result = solve_auto(graph, cfg)
    s = result.stats
    assert s["finalists"] == ["chordal", "tree"]  # chordal starts far lower (E0 1189 vs 52044)
    tree = s["candidates"]["tree"]
    assert tree["polish_iterations"] == 1 and tree["polish_cut_at_budget"] is True
    assert tree["final_energy"] > result.final_energy
    assert s["init"] == "chordal" and "stopped at its budget" in s["reason"]
    assert result.status is Status.CONVERGED


def test_a_continued_polish_is_one_trajectory(data_dir: Path) -> None:
    from hybridpgo.solvers.auto import _continue

    graph = read_graph(data_dir / "smallGrid3D.g2o")
    first = solve_exact(graph, None, None, GaussNewtonConfig(max_iterations=2))
    second = solve_exact(graph, first.rotations, first.translations, GaussNewtonConfig())
    both = _continue(first, second)
    assert both.iterations == first.iterations + second.iterations
    np.testing.assert_array_equal(both.energy_history, np.concatenate(
        [first.energy_history, second.energy_history[1:]]))
    assert len(both.times) == len(both.energy_history) and np.all(np.diff(both.times) >= 0)
    assert both.final_energy == second.final_energy and both.status is second.status


def test_a_swept_start_is_also_polished_from_its_own_poses(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    cfg = AutoConfig(inits=("tree",), sweeps=HybridConfig(sweeps=3), sweep_tolerance=0.0,
                     finalist_budget=100.0, certify=False)  # the twin is polished
    cands = solve_auto(graph, cfg).stats["candidates"]
    swept, raw = cands["tree"], cands["tree, no sweeps"]
    assert swept["sweeps"] == 3 and raw["sweeps"] == raw["sweeps_run"] == 0
    assert raw["initial_energy"] == raw["energy_after_sweeps"] == swept["initial_energy"]
    direct = optimize(graph, "exact", init="tree",
                      max_iterations=AutoConfig().polish.max_iterations)
    assert raw["final_energy"] == pytest.approx(direct.final_energy, rel=FLOAT64_IDENTITY)
    assert raw["polish_iterations"] == direct.iterations
    off = solve_auto(graph, AutoConfig(inits=("tree",), sweeps=HybridConfig(sweeps=3),
                                       polish_unswept=False, certify_first=False))
    assert list(off.stats["candidates"]) == ["tree"]


# ------------------------------------------------------------------------- large graphs
@pytest.mark.parametrize("gps", [0, 3])
def test_large_graph_policy_one_start_no_sweeps_one_polish(gps: int) -> None:
    graph, rot, trans = random_graph(np.random.default_rng(7 + gps), n=30, extra=25, gps=gps,
                                     rot_scale=0.5, noise=0.1)
    assert AutoConfig().is_large(10**6) and not AutoConfig().is_large(graph.num_nodes)
    assert not AutoConfig(large_poses=None).is_large(10**9)
    full = optimize(graph)
    assert full.stats["policy"] == "full"
    large = optimize(graph, AutoConfig(large_poses=graph.num_nodes, certify_first=False))
    assert large.stats["policy"] == "large"
    assert large.stats["reason"].startswith("large-graph policy")
    assert list(large.stats["candidates"]) == ["chordal"]  # the first of large_inits
    assert large.stats["sweeps"] == 0 and large.stats["finalists"] == ["chordal"]
    assert large.status is Status.CONVERGED
    ref = best_known(graph, (rot, trans))
    assert large.final_energy <= ref * (1 + OPTIMUM_RELATIVE)
    # its start is the chordal relaxation's poses (no hybrid solver): E as the energy module's
    tree = build_tree(graph, "bfs")
    start = global_poses(tree, *initial_locals(graph, tree, "chordal"))
    assert large.stats["candidates"]["chordal"]["initial_energy"] == pytest.approx(
        energy(graph, *start), rel=FLOAT64_IDENTITY)


def test_large_graph_policy_falls_back_to_the_next_start() -> None:
    graph, _, _ = random_graph(np.random.default_rng(9), n=20, extra=10)
    cfg = AutoConfig(large_poses=2, large_inits=("file", "tree"), large_max_sweeps=2,
                     certify_first=False)
    res = optimize(graph, cfg)
    assert list(res.stats["candidates"]) == ["file"]
    assert res.stats["candidates"]["file"]["sweeps_run"] <= 2
    # without vertices the file start does not apply: the next one is used
    bare = dataclasses.replace(graph, has_estimates=False)
    res = optimize(bare, cfg)
    assert list(res.stats["candidates"]) == ["tree"] and res.stats["skipped_inits"] == ["file"]
