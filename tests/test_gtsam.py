"""Cross-checks against GTSAM through the bridge ``hybridpgo.gtsam_bridge`` (optional peer;
docs/conventions.md "Comparing with GTSAM").

The bridge builds GTSAM factors from *our* converted information, reordered to GTSAM's
(rotation, translation) tangent order; then our E = 2 x ``graph.error`` to rounding.  (GTSAM's own
``readG2o`` keeps the g2o rotation information unscaled, so its optimum differs in 3D.)
"""

from __future__ import annotations

import builtins
from pathlib import Path

import numpy as np
import pytest
from ref_kernels import se3_exp, se3_log
from tolerances import FLOAT64_IDENTITY

from hybridpgo.energy import constraint_energies, energy
from hybridpgo.errors import GraphError, HybridPGOError
from hybridpgo.graph import PoseGraph
from hybridpgo.gtsam_bridge import TO_GTSAM_TANGENT, from_gtsam, gauge_prior, to_gtsam
from hybridpgo.io import read_graph
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact

gtsam = pytest.importorskip("gtsam")
pytestmark = pytest.mark.gtsam

#: Our E vs 2 x GTSAM's error at the same poses (same maths, different code): relative.
SAME_ENERGY_RTOL = 1e-9
#: Our LM optimum vs GTSAM LM's optimum, both stopped at relative decrease 1e-10: relative.
OPTIMUM_RTOL = 1e-6


def _perturbed(graph: PoseGraph, rng: np.random.Generator, size: float
               ) -> tuple[np.ndarray, np.ndarray]:
    rot = np.array(graph.rotations)
    trans = np.array(graph.translations)
    for i in range(graph.num_nodes):
        xi = rng.normal(scale=size, size=6)
        if graph.is_2d:
            xi[[2, 3, 4]] = 0.0
        dr, dt = se3_exp(xi)
        trans[i] = trans[i] + rot[i] @ dt
        rot[i] = rot[i] @ dr
    return rot, trans


def _with_gps(graph: PoseGraph, rng: np.random.Generator) -> PoseGraph:
    """``graph`` plus a GPS reading with a full (correlated) information on every 3rd pose."""
    ids = graph.node_ids[::3]
    a = rng.normal(size=(ids.size, 3, 3))
    info = 1e3 * (a @ np.swapaxes(a, 1, 2) + 0.5 * np.eye(3))
    xyz = graph.translations[::3] + rng.normal(scale=0.3, size=(ids.size, 3))
    return graph.add_gps(ids, xyz, info)


@pytest.fixture
def w100(data_dir: Path) -> PoseGraph:
    with pytest.warns(UserWarning, match="EQUIV"):  # w100 merges 40 ids (TORO EQUIV lines)
        graph = read_graph(data_dir / "w100_toro.graph")
    assert graph.is_2d
    return graph


# --------------------------------------------------------------------------- conventions
def test_gtsam_pose3_chart_is_the_full_se3_logmap() -> None:
    """Pose3's Logmap is (phi, V^-1 t) = ours reordered, and localCoordinates uses it.

    Checked because BetweenFactor's error is ``measured.localCoordinates(hx)``: with the full
    SE(3) Expmap chart (GTSAM_POSE3_EXPMAP) it is ``Logmap(measured^-1 hx)``, our error.
    """
    rng = np.random.default_rng(0)
    for angle in (1e-7, 0.3, 1.5, 3.0, np.pi - 1e-4):
        axis = rng.normal(size=3)
        r, _ = se3_exp(np.r_[0.0, 0.0, 0.0, angle * axis / np.linalg.norm(axis)])
        t = rng.normal(scale=3.0, size=3)
        ours = se3_log(r, t)
        theirs = np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(gtsam.Rot3(r), t)))
        np.testing.assert_allclose(theirs, ours[TO_GTSAM_TANGENT], rtol=0,
                                   atol=FLOAT64_IDENTITY * 1e3 * max(1.0, np.abs(ours).max()))
        z = gtsam.Pose3(gtsam.Rot3(se3_exp(rng.normal(size=6))[0]), rng.normal(size=3))
        x = gtsam.Pose3(gtsam.Rot3(r), t)
        np.testing.assert_allclose(np.asarray(z.localCoordinates(x)),
                                   np.asarray(gtsam.Pose3.Logmap(z.between(x))), rtol=0,
                                   atol=FLOAT64_IDENTITY * 1e3)


