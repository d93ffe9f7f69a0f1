"""Kernels of the pose tree: depths, constraint paths and global poses (docs/mathematics.md).

Every solver that parametrizes the poses by a spanning tree -- the hybrid solver, the TORO-style
baseline, the online mode and the hybrid solver's global correction -- keeps a parent array
(-1 at the root) and one local transform ``T_i = G_parent^-1 G_i`` per tree node.  These are the
one set of kernels over those arrays:

* :func:`depths` and :func:`lca`: depth below the root, lowest common ancestor by a walk on the
  depths;
* :func:`path_lengths` and :func:`fill_paths`: the CSR constraint paths (a constraint's domain:
  the a-side nodes from a up to, excluding, the lowest common ancestor with sign -1, then the
  b-side nodes from b up with sign +1);
* :func:`globals_from_locals` (every node, parents first), :func:`global_pose` (one node,
  O(depth)) and :func:`locals_from_globals`.

The products are written in scalar code with fused multiply-adds in a fixed order (``fma``:
``llvm.fma.f64``): each pose is rounded the same way whichever caller computes it, and no
BLAS call or temporary array is made per node (1M poses: a few milliseconds).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._numba import kernel


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


fma = _make_fma()


# --------------------------------------------------------------------------- structure
@kernel
def depths(order: np.ndarray, parent: np.ndarray, depth: np.ndarray) -> None:
    """Depth below the root of every node of ``order`` (parents before children)."""
    for k in range(order.shape[0]):
        i = order[k]
        depth[i] = 0 if parent[i] < 0 else depth[parent[i]] + 1


@kernel
def lca(parent: np.ndarray, depth: np.ndarray, a: int, b: int) -> tuple[int, int]:
    """``(root, d)``: the lowest common ancestor of a and b and the number of path nodes
    other than it."""
    u = a
    v = b
    d = 0
    while depth[u] > depth[v]:
        u = parent[u]
        d += 1
    while depth[v] > depth[u]:
        v = parent[v]
        d += 1
    while u != v:
        u = parent[u]
        v = parent[v]
        d += 2
    return u, d


@kernel
def path_lengths(ends: np.ndarray, parent: np.ndarray, depth: np.ndarray, lengths: np.ndarray,
                 roots: np.ndarray) -> int:
    """For every constraint ``ends[k] = (a, b)`` (tree nodes): its path length into
    ``lengths[k]`` and its lowest common ancestor into ``roots[k]``; returns the total."""
    total = 0
    for k in range(ends.shape[0]):
        r, d = lca(parent, depth, ends[k, 0], ends[k, 1])
        lengths[k] = d
        roots[k] = r
        total += d
    return total


@kernel
def fill_paths(ends: np.ndarray, parent: np.ndarray, roots: np.ndarray, starts: np.ndarray,
               path_node: np.ndarray, path_sign: np.ndarray) -> None:
    """Write the path of every constraint ``ends[k] = (a, b)`` at ``path_node[starts[k]:]``:
    from a up to (excluding) ``roots[k]`` with sign -1, then from b up with sign +1 (a GPS
    reading's ``a`` is the earth, the root: only its pose and the pose's ancestors, +1)."""
    for k in range(ends.shape[0]):
        r = roots[k]
        j = starts[k]
        u = ends[k, 0]
        while u != r:
            path_node[j] = u
            path_sign[j] = -1
            j += 1
            u = parent[u]
        v = ends[k, 1]
        while v != r:
            path_node[j] = v
            path_sign[j] = 1
            j += 1
            v = parent[v]


@kernel
def smallest_id_tree(
    indptr: np.ndarray, indices: np.ndarray, root: int, parent: np.ndarray, order: np.ndarray
) -> int:
    """Grow TORO's tree: visit nodes by increasing index; parent = smallest visited neighbour.

    Starting from ``root``, repeatedly visit the smallest-index node adjacent to the visited set
    and give it as parent its smallest-index visited neighbour.  When the root has the smallest
    index and every other node has a neighbour of smaller index, nodes are visited in index order
    and each parent is the node's smallest-index neighbour (TORO's rule).  The earth (index N,
    the largest) is therefore chosen as a parent only by a pose no other visited pose reaches.

    Writes ``parent`` (-1 for the root and unvisited nodes) and the visit ``order``; returns the
    number of nodes visited.
    """
    t_nodes = parent.shape[0]
    visited = np.zeros(t_nodes, np.bool_)
    for i in range(t_nodes):
        parent[i] = -1
    heap = np.empty(indices.shape[0] + 1, np.int64)
    size = 0
    heap[0] = root
    size = 1
    count = 0
    while size > 0:
        # pop the smallest
        node = heap[0]
        size -= 1
        last = heap[size]
        pos = 0
        while True:
            child = 2 * pos + 1
            if child >= size:
                break
            if child + 1 < size and heap[child + 1] < heap[child]:
                child += 1
            if heap[child] >= last:
                break
            heap[pos] = heap[child]
            pos = child
        if size > 0:
            heap[pos] = last
        if visited[node]:
            continue
        visited[node] = True
        order[count] = node
        count += 1
        best = -1
        for q in range(indptr[node], indptr[node + 1]):
            nb = indices[q]
            if visited[nb]:
                if nb != node and (best < 0 or nb < best):
                    best = nb
            else:
                # push nb
                pos = size
                size += 1
                while pos > 0:
                    up = (pos - 1) // 2
                    if heap[up] <= nb:
                        break
                    heap[pos] = heap[up]
                    pos = up
                heap[pos] = nb
        if node != root:
            parent[node] = best
    return count


# --------------------------------------------------------------------------- poses
@kernel
def _copy_pose(src_r: np.ndarray, src_t: np.ndarray, i: int, dst_r: np.ndarray,
               dst_t: np.ndarray) -> None:
    """Node i's pose from ``(src_r, src_t)`` into ``(dst_r, dst_t)``."""
    for a in range(3):
        dst_t[i, a] = src_t[i, a]
        for b in range(3):
            dst_r[i, a, b] = src_r[i, a, b]


