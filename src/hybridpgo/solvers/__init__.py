"""Solvers: the hybrid Hessian method (default) and the exact sparse GN/LM solver."""

from __future__ import annotations

from typing import Any

from ..graph import PoseGraph
from .config import GaussNewtonConfig as GaussNewtonConfig
from .hybrid import HybridConfig as HybridConfig
from .hybrid import solve_hybrid as solve_hybrid
from .result import SolveResult as SolveResult
from .result import Status as Status

METHODS = ("hybrid", "exact")


def optimize(graph: PoseGraph, method: str = "hybrid", **options: Any) -> SolveResult:
    """Optimize a pose graph.

    Parameters
    ----------
    graph : PoseGraph
    method : {"hybrid", "exact"}
        ``"hybrid"``: the paper's stochastic hybrid Hessian sweeps (options: the fields of
        :class:`HybridConfig`, plus ``progress``).  ``"exact"``: sparse Levenberg-Marquardt or
        Gauss-Newton from the graph's vertex estimates (options: the fields of
        :class:`GaussNewtonConfig`; ``init="tree"`` / ``"chordal"`` start from those
        initializations).

    Returns
    -------
    SolveResult
    """
    if method == "hybrid":
        progress = options.pop("progress", None)
        return solve_hybrid(graph, HybridConfig(**options), progress=progress)
    if method == "exact":
        from ..tree import build_tree, global_poses, initial_locals
        from .gauss_newton import solve_exact

        init = options.pop("init", "file" if graph.has_estimates else "tree")
        tree_kind = options.pop("tree", "bfs")
        rot = trans = None
        if init not in ("tree", "file", "chordal"):
            raise ValueError(f"init must be 'tree', 'file' or 'chordal', got {init!r}")
        if init == "file" and not graph.has_estimates:
            init = "tree"
        if init != "file":
            tree = build_tree(graph, tree_kind)
            rot, trans = global_poses(tree, *initial_locals(graph, tree, init))
        return solve_exact(graph, rot, trans, GaussNewtonConfig(**options))
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")
