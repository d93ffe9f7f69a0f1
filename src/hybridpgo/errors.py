"""Exception hierarchy.  Every error a user can cause is a :class:`HybridPGOError`."""

from __future__ import annotations


class HybridPGOError(Exception):
    """Base class of every error hybridpgo raises on purpose."""


class FormatError(HybridPGOError, ValueError):
    """A file could not be read: names the file, the 1-based line and the problem.

    The message reads like a compiler's: ``garage.g2o:1742: EDGE_SE3:QUAT needs 28 numbers ...``.
    """

    def __init__(self, message: str, path: str | None = None, line_no: int | None = None,
                 line: str | None = None) -> None:
        self.path = path
        self.line_no = line_no
        self.line = line
        self.problem = message
        where = ""
        if path is not None:
            where = f"{path}:{line_no}: " if line_no is not None else f"{path}: "
        super().__init__(where + message)


class GraphError(HybridPGOError, ValueError):
    """The graph itself is unusable (unknown node, disconnected, non-SPD information, ...)."""


class SolverError(HybridPGOError, RuntimeError):
    """A solver could not proceed (non-finite step, singular system, ...)."""
