"""The argparse definition of the ``hybridpgo`` command line (STYLE.md §11).

Every ``choices=`` comes from the list the library itself validates against (formats, solvers,
step kinds, tree kinds, init kinds, city presets); they are looked up lazily so that building the
parser imports nothing heavy.  Numeric options are checked here, so a bad value is a usage error
(exit 2) naming the option.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

from ._common import LazyChoices

__all__ = ["build_parser"]


# --------------------------------------------------------------------------- real choice lists
def _formats() -> list[str]:
    from ..io import FORMATS

    return list(FORMATS)


def _methods() -> list[str]:
    from ..solvers import METHODS

    return list(METHODS)


def _steps() -> list[str]:
    from ..solvers.config import STEP_NAMES

    return list(STEP_NAMES)


def _trees() -> list[str]:
    from ..solvers import TREES

    return list(TREES)


def _inits() -> list[str]:
    from ..tree import InitKind

    return [k.value for k in InitKind]


def _presets() -> list[str]:
    from ..generate import PRESETS

    return sorted(PRESETS)


def _solver_defaults() -> tuple[Any, Any]:
    """Default configs, so that --help shows the solvers' real defaults."""
    from ..solvers import GaussNewtonConfig, HybridConfig

    return HybridConfig(), GaussNewtonConfig()


