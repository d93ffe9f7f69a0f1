"""The pose tree: structure, constraint paths (vs a naive oracle), initializations, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo.errors import GraphError
from hybridpgo.geometry.se3 import compose
from hybridpgo.graph import PoseGraph
from hybridpgo.initialization import initial_locals
from hybridpgo.io import read_graph
from hybridpgo.tree import LINK_EDGE, LINK_GPS, build_tree, global_poses

#: Products of a few dozen rotations accumulate only rounding.
ROUNDING = 1e-10


def _ancestors(tree, i):
    out = [i]
    while tree.parent[out[-1]] >= 0:
        out.append(int(tree.parent[out[-1]]))
    return out


@pytest.mark.parametrize("kind", ["bfs", "mst", "gps"])
@pytest.mark.parametrize("gps", [0, 3])
def test_paths_match_a_naive_lowest_common_ancestor(kind, gps):
    rng = np.random.default_rng(0)
    graph, _, _ = random_graph(rng, n=30, extra=25, gps=gps)
    tree = build_tree(graph, kind)
    n = graph.num_nodes
    assert tree.has_earth == bool(gps)
    assert tree.root == (n if gps else 0)
    # a spanning tree: every node but the root has a parent, parents come first in `order`
    seen = np.zeros(tree.num_tree_nodes, bool)
    for i in tree.order:
        assert tree.parent[i] < 0 or seen[tree.parent[i]]
        seen[i] = True
        if tree.parent[i] >= 0:
            assert tree.depth[i] == tree.depth[tree.parent[i]] + 1
    assert seen.all() and (tree.parent < 0).sum() == 1
    ends = [tuple(e) for e in graph.edge_nodes] + [(n, int(v)) for v in graph.gps_nodes]
    for c, (a, b) in enumerate(ends):
        up_a, up_b = _ancestors(tree, a), _ancestors(tree, b)
        root = next(v for v in up_a if v in up_b)
        side_a = up_a[: up_a.index(root)]
        side_b = up_b[: up_b.index(root)]
        path = tree.path_node[tree.path_ptr[c]:tree.path_ptr[c + 1]].tolist()
        signs = tree.path_sign[tree.path_ptr[c]:tree.path_ptr[c + 1]].tolist()
        assert path == side_a + side_b
        assert signs == [-1] * len(side_a) + [1] * len(side_b)
        assert tree.constraint_root[c] == root
    roots_depth = tree.depth[tree.constraint_root[tree.sweep_order]]
    assert np.all(np.diff(roots_depth) >= 0)  # paper Algorithm 1: increasing root depth


def test_tree_edges_are_real_constraints_and_gps_is_avoided():
    rng = np.random.default_rng(1)
    graph, _, _ = random_graph(rng, n=20, extra=10, gps=5)
    tree = build_tree(graph)
    n = graph.num_nodes
    for i in range(n):
        p = int(tree.parent[i])
        if tree.link_kind[i] == LINK_EDGE:
            a, b = graph.edge_nodes[tree.link_index[i]]
            assert {int(a), int(b)} == {p, i}
            assert tree.link_forward[i] == (a == p)
        else:  # one GPS link per connected part (the graph is connected): only one
            assert tree.link_kind[i] == LINK_GPS and p == n
    assert (tree.link_kind == LINK_GPS).sum() == 1


def test_file_initialization_reproduces_the_file_poses():
    rng = np.random.default_rng(2)
    graph, _, _ = random_graph(rng, n=15, extra=10, gps=2, rot_scale=1.0)
    tree = build_tree(graph)
    rot, trans = global_poses(tree, *initial_locals(graph, tree, "file"))
    np.testing.assert_allclose(rot, graph.rotations, rtol=0, atol=ROUNDING)
    np.testing.assert_allclose(trans, graph.translations, rtol=0, atol=ROUNDING)


def test_tree_initialization_satisfies_every_tree_edge(data_dir):
    graph = read_graph(data_dir / "smallGrid3D.g2o")
    tree = build_tree(graph)
    rot, trans = global_poses(tree, *initial_locals(graph, tree, "tree"))
    for i in range(graph.num_nodes):
        if tree.parent[i] < 0:
            continue
        c = int(tree.link_index[i])
        a, b = graph.edge_nodes[c]
        pr, pt = compose(rot[a].T, -rot[a].T @ trans[a], rot[b], trans[b])
        np.testing.assert_allclose(pr, graph.edge_rotations[c], rtol=0, atol=ROUNDING)
        np.testing.assert_allclose(pt, graph.edge_translations[c], rtol=0, atol=ROUNDING * 100)


def test_gps_tree_hangs_from_a_central_reading():
    """A chain with GPS at both ends and in the middle hangs from the middle one."""
    n = 41
    eye = np.tile(np.eye(3), (n - 1, 1, 1))
    trans = np.zeros((n - 1, 3))
    trans[:, 0] = 1.0
    graph = PoseGraph(node_ids=np.arange(n), rotations=np.tile(np.eye(3), (n, 1, 1)),
                      translations=np.zeros((n, 3)),
                      edge_nodes=np.c_[np.arange(n - 1), np.arange(1, n)].astype(np.int32),
                      edge_rotations=eye, edge_translations=trans,
                      edge_information=np.tile(np.eye(6), (n - 1, 1, 1)))
    graph = graph.add_gps([0, 20, 40], [[0, 0, 0], [20, 0, 0], [40, 0, 0]], np.eye(3))
    tree = build_tree(graph)
    assert tree.parent[20] == n and tree.max_depth == 21


def test_gps_forest_hangs_every_gps_pose_from_the_earth():
    """tree="gps": each GPS pose is a child of the earth, linked by its first reading; so a
    GPS domain is that one pose, and the tree is shallow."""
    rng = np.random.default_rng(3)
    graph, _, _ = random_graph(rng, n=30, extra=10, gps=6)
    first = int(graph.node_ids[graph.gps_nodes[0]])
    graph = graph.add_gps([first], [[1.0, 2.0, 3.0]], np.eye(3))  # a second reading
    tree = build_tree(graph, "gps")
    n, m = graph.num_nodes, graph.num_edges
    gps_poses = np.unique(graph.gps_nodes)
    assert np.all(tree.parent[gps_poses] == n)
    assert np.all(tree.link_kind[gps_poses] == LINK_GPS)
    for v in gps_poses:
        assert tree.link_index[v] == np.flatnonzero(graph.gps_nodes == v)[0]
    others = np.setdiff1d(np.arange(n), gps_poses)
    assert np.all(tree.link_kind[others] == LINK_EDGE)
    assert np.all(np.diff(tree.path_ptr)[m:] == 1)  # every GPS domain: its own pose
    assert tree.max_depth <= build_tree(graph).max_depth


def test_parts_without_gps_are_rejected():
    rng = np.random.default_rng(3)
    g1, _, _ = random_graph(rng, n=5, extra=2)
    g2, _, _ = random_graph(rng, n=4, extra=1)
    two = PoseGraph(node_ids=np.r_[g1.node_ids, g2.node_ids + 1000],
                    rotations=np.r_[g1.rotations, g2.rotations],
                    translations=np.r_[g1.translations, g2.translations],
                    edge_nodes=np.r_[g1.edge_nodes, g2.edge_nodes + 5],
                    edge_rotations=np.r_[g1.edge_rotations, g2.edge_rotations],
                    edge_translations=np.r_[g1.edge_translations, g2.edge_translations],
                    edge_information=np.r_[g1.edge_information, g2.edge_information])
    with pytest.raises(GraphError, match="not connected"):
        build_tree(two)
    with_gps = two.add_gps(int(two.node_ids[0]), [0, 0, 0], np.eye(3))
    with pytest.raises(GraphError, match=r"no GPS constraint.*pose id\(s\) \[1003\]"):
        build_tree(with_gps)
    both = with_gps.add_gps(1003, [5, 0, 0], np.eye(3))
    assert build_tree(both).num_tree_nodes == two.num_nodes + 1


def test_more_than_one_fix_is_refused_by_the_tree():
    rng = np.random.default_rng(4)
    graph, _, _ = random_graph(rng, n=6, extra=2)
    graph = dataclasses.replace(graph, fixed_nodes=np.array([0, 3], np.int32))
    with pytest.raises(GraphError, match="FIX"):
        build_tree(graph)
    one = dataclasses.replace(graph, fixed_nodes=np.array([3], np.int32))
    assert build_tree(one).root == 3


def test_file_init_without_vertices_is_a_clear_error():
    rng = np.random.default_rng(5)
    graph, _, _ = random_graph(rng, n=6, extra=2)
    graph = dataclasses.replace(graph, has_estimates=False)
    with pytest.raises(GraphError, match="init='tree'"):
        initial_locals(graph, build_tree(graph), "file")
