"""Reading and writing pose-graph files: g2o, TORO and iSAM (DESIGN.md §1).

>>> from hybridpgo.io import read_graph, write_graph, bundled_path
>>> g = read_graph(bundled_path("M3500_isam.txt"))        # format detected from the content
>>> write_graph(g, "m3500.g2o")                           # iSAM source -> g2o by default

Every reader returns a :class:`~hybridpgo.graph.PoseGraph` whose ``node_ids`` are the file's ids,
sorted (dense index = rank), with the edges in file order.  Every problem with a file raises
:class:`~hybridpgo.errors.FormatError` whose message reads ``"{path}:{line}: {problem}"`` (or
``"{path}: {problem}"`` for the file as a whole).  Writers are atomic and write numbers with
``repr`` precision, so write -> read reproduces the arrays to float64 rounding.
"""

from __future__ import annotations

import importlib.resources
import os
import pathlib

from ..errors import FormatError
from ..graph import PoseGraph
from ._lines import PathLike, Source, load_source
from .g2o import TAGS as _G2O_TAGS
from .g2o import read_g2o as read_g2o
from .g2o import read_g2o_source as _read_g2o_source
from .g2o import write_g2o as write_g2o
from .isam import TAGS as _ISAM_TAGS
from .isam import read_isam as read_isam
from .isam import read_isam_source as _read_isam_source
from .isam import write_isam as write_isam
from .toro import EDGE3_ORDERS as EDGE3_ORDERS
from .toro import TAGS as _TORO_TAGS
from .toro import read_toro as read_toro
from .toro import read_toro_source as _read_toro_source
from .toro import write_toro as write_toro

__all__ = [
    "EDGE3_ORDERS",
    "FORMATS",
    "SUPPORTED_TAGS",
    "bundled_names",
    "bundled_path",
    "detect_format",
    "read_g2o",
    "read_graph",
    "read_isam",
    "read_toro",
    "write_g2o",
    "write_graph",
    "write_isam",
    "write_toro",
]

#: The formats, by the names ``read_graph``/``write_graph`` accept.
FORMATS: tuple[str, ...] = ("g2o", "toro", "isam")

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
               toro_edge3_order: str = "documented", check_connected: bool = True) -> PoseGraph:
    """Read a pose graph in any supported format.

    Parameters
    ----------
    path
        The file.
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

    Returns
    -------
    PoseGraph
        With ``source_format`` set to the format read.

    Raises
    ------
    FormatError
        For any problem with the file: ``"{path}:{line}: {problem}"``.
    ValueError
        For an unknown ``format`` or ``toro_edge3_order`` (a programming error).
    """
    if format is not None:
        _check_format(format)
    if toro_edge3_order not in EDGE3_ORDERS:
        raise ValueError(f"toro_edge3_order must be one of {EDGE3_ORDERS}, got "
                         f"{toro_edge3_order!r}")
    src = load_source(path)
    fmt = format if format is not None else _detect(src)
    if fmt == "g2o":
        return _read_g2o_source(src, skip_unknown=skip_unknown, check_connected=check_connected)
    if fmt == "toro":
        return _read_toro_source(src, skip_unknown=skip_unknown, edge3_order=toro_edge3_order,
                                 check_connected=check_connected)
    return _read_isam_source(src, skip_unknown=skip_unknown, check_connected=check_connected)


def write_graph(graph: PoseGraph, path: PathLike, format: str | None = None) -> None:
    """Write ``graph`` atomically (temporary file in the same directory, then ``os.replace``).

    Parameters
    ----------
    format
        "g2o", "toro" or "isam".  None: ``graph.source_format``, except that graphs read from
        iSAM (which cannot hold vertex estimates) or built in code are written as g2o.

    Raises
    ------
    FormatError
        When the format cannot hold the graph (e.g. GPS priors in TORO/iSAM) or the file cannot
        be written.
    """
    if format is None:
        format = graph.source_format if graph.source_format in ("g2o", "toro") else "g2o"
    _check_format(format)
    if format == "g2o":
        write_g2o(graph, path)
    elif format == "toro":
        write_toro(graph, path)
    else:
        write_isam(graph, path)


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
