"""Sliding-midpoint 3-D KD-tree: build, gated 1-NN, exact kNN and radius search (Numba).

One tree serves every exact Euclidean search of minegeo in 3-D (ICP and GICP correspondences,
GICP's kNN normals, the localisation's candidate refinement). Contiguous float64 arrays in, no
checks. The tree is one :class:`PackedKDTree` (a ``NamedTuple`` of the arrays ``idx, Qs, start, end,
dim, split, left, right`` and the int ``depth``) returned by :func:`kd_build`; kernels take it as one
argument and read its fields (a named tuple is a Numba value type: the same machine code as the
loose arrays, cacheable, usable in ``prange`` bodies); every search is exact and breaks ties by the lower point index, so its
answers do not depend on the tree's shape nor on the thread count (queries are independent;
the 1-NN drivers cut the rows into :data:`~minegeo.kernels.chunks.QUERY_TASK_ROWS`-row tasks,
the kNN and radius drivers into :data:`~minegeo.kernels.chunks.CHUNK`-row chunks).

Why a hand-written tree next to pykdtree: see ``docs/kernels.md`` (measurements of
``benchmarks/bench_kernels.py``): the strict gate ``sq < d2`` is part of the descent (few nodes
visited for a small gate), the ``(sq, index)`` tie rule is exact, the tree can be stored and
restored (:meth:`GatedKDTree.arrays`), and the kernels are callable from other njit code
(per-candidate ICP in :mod:`minegeo.localize._kernels`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo._validate import is_permutation
from minegeo.kernels.chunks import CHUNK, PARALLEL_QUERY_ROWS, QUERY_TASK_ROWS, by_size, n_chunks

__all__ = ["KD_LEAF", "PackedKDTree", "kd_build", "kd_walk_to_leaf", "kd_nn_descend", "kd_nn2_descend", "kd_nn_rows", "kd_nn_serial",
           "kd_nn_parallel", "kd_nn_warm_rows", "kd_nn_warm_serial", "kd_nn_warm_parallel", "warm_bound", "take_nearest2", "kd_knn_one",
           "kd_knn", "kd_radius_one", "kd_radius_count", "kd_boxes", "kd_knn_leaf_batch", "sq_to_row",
           "GatedKDTree"]

#: Maximum number of points in a KD-tree leaf.
KD_LEAF = 12


class PackedKDTree(NamedTuple):
    """A :func:`kd_build` tree over ``m`` points, in one value that Numba kernels take as one argument.

    Attributes
    ----------
    idx : (m,) int64
        Point order of the leaves: ``Qs = Q[idx]``.
    Qs : (m, 3) float64
        The points in leaf order (m).
    start, end : (nodes,) int64
        Per node the range ``[start, end)`` of its points in ``Qs``.
    dim : (nodes,) int64
        Split dimension (0, 1, 2), or -1 for a leaf.
    split : (nodes,) float64
        Split value (m) along ``dim``: points ``< split`` go left.
    left, right : (nodes,) int64
        Children (-1 for a leaf).
    depth : int
        The maximum node depth (the root is 0); search stacks hold ``depth + 2`` entries.
    """

    idx: np.ndarray
    Qs: np.ndarray
    start: np.ndarray
    end: np.ndarray
    dim: np.ndarray
    split: np.ndarray
    left: np.ndarray
    right: np.ndarray
    depth: int


@njit
def _grow(a, n):
    """Copy of ``a`` (first axis) with capacity ``n`` (new entries undefined)."""
    out = np.empty((n,) + a.shape[1:], a.dtype)
    out[: a.shape[0]] = a
    return out


@njit
def _widen(lo0, lo1, lo2, hi0, hi1, hi2, x, y, z):
    """The bounding box ``(lo, hi)`` widened to hold ``(x, y, z)`` (kept in registers)."""
    if x < lo0:
        lo0 = x
    if y < lo1:
        lo1 = y
    if z < lo2:
        lo2 = z
    if x > hi0:
        hi0 = x
    if y > hi1:
        hi1 = y
    if z > hi2:
        hi2 = z
    return lo0, lo1, lo2, hi0, hi1, hi2


@njit
def _set_box(box, b, lo0, lo1, lo2, hi0, hi1, hi2):
    box[b, 0] = lo0
    box[b, 1] = lo1
    box[b, 2] = lo2
    box[b, 3] = hi0
    box[b, 4] = hi1
    box[b, 5] = hi2


@njit
def kd_build(Q, leaf):
    """Sliding-midpoint KD-tree over ``Q`` (m, 3): split the widest bounding-box side at its middle.

    Returns the :class:`PackedKDTree` ``(idx, Qs, start, end, dim, split, left, right, depth)``: ``Qs = Q[idx]`` (points in
    leaf order), per node the ``[start, end)`` range into ``Qs``, the split dimension (-1 = leaf),
    the split value and the children; ``depth`` is the maximum node depth. Coincident points
    (zero spread) stay in one leaf.

    The points are partitioned in a contiguous working copy (rows swapped together with
    ``idx``), and the exact bounding boxes of both children are accumulated in registers while
    their parent is partitioned (:func:`_widen`), so each tree level costs one sequential pass.
    Node arrays start at ``m // 2 + 64`` entries and grow by doubling (at most ``2 m - 1`` nodes).
    """
    m = Q.shape[0]
    idx = np.arange(m)
    Qs = np.empty((m, 3))
    for a in range(m):
        for c in range(3):
            Qs[a, c] = Q[a, c]
    cap = m // 2 + 64
    start = np.empty(cap, np.int64)
    end = np.empty(cap, np.int64)
    dim = np.empty(cap, np.int64)
    split = np.empty(cap)
    left = np.empty(cap, np.int64)
    right = np.empty(cap, np.int64)
    level = np.empty(cap, np.int64)
    box = np.empty((cap, 6))  # lo x, y, z, hi x, y, z of the node's points
    stack = np.empty(cap, np.int64)
    n_nodes = 1
    start[0] = 0
    end[0] = m
    dim[0] = -1
    split[0] = 0.0
    left[0] = -1
    right[0] = -1
    level[0] = 0
    l0 = l1 = l2 = np.inf
    h0 = h1 = h2 = -np.inf
    for a in range(m):
        l0, l1, l2, h0, h1, h2 = _widen(l0, l1, l2, h0, h1, h2, Qs[a, 0], Qs[a, 1], Qs[a, 2])
    _set_box(box, 0, l0, l1, l2, h0, h1, h2)
    sp = 1
    stack[0] = 0
    depth = 0
    while sp > 0:
        sp -= 1
        nd = stack[sp]
        s = start[nd]
        e = end[nd]
        if level[nd] > depth:
            depth = level[nd]
        if e - s <= leaf:
            continue
        k = 0
        spread = box[nd, 3] - box[nd, 0]
        for c in range(1, 3):
            if box[nd, 3 + c] - box[nd, c] > spread:
                k = c
                spread = box[nd, 3 + c] - box[nd, c]
        if not spread > 0.0:
            continue
        sv = 0.5 * (box[nd, k] + box[nd, 3 + k])
        if n_nodes + 2 > cap:
            cap = 2 * cap
            start = _grow(start, cap)
            end = _grow(end, cap)
            dim = _grow(dim, cap)
            split = _grow(split, cap)
            left = _grow(left, cap)
            right = _grow(right, cap)
            level = _grow(level, cap)
            box = _grow(box, cap)
            stack = _grow(stack, cap)
        lc = n_nodes
        rc = n_nodes + 1
        l0 = l1 = l2 = r0 = r1 = r2 = np.inf
        h0 = h1 = h2 = g0 = g1 = g2 = -np.inf
        i = s
        jj = e - 1
        while i <= jj:  # partition: [s, mid) < sv <= [mid, e)
            x = Qs[i, 0]
            y = Qs[i, 1]
            z = Qs[i, 2]
            if Qs[i, k] < sv:
                l0, l1, l2, h0, h1, h2 = _widen(l0, l1, l2, h0, h1, h2, x, y, z)
                i += 1
            else:
                t = idx[i]
                idx[i] = idx[jj]
                idx[jj] = t
                Qs[i, 0] = Qs[jj, 0]
                Qs[i, 1] = Qs[jj, 1]
                Qs[i, 2] = Qs[jj, 2]
                Qs[jj, 0] = x
                Qs[jj, 1] = y
                Qs[jj, 2] = z
                r0, r1, r2, g0, g1, g2 = _widen(r0, r1, r2, g0, g1, g2, x, y, z)
                jj -= 1
        _set_box(box, lc, l0, l1, l2, h0, h1, h2)
        _set_box(box, rc, r0, r1, r2, g0, g1, g2)
        mid = i
        if mid == s or mid == e:  # midpoint rounding on a tiny spread: keep as a leaf
            continue
        dim[nd] = k
        split[nd] = sv
        n_nodes += 2
        for ch in (lc, rc):
            dim[ch] = -1
            split[ch] = 0.0
            left[ch] = -1
            right[ch] = -1
            level[ch] = level[nd] + 1
        start[lc] = s
        end[lc] = mid
        start[rc] = mid
        end[rc] = e
        left[nd] = lc
        right[nd] = rc
        stack[sp] = lc
        sp += 1
        stack[sp] = rc
        sp += 1
    return PackedKDTree(idx, Qs, start[:n_nodes].copy(), end[:n_nodes].copy(), dim[:n_nodes].copy(),
                        split[:n_nodes].copy(), left[:n_nodes].copy(), right[:n_nodes].copy(), depth)


@njit
def sq_to_row(px, py, pz, X, a):
    """Squared distance of ``(px, py, pz)`` to row ``a`` of ``X``: ``dx*dx + dy*dy + dz*dz``."""
    dx = px - X[a, 0]
    dy = py - X[a, 1]
    dz = pz - X[a, 2]
    return dx * dx + dy * dy + dz * dz


@njit
def kd_walk_to_leaf(px, py, pz, nd, bound, tree, st_node, st_lb, sp):
    """Descend a :func:`kd_build` tree from node ``nd`` to the leaf holding ``(px, py, pz)``,
    pushing every far child whose squared plane distance is ``<= bound`` (with that distance as
    its lower bound) onto the caller's stacks. Returns ``(leaf, stack size)``."""
    dim = tree.dim
    split = tree.split
    left = tree.left
    right = tree.right
    while dim[nd] >= 0:
        k = dim[nd]
        if k == 0:
            diff = px - split[nd]
        elif k == 1:
            diff = py - split[nd]
        else:
            diff = pz - split[nd]
        if diff < 0.0:
            near = left[nd]
            far = right[nd]
        else:
            near = right[nd]
            far = left[nd]
        dd = diff * diff
        if dd <= bound:
            st_node[sp] = far
            st_lb[sp] = dd
            sp += 1
        nd = near
    return nd, sp


