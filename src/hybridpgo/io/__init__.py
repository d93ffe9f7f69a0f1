"""Reading and writing pose-graph files: g2o, TORO and iSAM (docs/conventions.md); TUM trajectories.

>>> from hybridpgo.io import read_graph, write_graph, bundled_path
>>> g = read_graph(bundled_path("M3500_isam.txt"))        # format detected from the content
>>> write_graph(g, "m3500.g2o")                           # iSAM source -> g2o by default

Every reader returns a :class:`~hybridpgo.graph.PoseGraph` whose ``node_ids`` are the file's ids,
sorted (dense index = rank), with the edges in file order.  Every problem with a file raises
:class:`~hybridpgo.errors.FormatError` whose message reads ``"{path}:{line}: {problem}"`` (or
``"{path}: {problem}"`` for the file as a whole).  Writers are atomic and write numbers with
``repr`` precision, so write -> read reproduces the arrays to float64 rounding.

The path ``"-"`` means standard input (readers) or standard output (writers); a file literally
named ``-`` is ``./-``.  ``write_graph`` can also write a TUM trajectory (poses only, with a
warning that the constraints are lost).  Information that is not positive definite raises unless
``fix_information`` is ``"nearest"`` (projected) or ``"skip"`` (dropped).
"""

from __future__ import annotations

import importlib.resources
import os
import pathlib
import warnings

from ..errors import FormatError
from ..graph import PoseGraph
from ._lines import FIX_INFORMATION as FIX_INFORMATION
from ._lines import NEAREST_SPD_FLOOR as NEAREST_SPD_FLOOR
from ._lines import (
    PathLike,
    Source,
    check_fix_information,
    load_source,
    source_from_text,
    write_atomic,
)
from .g2o import TAGS as _G2O_TAGS
from .g2o import g2o_lines as _g2o_lines
from .g2o import read_g2o as read_g2o
from .g2o import read_g2o_source as _read_g2o_source
from .g2o import write_g2o as write_g2o
from .isam import TAGS as _ISAM_TAGS
from .isam import isam_lines as _isam_lines
from .isam import read_isam as read_isam
from .isam import read_isam_source as _read_isam_source
from .isam import write_isam as write_isam
from .toro import EDGE3_ORDERS as EDGE3_ORDERS
from .toro import TAGS as _TORO_TAGS
from .toro import read_toro as read_toro
from .toro import read_toro_source as _read_toro_source
from .toro import toro_lines as _toro_lines
from .toro import write_toro as write_toro
from .tum import graph_tum_lines as _graph_tum_lines
from .tum import read_tum as read_tum
from .tum import write_tum as write_tum

__all__ = [
    "EDGE3_ORDERS",
    "FIX_INFORMATION",
    "FORMATS",
    "NEAREST_SPD_FLOOR",
    "SUPPORTED_TAGS",
    "WRITE_FORMATS",
    "bundled_names",
    "bundled_path",
    "detect_format",
    "read_g2o",
    "read_graph",
    "read_isam",
    "read_toro",
    "read_tum",
    "write_g2o",
    "write_graph",
    "write_isam",
    "write_toro",
    "write_tum",
]

#: The graph formats, by the names ``read_graph``/``write_graph`` accept.
FORMATS: tuple[str, ...] = ("g2o", "toro", "isam")
#: What ``write_graph`` can write: the graph formats and TUM (poses only).
WRITE_FORMATS: tuple[str, ...] = (*FORMATS, "tum")

#: Tags each reader understands.  ``EDGE2``/``EDGE3`` belong to both TORO and iSAM.
SUPPORTED_TAGS: dict[str, tuple[str, ...]] = {
    "g2o": _G2O_TAGS,
    "toro": _TORO_TAGS,
    "isam": _ISAM_TAGS,
}


def _check_format(fmt: str) -> None:
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)} (or None), got {fmt!r}")


def _detect(src: Source) -> str:
    """First tag (in file order) that only one format uses decides.

    ``EDGE2``/``EDGE3`` are both TORO and iSAM: a file with only those is iSAM (iSAM files have
    no vertex lines, TORO files do), unless an ``EDGE3`` line lacks information (TORO 3D).
    """
    if not src.groups:
        raise src.error(None, "empty file: no vertex or edge lines found")
    ambiguous = False
    for tag in src.groups:  # dict order = order of first appearance
        owners = [f for f in FORMATS if tag in SUPPORTED_TAGS[f]]
        if len(owners) == 1:
            return owners[0]
        ambiguous = ambiguous or len(owners) > 1
    if ambiguous:
        if "EDGE3" in src.groups and src.count_fields("EDGE3", 8):
            return "toro"
        return "isam"
    listing = "; ".join(f"{f}: {', '.join(SUPPORTED_TAGS[f])}" for f in FORMATS)
    first = next(iter(src.groups))
    raise src.error(src.first_line(first), f"cannot detect the file format: tag {first!r} and "
                    f"the file's other tags belong to no supported format ({listing})")


def detect_format(path: PathLike) -> str:
    """The format of ``path`` ("g2o", "toro" or "isam"), from the first recognized tag.

    Raises
    ------
    FormatError
        When the file is unreadable, empty, or has no recognized tag.
    """
    return _detect(load_source(path))


