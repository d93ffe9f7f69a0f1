"""``hybridpgo info FILE``: counts, pose-tree statistics, energies and the worst constraints
of a graph file; ``--residuals CSV`` writes every constraint's error."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from ._common import describe_graph, fmt_energy, print_json, print_table, read_input

if TYPE_CHECKING:
    from ..energy import Residuals
    from ..graph import PoseGraph

#: How many of the largest-χ² constraints ``info`` lists.
NUM_WORST = 5

#: Columns of ``info --residuals``: e_* the error vector (relative: Log(Z^-1 X_a^-1 X_b) in
#: tangent order (rho, phi), metres and radians; GPS: p - g, metres, e_r* empty), w* the whitened
#: error L^T e (Omega = L L^T, dimensionless; |w|^2 = chi2).
RESIDUAL_COLUMNS = ("kind", "index", "id_a", "id_b", "chi2",
                    "e_tx", "e_ty", "e_tz", "e_rx", "e_ry", "e_rz",
                    "w1", "w2", "w3", "w4", "w5", "w6")


def residual_csv_lines(res: Residuals) -> list[str]:
    """``info --residuals``: a header, then one row per relative edge (kind ``edge``, index in
    the graph's edge order: the file's order of edge lines, without lines dropped while reading)
    and per GPS constraint (kind ``gps``, ``id_b`` empty)."""
    lines = [",".join(RESIDUAL_COLUMNS)]
    for k, ((a, b), s, e, w) in enumerate(zip(res.edge_ids.tolist(), res.edge_chi2.tolist(),
                                               res.edge_error.tolist(),
                                               res.edge_whitened.tolist(), strict=True)):
        lines.append(",".join(["edge", str(k), str(a), str(b), repr(s), *map(repr, e),
                               *map(repr, w)]))
    for k, (n, s, e, w) in enumerate(zip(res.gps_ids.tolist(), res.gps_chi2.tolist(),
                                         res.gps_error.tolist(), res.gps_whitened.tolist(),
                                         strict=True)):
        lines.append(",".join(["gps", str(k), str(n), "", repr(s), *map(repr, e), "", "", "",
                               *map(repr, w), "", "", ""]))
    return lines


def worst_constraints(res: Residuals, k: int = NUM_WORST,
                      graph: PoseGraph | None = None) -> list[dict[str, Any]]:
    """The ``k`` constraints with the largest χ², JSON-friendly, largest first; ``line`` is the
    constraint's line in the file when ``graph`` was read from one (else None)."""
    out: list[dict[str, Any]] = []
    edge_lines = None if graph is None else graph.edge_lines
    gps_lines = None if graph is None else graph.gps_lines
    for kind, i, s in res.worst(k):
        if kind == "edge":
            a, b = res.edge_ids[i].tolist()
            line = None if edge_lines is None else int(edge_lines[i])
            out.append({"kind": kind, "index": i, "id_a": a, "id_b": b, "chi2": s, "line": line})
        else:
            line = None if gps_lines is None else int(gps_lines[i])
            out.append({"kind": kind, "index": i, "id_a": int(res.gps_ids[i]), "id_b": None,
                        "chi2": s, "line": line})
    return out


def graph_info(path: str, fmt: str | None = None, *, tree_kind: str = "bfs",
               skip_unknown: bool = False, residuals_out: str | None = None) -> dict[str, Any]:
    """Everything ``hybridpgo info`` reports, as a JSON-friendly dict.

    ``odometry_edges`` join poses adjacent in id order, ``loop_edges`` are the other relative edges;
    ``non_tree_edges`` are the relative edges the spanning tree does not use.  ``worst`` lists
    the constraints with the largest χ² at the file's vertices (at the tree initialization when
    the file has none, ``residuals_at``); ``residuals_out`` receives every constraint's error
    (:func:`residual_csv_lines`).
    """
    import numpy as np

    from ..energy import energy, residuals
    from ..errors import GraphError
    from ..initialization import initial_locals
    from ..io._lines import write_atomic
    from ..tree import LINK_EDGE, build_tree, global_poses

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
    tree_poses = global_poses(tree, *initial_locals(graph, tree, "tree"))
    e_tree = energy(graph, *tree_poses)
    res = residuals(graph) if graph.has_estimates else residuals(graph, *tree_poses)
    if residuals_out is not None:
        write_atomic(residuals_out, lambda: residual_csv_lines(res))
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
        "residuals_at": "file" if graph.has_estimates else "tree",
        "worst": worst_constraints(res, graph=graph),
        "residuals": residuals_out,
        "_summary": describe_graph(graph),
    }


def run(args: argparse.Namespace) -> int:
    info = graph_info(args.file, args.format, tree_kind=args.tree,
                      skip_unknown=args.skip_unknown, residuals_out=args.residuals)
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
    where = "file vertices" if info["residuals_at"] == "file" else "tree initialization"
    for k, w in enumerate(info["worst"]):
        at = "" if w["line"] is None else f", line {w['line']}"
        what = (f"edge {w['index']} ({w['id_a']} -> {w['id_b']}{at})" if w["kind"] == "edge"
                else f"GPS {w['index']} (pose {w['id_a']}{at})")
        rows.append(("worst chi2" if k == 0 else "",
                     f"{w['chi2']:.6g}  {what}" + (f"  (at the {where})" if k == 0 else "")))
    if info["residuals"] is not None:
        rows.append(("residuals", f"{info['residuals']} (error, whitened error and chi2 of every "
                                  "constraint)"))
    print_table(rows)
    return 0
