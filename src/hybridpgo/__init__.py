"""hybridpgo: pose-graph optimization with hybrid Hessians."""

from .errors import FormatError as FormatError
from .errors import GraphError as GraphError
from .errors import HybridPGOError as HybridPGOError
from .errors import SolverError as SolverError
from .graph import PoseGraph as PoseGraph

__version__ = "0.1.0"
