"""``correction="pcg"`` and ``monotone`` (:mod:`hybridpgo.solvers.hybrid._correction`):
the O(N + M) products with J, J^T and 𝔅(H) against the dense twin, the gradient against finite
differences, CG against the exact Gauss-Newton step (and the batch of every constraint, III-F),
the energy test, the fixed point at the optimum, and the options."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import naive
import numpy as np
import pytest
from graphs import random_graph
from tolerances import CENTRAL_DIFF, CENTRAL_DIFF_STEP, FLOAT64_IDENTITY, SAME_EQUATION

from hybridpgo._tree_kernels import globals_from_locals
from hybridpgo.graph import PoseGraph
from hybridpgo.solvers import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, _correction

#: One sweep of a fixed-point method at a converged optimum changes E by at most this (relative).
FIXED_POINT = 1e-9


def _graph(seed: int, gps: int = 0) -> PoseGraph:
    graph, _, _ = random_graph(np.random.default_rng(seed), n=12, extra=9, gps=gps,
                               rot_scale=0.4, noise=0.1)
    return graph


def _dense(solver: HybridSolver) -> tuple[np.ndarray, np.ndarray]:
    """Dense whitened J (rows: constraints in index order; columns: 6 per tree node) and r
    from the naive twins, at the solver's state (robust weights folded in)."""
    tree, graph, prob = solver.tree, solver.graph, solver.problem
    grot, gtr = naive.tree_globals(tree.parent, solver.state.rot, solver.state.trans)
    domains, jacs, res = [], [], []
    for c in range(tree.num_constraints):
        if c < graph.num_edges:
            a, b = (int(v) for v in graph.edge_nodes[c])
            nodes, signs = naive.tree_domain(tree.parent, a, b)
            jac, r = naive.relative_jacobian(grot, gtr, a, b, graph.edge_rotations[c],
                                             graph.edge_translations[c], prob.edge_lt[c],
                                             nodes, signs)
            if solver.config.robust != "none":  # IRLS whitening sqrt(w) L^T, Cauchy
                delta = solver.config.robust_delta
                sw = np.sqrt(1.0 / (1.0 + float(r @ r) / delta**2))
                jac, r = sw * jac, sw * r
        else:
            n = int(graph.gps_nodes[c - graph.num_edges])
            nodes, _ = naive.tree_domain(tree.parent, tree.root, n)
            jac, r = naive.gps_jacobian(grot, gtr, n, graph.gps_positions[c - graph.num_edges],
                                        prob.gps_lt[c - graph.num_edges], nodes)
        domains.append(nodes)
        jacs.append(jac)
        res.append(r)
    return naive.stack_jacobian(domains, jacs, res, list(range(tree.num_tree_nodes)))


def _linearization(solver: HybridSolver) -> tuple[np.ndarray, ...]:
    topo = solver.topology
    nt, nc = topo.parent.shape[0], topo.ends.shape[0]
    yr, yt = np.empty((nt, 3, 3)), np.empty((nt, 3))
    globals_from_locals(topo.order, topo.parent, solver.state.rot, solver.state.trans, yr, yt)
    amat, res = np.empty((nc, 6, 6)), np.empty((nc, 6))
    _correction.linearize_all(solver.problem, topo.ends, yr, yt, amat, res)
    return yr, yt, amat, res


def _row_mask(solver: HybridSolver) -> np.ndarray:
    """Rows of the stacked (C, 6) arrays that exist (GPS readings have 3)."""
    m = solver.graph.num_edges
    mask = np.ones((solver.num_constraints, 6), bool)
    mask[m:, 3:] = False
    return mask


@pytest.mark.parametrize(("gps", "robust"), [(0, "none"), (3, "none"), (2, "cauchy")])
def test_products_match_the_dense_twin(gps: int, robust: str) -> None:
    graph = _graph(4, gps)
    solver = HybridSolver(graph, HybridConfig(init="tree", robust=robust))  # type: ignore[arg-type]
    solver.run(1)
    jd, rd = _dense(solver)
    topo, m = solver.topology, graph.num_edges
    yr, yt, amat, res = _linearization(solver)
    mask = _row_mask(solver)
    np.testing.assert_allclose(res[mask], rd, rtol=0, atol=FLOAT64_IDENTITY * np.abs(rd).max())
    rng = np.random.default_rng(1)
    nt = topo.parent.shape[0]
    v = rng.normal(size=(nt, 6))
    v[solver.tree.root] = 0.0
    jv = np.empty((solver.num_constraints, 6))
    _correction.jacobian_product(topo, m, yr, yt, amat, v, np.empty((nt, 6)), jv)
    want = jd @ v.reshape(-1)
    np.testing.assert_allclose(jv[mask], want, rtol=0, atol=1e-12 * np.abs(want).max())
    assert not jv[~mask].any()
    y = np.zeros((solver.num_constraints, 6))
    y[mask] = rng.normal(size=int(mask.sum()))
    jty = np.empty((nt, 6))
    _correction.transpose_product(topo, m, yr, yt, amat, y, jty)
    want = jd.T @ y[mask]
    np.testing.assert_allclose(jty.reshape(-1), want, rtol=0, atol=1e-12 * np.abs(want).max())
    blocks = np.empty((nt, 6, 6))
    _correction.block_diagonal(topo, m, yr, yt, amat, blocks)
    h = jd.T @ jd
    for i in range(nt):
        want = h[6 * i : 6 * i + 6, 6 * i : 6 * i + 6]
        assert np.abs(blocks[i] - want).max() <= 1e-12 * np.abs(h).max(), i


