"""Robust kernels (docs/conventions.md#robust-kernels): rho and w, the weighted hybrid step, the
exact solver's
gradient, the robust energy against GTSAM, and 'none' leaving every result unchanged."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from graphs import random_graph
from ref_kernels import se3_exp, se3_log
from tolerances import CENTRAL_DIFF, CENTRAL_DIFF_STEP, FLOAT64_IDENTITY, SPARSE_VS_DENSE_GN

from hybridpgo import _cost
from hybridpgo.energy import constraint_energies, energy, robust_energy, robust_weights
from hybridpgo.graph import PoseGraph
from hybridpgo.solvers.config import ROBUST_NAMES, GaussNewtonConfig, HybridConfig, RobustName
from hybridpgo.solvers.gauss_newton import normal_equations, solve_exact
from hybridpgo.solvers.hybrid import HybridSolver, solve_hybrid
from hybridpgo.solvers.hybrid._dense import TINY
from hybridpgo.tree import global_poses

KERNELS = ("huber", "cauchy", "geman_mcclure")
#: Two exact solves of the same equation (dense twin vs Woodbury), relative to the step size.
SAME_EQUATION = 1e-9


def rho_reference(name: str, delta: float, s: float) -> float:
    """g2o's rho(s) written out independently of the kernel (docs/conventions.md#robust-kernels)."""
    d2 = delta * delta
    if name == "none":
        return s
    if name == "huber":
        return s if s <= d2 else 2 * delta * math.sqrt(s) - d2
    if name == "cauchy":
        return d2 * math.log(1 + s / d2)
    return d2 * s / (d2 + s)


def test_kernel_names_agree() -> None:
    assert ROBUST_NAMES == _cost.ROBUST_NAMES
    assert ROBUST_NAMES == RobustName.__args__  # type: ignore[attr-defined]


@pytest.mark.parametrize("name", ("none", *KERNELS))
@pytest.mark.parametrize("delta", [0.5, 1.0, 3.0])
def test_rho_and_weight_match_reference_and_finite_differences(name: str, delta: float) -> None:
    kind = ROBUST_NAMES.index(name)
    # both Huber regimes, the kink's neighbourhood (not on it), tiny and huge chi2
    for s in (1e-4, 0.3 * delta**2, 0.97 * delta**2, 1.03 * delta**2, 5 * delta**2, 40.0, 1e4):
        h = CENTRAL_DIFF_STEP * max(1.0, s)  # a relative step: rounding ~ eps |rho| / h
        rho, w = _cost.robust_cost(kind, delta, s)
        assert rho == pytest.approx(rho_reference(name, delta, s), rel=FLOAT64_IDENTITY)
        fd = (rho_reference(name, delta, s + h) - rho_reference(name, delta, s - h)) / (2 * h)
        assert w == pytest.approx(fd, rel=CENTRAL_DIFF, abs=CENTRAL_DIFF * 1e-3)
        assert 0 < w <= 1
    assert _cost.robust_cost(kind, delta, 0.0) == (0.0, 1.0)


def test_weights_fall_off_for_outliers() -> None:
    s = np.array([0.0, 1.0, 100.0, 1e6])
    for name in KERNELS:
        rho = np.empty(4)
        w = np.empty(4)
        _cost.robust_costs(ROBUST_NAMES.index(name), 1.0, s, rho, w)
        assert np.all(np.diff(w) < 0) or name == "huber"
        assert w[-1] < 1e-2
    assert robust_weights.__doc__


def test_bad_kernel_names_and_scales_are_rejected() -> None:
    for cls in (GaussNewtonConfig, HybridConfig):
        with pytest.raises(ValueError, match="robust must be one of none, huber"):
            cls(robust="tukey")  # type: ignore[arg-type]
        for bad in (0.0, -1.0, math.inf, math.nan, True):
            with pytest.raises(ValueError, match="robust_scale must be"):
                cls(robust="huber", robust_scale=bad)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- helpers
