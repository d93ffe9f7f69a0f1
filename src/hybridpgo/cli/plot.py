"""``hybridpgo plot FILE [--optimized OUT] -o FIG``: draw a graph with its residuals."""

from __future__ import annotations

import argparse
import os

from ..errors import GraphError, HybridPGOError
from ._common import display_poses, phase, read_input


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..plot import check_drawable, graph_figure, residual_energy_range, save_figure

    with phase(f"reading {args.file}"):
        graph = read_input(args.file, args.format)
    name = os.path.basename(args.file)
    poses = [display_poses(graph)]
    titles = [name + ("" if graph.has_estimates else " (tree initialization)")]
    if args.optimized is not None:
        with phase(f"reading {args.optimized}"):
            opt = read_input(args.optimized, None)
        if not opt.has_estimates:
            raise HybridPGOError(f"{args.optimized}: has no vertex estimates to draw (an iSAM "
                                 "file holds only constraints)")
        if not np.array_equal(opt.node_ids, graph.node_ids):
            missing = np.setdiff1d(graph.node_ids, opt.node_ids)
            extra = np.setdiff1d(opt.node_ids, graph.node_ids)
            raise HybridPGOError(
                f"{args.optimized}: its pose ids differ from {args.file}'s "
                f"({missing.size} missing, e.g. {missing[:3].tolist()}; {extra.size} extra, "
                f"e.g. {extra[:3].tolist()}): --optimized must be an optimized version of FILE")
        poses.append((opt.rotations, opt.translations))
        titles.append(os.path.basename(args.optimized))
    for path, (rot, trans) in zip([args.file, args.optimized], poses, strict=False):
        try:
            check_drawable(graph, rot, trans)
        except GraphError as exc:
            raise GraphError(f"{path}: {exc}") from exc
    with phase(f"drawing {args.output}"):
        # each map on its own colour scale unless --shared-scale (then "redder" compares)
        e_range = (residual_energy_range(graph, poses)
                   if args.shared_scale and not args.no_residuals else None)
        fig = graph_figure(graph, poses, titles=titles, residuals=not args.no_residuals,
                           energy_range=e_range)
        save_figure(fig, args.output, dpi=args.dpi)
    print(f"wrote {args.output}")
    return 0
