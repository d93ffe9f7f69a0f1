"""The TORO ``.graph`` format (docs/conventions.md; line layouts in ``datasets/README.md``).

Supported lines::

    VERTEX2 id x y theta
    EDGE2 a b dx dy dtheta inf_xx inf_xy inf_yy inf_tt inf_xt inf_yt     TORO's own order!
    VERTEX3 id x y z roll pitch yaw                     R = Rz(yaw) Ry(pitch) Rx(roll)
    EDGE3 a b x y z roll pitch yaw [21 information values, upper triangle row by row]
    EQUIV i j                                            i and j are the same place

2D information is 3x3 over (x, y, theta), lifted like g2o's.  ``EDGE3`` information is taken as
information over (rho, phi) (docs/conventions.md); ``edge3_order="documented"`` reads the 21 values
over
(x, y, z, roll, pitch, yaw), ``"code"`` over (roll, pitch, yaw, x, y, z) (TORO's own code).  An
``EDGE3`` with no information gets the identity (one warning per file).  ``EQUIV i j`` merges
vertex j into i: ids are remapped, j's vertex line is dropped, edges that become self-loops are
dropped (one warning per file with the counts).
"""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import FormatError
from ..graph import PoseGraph, lift_information_2d, planar_information
from ._lines import (
    Block,
    FloatArray,
    IntArray,
    Parts,
    PathLike,
    Source,
    TagSpec,
    assemble,
    check_duplicate_vertices,
    check_self_loops,
    euler_rpy_to_matrix,
    fmt_floats,
    load_source,
    matrix_to_euler_rpy,
    parse_blocks,
    require_planar,
    require_readable_information,
    rot_z,
    spd_filter,
    stack,
    sym_from_upper,
    upper_from_sym,
    upper_names,
    write_atomic,
    yaw_of,
)

_INFO2 = ("inf_xx", "inf_xy", "inf_yy", "inf_tt", "inf_xt", "inf_yt")
_RPY = ("roll", "pitch", "yaw")

SPECS: dict[str, TagSpec] = {
    "VERTEX2": TagSpec("VERTEX2", ("id",), ("x", "y", "theta")),
    "EDGE2": TagSpec("EDGE2", ("id_a", "id_b"), ("dx", "dy", "dtheta", *_INFO2)),
    "VERTEX3": TagSpec("VERTEX3", ("id",), ("x", "y", "z", *_RPY)),
    "EDGE3": TagSpec("EDGE3", ("id_a", "id_b"), ("x", "y", "z", *_RPY,
                                                  *upper_names("I", "123456")), optional_from=6),
    "EQUIV": TagSpec("EQUIV", ("id_a", "id_b")),
}
TAGS: tuple[str, ...] = tuple(SPECS)
EDGE3_ORDERS = ("documented", "code")

#: TORO 2D order (xx, xy, yy, tt, xt, yt) -> (row, col) of the 3x3 over (x, y, theta).
_TORO2_ROWS = np.array([0, 0, 1, 2, 0, 1])
_TORO2_COLS = np.array([0, 1, 1, 2, 2, 2])
#: "code" order lists the 21 values over (roll, pitch, yaw, x, y, z): index of our (rho, phi)
#: coordinate in that order.
_CODE_PERM = np.array([3, 4, 5, 0, 1, 2])


def _check_order(edge3_order: str) -> None:
    if edge3_order not in EDGE3_ORDERS:
        raise ValueError(f"edge3_order must be one of {EDGE3_ORDERS}, got {edge3_order!r}")


def toro2_information(vals: FloatArray) -> FloatArray:
    """(k, 6) TORO ``inf_xx inf_xy inf_yy inf_tt inf_xt inf_yt`` -> (k, 3, 3) over (x, y, theta)."""
    out = np.zeros((vals.shape[0], 3, 3))
    out[:, _TORO2_ROWS, _TORO2_COLS] = vals
    out[:, _TORO2_COLS, _TORO2_ROWS] = vals
    return out


