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
