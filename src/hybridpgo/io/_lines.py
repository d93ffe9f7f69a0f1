"""Shared plumbing of the readers and writers: tokeniser with line numbers, vectorised number
parsing, graph assembly with file-level checks, and atomic writing.

Reading is vectorised per tag, so files of millions of lines read quickly: only the tag of each
line is split off in Python, the lines of each tag are joined and converted by one
:func:`numpy.loadtxt` call (C speed; per-line token lists would cost ~5x more, mostly in the
garbage collector).  Only when that fails is the group re-parsed line by line, to name the exact
line and field (docs/contributing.md#errors: errors read like a compiler's).

Also here: SE(2) angle helpers; the quaternion and Euler conversions are
:mod:`hybridpgo.geometry.so3`'s (re-exported for the format modules).
"""

from __future__ import annotations

import contextvars
import math
import os
import sys
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import IO

import numpy as np
import numpy.typing as npt

from .._output import Outputs
from ..errors import FormatError, GraphError, option_hint
from ..geometry.so3 import euler_rpy_to_matrix as euler_rpy_to_matrix
from ..geometry.so3 import matrix_to_euler_rpy as matrix_to_euler_rpy
from ..geometry.so3 import matrix_to_quat_xyzw as matrix_to_quat_xyzw
from ..geometry.so3 import normalize_quaternions as normalize_quaternions
from ..geometry.so3 import quat_xyzw_to_matrix as quat_xyzw_to_matrix
from ..graph import MAX_INFORMATION, PoseGraph, lift_information_2d

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
PathLike = str | os.PathLike[str]

#: A PARAMS_SE3OFFSET (or other "identity") value is accepted when every entry is within this
#: absolute distance of the identity's (files print ~7 digits; a real offset is >> 1e-9).
IDENTITY_ATOL = 1e-9

#: The path that means standard input (reading) or standard output (writing).
STDIO = "-"
#: Output paths written to ``sys.stdout`` (:data:`STDOUT_TARGET`): ``/dev/stdout`` too, so that
#: a shell redirection of it to a file is not replaced by a rename, nor truncated twice.
STDOUT_NAMES = (STDIO, "/dev/stdout")
#: How standard input is named in messages.
STDIN_NAME = "<stdin>"
#: Where writing to ``"-"`` goes (None: ``sys.stdout``).  The CLI sets it to the real standard
#: output while its own messages go to stderr, so a graph written to ``-o -`` stays clean.
STDOUT_TARGET: contextvars.ContextVar[IO[str] | None] = contextvars.ContextVar(
    "hybridpgo_stdout", default=None)

#: Policies for information matrices that are not positive definite (``fix_information``).
FIX_INFORMATION: tuple[str, ...] = ("nearest", "skip")
#: ``fix_information="nearest"`` clips the eigenvalues of a symmetric matrix at this fraction of
#: its largest eigenvalue magnitude (at this absolute value for the zero matrix): the result is
#: the nearest (Frobenius norm) symmetric matrix whose eigenvalues are all >= that floor, and its
#: condition number is at most 1e9.
NEAREST_SPD_FLOOR = 1e-9

#: Echoed file tokens longer than this are shortened in messages (a million-digit number must
#: not give a megabyte error line).
MAX_ECHO = 40
#: At most this many line numbers are listed in a message.
MAX_LINES_LISTED = 5


def show_token(tok: str) -> str:
    """``repr(tok)``, shortened to :data:`MAX_ECHO` characters with the full length noted."""
    if len(tok) <= MAX_ECHO:
        return repr(tok)
    return repr(tok[:MAX_ECHO]) + f"... ({len(tok)} characters)"


def list_lines(line_nos: Iterable[int]) -> str:
    """``lines 4, 6`` or ``lines 4, 6, 9, 12, 15 and 5016 more``."""
    nums = [int(n) for n in line_nos]
    shown = ", ".join(str(n) for n in nums[:MAX_LINES_LISTED])
    more = f" and {len(nums) - MAX_LINES_LISTED} more" if len(nums) > MAX_LINES_LISTED else ""
    return f"line{'s' if len(nums) > 1 else ''} {shown}{more}"