def read_toro(path: PathLike, *, skip_unknown: bool = False, edge3_order: str = "documented",
              check_connected: bool = True,
              fix_information: str | None = None) -> PoseGraph:
    """Read a TORO ``.graph`` file (2D ``VERTEX2``/``EDGE2`` or 3D ``VERTEX3``/``EDGE3``).

    Parameters
    ----------
    path
        The file.
    skip_unknown
        Skip lines with other tags (one warning with the count) instead of raising.
    edge3_order
        ``"documented"`` (translation first) or ``"code"`` (rotation first): how the 21
        ``EDGE3`` information values are ordered.
    check_connected
        Raise when the graph (after ``EQUIV`` merging) falls apart into several pieces.
    fix_information
        As :func:`~hybridpgo.io.read_g2o`.

    Raises
    ------
    FormatError
        As :func:`~hybridpgo.io.read_g2o`; also for ``EQUIV`` lines naming unknown vertices.
    """
    _check_order(edge3_order)
    return read_toro_source(load_source(path, fix_information), skip_unknown=skip_unknown,
                            edge3_order=edge3_order, check_connected=check_connected)


def read_toro_source(src: Source, *, skip_unknown: bool, edge3_order: str,
                     check_connected: bool) -> PoseGraph:
    _check_order(edge3_order)
    blocks = parse_blocks(src, SPECS, "TORO", skip_unknown)
    first2 = min((src.first_line(t) for t in ("VERTEX2", "EDGE2") if t in blocks), default=None)
    first3 = min((src.first_line(t) for t in ("VERTEX3", "EDGE3") if t in blocks), default=None)
    if first2 is not None and first3 is not None:
        raise src.error(max(first2, first3), "the file mixes 2D and 3D lines (the other kind "
                        f"starts at line {min(first2, first3)}); a TORO file must be all 2D or "
                        "all 3D")
    parts = Parts(is_2d=first3 is None)
    if parts.is_2d:
        _read_2d(src, blocks, parts)
    else:
        _read_3d(src, blocks, parts, edge3_order)
    if "EQUIV" in blocks:
        _merge_equiv(src, blocks["EQUIV"], parts)
    return assemble(src, "toro", parts, check_connected)


def _read_2d(src: Source, blocks: dict[str, list[Block]], parts: Parts) -> None:
    ln, ids, v, _ = stack(blocks.get("VERTEX2", []))
    if ln.size:
        parts.vertex_ids, parts.vertex_lines = ids[:, 0], ln
        parts.vertex_rotations = rot_z(v[:, 2])
        parts.vertex_translations = np.column_stack([v[:, 0], v[:, 1], np.zeros(ln.shape[0])])
    ln, ids, v, _ = stack(blocks.get("EDGE2", []))
    if ln.size:
        info3, keep = spd_filter(src, toro2_information(v[:, 3:9]), ln, "EDGE2",
                                 "information matrix (TORO order inf_xx inf_xy inf_yy inf_tt "
                                 "inf_xt inf_yt)")
        ln, ids, v, info3 = ln[keep], ids[keep], v[keep], info3[keep]
        parts.edge_ids, parts.edge_lines = ids, ln
        parts.edge_rotations = rot_z(v[:, 2])
        parts.edge_translations = np.column_stack([v[:, 0], v[:, 1], np.zeros(ln.shape[0])])
        parts.edge_information = lift_information_2d(info3)


