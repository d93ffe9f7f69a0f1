"""Chordal initialization: exact on noise-free graphs, and a valid start for the solvers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo.energy import energy
from hybridpgo.initialization import chordal_initialization
from hybridpgo.tree import build_tree, global_poses, initial_locals

#: Linear solves of well-conditioned small systems.
LINEAR_SOLVE = 1e-9


@pytest.mark.parametrize("gps", [0, 4])
def test_chordal_recovers_noise_free_poses(gps):
    rng = np.random.default_rng(0)
    graph, rot, trans = random_graph(rng, n=20, extra=15, gps=gps, rot_scale=1.0, noise=0.0)
    # the gauge pose keeps its file value: give it the true one; GPS readings exact too
    est_rot = graph.rotations.copy()
    est_trans = graph.translations.copy()
    est_rot[0], est_trans[0] = rot[0], trans[0]
    graph = dataclasses.replace(
        graph, rotations=est_rot, translations=est_trans, gps_positions=trans[graph.gps_nodes]
    )
    r, t = chordal_initialization(graph, gauge=0)
    np.testing.assert_allclose(r, rot, rtol=0, atol=LINEAR_SOLVE)
    np.testing.assert_allclose(t, trans, rtol=0, atol=LINEAR_SOLVE * 100)
    assert energy(graph, r, t) < LINEAR_SOLVE


def test_chordal_beats_dead_reckoning_under_rotation_noise():
    rng = np.random.default_rng(1)
    graph, _, _ = random_graph(rng, n=60, extra=60, rot_scale=0.2, noise=0.15, anisotropic=False)
    tree = build_tree(graph)
    e_tree = energy(graph, *global_poses(tree, *initial_locals(graph, tree, "tree")))
    e_chordal = energy(graph, *global_poses(tree, *initial_locals(graph, tree, "chordal")))
    assert e_chordal < 0.5 * e_tree
