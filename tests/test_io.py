"""Tests of the file-format layer ``hybridpgo.io`` (docs/conventions.md,
docs/contributing.md#errors and docs/contributing.md#tests)."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridpgo.errors import FormatError
from hybridpgo.graph import PoseGraph, lift_information_2d, planar_information
from hybridpgo.io import (
    FORMATS,
    SUPPORTED_TAGS,
    bundled_names,
    bundled_path,
    detect_format,
    read_g2o,
    read_graph,
    read_isam,
    read_toro,
    write_g2o,
    write_graph,
    write_isam,
    write_toro,
)
from hybridpgo.io._lines import euler_rpy_to_matrix, matrix_to_euler_rpy, write_atomic

try:  # shared constants (tests/tolerances.py), else the same value here
    from tolerances import FLOAT64_IDENTITY
except ImportError:  # pragma: no cover - depends on another helper's file
    FLOAT64_IDENTITY = 1e-12

#: Round trips: rotations and unit-scale numbers absolutely, translations and information
#: relative to their size (repr writing is exact; conversions cost a few ulps).
ROUND_TRIP = FLOAT64_IDENTITY
#: The iSAM M3500 file prints sqrt(2000) with 10 significant digits.
PRINTED_SQRT_2000 = 1e-9

DATA = Path(__file__).parent / "data"
IDENT6 = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"  # 21 upper-triangular entries of I6


def write(tmp_path: Path, name: str, *lines: str, newline: str = "\n") -> Path:
    p = tmp_path / name
    p.write_bytes((newline.join(lines) + newline).encode())
    return p


def _rel(x: np.ndarray, y: np.ndarray) -> float:
    """Largest difference, per item relative to that item's largest entry (>= 1)."""
    if x.size == 0:
        return 0.0
    k = x.shape[0]
    scale = np.maximum(np.abs(x).reshape(k, -1).max(axis=1), 1.0)
    return float((np.abs(x - y).reshape(k, -1).max(axis=1) / scale).max())


def assert_same_graph(a: PoseGraph, b: PoseGraph, *, estimates: bool = True) -> None:
    np.testing.assert_array_equal(a.node_ids, b.node_ids)
    np.testing.assert_array_equal(a.edge_nodes, b.edge_nodes)
    np.testing.assert_array_equal(a.gps_nodes, b.gps_nodes)
    np.testing.assert_array_equal(a.fixed_nodes, b.fixed_nodes)
    assert a.is_2d == b.is_2d
    assert _rel(a.edge_rotations, b.edge_rotations) <= ROUND_TRIP
    assert _rel(a.edge_translations, b.edge_translations) <= ROUND_TRIP
    assert _rel(a.edge_information, b.edge_information) <= ROUND_TRIP
    assert _rel(a.gps_positions, b.gps_positions) <= ROUND_TRIP
    assert _rel(a.gps_information, b.gps_information) <= ROUND_TRIP
    if estimates:
        assert _rel(a.rotations, b.rotations) <= ROUND_TRIP
        assert _rel(a.translations, b.translations) <= ROUND_TRIP


# =========================================================================== bundled & test data
EXPECTED_COUNTS = {  # from datasets/README.md (poses, edges, 2D, has vertex lines, format)
    "M3500_isam.txt": (3500, 5598, True, False, "isam"),
    "intel.g2o": (1728, 2512, True, True, "g2o"),
    "garage.g2o": (1661, 6275, False, True, "g2o"),
}


@pytest.mark.parametrize("name", sorted(EXPECTED_COUNTS))
def test_bundled_files_read(name: str) -> None:
    g = read_graph(bundled_path(name))
    n, m, is_2d, has_est, fmt = EXPECTED_COUNTS[name]
    assert (g.num_nodes, g.num_edges, g.is_2d, g.has_estimates, g.source_format) == (
        n, m, is_2d, has_est, fmt)
    np.testing.assert_array_equal(g.node_ids, np.arange(n))


def test_bundled_names_and_missing_name() -> None:
    assert set(EXPECTED_COUNTS) <= set(bundled_names())
    with pytest.raises(FormatError, match=r"no bundled graph named 'nope\.g2o'; available: .*"
                       r"M3500_isam\.txt"):
        bundled_path("nope.g2o")


@pytest.mark.parametrize(("name", "n", "m"), [("tinyGrid3D.g2o", 9, 11),
                                              ("smallGrid3D.g2o", 125, 297)])
