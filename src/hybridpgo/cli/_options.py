"""Option types and shared option groups of the ``hybridpgo`` command line: the choice lists
(looked up lazily, from the lists the library validates against), the numeric and id types
that make a bad value a usage error naming the option, and the options several commands share."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from ._common import LazyChoices


# --------------------------------------------------------------------------- real choice lists
def _formats() -> list[str]:
    from ..io import FORMATS

    return list(FORMATS)


def _write_formats() -> list[str]:
    from ..io import WRITE_FORMATS

    return list(WRITE_FORMATS)


def _fix_policies() -> list[str]:
    from ..io import FIX_INFORMATION

    return list(FIX_INFORMATION)


def methods() -> list[str]:
    from ..solvers import METHODS

    return list(METHODS)


def steps() -> list[str]:
    from ..solvers.config import STEP_NAMES

    return list(STEP_NAMES)


def trees() -> list[str]:
    from ..solvers import TREES

    return list(TREES)


def inits() -> list[str]:
    from ..initialization import InitKind

    return [k.value for k in InitKind]


def presets() -> list[str]:
    from ..generate import PRESETS

    return sorted(PRESETS)


def grid_presets() -> list[str]:
    from ..generate import GRID_PRESETS

    return list(GRID_PRESETS)


def solver_defaults() -> tuple[Any, Any]:
    """Default configs, so that --help shows the solvers' real defaults."""
    from ..solvers import GaussNewtonConfig, HybridConfig

    return HybridConfig(), GaussNewtonConfig()


def auto_defaults() -> Any:
    """The default pipeline's config, so that --help shows its real defaults."""
    from ..solvers import AutoConfig

    return AutoConfig()


# --------------------------------------------------------------------------- value checks
def number(kind: Callable[[str], float | int], test: Callable[[float], bool],
            what: str) -> Callable[[str], float | int]:
    def convert(text: str) -> float | int:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
        if not (math.isfinite(value) and test(value)):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    convert.__name__ = what  # shown by argparse in "invalid <name> value" messages
    return convert


nonneg_int = number(int, lambda v: v >= 0, "an integer >= 0")
pos_int = number(int, lambda v: v >= 1, "an integer >= 1")
any_int = number(int, lambda v: True, "an integer")
nonneg_float = number(float, lambda v: v >= 0, "a number >= 0")
pos_float = number(float, lambda v: v > 0, "a number > 0")
decay = number(float, lambda v: 0 < v <= 1, "a number in (0, 1]")
#: --sweeps and --tau0 bounds: the library's (solvers.config.MAX_SWEEPS, MAX_TAU), repeated
#: here to keep the parser light; tests/test_cli.py checks that they agree.
MAX_SWEEPS = 1_000_000
MAX_TAU = 2.0
sweeps = number(int, lambda v: 0 <= v <= MAX_SWEEPS, f"an integer in 0..{MAX_SWEEPS}")
tau = number(float, lambda v: 0 < v < MAX_TAU, f"a number in (0, {MAX_TAU:g})")
#: Largest ``plot --dpi`` (the same as ``hybridpgo.plot.MAX_DPI``; not imported, to keep the
#: parser light).  A 2x2-panel figure at 600 dpi is ~7800 x 7200 pixels (~225 MB to render).
MAX_DPI = 600
dpi = number(int, lambda v: 1 <= v <= MAX_DPI, f"an integer in 1..{MAX_DPI}")

#: How outputs are written, for the help of every command that writes a file.
OUTPUT_HELP = ("Outputs are checked before any work and written atomically (temporary file, then "
               "rename), so a command writes all its files or none; an output may not be one of "
               "the inputs.  A symbolic link is written through (its target is replaced, the "
               "link kept); a FIFO or character device (/dev/null) is written directly.")


def pose_ids(text: str) -> tuple[int, ...] | str:
    """``--covariance-poses``: ``all``, or ids and inclusive ranges ``A..B``, comma-separated."""
    if text.strip() == "all":
        return "all"
    ids: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("..")
        try:
            first = int(lo)
            last = int(hi) if sep else first
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be 'all' or pose ids and ranges like 0,5,10..20, got {text!r}") from None
        if last < first or last - first >= 100_000_000:
            raise argparse.ArgumentTypeError(f"bad range {part.strip()!r} in {text!r}")
        ids.extend(range(first, last + 1))
    return tuple(dict.fromkeys(ids))


