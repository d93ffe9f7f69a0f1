"""``hybridpgo noisify IN -o OUT``: rotate every edge about its local up axis (paper Fig. 8)."""

from __future__ import annotations

import argparse

from .._output import same_file
from ..errors import HybridPGOError
from ._common import describe_graph, log, output_format, read_input


def run(args: argparse.Namespace) -> int:
    from ..generate import noisify
    from ..io import write_graph

    if same_file(args.input, args.output):
        raise HybridPGOError(f"{args.output}: is the input file; noisify never overwrites its "
                             "input: choose another output")
    graph = read_input(args.input, args.format)
    noisy = noisify(graph, yaw_sigma_deg=args.yaw_sigma_deg, seed=args.seed)
    fmt = output_format(args.output, args.out_format, graph, allow_isam=True)
    write_graph(noisy, args.output, fmt)
    print(f"wrote {args.output} ({fmt}): {describe_graph(noisy)}; every edge rotation "
          f"multiplied by Rz(N(0, {args.yaw_sigma_deg:g} deg)), seed {args.seed}")
    if noisy.has_estimates and fmt != "isam":
        log("hybridpgo: note: the vertex estimates are unchanged and no longer match the "
            "noisy edges; optimize from the tree initialization (--init tree, the default)")
    return 0
