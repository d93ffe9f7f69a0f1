"""The examples of the hand-written pages run: every ``hybridpgo`` command of a fenced ``bash``
block and every fenced ``python`` block of README.md and docs/*.md, in page order, in a fresh
directory per page.

What runs, and how it is made small enough for the suite:

* A ``bash`` line is split at ``&&``, ``||``, ``;`` and ``|``; each part that starts with
  ``hybridpgo`` runs in-process through :func:`hybridpgo.cli.main` and must exit 0.  Other
  programs (``pip install``, ``rerun m.rrd``, ``python -m ...``) are not run.
* ``hybridpgo generate grid`` / ``generate city`` without ``--poses`` get ``--poses`` from
  ``SMALL_POSES`` (the pages generate the full-size graphs; every later command of the page then
  works on the small one, so the whole file stays within about a minute on 2 cores).
  ``bundled_path("M3500_isam.txt")``, the graph of ``hybridpgo demo`` and of the README's
  python block, gives a grid generated the same way at that size (``_small_bundled``): the
  command or block runs as written, on a smaller graph.
* A command or block that needs an optional extra (``--rerun``: rerun-sdk; ``batch``: dask;
  ``--compare isam2`` or ``import gtsam``: gtsam; plots: matplotlib) is skipped, with the extra
  named, when that extra is missing; the rest of the page still runs.
* A python block runs as a script of its own (fresh globals), in the page's directory, so it
  sees the files the commands above it wrote.

``--rerun`` recordings are kept small by the tiny graphs; no test here is marked ``slow``.
"""

from __future__ import annotations

import importlib.util
import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: The hand-written pages (api.md and cli.md are generated from the code: tests/test_docs.py).
PAGES = sorted([ROOT / "README.md",
                *(p for p in (ROOT / "docs").glob("*.md") if p.name not in ("api.md", "cli.md"))])
