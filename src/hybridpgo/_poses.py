"""The global poses a tool works with: the caller's, the graph's own, or the tree start."""

from __future__ import annotations

import numpy as np

from .graph import FloatArray, PoseGraph


def given_or_start(graph: PoseGraph, rotations: FloatArray | None,
                   translations: FloatArray | None,
                   names: tuple[str, str] = ("rotations", "translations")
                   ) -> tuple[FloatArray, FloatArray]:
    """``(rotations, translations)`` as float64 arrays checked against the graph's size; when
    both are None the graph's own estimates, or for a file without vertices (iSAM) the tree
    initialization.  ``names``: the two arguments as the caller calls them (in the errors).

    Raises ``ValueError`` when only one is given or a shape is not ``(N, 3, 3)`` / ``(N, 3)``.
    """
    if (rotations is None) != (translations is None):
        raise ValueError(f"give both {names[0]} and {names[1]}, or neither")
    if rotations is None or translations is None:
        if graph.has_estimates:
            return graph.rotations, graph.translations
        from .initialization import initial_locals
        from .tree import build_tree, global_poses

        tree = build_tree(graph, "bfs")
        return global_poses(tree, *initial_locals(graph, tree, "tree"))
    rot = np.asarray(rotations, np.float64)
    trans = np.asarray(translations, np.float64)
    if rot.shape != (graph.num_nodes, 3, 3) or trans.shape != (graph.num_nodes, 3):
        raise ValueError(f"poses must have shapes ({graph.num_nodes}, 3, 3) and "
                         f"({graph.num_nodes}, 3), got {rot.shape} and {trans.shape}")
    return rot, trans
