"""The argparse definition of the ``hybridpgo`` command line (docs/contributing.md#cli).

Every ``choices=`` comes from the list the library itself validates against (formats, solvers,
step kinds, tree kinds, init kinds, city presets); they are looked up lazily so that building the
parser imports nothing heavy.  Numeric options are checked here, so a bad value is a usage error
(exit 2) naming the option.
"""

from __future__ import annotations

import argparse
from typing import Any

from ._common import LazyChoices
from ._options import (
    MAX_DPI,
    MAX_TAU,
    OUTPUT_HELP,
    add_common,
    add_format,
    add_generate_common,
    add_progress,
    any_int,
    at_least_2,
    auto_defaults,
    decay,
    dpi,
    grid_presets,
    inits,
    methods,
    nonneg_float,
    nonneg_int,
    number,
    pos_float,
    pos_int,
    pose_ids,
    presets,
    probability,
    robust,
    solver_defaults,
    steps,
    sweeps,
    tau,
    trees,
)

__all__ = ["build_parser"]


def build_parser() -> argparse.ArgumentParser:
    """The ``hybridpgo`` argument parser; each subcommand sets ``command`` (its module name).

    Building it imports no solver, reader or Numba kernel: choice lists load when a value is
    checked or a command's help is shown (:class:`._common.LazyChoices`)."""
    LazyChoices.building = True
    try:
        return _build_parser()
    finally:
        LazyChoices.building = False


def _build_parser() -> argparse.ArgumentParser:
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

    _info(sub)
    _optimize(sub)
    _convert(sub)
    _plot(sub)
    _demo(sub)
    _warmup(sub)
    _generate(sub)
    _noisify(sub)
    _evaluate(sub)
    _batch(sub)
    _replay(sub)
    return parser


def _info(sub: Any) -> None:
    """The ``info`` command."""
    p = sub.add_parser("info", help="counts, tree statistics and energies of a graph file",
                       description="Counts by constraint type, dimension, pose-tree depth and "
                                   "constraint path lengths, the energy at the file's "
                                   "vertices and at the tree initialization, and the "
                                   "five constraints with the largest chi2.",
                       epilog=OUTPUT_HELP)
    p.add_argument("file", help="pose-graph file (g2o, TORO or iSAM; '-': standard input)")
    add_format(p)
    p.add_argument("--tree", choices=LazyChoices(trees), default="bfs",
                   help="spanning tree to analyze (default: bfs, the paper's)")
    p.add_argument("--skip-unknown", action="store_true",
                   help="skip lines with unsupported tags (one warning) instead of failing")
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    p.add_argument("--residuals", metavar="CSV",
                   help="write every constraint's error to CSV (at the file's vertices, or the "
                        "tree initialization when it has none): columns kind (edge or gps), "
                        "index (among that kind, in file order; lines dropped while reading "
                        "are not counted), id_a, id_b, chi2, the error e_tx e_ty e_tz e_rx "
                        "e_ry e_rz (tangent order translation, rotation; metres, radians) and "
                        "the whitened error w1..w6 (L^T e with Omega = L L^T); '-': standard "
                        "output")
    add_common(p)
    p.set_defaults(command="info")


