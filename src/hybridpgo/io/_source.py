"""A file's lines as the readers see them: the bytes read once (a path or standard input), split
into numbered lines, each line's tag separated from the rest; the limits of what a message
echoes; the information policies a reader accepts (docs/contributing.md#errors)."""

from __future__ import annotations

import contextvars
import os
import sys
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import IO

import numpy as np
import numpy.typing as npt

from ..errors import FormatError

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
#: ... and never below this absolute value: a floor of 1e-9 x the largest eigenvalue of a
#: matrix of subnormal entries (1e-320) underflows to 0, and eigenvalues this far above the
#: smallest normal float64 (2.2e-308) stay positive through the rounding of the result.
NEAREST_SPD_MIN = 1e-300

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
    number would be off.  A byte-order mark at the start of the text (U+FEFF, which some
    Windows editors write) is dropped.
    """
    if text.startswith("\ufeff"):
        text = text[1:]
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    return lines


def read_bytes(path: PathLike) -> tuple[str, bytes]:
    """(name for messages, content) of ``path``; ``"-"`` reads standard input."""
    name = os.fspath(path)
    if name == STDIO:
        stream = sys.stdin
        if stream is None:  # started with standard input closed ("<&-")
            raise FormatError("cannot read: standard input is closed", STDIN_NAME)
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