# =========================================================================== source & tokens
@dataclass(slots=True)
class Source:
    """A text file split into lines, with the data lines grouped by tag (first token)."""

    path: str
    lines: list[str]
    #: tag -> (1-based line numbers, the text after the tag); dict order = first appearance.
    groups: dict[str, tuple[list[int], Sequence[str]]] = field(default_factory=dict)
    #: What to do with information that is not positive definite: None (raise), or one of
    #: :data:`FIX_INFORMATION` (set by the readers from their ``fix_information`` argument).
    fix_information: str | None = None

    def error(self, line_no: int | None, problem: str) -> FormatError:
        """A :class:`FormatError` at ``line_no`` (``None``: the file as a whole)."""
        line = self.lines[line_no - 1] if line_no is not None else None
        return FormatError(problem, self.path, line_no, line)

    def first_line(self, tag: str) -> int:
        return self.groups[tag][0][0]

    def count_fields(self, tag: str, count: int) -> bool:
        """True when some ``tag`` line has exactly ``count`` fields after the tag."""
        return any(len(rest.split()) == count for rest in self.groups[tag][1])


def check_fix_information(fix_information: str | None) -> None:
    if fix_information is not None and fix_information not in FIX_INFORMATION:
        raise ValueError(f"fix_information must be one of {FIX_INFORMATION} or None, got "
                         f"{fix_information!r}")


def split_lines(text: str) -> list[str]:
    """Lines broken at ``\\n``, ``\\r\\n`` and ``\\r`` only.

    ``str.splitlines`` also breaks at form feeds, vertical tabs, ``\\x1c``-``\\x1e``, U+0085 and
    U+2028/9, which a text editor (and every other tool) shows inside one line: every later line
    number would be off.
    """
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    return lines


def read_bytes(path: PathLike) -> tuple[str, bytes]:
    """(name for messages, content) of ``path``; ``"-"`` reads standard input."""
    name = os.fspath(path)
    if name == STDIO:
        stream = sys.stdin
        buffer = getattr(stream, "buffer", None)
        try:
            raw = buffer.read() if buffer is not None else stream.read().encode("utf-8")
        except (OSError, ValueError) as exc:
            raise FormatError(f"cannot read standard input: {exc}", STDIN_NAME) from exc
        return STDIN_NAME, raw
    try:
        with open(name, "rb") as fh:
            return name, fh.read()
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise FormatError(f"cannot read the file: {reason}", name) from exc


def load_source(path: PathLike, fix_information: str | None = None) -> Source:
    """Read ``path`` (``"-"``: standard input) and group its data lines by tag; blank and ``#``
    lines are skipped.  ``fix_information`` becomes ``Source.fix_information``.

    Raises
    ------
    FormatError
        When the file cannot be read (missing, a directory, no permission, ...).
    """
    check_fix_information(fix_information)
    name, raw = read_bytes(path)
    text = raw.decode("utf-8", errors="replace")
    del raw  # a 1M-pose file is 500 MB: hold at most the text and its lines at once
    lines = split_lines(text)
    del text
    src = _source_from_lines(lines, name)
    src.fix_information = fix_information
    return src


def source_from_text(text: str, name: str) -> Source:
    """A :class:`Source` from text in memory (``name`` is used in messages)."""
    # Undecodable bytes become U+FFFD, so a binary file fails later as an unknown tag with a line.
    return _source_from_lines(split_lines(text), name)


class _Rests(Sequence[str]):
    """The text after the tag of some lines, split off when asked for (no second copy of a
    large file's text is kept)."""

    def __init__(self, lines: list[str], line_nos: list[int]) -> None:
        self._lines = lines
        self._line_nos = line_nos

    def __len__(self) -> int:
        return len(self._line_nos)

    @staticmethod
    def _rest(line: str) -> str:
        head = line.split(None, 1)
        return head[1] if len(head) > 1 else ""

    def __getitem__(self, k: int) -> str:  # type: ignore[override]
        return self._rest(self._lines[self._line_nos[k] - 1])

    def __iter__(self) -> Iterator[str]:
        lines, rest = self._lines, self._rest
        return (rest(lines[i - 1]) for i in self._line_nos)


def _source_from_lines(lines: list[str], name: str) -> Source:
    line_nos: dict[str, list[int]] = {}
    for i, line in enumerate(lines, start=1):
        head = line.split(None, 1)  # only the tag is split off here (see the module doc)
        if not head or head[0].startswith("#"):
            continue
        g = line_nos.get(head[0])
        if g is None:
            g = line_nos[head[0]] = []
        g.append(i)
    return Source(name, lines, {tag: (nos, _Rests(lines, nos)) for tag, nos in line_nos.items()})