# --------------------------------------------------------------------------- energies
@pytest.mark.parametrize("perturbation", [0.0, 0.05, 0.5])
def test_energy_is_twice_gtsam_error_on_small_grid(data_dir: Path, perturbation: float) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    rot, trans = _perturbed(graph, np.random.default_rng(1), perturbation)
    fg, values = to_gtsam(graph, rot, trans)
    assert fg.size() == graph.num_edges
    assert energy(graph, rot, trans) == pytest.approx(2.0 * fg.error(values),
                                                      rel=SAME_ENERGY_RTOL)


def test_energy_is_twice_gtsam_error_per_factor(data_dir: Path) -> None:
    graph = read_graph(data_dir / "tinyGrid3D.g2o")
    rot, trans = _perturbed(graph, np.random.default_rng(2), 0.3)
    fg, values = to_gtsam(graph, rot, trans)
    e_rel, _ = constraint_energies(graph, rot, trans)
    for c in range(graph.num_edges):
        assert e_rel[c] == pytest.approx(2.0 * fg.at(c).error(values), rel=SAME_ENERGY_RTOL)


def test_gps_constraints_become_gps_factors(data_dir: Path) -> None:
    rng = np.random.default_rng(4)
    graph = _with_gps(read_graph(data_dir / "smallGrid3D.g2o"), rng)
    rot, trans = _perturbed(graph, rng, 0.2)
    fg, values = to_gtsam(graph, rot, trans)
    assert fg.size() == graph.num_constraints
    e_rel, e_gps = constraint_energies(graph, rot, trans)
    assert e_gps.sum() > 0.1 * e_rel.sum()  # the GPS part matters in the total below
    for c in range(graph.num_gps):
        factor = fg.at(graph.num_edges + c)
        assert isinstance(factor, gtsam.GPSFactor)
        assert e_gps[c] == pytest.approx(2.0 * factor.error(values), rel=SAME_ENERGY_RTOL)
    assert energy(graph, rot, trans) == pytest.approx(2.0 * fg.error(values),
                                                      rel=SAME_ENERGY_RTOL)
    assert gauge_prior(graph, values).size() == 0  # the earth frame fixes the gauge


@pytest.mark.parametrize("perturbation", [0.0, 0.1])
def test_2d_energy_is_twice_gtsam_pose2_error(w100: PoseGraph, perturbation: float) -> None:
    rot, trans = _perturbed(w100, np.random.default_rng(3), perturbation)
    fg, values = to_gtsam(w100, rot, trans)
    assert isinstance(fg.at(0), gtsam.BetweenFactorPose2)
    assert energy(w100, rot, trans) == pytest.approx(2.0 * fg.error(values),
                                                     rel=SAME_ENERGY_RTOL)
    # The lifted graph as Pose3 factors: the same energy.
    fg3, values3 = to_gtsam(w100, rot, trans, planar=False)
    assert isinstance(fg3.at(0), gtsam.BetweenFactorPose3)
    assert 2.0 * fg3.error(values3) == pytest.approx(2.0 * fg.error(values),
                                                     rel=SAME_ENERGY_RTOL)


def test_2d_graph_with_gps_uses_pose3(w100: PoseGraph) -> None:
    graph = _with_gps(w100, np.random.default_rng(5))
    fg, values = to_gtsam(graph)
    assert isinstance(fg.at(0), gtsam.BetweenFactorPose3)
    assert energy(graph) == pytest.approx(2.0 * fg.error(values), rel=SAME_ENERGY_RTOL)
    with pytest.raises(ValueError, match="Pose2 cannot carry"):
        to_gtsam(graph, planar=True)


