"""Read a bundled graph, optimize it with the hybrid solver and the exact solver, write results.

    python examples/optimize_bundled.py [OUT_DIR]

Uses the Intel Research Lab graph shipped with the package (2D, 1728 poses).  The hybrid solver
starts from the tree initialization (the paper's); the exact Levenberg-Marquardt solver starts
from the file's vertices.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import hybridpgo as hp
from hybridpgo.io import bundled_path


def main(out_dir: Path) -> None:
    graph = hp.read_graph(bundled_path("intel.g2o"))
    m = graph.num_constraints
    print(f"intel.g2o: {graph.num_nodes} poses, {graph.num_edges} constraints, "
          f"energy at the file's vertices {hp.energy(graph):.6g}")

    hybrid = hp.optimize(graph, "hybrid", sweeps=10)
    print(f"hybrid, 10 sweeps from the tree:  E/c {hybrid.energy_per_constraint:.5g} "
          f"({hybrid.stats['us_per_constraint_mean']:.3g} us per constraint update)")

    polished = hp.optimize(graph, "hybrid", sweeps=10, polish=True)
    exact = hp.optimize(graph, "exact")  # Levenberg-Marquardt from the file's vertices
    print(f"hybrid + exact polish:            E/c {polished.energy_per_constraint:.5g}")
    print(f"exact LM from the file:           E/c {exact.final_energy / m:.5g} "
          f"({exact.iterations} iterations, {exact.status.value})")

    out = out_dir / "intel_hybrid.g2o"
    hp.write_graph(graph.with_poses(polished.rotations, polished.translations), out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp()))