@njit
def kd_nn_descend(px, py, pz, best, best_j, tree, d2, st_node, st_lb):
    """Gated nearest neighbour of ``(px, py, pz)`` on a :func:`kd_build` tree.

    ``(best, best_j)`` is the starting bound: ``(d2, m)`` for a cold search, or a known
    point's ``(sq, index)`` with ``sq < d2`` (a warm start: same answer, fewer nodes). Returns
    the lexicographically smallest ``(sq, index)`` with ``sq < d2``
    (``sq = dx*dx + dy*dy + dz*dz``), or the start bound when none is closer. ``st_node`` /
    ``st_lb`` are caller-owned stacks of length ``depth + 2``.
    """
    idx = tree.idx
    Qs = tree.Qs
    start = tree.start
    end = tree.end
    st_node[0] = 0
    st_lb[0] = 0.0
    sp = 1
    while sp > 0:
        sp -= 1
        nd = st_node[sp]
        if st_lb[sp] > best:
            continue
        nd, sp = kd_walk_to_leaf(px, py, pz, nd, best, tree, st_node, st_lb, sp)
        for a in range(start[nd], end[nd]):
            sq = sq_to_row(px, py, pz, Qs, a)
            if sq < d2:
                j = idx[a]
                if sq < best or (sq == best and j < best_j):
                    best = sq
                    best_j = j
    return best, best_j