# --------------------------------------------------------------------------- value checks
def _number(kind: Callable[[str], float | int], test: Callable[[float], bool],
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


_nonneg_int = _number(int, lambda v: v >= 0, "an integer >= 0")
_pos_int = _number(int, lambda v: v >= 1, "an integer >= 1")
_any_int = _number(int, lambda v: True, "an integer")
_pos_float = _number(float, lambda v: v > 0, "a number > 0")
_nonneg_float = _number(float, lambda v: v >= 0, "a number >= 0")
_decay = _number(float, lambda v: 0 < v <= 1, "a number in (0, 1]")


# --------------------------------------------------------------------------- parser
def _add_format(p: argparse.ArgumentParser, *, out: bool = False) -> None:
    p.add_argument("--format", choices=LazyChoices(_formats),
                   help="input format (default: detected from the content)")
    if out:
        p.add_argument("--out-format", choices=LazyChoices(_formats),
                       help="output format (default: from the output's extension, else the "
                            "input's format)")


def _add_common(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: "hybridpgo --debug CMD" and "hybridpgo CMD --debug" both work
    p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                   help="show a traceback for every error")


def build_parser() -> argparse.ArgumentParser:
    """The ``hybridpgo`` argument parser; each subcommand sets ``command`` (its module name)."""
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="hybridpgo",
        description="Pose-graph optimization with the hybrid Hessian method of Grimes, Anguelov "
                    "& LeCun (IROS 2010).  Results go to stdout, progress to stderr.",
        epilog="Run 'hybridpgo demo' for a first look, 'hybridpgo COMMAND --help' for details.")
    parser.add_argument("--version", action="version", version=f"hybridpgo {__version__}")
    parser.add_argument("--debug", action="store_true", default=False,
                        help="show a traceback for every error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    # ---------------------------------------------------------------- info
    p = sub.add_parser("info", help="counts, tree statistics and energies of a graph file",
                       description="Counts by constraint type, dimension, pose-tree depth and "
                                   "constraint path lengths, and the energy at the file's "
                                   "vertices and at the tree initialization.")
    p.add_argument("file", help="pose-graph file (g2o, TORO or iSAM)")
    _add_format(p)
    p.add_argument("--tree", choices=LazyChoices(_trees), default="bfs",
                   help="spanning tree to analyze (default: bfs, the paper's)")
    p.add_argument("--skip-unknown", action="store_true",
                   help="skip lines with unsupported tags (one warning) instead of failing")
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    _add_common(p)
    p.set_defaults(command="info")

    # ---------------------------------------------------------------- optimize
    hy, gn = _solver_defaults()
    p = sub.add_parser(
        "optimize", help="optimize a graph and write the result",
        description="Optimize a pose graph with the hybrid Hessian solver (default) or the exact "
                    "sparse Levenberg-Marquardt solver, and write the optimized graph.",
        epilog="Hybrid-only options: --sweeps --tau0 --tau-decay --damping --step "
               "--gps-batch-size --polish.  --max-iterations limits the exact solver, or the "
               "polish with --polish.  --solver toro (the TORO-style baseline) takes --sweeps "
               "(its iterations, default 100), --tolerance, --init tree|file and --tree "
               "toro|bfs.")
    p.add_argument("file", help="pose-graph file (g2o, TORO or iSAM)")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="where to write the optimized graph (written atomically)")
    _add_format(p, out=True)
    p.add_argument("--solver", choices=LazyChoices(_methods), default="hybrid",
                   help="solver: 'hybrid' (the paper's), 'exact' (sparse LM), 'toro' (the "
                        "TORO-style baseline) (default: hybrid)")
    p.add_argument("--init", choices=LazyChoices(_inits),
                   help="initial poses: 'tree' concatenates the tree edges' measurements (the "
                        "paper), 'file' uses the file's vertices, 'chordal' a chordal "
                        "relaxation (default: tree for hybrid; file for exact when the file has "
                        "vertices)")
    p.add_argument("--sweeps", type=_nonneg_int, metavar="N",
                   help=f"hybrid: number of sweeps over all constraints (default {hy.sweeps})")
    p.add_argument("--tau0", type=_pos_float, metavar="TAU",
                   help=f"hybrid: initial temperature (default {hy.tau0:g})")
    p.add_argument("--tau-decay", type=_decay, metavar="F",
                   help=f"hybrid: temperature factor per sweep (default {hy.tau_decay:g})")
    p.add_argument("--damping", type=_nonneg_float, metavar="MU",
                   help="hybrid: relative damping of the hybrid Hessian blocks "
                        f"(default {hy.damping:g})")
    p.add_argument("--step", choices=LazyChoices(_steps),
                   help="hybrid: 'woodbury' solves each step in O(d), 'givens' is the paper's "
                        f"O(d^2) triangularization (default {hy.step})")
    p.add_argument("--tree", choices=LazyChoices(_trees),
                   help="spanning tree: 'bfs' breadth-first (the paper's), 'mst' "
                        f"maximum-stiffness (default {hy.tree}); 'toro': each pose hangs from "
                        "its smallest-id neighbour (--solver toro's default)")
    p.add_argument("--gps-batch-size", type=_pos_int, metavar="N",
                   help=f"hybrid: GPS constraints relaxed together (default {hy.gps_batch_size})")
    p.add_argument("--tolerance", type=_nonneg_float, metavar="TOL",
                   help="stop when an iteration lowers the energy by less than this fraction "
                        f"(hybrid default {hy.energy_tolerance:g}, where 0 runs all sweeps; "
                        f"exact default {gn.energy_tolerance:g})")
    p.add_argument("--polish", action="store_true",
                   help="hybrid: finish with the exact Levenberg-Marquardt solver")
    p.add_argument("--max-iterations", type=_nonneg_int, metavar="N",
                   help=f"iteration limit of the exact solver (default {gn.max_iterations}) or of "
                        f"the polish (default {hy.polish_iterations})")
    p.add_argument("--plot", metavar="PREFIX",
                   help="also write PREFIX_before.png, PREFIX_after.png and PREFIX_energy.png "
                        "(needs matplotlib: pip install hybridpgo[plot])")
    p.add_argument("--skip-unknown", action="store_true",
                   help="skip lines with unsupported tags (one warning) instead of failing")
    p.add_argument("--json", action="store_true",
                   help="print the summary as JSON instead of text")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_common(p)
    p.set_defaults(command="optimize")

    # ---------------------------------------------------------------- convert
    p = sub.add_parser("convert", help="convert a graph between g2o, TORO and iSAM",
                       description="Convert a graph file.  The output format comes from "
                                   "--out-format, else OUT's extension (.g2o -> g2o, .graph -> "
                                   "toro, .txt -> isam), else the input's format.")
    p.add_argument("input", metavar="IN", help="pose-graph file to read")
    p.add_argument("output", metavar="OUT", help="file to write (atomically)")
    _add_format(p, out=True)
    p.add_argument("--skip-unknown", action="store_true",
                   help="skip lines with unsupported tags (one warning) instead of failing")
    _add_common(p)
    p.set_defaults(command="convert")

    # ---------------------------------------------------------------- plot
    p = sub.add_parser(
        "plot", help="draw a graph with its constraint residuals",
        description="Draw the trajectory top-down (plus an oblique 3D view for 3D graphs) with "
                    "each constraint's residual from its desired to its actual pose, redder for "
                    "higher energy (paper Fig. 6).  With --optimized, draw before and after.")
    p.add_argument("file", help="pose-graph file (its vertices, or the tree initialization "
                                "when it has none)")
    p.add_argument("--optimized", metavar="OUT",
                   help="an optimized version of FILE (same pose ids): draw it beside FILE")
    p.add_argument("-o", "--output", required=True, metavar="FIG",
                   help="image to write (.png, .pdf, .svg; written atomically)")
    _add_format(p)
    p.add_argument("--no-residuals", action="store_true", help="draw the trajectory only")
    p.add_argument("--dpi", type=_pos_int, default=150, help="resolution (default 150)")
    _add_common(p)
    p.set_defaults(command="plot")

    # ---------------------------------------------------------------- demo
    p = sub.add_parser(
        "demo", help="optimize the bundled Manhattan graph (M3500) and write plots",
        description="Run the hybrid solver (10 sweeps, then an exact polish) on the bundled "
                    "M3500_isam.txt, the paper's Manhattan graph, from the tree initialization; "
                    "write the optimized graph and before/after/energy plots into DIR.")
    p.add_argument("-o", "--output-dir", default="hybridpgo-demo", metavar="DIR",
                   help="output directory (default: hybridpgo-demo)")
    p.add_argument("--sweeps", type=_nonneg_int, default=hy.sweeps, metavar="N",
                   help=f"hybrid sweeps before the polish (default {hy.sweeps})")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_common(p)
    p.set_defaults(command="demo")

    # ---------------------------------------------------------------- generate
    p = sub.add_parser(
        "generate", help="generate a synthetic graph with ground truth",
        description="Generate a synthetic pose graph with ground truth.  'city': a street-grid "
                    "city driven by a vehicle, with odometry, probabilistic loop closures and "
                    "optional GPS (paper Table II shapes).")
    p.add_argument("kind", choices=["city"], help="what to generate")
    p.add_argument("--preset", choices=LazyChoices(_presets),
                   help="size and shape like the paper's Table II graphs (default: the "
                        "generator's default city, 2000 poses)")
    p.add_argument("--gps-every", type=_pos_int, metavar="K",
                   help="a GPS reading on every K-th pose (default: the preset's)")
    p.add_argument("--seed", type=_any_int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="graph file to write (g2o; vertices are dead reckoning)")
    p.add_argument("--ground-truth", required=True, metavar="GT",
                   help="ground-truth poses file to write")
    _add_common(p)
    p.set_defaults(command="generate")

    # ---------------------------------------------------------------- noisify
    p = sub.add_parser(
        "noisify", help="perturb every edge rotation about its local up axis (paper Fig. 8)",
        description="Multiply every relative constraint's rotation by a rotation about the "
                    "local up (z) axis with angle ~ N(0, sigma) (paper Fig. 8).")
    p.add_argument("input", metavar="IN", help="pose-graph file to read")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="file to write (format: --out-format, else OUT's extension, else IN's)")
    _add_format(p, out=True)
    p.add_argument("--yaw-sigma-deg", type=_nonneg_float, default=3.0, metavar="DEG",
                   help="standard deviation of the yaw noise in degrees (default 3)")
    p.add_argument("--seed", type=_any_int, default=0, help="random seed (default 0)")
    _add_common(p)
    p.set_defaults(command="noisify")

    # ---------------------------------------------------------------- evaluate
    p = sub.add_parser(
        "evaluate", help="accuracy of an optimized graph against ground truth",
        description="Position RMSE, heading error (mean and max, degrees) and relative pose "
                    "error of a graph's poses against ground truth.  Without GPS the estimate "
                    "is first rigidly aligned to the ground truth; with GPS the earth frame is "
                    "absolute and no alignment is done (override with --align).")
    p.add_argument("file", metavar="OUT", help="graph file with the estimated poses")
    p.add_argument("--ground-truth", required=True, metavar="GT", help="ground-truth file")
    _add_format(p)
    p.add_argument("--align", choices=["auto", "yes", "no"], default="auto",
                   help="rigid alignment before comparing (default auto: only without GPS)")
    p.add_argument("--tum", metavar="PATH",
                   help="also write the estimate to PATH and the ground truth to "
                        "PATH_gt (TUM trajectory format, for evo)")
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    _add_common(p)
    p.set_defaults(command="evaluate")

    # ---------------------------------------------------------------- replay
    p = sub.add_parser(
        "replay", help="stream a graph frame by frame through the online solver",
        description="Replay a graph as a robot would have produced it (frames in increasing "
                    "pose id: each pose with its odometry and loop closures to earlier poses, "
                    "GPS with its pose), one online update per frame within the budget.  "
                    "Reports the latency per frame (mean, p99, max, and the steady max: CPU "
                    "time, not inflated by preemption) and the energy of the estimate over "
                    "the prefix divided by the prefix's batch optimum (exact LM).")
    p.add_argument("file", metavar="FILE", help="pose-graph file to replay")
    _add_format(p)
    p.add_argument("--budget-ms", type=_pos_float, default=5.0, metavar="B",
                   help="time budget of one frame's update in milliseconds (default 5)")
    p.add_argument("--every", type=_nonneg_int, default=500, metavar="K",
                   help="measure the accuracy every K frames and at the end (default 500; "
                        "0: only the latency, no batch optima)")
    p.add_argument("--extra-frames", type=_nonneg_int, default=100, metavar="N",
                   help="after the last frame, N more updates with the same budget and no new "
                        "data (default 100)")
    p.add_argument("--compare", choices=["isam2"],
                   help="also run GTSAM's ISAM2 on the same stream (needs hybridpgo[gtsam])")
    p.add_argument("--tree", choices=["oldest", "odometry"], default="oldest",
                   help="parent of a new pose: the oldest pose it is constrained to in its "
                        "frame (default) or its odometry parent")
    p.add_argument("--tau-old", type=_pos_float, default=0.3, metavar="T",
                   help="temperature of spare-time updates of older constraints (default 0.3)")
    p.add_argument("--local-size", type=_nonneg_int, default=0, metavar="K",
                   help="local solve: relax the K newest relative constraints together in every "
                        "frame (default 0: off)")
    p.add_argument("--plot", metavar="PREFIX",
                   help="write PREFIX_latency.png and PREFIX_energy.png (needs matplotlib)")
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _add_common(p)
    p.set_defaults(command="replay")

    return parser
