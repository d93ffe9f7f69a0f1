"""The pose tree and constraint paths (paper III-A, DESIGN.md §2, §8).

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
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

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


class InitKind(enum.Enum):
    """Where the initial local transforms come from."""

    TREE = "tree"
    """Concatenate the tree edges' measurements down from the root (paper III-A)."""
    FILE = "file"
    """The file's vertex estimates, ``T_i = X_parent^-1 X_i``."""
    CHORDAL = "chordal"
    """Chordal relaxation of the rotations, then linear translations (robust to rotation noise)."""


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

    adj = sp.coo_matrix((np.ones(ea.shape[0]), (ea, eb)), shape=(t_nodes, t_nodes)).tocsr()
    order, pred = breadth_first_order(adj, root, directed=False, return_predecessors=True)
    if order.shape[0] != t_nodes:
        graph.check_connected()
        raise GraphError("the graph is not connected")  # pragma: no cover - check_connected raises
    parent = pred.astype(np.int32)
    parent[root] = -1

    # --- which constraint links each node to its parent
    link_kind = np.zeros(t_nodes, np.int8)
    link_index = np.full(t_nodes, -1, np.int32)
    link_forward = np.zeros(t_nodes, bool)
    child = np.nonzero(parent >= 0)[0]
    if has_earth:
        gps_child = child[parent[child] == n]
        child = child[parent[child] != n]
        link_kind[gps_child] = LINK_GPS
        if kind is TreeKind.GPS:
            link_index[gps_child] = first_gps[gps_child]
        else:
            link_index[gps_child] = anchor_gps[comp[gps_child]]
        link_forward[gps_child] = True
    if child.size:
        key_e = np.minimum(a, b) * t_nodes + np.maximum(a, b)
        if kind is TreeKind.MST:  # the stiffest of parallel edges
            srt = np.lexsort((-_stiffness(graph.edge_information), key_e))
        else:  # the first in file order
            srt = np.argsort(key_e, kind="stable")
        p = parent[child].astype(np.int64)
        key_c = np.minimum(p, child) * t_nodes + np.maximum(p, child)
        pos = np.searchsorted(key_e[srt], key_c)
        e_idx = srt[pos]
        assert np.all(key_e[e_idx] == key_c)
        link_kind[child] = LINK_EDGE
        link_index[child] = e_idx
        link_forward[child] = a[e_idx] == p

    depth = np.zeros(t_nodes, np.int32)
    _depths(order.astype(np.int32), parent, depth)

    c_nodes = np.empty((m + g, 2), np.int32)
    c_nodes[:m] = graph.edge_nodes
    c_nodes[m:, 0] = n
    c_nodes[m:, 1] = graph.gps_nodes
    lengths = np.zeros(m + g, np.int64)
    croot = np.zeros(m + g, np.int32)
    _path_lengths(c_nodes, parent, depth, lengths, croot)
    ptr = np.zeros(m + g + 1, np.int64)
    np.cumsum(lengths, out=ptr[1:])
    path_node = np.empty(ptr[-1], np.int32)
    path_sign = np.empty(ptr[-1], np.int8)
    _fill_paths(c_nodes, parent, depth, ptr, path_node, path_sign)
    sweep = np.argsort(depth[croot], kind="stable").astype(np.int32)

    arrays = dict(
        parent=parent,
        link_kind=link_kind,
        link_index=link_index,
        link_forward=link_forward,
        depth=depth,
        order=order.astype(np.int32),
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
def _depths(order: np.ndarray, parent: np.ndarray, depth: np.ndarray) -> None:
    for k in range(order.shape[0]):
        i = order[k]
        depth[i] = 0 if parent[i] < 0 else depth[parent[i]] + 1


@kernel
def _path_lengths(
    c_nodes: np.ndarray,
    parent: np.ndarray,
    depth: np.ndarray,
    lengths: np.ndarray,
    croot: np.ndarray,
) -> None:
    for c in range(c_nodes.shape[0]):
        u = c_nodes[c, 0]
        v = c_nodes[c, 1]
        count = 0
        while depth[u] > depth[v]:
            u = parent[u]
            count += 1
        while depth[v] > depth[u]:
            v = parent[v]
            count += 1
        while u != v:
            u = parent[u]
            v = parent[v]
            count += 2
        lengths[c] = count
        croot[c] = u


@kernel
def _fill_paths(
    c_nodes: np.ndarray,
    parent: np.ndarray,
    depth: np.ndarray,
    ptr: np.ndarray,
    path_node: np.ndarray,
    path_sign: np.ndarray,
) -> None:
    for c in range(c_nodes.shape[0]):
        a = c_nodes[c, 0]
        b = c_nodes[c, 1]
        # find the root first
        u, v = a, b
        while depth[u] > depth[v]:
            u = parent[u]
        while depth[v] > depth[u]:
            v = parent[v]
        while u != v:
            u = parent[u]
            v = parent[v]
        r = u
        k = ptr[c]
        u = a
        while u != r:
            path_node[k] = u
            path_sign[k] = -1
            k += 1
            u = parent[u]
        v = b
        while v != r:
            path_node[k] = v
            path_sign[k] = 1
            k += 1
            v = parent[v]


# --------------------------------------------------------------------------- poses <-> locals
def initial_locals(
    graph: PoseGraph, tree: PoseTree, init: InitKind | str = InitKind.TREE
) -> tuple[FloatArray, FloatArray]:
    """Initial local transforms ``(rot (T,3,3), trans (T,3))`` of every tree node.

    ``init="tree"`` concatenates tree-edge measurements (a GPS link gives the child its measured
    position and its rotation from the file, or the identity when the file has no vertices);
    ``init="file"`` uses the file's vertex estimates; ``init="chordal"`` the chordal relaxation
    (:mod:`hybridpgo.initialization`).  The root keeps its file pose (the gauge);
    the earth is the identity.
    """
    init = InitKind(init)
    if init is InitKind.FILE and not graph.has_estimates:
        raise GraphError(
            "init='file' needs vertex estimates, but the file has none "
            "(iSAM files list only constraints): use init='tree'"
        )
    t_nodes = tree.num_tree_nodes
    rot = np.zeros((t_nodes, 3, 3))
    trans = np.zeros((t_nodes, 3))
    rot[:] = np.eye(3)
    n = graph.num_nodes
    if init in (InitKind.FILE, InitKind.CHORDAL):
        if init is InitKind.CHORDAL:
            from .initialization import chordal_initialization

            grot0, gtr0 = chordal_initialization(graph, None if tree.has_earth else tree.root)
        else:
            grot0, gtr0 = graph.rotations, graph.translations
        grot = (
            np.concatenate([grot0, np.eye(3)[None]])
            if tree.has_earth
            else np.ascontiguousarray(grot0)
        )
        gtr = (
            np.concatenate([gtr0, np.zeros((1, 3))])
            if tree.has_earth
            else np.ascontiguousarray(gtr0)
        )
        locals_from_globals(tree.parent, grot, gtr, rot, trans)
        return rot, trans
    kind = tree.link_kind
    idx = tree.link_index
    e = kind == LINK_EDGE
    ei = idx[e]
    fwd = tree.link_forward[e]
    zr = graph.edge_rotations[ei]
    zt = graph.edge_translations[ei]
    # forward link (parent, child): T = Z; reversed (child, parent): T = Z^-1
    rot[e] = np.where(fwd[:, None, None], zr, np.swapaxes(zr, 1, 2))
    inv_t = -np.einsum("kji,kj->ki", zr, zt)
    trans[e] = np.where(fwd[:, None], zt, inv_t)
    gl = kind == LINK_GPS
    trans[gl] = graph.gps_positions[idx[gl]]
    if graph.has_estimates:
        rot[gl] = graph.rotations[np.nonzero(gl)[0]]
    if not tree.has_earth and tree.root < n:
        rot[tree.root] = graph.rotations[tree.root]
        trans[tree.root] = graph.translations[tree.root]
    return rot, trans


def _make_fma() -> Any:
    """``fma(a, b, c)`` = ``a * b + c`` rounded once (``llvm.fma.f64``) inside kernels."""
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    @intrinsic
    def fma(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
        sig = types.float64(types.float64, types.float64, types.float64)

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            dbl = ir.DoubleType()
            fn = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
                builder.module, ir.FunctionType(dbl, [dbl, dbl, dbl]), "llvm.fma.f64")
            return builder.call(fn, args)

        return sig, codegen

    return fma


_fma = _make_fma()


def locals_from_globals(parent: np.ndarray, grot: np.ndarray, gtr: np.ndarray,
                        rot: np.ndarray, trans: np.ndarray) -> None:
    """Local transforms ``T_i = G_parent^-1 G_i`` (``rot``, ``trans``: written) of global poses
    (``parent`` < 0: ``T_i = G_i``).  The arguments are normalized (int32 parents, read-only
    poses) so the kernel is compiled once, whoever calls it."""
    ro_rot = np.ascontiguousarray(grot).view()
    ro_tr = np.ascontiguousarray(gtr).view()
    ro_rot.flags.writeable = ro_tr.flags.writeable = False
    _locals_from_globals(np.ascontiguousarray(parent, np.int32), ro_rot, ro_tr, rot, trans)


@kernel
def _locals_from_globals(
    parent: np.ndarray, grot: np.ndarray, gtr: np.ndarray, rot: np.ndarray, trans: np.ndarray
) -> None:
    """:func:`locals_from_globals` in scalar code: ``G_p^T G_i`` and ``G_p^T (g_i - g_p)`` with
    the roundings of the ``@`` products this replaced (OpenBLAS's 3x3 kernels: fused
    multiply-adds in this order), so the starts stay bit-identical; ``@`` pulled Numba's dot
    machinery into the kernel (~5 s of compilation per signature)."""
    for i in range(parent.shape[0]):
        p = parent[i]
        if p < 0:
            for a in range(3):
                trans[i, a] = gtr[i, a]
                for b in range(3):
                    rot[i, a, b] = grot[i, a, b]
            continue
        d0 = gtr[i, 0] - gtr[p, 0]
        d1 = gtr[i, 1] - gtr[p, 1]
        d2 = gtr[i, 2] - gtr[p, 2]
        for a in range(3):
            for b in range(3):
                rot[i, a, b] = _fma(grot[p, 2, a], grot[i, 2, b],
                                    _fma(grot[p, 1, a], grot[i, 1, b],
                                         grot[p, 0, a] * grot[i, 0, b]))
            trans[i, a] = _fma(grot[p, 2, a], d2, _fma(grot[p, 1, a], d1, grot[p, 0, a] * d0))


@kernel
def _globals_from_locals(
    order: np.ndarray,
    parent: np.ndarray,
    rot: np.ndarray,
    trans: np.ndarray,
    grot: np.ndarray,
    gtr: np.ndarray,
) -> None:
    """``G_i = G_parent T_i`` down the tree, in scalar code (a BLAS call and two temporary
    arrays per node cost ~1 us: 1.2 s per call at 1M poses).  The sums are rounded as the
    ``@`` products this replaced (OpenBLAS's 3x3 dgemm and dgemv kernels, fused multiply-adds
    in this order), so the poses, and every energy and test computed from them, stay
    bit-identical to those of ``G_p @ R_i`` and ``G_p @ t_i + g_p``."""
    for k in range(order.shape[0]):
        i = order[k]
        p = parent[i]
        if p < 0:
            for a in range(3):
                gtr[i, a] = trans[i, a]
                for b in range(3):
                    grot[i, a, b] = rot[i, a, b]
            continue
        for a in range(3):
            for b in range(3):
                grot[i, a, b] = _fma(grot[p, a, 2], rot[i, 2, b],
                                     _fma(grot[p, a, 1], rot[i, 1, b],
                                          grot[p, a, 0] * rot[i, 0, b]))
            gtr[i, a] = _fma(grot[p, a, 2], trans[i, 2],
                             _fma(grot[p, a, 0], trans[i, 0], grot[p, a, 1] * trans[i, 1])
                             ) + gtr[p, a]


def global_poses(
    tree: PoseTree, rot: FloatArray, trans: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Global poses ``(R (N,3,3), t (N,3))`` of the N poses from local transforms (no earth)."""
    t_nodes = tree.num_tree_nodes
    grot = np.empty((t_nodes, 3, 3))
    gtr = np.empty((t_nodes, 3))
    _globals_from_locals(tree.order, tree.parent, rot, trans, grot, gtr)
    n = tree.num_poses
    return grot[:n].copy(), gtr[:n].copy()