def _with_outliers(rng: np.random.Generator, graph: PoseGraph, k: int) -> PoseGraph:
    """``graph`` with k extra relative edges whose measurements are random (false loops)."""
    n = graph.num_nodes
    pairs = np.array([rng.choice(n, 2, replace=False) for _ in range(k)], np.int32)
    zr = np.array([se3_exp(np.r_[0, 0, 0, rng.normal(size=3)])[0] for _ in range(k)])
    zt = rng.normal(scale=3.0, size=(k, 3))
    return dataclasses.replace(
        graph, edge_nodes=np.concatenate([graph.edge_nodes, pairs]),
        edge_rotations=np.concatenate([graph.edge_rotations, zr]),
        edge_translations=np.concatenate([graph.edge_translations, zt]),
        edge_information=np.concatenate([graph.edge_information,
                                         graph.edge_information[:k]]))


def _perturbed(rng: np.random.Generator, graph: PoseGraph, size: float
               ) -> tuple[np.ndarray, np.ndarray]:
    rot = np.array(graph.rotations)
    trans = np.array(graph.translations)
    for i in range(graph.num_nodes):
        dr, dt = se3_exp(rng.normal(scale=size, size=6))
        trans[i] = trans[i] + rot[i] @ dt
        rot[i] = rot[i] @ dr
    return rot, trans


def _whitened(graph: PoseGraph, lt: list[np.ndarray], rot: np.ndarray, trans: np.ndarray
              ) -> list[np.ndarray]:
    """L^T e of every constraint (relative then GPS) from global poses (NumPy twin)."""
    out = []
    for c, (a, b) in enumerate(graph.edge_nodes):
        rab = rot[a].T @ rot[b]
        tab = rot[a].T @ (trans[b] - trans[a])
        zr, zt = graph.edge_rotations[c], graph.edge_translations[c]
        out.append(lt[c] @ se3_log(zr.T @ rab, zr.T @ (tab - zt)))
    for k in range(graph.num_gps):
        out.append(lt[graph.num_edges + k]
                   @ (trans[graph.gps_nodes[k]] - graph.gps_positions[k]))
    return out


def _dense_twin(solver: HybridSolver, h: float = 1e-6
                ) -> tuple[list[np.ndarray], list[np.ndarray], list[int]]:
    """Per constraint: the unweighted whitened Jacobian over the free tree nodes (central
    differences of the local transforms) and its residual ``-L^T e``; the free nodes."""
    tree = solver.tree
    g = solver.graph
    lt = [solver.problem.edge_lt[c] for c in range(g.num_edges)]
    lt += [solver.problem.gps_lt[k] for k in range(g.num_gps)]
    free = [i for i in range(tree.num_tree_nodes) if tree.parent[i] >= 0]
    rl, tl = solver.state.rot, solver.state.trans
    w0 = _whitened(g, lt, *global_poses(tree, rl, tl))
    jacs = [np.zeros((w.shape[0], 6 * len(free))) for w in w0]
    for col, i in enumerate(free):
        for k in range(6):
            sides = []
            for sgn in (1.0, -1.0):
                rot = rl.copy()
                trans = tl.copy()
                d = np.zeros(6)
                d[k] = sgn * h
                dr, dt = se3_exp(d)
                trans[i] = rot[i] @ dt + trans[i]
                rot[i] = rot[i] @ dr
                sides.append(_whitened(g, lt, *global_poses(tree, rot, trans)))
            for c in range(len(w0)):
                jacs[c][:, 6 * col + k] = (sides[0][c] - sides[1][c]) / (2 * h)
    return jacs, [-w for w in w0], free


def _weights(name: str, delta: float, residuals: list[np.ndarray], num_edges: int
             ) -> np.ndarray:
    """w_c = rho'(s_c) by central differences of the reference rho (GPS: 1)."""
    out = np.ones(len(residuals))
    for c in range(num_edges):
        s = float(residuals[c] @ residuals[c])
        h = CENTRAL_DIFF_STEP * max(1.0, s)
        out[c] = (rho_reference(name, delta, s + h) - rho_reference(name, delta, s - h)) / (2 * h)
    return out