#: ``--poses`` given to a page's ``generate`` command that has none.
SMALL_POSES = {"grid": 300, "city": 400}
#: Optional extras: the module that must import, and how a user installs it.
EXTRAS = {
    "rerun": ("rerun", 'pip install "hybridpgo[rerun]"'),
    "dask": ("distributed", 'pip install "hybridpgo[dask]"'),
    "gtsam": ("gtsam", 'pip install "hybridpgo[gtsam]"'),
    "plot": ("matplotlib", 'pip install "hybridpgo[plot]"'),
}
_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>```+|~~~+)[ \t]*(?P<lang>[\w+-]*)[^\n]*$")
_SEPARATORS = {"&&", "||", ";", "|"}


@dataclass(frozen=True)
class Example:
    """One thing a reader of ``page`` would run: a command line or a python block."""

    page: str
    line: int
    kind: str  # "command" or "python"
    text: str  # the command's argument list joined, or the block's code

    @property
    def label(self) -> str:
        first = self.text.strip().splitlines()[0] if self.text.strip() else ""
        return f"{self.page}:{self.line}: {first[:70]}"


def fenced_blocks(text: str) -> Iterator[tuple[int, str, str]]:
    """``(line number of the block's first line, language, code)`` of every fenced block."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if m is None:
            i += 1
            continue
        indent, fence, lang = m["indent"], m["fence"], m["lang"].lower()
        body: list[str] = []
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence):
            body.append(lines[j][len(indent):] if lines[j].startswith(indent) else lines[j])
            j += 1
        yield i + 2, lang, "\n".join(body)
        i = j + 1


def command_parts(line: str) -> list[list[str]]:
    """The ``hybridpgo`` commands of one shell line (comments dropped, split at ``&&`` etc.)."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars="&|;")
    lexer.whitespace_split = True
    lexer.commenters = "#"
    parts: list[list[str]] = [[]]
    for token in lexer:
        if token in _SEPARATORS:
            parts.append([])
        else:
            parts[-1].append(token)
    return [p for p in parts if p and p[0] == "hybridpgo"]


def examples(page: Path) -> list[Example]:
    """The page's commands and python blocks, in page order."""
    name = page.relative_to(ROOT).as_posix()
    out: list[Example] = []
    for start, lang, code in fenced_blocks(page.read_text(encoding="utf-8")):
        if lang in ("bash", "sh", "shell", "console"):
            for k, raw in enumerate(code.splitlines()):
                for argv in command_parts(raw.removeprefix("$ ")):
                    out.append(Example(name, start + k, "command", shlex.join(argv)))
        elif lang in ("python", "py"):
            out.append(Example(name, start, "python", code))
    return out


def needed_extras(ex: Example) -> list[str]:
    """The optional extras an example needs (see ``EXTRAS``)."""
    need: list[str] = []
    if ex.kind == "command":
        argv = shlex.split(ex.text)
        if "--rerun" in argv:
            need.append("rerun")
        if len(argv) > 1 and argv[1] == "batch":
            need.append("dask")
        if "--compare" in argv:
            need.append("gtsam")
        if "--plot" in argv or (len(argv) > 1 and argv[1] == "plot"):
            need.append("plot")
    else:
        for extra, (module, _) in EXTRAS.items():
            if re.search(rf"^\s*(import|from)\s+{module}\b", ex.text, re.M):
                need.append(extra)
        if re.search(r"hybridpgo\.plot|from hybridpgo import plot|\bplot_graph", ex.text):
            need.append("plot")
    return need


def small_argv(argv: list[str]) -> list[str]:
    """``argv`` with ``--poses`` added to a ``generate`` command that has none."""
    if len(argv) > 2 and argv[1] == "generate" and argv[2] in SMALL_POSES:
        if "--poses" not in argv and not any(a.startswith("--poses=") for a in argv):
            return [*argv, "--poses", str(SMALL_POSES[argv[2]])]
    return argv


def _small_bundled(workdir: Path) -> object:
    """``bundled_path`` for python blocks: M3500_isam.txt becomes a small generated grid (the
    same generator as ``hybridpgo generate grid``, seed 1), every other name is unchanged."""
    from hybridpgo import io as hio
    from hybridpgo.cli import main

    real = hio.bundled_path

    def bundled_path(name: str) -> Path:
        if name != "M3500_isam.txt":
            return real(name)
        small = workdir / "_small_M3500.g2o"
        if not small.exists():
            assert main(["generate", "grid", "--seed", "1", "--poses",
                         str(SMALL_POSES["grid"]), "-o", str(small)]) == 0
        return small

    return bundled_path


def run_example(ex: Example, workdir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Run one example in ``workdir``; fail with the page and line when it does not work."""
    from hybridpgo.cli import main

    monkeypatch.chdir(workdir)
    monkeypatch.setattr("hybridpgo.io.bundled_path", _small_bundled(workdir))
    if ex.kind == "command":
        argv = small_argv(shlex.split(ex.text))
        code = main(argv[1:])
        assert code == 0, f"{ex.label}: `{shlex.join(argv)}` exited with status {code}"
        return
    namespace = {"__name__": "__main__"}
    code_obj = compile(ex.text, f"{ex.page}:{ex.line}", "exec")
    exec(code_obj, namespace)


#: The pages with at least one example (the others have nothing to run).
RUNNABLE = [p for p in PAGES if examples(p)]


@pytest.mark.parametrize("page", RUNNABLE, ids=[p.relative_to(ROOT).as_posix() for p in RUNNABLE])
def test_page_examples_run(page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                           subtests: pytest.Subtests) -> None:
    """Every command and python block of the page works, in order (see the module doc)."""
    for ex in examples(page):
        with subtests.test(msg=ex.label):
            missing = [e for e in needed_extras(ex)
                       if importlib.util.find_spec(EXTRAS[e][0]) is None]
            if missing:
                pytest.skip(", ".join(f"needs {e} ({EXTRAS[e][1]})" for e in missing))
            with monkeypatch.context() as m:
                run_example(ex, tmp_path, m)


# --------------------------------------------------------------------------- the harness itself
def test_fenced_blocks_and_commands_are_found() -> None:
    text = ("intro\n```bash\nhybridpgo info m.g2o   # counts\npip install x && hybridpgo demo\n"
            "hybridpgo optimize a -o b --rerun r.rrd && rerun r.rrd\nrerun x\n```\n"
            "1. step\n\n   ```python\n   import hybridpgo\n   x = 1\n   ```\n"
            "```\nhybridpgo not-bash\n```\n")
    blocks = list(fenced_blocks(text))
    assert [(line, lang) for line, lang, _ in blocks] == [(3, "bash"), (11, "python"), (15, "")]
    assert blocks[1][2] == "import hybridpgo\nx = 1"
    cmds = [p for line in blocks[0][2].splitlines() for p in command_parts(line)]
    assert cmds == [["hybridpgo", "info", "m.g2o"], ["hybridpgo", "demo"],
                    ["hybridpgo", "optimize", "a", "-o", "b", "--rerun", "r.rrd"]]


def test_generate_is_made_small_and_extras_are_detected() -> None:
    assert small_argv(["hybridpgo", "generate", "grid", "-o", "m.g2o"])[-2:] == ["--poses", "300"]
    assert small_argv(["hybridpgo", "generate", "city", "--poses", "9", "-o", "c"]).count(
        "--poses") == 1
    rr = Example("p", 1, "command", "hybridpgo optimize m.g2o -o o.g2o --rerun m.rrd")
    assert needed_extras(rr) == ["rerun"]
    py = Example("p", 1, "python", "import gtsam\nfrom hybridpgo.plot import plot_graph")
    assert needed_extras(py) == ["gtsam", "plot"]


def test_a_failing_command_fails_the_page(tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A documented option that the CLI rejects is a failure naming the page and line."""
    ex = Example("docs/x.md", 7, "command", "hybridpgo optimize missing.g2o -o out.g2o")
    with pytest.raises(AssertionError, match=r"docs/x\.md:7: .* exited with status 2"):
        run_example(ex, tmp_path, monkeypatch)
    bad = Example("docs/x.md", 9, "python", "import hybridpgo\nhybridpgo.no_such_function()")
    with pytest.raises(AttributeError):
        run_example(bad, tmp_path, monkeypatch)
