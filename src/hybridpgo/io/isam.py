"""The iSAM text format (docs/conventions.md; line layouts in ``datasets/README.md``).

Supported lines (edges only; iSAM files have no vertex lines)::

    ODOMETRY a b dx dy dtheta s11 s12 s13 s22 s23 s33
    EDGE2    a b dx dy dtheta s11 s12 s13 s22 s23 s33
    EDGE3    a b x y z roll pitch yaw s11 s12 ... s66 (21 values)

The ``s`` values are the upper-triangular **square-root** information ``R`` (row by row), so the
information is ``Omega = R^T R``, over (x, y, theta) in 2D and over (x, y, z, roll, pitch, yaw)
in 3D (taken as information over (rho, phi), docs/conventions.md).  Rotations: R = Rz(yaw) Ry(pitch)
Rx(roll).  The writer writes the upper Cholesky factor of Omega, so a round trip reproduces
Omega to rounding.  Node ids come from the edges (``has_estimates`` False).
"""

from __future__ import annotations

import numpy as np

from ..errors import FormatError
from ..graph import PoseGraph, lift_information_2d, planar_information
from ._lines import (
    FloatArray,
    Parts,
    PathLike,
    Source,
    TagSpec,
    assemble,
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
    upper_from_sym,
    upper_matrix,
    upper_names,
    write_atomic,
    yaw_of,
)

_S3 = upper_names("s", "123")
_S6 = upper_names("s", "123456")

SPECS: dict[str, TagSpec] = {
    "ODOMETRY": TagSpec("ODOMETRY", ("id_a", "id_b"), ("dx", "dy", "dtheta", *_S3)),
    "EDGE2": TagSpec("EDGE2", ("id_a", "id_b"), ("dx", "dy", "dtheta", *_S3)),
    "EDGE3": TagSpec("EDGE3", ("id_a", "id_b"), ("x", "y", "z", "roll", "pitch", "yaw", *_S6)),
}
TAGS: tuple[str, ...] = tuple(SPECS)

_HINT = (" (the numbers are the upper-triangular square-root information R, Omega = R^T R; a "
         "zero on R's diagonal makes Omega singular)")


def read_isam(path: PathLike, *, skip_unknown: bool = False,
              check_connected: bool = True,
              fix_information: str | None = None) -> PoseGraph:
    """Read an iSAM file (``ODOMETRY``/``EDGE2`` 2D or ``EDGE3`` 3D, square-root information).

    ``skip_unknown``, ``check_connected`` and ``fix_information`` as :func:`~hybridpgo.io.read_g2o`.

    Returns
    -------
    PoseGraph
        ``source_format == "isam"``, ``has_estimates`` False (identity rotations, zero
        translations), node ids = the sorted ids the edges use.

    Raises
    ------
    FormatError
        As :func:`~hybridpgo.io.read_g2o`.
    """
    return read_isam_source(load_source(path, fix_information), skip_unknown=skip_unknown,
                            check_connected=check_connected)


def _square(r_upper: FloatArray) -> FloatArray:
    # huge square roots overflow to inf here; spd_filter then reports the line
    with np.errstate(over="ignore", invalid="ignore"):
        omega = np.swapaxes(r_upper, 1, 2) @ r_upper
        return 0.5 * (omega + np.swapaxes(omega, 1, 2))  # exactly symmetric


