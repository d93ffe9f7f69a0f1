"""``hybridpgo convert IN OUT``: convert a graph between g2o, TORO and iSAM (or to TUM poses)."""

from __future__ import annotations

import argparse

from ..errors import FormatError, HybridPGOError
from ._common import describe_graph, output_format, read_input


def run(args: argparse.Namespace) -> int:
    from ..io import graph_lines, read_back
    from ..io._lines import source_from_text, write_atomic
    from ..io.tum import read_tum_source

    graph = read_input(args.input, args.format, skip_unknown=args.skip_unknown)
    fmt = output_format(args.output, args.out_format, graph, allow_isam=True)
    lines = graph_lines(graph, fmt, args.output)
    # Never write a file this tool cannot read: read the text back in memory first.
    try:
        if fmt == "tum":
            read_tum_source(source_from_text("\n".join(lines) + "\n", args.output))
        else:
            read_back(lines, fmt, args.output)
    except FormatError as exc:
        raise HybridPGOError(f"{args.output}: not written: the converted {fmt} text could not "
                             f"be read back ({exc}); please report this") from exc
    write_atomic(args.output, lambda: lines)
    print(f"wrote {args.output} ({fmt}) from {args.input} ({describe_graph(graph)})")
    return 0