def read_graph(path: PathLike, format: str | None = None, *, skip_unknown: bool = False,
               toro_edge3_order: str = "documented", check_connected: bool = True,
               fix_information: str | None = None) -> PoseGraph:
    """Read a pose graph in any supported format.

    Parameters
    ----------
    path
        The file; ``"-"`` reads standard input.
    format
        "g2o", "toro", "isam", or None to detect it from the content (:func:`detect_format`).
    skip_unknown
        Skip lines with tags the format does not support (one warning with the count per
        file) instead of raising.
    toro_edge3_order
        TORO ``EDGE3`` information order: "documented" (translation first) or "code"
        (rotation first, as TORO's own code reads it).  Ignored for other formats.
    check_connected
        Raise when the graph is not connected (the solvers need one connected graph).
    fix_information
        What to do with information matrices that are not positive definite: None raises
        (naming the first line and how many lines have one), "nearest" projects them onto the
        nearest positive definite matrix (eigenvalues clipped at :data:`NEAREST_SPD_FLOOR`
        times the largest), "skip" drops those lines; both warn once with the count.

    Returns
    -------
    PoseGraph
        With ``source_format`` set to the format read.

    Raises
    ------
    FormatError
        For any problem with the file: ``"{path}:{line}: {problem}"``.
    ValueError
        For an unknown ``format``, ``toro_edge3_order`` or ``fix_information`` (a programming
        error).
    """
    if format is not None:
        _check_format(format)
    if toro_edge3_order not in EDGE3_ORDERS:
        raise ValueError(f"toro_edge3_order must be one of {EDGE3_ORDERS}, got "
                         f"{toro_edge3_order!r}")
    check_fix_information(fix_information)
    return read_graph_source(load_source(path, fix_information), format,
                             skip_unknown=skip_unknown, toro_edge3_order=toro_edge3_order,
                             check_connected=check_connected)


def read_graph_source(src: Source, format: str | None = None, *, skip_unknown: bool = False,
                      toro_edge3_order: str = "documented",
                      check_connected: bool = True) -> PoseGraph:
    """:func:`read_graph` of a loaded :class:`~hybridpgo.io._lines.Source` (its
    ``fix_information`` applies)."""
    fmt = format if format is not None else _detect(src)
    if fmt == "g2o":
        return _read_g2o_source(src, skip_unknown=skip_unknown, check_connected=check_connected)
    if fmt == "toro":
        return _read_toro_source(src, skip_unknown=skip_unknown, edge3_order=toro_edge3_order,
                                 check_connected=check_connected)
    return _read_isam_source(src, skip_unknown=skip_unknown, check_connected=check_connected)


def default_write_format(graph: PoseGraph) -> str:
    """``graph.source_format``, except that graphs read from iSAM (which cannot hold vertex
    estimates) or built in code are written as g2o."""
    return graph.source_format if graph.source_format in ("g2o", "toro") else "g2o"


def graph_lines(graph: PoseGraph, format: str, name: str = "<memory>") -> list[str]:
    """The lines :func:`write_graph` would write, without writing them (``name`` for
    messages).  Raises as :func:`write_graph`; warns about a TUM output."""
    if format not in WRITE_FORMATS:
        raise ValueError(f"format must be one of {', '.join(WRITE_FORMATS)} (or None), got "
                         f"{format!r}")
    if format == "g2o":
        return list(_g2o_lines(graph, name))  # the writer yields chunks
    if format == "toro":
        return _toro_lines(graph, name)
    if format == "isam":
        return _isam_lines(graph, name)
    lines = _graph_tum_lines(graph, name)
    lost = [f"{graph.num_edges} relative constraints"]
    if graph.num_gps:
        lost.append(f"{graph.num_gps} GPS constraints")
    if graph.fixed_nodes.size:
        lost.append(f"{graph.fixed_nodes.size} FIX lines")
    warnings.warn(f"{name}: the TUM format holds poses only: the {' and the '.join(lost)} are "
                  "not written", UserWarning, stacklevel=3)
    return lines


def write_graph(graph: PoseGraph, path: PathLike, format: str | None = None) -> None:
    """Write ``graph`` atomically (temporary file in the same directory, then ``os.replace``;
    see :func:`~hybridpgo.io._lines.write_atomic` for symlinks, FIFOs and ``"-"``, standard
    output).

    Parameters
    ----------
    format
        "g2o", "toro", "isam" or "tum" (poses only, timestamp = pose id; warns that the
        constraints are lost).  None: :func:`default_write_format`.

    Raises
    ------
    FormatError
        When the format cannot hold the graph (e.g. GPS priors in TORO/iSAM, no poses for
        TUM) or the file cannot be written.
    """
    if format is None:
        format = default_write_format(graph)
    name = os.fspath(path)
    lines = graph_lines(graph, format, name)
    write_atomic(path, lambda: lines)


def read_back(lines: list[str], format: str, name: str) -> PoseGraph:
    """Read ``lines`` (what a writer produced) back from memory, as ``convert`` checks."""
    src = source_from_text("\n".join(lines) + "\n", name)
    return read_graph_source(src, format, check_connected=False)


# --------------------------------------------------------------------------- bundled data
def _data_dir() -> pathlib.Path:
    return pathlib.Path(str(importlib.resources.files("hybridpgo") / "data"))


def bundled_names() -> list[str]:
    """Names of the graph files shipped in ``hybridpgo/data`` (see its README.md)."""
    d = _data_dir()
    if not d.is_dir():
        return []
    return sorted(p.name for p in d.iterdir()
                  if p.is_file() and p.suffix in (".g2o", ".graph", ".txt"))


def bundled_path(name: str) -> pathlib.Path:
    """Path of a bundled graph file, e.g. ``bundled_path("M3500_isam.txt")`` (the demo graph).

    Raises
    ------
    FormatError
        When there is no bundled file of that name (the message lists the available ones).
    """
    path = _data_dir() / name
    if os.path.basename(name) != name or name not in bundled_names() or not path.is_file():
        raise FormatError(f"no bundled graph named {name!r}; available: "
                          + (", ".join(bundled_names()) or "none"))
    return path