def _optimize(sub: Any) -> None:
    """The ``optimize`` command."""
    hy, gn = solver_defaults()
    au = auto_defaults()
    p = sub.add_parser(
        "optimize", help="optimize a graph and write the result",
        description="Optimize a pose graph and write the optimized graph.  The default "
                    "(--solver auto) polishes with Levenberg-Marquardt from a certified start "
                    "where SE-Sync's certificate holds at the chordal start (no robust "
                    "kernel); otherwise it "
                    "chooses the start (chordal, tree or the file's vertices), "
                    "runs hybrid sweeps while they lower the energy by "
                    f"{au.sweep_tolerance:.0%} or more per sweep, and polishes with "
                    "Levenberg-Marquardt to convergence from each (and from each swept start's "
                    "own poses; all but the best within a budget), keeping the lowest.  "
                    "--solver hybrid is the paper's method alone, --solver exact sparse LM "
                    "from one start.",
        epilog="Hybrid-only options: --sweeps --tau0 --tau-decay --damping --step "
               "--gps-batch-size --correction --correction-iterations --monotone --polish.  "
               "--max-iterations limits the exact solver, or the "
               "polish with --polish.  --solver auto takes the hybrid options except --polish "
               "(it always polishes): --init is then the only start tried, --sweeps the most "
               f"sweeps per start (default {au.sweeps.sweeps}), --max-iterations and "
               f"--tolerance limit each polish (default {au.polish.max_iterations} and "
               f"{au.polish.energy_tolerance:g}).  --solver toro (the TORO-style baseline) "
               "takes --sweeps (its iterations, default 100), --tolerance, --init tree|file "
               "and --tree toro|bfs.  " + OUTPUT_HELP)
    p.add_argument("file", help="pose-graph file (g2o, TORO or iSAM; '-': standard input)")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="where to write the optimized graph ('-': standard output, the summary "
                        "then goes to stderr)")
    add_format(p, out=True)
    p.add_argument("--solver", choices=LazyChoices(methods), default="auto",
                   help="solver: 'auto' (start, sweeps while they pay, LM polish to "
                        "convergence), 'hybrid' (the paper's sweeps alone), 'exact' (sparse "
                        "LM), 'toro' (the TORO-style baseline) (default: auto)")
    p.add_argument("--init", choices=LazyChoices(inits),
                   help="initial poses: 'tree' concatenates the tree edges' measurements (the "
                        "paper), 'file' uses the file's vertices, 'chordal' a chordal "
                        "relaxation (default: auto tries all and keeps the best; tree for hybrid; "
                        "file for exact when the file has vertices)")
    p.add_argument("--sweeps", type=sweeps, metavar="N",
                   help=f"hybrid: number of sweeps over all constraints (default {hy.sweeps}); "
                        "auto: most sweeps from each start (given, they run even where a "
                        "certified start exists)")
    p.add_argument("--tau0", type=tau, metavar="TAU",
                   help=f"hybrid: initial temperature, below {MAX_TAU:g} (default {hy.tau0:g})")
    p.add_argument("--tau-decay", type=decay, metavar="F",
                   help=f"hybrid: temperature factor per sweep (default {hy.tau_decay:g})")
    p.add_argument("--damping", type=nonneg_float, metavar="MU",
                   help="hybrid: relative damping of the hybrid Hessian blocks "
                        f"(default {hy.damping:g})")
    p.add_argument("--step", choices=LazyChoices(steps),
                   help="hybrid: 'woodbury' solves each step in O(d), 'givens' is the paper's "
                        f"O(d^2) triangularization (default {hy.step})")
    p.add_argument("--tree", choices=LazyChoices(trees),
                   help="spanning tree: 'bfs' breadth-first (the paper's), 'mst' "
                        f"maximum-stiffness (default {hy.tree}); 'toro': each pose hangs from "
                        "its smallest-id neighbour (--solver toro's default)")
    p.add_argument("--gps-batch-size", type=pos_int, metavar="N",
                   help=f"hybrid: GPS constraints relaxed together (default {hy.gps_batch_size})")
    p.add_argument("--dmax", type=number(int, lambda v: v >= 2, "an integer >= 2"), metavar="N",
                   help="hybrid: interpolated solving (paper III-E): solve each update for at "
                        "most N nodes of its path and distribute the rest (default: the whole "
                        "path)")
    p.add_argument("--correction", choices=("none", "pcg"),
                   help="hybrid: after every sweep one global step, a truncated Gauss-Newton step "
                        "by conjugate gradients preconditioned by the hybrid Hessian's block "
                        "diagonal, taken when it lowers the energy ('pcg'), or none (the "
                        f"paper's sweeps alone; default {hy.correction})")
    p.add_argument("--correction-iterations", type=pos_int, metavar="N",
                   help="hybrid: CG iterations of one --correction pcg step "
                        f"(default {hy.correction_iterations})")
    p.add_argument("--monotone", action="store_true",
                   help="hybrid with --correction pcg: undo a sweep that raises the energy, so "
                        "every iteration lowers it and the optimum is a fixed point")
    p.add_argument("--tolerance", type=nonneg_float, metavar="TOL",
                   help="stop when an iteration lowers the energy by less than this fraction "
                        f"(hybrid default {hy.energy_tolerance:g}, where 0 runs all sweeps; "
                        f"exact default {gn.energy_tolerance:g})")
    p.add_argument("--polish", action="store_true",
                   help="hybrid: finish with the exact Levenberg-Marquardt solver")
    p.add_argument("--fix", type=any_int, action="append", metavar="ID",
                   help="hold pose ID fixed (the gauge), as a 'FIX ID' line in the file would; "
                        "may be repeated (the hybrid solver holds exactly one pose fixed)")
    p.add_argument("--max-iterations", type=nonneg_int, metavar="N",
                   help=f"iteration limit of the exact solver (default {gn.max_iterations}) or of "
                        f"the polish (default {hy.polish_iterations})")
    from ..solvers.config import ROBUST_DEFAULT_SCALE

    p.add_argument("--robust", type=robust, metavar="auto|none|NAME[:SCALE]",
                   help="outliers (auto, hybrid, exact): 'auto' solves least squares, tests "
                        "every constraint's chi2 and, when some false loop closure or false "
                        "GPS fix makes the graph inconsistent, solves again without them and "
                        "lists them (the summary counts them; --json and --rejected-out list "
                        "them); 'none' is least squares only; a kernel name (huber, cauchy, "
                        "geman_mcclure) robustifies every constraint, relative and GPS, with "
                        "the scale delta in whitened units, e.g. cauchy:2 (default scales: "
                        + ", ".join(f"{k} {v:g}" for k, v in ROBUST_DEFAULT_SCALE.items()
                                    if k != "none")
                        + "; the energies shown are then the robust ones) (default auto)")
    p.add_argument("--rejected-out", metavar="CSV",
                   help="with --robust auto: write the rejected constraints as CSV with "
                        "columns kind (edge or gps), index (among that kind, in file order), "
                        "id_a, id_b (empty for GPS), line (in the input file), sigmas (the "
                        "whitened error in estimated standard deviations at the result); a "
                        "header only when none was rejected")
    p.add_argument("--plot", metavar="PREFIX",
                   help="also write PREFIX_before.png, PREFIX_after.png and PREFIX_energy.png "
                        "(needs matplotlib: pip install hybridpgo[plot])")
    p.add_argument("--covariance", metavar="NPZ",
                   help="also write the marginal covariances of the poses at the solution "
                        "(Laplace approximation, from a sparse Cholesky factor; the gauge as "
                        "the exact solver's; a robust kernel's weights are not applied) to NPZ: "
                        "ids (k,), cov (k, 6, 6) in tangent order tx ty tz rx ry rz (metres, "
                        "radians; the right perturbation in the pose's frame), fixed_ids")
    p.add_argument("--covariance-poses", type=pose_ids, metavar="IDS",
                   help="the poses of --covariance: 'all', or ids and ranges like 0,5,10..20 "
                        "(default: all; every pose costs about two factorizations of the "
                        "exact solver in total, by selected inversion of the factor)")
    p.add_argument("--rerun", metavar="RRD",
                   help="record the poses and residuals after every sweep and polish (or exact) "
                        "iteration to RRD, to scrub through in the Rerun viewer ('rerun RRD'; "
                        "with --solver auto every start it tries, one after the other; needs: "
                        "pip install hybridpgo[rerun]; not for --solver toro)")
    p.add_argument("--skip-unknown", action="store_true",
                   help="skip lines with unsupported tags (one warning) instead of failing")
    p.add_argument("--json", action="store_true",
                   help="print the summary as JSON instead of text")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_progress(p)
    add_common(p)
    p.set_defaults(command="optimize")


