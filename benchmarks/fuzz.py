"""Mutation fuzzing of the readers and writers.

``python -m benchmarks.fuzz N [--seed S] [--save DIR]`` (or ``python -m benchmarks --only fuzz``,
100 000 inputs; 2 000 with ``--quick``) mutates small valid files of every format (g2o 2D/3D with
``FIX`` and position priors, TORO 2D/3D with ``EQUIV`` and bare ``EDGE3``, iSAM 2D/3D, TUM) and
feeds each result to the readers (``read_graph`` with every ``fix_information`` policy,
``read_tum``).  Every graph that reads is converted to every format (g2o, TORO, iSAM, TUM) in
memory, read back and compared with the original (``convert``'s round trip).

The target: no exception other than the package's own (``HybridPGOError`` subclasses), no
round-trip mismatch and no NumPy floating-point warning (over/underflow, invalid) in any input.
Failures are counted by kind; ``--save DIR`` keeps each failing input for reproduction.

Grammar-aware mode: ``python -m benchmarks.fuzz N --grammar`` (or ``python -m benchmarks --only
fuzz_cli``, 100 000 inputs; 1 000 with ``--quick``) builds files with the tags and field counts
of every format (g2o 2D/3D with ``FIX`` lines and position priors, TORO 2D/3D with ``EQUIV``
and bare ``EDGE3``, iSAM 2D/3D, TUM) filled with hostile values: the ends of float64,
subnormals, signed zeros, NaN and infinity spellings, numbers that overflow, long digit strings,
duplicate, missing, negative and out-of-range ids, several ``FIX`` lines; and file-level
oddities: unicode comments, long lines, blank lines, tabs, CRLF or CR line ends, a byte-order
mark, repeated or shuffled lines, a line of another format.  Each input goes through the readers
(as above) and through the command line in-process (``hybridpgo.cli.main``): ``info`` (text or
JSON), ``info --residuals``, ``convert``, ``optimize`` (every solver, few iterations),
``evaluate`` (against itself or another input) and, one input in 20, ``plot`` (Agg).  Inputs
run in forked worker processes, one at a time, so that a crash (a worker killed by a signal)
and a hang (an input over 60 s: its worker is killed) are counted and the run goes on.  Failures:
tracebacks (exit 1, or an exception out of ``main``), crashes, hangs, NumPy warnings, temporary
files left beside the outputs, inputs whose bytes or inode changed, outputs created or replaced
by a command that failed (exit 2), exit codes other than 0 and 2, and the reader failures above.
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib
import sys
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridpgo.errors import HybridPGOError
from hybridpgo.geometry import so3
from hybridpgo.graph import PoseGraph
from hybridpgo.io import (
    FIX_INFORMATION,
    FORMATS,
    WRITE_FORMATS,
    graph_lines,
    read_back,
    read_graph_source,
)
from hybridpgo.io._lines import source_from_text
from hybridpgo.io.tum import read_tum_source

#: Round-trip tolerance, relative to each item's largest entry (>= 1): repr writing is exact;
#: Euler angles, quaternions and the iSAM Cholesky factor cost a few ulps.
ROUND_TRIP_RTOL = 1e-9

#: Tokens that break parsers: special floats, overflow, odd spellings, non-ASCII digits.
SPECIAL_TOKENS = (
    "0", "-0", "1", "-1", "nan", "NaN", "inf", "-inf", "Infinity", "1e308", "-1e308", "1.8e308",
    "1e-320", "4.9e-324", "1e200", "1e154", "1e150", "4e150", "1e-200", "1e75", "9" * 400,
    "9223372036854775807", "9223372036854775808", "-9223372036854775809", "1" * 30, "+1", ".5",
    "5.", "1e", "e5", "0x10", "1_0", "\u0661", "\uff13", "\u0967.5", "1,5", "", "#", "--1",
    "1e+400", "3.14159", "-2.5e-3", "1e16", "2e9",
)
#: Characters inserted inside lines.
ODD_CHARS = ("\f", "\v", "\x1c", "\x85", "\u2028", "\u2029", "\r", "\x00", "\t", "\ufeff",
             "\ud800", " ", "#")

Failure = tuple[str, str]  # (kind, detail)


# =========================================================================== seed corpus
def _rot(rng: np.random.Generator, planar: bool) -> np.ndarray:
    if planar:
        a = rng.uniform(-np.pi, np.pi)
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _graph(rng: np.random.Generator, is_2d: bool, n: int, gps: int = 0,
           fixed: int = 0) -> PoseGraph:
    ids = np.sort(rng.choice(np.arange(0, 3 * n), n, replace=False)).astype(np.int64)
    edges = [(i, i + 1) for i in range(n - 1)] + [(0, n - 1), (1, n - 2)]
    rot = np.stack([_rot(rng, is_2d) for _ in range(n)])
    trans = rng.normal(scale=5.0, size=(n, 3))
    m = len(edges)
    erot = np.stack([_rot(rng, is_2d) for _ in range(m)])
    etrans = rng.normal(size=(m, 3))
    if is_2d:
        trans[:, 2] = 0.0
        etrans[:, 2] = 0.0
        a = rng.normal(size=(m, 3, 3))
        info = a @ np.swapaxes(a, 1, 2) + np.eye(3)
    else:
        a = rng.normal(size=(m, 6, 6))
        info = a @ np.swapaxes(a, 1, 2) + np.eye(6)
    g = PoseGraph(node_ids=ids, rotations=rot, translations=trans, edge_nodes=np.array(edges),
                  edge_rotations=erot, edge_translations=etrans, edge_information=info,
                  fixed_nodes=np.arange(fixed, dtype=np.int32), is_2d=is_2d)
    if gps:
        a = rng.normal(size=(gps, 3, 3))
        g = g.add_gps(ids[:gps], rng.normal(size=(gps, 3)), a @ np.swapaxes(a, 1, 2) + np.eye(3))
    return g


def seed_corpus(seed: int = 0) -> list[tuple[str, str]]:
    """(name, text) of small valid files of every format and line type."""
    rng = np.random.default_rng(seed)
    out: list[tuple[str, str]] = []

    def add(name: str, g: PoseGraph, fmt: str) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # TUM: "poses only"
            out.append((name, "\n".join(graph_lines(g, fmt, name)) + "\n"))

    add("g2o_2d", _graph(rng, True, 6, fixed=1), "g2o")
    add("g2o_3d", _graph(rng, False, 6, gps=2, fixed=1), "g2o")
    add("toro_2d", _graph(rng, True, 6), "toro")
    add("toro_3d", _graph(rng, False, 5), "toro")
    add("isam_2d", _graph(rng, True, 6), "isam")
    add("isam_3d", _graph(rng, False, 5), "isam")
    add("tum", _graph(rng, False, 5), "tum")
    out.append(("toro_equiv", "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nVERTEX2 2 2 0 0\n"
                "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 1 2 1 0 0 1 0 1 1 0 0\n"
                "EDGE2 2 0 -2 0 0 1 0 1 1 0 0\nEQUIV 0 2\n"))
    out.append(("toro_bare_edge3", "VERTEX3 0 0 0 0 0 0 0\nVERTEX3 1 1 0 0 0 0 0\n"
                "EDGE3 0 1 1 0 0 0 0 0\n# comment\n\nEDGE3 1 0 -1 0 0 0.1 0 0\n"))
    out.append(("isam_odometry", "ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\n"
                "ODOMETRY 1 2 1 0 0.1 2 0.5 0 2 0 3\nEDGE2 2 0 -2 0 0 1 0 0 1 0 1\n"))
    out.append(("g2o_edges_only", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
                "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\nFIX 0\n"))
    return out


# =========================================================================== mutations
def _tokens(line: str) -> list[str]:
    return line.split(" ")


def mutate(text: str, rng: np.random.Generator, corpus: list[tuple[str, str]]) -> str:
    """1-4 random edits of ``text``: tokens, lines, characters, tags, ids, bytes."""
    lines = text.split("\n")
    tags = sorted({ln.split(" ")[0] for _, t in corpus for ln in t.split("\n") if ln})
    for _ in range(int(rng.integers(1, 5))):
        op = int(rng.integers(0, 14))
        k = int(rng.integers(0, max(len(lines), 1)))
        if not lines:
            lines = [""]
            k = 0
        tok = _tokens(lines[k])
        j = int(rng.integers(0, max(len(tok), 1)))
        if op <= 2:  # a special token (most common: numbers are where parsers break)
            if tok:
                tok[j] = SPECIAL_TOKENS[int(rng.integers(len(SPECIAL_TOKENS)))]
        elif op == 3:  # scale a number
            if tok:
                try:
                    tok[j] = repr(float(tok[j]) * 10.0 ** float(rng.integers(-320, 320)))
                except (ValueError, OverflowError):
                    pass
        elif op == 4 and tok:  # delete a token
            del tok[j]
        elif op == 5 and tok:  # duplicate a token
            tok.insert(j, tok[j])
        elif op == 6:  # another tag
            if tok:
                tok[0] = tags[int(rng.integers(len(tags)))]
        elif op == 7:  # an id: existing, new, negative, huge
            if len(tok) > 1:
                tok[1 + int(rng.integers(0, min(2, len(tok) - 1)))] = str(
                    int(rng.choice([0, 1, 2, 3, 7, -1, 2**31, 2**63 - 1, -(2**63)])))
        elif op == 8:  # delete a line
            del lines[k]
            continue
        elif op == 9:  # duplicate or move a line
            lines.insert(int(rng.integers(0, len(lines) + 1)), lines[k])
            continue
        elif op == 10:  # a line from another file (mixes formats and dimensions)
            other = corpus[int(rng.integers(len(corpus)))][1].split("\n")
            lines.insert(k, other[int(rng.integers(len(other)))])
            continue
        elif op == 11:  # an odd character inside the line
            c = ODD_CHARS[int(rng.integers(len(ODD_CHARS)))]
            pos = int(rng.integers(0, len(lines[k]) + 1))
            lines[k] = lines[k][:pos] + c + lines[k][pos:]
            continue
        elif op == 12:  # truncate the file
            cut = int(rng.integers(0, len("\n".join(lines)) + 1))
            lines = "\n".join(lines)[:cut].split("\n")
            continue
        else:  # swap two tokens
            if len(tok) > 2:
                a, b = rng.integers(0, len(tok), 2)
                tok[a], tok[b] = tok[b], tok[a]
        lines[k] = " ".join(tok)
    return "\n".join(lines)


def as_read(text: str, rng: np.random.Generator) -> str:
    """``text`` as the readers see it from disk: UTF-8 bytes (one in ten with a random byte
    replaced, e.g. invalid UTF-8) decoded like ``load_source`` does."""
    data = bytearray(text.encode("utf-8", errors="surrogatepass"))
    if data and rng.random() < 0.1:
        data[int(rng.integers(len(data)))] = int(rng.integers(256))
    return bytes(data).decode("utf-8", errors="replace")


# =========================================================================== checking
class RoundTripMismatch(AssertionError):
    """A graph written in some format read back different."""


def _rel(x: np.ndarray, y: np.ndarray) -> float:
    if x.shape != y.shape:
        return float("inf")
    if x.size == 0:
        return 0.0
    k = x.shape[0]
    scale = np.maximum(np.abs(x).reshape(k, -1).max(axis=1), 1.0)
    return float((np.abs(x - y).reshape(k, -1).max(axis=1) / scale).max())


def _compare(a: PoseGraph, b: PoseGraph, fmt: str) -> None:
    def need(ok: bool, what: str) -> None:
        if not ok:
            raise RoundTripMismatch(f"{fmt}: {what} differ after write -> read")

    used = np.zeros(a.num_nodes, bool)
    used[a.edge_nodes.reshape(-1)] = True
    if fmt != "isam" or used.all():  # iSAM stores only the poses its edges use
        need(np.array_equal(a.node_ids, b.node_ids), "node ids")
        need(np.array_equal(a.edge_nodes, b.edge_nodes), "edge endpoints")
    else:
        need(np.array_equal(a.node_ids[a.edge_nodes], b.node_ids[b.edge_nodes]), "edge ids")
    need(a.is_2d == b.is_2d, "dimensions")
    need(_rel(a.edge_rotations, b.edge_rotations) <= ROUND_TRIP_RTOL, "edge rotations")
    need(_rel(a.edge_translations, b.edge_translations) <= ROUND_TRIP_RTOL, "edge translations")
    need(_rel(a.edge_information, b.edge_information) <= ROUND_TRIP_RTOL, "edge information")
    if fmt == "g2o":
        need(np.array_equal(a.gps_nodes, b.gps_nodes), "GPS nodes")
        need(np.array_equal(a.fixed_nodes, b.fixed_nodes), "fixed nodes")
        need(_rel(a.gps_positions, b.gps_positions) <= ROUND_TRIP_RTOL, "GPS positions")
        need(_rel(a.gps_information, b.gps_information) <= ROUND_TRIP_RTOL, "GPS information")
    if a.has_estimates and b.has_estimates:
        need(_rel(a.rotations, b.rotations) <= ROUND_TRIP_RTOL, "pose rotations")
        need(_rel(a.translations, b.translations) <= ROUND_TRIP_RTOL, "pose translations")


def _compare_tum(a: PoseGraph, lines: list[str], name: str) -> None:
    stamps, rot, trans = read_tum_source(source_from_text("\n".join(lines) + "\n", name))
    if not (np.array_equal(stamps, a.node_ids.astype(np.float64))
            and _rel(a.rotations, rot) <= ROUND_TRIP_RTOL
            and _rel(a.translations, trans) <= ROUND_TRIP_RTOL):
        raise RoundTripMismatch("tum: poses differ after write -> read")


@dataclass
class Stats:
    inputs: int = 0
    graphs_read: int = 0
    tum_read: int = 0
    rejected: int = 0
    writes: int = 0
    writes_refused: int = 0
    round_trips: int = 0
    failures: Counter[str] = field(default_factory=Counter)
    examples: dict[str, tuple[str, str]] = field(default_factory=dict)


def check_input(text: str, policy: str | None, stats: Stats | None = None,
                fmt: str | None = None) -> list[Failure]:
    """Read ``text`` as a graph (format ``fmt``, None: detected; information ``policy``) and as
    TUM; round-trip every graph that reads.

    Returns the failures: exceptions other than ``HybridPGOError`` (kind = the exception type),
    round-trip mismatches, and NumPy floating-point warnings (turned into errors here).
    """
    st = stats if stats is not None else Stats()
    failures: list[Failure] = []
    name = "fuzz.txt"

    def guard(step: str, fn: Callable[[], Any]) -> tuple[bool, Any]:
        try:
            with warnings.catch_warnings(), np.errstate(all="raise", under="ignore"):
                warnings.simplefilter("ignore", UserWarning)  # the readers' own notes
                warnings.simplefilter("error", RuntimeWarning)
                return True, fn()
        except HybridPGOError:
            return False, None
        except Exception as exc:
            kind = f"{step}: {type(exc).__name__}"
            failures.append((kind, "".join(traceback.format_exception_only(exc)).strip()))
            return False, None

    def read() -> PoseGraph:
        src = source_from_text(text, name)
        src.fix_information = policy
        return read_graph_source(src, fmt, check_connected=False)

    ok, graph = guard("read", read)
    if ok:
        st.graphs_read += 1
    else:
        st.rejected += 1
    ok_tum, _ = guard("read_tum", lambda: read_tum_source(source_from_text(text, name)))
    st.tum_read += int(ok_tum)
    if graph is None:
        return failures
    for out in WRITE_FORMATS:
        ok, lines = guard(f"write {out}", lambda f=out: graph_lines(graph, f, name))
        if not ok:
            st.writes_refused += 1
            continue
        st.writes += 1

        def back(f: str = out, ls: list[str] = lines) -> None:
            if f == "tum":
                _compare_tum(graph, ls, name)
            else:
                _compare(graph, read_back(ls, f, name), f)

        try:
            with warnings.catch_warnings(), np.errstate(all="raise", under="ignore"):
                warnings.simplefilter("ignore", UserWarning)
                warnings.simplefilter("error", RuntimeWarning)
                back()
            st.round_trips += 1
        except RoundTripMismatch as exc:
            failures.append((f"round trip {out}: mismatch", str(exc)))
        except Exception as exc:
            failures.append((f"read back {out}: {type(exc).__name__}",
                             "".join(traceback.format_exception_only(exc)).strip()))
    return failures


def fuzz(n: int, seed: int = 0, save: pathlib.Path | None = None,
         progress: bool = False) -> tuple[Stats, float]:
    """Run ``n`` mutated inputs; return the statistics and the wall time in seconds."""
    rng = np.random.default_rng(seed)
    corpus = seed_corpus(seed)
    policies: list[str | None] = [None, *FIX_INFORMATION]
    formats: list[str | None] = [None, None, None, *FORMATS]
    stats = Stats()
    t0 = time.perf_counter()
    for i in range(n):
        base = corpus[int(rng.integers(len(corpus)))][1]
        text = as_read(mutate(base, rng, corpus), rng)
        policy = policies[int(rng.integers(len(policies)))]
        fmt = formats[int(rng.integers(len(formats)))]
        stats.inputs += 1
        for kind, detail in check_input(text, policy, stats, fmt):
            stats.failures[kind] += 1
            if kind not in stats.examples:
                stats.examples[kind] = (detail, text)
                if save is not None:
                    save.mkdir(parents=True, exist_ok=True)
                    safe = "".join(c if c.isalnum() else "_" for c in kind)
                    (save / f"{safe}.txt").write_text(text, encoding="utf-8",
                                                      errors="surrogatepass")
        if progress and (i + 1) % 5000 == 0:
            print(f"  {i + 1} inputs, {sum(stats.failures.values())} failures, "
                  f"{time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return stats, time.perf_counter() - t0


# =========================================================================== grammar-aware mode
#: Numbers with a valid spelling that parsers, solvers, plots and writers choke on: the ends of
#: float64, subnormals, signed zero, NaN and infinity spellings, overflow to infinity, long
#: digit strings.
HOSTILE_NUMBERS = (
    "1e308", "-1e308", "1.7976931348623157e308", "1e200", "-1e200", "1e154", "1e150", "1e75",
    "1e16", "1e-16", "1e-300", "1e-320", "5e-324", "-0", "0", "-0.0", "nan", "NaN", "inf",
    "-inf", "1e400", "-1e400", "9" * 400, "0." + "0" * 400 + "1", "+1", ".5", "5.", "1E5",
    "2e9", "1" * 30, "-3.141592653589793", "6.283185307179586", "1e-9",
)
#: Ids with a valid spelling that break id handling: negative, beyond int64, leading zeros.
HOSTILE_IDS = ("-1", "9223372036854775807", "-9223372036854775808", "9223372036854775808",
               "2147483648", "00", "007", "+3", "1" * 25, "0", "1")
#: Lines of text that are not data: comments with unicode, blank and whitespace-only lines.
ODD_LINES = ("# ünïcödé ✓ 日本語", "#", "", "   ", "\t", "# " + "x" * 5000, "# \u2028 \u0085")


@dataclass(frozen=True)
class Layout:
    """One file kind of the grammar: its tags, dimension and file extension."""

    name: str
    ext: str
    is_2d: bool
    vertex: str | None
    edges: tuple[str, ...]


LAYOUTS = (
    Layout("g2o_2d", ".g2o", True, "VERTEX_SE2", ("EDGE_SE2",)),
    Layout("g2o_3d", ".g2o", False, "VERTEX_SE3:QUAT", ("EDGE_SE3:QUAT",)),
    Layout("toro_2d", ".graph", True, "VERTEX2", ("EDGE2",)),
    Layout("toro_3d", ".graph", False, "VERTEX3", ("EDGE3",)),
    Layout("isam_2d", ".txt", True, None, ("ODOMETRY", "EDGE2")),
    Layout("isam_3d", ".txt", False, None, ("EDGE3",)),
    Layout("tum", ".tum", False, None, ()),
)


def _num(rng: np.random.Generator, value: float, p_hostile: float) -> str:
    if rng.random() < p_hostile:
        return HOSTILE_NUMBERS[int(rng.integers(len(HOSTILE_NUMBERS)))]
    return repr(float(value)) if rng.random() < 0.5 else f"{value:.6g}"


def _id(rng: np.random.Generator, value: int, n: int, p_hostile: float) -> str:
    if rng.random() < p_hostile:
        if rng.random() < 0.5:  # another pose's id (duplicates, self-loops) or a missing one
            return str(int(rng.integers(-1, n + 3)))
        return HOSTILE_IDS[int(rng.integers(len(HOSTILE_IDS)))]
    return str(value)


def _info_values(rng: np.random.Generator, d: int, layout: str) -> list[float]:
    """Upper-triangular entries (row by row) of an SPD information matrix (TORO 2D: its own
    order xx xy yy tt xt yt; iSAM: the square-root matrix's entries)."""
    a = rng.normal(size=(d, d)) * (0.3 if rng.random() < 0.5 else 0.0)
    m = a @ a.T + np.eye(d) * 10.0 ** rng.uniform(-2, 3)
    if layout == "toro_2d":
        return [m[0, 0], m[0, 1], m[1, 1], m[2, 2], m[0, 2], m[1, 2]]
    if layout.startswith("isam"):
        m = np.linalg.cholesky(m).T
    iu = np.triu_indices(d)
    return [float(v) for v in m[iu]]


def grammar_input(rng: np.random.Generator) -> tuple[Layout, str]:
    """A file of one format (sometimes with lines of another) whose lines have the tags and
    field counts of the grammar, with hostile values: see the module docstring."""
    layout = LAYOUTS[int(rng.integers(len(LAYOUTS)))]
    p_num = float(rng.choice([0.0, 0.01, 0.05, 0.2]))
    p_id = float(rng.choice([0.0, 0.0, 0.02, 0.1]))
    n = int(rng.integers(1, 9))
    ids = np.sort(rng.choice(np.arange(3 * n + 1), n, replace=False)) if rng.random() < 0.3 \
        else np.arange(n)
    g = _graph(rng, layout.is_2d, max(n, 4), gps=0)  # only its poses are used
    lines: list[str] = []
    tok = lines.append
    if layout.name == "tum":
        q = so3.matrix_to_quat_xyzw(g.rotations)
        for k in range(n):
            vals = [float(ids[k]), *g.translations[k], *q[k]]
            tok(" ".join(_num(rng, v, p_num) for v in vals))
        return layout, _file_text(rng, lines)
    if layout.vertex is not None:
        for k in range(n):
            t = g.translations[k]
            r = g.rotations[k]
            if layout.name == "g2o_2d" or layout.name == "toro_2d":
                vals = [t[0], t[1], math.atan2(r[1, 0], r[0, 0])]
            elif layout.name == "g2o_3d":
                vals = [*t, *so3.matrix_to_quat_xyzw(r[None])[0]]
            else:
                vals = [*t, *so3.matrix_to_euler_rpy(r[None])[0]]
            tok(f"{layout.vertex} {_id(rng, int(ids[k]), n, p_id)} "
                + " ".join(_num(rng, v, p_num) for v in vals))
    pairs = [(k, k + 1) for k in range(n - 1)]
    pairs += [tuple(int(v) for v in rng.choice(n, 2, replace=False))
              for _ in range(int(rng.integers(0, 4))) if n > 1]
    for a, b in pairs:
        tag = layout.edges[int(rng.integers(len(layout.edges)))]
        rel_r = g.rotations[a].T @ g.rotations[b]
        rel_t = g.rotations[a].T @ (g.translations[b] - g.translations[a])
        rel_t = rel_t + rng.normal(scale=0.1, size=3)
        if layout.is_2d:
            vals = [rel_t[0], rel_t[1], math.atan2(rel_r[1, 0], rel_r[0, 0])]
            info = _info_values(rng, 3, layout.name)
        elif layout.name == "g2o_3d":
            vals = [*rel_t, *so3.matrix_to_quat_xyzw(rel_r[None])[0]]
            info = _info_values(rng, 6, layout.name)
        else:
            vals = [*rel_t, *so3.matrix_to_euler_rpy(rel_r[None])[0]]
            info = [] if layout.name == "toro_3d" and rng.random() < 0.2 else \
                _info_values(rng, 6, layout.name)
        tok(f"{tag} {_id(rng, int(ids[a]), n, p_id)} {_id(rng, int(ids[b]), n, p_id)} "
            + " ".join(_num(rng, v, p_num) for v in [*vals, *info]))
    if layout.name.startswith("g2o"):
        for _ in range(int(rng.choice([0, 0, 1, 1, 2, 3]))):  # g2o allows several FIX lines
            k = int(rng.integers(n))
            tok(f"FIX {_id(rng, int(ids[k]), n, p_id)}")
        if layout.name == "g2o_3d" and rng.random() < 0.2:
            tok("PARAMS_SE3OFFSET 0 " + " ".join(_num(rng, v, p_num)
                                                 for v in (0, 0, 0, 0, 0, 0, 1)))
            k = int(rng.integers(n))
            tok(f"EDGE_SE3_XYZ_PRIOR {_id(rng, int(ids[k]), n, p_id)} 0 "
                + " ".join(_num(rng, v, p_num)
                           for v in [*g.translations[k], *_info_values(rng, 3, "")]))
    if layout.name == "toro_2d" and n > 2 and rng.random() < 0.1:
        tok(f"EQUIV {_id(rng, int(ids[0]), n, p_id)} {_id(rng, int(ids[-1]), n, p_id)}")
    return layout, _file_text(rng, lines)


_CORPUS: list[tuple[str, str]] = []


def _corpus() -> list[tuple[str, str]]:
    if not _CORPUS:
        _CORPUS.extend(seed_corpus(0))
    return _CORPUS


def _file_text(rng: np.random.Generator, lines: list[str]) -> str:
    """Join ``lines`` with file-level oddities: odd lines, a line of another format, repeated
    or reordered lines, tabs, CRLF or CR line ends, a byte-order mark, no final newline."""
    lines = list(lines)
    for _ in range(int(rng.integers(0, 3))):
        odd = ODD_LINES[int(rng.integers(len(ODD_LINES)))]
        lines.insert(int(rng.integers(len(lines) + 1)), odd)
    if lines and rng.random() < 0.05:
        lines.insert(int(rng.integers(len(lines) + 1)), lines[int(rng.integers(len(lines)))])
    if rng.random() < 0.03:
        corpus = _corpus()
        other = corpus[int(rng.integers(len(corpus)))][1].splitlines()
        lines.insert(int(rng.integers(len(lines) + 1)), other[int(rng.integers(len(other)))])
    if rng.random() < 0.05:
        rng.shuffle(lines)
    if rng.random() < 0.05:
        lines = [ln.replace(" ", "\t") for ln in lines]
    end = str(rng.choice(["\n"] * 17 + ["\r\n", "\r\n", "\r"]))
    text = end.join(lines) + ("" if rng.random() < 0.1 else end)
    if rng.random() < 0.05:
        text = "\ufeff" + text
    return text


#: Solver options of ``optimize`` in the grammar mode: few iterations, every solver.
_SOLVER_ARGS = (["--sweeps", "3", "--max-iterations", "5"],
                ["--solver", "exact", "--max-iterations", "5"],
                ["--solver", "hybrid", "--sweeps", "3"],
                ["--solver", "toro", "--sweeps", "3"])
_OTHER_EXT = {".g2o": ".graph", ".graph": ".g2o", ".txt": ".g2o", ".tum": ".g2o"}


def cli_commands(layout: Layout, path: pathlib.Path, gt: pathlib.Path, work: pathlib.Path,
                 rng: np.random.Generator, plot_every: int) -> list[list[str]]:
    """The command lines one grammar input goes through."""
    fix = (["--fix-information", str(rng.choice(["nearest", "skip"]))]
           if rng.random() < 0.2 else [])
    solver = _SOLVER_ARGS[int(rng.choice([0, 0, 0, 1, 2, 3]))]
    cmds = [["info", str(path), *fix, *(["--json"] if rng.random() < 0.5 else [])],
            ["info", str(path), "--residuals", str(work / "r.csv"), *fix],
            ["convert", str(path), str(work / ("out" + _OTHER_EXT[layout.ext])), *fix],
            ["optimize", str(path), "-o", str(work / "o.g2o"), "-q", *solver, *fix],
            ["evaluate", str(path), "--ground-truth", str(gt), *fix]]
    if plot_every and rng.integers(plot_every) == 0:
        cmds.append(["plot", str(path), "-o", str(work / "p.png"), "--dpi", "20", *fix])
    return cmds


def _files(work: pathlib.Path) -> dict[str, tuple[int, int, int]]:
    """Each file of ``work``: (inode, modification time in ns, size)."""
    out = {}
    for p in work.iterdir():
        st = p.stat()
        out[p.name] = (st.st_ino, st.st_mtime_ns, st.st_size)
    return out


def run_cli_check(argv: list[str], work: pathlib.Path,
                  inputs: tuple[pathlib.Path, ...] = ()) -> tuple[int, list[Failure], int]:
    """``hybridpgo.cli.main(argv)`` in this process, output captured.  Returns the exit code,
    the failures (a traceback: exit 1 or an exception out of ``main``; an exit code other than
    0/2; a NumPy RuntimeWarning; a temporary file left in ``work``; an input in ``inputs``
    whose bytes or inode changed; a file of ``work`` created or replaced by a command that
    failed with exit 2) and the count of the package's own warnings (UserWarning: notes such as
    skipped lines)."""
    import contextlib
    import io

    from hybridpgo.cli import main as cli_main

    failures: list[Failure] = []
    before = _files(work)
    content = {p: p.read_bytes() for p in inputs}
    err = io.StringIO()
    cmd = argv[0] + (" --residuals" if "--residuals" in argv else "")
    with warnings.catch_warnings(record=True) as rec, contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(err):
        warnings.simplefilter("always")
        try:
            code = cli_main(argv)
        except BaseException as exc:  # anything out of main is a failure
            code = -1
            failures.append((f"{cmd}: escaped {type(exc).__name__}", str(exc)[:300]))
    text = err.getvalue()
    if code == 1 or "Traceback" in text:
        last = [ln for ln in text.splitlines() if ln and not ln.startswith(("hybridpgo:", " "))]
        kind = last[-1].split(":")[0] if last else "?"
        failures.append((f"{cmd}: traceback {kind}", "\n".join(text.splitlines()[-6:])))
    elif code not in (0, 2, -1):
        failures.append((f"{cmd}: exit {code}", text[-300:]))
    notes = 0
    for w in rec:
        if issubclass(w.category, UserWarning):
            notes += 1
        else:
            failures.append((f"{cmd}: {w.category.__name__} {str(w.message)[:50]}",
                             f"{w.filename}:{w.lineno}: {w.message}"))
    after = _files(work)
    for p, data in content.items():
        if after.get(p.name) != before.get(p.name) or p.read_bytes() != data:
            failures.append((f"{cmd}: input changed", p.name))
    if code == 2:
        written = sorted(k for k, v in after.items()
                         if not k.startswith(".") and before.get(k) != v)
        if written:
            failures.append((f"{cmd}: output written after an error", ", ".join(written)))
    left = [p.name for p in work.iterdir() if p.name.startswith(".")]
    if left:
        failures.append((f"{cmd}: temporary file left", ", ".join(left)))
        for name in left:
            (work / name).unlink()
    return code, failures, notes


def grammar_one(seed: int, index: int, work: pathlib.Path, plot_every: int) -> dict[str, Any]:
    """Input ``index`` of the run ``seed``: the readers (:func:`check_input`) and the command
    lines; JSON-friendly counts and failures."""
    rng = np.random.default_rng([seed, index])
    layout, text = grammar_input(rng)
    gt_layout, gt_text = grammar_input(rng) if rng.random() < 0.5 else (layout, text)
    policies: list[str | None] = [None, *FIX_INFORMATION]
    st = Stats()
    failures = [("read " + k, d) for k, d in
                check_input(text, policies[int(rng.integers(3))], st)]
    for f in work.iterdir():
        f.unlink()
    path = work / ("in" + layout.ext)
    path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
    gt = path
    if gt_text is not text:
        gt = work / ("gt" + gt_layout.ext)
        if gt == path:
            gt = work / ("gt2" + gt_layout.ext)
        gt.write_bytes(gt_text.encode("utf-8", errors="surrogatepass"))
    codes: dict[str, int] = {}
    notes = 0
    for argv in cli_commands(layout, path, gt, work, rng, plot_every):
        code, fails, k = run_cli_check(argv, work, (path, gt))
        key = argv[0] + (" --residuals" if "--residuals" in argv else "")
        codes[key] = code
        failures += fails
        notes += k
    return {"layout": layout.name, "graph_read": st.graphs_read, "codes": codes,
            "notes": notes, "failures": failures,
            "text": text if failures else ""}


@dataclass
class GrammarStats:
    inputs: int = 0
    graphs_read: int = 0
    runs: int = 0
    exit_codes: Counter[str] = field(default_factory=Counter)
    layouts: Counter[str] = field(default_factory=Counter)
    notes: int = 0
    reader: int = 0
    tracebacks: int = 0
    warnings: int = 0
    left_files: int = 0
    changed_inputs: int = 0
    error_outputs: int = 0
    other: int = 0
    crashes: int = 0
    hangs: int = 0
    slowest_s: float = 0.0
    failures: Counter[str] = field(default_factory=Counter)
    examples: dict[str, tuple[str, str]] = field(default_factory=dict)

    @property
    def bad(self) -> int:
        return self.reader + self.tracebacks + self.warnings + self.left_files \
            + self.changed_inputs + self.error_outputs + self.other + self.crashes + self.hangs


def _warm_up(work: pathlib.Path) -> None:
    """Before the workers fork: compile (or load) every kernel and import matplotlib once, and
    build the argument parser once (``main`` builds it on every call: ~25 ms, six times an
    input; a parser is not changed by parsing)."""
    import functools

    from hybridpgo.cli import _parser
    from hybridpgo.cli import main as cli_main

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cli_main(["warmup", "-q"])
    _parser.build_parser = functools.cache(_parser.build_parser)  # type: ignore[method-assign]
    for k in range(40):
        grammar_one(2**32 - 1, k, work, plot_every=1)  # a seed no run uses


def fuzz_grammar(n: int, seed: int = 0, *, timeout_s: float = 60.0, chunk: int = 200,
                 plot_every: int = 20, save: pathlib.Path | None = None,
                 progress: bool = False) -> tuple[GrammarStats, float]:
    """Run ``n`` grammar inputs through the readers and the command line.

    Inputs run in forked worker processes, ``chunk`` at a time and one worker at a time; an
    input whose worker dies (a crash: killed by a signal, or an exit without a result) or
    that takes more than ``timeout_s`` (a hang: the worker is killed) is counted, and the
    next worker carries on with the input after it.
    """
    import json
    import select
    import signal
    import tempfile

    os.environ.setdefault("MPLBACKEND", "Agg")
    stats = GrammarStats()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="hybridpgo-fuzz-") as tmp:
        work = pathlib.Path(tmp)
        _warm_up(work)
        t0 = time.perf_counter()
        start = 0
        while start < n:
            stop = min(start + chunk, n)
            rfd, wfd = os.pipe()
            pid = os.fork()
            if pid == 0:  # the worker
                os.close(rfd)
                try:
                    with os.fdopen(wfd, "w", buffering=1) as out:
                        for k in range(start, stop):
                            out.write(json.dumps({"start": k}) + "\n")
                            res = grammar_one(seed, k, work, plot_every)
                            out.write(json.dumps({"done": k, **res}) + "\n")
                finally:
                    os._exit(0)
            os.close(wfd)
            current, began, buf, done_upto = -1, time.perf_counter(), b"", start
            while True:
                ready, _, _ = select.select([rfd], [], [], 1.0)
                if not ready:
                    if current >= 0 and time.perf_counter() - began > timeout_s:
                        os.kill(pid, signal.SIGKILL)
                        os.waitpid(pid, 0)
                        stats.hangs += 1
                        _note(stats, "hang", f"input {current} ran over {timeout_s:g} s",
                              _regenerate(seed, current), save)
                        stats.inputs += 1
                        done_upto = current + 1
                        current = -1
                        break
                    continue
                data = os.read(rfd, 1 << 20)
                if not data:  # the worker exited
                    _, status = os.waitpid(pid, 0)
                    if current >= 0:
                        stats.crashes += 1
                        how = (f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status)
                               else f"exit {os.WEXITSTATUS(status)}")
                        _note(stats, f"crash ({how})", f"input {current}",
                              _regenerate(seed, current), save)
                        stats.inputs += 1
                        done_upto = current + 1
                    break
                buf += data
                *lines, buf = buf.split(b"\n")
                for line in lines:
                    msg = json.loads(line)
                    if "start" in msg:
                        current, began = int(msg["start"]), time.perf_counter()
                        continue
                    stats.slowest_s = max(stats.slowest_s, time.perf_counter() - began)
                    _count(stats, msg, save)
                    done_upto = int(msg["done"]) + 1
                    current = -1
            os.close(rfd)
            start = done_upto
            if progress:
                print(f"  {start} inputs, {stats.bad} failures, "
                      f"{time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return stats, time.perf_counter() - t0


def _regenerate(seed: int, index: int) -> str:
    rng = np.random.default_rng([seed, index])
    return grammar_input(rng)[1]


def _note(stats: GrammarStats, kind: str, detail: str, text: str,
          save: pathlib.Path | None) -> None:
    stats.failures[kind] += 1
    if kind not in stats.examples:
        stats.examples[kind] = (detail, text)
        if save is not None:
            save.mkdir(parents=True, exist_ok=True)
            safe = "".join(c if c.isalnum() else "_" for c in kind)[:80]
            (save / f"{safe}.txt").write_text(text, encoding="utf-8", errors="surrogatepass")


def _count(stats: GrammarStats, msg: dict[str, Any], save: pathlib.Path | None) -> None:
    stats.inputs += 1
    stats.graphs_read += int(msg["graph_read"])
    stats.layouts[msg["layout"]] += 1
    stats.notes += int(msg["notes"])
    for cmd, code in msg["codes"].items():
        stats.runs += 1
        stats.exit_codes[f"{cmd}: exit {code}"] += 1
    for kind, detail in msg["failures"]:
        if kind.startswith("read "):
            stats.reader += 1
        elif "traceback" in kind or "escaped" in kind:
            stats.tracebacks += 1
        elif "Warning" in kind:
            stats.warnings += 1
        elif "temporary file" in kind:
            stats.left_files += 1
        elif "input changed" in kind:
            stats.changed_inputs += 1
        elif "after an error" in kind:
            stats.error_outputs += 1
        else:
            stats.other += 1
        _note(stats, kind, detail, msg["text"], save)


def grammar_summary(stats: GrammarStats, seconds: float) -> str:
    """A few lines: counts, then each failure kind with an example."""
    out = [f"{stats.inputs} inputs in {seconds:.1f} s "
           f"({1e3 * seconds / max(stats.inputs, 1):.0f} ms each, slowest "
           f"{stats.slowest_s:.1f} s): "
           f"{stats.graphs_read} read as graphs; {stats.runs} command runs; reader failures "
           f"{stats.reader}, tracebacks {stats.tracebacks}, warnings {stats.warnings}, "
           f"temporary files left {stats.left_files}, inputs changed {stats.changed_inputs}, "
           f"outputs after an error {stats.error_outputs}, other {stats.other}, crashes "
           f"{stats.crashes}, hangs {stats.hangs}"]
    for kind, count in stats.failures.most_common():
        detail, text = stats.examples[kind]
        out.append(f"  {count:6d}  {kind}: {detail[:400]}")
        out.append("          input: " + repr(text[:300]))
    return "\n".join(out)


# =========================================================================== benchmark entry
def run(ctx: Any) -> tuple[list[Any], list[str]]:
    """The ``fuzz`` workload: 100 000 inputs (2 000 with ``--quick``)."""
    from .metrics import Metric, info, markdown_table, timing

    n = 2_000 if ctx.quick else 100_000
    stats, seconds = fuzz(n, seed=0, progress=True)
    bad = sum(stats.failures.values())
    metrics = [
        Metric("fuzz.failures", float(bad), "inputs", "lower", abs_tol=0.0,
               note=f"exceptions other than HybridPGOError or round-trip mismatches in {n}"),
        info("fuzz.inputs", n),
        info("fuzz.graphs_read", stats.graphs_read),
        info("fuzz.round_trips", stats.round_trips),
        timing("fuzz.seconds", seconds),
        info("fuzz.us_per_input", 1e6 * seconds / max(n, 1), "us"),
    ]
    rows: list[list[Any]] = [
        ["inputs", n], ["read as a graph", stats.graphs_read],
        ["read as TUM", stats.tum_read], ["rejected (HybridPGOError)", stats.rejected],
        ["writes (all formats)", stats.writes], ["writes refused (HybridPGOError)",
                                                 stats.writes_refused],
        ["round trips equal", stats.round_trips], ["failures", bad],
        ["time (s)", seconds],
    ]
    rows += [[f"failure: {k}", v] for k, v in sorted(stats.failures.items())]
    table = markdown_table(f"Mutation fuzzing of the readers and the convert round trip "
                           f"({n} inputs, seed 0)", ["", "count"], rows)
    return metrics, [table]


def run_grammar(ctx: Any) -> tuple[list[Any], list[str]]:
    """The ``fuzz_cli`` workload: 100 000 grammar inputs through the readers and the command
    line (1 000 with ``--quick``), one worker process at a time, 60 s per input."""
    from .metrics import Metric, info, markdown_table, timing

    n = 1_000 if ctx.quick else 100_000
    load_start = os.getloadavg()
    stats, seconds = fuzz_grammar(n, seed=0, progress=True)
    load_end = os.getloadavg()
    metrics = [
        Metric("fuzz_cli.failures", float(stats.bad), "inputs", "lower", abs_tol=0.0,
               note=f"tracebacks, crashes, hangs, warnings, temporary files left in {n}"),
        info("fuzz_cli.inputs", stats.inputs),
        info("fuzz_cli.command_runs", stats.runs),
        info("fuzz_cli.tracebacks", stats.tracebacks),
        info("fuzz_cli.crashes", stats.crashes),
        info("fuzz_cli.hangs", stats.hangs),
        info("fuzz_cli.warnings", stats.warnings),
        info("fuzz_cli.changed_inputs", stats.changed_inputs),
        info("fuzz_cli.error_outputs", stats.error_outputs),
        timing("fuzz_cli.seconds", seconds),
        info("fuzz_cli.ms_per_input", 1e3 * seconds / max(n, 1), "ms"),
        info("fuzz_cli.load_start", load_start[0], note="1-minute load average, 2 cores"),
        info("fuzz_cli.load_end", load_end[0], note="1-minute load average, 2 cores"),
    ]
    rows: list[list[Any]] = [
        ["inputs", stats.inputs], ["read as a graph (readers)", stats.graphs_read],
        ["command runs", stats.runs],
        ["reader failures (exceptions, round trips, NumPy warnings)", stats.reader],
        ["tracebacks (exit 1, or an exception out of main)", stats.tracebacks],
        ["crashes (worker killed by a signal)", stats.crashes],
        ["hangs (over 60 s)", stats.hangs],
        ["NumPy warnings (RuntimeWarning ...)", stats.warnings],
        ["temporary files left", stats.left_files],
        ["inputs changed (bytes or inode)", stats.changed_inputs],
        ["outputs created or replaced by a failed command (exit 2)", stats.error_outputs],
        ["other failures", stats.other],
        ["the package's own warnings (UserWarning notes)", stats.notes],
        ["slowest input (s)", stats.slowest_s], ["time (s)", seconds],
        ["load average at start / end (1 min, 2 cores)",
         f"{load_start[0]:.2f} / {load_end[0]:.2f}"],
    ]
    rows += [[f"inputs: {k}", v] for k, v in sorted(stats.layouts.items())]
    rows += [[k, v] for k, v in sorted(stats.exit_codes.items())]
    rows += [[f"failure: {k}", v] for k, v in sorted(stats.failures.items())]
    table = markdown_table(f"Grammar-aware fuzzing of the readers and the command line "
                           f"({n} inputs, seed 0)", ["", "count"], rows)
    return metrics, [table]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.fuzz",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("n", type=int, nargs="?", default=10_000, help="inputs (default 10000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", type=pathlib.Path, help="keep one failing input per kind here")
    ap.add_argument("--grammar", action="store_true",
                    help="grammar-aware inputs through the readers and the command line")
    ap.add_argument("--plot-every", type=int, default=20, metavar="K",
                    help="--grammar: run 'plot' on one input in K (0: never; default 20)")
    args = ap.parse_args(argv)
    if args.grammar:
        gstats, seconds = fuzz_grammar(args.n, args.seed, plot_every=args.plot_every,
                                       save=args.save, progress=True)
        print(grammar_summary(gstats, seconds))
        return 1 if gstats.bad else 0
    stats, seconds = fuzz(args.n, args.seed, args.save, progress=True)
    bad = sum(stats.failures.values())
    print(f"{args.n} inputs in {seconds:.1f} s ({1e6 * seconds / max(args.n, 1):.0f} us each): "
          f"{stats.graphs_read} read as graphs, {stats.tum_read} as TUM, {stats.rejected} "
          f"rejected; {stats.writes} writes, {stats.writes_refused} refused, "
          f"{stats.round_trips} round trips equal; {bad} failures")
    for kind, count in stats.failures.most_common():
        detail, text = stats.examples[kind]
        print(f"  {count:6d}  {kind}: {detail[:300]}")
        print("          input: " + repr(text[:300]))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
