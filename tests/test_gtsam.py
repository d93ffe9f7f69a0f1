"""Cross-checks against GTSAM (optional peer; DESIGN.md §1 "Comparing with GTSAM").

GTSAM factors are built here from *our* converted information, reordered to GTSAM's
(rotation, translation) tangent order; then our E = 2 x ``graph.error`` to rounding.  (GTSAM's own
``readG2o`` keeps the g2o rotation information unscaled, so its optimum differs in 3D.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tolerances import FLOAT64_IDENTITY

from hybridpgo.energy import energy
from hybridpgo.geometry._kernels import se3_exp, se3_log
from hybridpgo.graph import PoseGraph, planar_information
from hybridpgo.io import read_graph
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact

gtsam = pytest.importorskip("gtsam")
pytestmark = pytest.mark.gtsam

#: Our E vs 2 x GTSAM's error at the same poses (same maths, different code): relative.
SAME_ENERGY_RTOL = 1e-9
#: Our LM optimum vs GTSAM LM's optimum, both stopped at relative decrease 1e-10: relative.
OPTIMUM_RTOL = 1e-6

#: Our tangent (rho, phi) -> GTSAM Pose3's (rotation, translation).
_TO_GTSAM = np.r_[3:6, 0:3]
#: The (x, y, yaw) entries of our lifted tangent.
_PLANAR = np.array([0, 1, 5])


def _yaw(r: np.ndarray) -> float:
    return float(np.arctan2(r[1, 0], r[0, 0]))


def gtsam_values(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray) -> object:
    values = gtsam.Values()
    for i in range(graph.num_nodes):
        if graph.is_2d:
            values.insert(i, gtsam.Pose2(trans[i, 0], trans[i, 1], _yaw(rot[i])))
        else:
            values.insert(i, gtsam.Pose3(gtsam.Rot3(rot[i]), trans[i]))
    return values


def gtsam_factors(graph: PoseGraph) -> object:
    """BetweenFactorPose3 (or Pose2 for 2D graphs) with our information, GTSAM tangent order."""
    fg = gtsam.NonlinearFactorGraph()
    for c, (a, b) in enumerate(graph.edge_nodes):
        rz, tz = graph.edge_rotations[c], graph.edge_translations[c]
        if graph.is_2d:
            info = planar_information(graph.edge_information[c : c + 1])[0]
            fg.add(gtsam.BetweenFactorPose2(int(a), int(b), gtsam.Pose2(tz[0], tz[1], _yaw(rz)),
                                            gtsam.noiseModel.Gaussian.Information(info)))
        else:
            info = graph.edge_information[c][np.ix_(_TO_GTSAM, _TO_GTSAM)]
            fg.add(gtsam.BetweenFactorPose3(int(a), int(b), gtsam.Pose3(gtsam.Rot3(rz), tz),
                                            gtsam.noiseModel.Gaussian.Information(info)))
    return fg


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
        np.testing.assert_allclose(theirs, ours[_TO_GTSAM], rtol=0,
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
    fg = gtsam_factors(graph)
    ours = energy(graph, rot, trans)
    assert ours == pytest.approx(2.0 * fg.error(gtsam_values(graph, rot, trans)),
                                 rel=SAME_ENERGY_RTOL)


def test_energy_is_twice_gtsam_error_per_factor(data_dir: Path) -> None:
    from hybridpgo.energy import constraint_energies

    graph = read_graph(data_dir / "tinyGrid3D.g2o")
    rot, trans = _perturbed(graph, np.random.default_rng(2), 0.3)
    values = gtsam_values(graph, rot, trans)
    fg = gtsam_factors(graph)
    e_rel, _ = constraint_energies(graph, rot, trans)
    for c in range(graph.num_edges):
        assert e_rel[c] == pytest.approx(2.0 * fg.at(c).error(values), rel=SAME_ENERGY_RTOL)


@pytest.mark.parametrize("perturbation", [0.0, 0.1])
def test_2d_energy_is_twice_gtsam_pose2_error(data_dir: Path, perturbation: float) -> None:
    with pytest.warns(UserWarning, match="EQUIV"):  # w100 merges 40 ids (TORO EQUIV lines)
        graph = read_graph(data_dir / "w100_toro.graph")
    assert graph.is_2d
    rot, trans = _perturbed(graph, np.random.default_rng(3), perturbation)
    fg = gtsam_factors(graph)
    assert energy(graph, rot, trans) == pytest.approx(
        2.0 * fg.error(gtsam_values(graph, rot, trans)), rel=SAME_ENERGY_RTOL)


# --------------------------------------------------------------------------- optimum
def test_lm_optimum_equals_gtsam_lm_optimum_on_small_grid(data_dir: Path) -> None:
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    ours = solve_exact(graph, config=GaussNewtonConfig(method="lm"))
    fg = gtsam_factors(graph)
    prior = gtsam.NonlinearFactorGraph(fg)  # gauge: node 0 fixed, as ours
    prior.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(gtsam.Rot3(graph.rotations[0]),
                                                    graph.translations[0]),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    values = gtsam_values(graph, np.array(graph.rotations), np.array(graph.translations))
    result = gtsam.LevenbergMarquardtOptimizer(prior, values, params).optimize()
    theirs = 2.0 * fg.error(result)
    assert ours.final_energy == pytest.approx(theirs, rel=OPTIMUM_RTOL)
    # And GTSAM's optimum, scored by us, is the same number.
    rot = np.array([result.atPose3(i).rotation().matrix() for i in range(graph.num_nodes)])
    trans = np.array([result.atPose3(i).translation() for i in range(graph.num_nodes)])
    assert energy(graph, rot, trans) == pytest.approx(theirs, rel=SAME_ENERGY_RTOL)