def _read_3d(src: Source, blocks: dict[str, list[Block]], parts: Parts, order: str) -> None:
    ln, ids, v, _ = stack(blocks.get("VERTEX3", []))
    if ln.size:
        parts.vertex_ids, parts.vertex_lines = ids[:, 0], ln
        parts.vertex_rotations = euler_rpy_to_matrix(v[:, 3:6])
        parts.vertex_translations = np.ascontiguousarray(v[:, 0:3])
    edge_blocks = blocks.get("EDGE3", [])
    if not edge_blocks:
        return
    infos, bare_lines, kept = [], [], []
    for b in edge_blocks:
        if b.values.shape[1] == 27:
            info = sym_from_upper(b.values[:, 6:27], 6)
            if order == "code":  # checked in our order, as written back (same bits)
                info = info[:, _CODE_PERM[:, None], _CODE_PERM[None, :]]
            info, keep = spd_filter(src, info, b.line_nos, "EDGE3",
                                    "information matrix (21 values over "
                                    + ("x, y, z, roll, pitch, yaw)" if order == "documented"
                                       else "roll, pitch, yaw, x, y, z: edge3_order='code')"))
            info = info[keep]
        else:  # no information on the line: identity, warned about below
            keep = np.ones(len(b), bool)
            info = np.broadcast_to(np.eye(6), (len(b), 6, 6)).copy()
            bare_lines.append(b.line_nos)
        infos.append(info)
        kept.append(keep)
    all_lines = np.concatenate([b.line_nos[k] for b, k in zip(edge_blocks, kept, strict=True)])
    order_idx = np.argsort(all_lines, kind="stable")
    ln = all_lines[order_idx]
    ids = np.concatenate([b.ids[k] for b, k in zip(edge_blocks, kept, strict=True)])[order_idx]
    v = np.concatenate([b.values[k, 0:6] for b, k in zip(edge_blocks, kept,
                                                         strict=True)])[order_idx]
    parts.edge_ids, parts.edge_lines = ids, ln
    parts.edge_rotations = euler_rpy_to_matrix(v[:, 3:6])
    parts.edge_translations = np.ascontiguousarray(v[:, 0:3])
    parts.edge_information = np.concatenate(infos)[order_idx]
    if bare_lines:
        bare = np.concatenate(bare_lines)
        warnings.warn(f"{src.path}: {bare.shape[0]} EDGE3 line(s) have no information matrix "
                      f"(first at line {int(bare.min())}); using identity information for them",
                      UserWarning, stacklevel=4)


def _merge_equiv(src: Source, equiv: list[Block], parts: Parts) -> None:
    """EQUIV i j: vertex j is the same place as i; merge j into i (union-find, file order)."""
    ln, pairs, _, _ = stack(equiv)
    check_self_loops(src, parts.edge_ids, parts.edge_lines)  # on the file's own edges
    if parts.vertex_ids.size:
        check_duplicate_vertices(src, parts.vertex_ids, parts.vertex_lines)
        known = set(parts.vertex_ids.tolist())
    else:
        known = set(parts.edge_ids.reshape(-1).tolist())
    parent: dict[int, int] = {}

    def find(x: int) -> int:
        root = x
        while parent.get(root, root) != root:
            root = parent[root]
        while parent.get(x, x) != root:  # path compression
            parent[x], x = root, parent[x]
        return root

    for k in range(ln.shape[0]):
        i, j = int(pairs[k, 0]), int(pairs[k, 1])
        for v in (i, j):
            if v not in known:
                raise src.error(int(ln[k]), f"EQUIV refers to vertex {v}, which "
                                + ("no vertex line defines" if parts.vertex_ids.size
                                   else "no edge uses"))
        if i == j:
            raise src.error(int(ln[k]), f"EQUIV names vertex {i} twice")
        ri, rj = find(i), find(j)
        if ri != rj:
            parent[rj] = ri
    merged = {v: find(v) for v in list(parent)}
    merged = {v: r for v, r in merged.items() if v != r}
    if not merged:
        return
    keys = np.array(sorted(merged), np.int64)
    vals = np.array([merged[int(v)] for v in keys], np.int64)

    def remap(a: IntArray) -> IntArray:
        if a.size == 0:
            return a
        pos = np.searchsorted(keys, a).clip(0, keys.shape[0] - 1)
        hit = keys[pos] == a
        return np.where(hit, vals[pos], a)

    if parts.vertex_ids.size:
        keep = ~np.isin(parts.vertex_ids, keys)
        parts.vertex_ids = parts.vertex_ids[keep]
        parts.vertex_lines = parts.vertex_lines[keep]
        parts.vertex_rotations = parts.vertex_rotations[keep]
        parts.vertex_translations = parts.vertex_translations[keep]
    ids = remap(parts.edge_ids)
    keep = ids[:, 0] != ids[:, 1]
    dropped = int((~keep).sum())
    parts.edge_ids = ids[keep]
    parts.edge_lines = parts.edge_lines[keep]
    parts.edge_rotations = parts.edge_rotations[keep]
    parts.edge_translations = parts.edge_translations[keep]
    parts.edge_information = parts.edge_information[keep]
    warnings.warn(f"{src.path}: {ln.shape[0]} EQUIV line(s) merged {len(merged)} vertex id(s) "
                  f"into others; dropped {dropped} edge(s) that became self-loops",
                  UserWarning, stacklevel=4)


