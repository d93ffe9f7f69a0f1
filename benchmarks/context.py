"""What every workload receives (:class:`Context`: the data folder, the cache of graphs and
optima) and returns (:data:`Result`), and the starting points they share."""

from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridpgo.graph import PoseGraph
from hybridpgo.initialization import initial_locals
from hybridpgo.io import read_graph
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import solve_exact
from hybridpgo.tree import build_tree, global_poses

from .metrics import Metric


@dataclass
class Context:
    data_dir: pathlib.Path
    quick: bool
    cache: dict[str, Any]
    figures: pathlib.Path | None = None

    def graph(self, name: str) -> PoseGraph:
        if name not in self.cache:
            path = self.data_dir / name
            if not path.is_file():
                raise FileNotFoundError(
                    f"benchmark graph {path} not found: pass --data-dir DIR or set "
                    f"HYBRIDPGO_DATASETS to the folder of the public benchmark graphs "
                    f"(benchmarks/README.md)")
            self.cache[name] = read_graph(path)
        return self.cache[name]  # type: ignore[no-any-return]

    def optimum(self, name: str) -> float:
        """Best energy known for a file: LM from the chordal start (global on these files)."""
        key = "opt:" + name
        if key not in self.cache:
            g = self.graph(name)
            rot, trans = start(g, "chordal")
            res = solve_exact(g, rot, trans, GaussNewtonConfig(max_iterations=300))
            self.cache[key] = res.final_energy
        return float(self.cache[key])


Result = tuple[list[Metric], list[str]]


def start(graph: PoseGraph, init: str) -> tuple[np.ndarray, np.ndarray]:
    """Global poses of an initialization ('file', 'tree' or 'chordal')."""
    if init == "file":
        return np.array(graph.rotations), np.array(graph.translations)
    tree = build_tree(graph)
    return global_poses(tree, *initial_locals(graph, tree, init))