def test_the_gradient_matches_finite_differences() -> None:
    """``J^T r = -dE/dδ / 2`` for the right perturbations ``T_i <- T_i Exp(δ_i)`` of the locals."""
    solver = HybridSolver(_graph(7, gps=2), HybridConfig(init="tree"))
    solver.run(1)
    topo = solver.topology
    yr, yt, amat, res = _linearization(solver)
    nt = topo.parent.shape[0]
    grad = np.empty((nt, 6))
    _correction.transpose_product(topo, solver.problem.num_edges, yr, yt, amat, res, grad)
    state = solver.state
    rot0, tr0 = state.rot.copy(), state.trans.copy()
    fd = np.zeros((nt, 6))
    for i in range(nt):
        if topo.parent[i] < 0:
            continue
        for k in range(6):
            xi = np.zeros(6)
            xi[k] = CENTRAL_DIFF_STEP
            e = []
            for sgn in (1.0, -1.0):
                state.rot[i], state.trans[i] = naive.retract(rot0[i], tr0[i], sgn * xi, 1.0)
                e.append(solver.energy())
                state.rot[:], state.trans[:] = rot0, tr0
            fd[i, k] = -(e[0] - e[1]) / (2 * CENTRAL_DIFF_STEP) / 2
    assert np.abs(grad - fd).max() <= CENTRAL_DIFF * (1 + np.abs(fd).max())


@pytest.mark.parametrize("gps", [0, 3])
def test_enough_cg_iterations_give_the_gauss_newton_step(gps: int) -> None:
    """CG to convergence = least squares ``J x ~ r`` (eq. 14) = the batch of every constraint
    (eq. 37 with B_C = 0, III-F)."""
    solver = HybridSolver(_graph(5, gps), HybridConfig(init="tree", damping=0.0))
    solver.run(1)
    jd, rd = _dense(solver)
    nt = solver.tree.num_tree_nodes
    keep = np.ones(6 * nt, bool)
    keep[6 * solver.tree.root : 6 * solver.tree.root + 6] = False
    want = np.zeros(6 * nt)
    want[keep] = naive.gauss_newton_step(jd[:, keep], rd)
    x, done = _correction.gauss_newton_step(solver.problem, solver.state, solver.topology,
                                            6 * nt, 0.0)
    assert 0 < done <= 6 * nt
    scale = np.abs(want).max()
    assert np.abs(x.reshape(-1) - want).max() <= SAME_EQUATION * scale
    nodes, xb = solver.batch_step(np.arange(solver.num_constraints), tau=0.0, damping=0.0)
    assert np.abs(x[nodes] - xb).max() <= SAME_EQUATION * scale


def test_a_correction_lowers_the_energy_or_is_not_taken() -> None:
    solver = HybridSolver(_graph(9, gps=2), HybridConfig(init="tree"))
    solver.run(1)
    e0 = solver.energy()
    rep = solver.correct(5)
    assert rep.iterations == 5 and rep.scale > 0
    assert rep.energy_before == pytest.approx(e0, rel=FLOAT64_IDENTITY)
    assert rep.energy_after == pytest.approx(solver.energy(), rel=FLOAT64_IDENTITY)
    assert rep.energy_after < e0
    # a step that cannot help (the energy of a translated state is made to always rise) is
    # dropped and the state left as it was
    r0, t0 = solver.state.rot.copy(), solver.state.trans.copy()
    calls = iter(range(10**6))
    rep = _correction.correct(solver.problem, solver.state, solver.topology, 5, 1e-6,
                              lambda: float(next(calls)))
    assert rep.scale == 0.0
    assert np.array_equal(solver.state.rot, r0) and np.array_equal(solver.state.trans, t0)


