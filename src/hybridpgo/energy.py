"""Energy of a pose graph (DESIGN.md §1): ``E = sum_c e_c^T Omega_c e_c`` (no 1/2)."""

from __future__ import annotations

import numpy as np

from ._numba import kernel
from .geometry._kernels import relative_error
from .graph import FloatArray, PoseGraph


@kernel
def _edge_energies(rot: np.ndarray, trans: np.ndarray, edge_nodes: np.ndarray,
                   edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
                   out: np.ndarray) -> None:
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        rab = rot[a].T @ rot[b]
        tab = rot[a].T @ (trans[b] - trans[a])
        e = relative_error(edge_rot[c], edge_trans[c], rab, tab)
        out[c] = e @ (edge_info[c] @ e)


@kernel
def _gps_energies(trans: np.ndarray, gps_nodes: np.ndarray, gps_pos: np.ndarray,
                  gps_info: np.ndarray, out: np.ndarray) -> None:
    for c in range(gps_nodes.shape[0]):
        e = trans[gps_nodes[c]] - gps_pos[c]
        out[c] = e @ (gps_info[c] @ e)


def constraint_energies(graph: PoseGraph, rotations: FloatArray | None = None,
                        translations: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Per-constraint energies ``(relative (M,), gps (G,))`` at the given poses.

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64, optional
        Global poses R_world_node, t_world_node; default: the graph's own estimate.
    """
    rot = np.ascontiguousarray(graph.rotations if rotations is None else rotations, np.float64)
    trans = np.ascontiguousarray(graph.translations if translations is None else translations,
                                 np.float64)
    if rot.shape != (graph.num_nodes, 3, 3) or trans.shape != (graph.num_nodes, 3):
        raise ValueError("poses must have shapes (N, 3, 3) and (N, 3)")
    e_rel = np.empty(graph.num_edges)
    e_gps = np.empty(graph.num_gps)
    _edge_energies(rot, trans, graph.edge_nodes, graph.edge_rotations, graph.edge_translations,
                   graph.edge_information, e_rel)
    if graph.num_gps:
        _gps_energies(trans, graph.gps_nodes, graph.gps_positions, graph.gps_information, e_gps)
    return e_rel, e_gps


def energy(graph: PoseGraph, rotations: FloatArray | None = None,
           translations: FloatArray | None = None) -> float:
    """Total energy ``E = sum_c e_c^T Omega_c e_c`` at the given poses (default: the graph's)."""
    e_rel, e_gps = constraint_energies(graph, rotations, translations)
    return float(e_rel.sum() + e_gps.sum())
