"""The batch of a loop closure's neighbours (OnlineSolver._loop_neighbours / _loop_batch) and
the kernels it measures with: each against a naive twin, and the batch against the frame
without it from the same saved state."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from graphs import random_graph

from hybridpgo.io import bundled_path, read_graph
from hybridpgo.online import OnlineConfig, OnlineSolver
from hybridpgo.online import solver as online_solver
from hybridpgo.online.replay import feed_frame, make_stream
from hybridpgo.solvers.hybrid import _admission as adm


def _fed(graph, frames: int, **cfg) -> OnlineSolver:  # type: ignore[no-untyped-def]
    s = OnlineSolver(OnlineConfig(background_refine=False, **cfg))
    st = make_stream(graph)
    for k in range(frames):
        feed_frame(s, st, k)
        s.update(None, 30)
    return s


def _random(seed: int):  # type: ignore[no-untyped-def]
    g, _, _ = random_graph(np.random.default_rng(seed), n=60, extra=40, gps=0, noise=0.05)
    return g


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_crossing_is_every_constraint_sharing_a_path_node(seed: int) -> None:
    g = _random(seed)
    s = _fed(g, g.num_nodes)
    st = s._store
    prob, _, _ = st.views()
    m = st.m_laid
    rejected = np.zeros(st.rejected.shape[0], np.bool_)
    rejected[np.random.default_rng(seed).choice(m, 5, replace=False)] = True
    paths = [set(st.path_node[st.ptr[e]: st.ptr[e + 1]].tolist()) for e in range(m)]
    mark = np.zeros(st.placed + 1, np.bool_)
    out = np.empty(m, np.int64)
    for c in range(m):
        k = adm.crossing(prob, m, c, rejected, mark, out)
        naive = [e for e in range(m) if e != c and not rejected[e] and paths[e] & paths[c]]
        assert out[:k].tolist() == naive, c
        assert not mark.any()  # left as found


def test_edge_chi2s_sum_to_the_energy() -> None:
    g = _random(3)
    s = _fed(g, g.num_nodes)
    st = s._store
    prob, state, _ = st.views()
    cs = np.arange(st.m_laid, dtype=np.int64)
    out = np.empty(cs.size)
    total = adm.edge_chi2s(prob, state, cs, st.scratch(None).wk, out)
    assert total == pytest.approx(s.energy(), rel=1e-9)
    assert total == pytest.approx(out.sum(), rel=1e-12)
    assert (out >= 0).all()


def _city():  # type: ignore[no-untyped-def]
    """M3500: its loop closures go around blocks, with older loops on their paths."""
    return read_graph(bundled_path("M3500_isam.txt"))


def test_the_batch_lowers_e_where_the_loop_update_spread_its_error(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Loop-closure frames of M3500, each replayed twice from one saved state at the
    optimum of its prefix (as the worker's answer leaves it), with and without the batch:
    where the batch ran, E ends lower in sum, and it ran."""
    g = _city()
    st = make_stream(g)
    s = OnlineSolver(OnlineConfig(background_refine=False))
    gains: list[float] = []
    for k in range(400):
        e0, e1 = int(st.edge_ptr[k]), int(st.edge_ptr[k + 1])
        ends = g.edge_nodes[st.edges[e0:e1]]
        loop = e1 > e0 and int(np.abs(ends[:, 0] - ends[:, 1]).max()) > 20
        if loop and k >= 150 and len(gains) < 4:
            s.refine(20)
            path = tmp_path / f"{k}.npz"
            s.save(path)
            energies = []
            nodes = []
            for size in (0, 32):
                t = OnlineSolver.load(path)
                t.config = dataclasses.replace(t.config, loop_batch=size)
                feed_frame(t, st, k)
                nodes.append(t.update(None, 30).local_nodes)
                energies.append(t.energy())
                t.close()
            assert nodes[0] == 0  # local_size is 0: only the loop batch moves local nodes
            if nodes[1]:
                gains.append(energies[0] - energies[1])
        feed_frame(s, st, k)
        s.update(None, 30)
    s.close()
    assert gains, "the batch never ran"
    assert sum(gains) > 0, gains


def _batches(graph, frames: int, **cfg) -> int:  # type: ignore[no-untyped-def]
    """Frames of the stream's first ``frames`` whose loop batch ran."""
    s = OnlineSolver(OnlineConfig(background_refine=False, **cfg))
    st = make_stream(graph)
    n = 0
    for k in range(frames):
        feed_frame(s, st, k)
        n += s.update(None, 30).local_nodes > 0
    s.close()
    return n


def test_the_share_decides(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """With the share at infinity the batch never runs, at zero it runs wherever a loop
    closure's update raised its neighbours' χ² at all; never with ``loop_batch=0``."""
    g = _city()
    assert _batches(g, 400, loop_batch=0) == 0
    monkeypatch.setattr(online_solver, "LOOP_SHARE", np.inf)
    assert _batches(g, 400) == 0
    monkeypatch.setattr(online_solver, "LOOP_SHARE", 0.0)
    assert _batches(g, 400) > 0


def test_config_bounds() -> None:
    with pytest.raises(ValueError, match="loop_batch"):
        OnlineConfig(loop_batch=-1)
    with pytest.raises(ValueError, match="loop_batch must be at most 64"):
        OnlineConfig(loop_batch=65)
    assert OnlineConfig().loop_batch == 32
