"""Running the command line in tests."""

from __future__ import annotations

import pytest

from hybridpgo.cli import main


def run_cli(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    """``main(argv)`` (arguments turned into strings) with the captured (stdout, stderr)."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err