def read_isam_source(src: Source, *, skip_unknown: bool, check_connected: bool) -> PoseGraph:
    blocks = parse_blocks(src, SPECS, "iSAM", skip_unknown)
    first2 = min((src.first_line(t) for t in ("ODOMETRY", "EDGE2") if t in blocks), default=None)
    if first2 is not None and "EDGE3" in blocks:
        first3 = src.first_line("EDGE3")
        raise src.error(max(first2, first3), "the file mixes 2D and 3D lines (the other kind "
                        f"starts at line {min(first2, first3)}); an iSAM file must be all 2D or "
                        "all 3D")
    parts = Parts(is_2d=first2 is not None)
    if parts.is_2d:
        ln, ids, v, _ = stack(blocks.get("ODOMETRY", []) + blocks.get("EDGE2", []))
        if ln.size:
            omega, keep = spd_filter(src, _square(upper_matrix(v[:, 3:9], 3)), ln,
                                     "/".join(t for t in ("ODOMETRY", "EDGE2") if t in blocks),
                                     "information matrix", _HINT)
            ln, ids, v, omega = ln[keep], ids[keep], v[keep], omega[keep]
            parts.edge_ids, parts.edge_lines = ids, ln
            parts.edge_rotations = rot_z(v[:, 2])
            parts.edge_translations = np.column_stack([v[:, 0], v[:, 1], np.zeros(ln.shape[0])])
            parts.edge_information = lift_information_2d(omega)
    else:
        ln, ids, v, _ = stack(blocks.get("EDGE3", []))
        if ln.size:
            omega, keep = spd_filter(src, _square(upper_matrix(v[:, 6:27], 6)), ln, "EDGE3",
                                     "information matrix", _HINT)
            ln, ids, v, omega = ln[keep], ids[keep], v[keep], omega[keep]
            parts.edge_ids, parts.edge_lines = ids, ln
            parts.edge_rotations = euler_rpy_to_matrix(v[:, 3:6])
            parts.edge_translations = np.ascontiguousarray(v[:, 0:3])
            parts.edge_information = omega
    return assemble(src, "isam", parts, check_connected)


def _upper_cholesky(omega: FloatArray, path: str, graph: PoseGraph) -> FloatArray:
    """Upper-triangular R with R^T R = Omega, for each (k, d, d) matrix."""
    try:
        chol = np.linalg.cholesky(omega)
    except np.linalg.LinAlgError:
        bad = next(k for k in range(omega.shape[0]) if _chol_fails(omega[k]))
        a, b = graph.node_ids[graph.edge_nodes[bad]].tolist()
        raise FormatError(f"edge {bad} ({a} -> {b}): information matrix is numerically not "
                          "positive definite, so it has no square root to write", path) from None
    return np.swapaxes(chol, 1, 2)


def _chol_fails(m: FloatArray) -> bool:
    try:
        np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        return True
    return False


def write_isam(graph: PoseGraph, path: PathLike) -> None:
    """Write ``graph`` as iSAM edges (``EDGE2`` or ``EDGE3``), atomically.

    The format has no vertex lines, so the vertex estimates are not written.  Information is
    written as the upper Cholesky factor R (Omega = R^T R).

    Raises
    ------
    FormatError
        When the graph has position priors or ``FIX`` nodes (not representable), a 2D graph is
        not planar, or the file cannot be written.
    """
    name = str(path)
    write_atomic(path, lambda: isam_lines(graph, name))


def isam_lines(graph: PoseGraph, name: str) -> list[str]:
    """The lines :func:`write_isam` writes (``name`` is used in messages)."""
    if graph.num_gps:
        raise FormatError("the iSAM format cannot store position (GPS) priors; write g2o "
                          "instead", name)
    if graph.fixed_nodes.size:
        raise FormatError("the iSAM format cannot store FIX lines (fixed nodes "
                          f"{graph.node_ids[graph.fixed_nodes].tolist()}); write g2o instead",
                          name)
    if graph.num_edges == 0:
        raise FormatError("the graph has no edges; an iSAM file holds only edges", name)
    if graph.is_2d:
        require_planar(graph, name, "iSAM")
    ea = graph.node_ids[graph.edge_nodes[:, 0]].tolist()
    eb = graph.node_ids[graph.edge_nodes[:, 1]].tolist()
    if graph.is_2d:
        r = _upper_cholesky(planar_information(graph.edge_information), name, graph)
        # the reader squares the written R again: check what it will get
        require_readable_information(graph, _square(r), name, "iSAM")
        et = graph.edge_translations
        vals = np.column_stack([et[:, 0], et[:, 1], yaw_of(graph.edge_rotations),
                                upper_from_sym(r)])
        tag = "EDGE2"
    else:
        r = _upper_cholesky(graph.edge_information, name, graph)
        require_readable_information(graph, _square(r), name, "iSAM")
        vals = np.column_stack([graph.edge_translations,
                                matrix_to_euler_rpy(graph.edge_rotations), upper_from_sym(r)])
        tag = "EDGE3"
    rows = fmt_floats(vals)
    return [f"{tag} {a} {b} {s}" for a, b, s in zip(ea, eb, rows, strict=True)]

