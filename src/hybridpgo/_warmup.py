"""The graph the solvers' ``ensure_compiled`` functions solve to compile their kernels."""

from __future__ import annotations

import numpy as np

from .graph import PoseGraph


def tiny_graph(gps: bool = False, planar: bool = False) -> PoseGraph:
    """Three poses joined by three constraints (a loop), with one GPS reading on pose 2 when
    ``gps``, in the plane (``is_2d``) when ``planar``: every kernel of a solve runs on it, in
    a fraction of a millisecond."""
    eye = np.tile(np.eye(3), (3, 1, 1))
    lift = np.array([1.0, 1.0, 0.0 if planar else 1.0])  # planar: every z is 0
    return PoseGraph(
        node_ids=np.arange(3), rotations=eye, translations=np.eye(3) * lift,
        edge_nodes=np.array([[0, 1], [1, 2], [0, 2]], np.int32), edge_rotations=eye,
        edge_translations=np.ones((3, 3)) * lift,
        edge_information=np.tile(np.eye(6), (3, 1, 1)), is_2d=planar,
        gps_nodes=np.array([2] if gps else [], np.int32),
        gps_positions=np.ones((1, 3)) if gps else np.zeros((0, 3)),
        gps_information=np.eye(3)[None] if gps else np.zeros((0, 3, 3)),
    )
