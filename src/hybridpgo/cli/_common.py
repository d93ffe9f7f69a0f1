"""Helpers shared by the CLI commands: reading inputs, choosing output formats, the progress
bar, and printing summaries.  Results go to stdout, progress and logs to stderr
(docs/contributing.md#cli).
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING, Any

from .._output import check_output, same_file
from ..errors import FormatError, HybridPGOError
from ._progress import ProgressBar as ProgressBar
from ._progress import phase as phase

if TYPE_CHECKING:
    from ..graph import FloatArray, PoseGraph

#: Output format from a file name's extension (``convert``; ``optimize`` ignores ``.txt``).
FORMAT_FROM_SUFFIX: dict[str, str] = {".g2o": "g2o", ".graph": "toro", ".txt": "isam",
                                      ".tum": "tum"}

#: The path that means standard input / standard output.
STDIO = "-"
#: Output paths that mean standard output (as ``hybridpgo.io._lines.STDOUT_NAMES``).
STDOUT_NAMES = (STDIO, "/dev/stdout")


class LazyChoices:
    """``choices=`` for argparse that are looked up only when needed (help text or validation).

    Used for lists that live in modules the CLI imports only after parsing (city presets).
    When the module cannot be imported, every value is accepted here and the command itself
    reports the problem.
    """

    def __init__(self, load: Callable[[], Sequence[str]]) -> None:
        self._load = load
        self._values: list[str] | None = None

    def _get(self) -> list[str] | None:
        if self._values is None:
            try:
                self._values = list(self._load())
            except ImportError:
                return None
        return self._values

    def __contains__(self, item: object) -> bool:
        values = self._get()
        return True if values is None else item in values

    def __iter__(self) -> Iterator[str]:
        return iter(self._get() or [])

    def __len__(self) -> int:
        return len(self._get() or [])


def log(message: str) -> None:
    """A log line on stderr."""
    print(message, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class ReadOptions:
    """Options of the command line that apply to every graph a command reads."""

    fix_information: str | None = None
    """``--fix-information``: None, "nearest" or "skip" (see :func:`hybridpgo.io.read_graph`)."""
    fix_ids: tuple[int, ...] = ()
    """``--fix ID`` (optimize): pose ids to hold fixed, added to the file's ``FIX`` lines."""

    @classmethod
    def from_args(cls, args: Any) -> ReadOptions:
        return cls(fix_information=getattr(args, "fix_information", None),
                   fix_ids=tuple(getattr(args, "fix", None) or ()))


_NO_READ_OPTIONS = ReadOptions()
_READ_OPTIONS: contextvars.ContextVar[ReadOptions] = contextvars.ContextVar(
    "hybridpgo_read_options", default=_NO_READ_OPTIONS)


@contextlib.contextmanager
def read_options(options: ReadOptions) -> Iterator[None]:
    """Within this block :func:`read_input` applies ``options`` (set by ``main`` per command)."""
    token = _READ_OPTIONS.set(options)
    try:
        yield
    finally:
        _READ_OPTIONS.reset(token)


def read_input(path: str, fmt: str | None, *, skip_unknown: bool = False,
               check_connected: bool = True) -> PoseGraph:
    """Read a graph file for a command (every problem is a FormatError/GraphError).

    ``"-"`` reads standard input.  The command's ``--fix-information`` applies, and ``--fix ID``
    adds ``ID`` to the graph's fixed poses (``PoseGraph.fixed_nodes``, as a ``FIX`` line would).
    """
    from ..io import read_graph

    opts = _READ_OPTIONS.get()
    graph = read_graph(path, format=fmt, skip_unknown=skip_unknown,
                       check_connected=check_connected, fix_information=opts.fix_information)
    if opts.fix_ids:
        graph = with_fixed(graph, opts.fix_ids, path)
    return graph


def with_fixed(graph: PoseGraph, ids: Sequence[int], path: str) -> PoseGraph:
    """``graph`` with the poses of file ids ``ids`` added to ``fixed_nodes`` (``--fix``)."""
    import dataclasses

    import numpy as np

    index = graph.index_from_id()
    missing = [i for i in ids if i not in index]
    if missing:
        raise HybridPGOError(f"--fix {missing[0]}: {path} has no pose with id {missing[0]} "
                             f"(ids {int(graph.node_ids[0])}..{int(graph.node_ids[-1])})")
    fixed = list(graph.fixed_nodes.tolist())
    fixed += [index[i] for i in ids if index[i] not in fixed]
    return dataclasses.replace(graph, fixed_nodes=np.array(fixed, np.int32))