def test_grid_files_read(name: str, n: int, m: int) -> None:
    g = read_g2o(DATA / name)
    assert (g.num_nodes, g.num_edges, g.is_2d) == (n, m, False)
    # Uniform blocks 100 I (translation) and 25 I (rotation, quaternion units) -> 25/4 per rad^2.
    np.testing.assert_array_equal(g.edge_information[0], np.diag([100.0] * 3 + [6.25] * 3))
    rtr = np.swapaxes(g.rotations, 1, 2) @ g.rotations
    assert np.abs(rtr - np.eye(3)).max() <= ROUND_TRIP  # quaternions normalized on load


def test_m3500_isam_square_root_information() -> None:
    """iSAM numbers are sqrt-information: 44.72135955 = sqrt(2000) -> Omega = 2000 I."""
    g = read_isam(bundled_path("M3500_isam.txt"))
    info3 = planar_information(g.edge_information[:1])[0]
    np.testing.assert_array_equal(info3, 44.72135955**2 * np.eye(3))
    np.testing.assert_allclose(info3, 2000.0 * np.eye(3), rtol=PRINTED_SQRT_2000, atol=0)
    assert not g.has_estimates
    np.testing.assert_array_equal(g.rotations, np.broadcast_to(np.eye(3), (3500, 3, 3)))
    np.testing.assert_array_equal(g.translations, 0.0)


def test_intel_2d_lift_is_planar_information() -> None:
    g = read_g2o(bundled_path("intel.g2o"))
    first = (bundled_path("intel.g2o").read_text().splitlines()[1728]).split()
    assert first[0] == "EDGE_SE2"
    i11, i12, i13, i22, i23, i33 = map(float, first[6:12])
    file_info = np.array([[i11, i12, i13], [i12, i22, i23], [i13, i23, i33]])
    info = g.edge_information[0]
    np.testing.assert_array_equal(planar_information(g.edge_information[:1])[0], file_info)
    np.testing.assert_array_equal(info, lift_information_2d(file_info[None])[0])
    stiff = max(i11, i22, i33)  # docs/conventions.md: z, roll, pitch get the largest in-plane
    # diagonal
    np.testing.assert_array_equal(np.diag(info)[2:5], [stiff] * 3)
    assert np.count_nonzero(info[2:5, :] - np.diag(np.diag(info))[2:5, :]) == 0
    # Measurements are planar: z = 0, rotation about z only.
    assert np.all(g.edge_translations[:, 2] == 0.0)
    np.testing.assert_array_equal(g.edge_rotations[:, 2, :], np.tile([0.0, 0.0, 1.0], (2512, 1)))


def test_w100_equiv_merge() -> None:
    path = DATA / "w100_toro.graph"
    pairs, edges = [], []
    for line in path.read_text().splitlines():
        t = line.split()
        if t and t[0] == "EQUIV":
            pairs.append((int(t[1]), int(t[2])))
        elif t and t[0] == "EDGE2":
            edges.append((int(t[1]), int(t[2])))
    # Oracle: "same place" is transitive (EQUIV 21 1 and EQUIV 41 1 make {1, 21, 41} one
    # place); merging j into i relabels j's whole class with i's label (plain loops).
    label = {v: v for v in range(100)}
    for i, j in pairs:
        old, new = label[j], label[i]
        label = {v: new if lab == old else lab for v, lab in label.items()}
    kept = [(label[a], label[b]) for a, b in edges if label[a] != label[b]]
    with pytest.warns(UserWarning, match=r"w100_toro\.graph: 40 EQUIV line\(s\) merged 40 vertex "
                      rf"id\(s\) into others; dropped {len(edges) - len(kept)} edge\(s\)"):
        g = read_toro(path)
    np.testing.assert_array_equal(g.node_ids, sorted(set(label.values())))
    got = [tuple(g.node_ids[e].tolist()) for e in g.edge_nodes]
    assert got == kept  # file order, remapped ids


