"""Kernels of the incremental exact solver (:mod:`.incremental`).

The normal equations ``H delta = -g`` of the map linearized at the linearization point theta
(right perturbations, tangent order (rho, phi), ``E = sum_c e_c^T Omega_c e_c``: the exact
solver's conventions, :mod:`hybridpgo.solvers._gn_kernels`) are kept factored, ``H = L L^T``,
by 6x6 blocks (3x3 in the planar system below), one block column per free pose ("variable").
The elimination order is a position per variable (a stamp that only grows: a variable
re-eliminated later gets a larger one), the elimination tree ``parent`` is the
smallest-position row of each column.  A column stores its rows (variables) and their blocks
in a pool, the factored diagonal block apart; :func:`symbolic` writes the rows of a column
sorted by position.

One update ("cycle") re-eliminates only the set S of columns whose values changed (the ends
of the constraints that are new or were relinearized) and all their ancestors in the
elimination tree: every other column of L, and its forward-substitution value ``y = L^-1 (-g)``,
stays as it is, since a column depends only on its descendants.  S is given fresh positions
after every other column, in a new fill-reducing order; the columns hanging below S (the
"orphans") keep their blocks, and only their parent pointer changes.  Then

* :func:`symbolic` computes the rows of each column of S (its constraints to later variables
  of S, and its children's rows; sorted by position), its parent and the children lists;
* :func:`supernodes` groups S's columns into supernodes: runs of consecutive columns with
  nested rows (each column's rows are the next column and its rows);
* :func:`numeric` factors S one supernode at a time, left-looking, as a dense panel: A's
  entries, then the update of every earlier column k with a block in one of the supernode's
  rows (found by walking the elimination tree up from the constraint neighbours, "ereach"),
  then a blocked dense Cholesky factorization; the forward substitution ``y`` is computed in
  the same pass and the panel is copied to the column storage.  The earlier columns of S
  are read from their supernodes' panels, each supernode's update one matrix product (BLAS
  when large); the unchanged columns below S by 6x6 (3x3) block products;
* :func:`back_substitute` solves ``L^T x = y`` from the roots down, recomputing a column when it
  is in S or one of its rows changed by more than a threshold (0: exact), so the unchanged
  rest of the map is not visited.

The planar system: when the poses and measurements are planar (:mod:`.incremental`), the
factor's coordinates are the tangent coordinates ``perm[:nd]`` with ``perm = (0, 1, 5, 2, 3,
4)`` (x, y, yaw first) and ``nd = 3``; its blocks are (3, 3), the diagonal blocks the identity
beyond ``nd`` and ``y`` zero there, and the step's out-of-plane coordinates stay 0.  The full
system: ``perm`` the identity, ``nd = 6``.

Resumable: :func:`numeric` and :func:`back_substitute` stop when the cycle counter passes a
deadline (between two supernodes, two columns) and are called again from where they stopped.
Status codes instead of exceptions.
"""

from __future__ import annotations

import math

import numpy as np

from .._cost import chi2, gps_chi2, relative_chi2_at, retract_into
from .._numba import cycle_counter, kernel
from ..solvers._gn_kernels import _edge_linearization, _matmul_cols, _rows

#: numeric: a pivot of a diagonal block was not positive (the system is not SPD).
NOT_SPD = -2
#: numeric / symbolic: the elimination tree walk did not reach the column (internal error).
BROKEN_TREE = -3
#: symbolic: the row pool is full; grow it and call again from ``pool_used[1]``.
POOL_FULL = -4
#: symbolic: the deadline passed; call again from ``pool_used[1]``.
PAST_DEADLINE = -5


# --------------------------------------------------------------------------- linearization
@kernel
def differing_poses(rot: np.ndarray, trans: np.ndarray, ref_rot: np.ndarray,
                    ref_trans: np.ndarray, out: np.ndarray) -> None:
    """``out[i]``: pose i of ``(rot, trans)`` differs from ``(ref_rot, ref_trans)`` in some
    entry, for the first ``out.shape[0]`` poses (a NaN always differs)."""
    for i in range(out.shape[0]):
        d = False
        for a in range(3):
            d = d or trans[i, a] != ref_trans[i, a]
            for b in range(3):
                d = d or rot[i, a, b] != ref_rot[i, a, b]
        out[i] = d


@kernel
def refresh_energies(rot: np.ndarray, trans: np.ndarray, moved: np.ndarray, edge_nodes: np.ndarray,
                     edge_rot: np.ndarray, edge_trans: np.ndarray, edge_info: np.ndarray,
                     gps_nodes: np.ndarray, gps_pos: np.ndarray, gps_info: np.ndarray,
                     m0: int, g0: int, out_rel: np.ndarray, out_gps: np.ndarray) -> None:
    """χ² at the poses ``rot, trans`` (as :func:`hybridpgo._cost.constraint_energies`) of the
    constraints that are new (relative index ``>= m0``, position index ``>= g0``) or that have
    an end ``i`` with ``moved[i]``, written into ``out_rel`` / ``out_gps``; the others keep
    what those hold."""
    e = np.empty(6)
    oe = np.empty(6)
    for c in range(edge_nodes.shape[0]):
        a = edge_nodes[c, 0]
        b = edge_nodes[c, 1]
        if c >= m0 or moved[a] or moved[b]:
            out_rel[c] = relative_chi2_at(rot, trans, a, b, edge_rot, edge_trans, edge_info, c)
    for c in range(gps_nodes.shape[0]):
        n = gps_nodes[c]
        if c >= g0 or moved[n]:
            out_gps[c] = gps_chi2(trans[n], gps_pos[c], gps_info[c], e, oe)