# --------------------------------------------------------------------------- hybrid
@pytest.mark.parametrize("name", KERNELS)
def test_weighted_hybrid_step_equals_dense_twin(name: str) -> None:
    """x solves (w J^T J + B_c) x = w J^T r with 𝔅(H) = blockdiag(sum_c w_c J_c^T J_c) and
    B_c = 𝔅(H) - w_c 𝔅(J_c^T J_c) (docs/mathematics.md#hybrid-step,
    docs/conventions.md#robust-kernels), all built densely from finite differences."""
    rng = np.random.default_rng(11)
    clean, _, _ = random_graph(rng, n=9, extra=5, gps=2, rot_scale=0.4)
    graph = _with_outliers(rng, clean, 3)
    delta = 1.5
    mu = 1e-6
    cfg = HybridConfig(init="file", robust=name, robust_scale=delta, damping=mu)
    jacs, res, free = _dense_twin(HybridSolver(graph, cfg))
    w = _weights(name, delta, res, graph.num_edges)
    assert w.min() < 0.2  # the outliers are down-weighted
    col = {node: k for k, node in enumerate(free)}
    nf = 6 * len(free)
    bd = np.zeros((nf, nf))
    for c, jc in enumerate(jacs):
        bd += w[c] * np.where(_block_mask(nf), jc.T @ jc, 0.0)
    for c in range(graph.num_constraints):
        solver = HybridSolver(graph, cfg)
        np.testing.assert_allclose(
            _block_diagonal(solver, free), bd, rtol=0,
            atol=CENTRAL_DIFF * 100 * np.abs(bd).max())
        _jac, r, x = solver.probe(c)
        tree = solver.tree
        nodes = tree.path_node[tree.path_ptr[c]: tree.path_ptr[c + 1]]
        idx = np.concatenate([np.arange(6 * col[i], 6 * col[i] + 6) for i in nodes])
        jd = math.sqrt(w[c]) * jacs[c][:, idx]
        rd = math.sqrt(w[c]) * res[c]
        kr = rd.shape[0]
        np.testing.assert_allclose(r[:kr], rd, rtol=0, atol=CENTRAL_DIFF * np.abs(rd).max())
        bc = bd[np.ix_(idx, idx)] - np.where(_block_mask(idx.size), jd.T @ jd, 0.0)
        for k in range(nodes.size):
            blk = slice(6 * k, 6 * k + 6)
            jk = jd[:, blk]
            bc[blk, blk] += (mu * np.trace(bc[blk, blk]) / 6
                             + TINY * np.trace(jk.T @ jk)) * np.eye(6)
        x_dense = np.linalg.solve(jd.T @ jd + bc, jd.T @ rd)
        np.testing.assert_allclose(x.reshape(-1), x_dense, rtol=0,
                                   atol=CENTRAL_DIFF * 100 * np.abs(x_dense).max())


def _block_mask(n: int) -> np.ndarray:
    k = np.arange(n) // 6
    return k[:, None] == k[None, :]


def _block_diagonal(solver: HybridSolver, free: list[int]) -> np.ndarray:
    nf = 6 * len(free)
    out = np.zeros((nf, nf))
    for k, node in enumerate(free):
        out[6 * k: 6 * k + 6, 6 * k: 6 * k + 6] = solver.state.bdiag[node]
    return out


@pytest.mark.parametrize("name", KERNELS)
def test_weighted_batch_of_all_constraints_is_the_irls_step(name: str) -> None:
    """The all-constraint batch (paper eq. 37) with a kernel is the weighted GN (IRLS) step."""
    rng = np.random.default_rng(12)
    clean, _, _ = random_graph(rng, n=8, extra=5, gps=3, rot_scale=0.4)
    graph = _with_outliers(rng, clean, 2)
    solver = HybridSolver(graph, HybridConfig(init="file", robust=name, robust_scale=1.5))
    jacs, res, free = _dense_twin(solver)
    sw = np.sqrt(_weights(name, 1.5, res, graph.num_edges))
    jd = np.concatenate([s * j for s, j in zip(sw, jacs, strict=True)])
    rd = np.concatenate([s * r for s, r in zip(sw, res, strict=True)])
    x_irls = np.linalg.lstsq(jd, rd, rcond=None)[0].reshape(-1, 6)
    nodes, x = solver.batch_step(np.arange(graph.num_constraints), damping=0.0)
    pos = {node: k for k, node in enumerate(free)}
    got = np.zeros_like(x_irls)
    for node, xi in zip(nodes, x, strict=True):
        got[pos[int(node)]] = xi
    np.testing.assert_allclose(got, x_irls, rtol=0,
                               atol=CENTRAL_DIFF * 100 * np.abs(x_irls).max())


