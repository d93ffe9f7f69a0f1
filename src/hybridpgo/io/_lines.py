"""Shared plumbing of the readers and writers: information matrices (upper-triangle layouts,
the positive-definite check and the ``nearest`` projection), SE(2) angle helpers, graph assembly
with file-level checks, and atomic writing.  A file's lines (:mod:`._source`) and their parsing
by tag (:mod:`._parse`) are re-exported here for the format modules, as are the quaternion and
Euler conversions of :mod:`hybridpgo.geometry.so3`.
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from .._output import Outputs
from ..errors import FormatError, GraphError, option_hint
from ..geometry.so3 import euler_rpy_to_matrix as euler_rpy_to_matrix
from ..geometry.so3 import matrix_to_euler_rpy as matrix_to_euler_rpy
from ..geometry.so3 import matrix_to_quat_xyzw as matrix_to_quat_xyzw
from ..geometry.so3 import normalize_quaternions as normalize_quaternions
from ..geometry.so3 import quat_xyzw_to_matrix as quat_xyzw_to_matrix
from ..graph import (
    MAX_INFORMATION,
    PoseGraph,
    lift_information_2d,
    pd_problem,
    positive_definite,
)
from ._parse import (
    Block as Block,
)
from ._parse import (
    TagSpec as TagSpec,
)
from ._parse import (
    parse_blocks as parse_blocks,
)
from ._parse import (
    parse_float as parse_float,
)
from ._parse import (
    parse_int as parse_int,
)
from ._parse import (
    stack as stack,
)
from ._parse import (
    unknown_tag_problem as unknown_tag_problem,
)
from ._parse import (
    upper_names as upper_names,
)
from ._source import (
    FIX_INFORMATION as FIX_INFORMATION,
)
from ._source import (
    IDENTITY_ATOL as IDENTITY_ATOL,
)
from ._source import (
    MAX_ECHO as MAX_ECHO,
)
from ._source import (
    MAX_LINES_LISTED as MAX_LINES_LISTED,
)
from ._source import (
    NEAREST_SPD_FLOOR as NEAREST_SPD_FLOOR,
)
from ._source import (
    NEAREST_SPD_MIN as NEAREST_SPD_MIN,
)
from ._source import (
    STDIN_NAME as STDIN_NAME,
)
from ._source import (
    STDIO as STDIO,
)
from ._source import (
    STDOUT_NAMES as STDOUT_NAMES,
)
from ._source import (
    STDOUT_TARGET as STDOUT_TARGET,
)
from ._source import (
    FloatArray as FloatArray,
)
from ._source import (
    IntArray as IntArray,
)
from ._source import (
    PathLike as PathLike,
)
from ._source import (
    Source as Source,
)
from ._source import (
    check_fix_information as check_fix_information,
)
from ._source import (
    list_lines as list_lines,
)
from ._source import (
    load_source as load_source,
)
from ._source import (
    read_bytes as read_bytes,
)
from ._source import (
    show_token as show_token,
)
from ._source import (
    source_from_text as source_from_text,
)
from ._source import (
    split_lines as split_lines,
)


def sym_from_upper(vals: FloatArray, d: int) -> FloatArray:
    """(k, d(d+1)/2) upper-triangular entries, row by row -> (k, d, d) symmetric."""
    iu = np.triu_indices(d)
    out = np.zeros((vals.shape[0], d, d))
    out[:, iu[0], iu[1]] = vals
    out[:, iu[1], iu[0]] = vals
    return out


def upper_from_sym(mats: FloatArray) -> FloatArray:
    """(k, d, d) -> (k, d(d+1)/2) upper-triangular entries, row by row."""
    iu = np.triu_indices(mats.shape[-1])
    return np.ascontiguousarray(mats[:, iu[0], iu[1]])


def upper_matrix(vals: FloatArray, d: int) -> FloatArray:
    """(k, d(d+1)/2) entries, row by row -> (k, d, d) upper-triangular matrix (zeros below)."""
    iu = np.triu_indices(d)
    out = np.zeros((vals.shape[0], d, d))
    out[:, iu[0], iu[1]] = vals
    return out


def nearest_spd(mats: FloatArray) -> FloatArray:
    """(k, d, d) symmetric -> the nearest (Frobenius) symmetric matrices with eigenvalues >= the
    floor ``NEAREST_SPD_FLOOR * max |eigenvalue|`` (``NEAREST_SPD_FLOOR`` for a zero matrix),
    and at least :data:`NEAREST_SPD_MIN`.

    Eigenvalues above the floor and the eigenvectors are kept; the result is exactly symmetric.
    """
    sym = 0.5 * (mats + np.swapaxes(mats, 1, 2))
    lam, vec = np.linalg.eigh(sym)
    scale = np.abs(lam).max(axis=1)
    floor = np.where(scale > 0.0, np.maximum(NEAREST_SPD_FLOOR * scale, NEAREST_SPD_MIN),
                     NEAREST_SPD_FLOOR)
    lam = np.maximum(lam, floor[:, None])
    out = (vec * lam[:, None, :]) @ np.swapaxes(vec, 1, 2)
    res: FloatArray = 0.5 * (out + np.swapaxes(out, 1, 2))
    return res


#: :func:`spd_filter` computes eigenvalues of this many matrices at a time.
_EIG_CHUNK = 65536


def spd_filter(src: Source, mats: FloatArray, line_nos: IntArray, kind: str,
               what: str = "information matrix", hint: str = "",
               ) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Check the information matrices of ``kind`` lines (e.g. ``"EDGE_SE2"``).

    Entries beyond :data:`MAX_INFORMATION` (they would overflow when squared) always raise at
    their line.  Matrices that are not positive definite
    (:func:`hybridpgo.graph.positive_definite`, the criterion of
    :func:`hybridpgo.graph.check_information`) raise
    at the first such line, with their count, unless ``src.fix_information`` says to project
    them (:func:`nearest_spd`) or to drop them; either is warned about once, with the count.

    Returns
    -------
    mats : (k, d, d)
        The matrices, repaired where needed (the input when nothing was).
    keep : (k,) bool
        False for the lines to drop.
    """
    k = mats.shape[0]
    keep = np.ones(k, bool)
    if k == 0:
        return mats, keep
    flat = mats.reshape(k, -1)
    big = np.maximum(flat.max(axis=1), -flat.min(axis=1))  # max |entry|, NaN kept; no |mats| copy
    limit = MAX_INFORMATION
    over = np.nonzero(~(big <= limit))[0]
    if over.size:
        j = int(over[np.argmin(line_nos[over])])
        size = (f"an entry of magnitude {big[j]:.3g}" if np.isfinite(big[j])
                else "entries that overflow float64")
        raise src.error(int(line_nos[j]), f"{what} is too large: {size}; at most {limit:.3g} is "
                        f"supported (larger values overflow when squared){hint}")
    eig_min = np.concatenate([np.linalg.eigvalsh(mats[i:i + _EIG_CHUNK])[:, 0]
                              for i in range(0, k, _EIG_CHUNK)])  # bounded LAPACK copies
    bad = np.nonzero(~np.concatenate([positive_definite(mats[i:i + _EIG_CHUNK],
                                                        eig_min[i:i + _EIG_CHUNK])
                                      for i in range(0, k, _EIG_CHUNK)]))[0]
    if bad.size == 0:
        return mats, keep
    bad = bad[np.argsort(line_nos[bad], kind="stable")]
    lines = list_lines(line_nos[bad])
    count = f"{bad.size} of {k} {kind} lines"
    policy = src.fix_information
    if policy is None:
        j = int(bad[0])
        raise src.error(int(line_nos[j]), f"{what} is not positive definite "
                        f"({pd_problem(float(eig_min[j]))}){hint}; {count} have such information "
                        f"({lines}); pass {option_hint('fix_information', *FIX_INFORMATION)} "
                        "to project them onto the nearest positive definite matrix or to drop "
                        "them")
    if policy == "nearest":
        mats = np.array(mats, copy=True)
        mats[bad] = nearest_spd(mats[bad])
        done = (f"projected onto the nearest positive definite matrix (eigenvalues clipped at "
                f"{NEAREST_SPD_FLOOR:g} x the largest)")
    else:
        keep[bad] = False
        done = "dropped them"
    warnings.warn(f"{src.path}: {count} have information that is not positive definite "
                  f"({lines}); {done}", UserWarning, stacklevel=2)
    return mats, keep


