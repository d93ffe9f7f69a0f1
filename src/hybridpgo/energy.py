"""Energy of a pose graph (docs/conventions.md): ``E = sum_c e_c^T Omega_c e_c`` (no 1/2).

The per-constraint χ² comes from the cost layer (:mod:`hybridpgo._cost`), the same kernels the
solvers use.  With a robust kernel (docs/conventions.md#robust-kernels) the robust energy is
``E_rho = sum_c rho(s_c)``
over the relative constraints plus the plain χ² of the position (GPS) constraints.
:func:`residuals` gives every constraint's error vector, whitened error and χ².

``hybridpgo.energy`` is this module; calling it, ``hybridpgo.energy(graph)``, is shorthand for
:func:`energy` (typed code should call ``hybridpgo.energy.energy``).
"""

from __future__ import annotations

import sys
import types
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from . import _cost
from .graph import FloatArray, PoseGraph

__all__ = ["Residuals", "constraint_energies", "energy", "residuals", "robust_energy",
           "robust_weights"]


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
    """``(E_rho, E)``: the robust and the plain energy at the given poses
    (docs/conventions.md#robust-kernels).

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


@dataclass(frozen=True, slots=True)
class Residuals:
    """Every constraint's error at some poses (:func:`residuals`).

    Relative constraints are in the graph's edge order (the file's order of edge lines), GPS
    constraints in the graph's GPS order.  ``Omega = L L^T`` (Cholesky), so the whitened error
    ``L^T e`` has ``|L^T e|^2 = chi2``; under the model it is a standard normal vector.
    """

    edge_ids: npt.NDArray[np.int64]
    """(M, 2) int64: file ids ``(a, b)`` of each relative constraint."""
    edge_error: FloatArray
    """(M, 6) float64: ``e = Log(Z^-1 X_a^-1 X_b)``, order (rho, phi): metres, radians."""
    edge_whitened: FloatArray
    """(M, 6) float64: ``L^T e`` (dimensionless)."""
    edge_chi2: FloatArray
    """(M,) float64: ``e^T Omega e`` (no 1/2); their sum plus ``gps_chi2``'s is the energy."""
    edge_robust: FloatArray
    """(M,) float64: the robust cost ``rho(chi2)`` (``chi2`` itself without a kernel)."""
    edge_weight: FloatArray
    """(M,) float64: the IRLS weight ``rho'(chi2)`` (1 without a kernel; near 0: an outlier)."""
    gps_ids: npt.NDArray[np.int64]
    """(G,) int64: file id of the pose each GPS constraint measures."""
    gps_error: FloatArray
    """(G, 3) float64: ``e = p_n - g`` in the earth frame, metres."""
    gps_whitened: FloatArray
    """(G, 3) float64: ``L^T e``."""
    gps_chi2: FloatArray
    """(G,) float64: ``e^T Omega e``."""

    def worst(self, k: int) -> list[tuple[str, int, float]]:
        """The ``k`` largest χ² over both kinds: ``(kind, index, chi2)`` with kind ``"edge"``
        or ``"gps"`` and index into that kind's arrays, largest first (ties: edges, then by
        index)."""
        chi2 = np.concatenate([self.edge_chi2, self.gps_chi2])
        order = np.argsort(-chi2, kind="stable")[:max(k, 0)]
        m = self.edge_chi2.shape[0]
        return [("edge", int(i), float(chi2[i])) if i < m else ("gps", int(i - m),
                                                                 float(chi2[i]))
                for i in order]


def _whiten(information: FloatArray, e: FloatArray) -> FloatArray:
    """``L^T e`` per row, ``Omega = L L^T`` (vectorized Cholesky)."""
    if e.shape[0] == 0:
        return np.zeros_like(e)
    lower = np.linalg.cholesky(information)
    return np.asarray(np.einsum("kji,kj->ki", lower, e))


def residuals(graph: PoseGraph, rotations: FloatArray | None = None,
              translations: FloatArray | None = None, *, robust: str = "none",
              scale: float = 1.0) -> Residuals:
    """Per-constraint error vectors, whitened errors and χ² at the given poses.

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64, optional
        Global poses; default: the graph's own estimate.
    robust, scale
        A robust kernel and its delta, as :func:`robust_energy`: fills ``edge_robust`` and
        ``edge_weight`` (GPS constraints stay quadratic).

    Returns
    -------
    Residuals
        ``edge_chi2.sum() + gps_chi2.sum()`` equals :func:`energy` at the same poses (the same
        kernels, summed the same way).

    Raises
    ------
    ValueError
        Poses of the wrong shape, or a bad kernel name or scale.
    """
    kind = _cost.robust_kind(robust, scale)
    rot, trans = _poses(graph, rotations, translations)
    s, s_gps = constraint_energies(graph, rot, trans)
    e_rel = np.empty((graph.num_edges, 6))
    e_gps = np.empty((graph.num_gps, 3))
    _cost.constraint_errors(rot, trans, graph.edge_nodes, graph.edge_rotations,
                            graph.edge_translations, graph.gps_nodes, graph.gps_positions,
                            e_rel, e_gps)
    rho = np.empty_like(s)
    w = np.empty_like(s)
    _cost.robust_costs(kind, float(scale), s, rho, w)
    ids = graph.node_ids.astype(np.int64)
    return Residuals(
        edge_ids=ids[graph.edge_nodes].reshape(-1, 2), edge_error=e_rel,
        edge_whitened=_whiten(graph.edge_information, e_rel), edge_chi2=s, edge_robust=rho,
        edge_weight=w, gps_ids=ids[graph.gps_nodes], gps_error=e_gps,
        gps_whitened=_whiten(graph.gps_information, e_gps), gps_chi2=s_gps)


class _CallableModule(types.ModuleType):
    """This module's type: ``hybridpgo.energy`` is the module (``import hybridpgo.energy``
    works as for any submodule), and calling it calls :func:`energy`, so the earlier
    ``hybridpgo.energy(graph)`` keeps working."""

    def __call__(self, graph: PoseGraph, rotations: FloatArray | None = None,
                 translations: FloatArray | None = None) -> float:
        return energy(graph, rotations, translations)


sys.modules[__name__].__class__ = _CallableModule
