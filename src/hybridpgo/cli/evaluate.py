"""``hybridpgo evaluate OUT --ground-truth GT``: accuracy against ground truth (issue 4)."""

from __future__ import annotations

import argparse
import os
from typing import Any

from ..errors import HybridPGOError
from ._common import print_json, print_table, read_input


def tum_ground_truth_path(path: str) -> str:
    """``traj.tum`` -> ``traj_gt.tum`` (where ``--tum`` writes the ground truth)."""
    stem, ext = os.path.splitext(path)
    return f"{stem}_gt{ext}"


def _stats(m: dict[str, Any], name: str, unit: str) -> str:
    """``RMSE 1.2 m, mean 1.1 m, median 1 m, std 0.3 m, max 2.5 m`` (evo's statistics)."""
    labels = {"rmse": "RMSE", "mean": "mean", "median": "median", "std": "std", "max": "max"}
    return ", ".join(f"{label} {m[f'{name}_{key}_{unit}']:.4g} {unit}"
                     for key, label in labels.items())


def run(args: argparse.Namespace) -> int:
    from ..metrics import evaluate, match_by_ids, read_ground_truth, write_tum

    graph = read_input(args.file, args.format, check_connected=False)
    if not graph.has_estimates:
        raise HybridPGOError(f"{args.file}: the file has no vertex lines (iSAM), so no poses "
                             "to evaluate; evaluate an optimized g2o/TORO file")
    gt_rot, gt_trans, gt_ids = read_ground_truth(args.ground_truth)
    ie, ig = match_by_ids(graph.node_ids, gt_ids)
    align = graph.num_gps == 0 if args.align == "auto" else args.align == "yes"
    est_rot, est_trans = graph.rotations[ie], graph.translations[ie]
    m = evaluate(est_rot, est_trans, gt_rot[ig], gt_trans[ig], align=align)
    tum: list[str] = []
    if args.tum is not None:
        gt_path = tum_ground_truth_path(args.tum)
        write_tum(args.tum, est_rot, est_trans, timestamps=graph.node_ids[ie])
        write_tum(gt_path, gt_rot[ig], gt_trans[ig], timestamps=graph.node_ids[ie])
        tum = [args.tum, gt_path]
    if args.json:
        print_json({"file": args.file, "ground_truth": args.ground_truth, "gps": graph.num_gps,
                    **m, "tum": tum})
        return 0
    how = ("rigidly aligned to the ground truth first" if m["aligned"] else
           "no alignment (earth frame)")
    rows = [
        ("estimate", f"{args.file} ({m['num_poses']} poses, {graph.num_gps} GPS; {how})"),
        ("ground truth", args.ground_truth),
        ("position", _stats(m, "position", "m")),
        ("rotation", _stats(m, "rotation_error", "deg") + " (full 3D angle)"),
        ("heading", _stats(m, "heading_error", "deg") + " (yaw only)"),
        ("RPE", f"delta {m['rpe_delta']}: translation RMSE {m['rpe_translation_rmse_m']:.4g} m, "
                f"rotation RMSE {m['rpe_rotation_rmse_deg']:.4g} deg "
                f"({m['rpe_num_pairs']} pairs)"),
    ]
    if m["aligned"]:
        rows.append(("alignment", f"{m['alignment_rotation_deg']:.4g} deg, "
                                  f"{m['alignment_translation_m']:.4g} m"))
    rows += [("TUM", p) for p in tum]
    print_table(rows)
    return 0