@kernel
def globals_from_locals(order: np.ndarray, parent: np.ndarray, rot: np.ndarray,
                        trans: np.ndarray, grot: np.ndarray, gtr: np.ndarray) -> None:
    """``G_i = G_parent T_i`` for the nodes of ``order`` (parents before children; a node
    without parent: ``G_i = T_i``)."""
    for k in range(order.shape[0]):
        i = order[k]
        p = parent[i]
        if p < 0:
            _copy_pose(rot, trans, i, grot, gtr)
            continue
        for a in range(3):
            for b in range(3):
                grot[i, a, b] = fma(grot[p, a, 2], rot[i, 2, b],
                                    fma(grot[p, a, 1], rot[i, 1, b],
                                        grot[p, a, 0] * rot[i, 0, b]))
            gtr[i, a] = fma(grot[p, a, 2], trans[i, 2],
                            fma(grot[p, a, 0], trans[i, 0], grot[p, a, 1] * trans[i, 1])
                            ) + gtr[p, a]


@kernel
def locals_from_globals(parent: np.ndarray, grot: np.ndarray, gtr: np.ndarray,
                        rot: np.ndarray, trans: np.ndarray) -> None:
    """``T_i = G_parent^-1 G_i`` (``G_p^T G_i`` and ``G_p^T (g_i - g_p)``) of every node
    (``parent`` < 0: ``T_i = G_i``)."""
    for i in range(parent.shape[0]):
        p = parent[i]
        if p < 0:
            _copy_pose(grot, gtr, i, rot, trans)
            continue
        d0 = gtr[i, 0] - gtr[p, 0]
        d1 = gtr[i, 1] - gtr[p, 1]
        d2 = gtr[i, 2] - gtr[p, 2]
        for a in range(3):
            for b in range(3):
                rot[i, a, b] = fma(grot[p, 2, a], grot[i, 2, b],
                                   fma(grot[p, 1, a], grot[i, 1, b],
                                       grot[p, 0, a] * grot[i, 0, b]))
            trans[i, a] = fma(grot[p, 2, a], d2, fma(grot[p, 1, a], d1, grot[p, 0, a] * d0))


@kernel
def mul_pose_into(ra: np.ndarray, ta: np.ndarray, rb: np.ndarray, tb: np.ndarray,
                  ro: np.ndarray, to: np.ndarray) -> None:
    """(ro, to) = (ra, ta) * (rb, tb) without allocating (outputs must not alias inputs)."""
    for i in range(3):
        for j in range(3):
            ro[i, j] = ra[i, 0] * rb[0, j] + ra[i, 1] * rb[1, j] + ra[i, 2] * rb[2, j]
        to[i] = ra[i, 0] * tb[0] + ra[i, 1] * tb[1] + ra[i, 2] * tb[2] + ta[i]


@kernel
def global_pose(i: int, parent: np.ndarray, rot: np.ndarray, trans: np.ndarray, ro: np.ndarray,
                to: np.ndarray) -> None:
    """Pose of tree node i in the root's frame (the product of the locals up the tree),
    O(depth); the identity for ``i < 0``."""
    tmp_r = np.empty((3, 3))
    tmp_t = np.empty(3)
    if i < 0:
        for a in range(3):
            for b in range(3):
                ro[a, b] = 1.0 if a == b else 0.0
            to[a] = 0.0
        return
    ro[:] = rot[i]
    to[:] = trans[i]
    v = parent[i]
    while v >= 0:
        mul_pose_into(rot[v], trans[v], ro, to, tmp_r, tmp_t)
        ro[:] = tmp_r
        to[:] = tmp_t
        v = parent[v]