# --------------------------------------------------------------------------- exact solver
@pytest.mark.parametrize("name", KERNELS)
def test_exact_gradient_of_robust_energy_matches_finite_differences(name: str) -> None:
    """g = sum_c w_c J_c^T Omega_c e_c is half the gradient of E_rho (no 1/2)."""
    rng = np.random.default_rng(13)
    clean, _, _ = random_graph(rng, n=7, extra=4, gps=2, rot_scale=0.4)
    graph = _with_outliers(rng, clean, 2)
    rot, trans = _perturbed(rng, graph, 0.05)
    delta = 2.0
    ne = normal_equations(graph, rot, trans, robust=name, robust_scale=delta)
    e_rho, e_plain = robust_energy(graph, rot, trans, name, delta)
    assert ne.energy == pytest.approx(e_rho, rel=FLOAT64_IDENTITY)
    assert e_plain == pytest.approx(energy(graph, rot, trans), rel=FLOAT64_IDENTITY)
    assert e_rho < e_plain
    h = CENTRAL_DIFF_STEP
    fd = np.zeros_like(ne.gradient)
    for k, i in enumerate(ne.free_nodes):
        for j in range(6):
            vals = []
            for sgn in (1.0, -1.0):
                r2, t2 = rot.copy(), trans.copy()
                d = np.zeros(6)
                d[j] = sgn * h
                dr, dt = se3_exp(d)
                t2[i] = t2[i] + r2[i] @ dt
                r2[i] = r2[i] @ dr
                vals.append(robust_energy(graph, r2, t2, name, delta)[0])
            fd[6 * k + j] = (vals[0] - vals[1]) / (2 * h)
    scale = max(1.0, np.abs(fd).max())
    np.testing.assert_allclose(2 * ne.gradient, fd, rtol=0, atol=CENTRAL_DIFF * 10 * scale)
    # H = sum_c w_c J_c^T Omega_c J_c: the weighted sum of the plain per-constraint Hessians
    s, _ = constraint_energies(graph, rot, trans)
    w = np.array([_cost.robust_cost(ROBUST_NAMES.index(name), delta, v)[1] for v in s])
    h_sum = np.zeros(ne.hessian.shape)
    no_gps = {"gps_nodes": np.zeros(0, np.int32), "gps_positions": np.zeros((0, 3)),
              "gps_information": np.zeros((0, 3, 3))}
    for c in range(graph.num_edges):
        one = dataclasses.replace(graph, edge_nodes=graph.edge_nodes[c: c + 1],
                                  edge_rotations=graph.edge_rotations[c: c + 1],
                                  edge_translations=graph.edge_translations[c: c + 1],
                                  edge_information=graph.edge_information[c: c + 1], **no_gps)
        h_sum += w[c] * normal_equations(one, rot, trans, ne.free_nodes[:0]).hessian.toarray()
    gps_only = dataclasses.replace(graph, edge_nodes=np.zeros((0, 2), np.int32),
                                   edge_rotations=np.zeros((0, 3, 3)),
                                   edge_translations=np.zeros((0, 3)),
                                   edge_information=np.zeros((0, 6, 6)))
    h_sum += normal_equations(gps_only, rot, trans, ne.free_nodes[:0]).hessian.toarray()
    np.testing.assert_allclose(ne.hessian.toarray(), h_sum, rtol=0,
                               atol=SPARSE_VS_DENSE_GN * np.abs(h_sum).max())


