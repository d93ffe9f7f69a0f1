"""The online mode: a back end fed pose by pose, with a time budget per frame.

:class:`OnlineSolver` (:mod:`.solver`) on the whole-graph solver's kernels; its map in a
:class:`~.store.MapStore`; a worker process keeping the whole map at its optimum with an
incremental exact solver (:mod:`.worker`, :mod:`._link`, :mod:`.incremental`); saved states
(:mod:`.persist`); replaying a graph as a stream, beside GTSAM's iSAM2 (:mod:`.replay`).
"""

from ._frame import FrameReport as FrameReport
from .config import OnlineConfig as OnlineConfig
from .solver import OnlineSolver as OnlineSolver

__all__ = ["FrameReport", "OnlineConfig", "OnlineSolver"]
