"""Tags and their numbers: what each tag's line holds (:class:`TagSpec`), the lines of one tag
parsed together by one :func:`numpy.loadtxt` call (C speed), and only when that fails re-parsed
line by line to name the exact line and field (docs/contributing.md#errors: errors read like a
compiler's)."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import option_hint
from ._source import (
    FloatArray,
    IntArray,
    Source,
    show_token,
)


@dataclass(frozen=True, slots=True)
class TagSpec:
    """Layout of one line type: ``TAG <id fields> <number fields>``.

    ``optional_from``: the number fields from this index on may be omitted all together (TORO
    ``EDGE3`` without information).  ``variadic_ids``: one or more ids and no numbers (g2o ``FIX``).
    """

    tag: str
    id_fields: tuple[str, ...]
    number_fields: tuple[str, ...] = ()
    optional_from: int | None = None
    variadic_ids: bool = False

    @property
    def counts(self) -> tuple[int, ...]:
        """Accepted numbers of fields after the tag, the full layout first."""
        full = len(self.id_fields) + len(self.number_fields)
        if self.optional_from is None:
            return (full,)
        return (full, len(self.id_fields) + self.optional_from)

    def field_name(self, k: int) -> str:
        """Name of the k-th field after the tag (0-based)."""
        if self.variadic_ids:
            return self.id_fields[0]
        names = self.id_fields + self.number_fields
        return names[k]


@dataclass(frozen=True, slots=True)
class Block:
    """All lines of one tag with one field count, parsed: (k,) line numbers, ids, numbers."""

    spec: TagSpec
    line_nos: IntArray
    ids: IntArray
    """(k, n_ids) int64 (variadic tags: (total, 1), one row per id, ``line_nos`` repeated)."""
    values: FloatArray
    """(k, n_numbers) float64, all finite."""

    def __len__(self) -> int:
        return int(self.line_nos.shape[0])


def upper_names(prefix: str, labels: Iterable[str]) -> tuple[str, ...]:
    """Names of upper-triangular entries, row by row: ``I11 I12 ... Inn`` style."""
    labs = list(labels)
    return tuple(f"{prefix}{labs[i]}{labs[j]}" for i in range(len(labs))
                 for j in range(i, len(labs)))


def _count_problem(spec: TagSpec, got: int) -> str:
    counts = spec.counts
    if spec.variadic_ids:
        return f"{spec.tag} needs at least one vertex id after the tag, got none"
    if len(counts) == 1:
        return f"{spec.tag} needs {counts[0]} numbers after the tag, got {got}"
    return (f"{spec.tag} needs {counts[0]} numbers after the tag (or {counts[1]} without the "
            f"information matrix), got {got}")


def unknown_tag_problem(tag: str, fmt: str, supported: Iterable[str]) -> str:
    return (f"unknown tag {show_token(tag)} for the {fmt} format; supported tags: "
            + ", ".join(supported) + f" (pass {option_hint('skip_unknown')} to skip such lines "
            "with a warning)")


def parse_blocks(src: Source, specs: Mapping[str, TagSpec], fmt: str,
                 skip_unknown: bool) -> dict[str, list[Block]]:
    """Parse every group of ``src`` whose tag is in ``specs`` (one Block per field count).

    Unknown tags raise (earliest line first) or, with ``skip_unknown``, are skipped with ONE
    warning giving the count per tag.  Each group is parsed by :func:`numpy.loadtxt` (C speed);
    a group that fails is re-parsed line by line (:func:`_parse_slow`) to name the line and the
    field.  Field counts are checked before numbers, and the earliest bad line is reported.
    """
    unknown = [t for t in src.groups if t not in specs]
    if unknown:
        if not skip_unknown:
            first = min(unknown, key=src.first_line)
            raise src.error(src.first_line(first), unknown_tag_problem(first, fmt, specs))
        detail = ", ".join(f"{t} ({len(src.groups[t][0])})" for t in unknown)
        total = sum(len(src.groups[t][0]) for t in unknown)
        warnings.warn(f"{src.path}: skipped {total} line(s) with tags the {fmt} reader does "
                      f"not support: {detail}", UserWarning, stacklevel=4)
    out: dict[str, list[Block]] = {}
    slow: list[str] = []
    for tag, spec in specs.items():
        if tag in src.groups:
            fast = None if spec.variadic_ids else _parse_fast(spec, *src.groups[tag])
            if fast is None:
                slow.append(tag)
            else:
                out[tag] = [fast]
    if slow:
        tokens = {tag: [rest.split() for rest in src.groups[tag][1]] for tag in slow}
        bad: list[tuple[int, str]] = []  # field counts first, over all tags
        for tag in slow:
            spec = specs[tag]
            for ln, tk in zip(src.groups[tag][0], tokens[tag], strict=True):
                if (len(tk) < 1) if spec.variadic_ids else (len(tk) not in spec.counts):
                    bad.append((ln, _count_problem(spec, len(tk))))
                    break
        if bad:
            raise src.error(*min(bad))
        for tag in slow:
            try:
                out[tag] = _parse_slow(specs[tag], src.groups[tag][0], tokens[tag])
            except _BadField as exc:
                bad.append((exc.line_no, exc.problem))
        if bad:
            raise src.error(*min(bad))
    return out


def _parse_fast(spec: TagSpec, line_nos: list[int], rests: Sequence[str]) -> Block | None:
    """One ``loadtxt`` pass over the group (ids again as int64); None when anything is off."""
    k = len(rests)
    n_ids = len(spec.id_fields)
    try:  # straight from the list of lines: no joined copy, no StringIO (4 bytes a character)
        vals = np.loadtxt(iter(rests), dtype=np.float64, comments=None, ndmin=2)
        ids = np.loadtxt(iter(rests), dtype=np.int64, comments=None, ndmin=2,
                         usecols=range(n_ids))
    except (ValueError, OverflowError):
        return None
    # loadtxt skips empty lines and allows any constant width: check both, and finiteness.
    if vals.shape != (k, spec.counts[0]) and not (len(spec.counts) > 1
                                                  and vals.shape == (k, spec.counts[1])):
        return None
    if ids.shape != (k, n_ids) or not np.isfinite(vals[:, n_ids:]).all():
        return None
    return Block(spec, np.asarray(line_nos, np.int64), ids,
                 np.ascontiguousarray(vals[:, n_ids:]))


class _BadField(Exception):
    def __init__(self, line_no: int, problem: str) -> None:
        super().__init__(problem)
        self.line_no = line_no
        self.problem = problem


def parse_int(tok: str) -> int | None:
    """An int64 written with ASCII digits (optional sign), else None.

    Python's ``int`` also accepts ``"1_0"`` and non-ASCII digits (``"١"``); the fast path
    (``loadtxt``) and every other tool do not.
    """
    if not tok.isascii() or "_" in tok or len(tok) > 20:
        return None
    try:
        v = int(tok)
    except ValueError:
        return None
    return v if -(2**63) <= v < 2**63 else None


def parse_float(tok: str) -> float | None:
    """A float written in ASCII (``1``, ``-2.5e-3``, ``inf``, ``nan``), else None.

    Rejects what Python's ``float`` accepts beyond that: ``"1_0"`` and non-ASCII digits.
    """
    if not tok.isascii() or "_" in tok:
        return None
    try:
        return float(tok)
    except ValueError:
        return None


def _to_int(spec: TagSpec, ln: int, k: int, tok: str) -> int:
    v = parse_int(tok)
    if v is None:
        raise _BadField(ln, f"{spec.tag} field {spec.field_name(k)!r} must be an integer vertex "
                        f"id, got {show_token(tok)}")
    return v


def _to_float(spec: TagSpec, ln: int, k: int, tok: str) -> float:
    v = parse_float(tok)
    if v is None:
        raise _BadField(ln, f"{spec.tag} field {spec.field_name(k)!r} is not a number: "
                        f"{show_token(tok)}")
    if not math.isfinite(v):
        raise _BadField(ln, f"{spec.tag} field {spec.field_name(k)!r} is not finite: "
                        f"{show_token(tok)}")
    return v


def _parse_slow(spec: TagSpec, line_nos: list[int], toks: list[list[str]]) -> list[Block]:
    """Line-by-line parse with exact error reports (counts were checked by the caller)."""
    if spec.variadic_ids:
        ids_l = [_to_int(spec, ln, 0, t) for ln, tk in zip(line_nos, toks, strict=True)
                 for t in tk]
        rep = np.repeat(np.asarray(line_nos, np.int64), [len(tk) for tk in toks])
        return [Block(spec, rep, np.array(ids_l, np.int64).reshape(-1, 1),
                      np.zeros((len(ids_l), 0)))]
    n_ids = len(spec.id_fields)
    blocks = []
    for count in spec.counts:
        rows_i: list[list[int]] = []
        rows_v: list[list[float]] = []
        lns: list[int] = []
        for ln, tk in zip(line_nos, toks, strict=True):
            if len(tk) != count:
                continue
            rows_i.append([_to_int(spec, ln, k, tk[k]) for k in range(n_ids)])
            rows_v.append([_to_float(spec, ln, k, tk[k]) for k in range(n_ids, count)])
            lns.append(ln)
        if lns:
            blocks.append(Block(spec, np.asarray(lns, np.int64),
                                np.array(rows_i, np.int64).reshape(-1, n_ids),
                                np.array(rows_v, np.float64).reshape(-1, count - n_ids)))
    return blocks


def stack(blocks: Iterable[Block]) -> tuple[IntArray, IntArray, FloatArray, list[Block]]:
    """Concatenate blocks (same id/number widths) in file order: line_nos, ids, values, blocks."""
    bl = [b for b in blocks if len(b)]
    if not bl:
        return np.zeros(0, np.int64), np.zeros((0, 0), np.int64), np.zeros((0, 0)), []
    if len(bl) == 1:  # one field count (the usual case): already in file order, no copies
        return bl[0].line_nos, bl[0].ids, bl[0].values, bl
    ln = np.concatenate([b.line_nos for b in bl])
    order = np.argsort(ln, kind="stable")
    ids = np.concatenate([b.ids for b in bl])[order]
    vals = np.concatenate([b.values for b in bl])[order]
    return ln[order], ids, vals, bl


# =========================================================================== matrices