# --------------------------------------------------------------------------- outputs
@dataclass(frozen=True)
class Output:
    """A file a command will write: its path, the option that named it, and whether ``-``
    (standard output) is allowed for it."""

    path: str
    option: str
    stdout_ok: bool = False


def check_outputs(inputs: Sequence[str], outputs: Sequence[Output]) -> None:
    """Check every output before any work, so that a command writes all its files or none.

    Refuses (:class:`HybridPGOError`, exit 2): an empty path; ``-`` where standard output is not
    allowed, or for two outputs; two ``-`` inputs (standard input can be read once); an output
    that is an input (the same file: same device and inode, also through a symbolic or hard
    link, or the file standard input reads with ``-``: no command may destroy an input); two
    outputs that are one file; an existing directory, socket or block device; a directory that
    does not exist or where no file can be created (probed by creating and removing the
    temporary file the writer will create).  A FIFO or character device (``/dev/null``) is
    accepted and written into; a symbolic link is written through (its target is replaced).
    """
    if sum(1 for p in inputs if p == STDIO) > 1:
        raise HybridPGOError("standard input ('-') can be read only once: give '-' for at most "
                             "one input")
    stdout_users = [o for o in outputs if o.path in STDOUT_NAMES]
    for o in stdout_users:
        if not o.stdout_ok:
            raise HybridPGOError(f"{o.option} {o.path}: this output cannot go to standard "
                                 "output; give a file name")
    if len(stdout_users) > 1:
        raise HybridPGOError(f"{stdout_users[0].option} and {stdout_users[1].option}: only one "
                             "output can go to standard output ('-')")
    files = [o for o in outputs if o.path not in STDOUT_NAMES]
    real_inputs = [p for p in inputs if p != STDIO]
    stdin_id = _stdin_identity() if STDIO in inputs else None
    for k, o in enumerate(files):
        if o.path == "":
            raise HybridPGOError(f"{o.option}: the output path is empty")
        for inp in real_inputs:
            if same_file(o.path, inp):
                raise HybridPGOError(f"{o.path}: {o.option} is the input file {inp}; refusing to "
                                     "overwrite it (choose another output name)")
        if stdin_id is not None and _identity(o.path) == stdin_id:
            raise HybridPGOError(f"{o.path}: {o.option} is the file standard input reads ('-'); "
                                 "refusing to overwrite it (choose another output name)")
        for other in files[:k]:
            if same_file(o.path, other.path):
                raise HybridPGOError(f"{o.path}: would be written twice ({other.option} and "
                                     f"{o.option} name the same file)")
        try:
            check_output(o.path)
        except FormatError as exc:
            why = exc.problem.removeprefix("cannot write the file: ")
            raise HybridPGOError(f"{o.path}: cannot write {o.option}: {why}") from exc


