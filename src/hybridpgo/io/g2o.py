"""The g2o text format (docs/conventions.md; line layouts in ``datasets/README.md``).

Supported lines::

    VERTEX_SE2 id x y theta
    EDGE_SE2 a b dx dy dtheta I11 I12 I13 I22 I23 I33            information over (x, y, theta)
    VERTEX_SE3:QUAT id x y z qx qy qz qw                          quaternion scalar-last
    EDGE_SE3:QUAT a b x y z qx qy qz qw I11 ... I66 (21 values)   information over (t, q_vec)
    PARAMS_SE3OFFSET id x y z qx qy qz qw                         identity offsets only
    EDGE_SE3_XYZ_PRIOR vertex param_id x y z I11 I12 I13 I22 I23 I33
    FIX id [id ...]

Conversions: SE(2) lines are lifted into SE(3) with :func:`~hybridpgo.graph.lift_information_2d`;
``EDGE_SE3:QUAT`` information over (t, q_vec) becomes information over (rho, phi) as
``P Omega_q P`` with ``P = diag(1, 1, 1, 1/2, 1/2, 1/2)`` because ``q_vec ~ phi / 2``.  Writing
multiplies by ``P^-1`` (exact in binary floating point), so a round trip is exact.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..errors import FormatError
from ..graph import PoseGraph, lift_information_2d, planar_information
from ._lines import (
    IDENTITY_ATOL,
    Block,
    FloatArray,
    Parts,
    PathLike,
    Source,
    TagSpec,
    assemble,
    fmt_floats,
    load_source,
    matrix_to_quat_xyzw,
    normalize_quaternions,
    parse_blocks,
    quat_xyzw_to_matrix,
    require_planar,
    require_readable_information,
    rot_z,
    spd_filter,
    stack,
    sym_from_upper,
    upper_from_sym,
    upper_names,
    write_atomic,
    write_vertices_needed,
    yaw_of,
)

_I3 = upper_names("I", "123")
_I6 = upper_names("I", "123456")
_QUAT = ("qx", "qy", "qz", "qw")

SPECS: dict[str, TagSpec] = {
    "VERTEX_SE2": TagSpec("VERTEX_SE2", ("id",), ("x", "y", "theta")),
    "EDGE_SE2": TagSpec("EDGE_SE2", ("id_a", "id_b"), ("dx", "dy", "dtheta", *_I3)),
    "VERTEX_SE3:QUAT": TagSpec("VERTEX_SE3:QUAT", ("id",), ("x", "y", "z", *_QUAT)),
    "EDGE_SE3:QUAT": TagSpec("EDGE_SE3:QUAT", ("id_a", "id_b"), ("x", "y", "z", *_QUAT, *_I6)),
    "PARAMS_SE3OFFSET": TagSpec("PARAMS_SE3OFFSET", ("param_id",), ("x", "y", "z", *_QUAT)),
    "EDGE_SE3_XYZ_PRIOR": TagSpec("EDGE_SE3_XYZ_PRIOR", ("vertex", "param_id"),
                                  ("x", "y", "z", *_I3)),
    "FIX": TagSpec("FIX", ("id",), variadic_ids=True),
}
TAGS: tuple[str, ...] = tuple(SPECS)

_TAGS_2D = ("VERTEX_SE2", "EDGE_SE2")
_TAGS_3D = ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT", "EDGE_SE3_XYZ_PRIOR")

#: docs/conventions.md: information over (t, q_vec) -> over (rho, phi) is P Omega P, P =
#: diag(1,1,1,.5,.5,.5).
_P = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
_P_INV = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])


def read_g2o(path: PathLike, *, skip_unknown: bool = False,
             check_connected: bool = True,
             fix_information: str | None = None) -> PoseGraph:
    """Read a g2o file (2D ``SE2`` or 3D ``SE3:QUAT`` lines, position priors, ``FIX``).

    Parameters
    ----------
    path
        The file.
    skip_unknown
        Skip lines with other tags (one warning with the count) instead of raising.
    check_connected
        Raise when the graph falls apart into several pieces.
    fix_information
        None: information that is not positive definite raises (naming its line and how many
        lines have it).  ``"nearest"``: such matrices are projected onto the nearest positive
        definite matrix (:func:`~hybridpgo.io._lines.nearest_spd`: eigenvalues clipped at
        ``NEAREST_SPD_FLOOR`` times the largest).  ``"skip"``: their lines are dropped.  Either
        warns once per line type with the count.

    Returns
    -------
    PoseGraph
        ``source_format == "g2o"``; ``is_2d`` for SE(2) files; ``has_estimates`` is False when
        the file has no vertex lines (node ids then come from the edges).

    Raises
    ------
    FormatError
        ``"{path}:{line}: {problem}"`` for malformed lines, non-SPD information (unless
        ``fix_information``), information entries beyond ``MAX_INFORMATION``, unknown or
        duplicate vertices, self-loops, non-identity ``PARAMS_SE3OFFSET``; ``"{path}: ..."`` for
        an empty, unreadable or disconnected file.
    """
    return read_g2o_source(load_source(path, fix_information), skip_unknown=skip_unknown,
                           check_connected=check_connected)


def read_g2o_source(src: Source, *, skip_unknown: bool, check_connected: bool) -> PoseGraph:
    blocks = parse_blocks(src, SPECS, "g2o", skip_unknown)
    first2 = min((src.first_line(t) for t in _TAGS_2D if t in blocks), default=None)
    first3 = min((src.first_line(t) for t in _TAGS_3D if t in blocks), default=None)
    if first2 is not None and first3 is not None:
        later, earlier = max(first2, first3), min(first2, first3)
        raise src.error(later, "the file mixes SE(2) and SE(3) lines (the other kind starts at "
                        f"line {earlier}); a g2o file must be all 2D or all 3D")
    is_2d = first2 is not None
    parts = Parts(is_2d=is_2d)
    if is_2d:
        _vertices_se2(blocks, parts)
        _edges_se2(src, blocks, parts)
    else:
        _vertices_se3(src, blocks, parts)
        _edges_se3(src, blocks, parts)
        _priors(src, blocks, parts)
    if "FIX" in blocks:
        ln, ids, _, _ = stack(blocks["FIX"])
        parts.fix_ids, parts.fix_lines = ids[:, 0], ln
    return assemble(src, "g2o", parts, check_connected)


def _get(blocks: dict[str, list[Block]], tag: str) -> tuple[np.ndarray, np.ndarray, FloatArray]:
    ln, ids, vals, _ = stack(blocks.get(tag, []))
    return ln, ids, vals


def _vertices_se2(blocks: dict[str, list[Block]], parts: Parts) -> None:
    ln, ids, v = _get(blocks, "VERTEX_SE2")
    if ln.size == 0:
        return
    parts.vertex_ids, parts.vertex_lines = ids[:, 0], ln
    parts.vertex_rotations = rot_z(v[:, 2])
    parts.vertex_translations = np.column_stack([v[:, 0], v[:, 1], np.zeros(ln.shape[0])])


def _edges_se2(src: Source, blocks: dict[str, list[Block]], parts: Parts) -> None:
    ln, ids, v = _get(blocks, "EDGE_SE2")
    if ln.size == 0:
        return
    info3, keep = spd_filter(src, sym_from_upper(v[:, 3:9], 3), ln, "EDGE_SE2",
                             "information matrix (I11 I12 I13 I22 I23 I33 over x, y, theta)")
    ln, ids, v, info3 = ln[keep], ids[keep], v[keep], info3[keep]
    parts.edge_ids, parts.edge_lines = ids, ln
    parts.edge_rotations = rot_z(v[:, 2])
    parts.edge_translations = np.column_stack([v[:, 0], v[:, 1], np.zeros(ln.shape[0])])
    parts.edge_information = lift_information_2d(info3)


def _quaternions(src: Source, q: FloatArray, ln: np.ndarray, tag: str) -> FloatArray:
    zero = np.nonzero(np.abs(q).max(axis=1) == 0.0)[0]
    if zero.size:
        raise src.error(int(ln[zero[0]]), f"{tag} quaternion (qx, qy, qz, qw) is zero; it must "
                        "be a (nearly) unit quaternion")
    return quat_xyzw_to_matrix(q)


def _vertices_se3(src: Source, blocks: dict[str, list[Block]], parts: Parts) -> None:
    ln, ids, v = _get(blocks, "VERTEX_SE3:QUAT")
    if ln.size == 0:
        return
    parts.vertex_ids, parts.vertex_lines = ids[:, 0], ln
    parts.vertex_rotations = _quaternions(src, v[:, 3:7], ln, "VERTEX_SE3:QUAT")
    parts.vertex_translations = np.ascontiguousarray(v[:, 0:3])


def _edges_se3(src: Source, blocks: dict[str, list[Block]], parts: Parts) -> None:
    ln, ids, v = _get(blocks, "EDGE_SE3:QUAT")
    if ln.size == 0:
        return
    # Checked (and repaired) in (rho, phi) units, P Omega_q P: the scaling by powers of two is
    # exact, so writing (P^-1 Omega P^-1) and reading back gives the same bits, the same verdict.
    info = sym_from_upper(v[:, 7:28], 6)
    info *= _P[:, None] * _P[None, :]  # in place: a 1M-edge file's information is 288 MB
    info, keep = spd_filter(src, info, ln, "EDGE_SE3:QUAT",
                            "information matrix (21 entries over x, y, z, qx, qy, qz)")
    if not keep.all():
        ln, ids, v, info = ln[keep], ids[keep], v[keep], info[keep]
    parts.edge_ids, parts.edge_lines = ids, ln
    parts.edge_rotations = _quaternions(src, v[:, 3:7], ln, "EDGE_SE3:QUAT")
    parts.edge_translations = np.ascontiguousarray(v[:, 0:3])
    parts.edge_information = info


def _priors(src: Source, blocks: dict[str, list[Block]], parts: Parts) -> None:
    # Parameters: only the identity offset is supported (docs/conventions.md position prior).
    declared: dict[int, int] = {}
    pl, pids, pv = _get(blocks, "PARAMS_SE3OFFSET")
    for k in range(pl.shape[0]):
        pid, line = int(pids[k, 0]), int(pl[k])
        if pid in declared:
            raise src.error(line, f"PARAMS_SE3OFFSET {pid} is declared twice (first at line "
                            f"{declared[pid]})")
        q = normalize_quaternions(pv[k:k + 1, 3:7])[0]
        qn = np.abs(pv[k, 3:7]).max()
        if (np.abs(pv[k, 0:3]).max() > IDENTITY_ATOL or qn == 0.0
                or np.abs(q[0:3]).max() > IDENTITY_ATOL or abs(abs(q[3]) - 1.0) > IDENTITY_ATOL):
            raise src.error(line, f"PARAMS_SE3OFFSET {pid} is not the identity offset "
                            f"(t = {pv[k, 0:3].tolist()}, q = {pv[k, 3:7].tolist()}); only "
                            "position priors on the pose itself are supported: use "
                            "'PARAMS_SE3OFFSET id 0 0 0 0 0 0 1'")
        declared[pid] = line
    ln, ids, v = _get(blocks, "EDGE_SE3_XYZ_PRIOR")
    if ln.size == 0:
        return
    undeclared = ~np.isin(ids[:, 1], np.array(list(declared), np.int64))
    if undeclared.any():
        k = int(np.nonzero(undeclared)[0][0])
        raise src.error(int(ln[k]), f"EDGE_SE3_XYZ_PRIOR uses parameter id {int(ids[k, 1])}, "
                        "which no PARAMS_SE3OFFSET line declares")
    info, keep = spd_filter(src, sym_from_upper(v[:, 3:9], 3), ln, "EDGE_SE3_XYZ_PRIOR",
                            "information matrix (I11 I12 I13 I22 I23 I33 over x, y, z)")
    ln, ids, v, info = ln[keep], ids[keep], v[keep], info[keep]
    parts.gps_ids, parts.gps_lines = ids[:, 0], ln
    parts.gps_positions = np.ascontiguousarray(v[:, 0:3])
    parts.gps_information = info


# =========================================================================== writing
def write_g2o(graph: PoseGraph, path: PathLike) -> None:
    """Write ``graph`` as g2o, atomically (temporary file + ``os.replace``).

    2D graphs (``is_2d``) are written as ``VERTEX_SE2``/``EDGE_SE2`` (theta = atan2 of R, the
    planar (x, y, theta) information block); 3D graphs as ``SE3:QUAT`` lines with the
    information converted back to (t, q_vec) units.  Position priors are written after one
    ``PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1`` line.  Vertex lines are omitted when the graph has no
    estimates (``has_estimates`` False) and every node appears in a constraint, so that reading
    the file back gives the same graph.  Numbers are written with ``repr`` (round-trip exact).

    Raises
    ------
    FormatError
        When a 2D graph is not planar or has position priors, or the file cannot be written.
    """
    name = str(path)
    write_atomic(path, lambda: g2o_lines(graph, name))


def g2o_lines(graph: PoseGraph, name: str) -> Iterator[str]:
    """The lines :func:`write_g2o` writes (``name`` is used in messages)."""
    if graph.is_2d:
        if graph.num_gps:
            raise FormatError("a 2D graph with position priors cannot be written as g2o "
                              "SE(2) lines", name)
        require_planar(graph, name, "g2o")
        require_readable_information(graph, planar_information(graph.edge_information), name,
                                     "g2o")
    return _g2o_lines(graph)


#: Rows formatted at a time by the writer: bounds its memory on graphs of millions of lines.
_WRITE_CHUNK = 65536


def _chunks(n: int) -> Iterator[slice]:
    return (slice(i, min(i + _WRITE_CHUNK, n)) for i in range(0, n, _WRITE_CHUNK))


def _g2o_lines(graph: PoseGraph) -> Iterator[str]:
    """The file's text in blocks of up to ``_WRITE_CHUNK`` lines (each without its final
    newline), so that a large graph is never formatted into memory all at once."""
    ids = graph.node_ids
    vertices = write_vertices_needed(graph)
    fix = _fix_lines(graph)
    ea_all, eb_all = ids[graph.edge_nodes[:, 0]], ids[graph.edge_nodes[:, 1]]
    if graph.is_2d:
        for s in _chunks(graph.num_nodes if vertices else 0):
            t = graph.translations[s]
            rows = fmt_floats(np.column_stack([t[:, 0], t[:, 1], yaw_of(graph.rotations[s])]))
            yield "\n".join(f"VERTEX_SE2 {i} {r}" for i, r in zip(ids[s].tolist(), rows,
                                                                   strict=True))
        if fix:
            yield "\n".join(fix)
        for s in _chunks(graph.num_edges):
            et = graph.edge_translations[s]
            vals = np.column_stack([et[:, 0], et[:, 1], yaw_of(graph.edge_rotations[s]),
                                    upper_from_sym(planar_information(graph.edge_information[s]))])
            yield "\n".join(f"EDGE_SE2 {a} {b} {r}" for a, b, r in zip(
                ea_all[s].tolist(), eb_all[s].tolist(), fmt_floats(vals), strict=True))
        return
    for s in _chunks(graph.num_nodes if vertices else 0):
        rows = fmt_floats(np.column_stack([graph.translations[s],
                                           matrix_to_quat_xyzw(graph.rotations[s])]))
        yield "\n".join(f"VERTEX_SE3:QUAT {i} {r}" for i, r in zip(ids[s].tolist(), rows,
                                                                     strict=True))
    if fix:
        yield "\n".join(fix)
    for s in _chunks(graph.num_edges):
        info_q = graph.edge_information[s] * _P_INV[:, None] * _P_INV[None, :]
        vals = np.column_stack([graph.edge_translations[s],
                                matrix_to_quat_xyzw(graph.edge_rotations[s]),
                                upper_from_sym(info_q)])
        yield "\n".join(f"EDGE_SE3:QUAT {a} {b} {r}" for a, b, r in zip(
            ea_all[s].tolist(), eb_all[s].tolist(), fmt_floats(vals), strict=True))
    if graph.num_gps:
        yield "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1"
        gid = ids[graph.gps_nodes]
        for s in _chunks(graph.num_gps):
            vals = np.column_stack([graph.gps_positions[s],
                                    upper_from_sym(graph.gps_information[s])])
            yield "\n".join(f"EDGE_SE3_XYZ_PRIOR {v} 0 {r}" for v, r in zip(
                gid[s].tolist(), fmt_floats(vals), strict=True))


def _fix_lines(graph: PoseGraph) -> list[str]:
    return [f"FIX {i}" for i in graph.node_ids[graph.fixed_nodes].tolist()]