# =========================================================================== rotations
def rot_z(theta: FloatArray) -> FloatArray:
    """(k,) yaw angles -> (k, 3, 3) rotations about z."""
    c, s = np.cos(theta), np.sin(theta)
    r = np.zeros((theta.shape[0], 3, 3))
    r[:, 0, 0] = c
    r[:, 0, 1] = -s
    r[:, 1, 0] = s
    r[:, 1, 1] = c
    r[:, 2, 2] = 1.0
    return r


def yaw_of(r: FloatArray) -> FloatArray:
    """(k, 3, 3) planar rotations -> (k,) yaw angles in (-pi, pi]."""
    return np.arctan2(r[:, 1, 0], r[:, 0, 0])


# =========================================================================== assembly
@dataclass(slots=True)
class Parts:
    """What a format reader extracted, in file ids, before the id -> index mapping."""

    is_2d: bool
    vertex_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    vertex_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    vertex_rotations: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    vertex_translations: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    edge_ids: IntArray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    edge_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    edge_rotations: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    edge_translations: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    edge_information: FloatArray = field(default_factory=lambda: np.zeros((0, 6, 6)))
    gps_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    gps_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    gps_positions: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    gps_information: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    fix_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    fix_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))


def drop_edges(p: Parts, keep: npt.NDArray[np.bool_]) -> None:
    """Keep only the relative edges where ``keep`` is True."""
    p.edge_ids, p.edge_lines = p.edge_ids[keep], p.edge_lines[keep]
    p.edge_rotations, p.edge_translations = p.edge_rotations[keep], p.edge_translations[keep]
    p.edge_information = p.edge_information[keep]