# --------------------------------------------------------------------------- values
def test_values_are_keyed_by_node_id_and_round_trip(data_dir: Path) -> None:
    graph = read_graph(data_dir / "tinyGrid3D.g2o")
    rot, trans = _perturbed(graph, np.random.default_rng(6), 0.4)
    relabelled = PoseGraph(node_ids=graph.node_ids * 7 + 100, rotations=rot,
                           translations=trans, edge_nodes=graph.edge_nodes,
                           edge_rotations=graph.edge_rotations,
                           edge_translations=graph.edge_translations,
                           edge_information=graph.edge_information)
    fg, values = to_gtsam(relabelled)
    assert sorted(values.keys()) == (graph.node_ids * 7 + 100).tolist()
    assert fg.at(0).keys() == (graph.node_ids[graph.edge_nodes[0]] * 7 + 100).tolist()
    r2, t2 = from_gtsam(relabelled, values)
    np.testing.assert_array_equal(t2, trans)
    np.testing.assert_allclose(r2, rot, rtol=0, atol=FLOAT64_IDENTITY)


def test_pose2_values_round_trip(w100: PoseGraph) -> None:
    rot, trans = _perturbed(w100, np.random.default_rng(7), 0.2)
    _, values = to_gtsam(w100, rot, trans)
    r2, t2 = from_gtsam(w100, values)
    np.testing.assert_allclose(t2, trans, rtol=0, atol=FLOAT64_IDENTITY * 1e2)
    np.testing.assert_allclose(r2, rot, rtol=0, atol=FLOAT64_IDENTITY)


def test_from_gtsam_names_missing_nodes(data_dir: Path) -> None:
    graph = read_graph(data_dir / "tinyGrid3D.g2o")
    _, values = to_gtsam(graph)
    values.erase(int(graph.node_ids[3]))
    with pytest.raises(GraphError, match=rf"1 of 9 node\(s\): id\(s\) {graph.node_ids[3]}$"):
        from_gtsam(graph, values)
    with pytest.raises(GraphError, match=r"9 of 9"):
        from_gtsam(graph, gtsam.Values())


def test_negative_ids_cannot_be_keys() -> None:
    graph = PoseGraph(node_ids=[-1, 0], rotations=np.tile(np.eye(3), (2, 1, 1)),
                      translations=np.zeros((2, 3)), edge_nodes=[[0, 1]],
                      edge_rotations=np.eye(3)[None], edge_translations=[[1.0, 0, 0]],
                      edge_information=np.eye(6)[None])
    with pytest.raises(GraphError, match="node id -1: GTSAM keys are unsigned"):
        to_gtsam(graph)


def test_missing_gtsam_names_the_extra(monkeypatch: pytest.MonkeyPatch,
                                       data_dir: Path) -> None:
    real_import = builtins.__import__

    def no_gtsam(name: str, *args: object, **kwargs: object) -> object:
        if name == "gtsam":
            raise ImportError("No module named 'gtsam'")
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(builtins, "__import__", no_gtsam)
    with pytest.raises(HybridPGOError, match=r"pip install hybridpgo\[gtsam\]"):
        to_gtsam(read_graph(data_dir / "tinyGrid3D.g2o"))


# --------------------------------------------------------------------------- optimum
def test_lm_optimum_equals_gtsam_lm_optimum_on_small_grid(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    ours = solve_exact(graph, config=GaussNewtonConfig(method="lm"))
    fg, values = to_gtsam(graph)
    anchored, _ = to_gtsam(graph, anchor=True)  # gauge: node 0 fixed, as ours
    assert anchored.size() == fg.size() + 1
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    result = gtsam.LevenbergMarquardtOptimizer(anchored, values, params).optimize()
    theirs = 2.0 * fg.error(result)
    assert ours.final_energy == pytest.approx(theirs, rel=OPTIMUM_RTOL)
    # And GTSAM's optimum, scored by us, is the same number.
    rot, trans = from_gtsam(graph, result)
    assert energy(graph, rot, trans) == pytest.approx(theirs, rel=SAME_ENERGY_RTOL)