def _convert(sub: Any) -> None:
    """The ``convert`` command."""
    p = sub.add_parser("convert", help="convert a graph between g2o, TORO and iSAM",
                       description="Convert a graph file.  The output format comes from "
                                   "--out-format, else OUT's extension (.g2o -> g2o, .graph -> "
                                   "toro, .txt -> isam, .tum -> tum), else the input's format.  "
                                   "TUM keeps the poses only (timestamp = pose id) and warns "
                                   "that the constraints are lost.  The converted text is read "
                                   "back in memory before it is written.",
                       epilog=OUTPUT_HELP)
    p.add_argument("input", metavar="IN", help="pose-graph file to read ('-': standard input)")
    p.add_argument("output", metavar="OUT", help="file to write ('-': standard output)")
    add_format(p, out=True)
    p.add_argument("--skip-unknown", action="store_true",
                   help="skip lines with unsupported tags (one warning) instead of failing")
    add_common(p)
    p.set_defaults(command="convert")


def _plot(sub: Any) -> None:
    """The ``plot`` command."""
    p = sub.add_parser(
        "plot", help="draw a graph with its constraint residuals",
        description="Draw the trajectory top-down (plus an oblique 3D view for 3D graphs) with "
                    "each constraint's residual from its desired to its actual pose, redder for "
                    "higher energy (paper Fig. 6), a legend, start and end markers and the "
                    "energy per constraint.  With --optimized, draw before and after.",
        epilog=OUTPUT_HELP)
    p.add_argument("file", help="pose-graph file (its vertices, or the tree initialization "
                                "when it has none; '-': standard input)")
    p.add_argument("--optimized", metavar="OUT",
                   help="an optimized version of FILE (same pose ids): draw it beside FILE")
    p.add_argument("-o", "--output", required=True, metavar="FIG",
                   help="image to write (.png, .pdf, .svg; written atomically)")
    add_format(p)
    p.add_argument("--no-residuals", action="store_true", help="draw the trajectory only")
    p.add_argument("--shared-scale", action="store_true",
                   help="with --optimized: one energy colour scale for both maps (default: each "
                        "map its own, so each shows its worst residuals in red)")
    p.add_argument("--dpi", type=dpi, default=150,
                   help=f"resolution, 1..{MAX_DPI} (default 150)")
    add_progress(p)
    add_common(p)
    p.set_defaults(command="plot")


