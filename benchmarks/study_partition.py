"""Study (not a workload): how a city graph splits into submaps by subtree (docs/scaling.md).

    PYTHONPATH=src python -m benchmarks.study_partition [PRESET] [--gps-every K]

For P = 2 ... 64 machines, cut the pose tree at the nodes whose subtree holds at most 1/P of the
nodes while their parent's holds more; every constraint whose domain lies in one such subtree is
*internal* (relaxed by its machine, in parallel with the others), every other one *crosses* a
separator (its domain reaches the top tree or two subtrees).  Prints counts and the share of the
O(d) work (sum of domain sizes) the crossing constraints carry.
"""

from __future__ import annotations

import argparse

import numpy as np

from hybridpgo.generate import generate_city
from hybridpgo.graph import PoseGraph
from hybridpgo.tree import build_tree

#: Bytes per domain entry of the hybrid solver's state: one 6x6 float64 contribution block
#: (``HybridState.contrib``), the int32 node and the int8 sign of the CSR path.
BYTES_PER_DOMAIN_ENTRY = 36 * 8 + 4 + 1


def partition_report(name: str, graph: PoseGraph, machines: tuple[int, ...]) -> None:
    tree = build_tree(graph, "bfs")
    n_tree = tree.num_tree_nodes
    size = np.ones(n_tree, np.int64)
    for v in tree.order[::-1]:  # children before parents
        if tree.parent[v] >= 0:
            size[tree.parent[v]] += size[v]
    d = tree.path_lengths()
    c = tree.num_constraints
    print(f"{name}: {graph.num_nodes} poses, {c} constraints, tree depth {tree.max_depth}, "
          f"domain size mean {d.mean():.1f}, p99 {np.quantile(d, 0.99):.0f}, max {d.max()}; "
          f"state {d.sum() * BYTES_PER_DOMAIN_ENTRY / 1e6:.0f} MB for the domains")
    parent_size = np.where(tree.parent >= 0, size[np.maximum(tree.parent, 0)], n_tree + 1)
    member = np.repeat(np.arange(c), d)
    for p in machines:
        cap = n_tree / p
        cut = (size <= cap) & (parent_size > cap)
        owner = np.full(n_tree, -1)
        for v in tree.order:  # parents first
            if cut[v]:
                owner[v] = v
            elif tree.parent[v] >= 0:
                owner[v] = owner[tree.parent[v]]
        own = owner[tree.path_node]
        first = own[tree.path_ptr[:-1]]
        same = np.ones(c, bool)
        np.logical_and.at(same, member, own == first[member])
        cross = ~(same & (first >= 0))
        subs = np.bincount(owner[owner >= 0])
        subs = subs[subs > 0]
        print(f"  P={p:3d}: {subs.size} subtrees (largest {subs.max()}, median "
              f"{int(np.median(subs))}), top tree {int((owner < 0).sum())} nodes; crossing "
              f"{int(cross.sum())} constraints ({100 * cross.mean():.2f} %) carrying "
              f"{100 * d[cross].sum() / d.sum():.1f} % of the work (sum of d)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("preset", nargs="?", default="paris2")
    ap.add_argument("--gps-every", type=int)
    args = ap.parse_args()
    city = generate_city(preset=args.preset, seed=0, gps_every=args.gps_every)
    name = args.preset + (f", GPS every {args.gps_every}" if args.gps_every else "")
    partition_report(name, city.graph, (2, 4, 8, 16, 64))


if __name__ == "__main__":
    main()