# =========================================================================== tag layouts
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
def sym_from_upper(vals: FloatArray, d: int) -> FloatArray:
    """(k, d(d+1)/2) upper-triangular entries, row by row -> (k, d, d) symmetric."""
    iu = np.triu_indices(d)
    out = np.zeros((vals.shape[0], d, d))
    out[:, iu[0], iu[1]] = vals
    out[:, iu[1], iu[0]] = vals
    return out


def upper_from_sym(mats: FloatArray) -> FloatArray:
    """(k, d, d) -> (k, d(d+1)/2) upper-triangular entries, row by row."""
    iu = np.triu_indices(mats.shape[-1])
    return np.ascontiguousarray(mats[:, iu[0], iu[1]])


def upper_matrix(vals: FloatArray, d: int) -> FloatArray:
    """(k, d(d+1)/2) entries, row by row -> (k, d, d) upper-triangular matrix (zeros below)."""
    iu = np.triu_indices(d)
    out = np.zeros((vals.shape[0], d, d))
    out[:, iu[0], iu[1]] = vals
    return out


def nearest_spd(mats: FloatArray) -> FloatArray:
    """(k, d, d) symmetric -> the nearest (Frobenius) symmetric matrices with eigenvalues >= the
    floor ``NEAREST_SPD_FLOOR * max |eigenvalue|`` (``NEAREST_SPD_FLOOR`` for a zero matrix).

    Eigenvalues above the floor and the eigenvectors are kept; the result is exactly symmetric.
    """
    sym = 0.5 * (mats + np.swapaxes(mats, 1, 2))
    lam, vec = np.linalg.eigh(sym)
    scale = np.abs(lam).max(axis=1)
    floor = np.where(scale > 0.0, NEAREST_SPD_FLOOR * scale, NEAREST_SPD_FLOOR)
    lam = np.maximum(lam, floor[:, None])
    out = (vec * lam[:, None, :]) @ np.swapaxes(vec, 1, 2)
    res: FloatArray = 0.5 * (out + np.swapaxes(out, 1, 2))
    return res


#: :func:`spd_filter` computes eigenvalues of this many matrices at a time.
_EIG_CHUNK = 65536


