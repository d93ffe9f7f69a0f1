"""Hostile input for the readers and writers.

Each test here reproduced a defect before the fix: a traceback or a wrong result on finite
input, a misreported line, an unbounded error message, a lenient number parser.
"""

from __future__ import annotations

import os
import re
import stat
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from tolerances import FLOAT64_IDENTITY

from hybridpgo.errors import FormatError, GraphError
from hybridpgo.graph import MAX_INFORMATION, PoseGraph, lift_information_2d
from hybridpgo.io import (
    FIX_INFORMATION,
    NEAREST_SPD_FLOOR,
    WRITE_FORMATS,
    read_graph,
    read_tum,
    write_graph,
)

V2 = ("VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0")
E2 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1"
IDENT6 = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"


def write(tmp_path: Path, name: str, *lines: str) -> Path:
    p = tmp_path / name
    p.write_bytes(("\n".join(lines) + "\n").encode())
    return p


# =========================================================================== overflow
def test_isam_square_root_that_overflows_is_a_format_error(tmp_path: Path) -> None:
    # was: numpy.linalg.LinAlgError from the SPD check (R^T R overflows to inf)
    p = write(tmp_path, "big.txt", "ODOMETRY 0 1 1 0 0 1e200 0 0 1e200 0 1e200")
    with pytest.raises(FormatError, match=r"big\.txt:1: information .*too large"):
        read_graph(p)


def test_information_beyond_the_bound_is_a_format_error(tmp_path: Path) -> None:
    # was: read fine, then convert wrote an iSAM file that could not be read back, and the
    # chordal initialization failed with "SVD did not converge"
    p = write(tmp_path, "huge.g2o", *V2, "EDGE_SE2 0 1 1 0 0 1e308 0 0 1e308 0 1e308")
    with pytest.raises(FormatError, match=r"huge\.g2o:3: information .*too large.*1e\+150"):
        read_graph(p)
    with pytest.raises(GraphError, match="too large"):
        PoseGraph(node_ids=[0, 1], rotations=np.tile(np.eye(3), (2, 1, 1)),
                  translations=np.zeros((2, 3)), edge_nodes=[[0, 1]],
                  edge_rotations=np.eye(3)[None], edge_translations=np.zeros((1, 3)),
                  edge_information=np.eye(6)[None] * 1e200)


@pytest.mark.parametrize("fmt", ["g2o", "toro", "isam"])
@pytest.mark.parametrize("is_2d", [True, False])
def test_information_at_the_bound_round_trips_in_every_format(tmp_path: Path, fmt: str,
                                                              is_2d: bool) -> None:
    info = np.eye(3) * MAX_INFORMATION if is_2d else np.eye(6) * MAX_INFORMATION
    g = PoseGraph(node_ids=[0, 1], rotations=np.tile(np.eye(3), (2, 1, 1)),
                  translations=np.zeros((2, 3)), edge_nodes=[[0, 1]],
                  edge_rotations=np.eye(3)[None], edge_translations=np.zeros((1, 3)),
                  edge_information=info[None], is_2d=is_2d)
    path = tmp_path / f"at_bound.{fmt}"
    write_graph(g, path, fmt)
    back = read_graph(path, fmt)
    np.testing.assert_allclose(back.edge_information, g.edge_information,
                               rtol=FLOAT64_IDENTITY, atol=0)


# =========================================================================== quaternions
def test_huge_quaternion_component_is_normalized_not_identity(tmp_path: Path) -> None:
    # was: |q| overflowed to inf, q / inf = 0 and the zero quaternion gave the identity
    p = write(tmp_path, "q.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1",
              "VERTEX_SE3:QUAT 1 1 0 0 1e300 0 0 1",
              "VERTEX_SE3:QUAT 2 1 0 0 1e-300 0 0 1e-300",
              "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + IDENT6,
              "EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 " + IDENT6)
    g = read_graph(p)
    # qx dominates: the rotation by pi about x
    np.testing.assert_allclose(g.rotations[1], np.diag([1.0, -1.0, -1.0]), rtol=0,
                               atol=FLOAT64_IDENTITY)
    # (1e-300, 0, 0, 1e-300) is a quaternion, not zero: pi/2 about x
    np.testing.assert_allclose(g.rotations[2], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], rtol=0,
                               atol=FLOAT64_IDENTITY)


