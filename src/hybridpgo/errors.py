"""Exception hierarchy.  Every error a user can cause is a :class:`HybridPGOError`."""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator


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


# --------------------------------------------------------------------------- option names
#: True while the command line runs: messages then name CLI flags (``--skip-unknown``) instead
#: of Python parameters (``skip_unknown=True``).
_CLI_NAMES: contextvars.ContextVar[bool] = contextvars.ContextVar("hybridpgo_cli_names",
                                                                  default=False)


@contextlib.contextmanager
def cli_option_names() -> Iterator[None]:
    """Within this block :func:`option_hint` names command-line flags (used by the CLI)."""
    token = _CLI_NAMES.set(True)
    try:
        yield
    finally:
        _CLI_NAMES.reset(token)


def option_hint(parameter: str, *values: str) -> str:
    """How to pass an option, in the caller's terms.

    >>> option_hint("skip_unknown")
    'skip_unknown=True'
    >>> option_hint("fix_information", "nearest", "skip")
    'fix_information="nearest" or "skip"'

    Under :func:`cli_option_names` the same calls give ``--skip-unknown`` and
    ``--fix-information nearest or --fix-information skip``.
    """
    if _CLI_NAMES.get():
        flag = "--" + parameter.replace("_", "-")
        return " or ".join(f"{flag} {v}" for v in values) if values else flag
    if not values:
        return f"{parameter}=True"
    return f"{parameter}=" + " or ".join(f'"{v}"' for v in values)
