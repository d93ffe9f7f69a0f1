"""Helpers shared by the CLI commands: reading inputs, choosing output formats, the progress
bar, and printing summaries.  Results go to stdout, progress and logs to stderr (STYLE.md §11).
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import IO, TYPE_CHECKING, Any

from ..errors import HybridPGOError
from ._progress import ProgressBar as ProgressBar
from ._progress import phase as phase

if TYPE_CHECKING:
    from ..graph import FloatArray, PoseGraph

#: Output format from a file name's extension (``convert``; ``optimize`` ignores ``.txt``).
FORMAT_FROM_SUFFIX: dict[str, str] = {".g2o": "g2o", ".graph": "toro", ".txt": "isam"}


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


def read_input(path: str, fmt: str | None, *, skip_unknown: bool = False,
               check_connected: bool = True) -> PoseGraph:
    """Read a graph file for a command (every problem is a FormatError/GraphError)."""
    from ..io import read_graph

    return read_graph(path, format=fmt, skip_unknown=skip_unknown,
                      check_connected=check_connected)


def output_format(path: str, explicit: str | None, graph: PoseGraph, *,
                  allow_isam: bool) -> str:
    """The format to write: ``explicit`` > the extension of ``path`` > the input's format.

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
    from ..tree import build_tree, global_poses, initial_locals

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
