"""``hybridpgo info FILE``: counts, pose-tree statistics and energies of a graph file."""

from __future__ import annotations

import argparse
from typing import Any

from ._common import describe_graph, fmt_energy, print_json, print_table, read_input


def graph_info(path: str, fmt: str | None = None, *, tree_kind: str = "bfs",
               skip_unknown: bool = False) -> dict[str, Any]:
    """Everything ``hybridpgo info`` reports, as a JSON-friendly dict.

    ``odometry_edges`` join poses adjacent in id order, ``loop_edges`` are the other relative edges;
    ``non_tree_edges`` are the relative edges the spanning tree does not use.
    """
    import numpy as np

    from ..energy import energy
    from ..errors import GraphError
    from ..tree import LINK_EDGE, build_tree, global_poses, initial_locals

    graph = read_input(path, fmt, skip_unknown=skip_unknown)
    # odometry: edges between poses adjacent in id order (dense index = rank of the id)
    en = graph.edge_nodes
    odometry = int(np.count_nonzero(np.abs(en[:, 0] - en[:, 1]) == 1))
    try:
        tree = build_tree(graph, tree_kind)
    except GraphError as exc:  # e.g. two FIX lines: the message must name the file
        raise GraphError(f"{path}: {exc}") from exc
    in_tree = np.zeros(graph.num_edges, bool)
    in_tree[tree.link_index[tree.link_kind == LINK_EDGE]] = True
    lengths = tree.path_lengths()
    nc = graph.num_constraints
    e_file = energy(graph) if graph.has_estimates else None
    e_tree = energy(graph, *global_poses(tree, *initial_locals(graph, tree, "tree")))
    return {
        "path": str(path),
        "format": graph.source_format,
        "dimension": "2D" if graph.is_2d else "3D",
        "poses": graph.num_nodes,
        "relative_edges": graph.num_edges,
        "odometry_edges": odometry,
        "loop_edges": graph.num_edges - odometry,
        "non_tree_edges": int(np.count_nonzero(~in_tree)),
        "gps": graph.num_gps,
        "fixed": int(graph.fixed_nodes.size),
        "constraints": nc,
        "has_vertices": graph.has_estimates,
        "tree": {
            "kind": tree_kind,
            "root": "earth" if tree.has_earth else int(graph.node_ids[tree.root]),
            "max_depth": tree.max_depth,
            "path_length_max": int(lengths.max()) if lengths.size else 0,
            "path_length_mean": float(lengths.mean()) if lengths.size else 0.0,
        },
        "energy_file": e_file,
        "energy_file_per_constraint": None if e_file is None else e_file / max(nc, 1),
        "energy_tree_init": e_tree,
        "energy_tree_init_per_constraint": e_tree / max(nc, 1),
        "_summary": describe_graph(graph),
    }


def run(args: argparse.Namespace) -> int:
    info = graph_info(args.file, args.format, tree_kind=args.tree,
                      skip_unknown=args.skip_unknown)
    summary = info.pop("_summary")
    if args.json:
        print_json(info)
        return 0
    t = info["tree"]
    nc = info["constraints"]
    rows = [
        ("file", f"{info['path']} ({summary})"),
        ("poses", str(info["poses"])),
        ("relative edges", f"{info['relative_edges']}: {info['odometry_edges']} between "
                           f"consecutive ids, {info['loop_edges']} loop closures; "
                           f"{info['non_tree_edges']} not in the tree"),
        ("GPS", str(info["gps"])),
        ("fixed (FIX)", str(info["fixed"])),
        ("tree", f"{t['kind']}, root {t['root']}, depth {t['max_depth']}"),
        ("paths", f"longest constraint path {t['path_length_max']} poses, "
                  f"mean {t['path_length_mean']:.3g}"),
        ("energy (file)", "no vertices in the file" if info["energy_file"] is None
         else fmt_energy(info["energy_file"], nc)),
        ("energy (tree)", fmt_energy(info["energy_tree_init"], nc) + " at the tree "
                          "initialization"),
    ]
    print_table(rows)
    return 0