pose_ids.__name__ = "IDS"


probability = number(float, lambda v: 0 <= v <= 1, "a number in [0, 1]")
at_least_2 = number(int, lambda v: v >= 2, "an integer >= 2")


def robust(text: str) -> tuple[str, float | None]:
    """``auto``, ``none`` or ``NAME[:SCALE]`` of ``--robust`` -> (name, delta or None for the
    kernel's default)."""
    from ..solvers.config import ROBUST_CHOICES

    name, sep, scale = text.partition(":")
    if name not in ROBUST_CHOICES:
        raise argparse.ArgumentTypeError(
            f"must be auto, none or a kernel ({', '.join(ROBUST_CHOICES[2:])}, optionally "
            f"NAME:SCALE), got {name!r}")
    if not sep:
        return name, None
    if name in ("auto", "none"):
        raise argparse.ArgumentTypeError(f"{name} takes no scale, got {text!r}")
    return name, float(pos_float(scale))


robust.__name__ = "NAME[:SCALE]"


# --------------------------------------------------------------------------- parser
def add_format(p: argparse.ArgumentParser, *, out: bool = False) -> None:
    p.add_argument("--format", choices=LazyChoices(_formats),
                   help="input format (default: detected from the content)")
    if out:
        p.add_argument("--out-format", choices=LazyChoices(_write_formats),
                       help="output format (default: from the output's extension, .tum -> tum, "
                            "else the input's format); tum writes the poses only")
    p.add_argument("--fix-information", choices=LazyChoices(_fix_policies),
                   help="information matrices that are not positive definite: 'nearest' "
                        "projects each onto the nearest positive definite matrix (eigenvalues "
                        "clipped at 1e-9 x the largest), 'skip' drops those constraints; both "
                        "warn with the count (default: error)")


def add_common(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: "hybridpgo --debug CMD" and "hybridpgo CMD --debug" both work
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show a traceback for every error")


def add_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--progress", action="store_true",
                   help="draw progress even when stderr is not a terminal (default: only on a "
                        "terminal; --quiet turns it off)")


def add_generate_common(p: argparse.ArgumentParser, kind: str) -> None:
    """Outliers, seed and outputs of ``generate city`` and ``generate grid``."""
    p.add_argument("--outliers", type=nonneg_int, default=0, metavar="N",
                   help="add N false loop closures with the information of real ones: random "
                        "pose pairs and near misses (poses a few metres apart with a wrong "
                        "relative pose) (default 0)")
    p.add_argument("--near-miss-fraction", type=probability, metavar="F",
                   help="fraction of the outliers that are near misses (default 0.5)")
    p.add_argument("--outlier-pattern", default="mixed",
                   choices=("mixed", "random", "local", "random-grouped", "local-grouped"),
                   help="'mixed': random pairs and near misses (--near-miss-fraction); else "
                        "Suenderhauf and Protzel's patterns, every false edge claiming its two "
                        "poses are at the same place: between random poses, between a pose and "
                        "one of the 20 after it ('local'), or in groups of 10 consecutive "
                        "mutually consistent edges (default mixed)")
    p.add_argument("--outliers-out", metavar="CSV",
                   help="where to list the false edges: CSV with columns edge_index (0-based "
                        "among the file's edge lines), id_a, id_b, kind (random, near_miss or "
                        "aliased_<pattern>), true_distance_m (default with --outliers: GT, else "
                        "OUT, with its extension replaced by .outliers.csv)")
    p.add_argument("--seed", type=any_int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="graph file to write (g2o, or TORO for a .graph name; vertices are the "
                        "noisy odometry chained from the true first pose)")
    p.add_argument("--ground-truth", metavar="GT",
                   help="also write the ground truth: the same graph with the true poses as "
                        "vertices (g2o)")
    add_common(p)
    p.set_defaults(command="generate", kind=kind)