# =========================================================================== line numbers
@pytest.mark.parametrize("char", ["\f", "\v", "\x1c", "\x85", "\u2028"])
def test_odd_characters_inside_a_line_do_not_shift_line_numbers(tmp_path: Path,
                                                                 char: str) -> None:
    # was: str.splitlines() broke lines at these too, so every later line number was off by one
    p = write(tmp_path, "ff.g2o", f"VERTEX_SE2 0 0 0 0{char}", "VERTEX_SE2 1 1 0 0",
              E2, "EDGE_SE2 0 1 1 0 0 1 0 0 1 0")
    with pytest.raises(FormatError, match=r"ff\.g2o:4: EDGE_SE2 needs 11 numbers"):
        read_graph(p)


def test_old_mac_and_windows_line_ends_still_split(tmp_path: Path) -> None:
    p = tmp_path / "cr.g2o"
    p.write_bytes(b"VERTEX_SE2 0 0 0 0\rVERTEX_SE2 1 1 0 0\r\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n")
    with pytest.raises(FormatError, match=r"cr\.g2o:3: EDGE_SE2 needs 11 numbers"):
        read_graph(p)


# =========================================================================== tokens
@pytest.mark.parametrize("where", ["number", "id", "tag"])
def test_a_million_digit_token_gives_a_short_error(tmp_path: Path, where: str) -> None:
    big = "9" * 1_000_000
    line = {"number": f"VERTEX_SE2 0 0 0 {big}x", "id": f"VERTEX_SE2 {big} 0 0 0",
            "tag": f"{big} 0 0 0"}[where]
    p = write(tmp_path, "long.g2o", *V2, line, E2)
    with pytest.raises(FormatError, match=r"long\.g2o:3: ") as info:
        read_graph(p, "g2o")
    assert len(str(info.value)) < 400
    assert re.search(r"\.\.\. \(100000[01] characters\)", str(info.value))


@pytest.mark.parametrize("token", ["\u0661", "\uff13", "1\u0660", "\u0967.5"])
def test_non_ascii_digits_are_not_numbers(tmp_path: Path, token: str) -> None:
    # was: float("١") == 1.0, so Arabic-Indic or full-width digits were read as numbers
    p = write(tmp_path, "digits.g2o", *V2, f"EDGE_SE2 0 1 1 0 {token} 1 0 0 1 0 1")
    with pytest.raises(FormatError, match=r"digits\.g2o:3: EDGE_SE2 field 'dtheta' is not a "
                                          r"number"):
        read_graph(p)
    p = write(tmp_path, "ids.g2o", *V2, f"EDGE_SE2 0 {token} 1 0 0 1 0 0 1 0 1")
    with pytest.raises(FormatError, match=r"ids\.g2o:3: EDGE_SE2 field 'id_b' must be an "
                                          r"integer"):
        read_graph(p)


def test_non_ascii_digits_in_tum_are_not_numbers(tmp_path: Path) -> None:
    p = write(tmp_path, "t.tum", "0 0 0 0 0 0 0 1", "1 1 0 \u0661 0 0 0 1")
    with pytest.raises(FormatError, match=r"t\.tum:2: .*not a number"):
        read_tum(p)


# =========================================================================== non-SPD information
def _not_spd_file(tmp_path: Path) -> Path:
    """Five edges, lines 4 and 6 with information that is not positive definite."""
    return write(tmp_path, "nspd.g2o", "VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0",
                 "VERTEX_SE2 2 2 0 0",
                 "EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1",
                 "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1",
                 "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 0",
                 "EDGE_SE2 0 2 2 0 0 1 0 0 1 0 1",
                 "EDGE_SE2 1 2 1 0 0 2 0 0 2 0 2")


def test_non_spd_error_counts_the_edges_and_names_the_option(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"nspd\.g2o:4: information matrix .* is not positive "
                       r"definite \(smallest eigenvalue -1\); 2 of 5 EDGE_SE2 lines have such "
                       r"information \(lines 4, 6\); pass fix_information=\"nearest\" or "
                       r"\"skip\""):
        read_graph(_not_spd_file(tmp_path))