# =========================================================================== conversions
def test_g2o_3d_information_scaled_by_p(tmp_path: Path) -> None:
    """docs/conventions.md: Omega_phi = P Omega_q P, P = diag(1, 1, 1, 1/2, 1/2, 1/2)."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    omega_q = a @ a.T + 6 * np.eye(6)
    iu = np.triu_indices(6)
    upper = " ".join(repr(float(v)) for v in omega_q[iu])
    p = write(tmp_path, "one.g2o", f"EDGE_SE3:QUAT 0 1 1 2 3 0 0 0 1 {upper}")
    g = read_g2o(p)
    scale = np.array([1, 1, 1, 0.5, 0.5, 0.5])
    np.testing.assert_array_equal(g.edge_information[0], omega_q * np.outer(scale, scale))
    write_g2o(g, tmp_path / "back.g2o")
    line = (tmp_path / "back.g2o").read_text().split()
    np.testing.assert_array_equal(np.array(line[10:31], float), omega_q[iu])  # exact inverse


def test_toro_2d_information_order(tmp_path: Path) -> None:
    """TORO EDGE2 order is xx xy yy tt xt yt (datasets/README.md), not g2o's."""
    row = [1.0, 0.0, 1.0, 10.0, 0.5, 0.5]
    misread = np.array([[1.0, 0.0, 1.0], [0.0, 10.0, 0.5], [1.0, 0.5, 0.5]])  # as g2o order
    assert np.linalg.eigvalsh(misread)[0] < 0  # the row would be indefinite if misread
    p = write(tmp_path, "o.graph", "VERTEX2 0 0 0 0", "VERTEX2 1 1 0 0",
              "EDGE2 0 1 1 0 0 " + " ".join(map(str, row)))
    g = read_toro(p)
    expected = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.5, 0.5, 10.0]])
    np.testing.assert_array_equal(planar_information(g.edge_information)[0], expected)
    write_toro(g, tmp_path / "back.graph")
    back = (tmp_path / "back.graph").read_text().splitlines()[-1].split()
    np.testing.assert_array_equal(np.array(back[6:], float), row)


def test_toro_edge3_information_orders(tmp_path: Path) -> None:
    # Translation diagonal 1, 2, 3; rotation diagonal 40, 50, 60; in the documented order.
    vals = np.zeros((6, 6))
    vals[np.diag_indices(6)] = [1, 2, 3, 40, 50, 60]
    upper = " ".join(map(str, vals[np.triu_indices(6)]))
    p = write(tmp_path, "e3.graph", "VERTEX3 0 0 0 0 0 0 0", "VERTEX3 1 1 0 0 0 0 0",
              f"EDGE3 0 1 1 0 0 0.1 0.2 0.3 {upper}")
    doc = read_graph(p)
    code = read_graph(p, toro_edge3_order="code")
    np.testing.assert_array_equal(np.diag(doc.edge_information[0]), [1, 2, 3, 40, 50, 60])
    np.testing.assert_array_equal(np.diag(code.edge_information[0]), [40, 50, 60, 1, 2, 3])
    np.testing.assert_array_equal(doc.edge_rotations[0],
                                  euler_rpy_to_matrix(np.array([[0.1, 0.2, 0.3]]))[0])
    write_toro(code, tmp_path / "code.graph", edge3_order="code")
    assert_same_graph(code, read_toro(tmp_path / "code.graph", edge3_order="code"))


def test_toro_edge3_without_information_warns_once(tmp_path: Path) -> None:
    ident7 = " ".join(str(7.0 * float(v)) for v in IDENT6.split())
    p = write(tmp_path, "bare.graph", "VERTEX3 0 0 0 0 0 0 0", "VERTEX3 1 1 0 0 0 0 0",
              "VERTEX3 2 2 0 0 0 0 0", "EDGE3 0 1 1 0 0 0 0 0", f"EDGE3 1 2 2 0 0 0 0 0 {ident7}",
              "EDGE3 2 0 3 0 0 0 0 0")
    with pytest.warns(UserWarning, match=r"2 EDGE3 line\(s\) have no information matrix "
                      r"\(first at line 4\); using identity") as rec:
        g = read_graph(p)
    assert len(rec) == 1
    assert g.source_format == "toro"
    np.testing.assert_array_equal(g.edge_translations[:, 0], [1, 2, 3])  # file order kept
    np.testing.assert_array_equal(g.edge_information,
                                  np.eye(6) * np.array([1.0, 7.0, 1.0])[:, None, None])


def test_euler_near_gimbal_lock_round_trip() -> None:
    pitches = [math.pi / 2, math.pi / 2 - 1e-9, -math.pi / 2 + 1e-7, 1.0]
    rpy = np.array([[0.3, p, -1.1] for p in pitches])
    r = euler_rpy_to_matrix(rpy)
    back = euler_rpy_to_matrix(matrix_to_euler_rpy(r))
    assert np.abs(back - r).max() <= ROUND_TRIP


