"""Benchmark measurements and their JSON / Markdown output (docs/contributing.md#benchmarks)."""

from __future__ import annotations

import json
import os
import pathlib
import platform
import tempfile
from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class Metric:
    """One measurement with a stable key, e.g. ``garage.hybrid.us_per_constraint``."""

    key: str
    value: float
    unit: str
    direction: str = "lower"
    """'lower' or 'higher' is better; 'info' is never gated."""
    rel_tol: float = 0.0
    abs_tol: float = 0.0
    note: str = ""

    def regressed(self, base: float) -> bool:
        slack = max(self.rel_tol * abs(base), self.abs_tol)
        if self.direction == "lower":
            return self.value > base + slack
        if self.direction == "higher":
            return self.value < base - slack
        return False


def quality(key: str, value: float, unit: str = "", note: str = "") -> Metric:
    """A quality number (energy, error): tight tolerance."""
    return Metric(key, float(value), unit, "lower", rel_tol=1e-3, abs_tol=1e-9, note=note)


def timing(key: str, value: float, unit: str = "s", note: str = "") -> Metric:
    """A time: loose tolerance (machines and load differ)."""
    return Metric(key, float(value), unit, "lower", rel_tol=1.0, abs_tol=1e-3, note=note)


def info(key: str, value: float, unit: str = "", note: str = "") -> Metric:
    return Metric(key, float(value), unit, "info", note=note)


def machine() -> dict[str, Any]:
    import numba
    import numpy
    import scipy

    out: dict[str, Any] = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "processor": platform.processor(),
        "cpus": os.cpu_count(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
    }
    try:
        from importlib.metadata import version

        import gtsam  # noqa: F401

        out["gtsam"] = version("gtsam")
    except ImportError:
        out["gtsam"] = None
    return out


def _atomic_write(path: pathlib.Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def write_results(
    path_stem: pathlib.Path, metrics: list[Metric], tables: list[str], command: str
) -> None:
    """Write ``<stem>.json`` (machine-readable) and ``<stem>.md`` (tables)."""
    doc = {"command": command, "machine": machine(), "metrics": [asdict(m) for m in metrics]}
    _atomic_write(path_stem.with_suffix(".json"), json.dumps(doc, indent=1) + "\n")
    md = [
        f"# Benchmark results\n\nCommand: `{command}`\n",
        "Machine: " + ", ".join(f"{k} {v}" for k, v in doc["machine"].items()) + "\n",
    ]
    md.extend(tables)
    _atomic_write(path_stem.with_suffix(".md"), "\n".join(md) + "\n")


def markdown_table(title: str, header: list[str], rows: list[list[Any]]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            if v == 0 or 1e-3 <= abs(v) < 1e6:
                return f"{v:.6g}"
            return f"{v:.4g}"
        return str(v)

    lines = [
        f"## {title}\n",
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
