"""Solvers: the default pipeline (auto), the hybrid Hessian method, the exact sparse GN/LM
solver and the TORO-style baseline."""

from __future__ import annotations

from typing import Any

from ..graph import PoseGraph
from .config import TREE_NAMES
from .config import AutoConfig as AutoConfig
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

#: Solver names; the first is the default of :func:`optimize` and ``hybridpgo optimize``.
METHODS = ("auto", "hybrid", "exact", "toro")
#: Every tree name some solver accepts (the CLI's --tree choices).
TREES: tuple[str, ...] = tuple(dict.fromkeys(TREE_NAMES + _TORO_TREES))

SolverConfig = AutoConfig | HybridConfig | GaussNewtonConfig | ToroConfig


def config_for(method: str, **options: Any) -> SolverConfig:
    """The typed options object of ``method`` built from keyword options (ValueError if bad).

    ``robust`` defaults to ``"auto"`` for ``"auto"``, ``"hybrid"`` and ``"exact"`` (the outlier
    test and re-solve of :mod:`hybridpgo.solvers.robust`): the same default under every solver
    that has robust kernels, as on the command line.
    """
    if method in ("hybrid", "exact"):
        options.setdefault("robust", "auto")
    if method == "auto":
        inits = options.get("inits")
        if isinstance(inits, (list, str)):  # one name (a CLI --init, a batch grid) or a list
            options["inits"] = (inits,) if isinstance(inits, str) else tuple(inits)
        unknown = sorted(set(options) - set(AutoConfig.__dataclass_fields__))
        if unknown:
            raise TypeError(f"{', '.join(unknown)}: not an option of the default pipeline "
                            "(AutoConfig); for the paper's method alone name it: "
                            "optimize(graph, 'hybrid', ...)")
        return AutoConfig(**options)
    if method == "hybrid":
        return HybridConfig(**options)
    if method == "exact":
        return GaussNewtonConfig(**options)
    if method == "toro":
        return ToroConfig(**options)
    raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")


def optimize(graph: PoseGraph, config: SolverConfig | str = "auto", *,
             progress: Any = None, init: str | None = None, tree: str | None = None,
             **options: Any) -> SolveResult:
    """Optimize a pose graph.

    Parameters
    ----------
    graph : PoseGraph
    config : AutoConfig, HybridConfig, GaussNewtonConfig, ToroConfig, or a method name
        The solver's typed options, or a method name (``"auto"``, ``"hybrid"``, ``"exact"``,
        ``"toro"``) whose options are then given as keywords (the fields of its config).
        ``"auto"`` (default): the pipeline of :mod:`hybridpgo.solvers.auto` (chooses the
        start among chordal, tree and file, sweeps while they pay, polishes with LM to
        convergence); ``"hybrid"``: the paper's stochastic hybrid Hessian sweeps alone;
        ``"exact"``: sparse Levenberg-Marquardt or Gauss-Newton; ``"toro"``: the TORO-style
        baseline (:mod:`hybridpgo.solvers.toro`).
    progress : callable, optional
        ``progress(Progress)`` after every iteration (sweep, polish or exact iteration).
    init, tree : str, optional
        Exact solver only: the starting point (``"file"``, ``"tree"``, ``"chordal"``; default
        :func:`default_init`) and the tree the tree/chordal starts are grown on.  The hybrid
        solver takes them as fields of :class:`HybridConfig`; ``"auto"`` takes ``init`` as the
        only start to try (``inits=(init,)``) and ``tree`` as its tree.

    Returns
    -------
    SolveResult
    """
    if isinstance(config, str):
        if config == "auto":
            if init is not None:
                options["inits"] = (init,)
            if tree is not None:
                options["tree"] = tree
        elif config in ("hybrid", "toro"):
            if init is not None:
                options["init"] = init
            if tree is not None:
                options["tree"] = tree
        config = config_for(config, **options)
    elif options:
        raise TypeError("give either a config object or keyword options, not both")
    elif isinstance(config, AutoConfig) and (
            (init is not None and (init,) != config.inits)
            or (tree is not None and tree != config.tree)):
        raise ValueError("the default pipeline's starts and tree are fields of its config")
    elif isinstance(config, (HybridConfig, ToroConfig)) and (
            (init is not None and init != config.init)
            or (tree is not None and tree != config.tree)):
        raise ValueError("this solver's init and tree are fields of its config")
    if isinstance(config, AutoConfig):
        from .auto import solve_auto

        return solve_auto(graph, config, progress=progress)
    if isinstance(config, HybridConfig):
        return solve_hybrid(graph, config, progress=progress)
    if isinstance(config, ToroConfig):
        from .toro import solve_toro

        return solve_toro(graph, config, progress=progress)
    from .gauss_newton import solve_exact

    return solve_exact(graph, *exact_start(graph, init, tree), config, progress=progress)


def exact_start(graph: PoseGraph, init: str | None = None,
                tree: str | None = None) -> tuple[Any, Any]:
    """The exact solver's starting poses ``(R, t)`` for ``init`` (default
    :func:`default_init`), grown on ``tree`` (default ``"bfs"``); ``(None, None)`` for the
    file's own poses (``"file"`` falls back to ``"tree"`` when the file has none)."""
    from ..tree import build_tree, global_poses, initial_locals

    start = init or default_init(graph, "exact")
    if start == "file" and not graph.has_estimates:
        start = "tree"
    if start == "file":
        return None, None
    t = build_tree(graph, tree or "bfs")
    return global_poses(t, *initial_locals(graph, t, start))