def test_comments_blank_lines_crlf_and_tabs(tmp_path: Path) -> None:
    p = write(tmp_path, "crlf.g2o", "# a comment", "", "VERTEX_SE2 0 0 0 0",
              "  VERTEX_SE2\t1   1 0 0  ", "   ", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1", newline="\r\n")
    g = read_graph(p)
    assert (g.num_nodes, g.num_edges, g.is_2d) == (2, 1, True)


def test_fix_lines(tmp_path: Path) -> None:
    p = write(tmp_path, "fix.g2o", "VERTEX_SE2 5 0 0 0", "VERTEX_SE2 7 1 0 0", "FIX 7",
              "EDGE_SE2 5 7 1 0 0 1 0 0 1 0 1")
    g = read_g2o(p)
    np.testing.assert_array_equal(g.fixed_nodes, [1])
    np.testing.assert_array_equal(g.node_ids, [5, 7])
    write_g2o(g, tmp_path / "back.g2o")
    assert_same_graph(g, read_g2o(tmp_path / "back.g2o"))


def test_edges_only_g2o_has_no_estimates(tmp_path: Path) -> None:
    p = write(tmp_path, "e.g2o", "EDGE_SE2 3 9 1 0 0 1 0 0 1 0 1", "EDGE_SE2 9 4 1 0 0 1 0 0 1 0 1")
    g = read_graph(p)
    assert not g.has_estimates
    np.testing.assert_array_equal(g.node_ids, [3, 4, 9])
    np.testing.assert_array_equal(g.edge_nodes, [[0, 2], [2, 1]])


def test_check_connected_can_be_disabled(tmp_path: Path) -> None:
    p = write(tmp_path, "two.g2o", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1",
              "EDGE_SE2 2 3 1 0 0 1 0 0 1 0 1")
    assert read_graph(p, check_connected=False).num_nodes == 4


# =========================================================================== GPS priors
def _gps_graph() -> PoseGraph:
    rng = np.random.default_rng(1)
    n = 4
    q = rng.normal(size=(n, 4))
    from hybridpgo.io._lines import quat_xyzw_to_matrix

    rot = quat_xyzw_to_matrix(q)
    a = rng.normal(size=(3, 6, 6))
    g = rng.normal(size=(2, 3, 3))
    return PoseGraph(
        node_ids=np.array([0, 1, 2, 3]), rotations=rot, translations=rng.normal(size=(n, 3)),
        edge_nodes=np.array([[0, 1], [1, 2], [2, 3]]), edge_rotations=quat_xyzw_to_matrix(
            rng.normal(size=(3, 4))), edge_translations=rng.normal(size=(3, 3)),
        edge_information=a @ np.swapaxes(a, 1, 2) + np.eye(6),
        gps_nodes=np.array([0, 3]), gps_positions=rng.normal(size=(2, 3)) * 100,
        gps_information=g @ np.swapaxes(g, 1, 2) + np.eye(3), fixed_nodes=np.array([2]),
    )


def test_gps_round_trip(tmp_path: Path) -> None:
    g = _gps_graph()
    write_graph(g, tmp_path / "gps.g2o")  # source_format "" -> g2o
    text = (tmp_path / "gps.g2o").read_text()
    assert text.count("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n") == 1
    assert text.count("EDGE_SE3_XYZ_PRIOR ") == 2
    h = read_graph(tmp_path / "gps.g2o")
    assert_same_graph(g, h)
    assert h.source_format == "g2o"


def test_gps_read(tmp_path: Path) -> None:
    p = write(tmp_path, "gps.g2o", *V3,
              "PARAMS_SE3OFFSET 4 0 0 0 0 0 0 1", "EDGE_SE3_XYZ_PRIOR 1 4 10 20 30 1 0 0 2 0 3",
              "EDGE_SE3_XYZ_PRIOR 0 4 0 0 0 1 0 0 1 0 1")
    g = read_graph(p)  # no relative edge: connected through the earth node
    np.testing.assert_array_equal(g.gps_nodes, [1, 0])
    np.testing.assert_array_equal(g.gps_positions, [[10, 20, 30], [0, 0, 0]])
    np.testing.assert_array_equal(g.gps_information[0], np.diag([1.0, 2.0, 3.0]))


@pytest.mark.parametrize("fmt", ["toro", "isam"])
def test_gps_and_fix_cannot_be_written_to_toro_or_isam(tmp_path: Path, fmt: str) -> None:
    target = tmp_path / f"out.{fmt}"
    target.write_text("old content\n")
    with pytest.raises(FormatError, match=rf"out\.{fmt}: the (TORO|iSAM) format cannot store "
                       r"position \(GPS\) priors"):
        write_graph(_gps_graph(), target, fmt)
    assert target.read_text() == "old content\n"


# =========================================================================== detection
@pytest.mark.parametrize(("lines", "fmt"), [
    (["# header", "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1"], "g2o"),
    (["EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1"], "g2o"),
    (["UNKNOWN 1", "VERTEX2 0 0 0 0"], "toro"),
    (["EDGE2 0 1 1 0 0 1 0 1 1 0 0", "VERTEX2 0 0 0 0"], "toro"),
    (["EDGE3 0 1 1 0 0 0 0 0"], "toro"),
    (["ODOMETRY 0 1 1 0 0 1 0 0 1 0 1"], "isam"),
    (["EDGE2 0 1 1 0 0 1 0 0 1 0 1"], "isam"),
    ([f"EDGE3 0 1 1 0 0 0 0 0 {IDENT6}"], "isam"),
])
def test_detect_format(tmp_path: Path, lines: list[str], fmt: str) -> None:
    assert detect_format(write(tmp_path, "f.txt", *lines)) == fmt


def test_detect_format_failures(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"what\.txt:2: cannot detect the file format: tag "
                       r"'POINT'.*g2o: VERTEX_SE2"):
        detect_format(write(tmp_path, "what.txt", "# c", "POINT 1 2", "LANDMARK 3"))
    with pytest.raises(FormatError, match=r"empty\.g2o: empty file"):
        detect_format(write(tmp_path, "empty.g2o", "# only a comment", ""))


def test_supported_tags_and_bad_arguments(tmp_path: Path) -> None:
    assert set(SUPPORTED_TAGS) == set(FORMATS) == {"g2o", "toro", "isam"}
    assert "EDGE_SE3_XYZ_PRIOR" in SUPPORTED_TAGS["g2o"]
    assert "EQUIV" in SUPPORTED_TAGS["toro"]
    assert "ODOMETRY" in SUPPORTED_TAGS["isam"]
    p = write(tmp_path, "a.g2o", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1")
    with pytest.raises(ValueError, match="format must be one of"):
        read_graph(p, "graph")
    with pytest.raises(ValueError, match="toro_edge3_order must be one of"):
        read_graph(p, toro_edge3_order="rotation")


# =========================================================================== bad input
V2 = ("VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0")
E2 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1"
V3 = ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1")
E3 = f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {IDENT6}"

BAD_G2O = {
    "field count": ((*V3, E3.rsplit(" ", 1)[0]),
                    r"EDGE_SE3:QUAT needs 30 numbers after the tag, got 29"),
    "non-numeric": ((*V3, E3.replace(" 0 0 0 1 1 ", " 0 0 0 abc 1 ", 1)),
                    r"EDGE_SE3:QUAT field 'qw' is not a number: 'abc'"),
    "non-finite": ((*V2, "EDGE_SE2 0 1 nan 0 0 1 0 0 1 0 1"),
                   r"EDGE_SE2 field 'dx' is not finite: 'nan'"),
    "infinite information": ((*V2, "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 inf"),
                             r"EDGE_SE2 field 'I33' is not finite: 'inf'"),
    "non-integer id": ((*V2, "EDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1"),
                       r"EDGE_SE2 field 'id_b' must be an integer vertex id, got '1\.5'"),
    "huge id": ((*V2, "EDGE_SE2 99999999999999999999 1 1 0 0 1 0 0 1 0 1"),
                r"EDGE_SE2 field 'id_a' must be an integer vertex id, got '9+'"),
    "not positive definite": ((*V2, "EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1"),
                              r"information matrix .* is not positive definite \(smallest "
                              r"eigenvalue -1\)"),
    "3D not positive definite": ((*V3, E3.replace(IDENT6, IDENT6[:-1] + "0")),
                                 r"information matrix \(21 entries over x, y, z, qx, qy, qz\) is "
                                 r"not positive definite"),
    "unknown vertex": ((*V2, "EDGE_SE2 0 7 1 0 0 1 0 0 1 0 1"),
                       r"EDGE_SE2 refers to vertex 7, which no vertex line defines"),
    "duplicate vertex": ((V2[0], V2[1], "VERTEX_SE2 0 5 5 0"),
                         r"duplicate vertex id 0 \(VERTEX_SE2\); it was already defined at line 1"),
    "self-loop": ((*V2, "EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1"),
                  r"EDGE_SE2 connects vertex 1 to itself \(self-loop\)"),
    "unknown tag": ((*V2, "VERTEX_XY 3 1 2", E2),
                    r"unknown tag 'VERTEX_XY' for the g2o format; supported tags: VERTEX_SE2, "
                    r"EDGE_SE2, VERTEX_SE3:QUAT, .*FIX \(pass skip_unknown=True"),
    "zero quaternion": ((*V3, "VERTEX_SE3:QUAT 2 0 0 0 0 0 0 0"),
                        r"VERTEX_SE3:QUAT quaternion \(qx, qy, qz, qw\) is zero"),
    "mixed 2D/3D": ((V2[0], V2[1], V3[0]), r"the file mixes SE\(2\) and SE\(3\) lines \(the other "
                    r"kind starts at line 1\)"),
    "non-identity offset": ((*V3, "PARAMS_SE3OFFSET 0 0.1 0 0 0 0 0 1"),
                            r"PARAMS_SE3OFFSET 0 is not the identity offset"),
    "undeclared param": ((*V3, "EDGE_SE3_XYZ_PRIOR 1 2 0 0 0 1 0 0 1 0 1"),
                         r"EDGE_SE3_XYZ_PRIOR uses parameter id 2, which no PARAMS_SE3OFFSET"),
    "duplicate param": (("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1", *V3[:1],
                         "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1"),
                        r"PARAMS_SE3OFFSET 0 is declared twice \(first at line 1\)"),
    "prior not SPD": (("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1", V3[0],
                       "EDGE_SE3_XYZ_PRIOR 0 0 1 2 3 1 0 0 -1 0 1"),
                      r"information matrix \(I11 I12 I13 I22 I23 I33 over x, y, z\) is not "
                      r"positive definite"),
    "FIX unknown vertex": ((*V2, "FIX 9"), r"FIX refers to vertex 9, which no vertex line"),
    "FIX without id": ((*V2, "FIX"), r"FIX needs at least one vertex id after the tag"),
}


@pytest.mark.parametrize("case", sorted(BAD_G2O))
def test_bad_g2o(tmp_path: Path, case: str) -> None:
    lines, problem = BAD_G2O[case]
    with pytest.raises(FormatError, match=r"bad\.g2o:3: " + problem) as info:
        read_graph(write(tmp_path, "bad.g2o", *lines))
    assert info.value.line_no == 3
    assert info.value.line == lines[2]


BAD_OTHER = {
    "toro count": ("bad.graph", "toro", ("VERTEX2 0 0 0 0", "VERTEX2 1 1 0 0",
                                         "EDGE2 0 1 1 0 0 1 0 1 1 0"),
                   r"EDGE2 needs 11 numbers after the tag, got 10"),
    "toro EDGE3 count": ("bad.graph", "toro", ("VERTEX3 0 0 0 0 0 0 0", "VERTEX3 1 1 0 0 0 0 0",
                                               "EDGE3 0 1 1 0 0 0 0 0 1 0"),
                         r"EDGE3 needs 29 numbers after the tag \(or 8 without the information "
                         r"matrix\), got 10"),
    "toro 2D not SPD": ("bad.graph", "toro", ("VERTEX2 0 0 0 0", "VERTEX2 1 1 0 0",
                                              "EDGE2 0 1 1 0 0 1 0 1 0 0 0"),
                        r"information matrix \(TORO order inf_xx inf_xy inf_yy inf_tt inf_xt "
                        r"inf_yt\) is not positive definite \(smallest eigenvalue 0\)"),
    "toro EQUIV unknown": ("bad.graph", "toro", ("VERTEX2 0 0 0 0", "VERTEX2 1 1 0 0",
                                                 "EQUIV 0 5"),
                           r"EQUIV refers to vertex 5, which no vertex line defines"),
    "toro unknown tag": ("bad.graph", "toro", ("VERTEX2 0 0 0 0", "VERTEX2 1 1 0 0", E2),
                         r"unknown tag 'EDGE_SE2' for the TORO format; supported tags: VERTEX2, "
                         r"EDGE2, VERTEX3, EDGE3, EQUIV"),
    "isam singular sqrt": ("bad.txt", "isam", ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1",
                                               "ODOMETRY 1 2 1 0 0 1 0 0 1 0 1",
                                               "ODOMETRY 2 3 1 0 0 1 0 0 1 0 0"),
                           r"information matrix is not positive definite \(smallest eigenvalue "
                           r"0\) \(the numbers are the upper-triangular square-root"),
    "isam count": ("bad.txt", "isam", ("EDGE3 0 1 1 0 0 0 0 0 " + IDENT6,
                                       "EDGE3 1 2 1 0 0 0 0 0 " + IDENT6,
                                       "EDGE3 2 3 1 0 0 0 0 0 1"),
                   r"EDGE3 needs 29 numbers after the tag, got 9"),
    "isam vertex tag": ("bad.txt", "isam", ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1",
                                            "ODOMETRY 1 2 1 0 0 1 0 0 1 0 1",
                                            "VERTEX2 0 0 0 0"),
                        r"unknown tag 'VERTEX2' for the iSAM format; supported tags: ODOMETRY, "
                        r"EDGE2, EDGE3"),
    "isam self-loop": ("bad.txt", None, ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1",
                                         "ODOMETRY 1 2 1 0 0 1 0 0 1 0 1",
                                         "ODOMETRY 2 2 1 0 0 1 0 0 1 0 1"),
                       r"ODOMETRY connects vertex 2 to itself"),
}


