"""Bounded fuzzing of the readers and the convert round trip.

The long run is ``python -m benchmarks.fuzz N`` (``benchmarks/fuzz.py``, whose checker this file
reuses); here hypothesis drives a few hundred inputs in a few seconds: mutated valid files, and
lines assembled from tags and parser-breaking tokens.  The property: every input is either read
(and then every format it can be written to reads back equal) or rejected with the package's own
error (``HybridPGOError``) -- never another exception, never a NumPy floating-point warning.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # benchmarks/ is a top-level package beside src/
    sys.path.insert(0, str(ROOT))

from benchmarks.fuzz import (  # noqa: E402
    ODD_CHARS,
    SPECIAL_TOKENS,
    as_read,
    check_input,
    mutate,
    seed_corpus,
)

CORPUS = seed_corpus(0)
TAGS = sorted({line.split(" ")[0] for _, text in CORPUS for line in text.splitlines() if line})
POLICIES = st.sampled_from([None, "nearest", "skip"])
FORMATS = st.sampled_from([None, "g2o", "toro", "isam"])
FUZZ = settings(deadline=None, max_examples=150,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def test_the_seed_corpus_reads_and_round_trips() -> None:
    """Every seed file is valid: the mutations start from files that read."""
    for name, text in CORPUS:
        assert check_input(text, None) == [], name


def test_the_checker_can_fail(monkeypatch: pytest.MonkeyPatch) -> None:
    """The oracle is not vacuous: a non-package exception and a round-trip mismatch are both
    reported."""
    import benchmarks.fuzz as fz

    def broken(*args: object, **kwargs: object) -> None:
        raise KeyError("simulated bug")

    with monkeypatch.context() as m:
        m.setattr(fz, "read_graph_source", broken)
        assert [k for k, _ in check_input(CORPUS[0][1], None)] == ["read: KeyError"]
    real = fz.read_back

    def lossy(lines: list[str], fmt: str, name: str):  # type: ignore[no-untyped-def]
        return real([ln.replace("EDGE_SE2 0 1", "EDGE_SE2 1 0") for ln in lines], fmt, name)

    monkeypatch.setattr(fz, "read_back", lossy)
    kinds = [k for k, _ in check_input("\n".join(["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0 0",
                                                  "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1"]), None)]
    assert kinds == ["round trip g2o: mismatch"]


@FUZZ
@given(base=st.integers(0, len(CORPUS) - 1), seed=st.integers(0, 2**32 - 1), policy=POLICIES,
       fmt=FORMATS)
def test_mutated_files(base: int, seed: int, policy: str | None, fmt: str | None) -> None:
    rng = np.random.default_rng(seed)
    text = as_read(mutate(CORPUS[base][1], rng, CORPUS), rng)
    assert check_input(text, policy, fmt=fmt) == []


_TOKEN = st.one_of(st.sampled_from(SPECIAL_TOKENS), st.integers(-3, 9).map(str),
                   st.floats(allow_nan=True, allow_infinity=True).map(repr),
                   st.text(alphabet="0123456789.eE+-", max_size=6))
_LINE = st.builds(lambda tag, toks, sep: sep.join([tag, *toks]),
                  st.sampled_from(TAGS), st.lists(_TOKEN, min_size=0, max_size=30),
                  st.sampled_from([" ", "\t", " \f ", "  "]))


@FUZZ
@given(lines=st.lists(st.one_of(_LINE, st.sampled_from(ODD_CHARS)), min_size=1, max_size=12),
       policy=POLICIES, fmt=FORMATS)
def test_assembled_lines(lines: list[str], policy: str | None, fmt: str | None) -> None:
    assert check_input("\n".join(lines) + "\n", policy, fmt=fmt) == []


# --------------------------------------------------------------------------- grammar-aware mode
def test_grammar_inputs_use_the_tags_of_their_format() -> None:
    from benchmarks.fuzz import LAYOUTS, grammar_input

    extra = {"FIX", "PARAMS_SE3OFFSET", "EDGE_SE3_XYZ_PRIOR", "EQUIV"}
    other_tags = set(TAGS)
    seen = set()
    for k in range(300):
        layout, text = grammar_input(np.random.default_rng([7, k]))
        seen.add(layout.name)
        allowed = {layout.vertex, *layout.edges, *extra, *other_tags}
        for line in text.lstrip("\ufeff").replace("\r\n", "\n").replace("\r", "\n").split("\n"):
            head = line.split()
            if not head or head[0].startswith("#"):
                continue
            if layout.name == "tum":
                continue
            assert head[0] in allowed, (layout.name, line[:80])
    assert seen == {lay.name for lay in LAYOUTS}


def test_grammar_inputs_through_the_command_line(tmp_path: Path) -> None:
    """A few grammar inputs through the readers and every command: no failure."""
    from benchmarks.fuzz import grammar_one

    for k in range(8):
        res = grammar_one(3, k, tmp_path, plot_every=0)
        assert res["failures"] == [], res


def test_the_command_line_checker_can_fail(monkeypatch: pytest.MonkeyPatch,
                                           tmp_path: Path) -> None:
    """A traceback, a NumPy warning, a temporary file left behind, a changed input and an
    output written by a failing command are each reported."""
    import warnings

    import hybridpgo.cli.info as info
    from benchmarks.fuzz import run_cli_check

    graph = tmp_path / "g.g2o"
    graph.write_text(CORPUS[0][1])
    out = tmp_path / "work"
    out.mkdir()

    def bug(args: object) -> int:
        raise KeyError("simulated bug")

    def warns(args: object) -> int:
        warnings.warn("overflow encountered in multiply", RuntimeWarning, stacklevel=1)
        return 0

    def leaves(args: object) -> int:
        (out / ".g.g2o.12345678.tmp").write_text("x")
        return 0

    def changes(args: object) -> int:
        graph.write_text(CORPUS[0][1] + "\n")
        return 0

    def writes_and_fails(args: object) -> int:
        (out / "r.csv").write_text("x")
        return 2

    expected = {bug: "info: traceback KeyError", warns: "info: RuntimeWarning overflow",
                leaves: "info: temporary file left", changes: "info: input changed",
                writes_and_fails: "info: output written after an error"}
    for fake, kind in expected.items():
        monkeypatch.setattr(info, "run", fake)
        _, failures, _ = run_cli_check(["info", str(graph)], out, (graph,))
        graph.write_text(CORPUS[0][1])
        (out / "r.csv").unlink(missing_ok=True)
        assert [k for k, _ in failures] and all(k.startswith(kind) for k, _ in failures), \
            failures
    assert list(out.iterdir()) == []  # the checker removes what it found
