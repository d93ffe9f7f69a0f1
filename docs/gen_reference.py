"""Generate docs/api.md (from the docstrings) and docs/cli.md (from the argparse parsers).

Run from the repository root after changing a public docstring or a command-line option:

    PYTHONPATH=src python docs/gen_reference.py            # rewrites docs/api.md, docs/cli.md
    PYTHONPATH=src python docs/gen_reference.py --check    # exit 1 if they are out of date

The output is deterministic (fixed help width, sorted where the code has no order), and
``tests/test_docs.py`` fails when the committed pages differ from what this script writes.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import os
import sys
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

#: Public modules in the order the API reference shows them, each with a one-line role.
MODULES: tuple[tuple[str, str], ...] = (
    ("hybridpgo", "the package: the names most programs need"),
    ("hybridpgo.graph", "the PoseGraph struct-of-arrays"),
    ("hybridpgo.io", "reading and writing g2o, TORO, iSAM and TUM"),
    ("hybridpgo.solvers", "optimize() and the solvers' options and results"),
    ("hybridpgo.solvers.gauss_newton", "the exact sparse Gauss-Newton / Levenberg-Marquardt "
                                       "solver"),
    ("hybridpgo.solvers.hybrid", "the hybrid Hessian solver (the paper's method)"),
    ("hybridpgo.solvers.toro", "the TORO-style baseline"),
    ("hybridpgo.online", "the online (real-time) solver"),
    ("hybridpgo.online.replay", "replaying a graph as a stream of frames, beside iSAM2"),
    ("hybridpgo.tree", "the pose tree and the initializations"),
    ("hybridpgo.energy", "energies and per-constraint residuals"),
    ("hybridpgo.covariance", "marginal covariances of poses"),
    ("hybridpgo.metrics", "accuracy against ground truth (evo's statistics)"),
    ("hybridpgo.plot", "maps with residuals and energy plots (matplotlib)"),
    ("hybridpgo.recording", "recording a run for the Rerun viewer"),
    ("hybridpgo.gtsam_bridge", "conversion to and from GTSAM"),
    ("hybridpgo.generate", "synthetic graphs with ground truth"),
    ("hybridpgo.geometry.so3", "SO(3), vectorised"),
    ("hybridpgo.geometry.se3", "SE(3), vectorised"),
    ("hybridpgo.errors", "the exceptions"),
)

#: Width of the command-line help text (argparse reads $COLUMNS).
HELP_WIDTH = 100

ROOT = Path(__file__).resolve().parent.parent

#: argparse words its help differently between Python versions ("optional arguments" before
#: 3.10, colours from 3.14): cli.md records the version that wrote it, and the drift test
#: compares it only under the same version.
ARGPARSE_OF = f"argparse of Python {sys.version_info[0]}.{sys.version_info[1]}"


# --------------------------------------------------------------------------- API reference
def _public_names(module: Any) -> list[str]:
    """``__all__``, else the public functions and classes defined in the module itself."""
    names = getattr(module, "__all__", None)
    if names is not None:
        return list(names)
    return sorted(n for n, v in vars(module).items()
                  if not n.startswith("_") and (inspect.isfunction(v) or inspect.isclass(v))
                  and getattr(v, "__module__", None) == module.__name__)


def _doc(obj: Any) -> str:
    """A docstring as Markdown: its first paragraph as prose, the rest verbatim in a text
    block (numpydoc sections, doctest examples and tables keep their layout)."""
    doc = inspect.getdoc(obj)
    if not doc or not doc.strip():
        return "*(no docstring)*"
    head, _, rest = doc.strip().partition("\n\n")
    if head.lstrip().startswith(">>>"):  # the docstring opens with an example
        head, rest = "", doc.strip()
    out = " ".join(head.split())
    if rest.strip():
        out += ("\n\n" if out else "") + "```text\n" + rest.rstrip() + "\n```"
    return out


def _signature(obj: Any) -> str:
    try:
        return str(inspect.signature(obj))
    except (TypeError, ValueError):
        return "(...)"


def _attribute_docs(cls: type) -> list[tuple[str, str, str]]:
    """``(name, annotation, docstring)`` of the annotated class attributes that are followed
    by a string literal (attribute docstrings, as the dataclasses here are documented)."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return []
    body = ast.parse(source).body[0]
    if not isinstance(body, ast.ClassDef):
        return []
    out = []
    stmts = body.body
    for k, stmt in enumerate(stmts):
        if not (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)):
            continue
        nxt = stmts[k + 1] if k + 1 < len(stmts) else None
        doc = ""
        if (isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)):
            doc = inspect.cleandoc(nxt.value.value)
        out.append((stmt.target.id, ast.unparse(stmt.annotation), doc))
    return out


def _class_section(name: str, cls: type, qual: str) -> Iterator[str]:
    yield f"### `{qual}`\n"
    bases = [b.__name__ for b in cls.__bases__ if b is not object]
    kind = "dataclass" if dataclasses.is_dataclass(cls) else "class"
    sig = _signature(cls) if dataclasses.is_dataclass(cls) or "__init__" in vars(cls) else ""
    yield "```python\n" + f"{kind} {name}{sig}" + (f"  # bases: {', '.join(bases)}"
                                                   if bases else "") + "\n```\n"
    yield _doc(cls) + "\n"
    attrs = _attribute_docs(cls)
    if attrs:
        yield "| attribute | type | description |\n|---|---|---|"
        for a, ann, doc in attrs:
            cell = " ".join(doc.split()).replace("|", "\\|")
            yield f"| `{a}` | `{ann.replace('|', chr(92) + '|')}` | {cell} |"
        yield ""
    members = []
    for m, v in vars(cls).items():
        if m.startswith("_") and m != "__call__":
            continue
        if isinstance(v, (staticmethod, classmethod)):
            v = v.__func__
        if inspect.isfunction(v) or isinstance(v, property):
            members.append((m, v))
    for m, v in members:
        if isinstance(v, property):
            yield f"#### `{qual}.{m}` (property)\n"
            yield _doc(v) + "\n"
        else:
            yield f"#### `{qual}.{m}`\n"
            yield f"```python\ndef {m}{_signature(v)}\n```\n"
            yield _doc(v) + "\n"


