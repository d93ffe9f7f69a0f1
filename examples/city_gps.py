"""A synthetic city with and without GPS: solve, then measure the error against ground truth.

    python examples/city_gps.py [OUT_DIR]

Generates a small street-grid drive (same route, odometry and loop closures in both runs; one
run adds a GPS reading every 25 poses), optimizes each with the hybrid solver plus an exact
polish, and compares position and heading errors.  Without GPS the estimate is rigidly aligned
to the truth first (its frame is arbitrary); with GPS the earth frame is absolute.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import hybridpgo as hp
from hybridpgo.generate import generate_city, write_ground_truth
from hybridpgo.metrics import evaluate


def main(out_dir: Path) -> None:
    for gps_every in (None, 25):
        city = generate_city(seed=1, gps_every=gps_every, num_poses=1500)
        graph = city.graph
        result = hp.optimize(graph, "hybrid", sweeps=10, polish=True)
        m = evaluate(result.rotations, result.translations, city.truth_rotations,
                     city.truth_translations, align=graph.num_gps == 0)
        label = "no GPS" if gps_every is None else f"GPS every {gps_every}"
        print(f"{label:14s} {graph.num_nodes} poses, {graph.num_edges} edges, "
              f"{graph.num_gps} GPS: E/c {result.energy_per_constraint:.4g}, position RMSE "
              f"{m['position_rmse_m']:.3g} m, heading error mean "
              f"{m['heading_error_mean_deg']:.3g} deg")
        stem = "city" if gps_every is None else "city_gps"
        hp.write_graph(graph.with_poses(result.rotations, result.translations),
                       out_dir / f"{stem}_optimized.g2o")
        write_ground_truth(out_dir / f"{stem}_gt.g2o", graph, city.truth_rotations,
                           city.truth_translations)
    print(f"wrote the optimized graphs and ground truth into {out_dir}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp()))