@pytest.mark.parametrize("case", sorted(BAD_OTHER))
def test_bad_toro_and_isam(tmp_path: Path, case: str) -> None:
    name, fmt, lines, problem = BAD_OTHER[case]
    with pytest.raises(FormatError, match=re.escape(name) + ":3: " + problem):
        read_graph(write(tmp_path, name, *lines), fmt)


def test_unknown_tags_skipped_with_one_warning(tmp_path: Path) -> None:
    p = write(tmp_path, "skip.g2o", *V2, "VERTEX_XY 3 1 2", "VERTEX_XY 4 1 2", E2,
              "EDGE_SE2_XY 0 3 1 2 1 0 1")
    with pytest.warns(UserWarning, match=r"skip\.g2o: skipped 3 line\(s\) with tags the g2o "
                      r"reader does not support: VERTEX_XY \(2\), EDGE_SE2_XY \(1\)") as rec:
        g = read_graph(p, skip_unknown=True)
    assert len(rec) == 1
    assert (g.num_nodes, g.num_edges) == (2, 1)


def test_empty_file(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"bad\.g2o: empty file: no vertex or edge lines"):
        read_graph(write(tmp_path, "bad.g2o", "# nothing", "", "   "))
    with pytest.raises(FormatError, match=r"bad\.g2o: empty file"):
        read_graph(write(tmp_path, "bad.g2o", "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1"), "g2o")