def _home(obj: Any) -> str | None:
    """The listed module that documents ``obj`` in full: the one whose name is the longest
    prefix of the module defining it (None: documented wherever it is listed)."""
    defined = obj.__name__ if inspect.ismodule(obj) else getattr(obj, "__module__", None)
    if not isinstance(defined, str):
        return None
    best = None
    for modname, _ in MODULES:
        if (defined == modname or defined.startswith(modname + ".")) and (
                best is None or len(modname) > len(best)):
            best = modname
    return best


def _object_section(name: str, obj: Any, modname: str) -> Iterator[str]:
    qual = f"{modname}.{name}"
    home = _home(obj)
    if home is not None and home != modname and (
            inspect.ismodule(obj) or name in _public_names(importlib.import_module(home))):
        target = home if inspect.ismodule(obj) else f"{home}.{name}"
        what = "The module" if inspect.ismodule(obj) else "Documented under"
        yield f"### `{qual}`\n"
        yield f"{what} [`{target}`](#{_anchor(target)}).\n"
    elif inspect.isclass(obj):
        yield from _class_section(name, obj, qual)
    elif callable(obj):
        yield f"### `{qual}`\n"
        yield f"```python\ndef {name}{_signature(obj)}\n```\n"
        yield _doc(obj) + "\n"
    else:
        yield f"### `{qual}`\n"
        yield f"```python\n{name} = {obj!r}\n```\n"


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading made of a dotted name (dots dropped, lower case)."""
    return heading.replace(".", "").replace(" ", "-").lower()


def api_markdown() -> str:
    lines = ["<!-- generated by docs/gen_reference.py from the docstrings: do not edit -->",
             "# API reference", "",
             "Every public module, function and class of hybridpgo with its docstring.  Shapes, "
             "frames and units are in the docstrings; the conventions behind them are in "
             "[conventions.md](conventions.md).  Names starting with `_` are private.", "",
             "## Modules", ""]
    for modname, role in MODULES:
        lines.append(f"* [`{modname}`](#{_anchor(modname)}): {role}")
    lines.append("")
    for modname, _ in MODULES:
        module = importlib.import_module(modname)
        lines.append(f"## {modname}\n")
        lines.append(_doc(module) + "\n")
        for name in _public_names(module):
            obj = getattr(module, name)
            lines.extend(_object_section(name, obj, modname))
    return "\n".join(lines).rstrip() + "\n"


# --------------------------------------------------------------------------- CLI reference
def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _help_text(parser: argparse.ArgumentParser) -> str:
    return parser.format_help().rstrip()


def cli_markdown() -> str:
    from hybridpgo.cli._parser import build_parser

    parser = build_parser()
    lines = [f"<!-- generated by docs/gen_reference.py from the argparse parsers "
             f"({ARGPARSE_OF}): do not edit -->",
             "# Command-line reference", "",
             "The `hybridpgo` command (also `python -m hybridpgo.cli`).  Results go to standard "
             "output, progress and logs to standard error; a bad input is one line "
             "`hybridpgo: error: ...` and exit status 2.  This page is the `--help` of every "
             "command.", "",
             "## Commands", ""]
    commands = _subparsers(parser)
    rows: list[tuple[str, argparse.ArgumentParser]] = []
    for name, sub in commands.items():
        kinds = _subparsers(sub)
        rows.append((name, sub))
        rows.extend((f"{name} {k}", p) for k, p in kinds.items())
    for name, _ in rows:
        lines.append(f"* [`hybridpgo {name}`](#{_anchor('hybridpgo ' + name)})")
    lines += ["", "## hybridpgo", "", "```text", _help_text(parser), "```", ""]
    for name, sub in rows:
        lines += [f"## hybridpgo {name}", "", "```text", _help_text(sub), "```", ""]
    return "\n".join(lines).rstrip() + "\n"


# --------------------------------------------------------------------------- driver
PAGES: dict[str, Callable[[], str]] = {"api.md": api_markdown, "cli.md": cli_markdown}


def generate() -> dict[str, str]:
    """The text of every generated page, by file name."""
    # argparse wraps help text to $COLUMNS and (3.14+) colours it unless NO_COLOR is set
    env = {"COLUMNS": str(HELP_WIDTH), "NO_COLOR": "1"}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        return {name: make() for name, make in PAGES.items()}
    finally:
        for k, v in saved.items():
            if v is None:
                del os.environ[k]
            else:
                os.environ[k] = v


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="only compare with the committed pages; exit 1 if they differ")
    ap.add_argument("--out-dir", type=Path, default=ROOT / "docs",
                    help="where to write the pages (default: docs/)")
    args = ap.parse_args(argv)
    pages = generate()
    stale = []
    for name, text in pages.items():
        path = args.out_dir / name
        old = path.read_text(encoding="utf-8") if path.exists() else None
        if old != text:
            stale.append(name)
            if not args.check:
                path.write_text(text, encoding="utf-8")
    if args.check and stale:
        print(f"out of date: {', '.join(stale)} (run: PYTHONPATH=src python "
              "docs/gen_reference.py)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