def spd_filter(src: Source, mats: FloatArray, line_nos: IntArray, kind: str,
               what: str = "information matrix", hint: str = "",
               ) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Check the information matrices of ``kind`` lines (e.g. ``"EDGE_SE2"``).

    Entries beyond :data:`MAX_INFORMATION` (they would overflow when squared) always raise at
    their line.  Matrices that are not positive definite
    (smallest eigenvalue not > 0, :func:`hybridpgo.graph.check_information`'s criterion) raise
    at the first such line, with their count, unless ``src.fix_information`` says to project
    them (:func:`nearest_spd`) or to drop them; either is warned about once, with the count.

    Returns
    -------
    mats : (k, d, d)
        The matrices, repaired where needed (the input when nothing was).
    keep : (k,) bool
        False for the lines to drop.
    """
    k = mats.shape[0]
    keep = np.ones(k, bool)
    if k == 0:
        return mats, keep
    flat = mats.reshape(k, -1)
    big = np.maximum(flat.max(axis=1), -flat.min(axis=1))  # max |entry|, NaN kept; no |mats| copy
    limit = MAX_INFORMATION
    over = np.nonzero(~(big <= limit))[0]
    if over.size:
        j = int(over[np.argmin(line_nos[over])])
        size = (f"an entry of magnitude {big[j]:.3g}" if np.isfinite(big[j])
                else "entries that overflow float64")
        raise src.error(int(line_nos[j]), f"{what} is too large: {size}; at most {limit:.3g} is "
                        f"supported (larger values overflow when squared){hint}")
    eig_min = np.concatenate([np.linalg.eigvalsh(mats[i:i + _EIG_CHUNK])[:, 0]
                              for i in range(0, k, _EIG_CHUNK)])  # bounded LAPACK copies
    bad = np.nonzero(~(eig_min > 0.0))[0]
    if bad.size == 0:
        return mats, keep
    bad = bad[np.argsort(line_nos[bad], kind="stable")]
    lines = list_lines(line_nos[bad])
    count = f"{bad.size} of {k} {kind} lines"
    policy = src.fix_information
    if policy is None:
        j = int(bad[0])
        raise src.error(int(line_nos[j]), f"{what} is not positive definite (smallest "
                        f"eigenvalue {eig_min[j]:.6g}){hint}; {count} have such information "
                        f"({lines}); pass {option_hint('fix_information', *FIX_INFORMATION)} "
                        "to project them onto the nearest positive definite matrix or to drop "
                        "them")
    if policy == "nearest":
        mats = np.array(mats, copy=True)
        mats[bad] = nearest_spd(mats[bad])
        done = (f"projected onto the nearest positive definite matrix (eigenvalues clipped at "
                f"{NEAREST_SPD_FLOOR:g} x the largest)")
    else:
        keep[bad] = False
        done = "dropped them"
    warnings.warn(f"{src.path}: {count} have information that is not positive definite "
                  f"({lines}); {done}", UserWarning, stacklevel=2)
    return mats, keep


# =========================================================================== rotations
def rot_z(theta: FloatArray) -> FloatArray:
    """(k,) yaw angles -> (k, 3, 3) rotations about z."""
    c, s = np.cos(theta), np.sin(theta)
    r = np.zeros((theta.shape[0], 3, 3))
    r[:, 0, 0] = c
    r[:, 0, 1] = -s
    r[:, 1, 0] = s
    r[:, 1, 1] = c
    r[:, 2, 2] = 1.0
    return r


def yaw_of(r: FloatArray) -> FloatArray:
    """(k, 3, 3) planar rotations -> (k,) yaw angles in (-pi, pi]."""
    return np.arctan2(r[:, 1, 0], r[:, 0, 0])


# =========================================================================== assembly
@dataclass(slots=True)
class Parts:
    """What a format reader extracted, in file ids, before the id -> index mapping."""

    is_2d: bool
    vertex_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    vertex_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    vertex_rotations: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    vertex_translations: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    edge_ids: IntArray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    edge_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    edge_rotations: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    edge_translations: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    edge_information: FloatArray = field(default_factory=lambda: np.zeros((0, 6, 6)))
    gps_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    gps_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    gps_positions: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    gps_information: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    fix_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    fix_lines: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))


def drop_edges(p: Parts, keep: npt.NDArray[np.bool_]) -> None:
    """Keep only the relative edges where ``keep`` is True."""
    p.edge_ids, p.edge_lines = p.edge_ids[keep], p.edge_lines[keep]
    p.edge_rotations, p.edge_translations = p.edge_rotations[keep], p.edge_translations[keep]
    p.edge_information = p.edge_information[keep]


def drop_gps(p: Parts, keep: npt.NDArray[np.bool_]) -> None:
    """Keep only the position priors where ``keep`` is True."""
    p.gps_ids, p.gps_lines = p.gps_ids[keep], p.gps_lines[keep]
    p.gps_positions, p.gps_information = p.gps_positions[keep], p.gps_information[keep]


def check_duplicate_vertices(src: Source, ids: IntArray, line_nos: IntArray) -> None:
    """Raise at the second definition of a vertex id, naming the first line."""
    if ids.shape[0] < 2:
        return
    _, first = np.unique(ids, return_index=True)
    if first.shape[0] == ids.shape[0]:
        return
    dup = np.ones(ids.shape[0], bool)
    dup[first] = False
    k = int(np.nonzero(dup)[0][np.argmin(line_nos[dup])])
    earlier = int(line_nos[np.nonzero(ids == ids[k])[0]].min())
    tag = src.lines[int(line_nos[k]) - 1].split()[0]
    raise src.error(int(line_nos[k]), f"duplicate vertex id {int(ids[k])} ({tag}); it was "
                    f"already defined at line {earlier}")


def check_self_loops(src: Source, edge_ids: IntArray, line_nos: IntArray) -> None:
    loops: npt.NDArray[np.intp] = (
        np.nonzero(edge_ids[:, 0] == edge_ids[:, 1])[0] if edge_ids.size else np.zeros(0, np.intp)
    )
    if len(loops):
        k = int(loops[0])
        tag = src.lines[int(line_nos[k]) - 1].split()[0]
        raise src.error(int(line_nos[k]), f"{tag} connects vertex {int(edge_ids[k, 0])} to "
                        "itself (self-loop)")


def _check_known(src: Source, node_ids: IntArray, ids: IntArray, line_nos: IntArray,
                 cols: int) -> None:
    """Raise at the first line (in file order) naming an id that has no vertex line."""
    if ids.size == 0:
        return
    flat = ids.reshape(-1)
    pos = np.searchsorted(node_ids, flat).clip(0, node_ids.shape[0] - 1)
    unknown = (node_ids[pos] != flat).reshape(-1, cols).any(axis=1)
    if unknown.any():
        rows = np.nonzero(unknown)[0]
        k = int(rows[np.argmin(line_nos[rows])])
        row = ids.reshape(-1, cols)[k]
        missing = int(row[~np.isin(row, node_ids)][0])
        tag = src.lines[int(line_nos[k]) - 1].split()[0]
        raise src.error(int(line_nos[k]), f"{tag} refers to vertex {missing}, which no vertex "
                        "line defines")


def assemble(src: Source, fmt: str, parts: Parts, check_connected: bool) -> PoseGraph:
    """Map file ids to dense indices, run the file-level checks, build the :class:`PoseGraph`."""
    p = parts
    has_vertices = p.vertex_ids.shape[0] > 0
    if not has_vertices and p.edge_ids.shape[0] == 0 and p.gps_ids.shape[0] == 0:
        raise src.error(None, "empty file: no vertex or edge lines found")
    check_self_loops(src, p.edge_ids, p.edge_lines)
    if has_vertices:
        check_duplicate_vertices(src, p.vertex_ids, p.vertex_lines)
        order = np.argsort(p.vertex_ids, kind="stable")
        node_ids = p.vertex_ids[order]
        rotations = p.vertex_rotations[order]
        translations = p.vertex_translations[order]
        _check_known(src, node_ids, p.edge_ids, p.edge_lines, 2)
        _check_known(src, node_ids, p.gps_ids, p.gps_lines, 1)
        _check_known(src, node_ids, p.fix_ids, p.fix_lines, 1)
    else:
        node_ids = np.unique(np.concatenate([p.edge_ids.reshape(-1), p.gps_ids, p.fix_ids]))
        n = node_ids.shape[0]
        rotations = np.broadcast_to(np.eye(3), (n, 3, 3))
        translations = np.zeros((n, 3))
    # Safety net with line numbers: the readers check the file's own matrices; this checks the
    # converted ones with PoseGraph's criterion, so PoseGraph never rejects them without a line.
    p.edge_information, keep = spd_filter(src, p.edge_information, p.edge_lines, "edge",
                                          "information matrix converted to (rho, phi)")
    if not keep.all():
        drop_edges(p, keep)
    p.gps_information, keep = spd_filter(src, p.gps_information, p.gps_lines, "position prior")
    if not keep.all():
        drop_gps(p, keep)
    _, first = np.unique(p.fix_ids, return_index=True)
    fix_ids = p.fix_ids[np.sort(first)]  # first mention order, no repeats
    try:
        graph = PoseGraph(
            node_ids=node_ids, rotations=rotations, translations=translations,
            edge_nodes=np.searchsorted(node_ids, p.edge_ids).astype(np.int32).reshape(-1, 2),
            edge_rotations=p.edge_rotations, edge_translations=p.edge_translations,
            edge_information=p.edge_information,
            gps_nodes=np.searchsorted(node_ids, p.gps_ids).astype(np.int32),
            gps_positions=p.gps_positions, gps_information=p.gps_information,
            fixed_nodes=np.searchsorted(node_ids, fix_ids).astype(np.int32),
            is_2d=p.is_2d, has_estimates=has_vertices, source_format=fmt,
            edge_lines=p.edge_lines, gps_lines=p.gps_lines,
        )
        if check_connected:
            graph.check_connected(source="the graph")
    except GraphError as exc:
        raise src.error(None, str(exc)) from exc
    return graph


# =========================================================================== writing
def fmt_floats(rows: FloatArray) -> list[str]:
    """Each row of a (k, n) array as space-separated ``repr`` floats (round-trip exact)."""
    return [" ".join(map(repr, row)) for row in np.asarray(rows, np.float64).tolist()]


def write_atomic(path: PathLike, produce: Callable[[], Iterable[str]]) -> None:
    """Write the lines ``produce()`` yields to ``path`` so that a reader never sees half a file.

    The rules of :mod:`hybridpgo._output` apply: a regular file (or a new one) is written to a
    temporary file in the same directory, then renamed over ``path``, keeping its permissions;
    a symbolic link is written through (its target is replaced); a FIFO or character device
    (``/dev/null``) is written into; a directory, socket or block device is refused.  ``"-"``
    (and ``/dev/stdout``) writes to standard output (:data:`STDOUT_TARGET`).

    The lines are produced completely before anything is created; if anything fails nothing is
    written (an existing ``path`` is left untouched).  OS errors become :class:`FormatError`
    naming the file.
    """
    write_atomic_all([(path, list(produce()))])


def write_atomic_all(items: Sequence[tuple[PathLike, Sequence[str]]]) -> None:
    """Write several files all or nothing (:class:`hybridpgo._output.Outputs`): every temporary
    file is written first, then all are moved into place (as :func:`write_atomic`, which is the
    one-file case).  Standard output is written last."""
    to_stdout = [lines for path, lines in items if os.fspath(path) in STDOUT_NAMES]
    files = [(os.fspath(path), lines) for path, lines in items
             if os.fspath(path) not in STDOUT_NAMES]
    with Outputs([name for name, _ in files]) as out:
        for name, lines in files:
            try:
                with open(out.temp(name), "w", encoding="utf-8", newline="\n") as fh:
                    for line in lines:
                        fh.write(line)
                        fh.write("\n")
            except OSError as exc:
                raise FormatError(f"cannot write the file: {exc.strerror or exc}", name) from exc
        out.commit()
    for lines in to_stdout:
        stream = STDOUT_TARGET.get() or sys.stdout
        stream.write("".join(line + "\n" for line in lines))
        stream.flush()


def require_planar(graph: PoseGraph, path: str, fmt: str) -> None:
    """Raise unless every pose and measurement of a 2D graph is planar (z = roll = pitch = 0)."""
    tol = 1e-9
    for what, r, t in (("pose", graph.rotations, graph.translations),
                       ("edge", graph.edge_rotations, graph.edge_translations)):
        if r.shape[0] == 0:
            continue
        off = np.abs(np.stack([r[:, 0, 2], r[:, 1, 2], r[:, 2, 0], r[:, 2, 1],
                               r[:, 2, 2] - 1.0], axis=1)).max(axis=1)
        zoff = np.abs(t[:, 2]) / (1.0 + np.abs(t).max(axis=1))
        bad = np.nonzero((off > tol) | (zoff > tol))[0]
        if bad.size:
            k = int(bad[0])
            label = (f"pose {int(graph.node_ids[k])}" if what == "pose" else f"edge {k} "
                     f"({int(graph.node_ids[graph.edge_nodes[k, 0]])} -> "
                     f"{int(graph.node_ids[graph.edge_nodes[k, 1]])})")
            raise FormatError(f"cannot write the 2D graph as {fmt} SE(2) lines: {label} is not "
                              f"planar (z = {t[k, 2]:.3g}, out-of-plane rotation {off[k]:.3g})",
                              path)



def require_readable_information(graph: PoseGraph, mats: FloatArray, path: str,
                                 fmt: str) -> None:
    """Raise unless ``mats`` -- the information exactly as the reader will compute it from the
    written text (the planar 3x3 block of a 2D graph, iSAM's ``R^T R``) -- passes the reader's
    checks, including the lift of a 3x3 to 6x6.

    A matrix at the edge of positive definiteness (smallest eigenvalue ~1e-16 of the largest)
    can lose it to the rounding of a conversion; the file would then not read back.
    """
    if mats.shape[0] == 0:
        return
    checks = [mats] if mats.shape[-1] == 6 else [mats, lift_information_2d(mats)]
    for m in checks:
        big = np.abs(m).reshape(m.shape[0], -1).max(axis=1)
        with np.errstate(invalid="ignore"):
            eig_min = np.where(big <= MAX_INFORMATION,
                               np.linalg.eigvalsh(np.where((big <= MAX_INFORMATION)[:, None, None],
                                                           m, 1.0))[:, 0], -np.inf)
        bad = np.nonzero(~(eig_min > 0.0))[0]
        if bad.size:
            k = int(bad[0])
            a, b = graph.node_ids[graph.edge_nodes[k]].tolist()
            raise FormatError(f"edge {k} ({a} -> {b}): its information matrix is so close to "
                              f"singular that it would not read back positive definite from "
                              f"{fmt} (smallest eigenvalue {eig_min[k]:.3g} after the "
                              "conversion)" + ("; write g2o or TORO instead, which store the "
                                               "matrix itself" if fmt == "iSAM" else ""), path)


def write_vertices_needed(graph: PoseGraph) -> bool:
    """True when vertex lines must be written (estimates, or a node no constraint mentions).

    A graph without estimates (read from iSAM or an edges-only file) is written without vertex
    lines, so that reading the file back gives the same graph (``has_estimates`` False).
    """
    if graph.has_estimates:
        return True
    used = np.zeros(graph.num_nodes, bool)
    used[graph.edge_nodes.reshape(-1)] = True
    used[graph.gps_nodes] = True
    used[graph.fixed_nodes] = True
    return not bool(used.all())