def test_disconnected_file(tmp_path: Path) -> None:
    p = write(tmp_path, "bad.g2o", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1",
              "EDGE_SE2 5 6 1 0 0 1 0 0 1 0 1", "EDGE_SE2 6 7 1 0 0 1 0 0 1 0 1")
    with pytest.raises(FormatError, match=r"bad\.g2o: the graph is not connected: 2 separate "
                       r"parts: 2 pose\(s\) 0\.\.1 .*; 3 pose\(s\) 5\.\.7") as info:
        read_graph(p)
    assert info.value.line_no is None


def test_unreadable_file(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"missing\.g2o: cannot read the file: No such file"):
        read_graph(tmp_path / "missing.g2o")
    with pytest.raises(FormatError, match=r"cannot read the file: Is a directory"):
        read_graph(tmp_path)


# =========================================================================== writing
def test_write_default_formats(tmp_path: Path) -> None:
    isam = read_graph(bundled_path("M3500_isam.txt"))
    write_graph(isam, tmp_path / "m3500.out")  # isam source -> g2o, no vertex lines
    text = (tmp_path / "m3500.out").read_text()
    assert text.startswith("EDGE_SE2 0 1 ")
    back = read_graph(tmp_path / "m3500.out")
    assert back.source_format == "g2o" and not back.has_estimates
    assert_same_graph(isam, back)
    tiny = read_graph(DATA / "tinyGrid3D.g2o")
    write_graph(tiny, tmp_path / "tiny.toro", "toro")
    toro = read_graph(tmp_path / "tiny.toro")
    write_graph(toro, tmp_path / "again")  # toro source -> toro
    assert (tmp_path / "again").read_text().startswith("VERTEX3 0 ")
    write_graph(_gps_graph(), tmp_path / "code")  # built in code ("") -> g2o
    assert (tmp_path / "code").read_text().startswith("VERTEX_SE3:QUAT 0 ")