@njit(inline="always")
def take_nearest2(sq, j, best, best_j, second):
    """Offer point ``j`` at squared distance ``sq`` to a nearest-and-second search: ``(best, best_j)``
    stays the lexicographically smallest ``(sq, index)``, ``second`` the smallest squared distance
    of the other points offered; returns the updated ``(best, best_j, second)``."""
    if sq < best or (sq == best and j < best_j):
        if best < second:
            second = best
        return sq, j, second
    if sq < second:
        second = sq
    return best, best_j, second


@njit
def kd_nn2_descend(px, py, pz, best, best_j, tree, d2, st_node, st_lb):
    """:func:`kd_nn_descend` that also returns the second distance: ``(best, best_j, second)``.

    ``(best, best_j)`` is the answer of :func:`kd_nn_descend` from the same start; ``second``
    is the smallest ``sq < d2`` of the points other than ``best_j`` (``d2`` when there is none),
    so every other point is at least ``sqrt(second)`` away. Nodes are pruned against ``second``
    (never below ``best``), hence exact for both.
    """
    idx = tree.idx
    Qs = tree.Qs
    start = tree.start
    end = tree.end
    second = d2
    st_node[0] = 0
    st_lb[0] = 0.0
    sp = 1
    while sp > 0:
        sp -= 1
        nd = st_node[sp]
        if st_lb[sp] > second:
            continue
        nd, sp = kd_walk_to_leaf(px, py, pz, nd, second, tree, st_node, st_lb, sp)
        for a in range(start[nd], end[nd]):
            sq = sq_to_row(px, py, pz, Qs, a)
            if sq < d2:
                j = idx[a]
                if j != best_j:
                    best, best_j, second = take_nearest2(sq, j, best, best_j, second)
    return best, best_j, second


