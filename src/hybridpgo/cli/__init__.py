"""The ``hybridpgo`` command line (docs/contributing.md#cli).

``main(argv)`` parses the arguments, imports the command's module (heavy imports happen only
there, after parsing) and runs it inside the one error boundary:

* :class:`~hybridpgo.errors.HybridPGOError` (bad file, bad graph, solver failure, a missing
  optional package): ``hybridpgo: error: <message>`` on stderr, exit 2;
* ``KeyboardInterrupt`` (also during start-up: parsing, imports): "interrupted", exit 130; a
  closed stdout pipe (``| head``): exit 141, silently;
* anything else is a bug: traceback, exit 1.

Before a command runs, every file it will write is checked (``_common.check_outputs``): a
command writes all its outputs or none, and never overwrites an input.  With ``-`` as an output
(``-o -``) the graph goes to standard output and the command's own report to stderr.  Messages
name command-line flags (``--skip-unknown``), not the library's parameters.

``--debug`` prints the traceback in every case.  Usage errors from argparse also exit 2.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
import traceback
import warnings
from collections.abc import Iterator, Sequence
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
    try:
        return _main(argv)
    except KeyboardInterrupt:  # during start-up (parsing, imports) or outside _run's boundary
        print("\nhybridpgo: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _main(argv: Sequence[str] | None) -> int:
    from . import _parser

    parser = _parser.build_parser()
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


@contextlib.contextmanager
def _graph_to_stdout(args: Any) -> Iterator[None]:
    """With ``-o -`` the graph is written to the real standard output and everything else the
    command prints goes to stderr, so the graph stays clean for a pipe."""
    from ._common import uses_stdout

    if not uses_stdout(args):
        yield
        return
    from ..io._lines import STDOUT_TARGET

    token = STDOUT_TARGET.set(sys.stdout)
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        STDOUT_TARGET.reset(token)


def _run(args: Any, debug: bool) -> int:
    try:
        from ..errors import cli_option_names
        from ._common import ReadOptions, check_outputs, command_files, read_options

        check_outputs(*command_files(args))
        with cli_option_names(), read_options(ReadOptions.from_args(args)), \
                _graph_to_stdout(args):
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