def _moved(graph: PoseGraph, **options: object) -> float:
    """Relative change of E in one sweep from the converged optimum (vertices in the file)."""
    opt = solve_exact(graph, config=GaussNewtonConfig(  # converged to rounding
        method="gn", energy_tolerance=0.0, step_tolerance=1e-15, max_iterations=20))
    at_opt = dataclasses.replace(graph, rotations=opt.rotations, translations=opt.translations)
    solver = HybridSolver(at_opt, HybridConfig(init="file", **options))  # type: ignore[arg-type]
    e0 = solver.energy()
    return abs(solver.run(1).energy_history[-1] - e0) / e0


def test_the_optimum_is_a_fixed_point_of_monotone_iterations() -> None:
    assert _moved(_graph(11), correction="pcg", monotone=True) <= FIXED_POINT


def test_the_optimum_is_no_fixed_point_of_the_paper_sweeps() -> None:
    """Not of the paper's sweep, nor of the paper's sweep followed by the correction."""
    graph = _graph(11)
    assert _moved(graph) > 1e3 * FIXED_POINT
    assert _moved(graph, correction="pcg") > FIXED_POINT


def test_monotone_iterations_never_raise_the_energy() -> None:
    graph = _graph(8, gps=2)
    res = HybridSolver(graph, HybridConfig(init="tree", correction="pcg", monotone=True)).run(8)
    assert np.all(np.diff(res.energy_history) <= 0.0)
    assert 0 <= res.stats["sweeps_undone"] <= 8


@pytest.mark.parametrize("options", [{"correction": "pcg"},
                                     {"correction": "pcg", "monotone": True}])
def test_corrected_sweeps_end_closer_to_the_optimum(options: dict[str, object]) -> None:
    graph = _graph(5)
    opt = solve_exact(graph).final_energy
    plain = HybridSolver(graph, HybridConfig(init="tree")).run(5).energy_history[-1]
    res = HybridSolver(graph, HybridConfig(init="tree", **options)).run(5)  # type: ignore[arg-type]
    assert res.energy_history[-1] - opt < 0.1 * (plain - opt)
    assert len(res.stats["correction_scales"]) == 5


def test_the_correction_supports_gps() -> None:
    graph = _graph(6, gps=3)
    plain = HybridSolver(graph, HybridConfig(init="tree")).run(5).energy_history[-1]
    res = HybridSolver(graph, HybridConfig(init="tree", correction="pcg")).run(5)
    assert res.energy_history[-1] < plain


@pytest.mark.parametrize("options", [
    {"correction": "cg"}, {"correction_iterations": 0}, {"correction_iterations": 2.0},
    {"monotone": True}, {"correction": "pcg", "monotone": 1},
])
def test_bad_correction_options_are_refused(options: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        HybridConfig(**options)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- command line
def _cli(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str]:
    from hybridpgo.cli import main

    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def test_the_cli_runs_corrected_sweeps(capsys: pytest.CaptureFixture[str], data_dir: Path,
                                       tmp_path: Path) -> None:
    from hybridpgo import energy, read_graph

    src = data_dir / "tinyGrid3D.g2o"
    outs = {}
    for extra in ([], ["--correction", "pcg", "--correction-iterations", "10"],
                  ["--correction", "pcg", "--monotone"]):
        out = tmp_path / f"out{len(extra)}.g2o"
        code, err = _cli(capsys, "optimize", src, "-o", out, "--solver", "hybrid", "--init",
                         "tree", "--sweeps", "3", "--quiet", *extra)
        assert code == 0, err
        g = read_graph(out)
        outs[len(extra)] = energy(g, g.rotations, g.translations)
    assert outs[4] < outs[0] and outs[3] < outs[0]


@pytest.mark.parametrize(("argv", "message"), [
    (["--solver", "exact", "--correction", "pcg"], "--correction: only for the hybrid solver"),
    (["--solver", "hybrid", "--correction-iterations", "0"],
     "--correction-iterations: must be"),
    (["--solver", "hybrid", "--correction", "cg"], "invalid choice"),
    (["--solver", "hybrid", "--monotone"], "monotone=True needs correction='pcg'"),
    (["--solver", "toro", "--monotone"], "--monotone: not an option of --solver toro"),
])
def test_the_cli_refuses_bad_correction_options(capsys: pytest.CaptureFixture[str],
                                                data_dir: Path, tmp_path: Path,
                                                argv: list[str], message: str) -> None:
    out = tmp_path / "out.g2o"
    try:
        code, err = _cli(capsys, "optimize", data_dir / "tinyGrid3D.g2o", "-o", out, *argv)
    except SystemExit as exc:  # argparse's own errors
        code, err = int(exc.code or 0), capsys.readouterr().err
    assert code == 2
    assert message in err
    assert not out.exists()
