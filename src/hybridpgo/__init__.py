"""hybridpgo: pose-graph optimization with hybrid Hessians."""

from .errors import FormatError as FormatError
from .errors import GraphError as GraphError
from .errors import HybridPGOError as HybridPGOError
from .errors import SolverError as SolverError
from .energy import energy as energy
from .graph import PoseGraph as PoseGraph
from .io import read_graph as read_graph
from .io import write_graph as write_graph
from .solvers import GaussNewtonConfig as GaussNewtonConfig
from .solvers import HybridConfig as HybridConfig
from .solvers import SolveResult as SolveResult
from .solvers import optimize as optimize
from .tree import build_tree as build_tree

__version__ = "0.1.0"
