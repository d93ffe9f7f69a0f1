"""``hybridpgo evaluate OUT --ground-truth GT``: accuracy against ground truth."""

from __future__ import annotations

import argparse
import os
import warnings
from typing import Any

from ..errors import HybridPGOError
from ._common import print_json, print_table, read_input


def tum_ground_truth_path(path: str) -> str:
    """``traj.tum`` -> ``traj_gt.tum`` (where ``--tum`` writes the ground truth)."""
    stem, ext = os.path.splitext(path)
    return f"{stem}_gt{ext}"


def _shared_ids(est_ids: Any, gt_ids: Any, est_path: str, gt_path: str) -> Any:
    """The pose ids both files have; warns when the two pose sets differ."""
    import numpy as np

    from ..io._lines import MAX_LINES_LISTED

    est_only = np.setdiff1d(est_ids, gt_ids)
    gt_only = np.setdiff1d(gt_ids, est_ids)
    shared = np.intersect1d(est_ids, gt_ids)
    if shared.size == 0:
        raise HybridPGOError(f"{est_path} and {gt_path} have no pose id in common (estimate "
                             f"ids {_ids(est_ids, MAX_LINES_LISTED)}; ground truth ids "
                             f"{_ids(gt_ids, MAX_LINES_LISTED)})")
    if est_only.size or gt_only.size:
        warnings.warn(f"{est_path} and {gt_path} have different pose sets: compared on the "
                      f"{shared.size} poses both have; {est_only.size} estimated pose(s) have no "
                      f"ground truth (ids {_ids(est_only, MAX_LINES_LISTED)}); {gt_only.size} "
                      f"ground-truth pose(s) are not in the estimate "
                      f"(ids {_ids(gt_only, MAX_LINES_LISTED)})", UserWarning, stacklevel=2)
    return est_ids[np.isin(est_ids, shared)]


def _ids(ids: Any, limit: int) -> str:
    shown = ", ".join(str(int(v)) for v in ids[:limit])
    return shown + (f" and {ids.size - limit} more" if ids.size > limit else "") if shown \
        else "none"


def _stats(m: dict[str, Any], name: str, unit: str) -> str:
    """``RMSE 1.2 m, mean 1.1 m, median 1 m, std 0.3 m, max 2.5 m`` (evo's statistics)."""
    labels = {"rmse": "RMSE", "mean": "mean", "median": "median", "std": "std", "max": "max"}
    return ", ".join(f"{label} {m[f'{name}_{key}_{unit}']:.4g} {unit}"
                     for key, label in labels.items())


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..io._lines import write_atomic_all
    from ..io.tum import tum_lines
    from ..metrics import evaluate, match_by_ids, read_ground_truth

    graph = read_input(args.file, args.format, check_connected=False)
    if not graph.has_estimates:
        raise HybridPGOError(f"{args.file}: the file has no vertex lines (iSAM), so no poses "
                             "to evaluate; evaluate an optimized g2o/TORO file")
    gt_rot, gt_trans, gt_ids = read_ground_truth(args.ground_truth,
                                                 fix_information=args.fix_information)
    shared = _shared_ids(graph.node_ids, gt_ids, args.file, args.ground_truth)
    ie = np.searchsorted(graph.node_ids, shared)  # node_ids are sorted
    _, ig = match_by_ids(shared, gt_ids)
    align = graph.num_gps == 0 if args.align == "auto" else args.align == "yes"
    est_rot, est_trans = graph.rotations[ie], graph.translations[ie]
    m = evaluate(est_rot, est_trans, gt_rot[ig], gt_trans[ig], align=align)
    tum: list[str] = []
    if args.tum is not None:
        gt_path = tum_ground_truth_path(args.tum)
        ids = graph.node_ids[ie]
        # both files or neither (outputs were checked before the work)
        write_atomic_all([(args.tum, tum_lines(est_rot, est_trans, ids)),
                          (gt_path, tum_lines(gt_rot[ig], gt_trans[ig], ids))])
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
