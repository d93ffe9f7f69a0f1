"""Energy of a pose graph (DESIGN.md §1): ``E = sum_c e_c^T Omega_c e_c`` (no 1/2).

The per-constraint χ² comes from the cost layer (:mod:`hybridpgo._cost`), the same kernels the
solvers use.  With a robust kernel (DESIGN §10) the robust energy is ``E_rho = sum_c rho(s_c)``
over the relative constraints plus the plain χ² of the position (GPS) constraints.
"""

from __future__ import annotations

import numpy as np

from . import _cost
from .graph import FloatArray, PoseGraph


def _poses(graph: PoseGraph, rotations: FloatArray | None,
           translations: FloatArray | None) -> tuple[FloatArray, FloatArray]:
    rot = np.ascontiguousarray(graph.rotations if rotations is None else rotations, np.float64)
    trans = np.ascontiguousarray(graph.translations if translations is None else translations,
                                 np.float64)
    if rot.shape != (graph.num_nodes, 3, 3) or trans.shape != (graph.num_nodes, 3):
        raise ValueError("poses must have shapes (N, 3, 3) and (N, 3)")
    return rot, trans


def constraint_energies(graph: PoseGraph, rotations: FloatArray | None = None,
                        translations: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Per-constraint energies ``(relative (M,), gps (G,))`` at the given poses.

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64, optional
        Global poses R_world_node, t_world_node; default: the graph's own estimate.
    """
    rot, trans = _poses(graph, rotations, translations)
    e_rel = np.empty(graph.num_edges)
    e_gps = np.empty(graph.num_gps)
    _cost.constraint_energies(rot, trans, graph.edge_nodes, graph.edge_rotations,
                              graph.edge_translations, graph.edge_information, graph.gps_nodes,
                              graph.gps_positions, graph.gps_information, e_rel, e_gps)
    return e_rel, e_gps


def energy(graph: PoseGraph, rotations: FloatArray | None = None,
           translations: FloatArray | None = None) -> float:
    """Total energy ``E = sum_c e_c^T Omega_c e_c`` at the given poses (default: the graph's)."""
    e_rel, e_gps = constraint_energies(graph, rotations, translations)
    return float(e_rel.sum() + e_gps.sum())


def robust_energy(graph: PoseGraph, rotations: FloatArray | None = None,
                  translations: FloatArray | None = None, robust: str = "none",
                  scale: float | None = None) -> tuple[float, float]:
    """``(E_rho, E)``: the robust and the plain energy at the given poses (DESIGN §10).

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64, optional
        Global poses; default: the graph's own estimate.
    robust : {"none", "huber", "cauchy", "geman_mcclure"}
        The kernel applied to each relative constraint's χ² ``s``; GPS constraints stay
        quadratic.  ``E_rho`` equals 2 x GTSAM's ``graph.error`` with the same kernel, k = scale.
    scale : float, optional
        The kernel's delta (> 0), in units of the whitened error (sqrt of χ²); default: the
        kernel's (``hybridpgo._cost.ROBUST_DEFAULT_SCALE``).
    """
    scale = _cost.default_robust_scale(robust, scale)
    kind = _cost.robust_kind(robust, scale)
    s, s_gps = constraint_energies(graph, rotations, translations)
    rho = np.empty_like(s)
    _cost.robust_costs(kind, float(scale), s, rho, np.empty_like(s))
    gps = s_gps.sum()  # summed as energy() sums: where rho(s) = s the two agree to the bit
    return float(rho.sum() + gps), float(s.sum() + gps)


def robust_weights(graph: PoseGraph, rotations: FloatArray | None = None,
                   translations: FloatArray | None = None, robust: str = "none",
                   scale: float | None = None) -> tuple[FloatArray, FloatArray]:
    """``(rho (M,), w (M,))`` of every relative constraint: its robust cost ``rho(s_c)`` and
    IRLS weight ``w_c = rho'(s_c)`` at the given poses (1 for an inlier of Huber; a weight near
    0 marks a constraint the kernel treats as an outlier).  Parameters as :func:`robust_energy`.
    """
    scale = _cost.default_robust_scale(robust, scale)
    kind = _cost.robust_kind(robust, scale)
    s, _ = constraint_energies(graph, rotations, translations)
    rho = np.empty_like(s)
    w = np.empty_like(s)
    _cost.robust_costs(kind, float(scale), s, rho, w)
    return rho, w