# =========================================================================== writing
def write_toro(graph: PoseGraph, path: PathLike, *, edge3_order: str = "documented") -> None:
    """Write ``graph`` as TORO, atomically (temporary file + ``os.replace``).

    2D graphs as ``VERTEX2``/``EDGE2`` (TORO information order), 3D graphs as
    ``VERTEX3``/``EDGE3`` with roll-pitch-yaw angles and 21 information values in
    ``edge3_order``.  Vertex lines are always written (identity poses for a graph without
    estimates): TORO needs them, and an edges-only file would be read as iSAM.

    Raises
    ------
    FormatError
        When the graph has position priors or ``FIX`` nodes (TORO cannot store them), a 2D
        graph is not planar, or the file cannot be written.
    """
    _check_order(edge3_order)
    name = str(path)
    write_atomic(path, lambda: toro_lines(graph, name, edge3_order))


def toro_lines(graph: PoseGraph, name: str, edge3_order: str = "documented") -> list[str]:
    """The lines :func:`write_toro` writes (``name`` is used in messages)."""
    _check_order(edge3_order)
    if graph.num_gps:
        raise FormatError("the TORO format cannot store position (GPS) priors; write g2o "
                          "instead", name)
    if graph.fixed_nodes.size:
        raise FormatError("the TORO format cannot store FIX lines (fixed nodes "
                          f"{graph.node_ids[graph.fixed_nodes].tolist()}); write g2o instead",
                          name)
    if graph.is_2d:
        require_planar(graph, name, "TORO")
        require_readable_information(graph, planar_information(graph.edge_information), name,
                                     "TORO")
    return _toro_lines(graph, edge3_order)


def _toro_lines(graph: PoseGraph, order: str) -> list[str]:
    ids = graph.node_ids
    out: list[str] = []
    ea = ids[graph.edge_nodes[:, 0]].tolist()
    eb = ids[graph.edge_nodes[:, 1]].tolist()
    if graph.is_2d:
        t = graph.translations
        rows = fmt_floats(np.column_stack([t[:, 0], t[:, 1], yaw_of(graph.rotations)]))
        out += [f"VERTEX2 {i} {r}" for i, r in zip(ids.tolist(), rows, strict=True)]
        info3 = planar_information(graph.edge_information)
        et = graph.edge_translations
        vals = np.column_stack([et[:, 0], et[:, 1], yaw_of(graph.edge_rotations),
                                info3[:, _TORO2_ROWS, _TORO2_COLS]])
        out += [f"EDGE2 {a} {b} {r}" for a, b, r in zip(ea, eb, fmt_floats(vals), strict=True)]
        return out
    rows = fmt_floats(np.column_stack([graph.translations, matrix_to_euler_rpy(graph.rotations)]))
    out += [f"VERTEX3 {i} {r}" for i, r in zip(ids.tolist(), rows, strict=True)]
    info = graph.edge_information
    if order == "code":
        inv = np.argsort(_CODE_PERM)
        info = info[:, inv[:, None], inv[None, :]]
    vals = np.column_stack([graph.edge_translations, matrix_to_euler_rpy(graph.edge_rotations),
                            upper_from_sym(info)])
    out += [f"EDGE3 {a} {b} {r}" for a, b, r in zip(ea, eb, fmt_floats(vals), strict=True)]
    return out