@njit
def kd_nn_rows(P, tree, d2, out_idx, out_sq, r0, r1):
    m = tree.idx.shape[0]
    st_node = np.empty(tree.depth + 2, np.int64)
    st_lb = np.empty(tree.depth + 2)
    for i in range(r0, r1):
        best, best_j = kd_nn_descend(P[i, 0], P[i, 1], P[i, 2], d2, m, tree, d2, st_node, st_lb)
        out_idx[i] = best_j
        out_sq[i] = best if best_j < m else np.inf


@njit
def kd_nn_serial(P, tree, d2, out_idx, out_sq):
    kd_nn_rows(P, tree, d2, out_idx, out_sq, 0, P.shape[0])


@njit_parallel
def kd_nn_parallel(P, tree, d2, out_idx, out_sq):
    """:func:`kd_nn_serial` with ``prange`` over ``QUERY_TASK_ROWS``-row tasks (per-row results:
    any split gives the same bits)."""
    n = P.shape[0]
    for c in prange((n + QUERY_TASK_ROWS - 1) // QUERY_TASK_ROWS):
        kd_nn_rows(P, tree, d2, out_idx, out_sq, c * QUERY_TASK_ROWS, min(n, (c + 1) * QUERY_TASK_ROWS))


@njit(inline="always")
def warm_bound(px, py, pz, Q, j0, d2, m):
    """The start bound ``(best, best_j)`` of a warm 1-NN search (:func:`kd_nn_descend`) of
    ``(px, py, pz)`` from a known partner ``j0`` (row of ``Q``; ``m`` = none): ``(sq, j0)`` when its
    squared distance ``sq < d2``, else the cold bound ``(d2, m)``."""
    if j0 < m:
        sq0 = sq_to_row(px, py, pz, Q, j0)
        if sq0 < d2:
            return sq0, j0
    return d2, m


@njit
def kd_nn_warm_rows(P, Q, tree, d2, prev, out_idx, out_sq, r0, r1):
    """:func:`kd_nn_rows` with the search bound of row ``i`` initialised by a known partner
    ``prev[i]`` (``m`` = none), typically the previous iteration's correspondence.

    The partner's squared distance is an upper bound of the nearest one, so fewer nodes are
    visited; the answer is the cold search's: the lexicographically smallest ``(sq, index)``
    with ``sq < d2``, ``sq = dx*dx + dy*dy + dz*dz``.
    """
    m = tree.idx.shape[0]
    st_node = np.empty(tree.depth + 2, np.int64)
    st_lb = np.empty(tree.depth + 2)
    for i in range(r0, r1):
        px = P[i, 0]
        py = P[i, 1]
        pz = P[i, 2]
        best, best_j = warm_bound(px, py, pz, Q, prev[i], d2, m)
        best, best_j = kd_nn_descend(px, py, pz, best, best_j, tree, d2, st_node, st_lb)
        out_idx[i] = best_j
        out_sq[i] = best if best_j < m else np.inf


@njit
def kd_nn_warm_serial(P, Q, tree, d2, prev, out_idx, out_sq):
    kd_nn_warm_rows(P, Q, tree, d2, prev, out_idx, out_sq, 0, P.shape[0])


@njit_parallel
def kd_nn_warm_parallel(P, Q, tree, d2, prev, out_idx, out_sq):
    """:func:`kd_nn_warm_serial` with ``prange`` over ``QUERY_TASK_ROWS``-row tasks."""
    n = P.shape[0]
    for c in prange((n + QUERY_TASK_ROWS - 1) // QUERY_TASK_ROWS):
        kd_nn_warm_rows(P, Q, tree, d2, prev, out_idx, out_sq, c * QUERY_TASK_ROWS, min(n, (c + 1) * QUERY_TASK_ROWS))


class GatedKDTree:
    """Exact nearest target point within a gate, on a Numba KD-tree (built once per target).

    ``query(P, d2)`` returns ``(idx, sq)``: for every row of ``P`` the index of the nearest target
    point with squared distance ``< d2`` (strict; ties -> lowest index) or ``m`` when none, and that
    squared distance (``inf`` when none), computed as ``dx*dx + dy*dy + dz*dz``.
    The gate bounds the search, so each query visits only a few leaves.
    """

    def __init__(self, Q):
        self.m = Q.shape[0]
        self.data = Q
        self._tree = kd_build(Q, KD_LEAF)

    @property
    def packed(self) -> PackedKDTree:
        """The tree as the one :class:`PackedKDTree` value that the search kernels take."""
        return self._tree

    def arrays(self) -> dict:
        """The tree's own arrays (``Qs`` is not among them: it is ``data[idx]``), for storage."""
        idx, _, start, end, dim, split, left, right, depth = self._tree
        return {"idx": idx, "start": start, "end": end, "dim": dim, "split": split, "left": left, "right": right,
                "depth": np.array([depth], dtype=np.int64)}

    @classmethod
    def from_arrays(cls, Q, a: dict):
        """The tree of :meth:`arrays` over the same points ``Q``. Checks what a query relies on
        (``idx`` a permutation of the rows, node ranges and children in bounds, the stated depth
        the real one) and raises ``ValueError`` otherwise: the kernels do not bounds-check."""
        m = Q.shape[0]
        idx = np.ascontiguousarray(a["idx"], dtype=np.int64)
        nodes = [np.ascontiguousarray(a[k]) for k in ("start", "end", "dim", "split", "left", "right")]
        n = nodes[0].shape[0]
        if idx.shape != (m,) or n < 1 or any(x.ndim != 1 or x.shape[0] != n for x in nodes):
            raise ValueError("KD-tree arrays have the wrong shapes")
        start, end, dim, split, left, right = nodes
        if not is_permutation(idx, m):
            raise ValueError("KD-tree point order is not a permutation of the points")
        leaf = dim < 0
        if (start.min() < 0 or end.max() > m or np.any(start > end) or dim.max() > 2
                or np.any(~leaf & ((left < 1) | (left >= n) | (right < 1) | (right >= n)))):
            raise ValueError("KD-tree node ranges or children out of bounds")
        # depth: walk the levels from the root (a cycle or an orphan shows as a wrong count)
        level, depth, seen = np.array([0]), 0, 1
        while True:
            inner = level[~leaf[level]]
            if inner.size == 0:
                break
            level = np.concatenate([left[inner], right[inner]])
            depth += 1
            seen += level.size
            if seen > n:
                raise ValueError("KD-tree nodes do not form a tree")
        if seen != n or int(np.asarray(a["depth"]).ravel()[0]) != depth:
            raise ValueError("KD-tree depth or node count is wrong")
        self = cls.__new__(cls)
        self.m = m
        self.data = Q
        self._tree = PackedKDTree(idx, np.ascontiguousarray(Q[idx]), start.astype(np.int64), end.astype(np.int64),
                                  dim.astype(np.int64), split.astype(np.float64), left.astype(np.int64),
                                  right.astype(np.int64), depth)
        return self

    def query(self, P, d2):
        n = P.shape[0]
        idx = np.empty(n, dtype=np.int64)
        sq = np.empty(n)
        by_size(n, PARALLEL_QUERY_ROWS, kd_nn_serial, kd_nn_parallel)(P, self._tree, float(d2), idx, sq)
        return idx, sq


# ----------------------------------------------------------------------------- exact kNN


@njit
def kd_knn_one(px, py, pz, tree, k, bi, bs, st_node, st_lb):
    """The ``k`` nearest points of ``(px, py, pz)`` on a ``kd_build`` tree, sorted by
    ``(squared distance, index)`` into ``bi``/``bs``; returns the count (``min(k, m)``).

    Exact: a node is skipped only when its lower bound exceeds the current k-th distance, so a
    point tied with the k-th one is still visited and the lower index wins (the convention of
    :meth:`minegeo.geometry.NeighborIndex.knn`).
    """
    idx = tree.idx
    Qs = tree.Qs
    start = tree.start
    end = tree.end
    c = 0
    worst = np.inf
    st_node[0] = 0
    st_lb[0] = 0.0
    sp = 1
    while sp > 0:
        sp -= 1
        nd = st_node[sp]
        if st_lb[sp] > worst:
            continue
        nd, sp = kd_walk_to_leaf(px, py, pz, nd, worst, tree, st_node, st_lb, sp)
        for a in range(start[nd], end[nd]):
            sq = sq_to_row(px, py, pz, Qs, a)
            if c == k and sq > worst:
                continue
            j = idx[a]
            if c == k and sq == worst and j > bi[k - 1]:
                continue
            pos = c if c < k else k - 1  # insertion into the sorted buffer
            while pos > 0 and (bs[pos - 1] > sq or (bs[pos - 1] == sq and bi[pos - 1] > j)):
                bs[pos] = bs[pos - 1]
                bi[pos] = bi[pos - 1]
                pos -= 1
            bs[pos] = sq
            bi[pos] = j
            if c < k:
                c += 1
            if c == k:
                worst = bs[k - 1]
    return c


@njit
def _kd_knn_rows(P, tree, k, out_idx, out_sq, r0, r1):
    bi = np.empty(k, np.int64)
    bs = np.empty(k)
    st_node = np.empty(tree.depth + 2, np.int64)
    st_lb = np.empty(tree.depth + 2)
    for i in range(r0, r1):
        c = kd_knn_one(P[i, 0], P[i, 1], P[i, 2], tree, k, bi, bs, st_node, st_lb)
        for a in range(c):
            out_idx[i, a] = bi[a]
            out_sq[i, a] = bs[a]


@njit_parallel
def _kd_knn_parallel(P, tree, k, out_idx, out_sq):
    n = P.shape[0]
    for c in prange(n_chunks(n)):
        _kd_knn_rows(P, tree, k, out_idx, out_sq, c * CHUNK, min(n, (c + 1) * CHUNK))


def kd_knn(P, tree, k):
    """The ``k`` nearest tree points of every row of ``P`` (n, 3), sorted by ``(sq, index)``.

    Returns ``(idx (n, k) int64, sq (n, k) float64)``; when the tree holds ``m < k`` points
    the columns ``m..k-1`` are ``m`` / ``inf`` (pykdtree's convention). ``tree`` is the
    :class:`PackedKDTree` of :func:`kd_build`.
    """
    n = P.shape[0]
    m = tree.idx.shape[0]
    out_idx = np.full((n, k), m, dtype=np.int64)
    out_sq = np.full((n, k), np.inf)
    if n > 0 and k > 0:
        _kd_knn_parallel(P, tree, min(int(k), m), out_idx, out_sq)
    return out_idx, out_sq


# ----------------------------------------------------------------------------- radius search


@njit
def kd_radius_one(px, py, pz, r2, tree, out, st_node, st_lb):
    """Indices of every tree point with ``sq < r2`` around ``(px, py, pz)`` (strict, as Open3D's
    ``KDTreeSearchParamRadius``), written to ``out`` in leaf order; returns their number (it
    may exceed ``out.shape[0]``: only the first ``out.shape[0]`` are written)."""
    idx = tree.idx
    Qs = tree.Qs
    start = tree.start
    end = tree.end
    c = 0
    cap = out.shape[0]
    st_node[0] = 0
    st_lb[0] = 0.0
    sp = 1
    while sp > 0:
        sp -= 1
        nd = st_node[sp]
        if st_lb[sp] >= r2:
            continue
        nd, sp = kd_walk_to_leaf(px, py, pz, nd, r2, tree, st_node, st_lb, sp)
        for a in range(start[nd], end[nd]):
            if sq_to_row(px, py, pz, Qs, a) < r2:
                if c < cap:
                    out[c] = idx[a]
                c += 1
    return c


@njit_parallel
def _kd_radius_count_parallel(P, tree, r2, counts):
    n = P.shape[0]
    for c in prange(n_chunks(n)):
        st_node = np.empty(tree.depth + 2, np.int64)
        st_lb = np.empty(tree.depth + 2)
        buf = np.empty(0, np.int64)
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            counts[i] = kd_radius_one(P[i, 0], P[i, 1], P[i, 2], r2, tree, buf, st_node, st_lb)


def kd_radius_count(P, tree, radius):
    """Number of tree points strictly within ``radius`` (m) of every row of ``P`` (n, 3)."""
    counts = np.zeros(P.shape[0], dtype=np.int64)
    if P.shape[0] > 0:
        _kd_radius_count_parallel(P, tree, float(radius) ** 2, counts)
    return counts


# ----------------------------------------------------------------------------- batched kNN of a leaf's points


@njit
def kd_boxes(tree):
    """``(box (nodes, 6), leaf_at (m,))`` of a :func:`kd_build` tree: the exact
    bounding box (lo x, y, z, hi x, y, z) of every node's points, and the leaf holding each position
    of ``Qs`` (children are numbered after their parent, so one reverse pass gives every box)."""
    Qs = tree.Qs
    start = tree.start
    end = tree.end
    dim = tree.dim
    left = tree.left
    right = tree.right
    nn = start.shape[0]
    box = np.empty((nn, 6))
    leaf_at = np.empty(Qs.shape[0], np.int64)
    for nd in range(nn - 1, -1, -1):
        if dim[nd] < 0:
            l0 = l1 = l2 = np.inf
            h0 = h1 = h2 = -np.inf
            for a in range(start[nd], end[nd]):
                leaf_at[a] = nd
                x = Qs[a, 0]
                y = Qs[a, 1]
                z = Qs[a, 2]
                l0 = min(l0, x)
                l1 = min(l1, y)
                l2 = min(l2, z)
                h0 = max(h0, x)
                h1 = max(h1, y)
                h2 = max(h2, z)
            box[nd, 0] = l0
            box[nd, 1] = l1
            box[nd, 2] = l2
            box[nd, 3] = h0
            box[nd, 4] = h1
            box[nd, 5] = h2
        else:
            a = left[nd]
            b = right[nd]
            for c in range(3):
                box[nd, c] = min(box[a, c], box[b, c])
                box[nd, 3 + c] = max(box[a, 3 + c], box[b, 3 + c])
    return box, leaf_at


@njit
def _box_gap2(box, nd, l0, l1, l2, h0, h1, h2):
    """Squared gap between node ``nd``'s box and the box ``(l, h)``, summed as ``sq_to_row`` sums: a lower
    bound of the ``sq`` of any pair of points of the two boxes *in floating point* (each gap is a
    rounded difference no larger than the pair's, and sums and products of non-negative numbers are
    monotone), so pruning on it is exact."""
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    t = box[nd, 0] - h0
    if t > 0.0:
        g0 = t
    t = l0 - box[nd, 3]
    if t > 0.0:
        g0 = t
    t = box[nd, 1] - h1
    if t > 0.0:
        g1 = t
    t = l1 - box[nd, 4]
    if t > 0.0:
        g1 = t
    t = box[nd, 2] - h2
    if t > 0.0:
        g2 = t
    t = l2 - box[nd, 5]
    if t > 0.0:
        g2 = t
    return g0 * g0 + g1 * g1 + g2 * g2


@njit
def kd_knn_leaf_batch(tree, k, box, L, a0, nq, bi, bs, cnt, wq, st_node, st_lb):
    """The exact ``k`` nearest points (sorted by ``(sq, index)``, the answer of
    :func:`kd_knn_one`) of the ``nq`` points at positions ``a0 ..`` of leaf ``L``,
    with one traversal of the tree for all of them: a node is visited while its box is within the
    largest current k-th distance of the batch from the leaf's box, a leaf is scanned for a query
    while its box is within that query's k-th distance, and a point enters a query's sorted buffer
    (``bi[q]``, ``bs[q]``; ``cnt[q]`` entries) as in ``kd_knn_one`` (ties: the lower index wins).
    Every bound is a floating-point lower bound of the pair distances, so the visiting order changes
    the work only, never the answer."""
    Qs = tree.Qs
    idx = tree.idx
    start = tree.start
    end = tree.end
    dim = tree.dim
    left = tree.left
    right = tree.right
    l0 = box[L, 0]
    l1 = box[L, 1]
    l2 = box[L, 2]
    h0 = box[L, 3]
    h1 = box[L, 4]
    h2 = box[L, 5]
    for q in range(nq):
        cnt[q] = 0
        wq[q] = np.inf
    W = np.inf
    st_node[0] = 0
    st_lb[0] = 0.0
    sp = 1
    while sp > 0:
        sp -= 1
        if st_lb[sp] > W:
            continue
        nd = st_node[sp]
        if dim[nd] >= 0:  # push the farther child first: the nearer is scanned first
            a = left[nd]
            b = right[nd]
            ga = _box_gap2(box, a, l0, l1, l2, h0, h1, h2)
            gb = _box_gap2(box, b, l0, l1, l2, h0, h1, h2)
            if ga > gb:
                a, b = b, a
                ga, gb = gb, ga
            if gb <= W:
                st_node[sp] = b
                st_lb[sp] = gb
                sp += 1
            if ga <= W:
                st_node[sp] = a
                st_lb[sp] = ga
                sp += 1
            continue
        for q in range(nq):
            px = Qs[a0 + q, 0]
            py = Qs[a0 + q, 1]
            pz = Qs[a0 + q, 2]
            worst = wq[q]
            if _box_gap2(box, nd, px, py, pz, px, py, pz) > worst:
                continue
            c = cnt[q]
            for a in range(start[nd], end[nd]):
                dx = px - Qs[a, 0]
                dy = py - Qs[a, 1]
                dz = pz - Qs[a, 2]
                sq = dx * dx + dy * dy + dz * dz
                if sq > worst:
                    continue
                j = idx[a]
                if c == k and sq == worst and j > bi[q, k - 1]:
                    continue
                pos = c if c < k else k - 1  # insertion into the sorted buffer
                while pos > 0 and (bs[q, pos - 1] > sq or (bs[q, pos - 1] == sq and bi[q, pos - 1] > j)):
                    bs[q, pos] = bs[q, pos - 1]
                    bi[q, pos] = bi[q, pos - 1]
                    pos -= 1
                bs[q, pos] = sq
                bi[q, pos] = j
                if c < k:
                    c += 1
                if c == k:
                    worst = bs[q, k - 1]
            cnt[q] = c
            wq[q] = worst
        W = 0.0
        for q in range(nq):
            W = max(W, wq[q])
