"""Small synthetic pose graphs for tests (deterministic for a given generator)."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from hybridpgo.graph import PoseGraph


def random_rotations(rng: np.random.Generator, k: int, scale: float) -> np.ndarray:
    """k rotations with rotation vectors ~ N(0, scale^2 I)."""
    return Rotation.from_rotvec(rng.normal(scale=scale, size=(k, 3))).as_matrix()


def planar_rotations(yaw: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about z by the angles ``yaw`` (N,)."""
    rot = np.zeros((yaw.size, 3, 3))
    rot[:, 0, 0] = rot[:, 1, 1] = np.cos(yaw)
    rot[:, 1, 0], rot[:, 0, 1] = np.sin(yaw), -np.sin(yaw)
    rot[:, 2, 2] = 1.0
    return rot


def random_graph(
    rng: np.random.Generator,
    n: int = 8,
    extra: int = 6,
    *,
    gps: int = 0,
    rot_scale: float = 0.3,
    noise: float = 0.05,
    info_scale: float = 1.0,
    anisotropic: bool = True,
) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """A connected 3D graph: an odometry chain plus ``extra`` random loop edges.

    Returns ``(graph, true_rot, true_trans)``; measurements are the true relative poses with
    noise, the graph's vertex estimates are the truth perturbed.
    """
    rot = random_rotations(rng, n, rot_scale * 3)
    rot[0] = np.eye(3)
    trans = np.cumsum(rng.normal(scale=1.0, size=(n, 3)), axis=0)
    trans[0] = 0.0
    pairs = [(i, i + 1) for i in range(n - 1)]
    while len(pairs) < n - 1 + extra:
        a, b = rng.choice(n, size=2, replace=False)
        pairs.append((int(a), int(b)))
    en = np.array(pairs, np.int32)
    m = en.shape[0]
    zr = np.empty((m, 3, 3))
    zt = np.empty((m, 3))
    nr = random_rotations(rng, m, noise)
    for c, (a, b) in enumerate(pairs):
        zr[c] = rot[a].T @ rot[b] @ nr[c]
        zt[c] = rot[a].T @ (trans[b] - trans[a]) + rng.normal(scale=noise, size=3)
    info = np.empty((m, 6, 6))
    for c in range(m):
        if anisotropic:
            q = rng.normal(size=(6, 6))
            info[c] = info_scale * (q @ q.T + 6 * np.eye(6))
        else:
            info[c] = info_scale * np.eye(6)
    gps_nodes = (
        rng.choice(n, size=gps, replace=False).astype(np.int32) if gps else np.zeros(0, np.int32)
    )
    gps_pos = trans[gps_nodes] + rng.normal(scale=noise, size=(gps, 3))
    gps_info = np.empty((gps, 3, 3))
    for k in range(gps):
        q = rng.normal(size=(3, 3))
        gps_info[k] = q @ q.T + 3 * np.eye(3)
    est_rot = rot @ random_rotations(rng, n, rot_scale)
    est_trans = trans + rng.normal(scale=rot_scale, size=(n, 3))
    graph = PoseGraph(
        node_ids=np.arange(n) * 10 + 3,
        rotations=est_rot,
        translations=est_trans,
        edge_nodes=en,
        edge_rotations=zr,
        edge_translations=zt,
        edge_information=info,
        gps_nodes=gps_nodes,
        gps_positions=gps_pos,
        gps_information=gps_info,
    )
    return graph, rot, trans


def with_gps(graph: PoseGraph, every: int = 4, sigma: float = 0.3, seed: int = 0) -> PoseGraph:
    """``graph`` with a noisy GPS reading of every ``every``-th pose (anisotropic information;
    planar readings on a 2D graph) and no fixed pose."""
    rng = np.random.default_rng(seed)
    idx = np.arange(0, graph.num_nodes, every)
    pos = graph.translations[idx] + sigma * rng.standard_normal((idx.size, 3)) + 2.0
    info = np.diag([1.0, 2.0, 0.5]) / sigma ** 2
    if graph.is_2d:
        pos[:, 2] = 0.0
        info[:2, 2] = info[2, :2] = 0.0
    out = graph.add_gps(graph.node_ids[idx], pos, np.broadcast_to(info, (idx.size, 3, 3)))
    return dataclasses.replace(out, fixed_nodes=np.zeros(0, np.int32))
