"""The only place Numba options live (STYLE.md §3).

``kernel`` is the decorator every hot loop uses.  ``fastmath`` stays off: it breaks NaN checks
and bit-reproducibility.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numba

F = TypeVar("F", bound=Callable[..., Any])

_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}


def kernel(fn: F) -> F:
    """Compile ``fn`` with the project's Numba options (typed once here for mypy)."""
    return numba.njit(**_OPTIONS)(fn)  # type: ignore[no-any-return]
