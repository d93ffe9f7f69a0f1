"""Rebuilding an online solver's store from the members of a saved state (:mod:`.persist`).

Every value the kernels index with is checked here before it reaches the store: ids, parents,
edge and GPS endpoints, odometry links, the queue, the groups.  Every matrix is checked as the
API's ``add_*`` checks its input (finite, rotations orthonormal, information SPD, whitening
recomputed).  Depths, paths, path counts and group membership are recomputed from the parents
and the constraints, so no derived array of the file is trusted.  A check that fails raises
``ValueError`` (or :class:`~hybridpgo.errors.GraphError`), which the loader turns into one
:class:`~hybridpgo.errors.FormatError`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import _tree_kernels as tk
from ._validate import ROTATION_TOL
from .store import MapStore


def _rotations(name: str, r: np.ndarray) -> None:
    """Raise unless every (3, 3) of ``r`` is a rotation."""
    if r.shape[0] == 0:
        return
    dev = np.abs(np.einsum("kji,kjl->kil", r, r) - np.eye(3)).max(axis=(1, 2))
    bad = np.nonzero((dev > ROTATION_TOL) | (np.linalg.det(r) <= 0))[0]
    if bad.size:
        raise ValueError(f"{name}[{int(bad[0])}] is not a rotation")


def _whitening(name: str, info: np.ndarray) -> np.ndarray:
    """``L^T`` of every SPD information of ``info`` (k, d, d); raise unless each is SPD."""
    if info.shape[0] == 0:
        return np.zeros_like(info)
    scale = np.abs(info).max(axis=(1, 2))
    asym = np.abs(info - np.swapaxes(info, 1, 2)).max(axis=(1, 2))
    bad = np.nonzero(asym > 1e-9 * np.maximum(scale, 1e-300))[0]
    if bad.size:
        raise ValueError(f"{name}[{int(bad[0])}] is not symmetric")
    try:
        low = np.linalg.cholesky(info)
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"{name} holds a matrix that is not positive definite") from exc
    if not np.all(np.isfinite(low)):
        raise ValueError(f"{name} holds a matrix that is not positive definite")
    return np.ascontiguousarray(np.swapaxes(low, 1, 2))


def _in_range(name: str, a: np.ndarray, lo: int, hi: int) -> None:
    """Raise unless every entry of ``a`` is in ``lo..hi-1``."""
    if a.size and (int(a.min()) < lo or int(a.max()) >= hi):
        raise ValueError(f"{name} holds an index outside {lo}..{hi - 1}")


def _constraint_names(name: str, names: np.ndarray, m: int, g: int) -> None:
    """Arrival-order names: edge ``0..m-1`` or GPS reading ``-1..-g``."""
    if names.size and (int(names.max()) >= m or int(names.min()) < -g):
        raise ValueError(f"{name} names a constraint that does not exist")


def restore(st: MapStore, meta: dict[str, Any], d: dict[str, np.ndarray]) -> None:
    """Fill the new, empty store ``st`` from the members ``d``, checking every value first
    (the index of the edges by their pose pair, the solver's duplicate check, included)."""
    sz = {k: int(meta[k]) for k in ("n", "placed", "m", "m_laid", "g", "g_laid", "frame",
                                    "ngroups")}
    n, placed, m, m_laid, g, g_laid = (sz[k] for k in ("n", "placed", "m", "m_laid", "g",
                                                       "g_laid"))
    frame, ngroups = sz["frame"], sz["ngroups"]
    if not (placed <= n and m_laid <= m and g_laid <= g and ngroups <= n):
        raise ValueError("inconsistent counters")
    # --- inputs
    ids = d["ids"].astype(np.int64)
    if np.unique(ids).size != n:
        raise ValueError("duplicate pose ids")
    edge_ab = d["edge_ab"].astype(np.int64)
    _in_range("edge_ab", edge_ab, 0, n)
    if m and np.any(edge_ab[:, 0] == edge_ab[:, 1]):
        raise ValueError("an edge joins a pose to itself")
    _rotations("edge_rot", d["edge_rot"])
    edge_lt = _whitening("edge_info", d["edge_info"])
    gps_node = d["gps_node"].astype(np.int64)
    _in_range("gps_node", gps_node, 0, n)
    gps_lt = _whitening("gps_info", d["gps_info"])
    odom = d["odom"].astype(np.int64)
    if n and odom[0] != -1:
        raise ValueError("the first pose has an odometry edge")
    _in_range("odom", odom[1:], 0, m)
    if n > 1 and not (np.all(edge_ab[odom[1:], 1] == np.arange(1, n))
                      and np.all(edge_ab[odom[1:], 0] < np.arange(1, n))):
        raise ValueError("an odometry edge does not join a pose to an earlier one")
    _rotations("first_rot", d["first_rot"][None])
    # --- the tree: parents older than their children, every laid constraint on placed poses
    parent = d["parent"].astype(np.int64)
    if parent[0] != -1:
        raise ValueError("the earth has a parent")
    if placed and not np.all((parent[1:] >= 0) & (parent[1:] < np.arange(1, placed + 1))):
        raise ValueError("a pose's parent is not an older tree node")
    _in_range("edge_ab of a laid edge", edge_ab[:m_laid], 0, placed)
    _in_range("gps_node of a laid reading", gps_node[:g_laid], 0, placed)
    _rotations("rot", d["rot"])
    # --- everything checked: fill the store, then derive what can be derived
    st.ensure_nodes(n + 2)
    st.ensure_constraints(m, g)
    st.n, st.placed, st.m, st.g = n, placed, m, g
    st.ids[:n], st.odom[:n] = ids, odom
    st.first_rot, st.first_trans = d["first_rot"].astype(np.float64), d["first_trans"].astype(
        np.float64)
    st.parent[: placed + 1] = parent
    st.rot[: placed + 1], st.trans[: placed + 1] = d["rot"], d["trans"]
    st.bdiag[: placed + 1] = d["bdiag"]
    st.slot[: placed + 1] = -1
    depth = st.depth
    tk.depths(np.arange(placed + 1, dtype=np.int32), st.parent, depth)
    st.edge_ab[:m], st.edge_rot[:m], st.edge_trans[:m] = edge_ab, d["edge_rot"], d["edge_trans"]
    st.edge_info[:m], st.edge_lt[:m] = d["edge_info"], edge_lt
    st.gps_node[:g], st.gps_pos[:g], st.gps_info[:g], st.gps_lt[:g] = (
        gps_node, d["gps_pos"], d["gps_info"], gps_lt)
    cm = st.cap_m
    st.group_of[:m] = -1
    st.group_of[cm: cm + g] = -1
    st.m_laid = st.g_laid = 0
    _lay(st, m_laid, g_laid)
    _contributions(st, d)
    for key, lo in (("chi2_e", 0), ("chi2_g", cm)):
        vals = d[key]
        if vals.size and vals.min() < 0:
            raise ValueError(f"{key} holds a negative χ²")
        st.chi2[lo: lo + vals.shape[0]] = vals
    _groups(st, d, ngroups, m, g, frame)
    queue = d["queue"].astype(np.int64)
    _constraint_names("queue", queue, m, g)
    if np.unique(queue).size != queue.size:
        raise ValueError("the queue lists a constraint twice")
    st.set_queue(st.store_indices(queue))
    model = d["model"].astype(np.float64)
    if not np.all(model > 0):
        raise ValueError("the cost model is not positive")
    st.model[:] = model
    st.gps_links = int(meta["gps_links"])
    st.index_pairs()
    st._views = None
    rejected = d["rejected"].astype(np.int64)
    _constraint_names("rejected", rejected, m_laid, g_laid)
    if np.unique(rejected).size != rejected.size:
        raise ValueError("rejected lists a constraint twice")
    st.set_rejected(rejected[rejected >= 0], -rejected[rejected < 0] - 1, (m_laid, g_laid))
    requeue = d["requeue"].astype(np.int64)
    _constraint_names("requeue", requeue, m_laid, g_laid)
    if np.unique(requeue).size != requeue.size:
        raise ValueError("the requeue lists a constraint twice")
    st.requeue = st.store_indices(requeue)


def _lay(st: Any, m_laid: int, g_laid: int) -> None:
    """Lay the paths of the first ``m_laid`` edges and ``g_laid`` GPS readings."""
    m, g = st.m, st.g
    st.m, st.g = m_laid, g_laid
    st.lay_paths()
    st.m, st.g = m, g


def _contributions(st: Any, d: dict[str, np.ndarray]) -> None:
    """The saved contributions, whose number must match the recomputed paths."""
    pe = int(st.ptr[st.m_laid])
    g0, g1 = st.cap_pe, int(st.ptr[st.cap_m + st.g_laid])
    if d["contrib_e"].shape[0] != pe or d["contrib_g"].shape[0] != g1 - g0:
        raise ValueError("the contributions do not match the constraint paths")
    st.contrib[:pe] = d["contrib_e"]
    st.contrib[g0:g1] = d["contrib_g"]


def _groups(st: Any, d: dict[str, np.ndarray], ngroups: int, m: int, g: int,
            frame: int) -> None:
    """The junction groups: offsets, members (each constraint in one group at most), stamps."""
    ptr = d["group_ptr"].astype(np.int64)
    members = d["group_members"].astype(np.int64)
    if ptr[0] != 0 or np.any(np.diff(ptr) < 1) or int(ptr[-1]) != members.shape[0]:
        raise ValueError("the junction groups' offsets are not increasing from 0")
    _constraint_names("group_members", members, m, g)
    inner = st.store_indices(members)
    if np.unique(inner).size != inner.size:
        raise ValueError("a constraint is in two junction groups")
    _in_range("group_stamp", d["group_stamp"], -1, frame + 1)
    st.ensure_group_members(int(inner.shape[0]))
    st.group_ptr[: ngroups + 1] = ptr
    st.group_members[: inner.shape[0]] = inner
    st.group_stamp[:ngroups] = d["group_stamp"]
    st.ngroups = ngroups
    for k in range(ngroups):
        st.group_of[inner[ptr[k]: ptr[k + 1]]] = k