def _demo(sub: Any) -> None:
    """The ``demo`` command."""
    au = auto_defaults()
    p = sub.add_parser(
        "demo", help="optimize the bundled Manhattan graph (M3500) and write plots",
        description="Run the default pipeline (as 'hybridpgo optimize' does: a certified "
                    "start where the certificate holds, else the best start after hybrid "
                    "sweeps while they pay; an exact polish) on the bundled "
                    "M3500_isam.txt, the paper's Manhattan graph; write the optimized graph and "
                    "before/after/energy plots into DIR.")
    p.add_argument("-o", "--output-dir", default="hybridpgo-demo", metavar="DIR",
                   help="output directory (default: hybridpgo-demo)")
    p.add_argument("--sweeps", type=sweeps, metavar="N",
                   help="most hybrid sweeps from each start before the polish (default "
                        f"{au.sweeps.sweeps}, run only when no certified start is found; "
                        "given, they run; fewer when a sweep stops paying)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_progress(p)
    add_common(p)
    p.set_defaults(command="demo")


def _warmup(sub: Any) -> None:
    """The ``warmup`` command."""
    p = sub.add_parser(
        "warmup", help="compile the solvers' Numba kernels now (first run only; then cached)",
        description="Compile every Numba kernel of the solvers now, or load them from the "
                    "on-disk cache if they already are: the first solve of a fresh install "
                    "otherwise spends a minute or two compiling (once; later runs load the "
                    "cache in about a second).  Useful in an image build or after pip install.")
    p.add_argument("--solver", choices=["all", "hybrid", "exact", "toro"], default="all",
                   help="which solver's kernels (default: all)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress and no summary")
    add_progress(p)
    add_common(p)
    p.set_defaults(command="warmup")


def _generate(sub: Any) -> None:
    """The ``generate`` command."""
    p = sub.add_parser(
        "generate", help="generate a synthetic graph with ground truth",
        description="Generate a synthetic pose graph with ground truth.  'city': a street-grid "
                    "city driven by a vehicle, with odometry, probabilistic loop closures and "
                    "optional GPS (paper Table II shapes), any size.  'grid': a Manhattan world "
                    "after Olson (M3500-like), 2D or 3D, with adjustable noise.  Both can add "
                    "false loop closures (--outliers).  Every output is checked before any work "
                    "and all are written or none.",
        epilog="Run 'hybridpgo generate city --help' or 'hybridpgo generate grid --help' for "
               "their options.")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    add_common(p)
    p.set_defaults(command="generate")

    c = kinds.add_parser(
        "city", help="a vehicle driving through a 3D street-grid city (paper Table II shapes)",
        description="A vehicle drives through a street-grid city with gentle elevation; the "
                    "graph has odometry, loop closures detected with some probability when it "
                    "revisits a street, and optional GPS readings.  The file's vertices are "
                    "dead reckoning (the noisy odometry chained from the true first pose).")
    c.add_argument("--preset", choices=LazyChoices(presets),
                   help="size and shape like the paper's Table II graphs (default: the "
                        "generator's default city, 2000 poses)")
    c.add_argument("--poses", type=at_least_2, metavar="N",
                   help="number of poses; the street grid grows with N so that the density of "
                        "loop closures stays the preset's (default: the preset's)")
    c.add_argument("--gps-outliers", type=nonneg_int, default=0, metavar="N",
                   help="move N GPS readings by a multipath jump of 20-60 m in a random "
                        "horizontal direction (false fixes; default 0)")
    c.add_argument("--gps-outliers-out", metavar="CSV",
                   help="where to list the false fixes: CSV with columns gps_index (0-based "
                        "among the file's GPS lines), id, jump_m, dx, dy, dz (default with "
                        "--gps-outliers: GT, else OUT, with its extension replaced by "
                        ".gps_outliers.csv)")
    c.add_argument("--gps-every", type=nonneg_int, metavar="K",
                   help="a GPS reading on every K-th pose (the paper: 100); 0: no GPS "
                        "(default: no GPS)")
    add_generate_common(c, "city")

    g = kinds.add_parser(
        "grid", help="a Manhattan world after Olson (M3500-like), 2D or 3D",
        description="A robot takes unit steps (1 m) on a grid of streets, turning at "
                    "intersections (straight 76%, left 8%, right 8%, back 8%; in 3D also up "
                    "and down), with a loop closure to each earlier pose nearby with probability "
                    "P_LOOP exp(-d^2 / (2 x 0.8^2)) within 3 m, like M3500.  Every measurement "
                    "has the same noise (TRANS_SIGMA per axis, ROT_SIGMA per axis) and matching "
                    "information.  The file's vertices are the odometry chained from the true "
                    "first pose; 2D grids are written as g2o SE2.",
        epilog="Hard graphs (local minima): --preset m3500a, m3500b, m3500c have rotation noise "
               "0.1, 0.2, 0.3 rad; for a family vary --rot-sigma and --seed, e.g. "
               "'for s in 0.1 0.2 0.3 0.5; do hybridpgo generate grid --rot-sigma $s --seed 1 "
               "-o m_$s.g2o --ground-truth m_${s}_gt.g2o; done'.")
    g.add_argument("--preset", choices=LazyChoices(grid_presets),
                   help="m3500 (the default: 3500 poses, sigma 0.0224 m and rad like M3500), "
                        "m3500a/b/c (rotation sigma 0.1/0.2/0.3 rad), grid3d (3D)")
    g.add_argument("--poses", type=at_least_2, metavar="N",
                   help="number of poses (default 3500); the grid grows with N unless --nx is "
                        "given")
    g.add_argument("--3d", dest="three_d", action="store_true",
                   help="a 3D lattice (turns up and down too), written as g2o SE3:QUAT")
    g.add_argument("--nx", type=pos_int, metavar="B",
                   help="blocks along x (default: 0.73 sqrt(N) in 2D, 0.86 N^(1/3) in 3D)")
    g.add_argument("--ny", type=pos_int, metavar="B", help="blocks along y (default: as --nx)")
    g.add_argument("--nz", type=pos_int, metavar="B",
                   help="3D: blocks along z (default: as --nx)")
    g.add_argument("--street-spacing", type=pos_int, metavar="K",
                   help="unit steps between intersections (default 1: turn at any step)")
    g.add_argument("--rot-sigma", type=nonneg_float, metavar="RAD",
                   help="rotation noise of every measurement, radians per axis (default: the "
                        "preset's, 0.0224 for m3500)")
    g.add_argument("--trans-sigma", type=nonneg_float, metavar="M",
                   help="translation noise of every measurement, metres per axis (default "
                        "0.0224)")
    g.add_argument("--p-loop", type=probability, metavar="P",
                   help="probability of closing a pair of poses at the same place (default "
                        "0.12; falls off with distance)")
    g.add_argument("--loop-radius", type=nonneg_float, metavar="M",
                   help="only poses within this distance are closed (default 3)")
    add_generate_common(g, "grid")


def _noisify(sub: Any) -> None:
    """The ``noisify`` command."""
    p = sub.add_parser(
        "noisify", help="perturb every edge rotation about its local up axis (paper Fig. 8)",
        description="Multiply every relative constraint's rotation by a rotation about the "
                    "local up (z) axis with angle ~ N(0, sigma) (paper Fig. 8).",
        epilog=OUTPUT_HELP)
    p.add_argument("input", metavar="IN", help="pose-graph file to read ('-': standard input)")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="file to write (format: --out-format, else OUT's extension, else IN's; "
                        "'-': standard output)")
    add_format(p, out=True)
    p.add_argument("--yaw-sigma-deg", type=nonneg_float, default=3.0, metavar="DEG",
                   help="standard deviation of the yaw noise in degrees (default 3)")
    p.add_argument("--seed", type=any_int, default=0, help="random seed (default 0)")
    add_common(p)
    p.set_defaults(command="noisify")