@pytest.mark.parametrize("name", KERNELS)
def test_robust_lm_recovers_from_false_loop_closures(name: str) -> None:
    """With 3 random false loops, robust LM started at the truth stays near the clean optimum
    (plain LM is pulled away); the robust energy never rises; with the redescending kernels the
    outliers end with w < 0.1 and the inliers above."""
    rng = np.random.default_rng(14)
    clean, rot0, trans0 = random_graph(rng, n=20, extra=10, rot_scale=0.3, noise=0.02)
    graph = _with_outliers(rng, clean, 3)
    ref = solve_exact(clean, rot0, trans0)
    plain = solve_exact(graph, rot0, trans0)
    cfg = GaussNewtonConfig(robust=name, robust_scale=1.0)
    res = solve_exact(graph, rot0, trans0, cfg)
    err = np.linalg.norm(res.translations - ref.translations, axis=1).max()
    err_plain = np.linalg.norm(plain.translations - ref.translations, axis=1).max()
    # Huber is convex with a bounded influence, not redescending: it only reduces the pull
    assert err < (err_plain if name == "huber" else 0.05 * err_plain)
    assert np.all(np.diff(res.energy_history) <= 0)
    assert res.stats["robust"] == name
    assert res.stats["plain_energy"] == pytest.approx(
        energy(graph, res.rotations, res.translations), rel=FLOAT64_IDENTITY)
    assert res.final_energy == pytest.approx(
        robust_energy(graph, res.rotations, res.translations, name, 1.0)[0],
        rel=FLOAT64_IDENTITY)
    _, w = robust_weights(graph, res.rotations, res.translations, name, 1.0)
    m = clean.num_edges
    if name != "huber":  # Huber's weight decays like 1/sqrt(s) only: it does not classify
        assert np.all(w[m:] < 0.1) and np.all(w[:m] > 0.1)


def test_hybrid_polish_uses_the_kernel() -> None:
    rng = np.random.default_rng(15)
    clean, _, _ = random_graph(rng, n=12, extra=6, gps=2, rot_scale=0.3, noise=0.02)
    graph = _with_outliers(rng, clean, 2)
    cfg = HybridConfig(sweeps=5, polish=True, robust="cauchy", robust_scale=2.0)
    res = solve_hybrid(graph, cfg)
    st = res.stats
    assert res.method == "hybrid+polish"
    assert len(st["plain_energy_history"]) == res.energy_history.shape[0]
    assert res.final_energy == pytest.approx(
        robust_energy(graph, res.rotations, res.translations, "cauchy", 2.0)[0],
        rel=FLOAT64_IDENTITY)
    assert st["plain_energy"] == pytest.approx(st["plain_energy_history"][-1])
    assert res.energy_history[st["sweeps"]] < res.energy_history[0]


# --------------------------------------------------------------------------- 'none' unchanged
def test_huber_with_a_huge_scale_is_bit_identical_to_none() -> None:
    """Every s <= delta^2 gives w = 1 exactly: the weighting must not change one bit."""
    rng = np.random.default_rng(16)
    graph, _, _ = random_graph(rng, n=12, extra=8, gps=2, rot_scale=0.4)
    big = {"robust": "huber", "robust_scale": 1e8}
    a = solve_hybrid(graph, HybridConfig(sweeps=3, polish=True))
    b = solve_hybrid(graph, HybridConfig(sweeps=3, polish=True, **big))  # type: ignore[arg-type]
    np.testing.assert_array_equal(a.rotations, b.rotations)
    np.testing.assert_array_equal(a.translations, b.translations)
    np.testing.assert_array_equal(a.energy_history, b.energy_history)
    np.testing.assert_array_equal(b.energy_history, b.stats["plain_energy_history"])
    assert "robust" not in a.stats
    c = solve_exact(graph, config=GaussNewtonConfig())
    d = solve_exact(graph, config=GaussNewtonConfig(**big))  # type: ignore[arg-type]
    np.testing.assert_array_equal(c.translations, d.translations)
    np.testing.assert_array_equal(c.energy_history, d.energy_history)


# --------------------------------------------------------------------------- GTSAM
_TO_GTSAM = np.r_[3:6, 0:3]


