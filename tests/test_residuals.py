"""Tests of per-constraint residuals (hybridpgo.energy.residuals) against a NumPy twin."""

from __future__ import annotations

import dataclasses
import inspect

import naive
import numpy as np
import pytest
from graphs import random_graph
from tolerances import FLOAT64_IDENTITY, TWIN_JACOBIAN

import hybridpgo
from hybridpgo.energy import Residuals, energy, residuals, robust_energy


def _naive_residuals(graph: hybridpgo.PoseGraph, delta: float) -> dict[str, np.ndarray]:
    """One Python loop per constraint: 4x4 products, np.linalg.cholesky, Cauchy by hand."""
    rot, trans = graph.rotations, graph.translations
    out: dict[str, list[np.ndarray | float]] = {k: [] for k in (
        "e", "w", "chi2", "rho", "weight", "ge", "gw", "gchi2")}
    for c, (a, b) in enumerate(graph.edge_nodes):
        rab, tab = naive.between(rot[a], trans[a], rot[b], trans[b])
        e = naive.relative_error(graph.edge_rotations[c], graph.edge_translations[c], rab, tab)
        info = graph.edge_information[c]
        s = naive.chi2(info, e)
        out["e"].append(e)
        out["w"].append(np.linalg.cholesky(info).T @ e)
        out["chi2"].append(s)
        d2 = delta * delta
        out["rho"].append(d2 * np.log1p(s / d2))
        out["weight"].append(d2 / (d2 + s))
    for c, n in enumerate(graph.gps_nodes):
        e = trans[n] - graph.gps_positions[c]
        info = graph.gps_information[c]
        out["ge"].append(e)
        out["gw"].append(np.linalg.cholesky(info).T @ e)
        out["gchi2"].append(naive.chi2(info, e))
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("gps", [0, 4])
def test_residuals_match_the_naive_twin(gps: int) -> None:
    graph, _, _ = random_graph(np.random.default_rng(11), n=12, extra=7, gps=gps)
    # non-contiguous file ids: the ids reported must be the file's, not dense indices
    graph = dataclasses.replace(graph, node_ids=np.arange(graph.num_nodes, dtype=np.int64) * 3 + 5)
    res = residuals(graph, robust="cauchy", scale=1.5)
    ref = _naive_residuals(graph, 1.5)
    scale = max(1.0, float(np.abs(ref["e"]).max()))
    np.testing.assert_allclose(res.edge_error, ref["e"], rtol=0, atol=TWIN_JACOBIAN * scale)
    wscale = max(1.0, float(np.abs(ref["w"]).max()))
    np.testing.assert_allclose(res.edge_whitened, ref["w"], rtol=0, atol=TWIN_JACOBIAN * wscale)
    np.testing.assert_allclose(res.edge_chi2, ref["chi2"], rtol=TWIN_JACOBIAN, atol=0)
    np.testing.assert_allclose(res.edge_robust, ref["rho"], rtol=TWIN_JACOBIAN, atol=0)
    np.testing.assert_allclose(res.edge_weight, ref["weight"], rtol=TWIN_JACOBIAN, atol=0)
    np.testing.assert_array_equal(res.edge_ids, graph.node_ids[graph.edge_nodes])
    assert res.gps_error.shape == (gps, 3) and res.gps_ids.shape == (gps,)
    if gps:
        np.testing.assert_allclose(res.gps_error, ref["ge"], rtol=0, atol=FLOAT64_IDENTITY)
        np.testing.assert_allclose(res.gps_whitened, ref["gw"], rtol=0,
                                   atol=FLOAT64_IDENTITY * max(1.0, np.abs(ref["gw"]).max()))
        np.testing.assert_allclose(res.gps_chi2, ref["gchi2"], rtol=TWIN_JACOBIAN, atol=0)
        np.testing.assert_array_equal(res.gps_ids, graph.node_ids[graph.gps_nodes])
    # the whitened error's squared norm is the chi2, and the chi2 sum is energy() to the bit
    np.testing.assert_allclose((res.edge_whitened ** 2).sum(axis=1), res.edge_chi2,
                               rtol=TWIN_JACOBIAN, atol=0)
    assert res.edge_chi2.sum() + res.gps_chi2.sum() == energy(graph)
    e_rho, _ = robust_energy(graph, robust="cauchy", scale=1.5)
    assert res.edge_robust.sum() + res.gps_robust.sum() == pytest.approx(e_rho,
                                                                         rel=FLOAT64_IDENTITY)
    d2 = 1.5**2  # Cauchy on the GPS constraints too: rho = d2 log(1 + s / d2), w = d2 / (d2 + s)
    np.testing.assert_allclose(res.gps_robust, d2 * np.log1p(res.gps_chi2 / d2),
                               rtol=TWIN_JACOBIAN, atol=0)
    np.testing.assert_allclose(res.gps_weight, d2 / (d2 + res.gps_chi2), rtol=TWIN_JACOBIAN,
                               atol=0)


def test_residuals_at_given_poses_and_without_kernel() -> None:
    graph, true_rot, true_trans = random_graph(np.random.default_rng(12), n=6, extra=3)
    res = residuals(graph, true_rot, true_trans)
    np.testing.assert_array_equal(res.edge_weight, 1.0)
    np.testing.assert_array_equal(res.edge_robust, res.edge_chi2)
    ref = _naive_residuals(dataclasses.replace(graph, rotations=true_rot,
                                               translations=true_trans), 1.0)
    np.testing.assert_allclose(res.edge_chi2, ref["chi2"], rtol=TWIN_JACOBIAN, atol=0)
    with pytest.raises(ValueError, match="shapes"):
        residuals(graph, true_rot[:2], true_trans)
    with pytest.raises(ValueError, match="robust"):
        residuals(graph, robust="tukey")


def test_worst_lists_the_largest_chi2_of_both_kinds() -> None:
    res = Residuals(
        edge_ids=np.array([[0, 1], [1, 2], [2, 3]]), edge_error=np.zeros((3, 6)),
        edge_whitened=np.zeros((3, 6)), edge_chi2=np.array([1.0, 9.0, 4.0]),
        edge_robust=np.zeros(3), edge_weight=np.ones(3), gps_ids=np.array([2, 3]),
        gps_error=np.zeros((2, 3)), gps_whitened=np.zeros((2, 3)),
        gps_chi2=np.array([5.0, 9.0]), gps_robust=np.zeros(2), gps_weight=np.ones(2))
    assert res.worst(3) == [("edge", 1, 9.0), ("gps", 1, 9.0), ("gps", 0, 5.0)]
    assert len(res.worst(10)) == 5 and res.worst(0) == []


def test_hybridpgo_energy_is_the_module_and_still_callable() -> None:
    import hybridpgo.energy as m

    assert inspect.ismodule(m)
    assert hybridpgo.energy is m
    assert m.residuals is residuals
    graph, _, _ = random_graph(np.random.default_rng(13), n=5, extra=2)
    assert hybridpgo.energy(graph) == m.energy(graph)
