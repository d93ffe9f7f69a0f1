"""``hybridpgo convert IN OUT``: convert a graph between g2o, TORO and iSAM."""

from __future__ import annotations

import argparse

from ._common import describe_graph, output_format, read_input


def run(args: argparse.Namespace) -> int:
    from ..io import write_graph

    graph = read_input(args.input, args.format, skip_unknown=args.skip_unknown)
    fmt = output_format(args.output, args.out_format, graph, allow_isam=True)
    write_graph(graph, args.output, fmt)
    print(f"wrote {args.output} ({fmt}) from {args.input} ({describe_graph(graph)})")
    return 0