@pytest.mark.gtsam
@pytest.mark.parametrize("name", KERNELS)
def test_robust_energy_is_twice_gtsam_error(name: str) -> None:
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(17)
    clean, _, _ = random_graph(rng, n=8, extra=5, rot_scale=0.4)
    graph = _with_outliers(rng, clean, 3)
    rot, trans = _perturbed(rng, graph, 0.02)
    s, _ = constraint_energies(graph, rot, trans)
    k = float(np.sqrt(np.median(s)))  # half the constraints on either side of the kink
    est = {"huber": gtsam.noiseModel.mEstimator.Huber,
           "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
           "geman_mcclure": gtsam.noiseModel.mEstimator.GemanMcClure}[name](k)
    fg = gtsam.NonlinearFactorGraph()
    for c, (a, b) in enumerate(graph.edge_nodes):
        info = graph.edge_information[c][np.ix_(_TO_GTSAM, _TO_GTSAM)]
        model = gtsam.noiseModel.Robust.Create(est, gtsam.noiseModel.Gaussian.Information(info))
        z = gtsam.Pose3(gtsam.Rot3(graph.edge_rotations[c]), graph.edge_translations[c])
        fg.add(gtsam.BetweenFactorPose3(int(a), int(b), z, model))
    values = gtsam.Values()
    for i in range(graph.num_nodes):
        values.insert(i, gtsam.Pose3(gtsam.Rot3(rot[i]), trans[i]))
    e_rho, e_plain = robust_energy(graph, rot, trans, name, k)
    assert s.max() > 10 * k * k  # the outliers are far out on the kernel
    assert e_rho < e_plain
    assert e_rho == pytest.approx(2.0 * fg.error(values), rel=1e-9)


# --------------------------------------------------------------------------- CLI
def _cli(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    from hybridpgo.cli import main

    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_robust_exact_reports_both_energies(capsys: pytest.CaptureFixture[str], data_dir,
                                                tmp_path) -> None:
    import json

    from hybridpgo.io import read_graph

    out = tmp_path / "o.g2o"
    code, text, err = _cli(capsys, "optimize", data_dir / "tinyGrid3D.g2o", "-o", out,
                           "--solver", "exact", "--robust", "cauchy:2", "--json", "-q")
    assert code == 0, err
    s = json.loads(text)
    assert s["result"]["robust"] == "cauchy" and s["result"]["robust_scale"] == 2.0
    g = read_graph(out)
    e_rho, e_plain = robust_energy(g, robust="cauchy", scale=2.0)
    assert s["energy_after"] == pytest.approx(e_rho, rel=1e-9)  # the file keeps 9 digits
    assert s["result"]["plain_energy"] == pytest.approx(e_plain, rel=1e-9)
    code, text, err = _cli(capsys, "optimize", data_dir / "tinyGrid3D.g2o", "-o", out,
                           "--solver", "hybrid", "--robust", "huber", "--polish", "--sweeps", "2",
                           "-q")
    assert code == 0, err
    assert "robust kernel   huber, scale 3" in text and "plain energy" in text  # its default


@pytest.mark.parametrize("argv, message", [
    (["--robust", "tukey"], "kernel must be one of none, huber, cauchy, geman_mcclure"),
    (["--robust", "huber:0"], "must be a number > 0, got '0'"),
    (["--robust", "cauchy:x"], "must be a number > 0, got 'x'"),
    (["--robust", "huber", "--solver", "toro"], "--robust: not an option of --solver toro"),
])
def test_cli_bad_robust_options(capsys: pytest.CaptureFixture[str], data_dir, tmp_path,
                                argv: list[str], message: str) -> None:
    out = tmp_path / "o.g2o"
    code, _, err = _cli(capsys, "optimize", data_dir / "tinyGrid3D.g2o", "-o", out, *argv)
    assert code == 2
    assert message in err
    assert not out.exists()


def test_default_scale_is_the_kernels() -> None:
    """robust_scale=None means the kernel's documented default, in both configs and energy()."""
    from hybridpgo._cost import ROBUST_DEFAULT_SCALE

    rng = np.random.default_rng(21)
    graph, _, _ = random_graph(rng, n=8, extra=4, gps=0, rot_scale=0.3)
    for name in ("huber", "cauchy", "geman_mcclure"):
        delta = ROBUST_DEFAULT_SCALE[name]
        assert HybridConfig(robust=name).robust_delta == delta  # type: ignore[arg-type]
        assert GaussNewtonConfig(robust=name).robust_delta == delta  # type: ignore[arg-type]
        assert HybridConfig(robust=name, robust_scale=0.5).robust_delta == 0.5  # type: ignore[arg-type]
        assert robust_energy(graph, robust=name) == robust_energy(graph, robust=name, scale=delta)
        assert robust_energy(graph, robust=name) != robust_energy(graph, robust=name, scale=0.5)
    res = solve_exact(graph, config=GaussNewtonConfig(robust="geman_mcclure", max_iterations=2))
    assert res.stats["robust_scale"] == ROBUST_DEFAULT_SCALE["geman_mcclure"]