def drop_gps(p: Parts, keep: npt.NDArray[np.bool_]) -> None:
    """Keep only the position priors where ``keep`` is True."""
    p.gps_ids, p.gps_lines = p.gps_ids[keep], p.gps_lines[keep]
    p.gps_positions, p.gps_information = p.gps_positions[keep], p.gps_information[keep]


def check_duplicate_vertices(src: Source, ids: IntArray, line_nos: IntArray) -> None:
    """Raise at the second definition of a vertex id, naming the first line."""
    if ids.shape[0] < 2:
        return
    _, first = np.unique(ids, return_index=True)
    if first.shape[0] == ids.shape[0]:
        return
    dup = np.ones(ids.shape[0], bool)
    dup[first] = False
    k = int(np.nonzero(dup)[0][np.argmin(line_nos[dup])])
    earlier = int(line_nos[np.nonzero(ids == ids[k])[0]].min())
    tag = src.lines[int(line_nos[k]) - 1].split()[0]
    raise src.error(int(line_nos[k]), f"duplicate vertex id {int(ids[k])} ({tag}); it was "
                    f"already defined at line {earlier}")


def check_self_loops(src: Source, edge_ids: IntArray, line_nos: IntArray) -> None:
    loops: npt.NDArray[np.intp] = (
        np.nonzero(edge_ids[:, 0] == edge_ids[:, 1])[0] if edge_ids.size else np.zeros(0, np.intp)
    )
    if len(loops):
        k = int(loops[0])
        tag = src.lines[int(line_nos[k]) - 1].split()[0]
        raise src.error(int(line_nos[k]), f"{tag} connects vertex {int(edge_ids[k, 0])} to "
                        "itself (self-loop)")


def _check_known(src: Source, node_ids: IntArray, ids: IntArray, line_nos: IntArray,
                 cols: int) -> None:
    """Raise at the first line (in file order) naming an id that has no vertex line."""
    if ids.size == 0:
        return
    flat = ids.reshape(-1)
    pos = np.searchsorted(node_ids, flat).clip(0, node_ids.shape[0] - 1)
    unknown = (node_ids[pos] != flat).reshape(-1, cols).any(axis=1)
    if unknown.any():
        rows = np.nonzero(unknown)[0]
        k = int(rows[np.argmin(line_nos[rows])])
        row = ids.reshape(-1, cols)[k]
        missing = int(row[~np.isin(row, node_ids)][0])
        tag = src.lines[int(line_nos[k]) - 1].split()[0]
        raise src.error(int(line_nos[k]), f"{tag} refers to vertex {missing}, which no vertex "
                        "line defines")