def test_write_into_missing_directory(tmp_path: Path) -> None:
    g = read_graph(DATA / "tinyGrid3D.g2o")
    with pytest.raises(FormatError, match=r"out\.g2o: cannot write the file"):
        write_graph(g, tmp_path / "no" / "such" / "out.g2o")


def test_write_atomic_leaves_no_half_file(tmp_path: Path) -> None:
    target = tmp_path / "keep.g2o"
    target.write_text("precious\n")

    def produce():  # type: ignore[no-untyped-def]
        yield "first line"
        raise RuntimeError("disk full (simulated)")

    with pytest.raises(RuntimeError, match="simulated"):
        write_atomic(target, produce)
    assert target.read_text() == "precious\n"
    assert os.listdir(tmp_path) == ["keep.g2o"]  # the temporary file is gone


def test_write_2d_graph_must_be_planar(tmp_path: Path) -> None:
    g = read_graph(bundled_path("intel.g2o"))
    t = g.translations.copy()
    t[3, 2] = 0.5
    bent = g.with_poses(g.rotations, t)
    with pytest.raises(FormatError, match=r"cannot write the 2D graph as g2o SE\(2\) lines: pose 3 "
                       r"is not planar"):
        write_graph(bent, tmp_path / "bent.g2o")


# =========================================================================== round trips
WRITERS = {"g2o": write_g2o, "toro": write_toro, "isam": write_isam}


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("path", [bundled_path("intel.g2o"), bundled_path("garage.g2o"),
                                  bundled_path("M3500_isam.txt"), DATA / "tinyGrid3D.g2o",
                                  DATA / "smallGrid3D.g2o"], ids=lambda p: p.name)
