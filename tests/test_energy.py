"""Tests of the energy (docs/conventions.md): E = sum_c e_c^T Omega_c e_c, no 1/2."""

from __future__ import annotations

import numpy as np
import pytest
from ref_kernels import se3_exp
from tolerances import FLOAT64_IDENTITY

from hybridpgo.energy import constraint_energies, energy
from hybridpgo.graph import PoseGraph, lift_information_2d

#: Energy of a noise-free graph at its ground truth: errors are rounding (~1e-15), E ~ 1e-28.
ZERO_ENERGY = 1e-20


# --------------------------------------------------------------------------- SE(2) reference
def _rot2(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def se2_log(x: float, y: float, theta: float) -> np.ndarray:
    """GTSAM ``Pose2::Logmap`` convention: (V(theta)^-1 t, theta), theta in (-pi, pi]."""
    theta = float(np.arctan2(np.sin(theta), np.cos(theta)))
    if abs(theta) < 1e-10:
        return np.array([x, y, theta])
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta
    v_inv = np.array([[a, b], [-b, a]]) / (a * a + b * b)  # V = [[a, -b], [b, a]]
    return np.r_[v_inv @ np.array([x, y]), theta]


def se2_between(pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """(x, y, theta) of pa^-1 pb."""
    t = _rot2(pa[2]).T @ (pb[:2] - pa[:2])
    return np.r_[t, pb[2] - pa[2]]


def se2_energy(poses: np.ndarray, edges: np.ndarray, meas: np.ndarray, info3: np.ndarray) -> float:
    """sum_c e^T Omega e with e = Log(Z^-1 X_a^-1 X_b) in SE(2)."""
    total = 0.0
    for (a, b), z, om in zip(edges, meas, info3, strict=True):
        rel = se2_between(poses[a], poses[b])
        err_pose = se2_between(z, rel)  # Z^-1 (X_a^-1 X_b)
        e = se2_log(*err_pose)
        total += float(e @ om @ e)
    return total


def _spd(rng: np.random.Generator, d: int) -> np.ndarray:
    a = rng.normal(size=(d, d))
    return a @ a.T + d * np.eye(d)


def planar_graph(rng: np.random.Generator, n: int = 12, extra: int = 10, noise: float = 0.3
                 ) -> tuple[PoseGraph, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random 2D graph lifted into SE(3), plus its SE(2) data (poses, edges, meas, info3)."""
    poses = np.column_stack([rng.normal(scale=5.0, size=(n, 2)), rng.uniform(-np.pi, np.pi, n)])
    edges = [(i, i + 1) for i in range(n - 1)]
    while len(edges) < n - 1 + extra:
        a, b = rng.choice(n, 2, replace=False)
        edges.append((int(a), int(b)))
    en = np.array(edges)
    # Measurements far from the truth in places: error angles up to ~2.5 rad.
    meas = np.array([se2_between(poses[a], poses[b]) + rng.normal(scale=noise, size=3)
                     * np.array([1.0, 1.0, 3.0]) for a, b in en])
    info3 = np.array([_spd(rng, 3) for _ in en])
    rot = np.zeros((n, 3, 3))
    rot[:, :2, :2] = [_rot2(th) for th in poses[:, 2]]
    rot[:, 2, 2] = 1.0
    trans = np.column_stack([poses[:, :2], np.zeros(n)])
    er = np.zeros((len(en), 3, 3))
    er[:, :2, :2] = [_rot2(th) for th in meas[:, 2]]
    er[:, 2, 2] = 1.0
    et = np.column_stack([meas[:, :2], np.zeros(len(en))])
    g = PoseGraph(node_ids=np.arange(n), rotations=rot, translations=trans, edge_nodes=en,
                  edge_rotations=er, edge_translations=et,
                  edge_information=lift_information_2d(info3), is_2d=True)
    return g, poses, en, meas, info3


# --------------------------------------------------------------------------- tests
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lifted_2d_energy_equals_se2_energy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    g, poses, en, meas, info3 = planar_graph(rng)
    expected = se2_energy(poses, en, meas, info3)
    e_rel, e_gps = constraint_energies(g)
    assert e_gps.shape == (0,)
    assert np.abs(meas[:, 2]).max() > 1.0  # large angles are covered
    assert energy(g) == pytest.approx(expected, rel=FLOAT64_IDENTITY)
    # Term by term as well (no cancellation can hide a wrong term).
    for c, ((a, b), z, om) in enumerate(zip(en, meas, info3, strict=True)):
        e = se2_log(*se2_between(z, se2_between(poses[a], poses[b])))
        assert e_rel[c] == pytest.approx(float(e @ om @ e), rel=FLOAT64_IDENTITY, abs=1e-300)


def test_energy_is_zero_at_ground_truth() -> None:
    rng = np.random.default_rng(3)
    n = 10
    rot = np.array([se3_exp(np.r_[0, 0, 0, rng.normal(size=3)])[0] for _ in range(n)])
    trans = rng.normal(scale=4.0, size=(n, 3))
    en = np.array([(i, (i + k) % n) for i in range(n) for k in (1, 3)])
    er = np.array([rot[a].T @ rot[b] for a, b in en])
    et = np.array([rot[a].T @ (trans[b] - trans[a]) for a, b in en])
    info = np.array([_spd(rng, 6) for _ in en])
    g = PoseGraph(node_ids=np.arange(n), rotations=rot, translations=trans, edge_nodes=en,
                  edge_rotations=er, edge_translations=et, edge_information=info,
                  gps_nodes=np.array([2, 7]), gps_positions=trans[[2, 7]],
                  gps_information=np.array([_spd(rng, 3), _spd(rng, 3)]))
    assert 0.0 <= energy(g) < ZERO_ENERGY
    # Any pose change raises it.
    t2 = trans.copy()
    t2[4, 0] += 0.1
    assert energy(g, rot, t2) > 1e-4


def test_gps_energy() -> None:
    rng = np.random.default_rng(4)
    n = 5
    trans = rng.normal(size=(n, 3))
    rot = np.array([se3_exp(np.r_[0, 0, 0, rng.normal(size=3)])[0] for _ in range(n)])
    gps_nodes = np.array([0, 3, 3, 4])
    gps_pos = rng.normal(size=(4, 3))
    gps_info = np.array([_spd(rng, 3) for _ in gps_nodes])
    en = np.array([[0, 1], [1, 2], [2, 3], [3, 4]])
    er = np.array([rot[a].T @ rot[b] for a, b in en])
    et = np.array([rot[a].T @ (trans[b] - trans[a]) for a, b in en])
    g = PoseGraph(node_ids=np.arange(n), rotations=rot, translations=trans, edge_nodes=en,
                  edge_rotations=er, edge_translations=et,
                  edge_information=np.broadcast_to(np.eye(6), (4, 6, 6)),
                  gps_nodes=gps_nodes, gps_positions=gps_pos, gps_information=gps_info)
    e_rel, e_gps = constraint_energies(g)
    expected = [float((trans[k] - p) @ om @ (trans[k] - p))
                for k, p, om in zip(gps_nodes, gps_pos, gps_info, strict=True)]
    np.testing.assert_allclose(e_gps, expected, rtol=FLOAT64_IDENTITY, atol=0)
    assert np.all(e_rel < ZERO_ENERGY)  # edges are exact: only the GPS terms count
    assert energy(g) == pytest.approx(sum(expected), rel=FLOAT64_IDENTITY)
    # Rotations do not enter a position constraint.
    rot2 = np.array([r @ se3_exp(np.r_[0, 0, 0, 0.3, 0, 0])[0] for r in rot])
    np.testing.assert_allclose(constraint_energies(g, rot2, trans)[1], expected,
                               rtol=FLOAT64_IDENTITY, atol=0)


def test_pure_translation_error_has_no_half() -> None:
    """Identity rotations: e = (t_err, 0) exactly and E = e^T Omega e (no 1/2,
    docs/conventions.md)."""
    rot = np.broadcast_to(np.eye(3), (2, 3, 3))
    trans = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    om = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    g = PoseGraph(node_ids=np.array([5, 9]), rotations=rot, translations=trans,
                  edge_nodes=np.array([[0, 1]]), edge_rotations=np.eye(3)[None],
                  edge_translations=np.array([[1.0, 1.0, 1.0]]), edge_information=om[None])
    # e = (0, 1, 2, 0, 0, 0): E = 2 * 1 + 3 * 4 = 14
    assert energy(g) == pytest.approx(14.0, rel=FLOAT64_IDENTITY)


def test_energy_rejects_wrong_pose_shapes() -> None:
    rng = np.random.default_rng(5)
    g, *_ = planar_graph(rng, n=4, extra=1)
    with pytest.raises(ValueError, match="shapes"):
        energy(g, np.array(g.rotations)[:3], np.array(g.translations))