def test_fix_information_nearest_clips_eigenvalues(tmp_path: Path) -> None:
    with pytest.warns(UserWarning, match=r"nspd\.g2o: 2 of 5 EDGE_SE2 lines have information "
                      r"that is not positive definite \(lines 4, 6\); projected onto the "
                      r"nearest positive definite matrix") as rec:
        g = read_graph(_not_spd_file(tmp_path), fix_information="nearest")
    assert len(rec) == 1
    assert g.num_edges == 5
    planar = g.edge_information[:, [0, 1, 5]][:, :, [0, 1, 5]]
    # edge 0: diag(1, -1, 1) -> diag(1, floor, 1); edge 2: diag(1, 1, 0) -> diag(1, 1, floor)
    floor = NEAREST_SPD_FLOOR * 1.0
    np.testing.assert_allclose(planar[0], np.diag([1.0, floor, 1.0]), rtol=0,
                               atol=FLOAT64_IDENTITY)
    np.testing.assert_allclose(planar[2], np.diag([1.0, 1.0, floor]), rtol=0,
                               atol=FLOAT64_IDENTITY)
    # SPD matrices are untouched (bit for bit)
    np.testing.assert_array_equal(planar[4], np.diag([2.0, 2.0, 2.0]))
    assert np.linalg.eigvalsh(g.edge_information).min() > 0


def test_nearest_spd_is_the_frobenius_projection() -> None:
    from hybridpgo.io._lines import nearest_spd

    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 6, 6))
    a = a + np.swapaxes(a, 1, 2)
    p = nearest_spd(a)
    lam = np.linalg.eigvalsh(a)
    floor = NEAREST_SPD_FLOOR * np.abs(lam).max(axis=1)
    # oracle: ||A - P||_F^2 = sum of (lambda - max(lambda, floor))^2 (same eigenvectors)
    expect = np.sqrt((np.minimum(lam - floor[:, None], 0.0) ** 2).sum(axis=1))
    got = np.linalg.norm(a - p, axis=(1, 2))
    np.testing.assert_allclose(got, expect, rtol=0, atol=FLOAT64_IDENTITY * 10)
    np.testing.assert_array_equal(p, np.swapaxes(p, 1, 2))
    assert (np.linalg.eigvalsh(p)[:, 0] > 0).all()


def test_fix_information_skip_drops_the_edges(tmp_path: Path) -> None:
    with pytest.warns(UserWarning, match=r"nspd\.g2o: 2 of 5 EDGE_SE2 lines .*\(lines 4, 6\); "
                      r"dropped them"):
        g = read_graph(_not_spd_file(tmp_path), fix_information="skip")
    assert g.num_edges == 3
    np.testing.assert_array_equal(g.edge_nodes, [[1, 2], [0, 2], [1, 2]])


@pytest.mark.parametrize("case", ["toro2", "toro3", "isam2", "isam3", "g2o3", "prior"])
def test_fix_information_in_every_reader(tmp_path: Path, case: str) -> None:
    bad6 = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 -1"
    lines = {
        "toro2": ("VERTEX2 0 0 0 0", "VERTEX2 1 1 0 0", "EDGE2 0 1 1 0 0 1 0 1 1 0 0",
                  "EDGE2 0 1 1 0 0 1 0 -1 1 0 0"),
        "toro3": ("VERTEX3 0 0 0 0 0 0 0", "VERTEX3 1 1 0 0 0 0 0",
                  "EDGE3 0 1 1 0 0 0 0 0 " + IDENT6, "EDGE3 0 1 1 0 0 0 0 0 " + bad6),
        "isam2": ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1", "ODOMETRY 0 1 1 0 0 1 0 0 1 0 0"),
        "isam3": ("EDGE3 0 1 1 0 0 0 0 0 " + IDENT6,
                  "EDGE3 0 1 1 0 0 0 0 0 " + IDENT6[:-1] + "0"),
        "g2o3": ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1",
                 "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + IDENT6,
                 "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + bad6),
        "prior": ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1",
                  "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + IDENT6,
                  "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1",
                  "EDGE_SE3_XYZ_PRIOR 1 0 1 0 0 1 0 0 -1 0 1"),
    }[case]
    p = write(tmp_path, "f.txt", *lines)
    n = len(lines)
    with pytest.raises(FormatError, match=rf"f\.txt:{n}: .*not positive definite .*; 1 of "
                       rf"\d \S+ lines have such information \(lines? {n}\)"):
        read_graph(p)
    with pytest.warns(UserWarning, match=rf"f\.txt: 1 of \d \S+ lines .*\(lines? {n}\); projected"):
        g = read_graph(p, fix_information="nearest")
    assert np.linalg.eigvalsh(g.edge_information).min() > 0
    assert np.linalg.eigvalsh(g.gps_information).min(initial=1.0) > 0
    assert g.num_constraints == 2
    with pytest.warns(UserWarning, match=rf"\(lines? {n}\); dropped them"):
        g = read_graph(p, fix_information="skip")
    assert g.num_constraints == 1