def test_file_round_trip(tmp_path: Path, path: Path, fmt: str) -> None:
    g = read_graph(path)
    out = tmp_path / f"rt.{fmt}"
    write_graph(g, out, fmt)
    h = read_graph(out)  # detected from the content
    assert h.source_format == fmt
    # iSAM files hold no vertex lines; TORO writes identity vertices for a graph without any.
    assert_same_graph(g, h, estimates=fmt != "isam")
    assert h.has_estimates == (g.has_estimates if fmt == "g2o" else fmt == "toro")


def test_w100_round_trip(tmp_path: Path) -> None:
    with pytest.warns(UserWarning, match="EQUIV"):
        g = read_graph(DATA / "w100_toro.graph")
    write_graph(g, tmp_path / "w.graph")  # source toro -> toro, merged (no EQUIV lines)
    assert "EQUIV" not in (tmp_path / "w.graph").read_text()
    assert_same_graph(g, read_graph(tmp_path / "w.graph"))


def _random_rotations(rng: np.random.Generator, n: int, regime: str) -> np.ndarray:
    if regime == "planar":
        from hybridpgo.io._lines import rot_z

        return rot_z(rng.uniform(-math.pi, math.pi, n))
    if regime == "gimbal":  # pitch at or next to +-pi/2 (Euler formats' hard case)
        pitch = rng.choice([-1.0, 1.0], n) * (math.pi / 2 - rng.choice([0.0, 1e-9, 1e-6], n))
        rpy = np.column_stack([rng.uniform(-3, 3, n), pitch, rng.uniform(-3, 3, n)])
        return euler_rpy_to_matrix(rpy)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = {"random": rng.uniform(0, math.pi, n), "near_zero": rng.uniform(0, 1e-8, n),
             "near_pi": math.pi - rng.uniform(0, 1e-6, n)}[regime]
    k = np.zeros((n, 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k -= np.swapaxes(k, 1, 2)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def _random_graph(seed: int, is_2d: bool, regime: str) -> PoseGraph:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 8))
    ids = np.sort(rng.choice(1000, n, replace=False))
    parents = [int(rng.integers(0, i)) for i in range(1, n)]  # a random spanning tree
    extra = [tuple(rng.choice(n, 2, replace=False)) for _ in range(int(rng.integers(0, 4)))]
    edges = np.array([(p, i) for i, p in enumerate(parents, start=1)] + extra, np.int32)
    m = edges.shape[0]
    if is_2d:
        rot, erot = _random_rotations(rng, n, "planar"), _random_rotations(rng, m, "planar")
        t = np.column_stack([rng.normal(size=(n, 2)) * 10, np.zeros(n)])
        et = np.column_stack([rng.normal(size=(m, 2)) * 10, np.zeros(m)])
        a = rng.normal(size=(m, 3, 3))
        info = lift_information_2d(a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(3))
    else:
        rot, erot = _random_rotations(rng, n, regime), _random_rotations(rng, m, regime)
        t, et = rng.normal(size=(n, 3)) * 10, rng.normal(size=(m, 3)) * 10
        a = rng.normal(size=(m, 6, 6)) * rng.uniform(0.1, 100)
        info = a @ np.swapaxes(a, 1, 2) + 1e-3 * np.eye(6)
    return PoseGraph(node_ids=ids, rotations=rot, translations=t, edge_nodes=edges,
                     edge_rotations=erot, edge_translations=et, edge_information=info,
                     is_2d=is_2d)


@settings(deadline=None, max_examples=25)
@given(seed=st.integers(0, 2**32 - 1), is_2d=st.booleans(), fmt=st.sampled_from(FORMATS),
       regime=st.sampled_from(["random", "near_zero", "near_pi", "gimbal"]))
def test_round_trip_property(tmp_path_factory: pytest.TempPathFactory, seed: int, is_2d: bool,
                             fmt: str, regime: str) -> None:
    g = _random_graph(seed, is_2d, regime)
    out = tmp_path_factory.mktemp("rt") / "graph.txt"
    WRITERS[fmt](g, out)
    h = read_graph(out, fmt)
    assert h.source_format == fmt
    assert_same_graph(g, h, estimates=fmt != "isam")
