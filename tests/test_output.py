"""The output rules every writer shares (``hybridpgo._output``): temporary file + rename,
symbolic links written through, FIFOs and devices written into or refused, directories refused,
names at the file system's length limit, nothing left behind after a failure."""

from __future__ import annotations

import os
import stat
import threading
from pathlib import Path
from typing import IO

import pytest

from hybridpgo._output import Outputs, check_output, name_max, same_file, write_file
from hybridpgo.errors import FormatError


def _writer(data: bytes):  # type: ignore[no-untyped-def]
    def write(fh: IO[bytes]) -> None:
        fh.write(data)
    return write


def _entries(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


def test_new_and_existing_files_keep_permissions(tmp_path: Path) -> None:
    out = tmp_path / "a.bin"
    write_file(out, _writer(b"one"))
    assert out.read_bytes() == b"one"
    out.chmod(0o640)
    write_file(out, _writer(b"two"))
    assert out.read_bytes() == b"two"
    assert stat.S_IMODE(out.stat().st_mode) == 0o640
    assert _entries(tmp_path) == ["a.bin"]


def test_a_symlink_is_written_through(tmp_path: Path) -> None:
    target = tmp_path / "target.bin"
    target.write_bytes(b"old")
    link = tmp_path / "link.bin"
    link.symlink_to(target)
    write_file(link, _writer(b"new"))
    assert link.is_symlink() and target.read_bytes() == b"new"
    dangling = tmp_path / "dangling.bin"
    dangling.symlink_to(tmp_path / "created.bin")
    write_file(dangling, _writer(b"made"))
    assert dangling.is_symlink() and (tmp_path / "created.bin").read_bytes() == b"made"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
def test_a_fifo_is_written_into_or_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(FormatError, match=r"pipe: cannot write the file: it is a FIFO"):
        write_file(fifo, _writer(b"x"), streams=False)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    write_file(fifo, _writer(b"streamed"))
    reader.join(timeout=30)
    assert got == [b"streamed"]
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still a FIFO, not replaced by a file


def test_a_device_is_written_into_or_refused() -> None:
    write_file(os.devnull, _writer(b"x"))
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)
    with pytest.raises(FormatError, match=r"cannot write the file: it is a device"):
        write_file(os.devnull, _writer(b"x"), streams=False)


def test_a_directory_and_a_missing_directory_are_refused(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"cannot write the file: it is a directory"):
        write_file(tmp_path, _writer(b"x"))
    with pytest.raises(FormatError, match=r"directory .*missing does not exist"):
        write_file(tmp_path / "missing" / "a.bin", _writer(b"x"))
    with pytest.raises(FormatError, match=r"the output path is empty"):
        write_file("", _writer(b"x"))


def test_a_name_at_the_length_limit_is_written(tmp_path: Path) -> None:
    longest = "n" * (name_max(str(tmp_path)) - 4) + ".g2o"
    out = tmp_path / longest
    check_output(out)
    write_file(out, _writer(b"long"))
    assert out.read_bytes() == b"long"
    assert _entries(tmp_path) == [longest]
    wide = "\u00e9" * ((name_max(str(tmp_path)) - 4) // 2) + ".g2o"  # two bytes a character
    write_file(tmp_path / wide, _writer(b"wide"))
    assert (tmp_path / wide).read_bytes() == b"wide"
    with pytest.raises(FormatError, match=r"cannot write the file: File name too long"):
        write_file(tmp_path / ("n" + longest), _writer(b"x"))


@pytest.mark.parametrize("error", [OSError, KeyboardInterrupt, ValueError])
def test_a_failed_write_leaves_nothing_and_keeps_the_old_file(tmp_path: Path,
                                                              error: type[BaseException]) -> None:
    out = tmp_path / "a.bin"
    out.write_bytes(b"old")

    def failing(fh: IO[bytes]) -> None:
        fh.write(b"half")
        raise error(28, "No space left on device") if error is OSError else error()

    with pytest.raises(FormatError if error is OSError else error):
        write_file(out, failing)
    assert out.read_bytes() == b"old"
    assert _entries(tmp_path) == ["a.bin"]


def test_outputs_are_all_or_nothing(tmp_path: Path) -> None:
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    b.write_text("old")
    with Outputs([a, b]) as out:
        Path(out.temp(str(a))).write_text("A")
        Path(out.temp(str(b))).write_text("B")
        # not committed: an exception here leaves both untouched
    assert not a.exists() and b.read_text() == "old"
    assert _entries(tmp_path) == ["b.txt"]
    with Outputs([a, b]) as out:
        Path(out.temp(str(a))).write_text("A")
        Path(out.temp(str(b))).write_text("B")
        out.commit()
    assert a.read_text() == "A" and b.read_text() == "B"
    assert _entries(tmp_path) == ["a.txt", "b.txt"]


def test_two_names_of_one_file_are_refused(tmp_path: Path) -> None:
    a = tmp_path / "a.txt"
    a.write_text("x")
    (tmp_path / "hard.txt").hardlink_to(a)
    (tmp_path / "d").symlink_to(tmp_path)
    for other in (tmp_path / "hard.txt", tmp_path / "d" / "a.txt"):
        assert same_file(a, other)
        with pytest.raises(FormatError, match=r"name the same file"):
            Outputs([a, other])
    assert not same_file(a, tmp_path / "b.txt")
