"""How every file hybridpgo writes reaches its path: one set of rules for all writers.

Graph files, CSV and JSON tables, figures, covariance archives, Rerun recordings and online
solver states are all written through :class:`Outputs` (or its one-file shortcut
:func:`write_file`):

* **Regular file or new name**: the content goes to a temporary file in the same directory,
  which is then renamed over the name (``os.replace``): a reader never sees half a file, and a
  failure or an interruption (Ctrl-C, SIGTERM) leaves what was there untouched and removes the
  temporary file.  An existing file keeps its permissions; a new one gets ``0o666`` minus the
  umask, as ``open`` would give it.
* **Symbolic link**: written through.  The file it points to is replaced as above (a dangling
  link creates its target) and the link stays a link, as with ``cp`` or a shell's ``>``.
* **FIFO or character device** (``/dev/null``, a terminal): it cannot be replaced, so the
  content is written into it once complete (with ``streams=False``: refused).
* **Directory, socket, block device**: refused.
* **Names**: the temporary file's name is a shortened copy of the output's, so it fits the file
  system's limit on name length (``NAME_MAX``) whatever the output's name.

Every problem is a :class:`~hybridpgo.errors.FormatError` naming the path.  The command line
checks its outputs before any work with :func:`check_output`, which creates and removes the
same temporary file the writer will create.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import IO

from .errors import FormatError

PathLike = str | os.PathLike[str]

#: Suffix of temporary files (they also start with a dot: hidden from ``ls``).
TEMP_SUFFIX = ".tmp"
#: ``tempfile.mkstemp`` adds this many random characters to a temporary file's name.
_RANDOM_CHARS = 8
#: The name length limit assumed when the file system does not report one.
_DEFAULT_NAME_MAX = 255


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: The process umask, read once at import (``os.umask`` can only be read by setting it).
UMASK = _current_umask()


@dataclass(frozen=True, slots=True)
class Target:
    """Where an output goes (see :func:`resolve`)."""

    name: str
    """The path as given (used in messages)."""
    path: str
    """The file that is replaced or written into: ``name``, or a symbolic link's target."""
    kind: str
    """``"new"`` (nothing there, or a dangling link), ``"file"`` (a regular file) or
    ``"stream"`` (a FIFO or a character device: written into, never replaced)."""
    mode: int
    """Permission bits the written file gets (an existing file's own)."""


def _error(name: str, exc: OSError | str) -> FormatError:
    why = exc if isinstance(exc, str) else (exc.strerror or str(exc))
    return FormatError(f"cannot write the file: {why}", name)


