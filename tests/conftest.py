"""Shared fixtures; keep this file small (docs/contributing.md#tests)."""

from __future__ import annotations

from pathlib import Path

import pytest

#: Small graph files with provenance (tests/data/README.md); tests never read anything else.
DATA_DIR = Path(__file__).parent / "data"


@pytest.fixture
def data_dir() -> Path:
    """Directory of the committed test graphs."""
    return DATA_DIR


@pytest.fixture
def tiny(data_dir: Path) -> Path:
    """The smallest committed 3D graph (9 poses)."""
    return data_dir / "tinyGrid3D.g2o"
