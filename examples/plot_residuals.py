"""Before/after maps with constraint residuals (paper Fig. 6) and energy vs time (Fig. 5).

    python examples/plot_residuals.py [OUT_DIR]        (needs: pip install hybridpgo[plot])

Optimizes the bundled Manhattan graph (M3500, as in the paper) with the hybrid solver and with
Levenberg-Marquardt, both from the tree initialization, and writes two PNG files.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import hybridpgo as hp
from hybridpgo.initialization import initial_locals
from hybridpgo.io import bundled_path
from hybridpgo.plot import energy_figure, graph_figure, residual_energy_range, save_figure
from hybridpgo.tree import build_tree, global_poses


def main(out_dir: Path) -> None:
    graph = hp.read_graph(bundled_path("M3500_isam.txt"))
    tree = build_tree(graph, "bfs")
    before = global_poses(tree, *initial_locals(graph, tree, "tree"))

    results = {
        "hybrid (10 sweeps)": hp.optimize(graph, "hybrid", sweeps=10),
        "exact LM": hp.optimize(graph, "exact", init="tree"),
    }
    hybrid = results["hybrid (10 sweeps)"]
    after = (hybrid.rotations, hybrid.translations)

    # one colour scale for both maps, so "redder" means the same energy in each
    fig = graph_figure(graph, [before, after],
                       titles=["tree initialization", "after 10 hybrid sweeps"],
                       energy_range=residual_energy_range(graph, [before, after]))
    save_figure(fig, out_dir / "m3500_maps.png")
    save_figure(energy_figure(results, title="M3500: energy per constraint"),
                out_dir / "m3500_energy.png")
    for name, res in results.items():
        print(f"{name:20s} E/c {res.energy_per_constraint:.4g} after {res.times[-1]:.2f} s")
    print(f"wrote {out_dir / 'm3500_maps.png'} and {out_dir / 'm3500_energy.png'}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp()))
