"""hybridpgo: pose-graph optimization with hybrid Hessians (Grimes, Anguelov & LeCun, 2010).

>>> import hybridpgo
>>> graph = hybridpgo.read_graph("input.g2o")               # doctest: +SKIP
>>> result = hybridpgo.optimize(graph)  # default pipeline: start, sweeps, LM  # doctest: +SKIP
>>> hybridpgo.write_graph(graph.with_poses(result.rotations, result.translations), "out.g2o")
... # doctest: +SKIP

The public names load lazily, so ``import hybridpgo`` (and ``hybridpgo --help``) stays fast;
Numba and SciPy load when a solver or reader is first used.

``hybridpgo.energy`` is the module :mod:`hybridpgo.energy` (``residuals``, ``robust_energy``,
...); calling it, ``hybridpgo.energy(graph)``, returns the energy :func:`hybridpgo.energy.energy`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .errors import FormatError as FormatError
from .errors import GraphError as GraphError
from .errors import HybridPGOError as HybridPGOError
from .errors import SolverError as SolverError

__version__ = "0.1.0"

#: Submodules that are public names themselves (loaded lazily like the functions).
_MODULES = {"energy": ".energy"}
_LAZY = {
    "PoseGraph": ".graph",
    "read_graph": ".io",
    "write_graph": ".io",
    "AutoConfig": ".solvers",
    "GaussNewtonConfig": ".solvers",
    "HybridConfig": ".solvers",
    "SolveResult": ".solvers",
    "optimize": ".solvers",
    "build_tree": ".tree",
    "OnlineSolver": ".online",
    "OnlineConfig": ".online",
}

__all__ = ["FormatError", "GraphError", "HybridPGOError", "SolverError", *_MODULES, *_LAZY]


if TYPE_CHECKING:
    from . import energy as energy
    from .graph import PoseGraph as PoseGraph
    from .io import read_graph as read_graph
    from .io import write_graph as write_graph
    from .online import OnlineConfig as OnlineConfig
    from .online import OnlineSolver as OnlineSolver
    from .solvers import AutoConfig as AutoConfig
    from .solvers import GaussNewtonConfig as GaussNewtonConfig
    from .solvers import HybridConfig as HybridConfig
    from .solvers import SolveResult as SolveResult
    from .solvers import optimize as optimize
    from .tree import build_tree as build_tree


def __getattr__(name: str) -> Any:
    if name in _MODULES:  # the import system binds the submodule as an attribute itself
        return importlib.import_module(_MODULES[name], __name__)
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'hybridpgo' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*__all__, "__version__"])