def _evaluate(sub: Any) -> None:
    """The ``evaluate`` command."""
    p = sub.add_parser(
        "evaluate", help="accuracy of an optimized graph against ground truth",
        description="Position error, rotation error (full 3D angle) and heading error (yaw "
                    "only), each as RMSE, mean, median, standard deviation and max (evo's "
                    "statistics), and the relative pose error of a graph's poses against ground "
                    "truth.  Without GPS the estimate "
                    "is first rigidly aligned to the ground truth; with GPS the earth frame is "
                    "absolute and no alignment is done (override with --align).",
        epilog=OUTPUT_HELP)
    p.add_argument("file", metavar="OUT", help="graph file with the estimated poses ('-': "
                                               "standard input)")
    p.add_argument("--ground-truth", required=True, metavar="GT",
                   help="ground-truth file: g2o/TORO vertices or a TUM trajectory ('-': "
                        "standard input)")
    add_format(p)
    p.add_argument("--align", choices=["auto", "yes", "no"], default="auto",
                   help="rigid alignment before comparing (default auto: only without GPS)")
    p.add_argument("--tum", metavar="PATH",
                   help="also write the estimate to PATH and the ground truth to "
                        "PATH_gt (TUM trajectory format, for evo); both or neither is written")
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    add_common(p)
    p.set_defaults(command="evaluate")


