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
"""

from __future__ import annotations

import argparse
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.fuzz",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("n", type=int, nargs="?", default=10_000, help="inputs (default 10000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", type=pathlib.Path, help="keep one failing input per kind here")
    args = ap.parse_args(argv)
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
