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
    """The typed options object of ``method`` built from flat keyword options.

    The one place where the command line's option names meet the configs' fields: ``sweeps``
    (hybrid: its sweeps; auto: the most sweeps per start; toro: its iterations),
    ``max_iterations`` (exact: its limit; hybrid and auto: of the polish), ``init`` (auto: the
    only start to try), and every config's own fields.  TypeError for an option the method does
    not have, ValueError for a value it does not allow.
    """
    opts = dict(options)
    if method == "auto":
        return AutoConfig.from_options(**opts)
    if method == "hybrid":
        if "max_iterations" in opts:
            opts["polish_iterations"] = opts.pop("max_iterations")
        return HybridConfig(**opts)
    if method == "exact":
        return GaussNewtonConfig(**opts)
    if method == "toro":
        if "sweeps" in opts:
            opts["iterations"] = opts.pop("sweeps")
        return ToroConfig(**opts)
    raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")


def option_names(method: str) -> list[str]:
    """The flat option names :func:`config_for` takes for ``method`` (the command line's and
    a batch grid's vocabulary)."""
    from dataclasses import fields

    if method == "auto":
        own = [f.name for f in fields(AutoConfig) if f.name not in ("sweeps", "polish")]
        hybrid = [f.name for f in fields(HybridConfig)
                  if f.name not in ("init", "polish", "polish_iterations", "energy_tolerance")]
        return own + hybrid + ["init", "max_iterations", "energy_tolerance", "linear_solver",
                               "initial_damping"]
    if method == "hybrid":
        return [f.name for f in fields(HybridConfig)] + ["max_iterations"]
    if method == "exact":
        # GaussNewtonConfig.method ("gn"/"lm") cannot pass through optimize(graph, method,
        # **opts), whose own first parameter is called method
        return [f.name for f in fields(GaussNewtonConfig) if f.name != "method"] + [
            "init", "tree"]
    if method == "toro":
        return [f.name for f in fields(ToroConfig)] + ["sweeps"]
    raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")


def optimize(graph: PoseGraph, config: SolverConfig | str = "auto", *,
             progress: Any = None, iterate: Any = None, init: str | None = None,
             tree: str | None = None, **options: Any) -> SolveResult:
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
    iterate : callable, optional
        ``iterate(Progress, rotations, translations)``: the global poses at the same points
        as ``progress`` (e.g. :class:`hybridpgo.recording.RerunRecorder`; the arrays may be the
        solver's own: copy what you keep).  Not for the TORO baseline.
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
        if config != "exact":
            options.update({k: v for k, v in (("init", init), ("tree", tree)) if v is not None})
        config = config_for(config, **options)
    elif options:
        raise TypeError("give either a config object or keyword options, not both")
    elif isinstance(config, AutoConfig) and (
            (init is not None and (init,) != config.inits)
            or (tree is not None and tree != config.sweeps.tree)):
        raise ValueError("the default pipeline's starts and tree are fields of its config")
    elif isinstance(config, (HybridConfig, ToroConfig)) and (
            (init is not None and init != config.init)
            or (tree is not None and tree != config.tree)):
        raise ValueError("this solver's init and tree are fields of its config")
    if isinstance(config, AutoConfig):
        from .auto import solve_auto

        return solve_auto(graph, config, progress=progress, iterate=iterate)
    if isinstance(config, HybridConfig):
        return solve_hybrid(graph, config, progress=progress, iterate=iterate)
    if isinstance(config, ToroConfig):
        if iterate is not None:
            raise ValueError("the TORO baseline reports no poses per iteration (iterate)")
        from .toro import solve_toro

        return solve_toro(graph, config, progress=progress)
    from .gauss_newton import solve_exact

    return solve_exact(graph, *exact_start(graph, init, tree), config, progress=progress,
                       iterate=iterate)


def exact_start(graph: PoseGraph, init: str | None = None,
                tree: str | None = None) -> tuple[Any, Any]:
    """The exact solver's starting poses ``(R, t)`` for ``init`` (default
    :func:`default_init`), grown on ``tree`` (default ``"bfs"``); ``(None, None)`` for the
    file's own poses (``"file"`` falls back to ``"tree"`` when the file has none)."""
    from ..initialization import initial_locals
    from ..tree import build_tree, global_poses

    start = init or default_init(graph, "exact")
    if start == "file" and not graph.has_estimates:
        start = "tree"
    if start == "file":
        return None, None
    t = build_tree(graph, tree or "bfs")
    return global_poses(t, *initial_locals(graph, t, start))
