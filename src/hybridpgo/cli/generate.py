"""``hybridpgo generate city|grid``: synthetic graphs with ground truth and optional false loop
closures.

Outputs are all or nothing: every output path is checked (distinct files, writable directories)
and a temporary file is reserved beside each before any work; the files are written to those
temporaries and renamed into place together only when all of them have been written.
"""

from __future__ import annotations

import argparse
import os
from types import TracebackType
from typing import Any

from .._output import Outputs, same_file
from ..errors import FormatError, HybridPGOError
from ._common import FORMAT_FROM_SUFFIX, describe_graph, print_table

#: Extension of the default outliers file (replacing the ground truth's, else the graph's).
OUTLIERS_SUFFIX = ".outliers.csv"


def run(args: argparse.Namespace) -> int:
    from ..generate import write_ground_truth, write_outliers
    from ..io import write_graph

    fmt = _graph_format(args.output)
    outliers_out = args.outliers_out
    if outliers_out is None and args.outliers > 0:
        outliers_out = os.path.splitext(args.ground_truth or args.output)[0] + OUTLIERS_SUFFIX
    outputs = [("-o/--output", args.output)]
    if args.ground_truth is not None:
        outputs.append(("--ground-truth", args.ground_truth))
    if outliers_out is not None:
        outputs.append(("--outliers-out" if args.outliers_out else "the outliers file",
                        outliers_out))
    if fmt == "toro" and args.kind == "city" and args.gps_every:
        raise HybridPGOError(f"{args.output}: TORO files cannot hold GPS readings; write g2o "
                             "(a .g2o name) or drop --gps-every")

    with OutputGroup(outputs) as group:  # reserves the outputs before any work
        made = _city(args) if args.kind == "city" else _grid(args)
        graph = made.graph
        write_graph(graph, group.temp(args.output), fmt)
        if args.ground_truth is not None:
            # the constraint lines are the graph file's: copy them instead of formatting twice
            write_ground_truth(group.temp(args.ground_truth), graph, made.truth_rotations,
                               made.truth_translations,
                               graph_file=group.temp(args.output) if fmt == "g2o" else None)
        if outliers_out is not None:
            write_outliers(group.temp(outliers_out), graph, made.outliers)
        group.commit()

    rows = [(args.kind, f"{made.name}, seed {args.seed}"),
            ("graph", f"{args.output} ({describe_graph(graph)}; {made.num_loop_edges} loop "
                      "closures; vertices are dead reckoning)")]
    if args.ground_truth is not None:
        rows.append(("ground truth", args.ground_truth))
    if outliers_out is not None:
        k = made.outliers.num_outliers
        near = int((made.outliers.kinds == 1).sum())
        rows.append(("outliers", f"{outliers_out} ({k} false loop closures: {k - near} random, "
                                 f"{near} near misses)"))
    print_table(rows)
    return 0


def _graph_format(path: str) -> str:
    """g2o, or TORO for a ``.graph`` name (iSAM cannot hold the vertices)."""
    fmt = FORMAT_FROM_SUFFIX.get(os.path.splitext(path)[1].lower(), "g2o")
    return "toro" if fmt == "toro" else "g2o"


def _outlier_params(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {"num_outliers": args.outliers}
    if args.near_miss_fraction is not None:
        out["near_miss_fraction"] = args.near_miss_fraction
    return out


def _city(args: argparse.Namespace) -> Any:
    from ..generate import PRESETS, generate_city, scale_city

    if args.preset is not None and args.preset not in PRESETS:  # LazyChoices let it through
        raise HybridPGOError(f"unknown preset {args.preset!r}; choose one of "
                             + ", ".join(sorted(PRESETS)))
    kwargs = _outlier_params(args)
    if args.poses is not None:
        kwargs.update(scale_city(args.preset, args.poses))
    if args.gps_every is not None:
        kwargs["gps_every"] = args.gps_every
    try:
        return generate_city(args.preset, seed=args.seed, **kwargs)
    except ValueError as exc:
        raise HybridPGOError(f"cannot generate the city: {exc}") from exc


def _grid(args: argparse.Namespace) -> Any:
    from ..generate import GRID_PRESETS, generate_grid

    if args.preset is not None and args.preset not in GRID_PRESETS:
        raise HybridPGOError(f"unknown grid preset {args.preset!r}; choose one of "
                             + ", ".join(GRID_PRESETS))
    kwargs = _outlier_params(args)
    for name, key in (("poses", "num_poses"), ("nx", "nx"), ("ny", "ny"), ("nz", "nz"),
                      ("street_spacing", "street_spacing"), ("rot_sigma", "rot_sigma_rad"),
                      ("trans_sigma", "trans_sigma_m"), ("p_loop", "p_loop"),
                      ("loop_radius", "loop_radius_m")):
        value = getattr(args, name)
        if value is not None:
            kwargs[key] = value
    if args.three_d:
        kwargs["dim"] = 3
    try:
        return generate_grid(args.preset, seed=args.seed, **kwargs)
    except ValueError as exc:
        raise HybridPGOError(f"cannot generate the grid: {exc}") from exc


# =========================================================================== all-or-nothing
class OutputGroup:
    """Several output files written all or nothing (:class:`hybridpgo._output.Outputs`), with
    messages that name each output's option.

    On entering, every path is checked (no two name the same file, none is a directory) and a
    temporary file is created beside each, so an unwritable output fails before any work.
    Write each output to :meth:`temp`, then call :meth:`commit` to move them all into place;
    leaving the ``with`` block without committing (or with an exception) removes the
    temporaries and leaves existing files untouched.
    """

    def __init__(self, outputs: list[tuple[str, str]]) -> None:
        self._outputs = outputs
        self._out: Outputs | None = None

    def __enter__(self) -> OutputGroup:
        for k, (label, path) in enumerate(self._outputs):
            for other_label, other_path in self._outputs[:k]:
                if same_file(path, other_path):
                    raise HybridPGOError(
                        f"{path}: {other_label} and {label} name the same file; give each "
                        "output its own file name")
        try:
            self._out = Outputs([path for _, path in self._outputs])
        except FormatError as exc:
            raise self._labelled(exc) from exc
        return self

    def _labelled(self, exc: FormatError) -> HybridPGOError:
        label = next((lb for lb, p in self._outputs if p == exc.path), "the output")
        why = exc.problem.removeprefix("cannot write the file: ")
        return HybridPGOError(f"{exc.path}: cannot write {label}: {why}")

    def temp(self, path: str) -> str:
        """The temporary file to write ``path``'s content to."""
        assert self._out is not None
        return self._out.temp(path)

    def commit(self) -> None:
        """Move every output into place (keeping an existing file's permissions)."""
        assert self._out is not None
        try:
            self._out.commit()
        except FormatError as exc:
            raise self._labelled(exc) from exc

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._out is not None:
            self._out.discard()