@kernel
def linearize_edges(ids: np.ndarray, rot: np.ndarray, trans: np.ndarray, ab: np.ndarray,
                    zr: np.ndarray, zt: np.ndarray, info: np.ndarray, haa: np.ndarray,
                    hbb: np.ndarray, hab: np.ndarray, ga: np.ndarray, gb: np.ndarray,
                    chi: np.ndarray) -> int:
    """Each listed edge's blocks of H and g at the poses ``rot, trans`` (the linearization
    point): ``haa = Ja^T W Ja``, ``hbb = Jb^T W Jb``, ``hab = Ja^T W Jb`` (block (a, b)),
    ``ga = Ja^T W e``, ``gb = Jb^T W e``, its χ².  Returns -1, or the first non-finite edge."""
    e = np.empty(6)
    oe = np.empty(6)
    ja = np.empty((6, 6))
    jb = np.empty((6, 6))
    wa = np.empty((6, 6))
    wb = np.empty((6, 6))
    for q in range(ids.shape[0]):
        c = ids[q]
        a = ab[c, 0]
        b = ab[c, 1]
        _edge_linearization(rot, trans, zr, zt, a, b, c, e, ja, jb)
        om = info[c]
        s = chi2(om, e, 6, oe)
        if not math.isfinite(s):
            return int(c)
        chi[c] = s
        _matmul_cols(om, ja, (0, 1, 2, 3, 4, 5), wa)
        _matmul_cols(om, jb, (0, 1, 2, 3, 4, 5), wb)
        for p in range(6):
            sa = 0.0
            sb = 0.0
            for k in range(_rows(p)):  # the Jacobians' structural zeros left out (_gn_kernels)
                sa += ja[k, p] * oe[k]
                sb += jb[k, p] * oe[k]
            ga[c, p] = sa
            gb[c, p] = sb
            for r in range(6):
                s1 = 0.0
                s2 = 0.0
                s3 = 0.0
                for k in range(_rows(p)):
                    s1 += ja[k, p] * wa[k, r]
                    s2 += jb[k, p] * wb[k, r]
                    s3 += ja[k, p] * wb[k, r]
                haa[c, p, r] = s1
                hbb[c, p, r] = s2
                hab[c, p, r] = s3
        for p in range(6):
            for r in range(6):
                if not (math.isfinite(haa[c, p, r]) and math.isfinite(hbb[c, p, r])
                        and math.isfinite(hab[c, p, r])):
                    return int(c)
    return -1


@kernel
def linearize_gps(ids: np.ndarray, rot: np.ndarray, trans: np.ndarray, node: np.ndarray,
                  pos: np.ndarray, info: np.ndarray, hgg: np.ndarray, gg: np.ndarray,
                  chi: np.ndarray) -> int:
    """Position constraints ``e = t_n - g``, ``J = [R_n | 0]``: ``hgg = R^T Omega R`` (the
    (rho, rho) block of H), ``gg = R^T Omega e``, χ².  Returns -1, or the first non-finite."""
    e = np.empty(3)
    oe = np.empty(3)
    for q in range(ids.shape[0]):
        c = ids[q]
        n = node[c]
        r = rot[n]
        om = info[c]
        for i in range(3):
            e[i] = trans[n, i] - pos[c, i]
        s = chi2(om, e, 3, oe)
        if not math.isfinite(s):
            return int(c)
        chi[c] = s
        for p in range(3):
            gg[c, p] = r[0, p] * oe[0] + r[1, p] * oe[1] + r[2, p] * oe[2]
            for qq in range(3):
                acc = 0.0
                for k in range(3):
                    for m in range(3):
                        acc += r[k, p] * om[k, m] * r[m, qq]
                hgg[c, p, qq] = acc
    return -1


# --------------------------------------------------------------------------- the set S
@kernel
def ancestor_closure(cands: np.ndarray, free: np.ndarray, parent: np.ndarray,
                     in_s: np.ndarray, stamp: int, out: np.ndarray) -> int:
    """S: the free candidates and all their ancestors (each once; ``in_s[v] = stamp`` marks
    them).  Writes S to ``out`` and returns its size."""
    k = 0
    for q in range(cands.shape[0]):
        v = cands[q]
        while v >= 0 and free[v] and in_s[v] != stamp:
            in_s[v] = stamp
            out[k] = v
            k += 1
            v = parent[v]
    return k


@kernel
def find_orphans(s_vars: np.ndarray, in_s: np.ndarray, stamp: int, ch_head: np.ndarray,
                 ch_next: np.ndarray, out: np.ndarray) -> int:
    """The columns outside S whose parent is in S; returns how many were written to ``out``."""
    k = 0
    for q in range(s_vars.shape[0]):
        c = ch_head[s_vars[q]]
        while c >= 0:
            if in_s[c] != stamp:
                out[k] = c
                k += 1
            c = ch_next[c]
    return k


