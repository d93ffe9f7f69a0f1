"""Solvers: the hybrid Hessian method (default) and the exact sparse GN/LM solver."""

from __future__ import annotations

from typing import Any

from ..graph import PoseGraph
from .config import TREE_NAMES
from .config import GaussNewtonConfig as GaussNewtonConfig
from .config import HybridConfig as HybridConfig
from .config import Progress as Progress
from .config import default_init as default_init
from .hybrid import HybridSolver as HybridSolver
from .hybrid import solve_hybrid as solve_hybrid
from .result import SolveResult as SolveResult
from .result import Status as Status
from .toro import TREES as _TORO_TREES
from .toro import ToroConfig as ToroConfig

METHODS = ("hybrid", "exact", "toro")
#: Every tree name some solver accepts (the CLI's --tree choices).
TREES: tuple[str, ...] = tuple(dict.fromkeys(TREE_NAMES + _TORO_TREES))

SolverConfig = HybridConfig | GaussNewtonConfig | ToroConfig


def config_for(method: str, **options: Any) -> SolverConfig:
    """The typed options object of ``method`` built from keyword options (ValueError if bad)."""
    if method == "hybrid":
        return HybridConfig(**options)
    if method == "exact":
        return GaussNewtonConfig(**options)
    if method == "toro":
        return ToroConfig(**options)
    raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")


def optimize(graph: PoseGraph, config: SolverConfig | str = "hybrid", *,
             progress: Any = None, init: str | None = None, tree: str | None = None,
             **options: Any) -> SolveResult:
    """Optimize a pose graph.

    Parameters
    ----------
    graph : PoseGraph
    config : HybridConfig, GaussNewtonConfig, ToroConfig, or {"hybrid", "exact", "toro"}
        The solver's typed options, or a method name whose options are then given as keywords
        (the fields of :class:`HybridConfig` or :class:`GaussNewtonConfig`).  ``"hybrid"``: the
        paper's stochastic hybrid Hessian sweeps; ``"exact"``: sparse Levenberg-Marquardt or
        Gauss-Newton; ``"toro"``: the TORO-style baseline (:mod:`hybridpgo.solvers.toro`).
    progress : callable, optional
        ``progress(Progress)`` after every iteration (sweep, polish or exact iteration).
    init, tree : str, optional
        Exact solver only: the starting point (``"file"``, ``"tree"``, ``"chordal"``; default
        :func:`default_init`) and the tree the tree/chordal starts are grown on.  The hybrid
        solver takes them as fields of :class:`HybridConfig`.

    Returns
    -------
    SolveResult
    """
    if isinstance(config, str):
        if config in ("hybrid", "toro"):
            if init is not None:
                options["init"] = init
            if tree is not None:
                options["tree"] = tree
        config = config_for(config, **options)
    elif options:
        raise TypeError("give either a config object or keyword options, not both")
    elif isinstance(config, (HybridConfig, ToroConfig)) and (
            (init is not None and init != config.init)
            or (tree is not None and tree != config.tree)):
        raise ValueError("this solver's init and tree are fields of its config")
    if isinstance(config, HybridConfig):
        return solve_hybrid(graph, config, progress=progress)
    if isinstance(config, ToroConfig):
        from .toro import solve_toro

        return solve_toro(graph, config, progress=progress)
    from ..tree import build_tree, global_poses, initial_locals
    from .gauss_newton import solve_exact

    start = init or default_init(graph, "exact")
    if start == "file" and not graph.has_estimates:
        start = "tree"
    rot = trans = None
    if start != "file":
        t = build_tree(graph, tree or "bfs")
        rot, trans = global_poses(t, *initial_locals(graph, t, start))
    return solve_exact(graph, rot, trans, config, progress=progress)
