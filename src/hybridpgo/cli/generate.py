"""``hybridpgo generate city``: a synthetic city drive with ground truth (issue 4)."""

from __future__ import annotations

import argparse
from typing import Any

from ..errors import HybridPGOError
from ._common import describe_graph, output_format, print_table


def run(args: argparse.Namespace) -> int:
    from ..generate import PRESETS, generate_city, write_ground_truth
    from ..io import write_graph

    if args.preset is not None and args.preset not in PRESETS:  # LazyChoices let it through
        raise HybridPGOError(f"unknown preset {args.preset!r}; choose one of "
                             + ", ".join(sorted(PRESETS)))
    kwargs: dict[str, Any] = {"seed": args.seed}
    if args.gps_every is not None:
        kwargs["gps_every"] = args.gps_every
    try:
        city = generate_city(args.preset, **kwargs)
    except ValueError as exc:
        raise HybridPGOError(f"cannot generate the city: {exc}") from exc
    graph = city.graph
    fmt = output_format(args.output, None, graph, allow_isam=False)
    write_graph(graph, args.output, fmt)
    write_ground_truth(args.ground_truth, graph, city.truth_rotations, city.truth_translations)
    print_table([
        ("city", f"{city.name}, seed {args.seed}"),
        ("graph", f"{args.output} ({describe_graph(graph)}; {city.num_loop_edges} loop "
                  "closures; vertices are dead reckoning)"),
        ("ground truth", args.ground_truth),
    ])
    return 0