def test_fix_information_bad_value() -> None:
    assert FIX_INFORMATION == ("nearest", "skip")
    with pytest.raises(ValueError, match="fix_information"):
        read_graph("whatever.g2o", fix_information="clip")


# =========================================================================== 2D information
def test_posegraph_accepts_3x3_information_for_2d_graphs() -> None:
    info3 = np.array([[[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]]])
    kw = dict(node_ids=[0, 1], rotations=np.tile(np.eye(3), (2, 1, 1)),
              translations=np.zeros((2, 3)), edge_nodes=[[0, 1]],
              edge_rotations=np.eye(3)[None], edge_translations=np.zeros((1, 3)))
    g = PoseGraph(edge_information=info3, is_2d=True, **kw)  # type: ignore[arg-type]
    np.testing.assert_array_equal(g.edge_information, lift_information_2d(info3))
    with pytest.raises(GraphError, match=r"3x3 .*only for 2D graphs \(is_2d=True\)"):
        PoseGraph(edge_information=info3, **kw)  # type: ignore[arg-type]


# =========================================================================== TUM output
def test_write_graph_tum(tmp_path: Path) -> None:
    g = read_graph(Path(__file__).parent / "data" / "tinyGrid3D.g2o")
    assert "tum" in WRITE_FORMATS
    path = tmp_path / "t.tum"
    with pytest.warns(UserWarning, match=r"t\.tum: the TUM format holds poses only: the "
                      rf"{g.num_edges} relative constraints are not written"):
        write_graph(g, path, "tum")
    stamps, rot, trans = read_tum(path)
    np.testing.assert_array_equal(stamps, g.node_ids.astype(float))
    np.testing.assert_allclose(rot, g.rotations, rtol=0, atol=FLOAT64_IDENTITY)
    np.testing.assert_array_equal(trans, g.translations)


# =========================================================================== stdin / stdout
def test_dash_reads_stdin_and_writes_stdout(monkeypatch: pytest.MonkeyPatch,
                                            capsysbinary: pytest.CaptureFixture[bytes]) -> None:
    import io

    text = "\n".join([*V2, E2]) + "\n"
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(text.encode())))
    g = read_graph("-")
    assert g.num_edges == 1 and g.source_format == "g2o"
    write_graph(g, "-", "g2o")
    out = capsysbinary.readouterr().out.decode()
    assert out.splitlines()[-1].startswith("EDGE_SE2 0 1 1.0 0.0 0.0 1.0")


def test_stdin_errors_name_stdin(monkeypatch: pytest.MonkeyPatch) -> None:
    import io

    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(b"VERTEX_SE2 0 0 0\n")))
    with pytest.raises(FormatError, match=r"<stdin>:1: VERTEX_SE2 needs 4 numbers"):
        read_graph("-")


# =========================================================================== symlinks and FIFOs
def test_write_through_a_symlink_keeps_the_link(tmp_path: Path) -> None:
    g = read_graph(write(tmp_path, "a.g2o", *V2, E2))
    target = tmp_path / "target.g2o"
    target.write_text("old\n")
    link = tmp_path / "link.g2o"
    link.symlink_to(target)
    write_graph(g, link)
    assert link.is_symlink()
    assert target.read_text().startswith("VERTEX_SE2 0")
    dangling = tmp_path / "dangling.g2o"
    dangling.symlink_to(tmp_path / "new.g2o")
    write_graph(g, dangling)
    assert dangling.is_symlink() and (tmp_path / "new.g2o").read_text().startswith("VERTEX")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_write_to_a_fifo_streams_into_it(tmp_path: Path) -> None:
    g = read_graph(write(tmp_path, "a.g2o", *V2, E2))
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    write_graph(g, fifo, "g2o")
    reader.join(timeout=10)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still a FIFO, not replaced by a file
    assert got and got[0].decode().startswith("VERTEX_SE2 0")


def test_write_to_a_directory_is_a_format_error(tmp_path: Path) -> None:
    g = read_graph(write(tmp_path, "a.g2o", *V2, E2))
    with pytest.raises(FormatError, match=re.escape(str(tmp_path)) + r": cannot write .*a "
                       r"directory"):
        write_graph(g, tmp_path)
