"""Tests of marginal covariances (covariance.py): dense inverse, exact cases, GTSAM Marginals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from graphs import random_graph
from ref_kernels import se3_exp
from tolerances import COVARIANCE_VS_GTSAM, FLOAT64_IDENTITY, SPARSE_VS_DENSE_GN

from hybridpgo.covariance import marginal_covariances
from hybridpgo.errors import SolverError
from hybridpgo.graph import PoseGraph
from hybridpgo.io import read_graph
from hybridpgo.linalg._factor import cholmod_available
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import normal_equations, solve_exact

BACKENDS = [
    "auto",  # the block Cholesky and selected inversion
    "splu",
    pytest.param("cholmod", marks=pytest.mark.skipif(not cholmod_available(),
                                                     reason="cvxopt not installed")),
]
#: Our tangent (rho, phi) -> GTSAM Pose3's (rotation, translation).
_TO_GTSAM = np.r_[3:6, 0:3]


def _dense_blocks(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray,
                  nodes: np.ndarray) -> np.ndarray:
    """Blocks of the dense inverse of H (0 for fixed nodes): the oracle."""
    ne = normal_equations(graph, rot, trans)
    inv = np.linalg.inv(ne.hessian.toarray())
    out = np.zeros((nodes.shape[0], 6, 6))
    for k, n in enumerate(nodes):
        hit = np.flatnonzero(ne.free_nodes == n)
        if hit.size:
            s = slice(6 * hit[0], 6 * hit[0] + 6)
            out[k] = inv[s, s]
    return out


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("gps", [0, 3])
def test_matches_dense_inverse(backend: str, gps: int) -> None:
    graph, _, _ = random_graph(np.random.default_rng(4), n=9, extra=5, gps=gps)
    res = solve_exact(graph)
    nodes = np.array([0, 8, 3, 3])
    cov = marginal_covariances(graph, res.rotations, res.translations, nodes,
                               linear_solver=backend)
    expected = _dense_blocks(graph, res.rotations, res.translations, nodes)
    assert cov.shape == (4, 6, 6)
    np.testing.assert_allclose(cov, expected, rtol=0,
                               atol=SPARSE_VS_DENSE_GN * np.abs(expected).max())
    if gps:  # the earth frame is the gauge: every pose is uncertain
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    else:  # pose 0 is the gauge
        np.testing.assert_array_equal(cov[0], 0.0)
        assert np.all(np.linalg.eigvalsh(cov[1:]) > 0)
    np.testing.assert_array_equal(cov, cov.transpose(0, 2, 1))


def test_one_measurement_from_the_gauge_has_its_noise_covariance() -> None:
    """Pose 1 measured once from the fixed pose 0, zero residual: Cov = Omega^-1 (no factor 2)."""
    rng = np.random.default_rng(5)
    q = rng.normal(size=(6, 6))
    omega = q @ q.T + 6.0 * np.eye(6)
    zr, zt = se3_exp(rng.normal(size=6))
    rot = np.stack([np.eye(3), zr])
    trans = np.stack([np.zeros(3), zt])
    graph = PoseGraph(node_ids=np.arange(2), rotations=rot, translations=trans,
                      edge_nodes=np.array([[0, 1]]), edge_rotations=zr[None],
                      edge_translations=zt[None], edge_information=omega[None])
    cov = marginal_covariances(graph, None, None, [1])
    np.testing.assert_allclose(cov[0], np.linalg.inv(omega), rtol=0,
                               atol=FLOAT64_IDENTITY * np.abs(np.linalg.inv(omega)).max() * 1e2)


def test_gtsam_marginals_on_small_grid(data_dir: Path) -> None:
    gtsam = pytest.importorskip("gtsam")
    from hybridpgo.gtsam_bridge import to_gtsam

    graph = read_graph(data_dir / "smallGrid3D.g2o")
    res = solve_exact(graph, config=GaussNewtonConfig(method="lm"))
    nodes = np.array([1, 17, 62, 124])
    ours = marginal_covariances(graph, res.rotations, res.translations, nodes)
    fg, values = to_gtsam(graph, res.rotations, res.translations)
    fg.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(gtsam.Rot3(res.rotations[0]),
                                                 res.translations[0]),
                                  gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))  # our gauge
    marginals = gtsam.Marginals(fg, values)
    for k, n in enumerate(nodes):
        theirs = np.asarray(marginals.marginalCovariance(int(n)))
        back = np.argsort(_TO_GTSAM)  # GTSAM's (rotation, translation) -> our (rho, phi)
        expected = theirs[np.ix_(back, back)]
        np.testing.assert_allclose(ours[k], expected, rtol=0,
                                   atol=COVARIANCE_VS_GTSAM * np.abs(expected).max())


@pytest.mark.parametrize("gps", [0, 4])
def test_every_pose_by_default_matches_the_per_pose_solves(gps: int) -> None:
    """nodes=None: all N poses, by selected inversion; the same as one triangular solve per pose
    with CHOLMOD or SuperLU (another factorization, another ordering of the work)."""
    graph, _, _ = random_graph(np.random.default_rng(8), n=60, extra=40, gps=gps)
    res = solve_exact(graph)
    cov = marginal_covariances(graph, res.rotations, res.translations)
    assert cov.shape == (60, 6, 6)
    backend = "cholmod" if cholmod_available() else "splu"
    expected = marginal_covariances(graph, res.rotations, res.translations, np.arange(60),
                                    linear_solver=backend)
    np.testing.assert_allclose(cov, expected, rtol=0,
                               atol=SPARSE_VS_DENSE_GN * np.abs(expected).max())
    np.testing.assert_allclose(cov, _dense_blocks(graph, res.rotations, res.translations,
                                                  np.arange(60)),
                               rtol=0, atol=SPARSE_VS_DENSE_GN * np.abs(expected).max())


def test_gtsam_marginals_of_every_pose_of_a_city() -> None:
    """All 400 poses of a generated city (loop closures, so the factor fills in) against
    gtsam.Marginals, relative to each block's largest entry."""
    gtsam = pytest.importorskip("gtsam")
    from hybridpgo.generate import generate_city
    from hybridpgo.gtsam_bridge import to_gtsam

    graph = generate_city("paris2", seed=2, num_poses=400).graph
    res = solve_exact(graph, config=GaussNewtonConfig(method="lm"))
    ours = marginal_covariances(graph, res.rotations, res.translations)
    fg, values = to_gtsam(graph, res.rotations, res.translations)
    fg.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(gtsam.Rot3(res.rotations[0]),
                                                 res.translations[0]),
                                  gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))  # our gauge
    marginals = gtsam.Marginals(fg, values)
    back = np.argsort(_TO_GTSAM)
    worst = 0.0
    for n in range(1, graph.num_nodes):
        theirs = np.asarray(marginals.marginalCovariance(int(graph.node_ids[n])))
        expected = theirs[np.ix_(back, back)]
        worst = max(worst, float(np.abs(ours[n] - expected).max() / np.abs(expected).max()))
    assert worst <= COVARIANCE_VS_GTSAM, worst


def test_bad_nodes_raise() -> None:
    graph, _, _ = random_graph(np.random.default_rng(6), n=4, extra=1)
    with pytest.raises(ValueError, match=r"0\.\.3"):
        marginal_covariances(graph, None, None, [4])
    with pytest.raises(ValueError, match="1-D"):
        marginal_covariances(graph, None, None, [[1]])
    with pytest.raises(ValueError, match="1-D"):
        marginal_covariances(graph, None, None, [1.5])
    assert marginal_covariances(graph, None, None, np.zeros(0, int)).shape == (0, 6, 6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_undetermined_gauge_raises_solver_error(backend: str) -> None:
    """One GPS reading is the gauge (no pose fixed) but leaves the rotation about it free."""
    graph, _, _ = random_graph(np.random.default_rng(7), n=5, extra=2, gps=1)
    res = solve_exact(graph)
    with pytest.raises(SolverError, match=r"singular|positive definite"):
        marginal_covariances(graph, res.rotations, res.translations, [3],
                             linear_solver=backend)