def _batch(sub: Any) -> None:
    """The ``batch`` command."""
    p = sub.add_parser(
        "batch", help="optimize many graphs, or one over a grid of options, on Dask",
        description="Optimize every INPUT with every combination of the --grid options, each "
                    "as one task on a Dask cluster: a local one (one worker process per core) "
                    "unless --scheduler names a running one.  A failing job does not stop the "
                    "others.  Writes the optimized graphs and OUTDIR/summary.csv and "
                    "summary.json (input, options, energy, time, status, error per job).  "
                    "Needs: pip install hybridpgo[dask].",
        epilog="Exit status: 0 every job succeeded, 3 some failed (see the summary), 2 bad "
               "arguments (nothing run).  Example: hybridpgo batch city*.g2o -o out --grid "
               "sweeps=10,40 --grid polish=false,true")
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="pose-graph files")
    p.add_argument("-o", "--output-dir", required=True, metavar="OUTDIR",
                   help="directory for the optimized graphs and the summary (created if "
                        "missing; its parent must exist)")
    p.add_argument("--solver", choices=LazyChoices(methods), default="hybrid",
                   help="solver (default: hybrid)")
    p.add_argument("--grid", action="append", metavar="KEY=V1,V2",
                   help="a solver option and its values (repeatable; every combination runs). "
                        "KEY: a HybridConfig / GaussNewtonConfig field, e.g. sweeps, tau_decay, "
                        "polish, init, method, max_iterations")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="address of a running Dask scheduler, e.g. tcp://10.0.0.5:8786 "
                        "(default: start a local cluster)")
    p.add_argument("--workers", type=pos_int, metavar="N",
                   help="local cluster: number of worker processes (default: one per core)")
    p.add_argument("--json", action="store_true",
                   help="print the summary as JSON instead of a table")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or log lines")
    add_progress(p)
    add_common(p)
    p.set_defaults(command="batch")