@kernel
def reduced_pattern(s_vars: np.ndarray, orphans: np.ndarray, in_s: np.ndarray, stamp: int,
                    local: np.ndarray, free: np.ndarray, ab: np.ndarray, inc_head: np.ndarray,
                    inc_next: np.ndarray, col_start: np.ndarray, col_len: np.ndarray,
                    row_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The block pattern of the system S is re-eliminated from (local indices ``local[v]``):
    the constraints between variables of S, and a clique over the rows of each orphan (its
    subtree's Schur complement).  Both orientations of each pair (duplicates allowed)."""
    cap = 64
    for q in range(s_vars.shape[0]):
        v = s_vars[q]
        i = inc_head[v]
        while i >= 0:
            cap += 2
            i = inc_next[i]
    for q in range(orphans.shape[0]):
        n = col_len[orphans[q]]
        cap += n * n
    rows = np.empty(cap, np.int64)
    cols = np.empty(cap, np.int64)
    k = 0
    for q in range(s_vars.shape[0]):
        v = s_vars[q]
        i = inc_head[v]
        while i >= 0:
            c = i >> 1
            u = ab[c, 1 - (i & 1)]
            if u != v and free[u] and in_s[u] == stamp:
                rows[k] = local[v]
                cols[k] = local[u]
                k += 1
            i = inc_next[i]
    for q in range(orphans.shape[0]):
        o = orphans[q]
        s0 = col_start[o]
        n = col_len[o]
        for x in range(n):
            for y in range(n):
                if x != y:
                    rows[k] = local[row_var[s0 + x]]
                    cols[k] = local[row_var[s0 + y]]
                    k += 1
    return rows[:k], cols[:k]


# --------------------------------------------------------------------------- tree lists
@kernel
def _unlink(v: int, parent: np.ndarray, ch_head: np.ndarray, ch_next: np.ndarray,
            ch_prev: np.ndarray) -> None:
    p = parent[v]
    if p < 0:
        return
    nx = ch_next[v]
    pv = ch_prev[v]
    if pv >= 0:
        ch_next[pv] = nx
    else:
        ch_head[p] = nx
    if nx >= 0:
        ch_prev[nx] = pv
    ch_next[v] = -1
    ch_prev[v] = -1


@kernel
def _link(v: int, p: int, parent: np.ndarray, ch_head: np.ndarray, ch_next: np.ndarray,
          ch_prev: np.ndarray) -> None:
    parent[v] = p
    ch_prev[v] = -1
    if p < 0:
        ch_next[v] = -1
        return
    h = ch_head[p]
    ch_next[v] = h
    if h >= 0:
        ch_prev[h] = v
    ch_head[p] = v


# --------------------------------------------------------------------------- symbolic
@kernel
def detach(s_vars: np.ndarray, orphans: np.ndarray, parent: np.ndarray, ch_head: np.ndarray,
           ch_next: np.ndarray, ch_prev: np.ndarray) -> None:
    """Take S and the orphans out of the tree lists (S's own lists emptied), before
    :func:`symbolic` links them again at their new parents."""
    for q in range(orphans.shape[0]):
        _unlink(orphans[q], parent, ch_head, ch_next, ch_prev)
        parent[orphans[q]] = -1
    for q in range(s_vars.shape[0]):
        _unlink(s_vars[q], parent, ch_head, ch_next, ch_prev)
        parent[s_vars[q]] = -1
    for q in range(s_vars.shape[0]):
        ch_head[s_vars[q]] = -1


@kernel
def link_orphans(orphans: np.ndarray, position: np.ndarray, col_start: np.ndarray,
                 col_len: np.ndarray, row_var: np.ndarray, parent: np.ndarray,
                 ch_head: np.ndarray, ch_next: np.ndarray, ch_prev: np.ndarray) -> None:
    """Each orphan's new parent: its row with the smallest (new) position."""
    for q in range(orphans.shape[0]):
        o = orphans[q]
        best = -1
        for t in range(col_start[o], col_start[o] + col_len[o]):
            r = row_var[t]
            if best < 0 or position[r] < position[best]:
                best = r
        _link(o, best, parent, ch_head, ch_next, ch_prev)


@kernel
def compact_pool(order: np.ndarray, col_start: np.ndarray, col_cap: np.ndarray,
                 col_len: np.ndarray, used: int, row_var: np.ndarray,
                 row_blk: np.ndarray) -> int:
    """Move the columns' segments to the front of the pool, back to back in the order of
    their old starts (``order``: the columns by increasing ``col_start``), in place; the rows
    past each segment's length and past the last segment (up to ``used``, the old end) are
    zeroed, as in a new pool.  Returns the new end.  A segment never moves up (its new start
    is the sum of the capacities of the segments before it, and those of nonzero capacity
    lay below it, disjoint), so copying each one row by row from its first row is safe; a
    column of zero capacity has no rows to move."""
    p = 0
    for q in range(order.shape[0]):
        c = order[q]
        s = col_start[c]
        k = col_len[c]
        if s != p:
            for t in range(k):
                row_var[p + t] = row_var[s + t]
                row_blk[p + t] = row_blk[s + t]
        for t in range(k, col_cap[c]):
            row_var[p + t] = 0
            row_blk[p + t] = 0.0
        col_start[c] = p
        p += col_cap[c]
    for t in range(p, used):
        row_var[t] = 0
        row_blk[t] = 0.0
    return p


@kernel
def symbolic(order: np.ndarray, i0: int, deadline: np.uint64, position: np.ndarray,
             free: np.ndarray,
             in_s: np.ndarray, stamp: int, ab: np.ndarray, inc_head: np.ndarray,
             inc_next: np.ndarray, parent: np.ndarray, ch_head: np.ndarray,
             ch_next: np.ndarray, ch_prev: np.ndarray, col_start: np.ndarray,
             col_len: np.ndarray, col_cap: np.ndarray, row_var: np.ndarray,
             pool_used: np.ndarray, mark: np.ndarray) -> int:
    """Rows, parent and tree links of the columns ``order[i0:]`` (S in its new order; the
    orphans already linked).  A column whose rows do not fit its segment gets a new one at the
    end of the pool (``pool_used[0]``).  Returns ``len(order)``, or ``POOL_FULL`` /
    ``PAST_DEADLINE`` with ``pool_used[1]`` set to the index to resume from."""
    cap_pool = row_var.shape[0]
    for q in range(i0, order.shape[0]):
        j = order[q]
        tag = position[j]
        mark[j] = tag
        cnt = 0
        # count first: rows from the constraints to later variables of S and from the children
        i = inc_head[j]
        while i >= 0:
            u = ab[i >> 1, 1 - (i & 1)]
            if free[u] and in_s[u] == stamp and position[u] > tag and mark[u] != tag:
                mark[u] = tag
                cnt += 1
            i = inc_next[i]
        c = ch_head[j]
        while c >= 0:
            for t in range(col_start[c], col_start[c] + col_len[c]):
                r = row_var[t]
                if mark[r] != tag:
                    mark[r] = tag
                    cnt += 1
            c = ch_next[c]
        if cnt > col_cap[j]:
            need = max(2 * cnt, 4)
            if pool_used[0] + need > cap_pool:
                # undo the marks of this column (it is redone after the pool grows)
                mark[j] = -1
                i = inc_head[j]
                while i >= 0:
                    u = ab[i >> 1, 1 - (i & 1)]
                    if mark[u] == tag:
                        mark[u] = -1
                    i = inc_next[i]
                c = ch_head[j]
                while c >= 0:
                    for t in range(col_start[c], col_start[c] + col_len[c]):
                        mark[row_var[t]] = -1
                    c = ch_next[c]
                pool_used[1] = q
                return POOL_FULL
            col_start[j] = pool_used[0]
            col_cap[j] = need
            pool_used[0] += need
        # write (the marks are set: collect them again in the same order)
        s0 = col_start[j]
        k = 0
        best = -1
        i = inc_head[j]
        while i >= 0:
            u = ab[i >> 1, 1 - (i & 1)]
            if mark[u] == tag and u != j:
                mark[u] = -1 - tag  # consumed
                row_var[s0 + k] = u
                k += 1
                if best < 0 or position[u] < position[best]:
                    best = u
            i = inc_next[i]
        c = ch_head[j]
        while c >= 0:
            for t in range(col_start[c], col_start[c] + col_len[c]):
                r = row_var[t]
                if mark[r] == tag and r != j:
                    mark[r] = -1 - tag
                    row_var[s0 + k] = r
                    k += 1
                    if best < 0 or position[r] < position[best]:
                        best = r
            c = ch_next[c]
        if k != cnt:
            return BROKEN_TREE
        _sort_rows(row_var, s0, cnt, position)
        col_len[j] = cnt
        _link(j, best, parent, ch_head, ch_next, ch_prev)
        if cycle_counter() > deadline and q + 1 < order.shape[0]:
            pool_used[1] = q + 1
            return PAST_DEADLINE
    return int(order.shape[0])


@kernel
def _sort_rows(row_var: np.ndarray, s0: int, cnt: int, position: np.ndarray) -> None:
    """Sort ``row_var[s0:s0 + cnt]`` by position (insertion sort up to 32 rows)."""
    if cnt <= 32:
        for a in range(s0 + 1, s0 + cnt):
            v = row_var[a]
            pv = position[v]
            b = a - 1
            while b >= s0 and position[row_var[b]] > pv:
                row_var[b + 1] = row_var[b]
                b -= 1
            row_var[b + 1] = v
        return
    seg = row_var[s0: s0 + cnt].copy()
    keys = np.empty(cnt, np.int64)
    for a in range(cnt):
        keys[a] = position[seg[a]]
    idx = np.argsort(keys)
    for a in range(cnt):
        row_var[s0 + a] = seg[idx[a]]


# --------------------------------------------------------------------------- numeric
#: :func:`supernodes`: the most columns in one supernode (bounds a panel's size and the dense
#: work between two deadline checks).
SUPERNODE_MAX = 64
#: :func:`numeric`: a product of panels with fewer multiply-adds than this is done by loops
#: here; a larger one by BLAS (``np.dot``), whose call costs about a microsecond.
SMALL_GEMM = 8192
#: :func:`numeric`: columns per step of a panel's blocked Cholesky factorization.
PANEL_STEP = 32


@kernel
def supernodes(order: np.ndarray, parent: np.ndarray, col_len: np.ndarray, max_width: int,
               nd: int, sn_ptr: np.ndarray, sn_of: np.ndarray, pan_off: np.ndarray) -> int:
    """Group the columns ``order`` (S in its elimination order, rows known) into supernodes:
    runs of consecutive columns in which each column's parent is the next one and it has one
    row more, so that its rows are the next column and the next column's rows.  Supernode
    ``s`` is ``order[sn_ptr[s]:sn_ptr[s + 1]]``; ``sn_of[j] = s``; its panel, ``(w + r) nd``
    rows by ``w nd`` columns for ``w`` columns and ``r`` rows of its last column, starts at
    ``pan_off[s]`` of the panel pool (``pan_off[count]``: the pool's size).  Returns the count.
    """
    ns = order.shape[0]
    count = 0
    sn_ptr[0] = 0
    pan_off[0] = 0
    w = 1
    for q in range(ns):
        j = order[q]
        sn_of[j] = count
        join = False
        if q + 1 < ns and w < max_width:
            j2 = order[q + 1]
            join = parent[j] == j2 and col_len[j] == col_len[j2] + 1
        if join:
            w += 1
            continue
        count += 1
        sn_ptr[count] = q + 1
        pan_off[count] = pan_off[count - 1] + (w + col_len[j]) * nd * w * nd
        w = 1
    return count


@kernel
def _first_at_least(row_var: np.ndarray, t0: int, n: int, position: np.ndarray,
                    tag: int) -> int:
    """The index (from ``t0``) of the first of the ``n`` rows at ``row_var[t0:]``, sorted by
    position, whose position is at least ``tag`` (``n`` when none)."""
    lo = 0
    hi = n
    while lo < hi:
        mid = (lo + hi) >> 1
        if position[row_var[t0 + mid]] < tag:
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel
def _product(a: np.ndarray, b: np.ndarray, out: np.ndarray, lower: bool) -> None:
    """``out = a b^T``: BLAS for a product of at least :data:`SMALL_GEMM` multiplications,
    loops for a smaller one, which with ``lower`` fill only ``out[r, t]`` for ``t <= r``."""
    mr = a.shape[0]
    mq = b.shape[0]
    kk = a.shape[1]
    if mr * mq * kk >= SMALL_GEMM:
        np.dot(a, b.T, out)
        return
    for r in range(mr):
        for t in range(min(r + 1, mq) if lower else mq):
            x = 0.0
            for m in range(kk):
                x += a[r, m] * b[t, m]
            out[r, t] = x


@kernel
def _subtract_product(p: np.ndarray, a: np.ndarray, b: np.ndarray, rows: np.ndarray,
                      cols: np.ndarray, nd: int, scratch: np.ndarray) -> None:
    """``p[rows[i] nd + u, cols[q] nd + v] -= (a b^T)[i nd + u, q nd + v]`` for the blocks
    with ``rows[i] >= cols[q]`` (the lower part of the target); the product (:func:`_product`)
    into ``scratch`` (at least ``a.shape[0] * b.shape[0]`` floats)."""
    mr = a.shape[0]
    mq = b.shape[0]
    c = scratch[: mr * mq].reshape(mr, mq)
    _product(a, b, c, False)
    for i in range(mr // nd):
        tr = rows[i]
        for q in range(mq // nd):
            tc = cols[q]
            if tr < tc:
                continue
            for u in range(nd):
                for v in range(nd):
                    p[tr * nd + u, tc * nd + v] -= c[i * nd + u, q * nd + v]


def panel_scratch(rows: int, nc: int) -> int:
    """Floats of scratch :func:`numeric` needs for panels of at most ``rows`` rows and ``nc``
    columns (products of panels, the panel factorization's steps)."""
    return rows * nc + 2 * rows * PANEL_STEP + PANEL_STEP * PANEL_STEP


@kernel
def _factor_panel(p: np.ndarray, nc: int, scratch: np.ndarray) -> bool:
    """In place: the lower Cholesky factor of the panel's leading (nc, nc) part (its lower
    triangle read) and the rows below it solved against it (``X L^T = B``), by blocked
    right-looking steps of :data:`PANEL_STEP` columns; False: not positive definite.
    ``scratch``: :func:`panel_scratch` floats for the panel's size."""
    nrow = p.shape[0]
    o_x = nrow * nc
    o_b = o_x + nrow * PANEL_STEP
    o_l = o_b + nrow * PANEL_STEP
    for c0 in range(0, nc, PANEL_STEP):
        c1 = min(c0 + PANEL_STEP, nc)
        for c in range(c0, c1):
            s = p[c, c]
            for t in range(c0, c):
                s -= p[c, t] * p[c, t]
            if not (s > 0.0):
                return False
            lc = math.sqrt(s)
            p[c, c] = lc
            for r in range(c + 1, c1):
                s2 = p[r, c]
                for t in range(c0, c):
                    s2 -= p[r, t] * p[c, t]
                p[r, c] = s2 / lc
        nb = c1 - c0
        mr = nrow - c1
        if mr == 0:
            break
        x = scratch[o_x: o_x + mr * nb].reshape(mr, nb)
        if mr * nb * nb < SMALL_GEMM:
            for r in range(c1, nrow):
                for c in range(c0, c1):
                    s = p[r, c]
                    for t in range(c0, c):
                        s -= p[r, t] * p[c, t]
                    p[r, c] = s / p[c, c]
                    x[r - c1, c - c0] = p[r, c]
        else:  # X = B L^-T with L's inverse (nb, nb), by BLAS
            li = scratch[o_l: o_l + nb * nb].reshape(nb, nb)
            for c in range(nb):
                for r in range(c):
                    li[r, c] = 0.0
                li[c, c] = 1.0 / p[c0 + c, c0 + c]
                for r in range(c + 1, nb):
                    s = 0.0
                    for t in range(c, r):
                        s -= p[c0 + r, c0 + t] * li[t, c]
                    li[r, c] = s / p[c0 + r, c0 + r]
            bm = scratch[o_b: o_b + mr * nb].reshape(mr, nb)
            for r in range(mr):
                for c in range(nb):
                    bm[r, c] = p[c1 + r, c0 + c]
            np.dot(bm, li.T, x)
            for r in range(mr):
                for c in range(nb):
                    p[c1 + r, c0 + c] = x[r, c]
        if c1 < nc:  # the trailing columns' lower triangle: X X^T subtracted
            mq = nc - c1
            u = scratch[: mr * mq].reshape(mr, mq)
            _product(x, x[:mq], u, True)
            for r in range(mr):
                for c in range(min(r + 1, mq)):
                    p[c1 + r, c1 + c] -= u[r, c]
    return True


@kernel
def numeric(order: np.ndarray, s_from: int, deadline: np.uint64, position: np.ndarray,
            free: np.ndarray, ab: np.ndarray, inc_head: np.ndarray, inc_next: np.ndarray,
            gps_head: np.ndarray, gps_next: np.ndarray, haa: np.ndarray, hbb: np.ndarray,
            hab: np.ndarray, ga: np.ndarray, gb: np.ndarray, hgg: np.ndarray, gg: np.ndarray,
            parent: np.ndarray, col_start: np.ndarray, col_len: np.ndarray,
            row_var: np.ndarray, row_blk: np.ndarray, diag: np.ndarray, y: np.ndarray,
            slot: np.ndarray, walk: np.ndarray, in_s: np.ndarray, stamp: int,
            sn_ptr: np.ndarray, sn_count: int, sn_of: np.ndarray, sn_mark: np.ndarray,
            pan_off: np.ndarray, panel: np.ndarray, src: np.ndarray, scratch: np.ndarray,
            damping: float, nd: int, perm: np.ndarray, work: np.ndarray) -> int:
    """Factor the supernodes ``s_from, ..., sn_count - 1`` of S (:func:`supernodes`) and their
    forward substitution ``y`` (module doc).

    ``nd``, ``perm``: the factor's coordinates are the tangent coordinates ``perm[:nd]``
    (module doc: the planar system), ``row_blk`` holds (nd, nd) blocks; GPS readings need the
    identity ``perm`` and ``nd = 6``.

    A supernode J is factored as one dense panel (its columns; as rows, its columns and the
    rows of its last column, in position order): A's entries; the updates of every earlier
    column with a row in J, found by walking the elimination tree up from the constraint
    neighbours of J's columns ("ereach"); a blocked Cholesky factorization; then its columns
    are copied to the column storage (``diag``, ``row_blk``).  An earlier supernode K of S
    updates J by one product of two slices of its panel, the rows of K from J's first column
    on (all of them rows of J's panel, by the elimination tree's property) times the rows
    that are columns of J, with BLAS when large; an unchanged column below S by 6x6 block
    products (its rows are not in position order).  ``slot[v]`` is the panel row of
    variable v while J is factored (-1 otherwise); ``sn_mark[K]``, ``walk[k]``: J's first
    position once K, k were applied to J.  ``scratch``: :func:`panel_scratch` floats for the
    largest panel (products and the panel factorization work there, not in new arrays).

    ``damping``: ``H + damping * diag(H)`` (Levenberg-Marquardt; 0 for Gauss-Newton).  Stops
    after the first supernode that ends past ``deadline`` (cycle counter); returns the
    supernode to resume from (``sn_count`` when done), or ``NOT_SPD`` / ``BROKEN_TREE``.
    ``work`` (2,): += earlier columns applied, += their blocks multiplied.
    """
    qbuf = np.empty(64, np.int64)
    bv = np.empty(SUPERNODE_MAX * 6)
    ljt = np.empty((6, 6))
    for s in range(s_from, sn_count):
        a0 = sn_ptr[s]
        a1 = sn_ptr[s + 1]
        w = a1 - a0
        jl = order[a1 - 1]
        ls0 = col_start[jl]
        ln = col_len[jl]
        nr = w + ln
        nc = w * nd
        pj = panel[pan_off[s]: pan_off[s + 1]].reshape(nr * nd, nc)
        pj[:, :] = 0.0
        for c in range(nc):
            bv[c] = 0.0
        for c in range(w):
            slot[order[a0 + c]] = c
        for t in range(ln):
            slot[row_var[ls0 + t]] = w + t
        tag0 = position[order[a0]]
        # A's columns: the constraints' diagonal blocks, gradients and blocks to later rows
        for c in range(w):
            j = order[a0 + c]
            tag = position[j]
            o = c * nd
            i = inc_head[j]
            while i >= 0:
                e = i >> 1
                side = i & 1
                u = ab[e, 1 - side]
                if side == 0:
                    for a in range(nd):
                        pa = perm[a]
                        bv[o + a] -= ga[e, pa]
                        for v in range(nd):
                            pj[o + a, o + v] += haa[e, pa, perm[v]]
                else:
                    for a in range(nd):
                        pa = perm[a]
                        bv[o + a] -= gb[e, pa]
                        for v in range(nd):
                            pj[o + a, o + v] += hbb[e, pa, perm[v]]
                if free[u] and position[u] > tag:
                    r = slot[u] * nd
                    if r < 0:
                        return BROKEN_TREE
                    if side == 0:  # block (row b, column a) = hab^T
                        for a in range(nd):
                            for v in range(nd):
                                pj[r + a, o + v] += hab[e, perm[v], perm[a]]
                    else:  # block (row a, column b) = hab
                        for a in range(nd):
                            for v in range(nd):
                                pj[r + a, o + v] += hab[e, perm[a], perm[v]]
                i = inc_next[i]
            i = gps_head[j]
            while i >= 0:
                for a in range(3):
                    bv[o + a] -= gg[i, a]
                    for v in range(3):
                        pj[o + a, o + v] += hgg[i, a, v]
                i = gps_next[i]
            if damping > 0.0:
                for a in range(nd):
                    pj[o + a, o + a] *= 1.0 + damping
        # the earlier columns with a row in J (ereach of J's columns; J's own columns stop
        # the walks: their updates to each other are the panel's factorization)
        nsrc = 0
        for c in range(w):
            walk[order[a0 + c]] = tag0
        for c in range(w):
            j = order[a0 + c]
            tag = position[j]
            i = inc_head[j]
            while i >= 0:
                k = ab[i >> 1, 1 - (i & 1)]
                if free[k] and position[k] < tag:
                    while walk[k] != tag0:
                        walk[k] = tag0
                        src[nsrc] = k
                        nsrc += 1
                        k = parent[k]
                        if k < 0:
                            return BROKEN_TREE
                i = inc_next[i]
        for si in range(nsrc):
            k = src[si]
            if in_s[k] == stamp:
                sk = sn_of[k]
                if sn_mark[sk] == tag0:
                    continue
                sn_mark[sk] = tag0
                b0 = sn_ptr[sk]
                wk = sn_ptr[sk + 1] - b0
                kl = order[b0 + wk - 1]
                ks0 = col_start[kl]
                kn = col_len[kl]
                nck = wk * nd
                r0 = _first_at_least(row_var, ks0, kn, position, tag0)
                r1 = r0 + _first_at_least(row_var, ks0 + r0, kn - r0, position,
                                          position[jl] + 1)
                if r1 == r0 or r1 > w + r0:
                    return BROKEN_TREE
                base = pan_off[sk] + (wk + r0) * nd * nck
                a_ = panel[base: pan_off[sk + 1]].reshape((kn - r0) * nd, nck)
                b_ = panel[base: base + (r1 - r0) * nd * nck].reshape((r1 - r0) * nd, nck)
                if kn - r0 > qbuf.shape[0]:
                    qbuf = np.empty(2 * (kn - r0), np.int64)
                rows = qbuf[: kn - r0]
                for t in range(kn - r0):
                    rows[t] = slot[row_var[ks0 + r0 + t]]
                    if rows[t] < 0:
                        return BROKEN_TREE
                # forward substitution: b_q -= L_qK y_K
                for q in range(r1 - r0):
                    o = rows[q] * nd
                    for a in range(nd):
                        acc = 0.0
                        for kk in range(wk):
                            yk = order[b0 + kk]
                            for m in range(nd):
                                acc += b_[q * nd + a, kk * nd + m] * y[yk, m]
                        bv[o + a] -= acc
                _subtract_product(pj, a_, b_, rows, rows[: r1 - r0], nd, scratch)
                work[0] += wk
                work[1] += (kn - r0) * (r1 - r0) * wk
            else:
                # an unchanged column: its rows in J's panel (those in J's columns first)
                k0 = col_start[k]
                kn = col_len[k]
                if 2 * kn > qbuf.shape[0]:
                    qbuf = np.empty(4 * kn, np.int64)
                nq = 0
                for t in range(k0, k0 + kn):
                    sr = slot[row_var[t]]
                    if 0 <= sr < w:
                        qbuf[2 * nq] = t
                        qbuf[2 * nq + 1] = sr
                        nq += 1
                if nq == 0:
                    return BROKEN_TREE
                nb = nq
                for t in range(k0, k0 + kn):
                    sr = slot[row_var[t]]
                    if sr >= w:
                        qbuf[2 * nb] = t
                        qbuf[2 * nb + 1] = sr
                        nb += 1
                work[0] += 1
                for qi in range(nq):
                    lq = row_blk[qbuf[2 * qi]]
                    tc = qbuf[2 * qi + 1]
                    o = tc * nd
                    for a in range(nd):
                        acc = 0.0
                        for m in range(nd):
                            acc += lq[a, m] * y[k, m]
                        bv[o + a] -= acc
                    for m in range(nd):
                        for v in range(nd):
                            ljt[m, v] = lq[v, m]
                    for ri in range(nb):
                        tr = qbuf[2 * ri + 1]
                        if tr < tc:
                            continue
                        lr = row_blk[qbuf[2 * ri]]
                        r = tr * nd
                        work[1] += 1
                        if nd == 3:
                            for a in range(3):  # as below
                                u0 = u1 = u2 = 0.0
                                for m in range(3):
                                    x = lr[a, m]
                                    u0 += x * ljt[m, 0]
                                    u1 += x * ljt[m, 1]
                                    u2 += x * ljt[m, 2]
                                pj[r + a, o] -= u0
                                pj[r + a, o + 1] -= u1
                                pj[r + a, o + 2] -= u2
                            continue
                        # pj block -= lr lq^T: six independent sums per row of lr, each over
                        # m in order (held in registers)
                        for a in range(6):
                            u0 = u1 = u2 = u3 = u4 = u5 = 0.0
                            for m in range(6):
                                x = lr[a, m]
                                u0 += x * ljt[m, 0]
                                u1 += x * ljt[m, 1]
                                u2 += x * ljt[m, 2]
                                u3 += x * ljt[m, 3]
                                u4 += x * ljt[m, 4]
                                u5 += x * ljt[m, 5]
                            pj[r + a, o] -= u0
                            pj[r + a, o + 1] -= u1
                            pj[r + a, o + 2] -= u2
                            pj[r + a, o + 3] -= u3
                            pj[r + a, o + 4] -= u4
                            pj[r + a, o + 5] -= u5
        if not _factor_panel(pj, nc, scratch):
            return NOT_SPD
        # y_J = L_JJ^-1 b_J; the columns back to the column storage
        for c in range(nc):
            acc = bv[c]
            for m in range(c):
                acc -= pj[c, m] * bv[m]
            bv[c] = acc / pj[c, c]
        for c in range(w):
            j = order[a0 + c]
            o = c * nd
            if col_len[j] != nr - c - 1:
                return BROKEN_TREE
            dj = diag[j]
            for a in range(6):
                for v in range(6):
                    dj[a, v] = 0.0
                dj[a, a] = 1.0
            for a in range(nd):
                for v in range(a + 1):
                    dj[a, v] = pj[o + a, o + v]
                y[j, a] = bv[o + a]
            for a in range(nd, 6):
                y[j, a] = 0.0
            s0 = col_start[j]
            for t in range(nr - c - 1):
                blk = row_blk[s0 + t]
                r = (c + 1 + t) * nd
                for a in range(nd):
                    for v in range(nd):
                        blk[a, v] = pj[r + a, o + v]
        for c in range(w):
            slot[order[a0 + c]] = -1
        for t in range(ln):
            slot[row_var[ls0 + t]] = -1
        if cycle_counter() > deadline:
            return s + 1
    return sn_count


# --------------------------------------------------------------------------- back substitution
@kernel
def back_substitute(stack: np.ndarray, top: np.ndarray, deadline: np.uint64,
                    in_s: np.ndarray, stamp: int, changed: np.ndarray, threshold: float,
                    ch_head: np.ndarray, ch_next: np.ndarray, col_start: np.ndarray,
                    col_len: np.ndarray, row_var: np.ndarray, row_blk: np.ndarray,
                    diag: np.ndarray, y: np.ndarray, x: np.ndarray, touched: np.ndarray,
                    n_touched: np.ndarray, nd: int, perm: np.ndarray) -> bool:
    """``L^T x = y`` from the roots down (the caller pushes S's roots on ``stack``); ``x``
    in tangent coordinates, the factor's coordinate ``a < nd`` being ``perm[a]`` (the others
    0: see :func:`numeric`).

    A popped column is recomputed when it is in S or one of its rows changed in this cycle
    (``changed[r] == stamp``); it is marked changed when its x moved by more than
    ``threshold`` (inf-norm).  A child's rows are its parent and rows of its parent, so a
    child needs recomputing only when the column or one of its rows changed: its children
    are pushed then (always with ``threshold`` 0), and a child of S is pushed always.
    Recomputed columns are appended to ``touched``.  Returns True when the stack is empty,
    False when stopped at ``deadline`` (call again).
    """
    xn = np.empty(6)
    while top[0] > 0:
        top[0] -= 1
        j = stack[top[0]]
        s0 = col_start[j]
        n = col_len[j]
        rows_changed = False
        for t in range(s0, s0 + n):
            if changed[row_var[t]] == stamp:
                rows_changed = True
                break
        if not (rows_changed or in_s[j] == stamp):
            continue
        for a in range(6):
            xn[a] = y[j, a]
        for t in range(s0, s0 + n):
            r = row_var[t]
            blk = row_blk[t]
            if nd == 3:  # as below, x_r read in the factor's coordinates
                u0 = u1 = u2 = 0.0
                for m in range(3):
                    xm = x[r, perm[m]]
                    u0 += blk[m, 0] * xm
                    u1 += blk[m, 1] * xm
                    u2 += blk[m, 2] * xm
                xn[0] -= u0
                xn[1] -= u1
                xn[2] -= u2
                continue
            # xn -= blk^T x_r: six independent sums, each over m in order (in registers)
            u0 = u1 = u2 = u3 = u4 = u5 = 0.0
            for m in range(6):
                xm = x[r, m]
                u0 += blk[m, 0] * xm
                u1 += blk[m, 1] * xm
                u2 += blk[m, 2] * xm
                u3 += blk[m, 3] * xm
                u4 += blk[m, 4] * xm
                u5 += blk[m, 5] * xm
            xn[0] -= u0
            xn[1] -= u1
            xn[2] -= u2
            xn[3] -= u3
            xn[4] -= u4
            xn[5] -= u5
        dj = diag[j]
        for c in range(nd - 1, -1, -1):
            s = xn[c]
            for m in range(c + 1, nd):
                s -= dj[m, c] * xn[m]
            xn[c] = s / dj[c, c]
        dev = 0.0
        for a in range(nd):
            pa = perm[a]
            dv = abs(xn[a] - x[j, pa])
            if dv > dev:
                dev = dv
            x[j, pa] = xn[a]
        moved = dev > threshold
        if moved:
            changed[j] = stamp
        # exact (threshold 0): every child of a recomputed column is visited
        touched[n_touched[0]] = j
        n_touched[0] += 1
        push = moved or rows_changed or threshold <= 0.0
        c = ch_head[j]
        while c >= 0:
            if push or in_s[c] == stamp:
                if top[0] >= stack.shape[0]:
                    return False  # cannot happen: the stack holds every variable
                stack[top[0]] = c
                top[0] += 1
            c = ch_next[c]
        if cycle_counter() > deadline:
            return bool(top[0] == 0)
    return True


# --------------------------------------------------------------------------- poses
@kernel
def publish(vars_: np.ndarray, th_r: np.ndarray, th_t: np.ndarray, x: np.ndarray,
            est_r: np.ndarray, est_t: np.ndarray) -> None:
    """The estimate ``theta_v Exp(x_v)`` of each listed variable."""
    er = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for q in range(vars_.shape[0]):
        v = vars_[q]
        retract_into(th_r[v], th_t[v], x[v], 1.0, est_r[v], est_t[v], er, tmp)


@kernel
def append_moved(vars_: np.ndarray, x: np.ndarray, beta_rho: float, beta_phi: float,
                 flag: np.ndarray, out: np.ndarray, count: np.ndarray) -> None:
    """Append to ``out`` (from ``count[0]``) each listed variable whose step exceeds the
    thresholds (negative thresholds: every one) and is not listed yet (``flag``)."""
    for q in range(vars_.shape[0]):
        v = vars_[q]
        if flag[v]:
            continue
        mr = max(abs(x[v, 0]), abs(x[v, 1]), abs(x[v, 2]))
        mp = max(abs(x[v, 3]), abs(x[v, 4]), abs(x[v, 5]))
        if mr > beta_rho or mp > beta_phi:
            flag[v] = True
            out[count[0]] = v
            count[0] += 1


@kernel
def relinearize(vars_: np.ndarray, beta_rho: float, beta_phi: float, th_r: np.ndarray,
                th_t: np.ndarray, x: np.ndarray, est_r: np.ndarray, est_t: np.ndarray,
                out: np.ndarray) -> int:
    """Move the linearization point of each listed variable whose step exceeds the thresholds
    (translation part > ``beta_rho`` or rotation part > ``beta_phi``, inf-norm) to its
    estimate, its step to 0.  Writes those variables to ``out``; returns how many."""
    k = 0
    for q in range(vars_.shape[0]):
        v = vars_[q]
        mr = max(abs(x[v, 0]), abs(x[v, 1]), abs(x[v, 2]))
        mp = max(abs(x[v, 3]), abs(x[v, 4]), abs(x[v, 5]))
        if mr > beta_rho or mp > beta_phi:
            for a in range(3):
                th_t[v, a] = est_t[v, a]
                for c in range(3):
                    th_r[v, a, c] = est_r[v, a, c]
            for a in range(6):
                x[v, a] = 0.0
            out[k] = v
            k += 1
    return k


@kernel
def incident_factors(vars_: np.ndarray, inc_head: np.ndarray, inc_next: np.ndarray,
                     gps_head: np.ndarray, gps_next: np.ndarray, e_stamp: np.ndarray,
                     g_stamp: np.ndarray, stamp: int, out_e: np.ndarray,
                     out_g: np.ndarray, counts: np.ndarray) -> None:
    """The edges and GPS readings touching the listed variables, each once (appended to
    ``out_e``/``out_g`` from ``counts[0]``/``counts[1]``)."""
    for q in range(vars_.shape[0]):
        v = vars_[q]
        i = inc_head[v]
        while i >= 0:
            e = i >> 1
            if e_stamp[e] != stamp:
                e_stamp[e] = stamp
                out_e[counts[0]] = e
                counts[0] += 1
            i = inc_next[i]
        i = gps_head[v]
        while i >= 0:
            if g_stamp[i] != stamp:
                g_stamp[i] = stamp
                out_g[counts[1]] = i
                counts[1] += 1
            i = gps_next[i]


# --------------------------------------------------------------------------- integration
@kernel
def insert_incidences(e0: int, e1: int, ab: np.ndarray, inc_head: np.ndarray,
                      inc_next: np.ndarray) -> None:
    """Link edges ``e0..e1-1`` into their ends' incidence lists (incidence ``2 e + side``)."""
    for e in range(e0, e1):
        for side in range(2):
            v = ab[e, side]
            i = 2 * e + side
            inc_next[i] = inc_head[v]
            inc_head[v] = i


@kernel
def insert_gps(g0: int, g1: int, node: np.ndarray, gps_head: np.ndarray,
               gps_next: np.ndarray) -> None:
    """Link GPS readings ``g0..g1-1`` into their poses' lists."""
    for g in range(g0, g1):
        v = node[g]
        gps_next[g] = gps_head[v]
        gps_head[v] = g


@kernel
def place_poses(p0: int, p1: int, ref: np.ndarray, rel_r: np.ndarray, rel_t: np.ndarray,
                est_r: np.ndarray, est_t: np.ndarray, th_r: np.ndarray,
                th_t: np.ndarray) -> None:
    """Initial estimate (and linearization point) of poses ``p0..p1-1``: ``rel`` composed onto
    the current estimate of pose ``ref[p]`` (< p), or ``rel`` itself when ``ref[p] < 0``."""
    for p in range(p0, p1):
        r = ref[p]
        if r < 0:
            for a in range(3):
                est_t[p, a] = rel_t[p, a]
                for c in range(3):
                    est_r[p, a, c] = rel_r[p, a, c]
        else:
            for a in range(3):
                s = est_t[r, a]
                for m in range(3):
                    s += est_r[r, a, m] * rel_t[p, m]
                est_t[p, a] = s
                for c in range(3):
                    s = 0.0
                    for m in range(3):
                        s += est_r[r, a, m] * rel_r[p, m, c]
                    est_r[p, a, c] = s
        for a in range(3):
            th_t[p, a] = est_t[p, a]
            for c in range(3):
                th_r[p, a, c] = est_r[p, a, c]