def name_max(directory: str) -> int:
    """The longest file name (in bytes) the file system of ``directory`` allows."""
    try:
        return int(os.pathconf(directory, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return _DEFAULT_NAME_MAX


def resolve(path: PathLike, *, streams: bool = True) -> Target:
    """Check that ``path`` can be written under the rules of this module; where it goes.

    Raises
    ------
    FormatError
        An empty path; a directory, socket or block device (or, with ``streams=False``, a
        FIFO or character device); a directory that does not exist; a path that cannot be
        examined (a name longer than the file system allows, no permission, a loop of links).
    """
    name = os.fspath(path)
    if name == "":
        raise FormatError("cannot write: the output path is empty")
    try:
        st: os.stat_result | None = os.stat(name)  # through symbolic links
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise _error(name, exc) from exc
    if st is not None:
        mode = st.st_mode
        if stat.S_ISFIFO(mode) or stat.S_ISCHR(mode):
            if not streams:
                what = "a FIFO" if stat.S_ISFIFO(mode) else "a device"
                raise _error(name, f"it is {what}, not a regular file")
            return Target(name, name, "stream", stat.S_IMODE(mode))
        if not stat.S_ISREG(mode):
            what = "a directory" if stat.S_ISDIR(mode) else "not a regular file, FIFO or device"
            raise _error(name, f"it is {what}")
    target = os.path.realpath(name) if os.path.islink(name) else name
    directory = os.path.dirname(os.path.abspath(target))
    if st is None and not os.path.isdir(directory):
        raise _error(name, f"directory {directory} does not exist")
    if st is not None:
        return Target(name, target, "file", stat.S_IMODE(st.st_mode))
    return Target(name, target, "new", 0o666 & ~UMASK)


def temp_file(target: str, *, suffix: str = TEMP_SUFFIX) -> tuple[int, str]:
    """Create a temporary file beside ``target``, named after it but short enough for the file
    system (``.<start of the name>.<random><suffix>``); returns ``(descriptor, path)``.

    Raises
    ------
    OSError
        The directory does not exist or no file can be created in it.
    """
    directory = os.path.dirname(os.path.abspath(target))
    base = os.fsencode(os.path.basename(target))
    room = name_max(directory) - len(os.fsencode(suffix)) - _RANDOM_CHARS - 2  # two dots
    stem = os.fsdecode(base[:max(room, 0)]) if room > 0 else ""
    while stem and len(os.fsencode(stem)) > room:  # a multi-byte character cut in the middle
        stem = stem[:-1]
    return tempfile.mkstemp(dir=directory, prefix=f".{stem}.", suffix=suffix)


def check_output(path: PathLike, *, streams: bool = True) -> Target:
    """:func:`resolve`, then create and remove the temporary file the writer will create (the
    real test that the directory takes a new file).  Raises :class:`FormatError`."""
    tgt = resolve(path, streams=streams)
    if tgt.kind != "stream":
        try:
            fd, probe = temp_file(tgt.path)
        except OSError as exc:
            raise _error(tgt.name, exc) from exc
        os.close(fd)
        os.unlink(probe)
    return tgt


def same_file(a: PathLike, b: PathLike) -> bool:
    """True when ``a`` and ``b`` are one file: the same device and inode (through symbolic and
    hard links), or, when one does not exist yet, the same resolved path."""
    try:
        sa, sb = os.stat(a), os.stat(b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


class Outputs:
    """Several output files written all or nothing.

    Creating the group resolves every path (:func:`resolve`), refuses two paths that are one
    file, and creates a temporary file for each (beside it; for a FIFO or device, in the
    system's temporary directory), so an output that cannot be written fails before any work.
    Write each output's content to :meth:`temp`, then :meth:`commit`: every temporary file is
    renamed into place, then the FIFOs and devices are written into.  :meth:`discard` (or
    leaving a ``with`` block without a commit, for instance by an exception or an interruption)
    removes the temporary files and leaves the outputs untouched.

    Parameters
    ----------
    paths : sequence of path-like
    streams : bool
        Write into FIFOs and character devices (True) or refuse them (False).
    """

    def __init__(self, paths: Sequence[PathLike], *, streams: bool = True) -> None:
        self.targets: list[Target] = []
        self._temps: dict[str, str] = {}
        for p in paths:
            tgt = resolve(p, streams=streams)
            for other in self.targets:
                if same_file(tgt.path, other.path):
                    raise FormatError(f"cannot write the file twice: {other.name} and "
                                      f"{tgt.name} name the same file", tgt.name)
            self.targets.append(tgt)
        try:
            for tgt in self.targets:
                try:
                    if tgt.kind == "stream":
                        fd, tmp = tempfile.mkstemp(prefix=".hybridpgo-", suffix=TEMP_SUFFIX)
                    else:
                        fd, tmp = temp_file(tgt.path)
                except OSError as exc:
                    raise _error(tgt.name, exc) from exc
                os.close(fd)
                self._temps[tgt.name] = tmp
        except BaseException:
            self.discard()
            raise

    def temp(self, name: PathLike) -> str:
        """The temporary file to write ``name``'s content to (the path given to the group)."""
        return self._temps[os.fspath(name)]

    def commit(self) -> None:
        """Move every output into place (renames first, then FIFOs and devices).

        Raises
        ------
        FormatError
            An output could not be written; the temporary files are removed.
        """
        try:
            for tgt in self.targets:
                if tgt.kind != "stream":
                    tmp = self._temps[tgt.name]
                    try:
                        os.chmod(tmp, tgt.mode)
                        os.replace(tmp, tgt.path)
                    except OSError as exc:
                        raise _error(tgt.name, exc) from exc
                    del self._temps[tgt.name]
            for tgt in self.targets:
                if tgt.kind == "stream":
                    try:
                        with open(self._temps[tgt.name], "rb") as src, \
                                open(tgt.path, "wb") as dst:
                            shutil.copyfileobj(src, dst)
                    except OSError as exc:
                        raise _error(tgt.name, exc) from exc
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove the temporary files that were not moved into place."""
        for tmp in self._temps.values():
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        self._temps.clear()

    def __enter__(self) -> Outputs:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.discard()


def write_file(path: PathLike, write: Callable[[IO[bytes]], None], *,
               streams: bool = True) -> None:
    """Write one file under the rules of this module: ``write(fh)`` receives the temporary
    file, opened for binary writing.

    Raises
    ------
    FormatError
        The path cannot be written (see :func:`resolve`), or writing failed; nothing is left
        behind and an existing file is untouched.
    """
    name = os.fspath(path)
    with Outputs([name], streams=streams) as out:
        try:
            with open(out.temp(name), "wb") as fh:
                write(fh)
        except OSError as exc:
            raise _error(name, exc) from exc
        out.commit()