def _identity(path: str) -> tuple[int, int] | None:
    """(device, inode) of the file at ``path`` (through links), or None."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _stdin_identity() -> tuple[int, int] | None:
    """(device, inode) of the file standard input reads, or None (closed, no descriptor)."""
    try:
        st = os.fstat(sys.stdin.fileno())
    except (AttributeError, OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def command_files(args: Any) -> tuple[list[str], list[Output]]:
    """The graph/trajectory/figure files a parsed command reads and writes (for
    :func:`check_outputs`).  ``generate`` and ``demo`` check their own outputs."""
    cmd = args.command
    if cmd == "info":
        res = getattr(args, "residuals", None)
        return [args.file], ([] if res is None else [Output(res, "--residuals", stdout_ok=True)])
    if cmd == "optimize":
        outs = [Output(args.output, "-o/--output", stdout_ok=True)]
        if args.plot is not None:
            outs += [Output(f"{args.plot}_{k}.png", "--plot") for k in ("before", "after",
                                                                        "energy")]
        if getattr(args, "covariance", None) is not None:
            outs.append(Output(args.covariance, "--covariance"))
        if getattr(args, "rerun", None) is not None:
            outs.append(Output(args.rerun, "--rerun"))
        return [args.file], outs
    if cmd == "replay":
        outs = []
        if args.plot is not None:
            outs += [Output(f"{args.plot}_{k}.png", "--plot") for k in ("latency", "energy")]
        if getattr(args, "rerun", None) is not None:
            outs.append(Output(args.rerun, "--rerun"))
        return [args.file], outs
    if cmd in ("convert", "noisify"):
        option = "OUT" if cmd == "convert" else "-o/--output"
        return [args.input], [Output(args.output, option, stdout_ok=True)]
    if cmd == "plot":
        inputs = [args.file] + ([args.optimized] if args.optimized is not None else [])
        return inputs, [Output(args.output, "-o/--output")]
    if cmd == "evaluate":
        outs = []
        if args.tum is not None:
            from .evaluate import tum_ground_truth_path

            outs = [Output(args.tum, "--tum"), Output(tum_ground_truth_path(args.tum), "--tum")]
        return [args.file, args.ground_truth], outs
    return [], []


def uses_stdout(args: Any) -> bool:
    """True when the command writes a file to standard output (``-o -``)."""
    return any(o.path in STDOUT_NAMES for o in command_files(args)[1])


def output_format(path: str, explicit: str | None, graph: PoseGraph, *,
                  allow_isam: bool) -> str:
    """The format to write: ``explicit`` > the extension of ``path`` > the input's format.

    ``.tum`` (or ``--out-format tum``) writes the poses as a TUM trajectory (the constraints are
    lost, with a warning).

    An input read from iSAM is written as g2o unless ``allow_isam`` (iSAM has no vertex lines, so
    writing optimized poses to it would lose them).  With ``allow_isam`` False, the ``.txt``
    extension does not select iSAM either.
    """
    if explicit is not None:
        if explicit == "isam" and not allow_isam:
            raise HybridPGOError(
                f"{path}: the iSAM format has no vertex lines, so the optimized poses would be "
                "lost; write g2o or toro (--out-format g2o)")
        return explicit
    suffix = os.path.splitext(path)[1].lower()
    by_suffix = FORMAT_FROM_SUFFIX.get(suffix)
    if by_suffix is not None and (by_suffix != "isam" or allow_isam):
        return by_suffix
    src = graph.source_format
    if src == "isam" and not allow_isam:
        return "g2o"
    return src if src in ("g2o", "toro", "isam") else "g2o"


def tree_initial_poses(graph: PoseGraph, tree_kind: str = "bfs",
                       ) -> tuple[FloatArray, FloatArray]:
    """Global poses of the paper's tree initialization (concatenated tree-edge measurements)."""
    from ..initialization import initial_locals
    from ..tree import build_tree, global_poses

    tree = build_tree(graph, tree_kind)
    return global_poses(tree, *initial_locals(graph, tree, "tree"))


def display_poses(graph: PoseGraph) -> tuple[FloatArray, FloatArray]:
    """The file's poses, or the tree initialization when the file has none (iSAM)."""
    if graph.has_estimates:
        return graph.rotations, graph.translations
    return tree_initial_poses(graph)


def describe_graph(graph: PoseGraph) -> str:
    """One line: ``isam, 2D, 3500 poses, 5598 relative constraints, 0 GPS``."""
    dim = "2D" if graph.is_2d else "3D"
    fmt = f"{graph.source_format}, " if graph.source_format else ""
    return (f"{fmt}{dim}, {graph.num_nodes} poses, "
            f"{graph.num_edges} relative constraints, {graph.num_gps} GPS")


def print_json(data: dict[str, Any], stream: IO[str] | None = None) -> None:
    """Print ``data`` as indented JSON (NaN/inf become null)."""
    print(json.dumps(_clean(data), indent=2), file=stream or sys.stdout)


def _clean(v: Any) -> Any:
    import math

    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if hasattr(v, "item") and callable(v.item):  # NumPy scalar
        return _clean(v.item())
    return v


def print_table(rows: Sequence[tuple[str, str]], stream: IO[str] | None = None) -> None:
    """Print ``label  value`` rows with aligned labels."""
    out = stream or sys.stdout
    width = max((len(k) for k, _ in rows), default=0)
    for key, value in rows:
        print(f"{key:<{width}}  {value}", file=out)


def fmt_energy(e: float, num_constraints: int) -> str:
    """``3.2780e+06 (585.567 per constraint)``."""
    per = e / max(num_constraints, 1)
    return f"{e:.6g} ({per:.6g} per constraint)"
