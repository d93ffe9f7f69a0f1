"""Pieces shared by the generators: measurement noise, information, dead reckoning, noisify,
and writing the ground truth."""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterator

import numpy as np

from .._numba import kernel
from ..geometry import se3
from ..graph import FloatArray, PoseGraph
from ..io import write_graph
from ..io._lines import PathLike, require_planar, write_atomic
from ..io.g2o import _g2o_lines as g2o_text_blocks

#: Sigma (m or rad) used for the information of a measurement configured with sigma 0.
MIN_SIGMA = 1e-6


def perturb(r: FloatArray, t: FloatArray, sigma: FloatArray, rng: np.random.Generator
            ) -> tuple[FloatArray, FloatArray]:
    """``(R, t) Exp(xi)`` with ``xi ~ N(0, diag(sigma^2))`` per row, sigma (k, 6) over (rho, phi).

    A zero sigma gives an exactly zero component (so planar measurements stay planar).
    """
    xi = rng.normal(size=sigma.shape) * sigma
    nr, nt = se3.exp(xi)
    return se3.compose(r, t, nr, nt)


def diag_information(sigma: FloatArray) -> FloatArray:
    """(k, d, d) information ``diag(1 / max(sigma, MIN_SIGMA)^2)`` of (k, d) sigmas."""
    inv = 1.0 / np.maximum(sigma, MIN_SIGMA) ** 2
    k, d = sigma.shape
    out = np.zeros((k, d, d))
    out[:, np.arange(d), np.arange(d)] = inv
    return out


def chain(r0: FloatArray, t0: FloatArray, zr: FloatArray, zt: FloatArray
          ) -> tuple[FloatArray, FloatArray]:
    """Dead reckoning ``X_0, X_0 Z_0, X_0 Z_0 Z_1, ...`` of (k, 3, 3), (k, 3) measurements."""
    k = zr.shape[0]
    r = np.empty((k + 1, 3, 3))
    t = np.empty((k + 1, 3))
    r[0] = r0
    t[0] = t0
    _chain_into(np.ascontiguousarray(zr, np.float64), np.ascontiguousarray(zt, np.float64), r, t)
    return r, t


@kernel
def _chain_into(zr: FloatArray, zt: FloatArray, r: FloatArray, t: FloatArray) -> None:
    """``X_{i+1} = X_i Z_i`` for i = 0..k-1, given X_0 in ``r[0], t[0]`` (O(k), sequential)."""
    for i in range(zr.shape[0]):
        for a in range(3):
            acc = t[i, a]
            for b in range(3):
                acc += r[i, a, b] * zt[i, b]
                s = 0.0
                for c in range(3):
                    s += r[i, a, c] * zr[i, c, b]
                r[i + 1, a, b] = s
            t[i + 1, a] = acc


def online_order(num_nodes: int, later: np.ndarray) -> np.ndarray:
    """Order of ``N - 1`` odometry edges ``(i, i + 1)`` followed by closures with the given later
    poses, so that each closure comes right after the odometry edge that reaches its later pose
    (the order a front end would emit them; closures of one pose keep their given order)."""
    keys = np.concatenate([2 * np.arange(1, num_nodes, dtype=np.int64),
                           2 * np.asarray(later, np.int64) + 1])
    return np.argsort(keys, kind="stable")


# =========================================================================== noisify & output
def noisify(graph: PoseGraph, yaw_sigma_deg: float = 3.0, seed: int = 0) -> PoseGraph:
    """Add rotation noise about the local up axis to every relative constraint (paper Fig. 8).

    Each measured rotation becomes ``Z_rot Rz(angle)`` with ``angle ~ N(0, yaw_sigma_deg)``
    (drawn from ``np.random.default_rng(seed)``, one per edge in edge order).  Translations,
    information, GPS constraints and the vertex estimates are unchanged, so the file's vertices
    no longer match the measurements: start solvers from the tree initialization
    (``init="tree"``, the hybrid solver's default), which concatenates the noisified edges as
    the paper does.

    Parameters
    ----------
    graph : PoseGraph
    yaw_sigma_deg : float
        Standard deviation of the angle, degrees (the paper: 3).
    seed : int

    Returns
    -------
    PoseGraph
    """
    if not (math.isfinite(yaw_sigma_deg) and yaw_sigma_deg >= 0.0):
        raise ValueError(f"yaw_sigma_deg must be a non-negative number, got {yaw_sigma_deg!r}")
    ang = np.random.default_rng(seed).normal(size=graph.num_edges) * math.radians(yaw_sigma_deg)
    c, s = np.cos(ang), np.sin(ang)
    rz = np.zeros((graph.num_edges, 3, 3))
    rz[:, 0, 0] = c
    rz[:, 0, 1] = -s
    rz[:, 1, 0] = s
    rz[:, 1, 1] = c
    rz[:, 2, 2] = 1.0
    return dataclasses.replace(graph, edge_rotations=graph.edge_rotations @ rz)


def write_ground_truth(path: PathLike, graph: PoseGraph, rotations: FloatArray,
                       translations: FloatArray, *, graph_file: PathLike | None = None) -> None:
    """Write the true poses as a g2o file (atomically) that :func:`hybridpgo.metrics.
    read_ground_truth` and :func:`hybridpgo.io.read_graph` read back.

    The file is the whole graph (same node ids, same constraints) with the true poses as its
    vertices (``VERTEX_SE3:QUAT``, or ``VERTEX_SE2`` for a 2D graph), so it is also a valid
    problem whose vertex estimates are the truth.

    Parameters
    ----------
    path : str or os.PathLike
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64
        True R_world_node and t_world_node in the graph's dense order.
    graph_file : str or os.PathLike, optional
        A g2o file that :func:`hybridpgo.io.write_graph` wrote for this very ``graph``: its
        constraint lines are copied instead of being formatted again (the same bytes, in half
        the time for a large graph).  It must have been written from ``graph``.
    """
    if graph_file is None:
        write_graph(graph.with_poses(rotations, translations), path, format="g2o")
        return
    vertices = PoseGraph(
        node_ids=graph.node_ids, rotations=rotations, translations=translations,
        edge_nodes=np.zeros((0, 2), np.int32), edge_rotations=np.zeros((0, 3, 3)),
        edge_translations=np.zeros((0, 3)), edge_information=np.zeros((0, 6, 6)),
        is_2d=graph.is_2d)
    if graph.is_2d:
        require_planar(vertices, os.fspath(path), "g2o")

    def blocks() -> Iterator[str]:
        yield from g2o_text_blocks(vertices)  # the vertex lines write_graph would write
        block: list[str] = []
        with open(graph_file, encoding="utf-8") as fh:
            for line in fh:
                if not line.startswith("VERTEX_"):
                    block.append(line.rstrip("\n"))
                    if len(block) == 65536:
                        yield "\n".join(block)
                        block = []
        if block:
            yield "\n".join(block)

    write_atomic(path, blocks)
