"""The ``hybridpgo`` command line (STYLE.md §11).

``main(argv)`` parses the arguments, imports the command's module (heavy imports happen only
there, after parsing) and runs it inside the one error boundary:

* :class:`~hybridpgo.errors.HybridPGOError` (bad file, bad graph, solver failure, a missing
  optional package): ``hybridpgo: error: <message>`` on stderr, exit 2;
* ``KeyboardInterrupt``: exit 130; a closed stdout pipe (``| head``): exit 141, silently;
* anything else is a bug: traceback, exit 1.

``--debug`` prints the traceback in every case.  Usage errors from argparse also exit 2.
"""

from __future__ import annotations

import importlib
import os
import sys
import traceback
import warnings
from collections.abc import Sequence
from typing import Any

from ..errors import HybridPGOError

__all__ = ["main"]

#: Exit codes (141 = 128 + SIGPIPE, as a shell reports a reader that went away).
EXIT_OK, EXIT_BUG, EXIT_ERROR, EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 0, 1, 2, 130, 141


def _format_warning(message: Warning | str, category: type[Warning], filename: str,
                    lineno: int, line: str | None = None) -> str:
    """Warnings read like errors: ``hybridpgo: warning: <message>``."""
    return f"hybridpgo: warning: {message}\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``hybridpgo`` command line with ``argv`` (default ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit code: 0 success, 2 user error (bad input or usage), 130 interrupted,
        1 an unexpected error (a bug: the traceback is printed).
    """
    from ._parser import build_parser

    parser = build_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exc:  # --help, --version, usage errors
        return exc.code if isinstance(exc.code, int) else (EXIT_OK if exc.code is None
                                                           else EXIT_ERROR)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_ERROR
    debug = bool(getattr(args, "debug", False))
    # formatwarning, not showwarning: recorders (pytest.warns, catch_warnings(record=True)) of
    # in-process callers keep working; restored afterwards
    saved = warnings.formatwarning
    warnings.formatwarning = _format_warning
    from ._progress import configure

    configure(force=bool(getattr(args, "progress", False)))  # --progress: draw off a terminal
    try:
        return _run(args, debug)
    finally:
        warnings.formatwarning = saved
        configure(force=False)


def _run(args: Any, debug: bool) -> int:
    try:
        module = importlib.import_module(f"{__name__}.{args.command}")
        return int(module.run(args))
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc()
        print("\nhybridpgo: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except HybridPGOError as exc:
        if debug:
            traceback.print_exc()
        print(f"hybridpgo: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except BrokenPipeError:  # e.g. "hybridpgo info FILE | head -1"
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):  # pragma: no cover - stdout without a descriptor
            pass
        return EXIT_BROKEN_PIPE
    except Exception:
        traceback.print_exc()
        print("hybridpgo: internal error (a bug): please report it with the traceback above",
              file=sys.stderr)
        return EXIT_BUG