def assemble(src: Source, fmt: str, parts: Parts, check_connected: bool) -> PoseGraph:
    """Map file ids to dense indices, run the file-level checks, build the :class:`PoseGraph`."""
    p = parts
    has_vertices = p.vertex_ids.shape[0] > 0
    if not has_vertices and p.edge_ids.shape[0] == 0 and p.gps_ids.shape[0] == 0:
        raise src.error(None, "empty file: no vertex or edge lines found")
    check_self_loops(src, p.edge_ids, p.edge_lines)
    if has_vertices:
        check_duplicate_vertices(src, p.vertex_ids, p.vertex_lines)
        order = np.argsort(p.vertex_ids, kind="stable")
        node_ids = p.vertex_ids[order]
        rotations = p.vertex_rotations[order]
        translations = p.vertex_translations[order]
        _check_known(src, node_ids, p.edge_ids, p.edge_lines, 2)
        _check_known(src, node_ids, p.gps_ids, p.gps_lines, 1)
        _check_known(src, node_ids, p.fix_ids, p.fix_lines, 1)
    else:
        node_ids = np.unique(np.concatenate([p.edge_ids.reshape(-1), p.gps_ids, p.fix_ids]))
        n = node_ids.shape[0]
        rotations = np.broadcast_to(np.eye(3), (n, 3, 3))
        translations = np.zeros((n, 3))
    # Safety net with line numbers: the readers check the file's own matrices; this checks the
    # converted ones with PoseGraph's criterion, so PoseGraph never rejects them without a line.
    p.edge_information, keep = spd_filter(src, p.edge_information, p.edge_lines, "edge",
                                          "information matrix converted to (rho, phi)")
    if not keep.all():
        drop_edges(p, keep)
    p.gps_information, keep = spd_filter(src, p.gps_information, p.gps_lines, "position prior")
    if not keep.all():
        drop_gps(p, keep)
    _, first = np.unique(p.fix_ids, return_index=True)
    fix_ids = p.fix_ids[np.sort(first)]  # first mention order, no repeats
    try:
        graph = PoseGraph(
            node_ids=node_ids, rotations=rotations, translations=translations,
            edge_nodes=np.searchsorted(node_ids, p.edge_ids).astype(np.int32).reshape(-1, 2),
            edge_rotations=p.edge_rotations, edge_translations=p.edge_translations,
            edge_information=p.edge_information,
            gps_nodes=np.searchsorted(node_ids, p.gps_ids).astype(np.int32),
            gps_positions=p.gps_positions, gps_information=p.gps_information,
            fixed_nodes=np.searchsorted(node_ids, fix_ids).astype(np.int32),
            is_2d=p.is_2d, has_estimates=has_vertices, source_format=fmt,
            edge_lines=p.edge_lines, gps_lines=p.gps_lines,
        )
        if check_connected:
            graph.check_connected(source="the graph")
    except GraphError as exc:
        raise src.error(None, str(exc)) from exc
    return graph


# =========================================================================== writing
def fmt_floats(rows: FloatArray) -> list[str]:
    """Each row of a (k, n) array as space-separated ``repr`` floats (round-trip exact)."""
    return [" ".join(map(repr, row)) for row in np.asarray(rows, np.float64).tolist()]


def write_atomic(path: PathLike, produce: Callable[[], Iterable[str]]) -> None:
    """Write the lines ``produce()`` yields to ``path`` so that a reader never sees half a file.

    The rules of :mod:`hybridpgo._output` apply: a regular file (or a new one) is written to a
    temporary file in the same directory, then renamed over ``path``, keeping its permissions;
    a symbolic link is written through (its target is replaced); a FIFO or character device
    (``/dev/null``) is written into; a directory, socket or block device is refused.  ``"-"``
    (and ``/dev/stdout``) writes to standard output (:data:`STDOUT_TARGET`).

    The lines are produced completely before anything is created; if anything fails nothing is
    written (an existing ``path`` is left untouched).  OS errors become :class:`FormatError`
    naming the file.
    """
    write_atomic_all([(path, list(produce()))])


