"""TUM trajectories (poses only): ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments.

The format of the TUM RGB-D benchmark and of ``evo``.  A pose graph written as TUM keeps its
poses (timestamp = the pose id, written as an integer) and loses every constraint, so
:func:`hybridpgo.io.write_graph` warns when it writes one.  :func:`read_tum` is used for ground
truth (:func:`hybridpgo.metrics.read_ground_truth`).
"""

from __future__ import annotations

import io

import numpy as np
import numpy.typing as npt

from ..errors import FormatError
from ..graph import PoseGraph
from ._lines import (
    FloatArray,
    PathLike,
    Source,
    fmt_floats,
    load_source,
    matrix_to_quat_xyzw,
    parse_float,
    quat_xyzw_to_matrix,
    show_token,
    write_atomic,
)

__all__ = ["read_tum", "read_tum_source", "tum_lines", "write_tum"]

_FIELDS = 8


def read_tum(path: PathLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Read a TUM trajectory (``"-"``: standard input).

    Returns
    -------
    timestamps : (N,) float64
    rotations : (N, 3, 3) float64
    translations : (N, 3) float64

    Raises
    ------
    FormatError
        Naming the line of the first malformed row (wrong count, not an ASCII number, not
        finite, zero quaternion), or for an empty or unreadable file.
    """
    return read_tum_source(load_source(path))


def _data_lines(src: Source) -> tuple[list[int], list[str]]:
    nos, rows = [], []
    for no, line in enumerate(src.lines, start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            nos.append(no)
            rows.append(line)
    return nos, rows


def read_tum_source(src: Source) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`read_tum` of an already loaded :class:`~hybridpgo.io._lines.Source`."""
    nos, rows = _data_lines(src)
    if not rows:
        raise src.error(None, "empty file: no trajectory lines found")
    data = _parse_fast(rows)
    if data is None:
        data = _parse_slow(src, nos, rows)
    if not (np.abs(data[:, 4:8]).max(axis=1) > 0.0).all():
        k = int(np.nonzero(~(np.abs(data[:, 4:8]).max(axis=1) > 0.0))[0][0])
        raise src.error(nos[k], "values must be finite and the quaternion non-zero")
    return (np.ascontiguousarray(data[:, 0]), quat_xyzw_to_matrix(data[:, 4:8]),
            np.ascontiguousarray(data[:, 1:4]))


def _parse_fast(rows: list[str]) -> FloatArray | None:
    text = "\n".join(rows)
    if not text.isascii():
        return None
    try:
        data = np.loadtxt(io.StringIO(text), dtype=np.float64, comments=None, ndmin=2)
    except (ValueError, OverflowError):
        return None
    if data.shape != (len(rows), _FIELDS) or not np.isfinite(data).all():
        return None
    return data


def _parse_slow(src: Source, nos: list[int], rows: list[str]) -> FloatArray:
    out = np.empty((len(rows), _FIELDS))
    for k, (no, line) in enumerate(zip(nos, rows, strict=True)):
        tok = line.split()
        if len(tok) != _FIELDS:
            raise src.error(no, "a TUM line needs 8 numbers (timestamp tx ty tz qx qy qz qw), "
                            f"got {len(tok)}")
        for j, t in enumerate(tok):
            v = parse_float(t)
            if v is None:
                raise src.error(no, f"not a number: {show_token(t)}")
            if not np.isfinite(v):
                raise src.error(no, "values must be finite and the quaternion non-zero")
            out[k, j] = v
    return out


def tum_lines(rotations: npt.ArrayLike, translations: npt.ArrayLike,
              timestamps: npt.ArrayLike) -> list[str]:
    """TUM lines; integer timestamps (node ids) are written as integers, others with ``repr``."""
    r = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    stamps = np.asarray(timestamps).reshape(-1)
    if not (r.shape[0] == t.shape[0] == stamps.shape[0]):
        raise ValueError(f"rotations, translations and timestamps must have one entry per "
                         f"pose, got {r.shape[0]}, {t.shape[0]} and {stamps.shape[0]}")
    if np.issubdtype(stamps.dtype, np.integer):
        heads = [str(v) for v in stamps.tolist()]
    else:
        heads = [repr(float(v)) for v in stamps.tolist()]
    rest = fmt_floats(np.column_stack([t, matrix_to_quat_xyzw(r)]))
    return [f"{h} {x}" for h, x in zip(heads, rest, strict=True)]


def write_tum(path: PathLike, rotations: npt.ArrayLike, translations: npt.ArrayLike,
              timestamps: npt.ArrayLike) -> None:
    """Write poses as a TUM trajectory, atomically (``"-"``: standard output)."""
    write_atomic(path, lambda: tum_lines(rotations, translations, timestamps))


def graph_tum_lines(graph: PoseGraph, name: str) -> list[str]:
    """A graph's poses as TUM lines, timestamp = pose id (the caller warns about constraints)."""
    if not graph.has_estimates:
        raise FormatError("the graph has no vertex estimates (e.g. read from iSAM), so there "
                          "are no poses to write as TUM; optimize it first", name)
    return tum_lines(graph.rotations, graph.translations, graph.node_ids)
