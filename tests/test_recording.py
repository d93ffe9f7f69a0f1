"""The solvers' ``iterate`` hook and the Rerun recorder (hybridpgo.recording)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo.solvers import HybridConfig, solve_hybrid
from hybridpgo.solvers.config import GaussNewtonConfig, Progress
from hybridpgo.solvers.gauss_newton import solve_exact


class _Frames:
    def __init__(self) -> None:
        self.frames: list[tuple[Progress, np.ndarray, np.ndarray]] = []

    def __call__(self, p: Progress, rot: np.ndarray, trans: np.ndarray) -> None:
        self.frames.append((p, rot.copy(), trans.copy()))


def test_iterate_sees_every_sweep_and_polish_iteration_and_changes_nothing() -> None:
    graph, _, _ = random_graph(np.random.default_rng(21), n=10, extra=6, gps=2)
    cfg = HybridConfig(sweeps=4, polish=True)
    plain = solve_hybrid(graph, cfg)
    seen = _Frames()
    progress: list[Progress] = []
    hooked = solve_hybrid(graph, cfg, progress=progress.append, iterate=seen)
    np.testing.assert_array_equal(hooked.rotations, plain.rotations)
    np.testing.assert_array_equal(hooked.translations, plain.translations)
    assert [f[0] for f in seen.frames] == progress  # the same points, the same reports
    phases = [f[0].phase for f in seen.frames]
    assert phases == ["sweeps"] * 5 + ["polish"] * (hooked.stats["polish_iterations"] + 1)
    # each frame's poses have the energy the solver reported there
    from hybridpgo.energy import energy

    for p, rot, trans in seen.frames:
        assert energy(graph, rot, trans) == pytest.approx(p.energy, rel=1e-12)
    np.testing.assert_array_equal(seen.frames[-1][1], hooked.rotations)
    np.testing.assert_array_equal(seen.frames[-1][2], hooked.translations)


def test_iterate_of_the_exact_solver() -> None:
    graph, _, _ = random_graph(np.random.default_rng(22), n=8, extra=4)
    seen = _Frames()
    res = solve_exact(graph, config=GaussNewtonConfig(), iterate=seen)
    assert [f[0].iteration for f in seen.frames] == list(range(res.iterations + 1))
    np.testing.assert_array_equal(seen.frames[-1][2], res.translations)


def test_residual_colors_run_from_brown_to_red() -> None:
    from hybridpgo.recording import residual_colors

    c = residual_colors(np.array([1e-3, 1.0, 1e3, np.inf]))
    assert c.dtype == np.uint8 and c.shape == (4, 3)
    assert c[0].tolist() == [0x3B, 0x1D, 0x0E] and c[3].tolist() == [0xFF, 0x1A, 0x1A]
    assert c[0, 0] < c[1, 0] < c[2, 0] <= c[3, 0]
    assert residual_colors(np.zeros(0)).shape == (0, 3)
    assert residual_colors(np.array([2.0, 2.0])).tolist() == [[0xFF, 0x1A, 0x1A]] * 2


def test_recorder_abort_leaves_nothing(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from hybridpgo.recording import RerunRecorder

    graph, _, _ = random_graph(np.random.default_rng(23), n=5, extra=2)
    rec = RerunRecorder(graph, tmp_path / "x.rrd")
    rec(Progress("sweeps", 0, 1, 1.0, 1.0), graph.rotations, graph.translations)
    rec.abort()
    assert list(tmp_path.iterdir()) == []
    rec = RerunRecorder(graph, tmp_path / "y.rrd")
    rec(Progress("exact", 0, 1, 1.0), graph.rotations, graph.translations)
    rec.close()
    assert [p.name for p in tmp_path.iterdir()] == ["y.rrd"] and rec.frames == 1


@pytest.mark.parametrize("early", [True, False], ids=["early try", "every start"])
def test_iterate_of_the_default_pipeline_sees_every_start_and_the_winner(early: bool) -> None:
    from hybridpgo.energy import energy
    from hybridpgo.solvers.auto import solve_auto
    from hybridpgo.solvers.config import AutoConfig

    graph, _, _ = random_graph(np.random.default_rng(24), n=10, extra=6, gps=2)
    # the early try certifies this graph at its first start; without it every start runs
    cfg = AutoConfig(certify_first=early)
    plain = solve_auto(graph, cfg)
    seen = _Frames()
    res = solve_auto(graph, cfg, iterate=seen)
    np.testing.assert_array_equal(res.translations, plain.translations)
    starts = [f[0].detail for f in seen.frames if f[0].phase == "start"]
    cands = res.stats["candidates"]
    assert starts == [k for k, v in cands.items() if ", no sweeps" not in k
                      and k != "certified start"
                      and not str(v.get("error", "")).startswith("start:")]
    assert len(starts) == (1 if early else 3)
    for p, rot, trans in seen.frames:
        assert energy(graph, rot, trans) == pytest.approx(p.energy, rel=1e-12)
    winner = [f for f in seen.frames if f[0].phase == "polish"
              and f[0].detail == res.stats["start"]]
    np.testing.assert_array_equal(winner[-1][2], res.translations)