def write_atomic_all(items: Sequence[tuple[PathLike, Sequence[str]]]) -> None:
    """Write several files all or nothing (:class:`hybridpgo._output.Outputs`): every temporary
    file is written first, then all are moved into place (as :func:`write_atomic`, which is the
    one-file case).  Standard output is written last."""
    to_stdout = [lines for path, lines in items if os.fspath(path) in STDOUT_NAMES]
    files = [(os.fspath(path), lines) for path, lines in items
             if os.fspath(path) not in STDOUT_NAMES]
    with Outputs([name for name, _ in files]) as out:
        for name, lines in files:
            try:
                with open(out.temp(name), "w", encoding="utf-8", newline="\n") as fh:
                    for line in lines:
                        fh.write(line)
                        fh.write("\n")
            except OSError as exc:
                raise FormatError(f"cannot write the file: {exc.strerror or exc}", name) from exc
        out.commit()
    for lines in to_stdout:
        stream = STDOUT_TARGET.get() or sys.stdout
        stream.write("".join(line + "\n" for line in lines))
        stream.flush()


def require_planar(graph: PoseGraph, path: str, fmt: str) -> None:
    """Raise unless every pose and measurement of a 2D graph is planar (z = roll = pitch = 0)."""
    tol = 1e-9
    for what, r, t in (("pose", graph.rotations, graph.translations),
                       ("edge", graph.edge_rotations, graph.edge_translations)):
        if r.shape[0] == 0:
            continue
        off = np.abs(np.stack([r[:, 0, 2], r[:, 1, 2], r[:, 2, 0], r[:, 2, 1],
                               r[:, 2, 2] - 1.0], axis=1)).max(axis=1)
        zoff = np.abs(t[:, 2]) / (1.0 + np.abs(t).max(axis=1))
        bad = np.nonzero((off > tol) | (zoff > tol))[0]
        if bad.size:
            k = int(bad[0])
            label = (f"pose {int(graph.node_ids[k])}" if what == "pose" else f"edge {k} "
                     f"({int(graph.node_ids[graph.edge_nodes[k, 0]])} -> "
                     f"{int(graph.node_ids[graph.edge_nodes[k, 1]])})")
            raise FormatError(f"cannot write the 2D graph as {fmt} SE(2) lines: {label} is not "
                              f"planar (z = {t[k, 2]:.3g}, out-of-plane rotation {off[k]:.3g})",
                              path)



def require_readable_information(graph: PoseGraph, mats: FloatArray, path: str,
                                 fmt: str) -> None:
    """Raise unless ``mats`` -- the information exactly as the reader will compute it from the
    written text (the planar 3x3 block of a 2D graph, iSAM's ``R^T R``) -- passes the reader's
    checks, including the lift of a 3x3 to 6x6.

    A matrix at the edge of positive definiteness (smallest eigenvalue ~1e-16 of the largest)
    can lose it to the rounding of a conversion; the file would then not read back.
    """
    if mats.shape[0] == 0:
        return
    checks = [mats] if mats.shape[-1] == 6 else [mats, lift_information_2d(mats)]
    for m in checks:
        big = np.abs(m).reshape(m.shape[0], -1).max(axis=1)
        with np.errstate(invalid="ignore"):
            eig_min = np.where(big <= MAX_INFORMATION,
                               np.linalg.eigvalsh(np.where((big <= MAX_INFORMATION)[:, None, None],
                                                           m, 1.0))[:, 0], -np.inf)
        finite = np.isfinite(eig_min)
        ok = np.zeros(m.shape[0], bool)
        ok[finite] = positive_definite(m[finite], eig_min[finite])
        bad = np.nonzero(~ok)[0]
        if bad.size:
            k = int(bad[0])
            a, b = graph.node_ids[graph.edge_nodes[k]].tolist()
            raise FormatError(f"edge {k} ({a} -> {b}): its information matrix is so close to "
                              f"singular that it would not read back positive definite from "
                              f"{fmt} (smallest eigenvalue {eig_min[k]:.3g} after the "
                              "conversion)" + ("; write g2o or TORO instead, which store the "
                                               "matrix itself" if fmt == "iSAM" else ""), path)


def write_vertices_needed(graph: PoseGraph) -> bool:
    """True when vertex lines must be written (estimates, or a node no constraint mentions).

    A graph without estimates (read from iSAM or an edges-only file) is written without vertex
    lines, so that reading the file back gives the same graph (``has_estimates`` False).
    """
    if graph.has_estimates:
        return True
    used = np.zeros(graph.num_nodes, bool)
    used[graph.edge_nodes.reshape(-1)] = True
    used[graph.gps_nodes] = True
    used[graph.fixed_nodes] = True
    return not bool(used.all())