def _replay(sub: Any) -> None:
    """The ``replay`` command."""
    p = sub.add_parser(
        "replay", help="stream a graph frame by frame through the online solver",
        description="Replay a graph as a robot would have produced it (frames in increasing "
                    "pose id: each pose with its odometry and loop closures to earlier poses, "
                    "GPS with its pose), one online update per frame within the budget.  "
                    "Reports the latency per frame (mean, p99, max, and the steady max: CPU "
                    "time, not inflated by preemption) and the energy of the estimate over "
                    "the prefix divided by the prefix's batch optimum (exact LM).")
    p.add_argument("file", metavar="FILE", help="pose-graph file to replay")
    add_format(p)
    p.add_argument("--budget-ms", type=pos_float, default=5.0, metavar="B",
                   help="time budget of one frame's update in milliseconds (default 5)")
    p.add_argument("--rate", type=pos_float, metavar="HZ",
                   help="frames arrive at this rate (e.g. 10 for a lidar): the time between a "
                        "frame's work and the next frame goes to the back end (default: back "
                        "to back, the worst case)")
    p.add_argument("--every", type=nonneg_int, default=500, metavar="K",
                   help="measure the accuracy every K frames and at the end (default 500; "
                        "0: only the latency, no batch optima)")
    p.add_argument("--extra-frames", type=nonneg_int, default=100, metavar="N",
                   help="after the last frame, N more updates with the same budget and no new "
                        "data (default 100)")
    p.add_argument("--compare", choices=["isam2"],
                   help="also run GTSAM's ISAM2 on the same stream (needs hybridpgo[gtsam])")
    p.add_argument("--tree", choices=["oldest", "odometry"], default="oldest",
                   help="parent of a new pose: the oldest pose it is constrained to in its "
                        "frame (default) or its odometry parent")
    p.add_argument("--tau-old", type=pos_float, default=0.3, metavar="T",
                   help="temperature of spare-time updates of older constraints (default 0.3)")
    p.add_argument("--local-size", type=nonneg_int, default=0, metavar="K",
                   help="local solve: relax the K newest relative constraints together in every "
                        "frame (default 0: off)")
    p.add_argument("--robust", type=robust, default=("auto", None),
                   metavar="auto|none|NAME[:SCALE]",
                   help="outliers, as for optimize: 'auto' (default) keeps least squares, "
                        "the background worker tests its answers and re-solves without the "
                        "false loop closures and GPS fixes it finds, and the frames stop "
                        "relaxing them (counted as 'rejected'); 'none' is least squares "
                        "only; a kernel name robustifies every update and the worker's solves")
    p.add_argument("--background-refine", action=argparse.BooleanOptionalAction,
                   default=None,
                   help="keep the whole map at its optimum in a worker process (an "
                        "incremental exact solver) and adopt each answer in the next frame "
                        "(default: on, the library's OnlineConfig.background_refine; "
                        "--no-background-refine: no worker process)")
    p.add_argument("--plot", metavar="PREFIX",
                   help="write PREFIX_latency.png and PREFIX_energy.png (needs matplotlib)")
    p.add_argument("--rerun", metavar="RRD",
                   help="record the online run to RRD for the Rerun viewer ('rerun RRD', "
                        "timeline 'frame'): every frame the newest pose and the update's "
                        "latency, and the map so far (poses, residuals, energy) every "
                        "--rerun-every frames and at the last one; recorded outside the "
                        "timing; needs: pip install hybridpgo[rerun]")
    p.add_argument("--rerun-every", type=nonneg_int, default=0, metavar="K",
                   help="with --rerun: the map every K frames (default 0: about 300 maps over "
                        "the run, every frame for runs of at most 300 frames)")
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    add_common(p)
    p.set_defaults(command="replay")
