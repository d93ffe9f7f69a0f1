"""The pose tree and constraint paths (paper III-A, docs/mathematics.md#pose-tree,
docs/contributing.md#data).

Each non-root node stores its pose relative to its parent (the *local transform*).  A
constraint's *root* is the lowest common ancestor of its two nodes; its *domain* is every node
on the tree path between them except the root.  Paths are stored in CSR form:

* relative constraint c = (a, b): ``path_node[path_ptr[c]:path_ptr[c+1]]`` lists the a-side
  nodes from a up to (excluding) the root with sign -1, then the b-side nodes from b up with
  sign +1;
* GPS constraint g (constraint index ``M + g``): node n and its ancestors below the earth, sign +1.

With GPS constraints the tree has one extra node, the fixed *earth* (index ``N``), whose
children are linked to it by a GPS constraint.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from . import _tree_kernels as tk
from ._numba import kernel
from .errors import GraphError
from .graph import FloatArray, PoseGraph

I32 = npt.NDArray[np.int32]

#: Parent link kinds.
LINK_ROOT, LINK_EDGE, LINK_GPS = 0, 1, 2


class TreeKind(enum.Enum):
    """How the spanning tree is grown."""

    BFS = "bfs"
    """Breadth-first from the root, avoiding GPS edges where a relative edge reaches (paper)."""
    MST = "mst"
    """Maximum-stiffness spanning tree (stiffness = trace of the information), then rooted."""
    GPS = "gps"
    """Breadth-first from the earth through every GPS reading (each GPS pose a child of the
    earth, the rest reached by relative edges): GPS domains of one node and shallow
    subtrees, so far fewer per-path blocks than one anchor per part (experimental)."""
    TORO = "toro"
    """TORO's tree: nodes visited by increasing index from the root, each taking as parent its
    smallest-index visited neighbour; with GPS readings, a pose hangs from the earth (whose
    index is the largest) only where no pose reaches it first."""


@dataclass(frozen=True, slots=True)
class PoseTree:
    """A rooted spanning tree over the poses (plus the earth node when there is GPS)."""

    num_poses: int
    """N, the number of poses of the graph."""
    has_earth: bool
    """True when node ``N`` is the earth (the graph has GPS constraints)."""
    root: int
    """Index of the fixed root (``N`` for the earth)."""
    parent: I32
    """(T,) parent index, -1 for the root; T = N + has_earth."""
    link_kind: npt.NDArray[np.int8]
    """(T,) LINK_ROOT, LINK_EDGE or LINK_GPS: what joins the node to its parent."""
    link_index: I32
    """(T,) edge index (LINK_EDGE) or GPS index (LINK_GPS) of the link, -1 for the root."""
    link_forward: npt.NDArray[np.bool_]
    """(T,) True when the linking edge is stored as (parent, child)."""
    depth: I32
    """(T,) depth below the root (root: 0)."""
    order: I32
    """(T,) nodes in breadth-first order (every parent before its children)."""
    path_ptr: npt.NDArray[np.int64]
    """(C+1,) CSR offsets of the constraint paths; constraints are the M edges then the G GPS."""
    path_node: I32
    """(nnz,) domain nodes."""
    path_sign: npt.NDArray[np.int8]
    """(nnz,) -1 on the a side, +1 on the b side (and for GPS)."""
    constraint_root: I32
    """(C,) the lowest common ancestor of each constraint (the earth for GPS)."""
    sweep_order: I32
    """(C,) constraint indices sorted by increasing root depth (stable; paper Algorithm 1)."""

    @property
    def num_tree_nodes(self) -> int:
        return int(self.parent.shape[0])

    @property
    def num_constraints(self) -> int:
        return int(self.path_ptr.shape[0] - 1)

    def path_lengths(self) -> npt.NDArray[np.int64]:
        """(C,) domain size d of every constraint."""
        return np.diff(self.path_ptr)

    @property
    def max_depth(self) -> int:
        return int(self.depth.max())


def _stiffness(info: FloatArray) -> FloatArray:
    out: FloatArray = np.trace(info, axis1=1, axis2=2)
    return out


def build_tree(graph: PoseGraph, kind: TreeKind | str = TreeKind.BFS) -> PoseTree:
    """Grow the pose tree of ``graph`` and compute every constraint's path.

    Raises
    ------
    GraphError
        If the graph is not connected, or (with GPS) a part of it has no GPS constraint, which
        leaves that part without a gauge.
    """
    kind = TreeKind(kind)
    n, m, g = graph.num_nodes, graph.num_edges, graph.num_gps
    has_earth = g > 0
    t_nodes = n + (1 if has_earth else 0)
    a = graph.edge_nodes[:, 0].astype(np.int64)
    b = graph.edge_nodes[:, 1].astype(np.int64)

    # --- the edges the tree may use (all relative edges, or a maximum-stiffness forest)
    if kind is TreeKind.MST and m:
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        w = 1.0 / (1.0 + _stiffness(graph.edge_information))  # small weight = stiff
        key = lo * n + hi
        order = np.lexsort((w, key))
        first = np.ones(order.shape[0], bool)
        first[1:] = key[order[1:]] != key[order[:-1]]
        keep = order[first]
        mst = minimum_spanning_tree(
            sp.coo_matrix((w[keep], (lo[keep], hi[keep])), shape=(n, n)).tocsr()
        )
        mst = mst.tocoo()
        ta, tb = mst.row.astype(np.int64), mst.col.astype(np.int64)
    else:
        ta, tb = a, b

    # --- root and (with GPS) the anchors that hang each component from the earth
    if has_earth:
        ncomp, comp = connected_components(
            sp.coo_matrix((np.ones(m), (a, b)), shape=(n, n)), directed=False
        )
        anchor = np.full(ncomp, -1, np.int64)
        anchor_gps = np.full(ncomp, -1, np.int64)
        # Each part hangs from the earth by the GPS reading nearest its centre (fewest hops to
        # the farthest pose), which keeps the tree shallow: constraint paths, and so update
        # costs, are about half as long as from an end of the drive.
        ecc = _eccentricity_bound(
            sp.coo_matrix((np.ones(m), (a, b)), shape=(n, n)).tocsr(), comp, ncomp, graph.gps_nodes
        )
        for k in range(g - 1, -1, -1):  # ties: the first GPS constraint in file order
            node = graph.gps_nodes[k]
            c = comp[node]
            if anchor[c] < 0 or ecc[node] <= ecc[anchor[c]]:
                anchor[c] = node
                anchor_gps[c] = k
        if np.any(anchor < 0):
            missing = np.nonzero(anchor < 0)[0]
            ids = [int(graph.node_ids[np.argmax(comp == c)]) for c in missing[:5]]
            raise GraphError(
                f"{missing.size} part(s) of the graph have no GPS constraint and so no gauge "
                f"in the earth frame (e.g. the part containing pose id(s) {ids}); add GPS "
                "readings to them or link them to the rest with relative constraints"
            )
        root = n
        if kind is TreeKind.GPS:  # every GPS pose hangs from the earth (first reading's link)
            anchored, first = np.unique(graph.gps_nodes, return_index=True)
            first_gps = np.full(n, -1, np.int64)
            first_gps[anchored] = first
            ea = np.concatenate([ta, np.full(anchored.shape[0], n, np.int64)])
            eb = np.concatenate([tb, anchored])
        else:
            ea = np.concatenate([ta, np.full(ncomp, n, np.int64)])
            eb = np.concatenate([tb, anchor])
    else:
        if graph.fixed_nodes.size > 1:
            raise GraphError(
                f"the graph fixes {graph.fixed_nodes.size} poses (FIX lines); the pose tree holds "
                "exactly one pose fixed, its root: keep one FIX line, or use the exact solver"
            )
        root = int(graph.fixed_nodes[0]) if graph.fixed_nodes.size else 0
        ea, eb = ta, tb
        anchor_gps = np.zeros(0, np.int64)

    if kind is TreeKind.TORO:
        return _toro_tree(graph, root)
    adj = sp.coo_matrix((np.ones(ea.shape[0]), (ea, eb)), shape=(t_nodes, t_nodes)).tocsr()
    order, pred = breadth_first_order(adj, root, directed=False, return_predecessors=True)
    if order.shape[0] != t_nodes:
        graph.check_connected()
        raise GraphError("the graph is not connected")  # pragma: no cover - check_connected raises
    parent = pred.astype(np.int32)
    parent[root] = -1
    return tree_from_parents(graph, parent, root, order=order.astype(np.int32),
                             stiffest=kind is TreeKind.MST)


def _toro_tree(graph: PoseGraph, root: int) -> PoseTree:
    """TORO's tree (:data:`TreeKind.TORO`): visit nodes by increasing index from the root, each
    taking as parent its smallest-index visited neighbour; GPS readings are edges to the
    earth, whose index is the largest."""
    from ._tree_kernels import smallest_id_tree

    n, g = graph.num_nodes, graph.num_gps
    t_nodes = n + int(g > 0)
    a = np.concatenate([graph.edge_nodes[:, 0].astype(np.int64), np.full(g, n, np.int64)])
    b = np.concatenate([graph.edge_nodes[:, 1].astype(np.int64),
                        graph.gps_nodes.astype(np.int64)])
    src = np.concatenate([a, b])
    dst = np.concatenate([b, a])
    srt = np.lexsort((dst, src))  # CSR adjacency, neighbours sorted
    indptr = np.zeros(t_nodes + 1, np.int64)
    np.cumsum(np.bincount(src, minlength=t_nodes), out=indptr[1:])
    parent = np.empty(t_nodes, np.int32)
    order = np.empty(t_nodes, np.int32)
    visited = smallest_id_tree(indptr, np.ascontiguousarray(dst[srt]), root, parent, order)
    if visited != t_nodes:
        graph.check_connected()
        raise GraphError("the graph is not connected")  # pragma: no cover
    return tree_from_parents(graph, parent, root, order=order)


def tree_from_parents(graph: PoseGraph, parent: npt.ArrayLike, root: int, *,
                      order: npt.ArrayLike | None = None, stiffest: bool = False) -> PoseTree:
    """The :class:`PoseTree` of ``graph`` with the given parent of every tree node.

    Parameters
    ----------
    graph : PoseGraph
    parent : (T,) int
        Parent of each tree node (T = N, or N + 1 with the earth ``N`` when the graph has GPS
        readings), -1 at ``root``.  Every child of the earth must have a GPS reading, every
        other parent link must be a relative edge of the graph.
    root : int
    order : (T,) int, optional
        The nodes with every parent before its children (default: by depth).
    stiffest : bool
        A node linked to its parent by parallel edges uses the stiffest (largest information
        trace) as its link; by default the first in file order.  A GPS link is the node's first
        reading in file order.

    Raises
    ------
    GraphError
        A parent link that is not a constraint of the graph.
    """
    n, m, g = graph.num_nodes, graph.num_edges, graph.num_gps
    has_earth = g > 0
    t_nodes = n + int(has_earth)
    parent = np.ascontiguousarray(parent, np.int32)
    if parent.shape != (t_nodes,):
        raise ValueError(f"parent must have shape ({t_nodes},), got {parent.shape}")
    a = graph.edge_nodes[:, 0].astype(np.int64)
    b = graph.edge_nodes[:, 1].astype(np.int64)
    depth = np.zeros(t_nodes, np.int32)
    if order is None:
        _depths_unordered(parent, depth)
        order = np.argsort(depth, kind="stable").astype(np.int32)
    else:
        order = np.ascontiguousarray(order, np.int32)
        tk.depths(order, parent, depth)

    # --- which constraint links each node to its parent
    link_kind = np.zeros(t_nodes, np.int8)
    link_index = np.full(t_nodes, -1, np.int32)
    link_forward = np.zeros(t_nodes, bool)
    child = np.nonzero(parent >= 0)[0]
    if has_earth:
        gps_child = child[parent[child] == n]
        child = child[parent[child] != n]
        first = np.full(n, -1, np.int64)
        first[graph.gps_nodes[::-1]] = np.arange(g - 1, -1, -1)
        if np.any(first[gps_child] < 0):
            raise GraphError("a pose hangs from the earth without a GPS reading")
        link_kind[gps_child] = LINK_GPS
        link_index[gps_child] = first[gps_child]
        link_forward[gps_child] = True
    if child.size:
        key_e = np.minimum(a, b) * t_nodes + np.maximum(a, b)
        if stiffest:  # the stiffest of parallel edges
            srt = np.lexsort((-_stiffness(graph.edge_information), key_e))
        else:  # the first in file order
            srt = np.argsort(key_e, kind="stable")
        p = parent[child].astype(np.int64)
        key_c = np.minimum(p, child) * t_nodes + np.maximum(p, child)
        pos = np.minimum(np.searchsorted(key_e[srt], key_c), max(m - 1, 0))
        e_idx = srt[pos] if m else np.zeros(0, np.int64)
        if not m or not np.all(key_e[e_idx] == key_c):
            raise GraphError("a parent link is not a relative edge of the graph")
        link_kind[child] = LINK_EDGE
        link_index[child] = e_idx
        link_forward[child] = a[e_idx] == p

    # --- the constraint paths (relative edges, then GPS readings from the earth)
    ends = np.empty((m + g, 2), np.int32)
    ends[:m] = graph.edge_nodes
    ends[m:, 0] = n
    ends[m:, 1] = graph.gps_nodes
    lengths = np.zeros(m + g, np.int64)
    croot = np.zeros(m + g, np.int32)
    tk.path_lengths(ends, parent, depth, lengths, croot)
    ptr = np.zeros(m + g + 1, np.int64)
    np.cumsum(lengths, out=ptr[1:])
    path_node = np.empty(ptr[-1], np.int32)
    path_sign = np.empty(ptr[-1], np.int8)
    tk.fill_paths(ends, parent, croot, ptr[:-1], path_node, path_sign)
    sweep = np.argsort(depth[croot], kind="stable").astype(np.int32)

    arrays = dict(
        parent=parent,
        link_kind=link_kind,
        link_index=link_index,
        link_forward=link_forward,
        depth=depth,
        order=order,
        path_ptr=ptr,
        path_node=path_node,
        path_sign=path_sign,
        constraint_root=croot,
        sweep_order=sweep,
    )
    for v in arrays.values():
        v.flags.writeable = False
    return PoseTree(num_poses=n, has_earth=has_earth, root=root, **arrays)


def _eccentricity_bound(
    adj: sp.csr_matrix, comp: np.ndarray, ncomp: int, seeds: np.ndarray
) -> np.ndarray:
    """Per node, max(hops to u, hops to v) for a far pair (u, v) of its part (double sweep).

    A cheap stand-in for the eccentricity: it is smallest near the middle of the part.
    """
    from scipy.sparse.csgraph import shortest_path

    n = adj.shape[0]
    out = np.zeros(n)
    starts = np.full(ncomp, -1, np.int64)
    for node in seeds[::-1]:
        starts[comp[node]] = node
    for c in range(ncomp):
        if starts[c] < 0:
            continue
        d0 = shortest_path(adj, directed=False, unweighted=True, indices=int(starts[c]))
        d0[~np.isfinite(d0)] = -1
        u = int(np.argmax(d0))
        du = shortest_path(adj, directed=False, unweighted=True, indices=u)
        du[~np.isfinite(du)] = -1
        v = int(np.argmax(du))
        dv = shortest_path(adj, directed=False, unweighted=True, indices=v)
        mask = comp == c
        out[mask] = np.maximum(du[mask], dv[mask])
    return out


@kernel
def _depths_unordered(parent: np.ndarray, depth: np.ndarray) -> None:
    """Depth of every node from the parent array alone (each walk stops at a known depth)."""
    known = np.zeros(parent.shape[0], np.bool_)
    stack = np.empty(parent.shape[0], np.int64)
    for i in range(parent.shape[0]):
        k = 0
        u = i
        while u >= 0 and not known[u]:
            stack[k] = u
            k += 1
            u = parent[u]
        d = -1 if u < 0 else depth[u]
        for j in range(k - 1, -1, -1):
            d += 1
            depth[stack[j]] = d
            known[stack[j]] = True


# --------------------------------------------------------------------------- poses <-> locals
def locals_from_globals(parent: np.ndarray, grot: np.ndarray, gtr: np.ndarray,
                        rot: np.ndarray, trans: np.ndarray) -> None:
    """Local transforms ``T_i = G_parent^-1 G_i`` (``rot``, ``trans``: written) of global poses
    (``parent`` < 0: ``T_i = G_i``).  The arguments are normalized (int32 parents, read-only
    poses) so the kernel is compiled once, whoever calls it."""
    ro_rot = np.ascontiguousarray(grot).view()
    ro_tr = np.ascontiguousarray(gtr).view()
    ro_rot.flags.writeable = ro_tr.flags.writeable = False
    tk.locals_from_globals(np.ascontiguousarray(parent, np.int32), ro_rot, ro_tr, rot, trans)


def global_poses(
    tree: PoseTree, rot: FloatArray, trans: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Global poses ``(R (N,3,3), t (N,3))`` of the N poses from local transforms (no earth)."""
    t_nodes = tree.num_tree_nodes
    grot = np.empty((t_nodes, 3, 3))
    gtr = np.empty((t_nodes, 3))
    tk.globals_from_locals(tree.order, tree.parent, rot, trans, grot, gtr)
    n = tree.num_poses
    return grot[:n].copy(), gtr[:n].copy()
