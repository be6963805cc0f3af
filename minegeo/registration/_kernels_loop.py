"""Numba kernels of the registration loop (:mod:`minegeo.registration.loop`; arrays in, no checks).

The loop asks, every iteration, for the *gated nearest neighbour* of each moved source point
``p``: the target point ``q_j`` with the lexicographically smallest ``(sq, j)`` among those with
``sq < d²``, ``sq = dx*dx + dy*dy + dz*dz`` (Open3D ``evaluate_registration``, oracle spec §8).
The answer is defined without reference to a search structure, so every exact search returns
the same bits.

The search is the warm-started KD-tree query of :mod:`minegeo.registration._kernels_gicp`
(the previous partner's ``sq`` only tightens the initial bound: same answer). Each row is
independent (no reduction), so its parallel driver :func:`warm_nn_parallel` cuts the rows into
``QUERY_TASK_ROWS``-row tasks instead of the reductions' 1024-row chunks: 4,761 queries are 38
tasks shared evenly by 2 threads instead of 5 chunks split 3:2.
:func:`compact_matches` turns the per-row answer into the correspondence list and the inlier
sum in one pass.

:func:`kd_build_fast` builds the tree of :func:`minegeo.kernels.kdtree.kd_build` byte for byte
(tested), ~2x faster; the loop uses it for the private tree of a call without ``target_index``.

Determinism: the sum uses the fixed chunking of :mod:`minegeo.kernels.chunks` (partials of
``CHUNK`` consecutive pairs, added serially in chunk order from 0.0), i.e. the bits of
``registration._kernels.sum_kernel`` on the gathered squared distances, whatever the thread count.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.kernels.chunks import CHUNK
from minegeo.kernels.kdtree import _box_add, _grow
from minegeo.registration._kernels_gicp import _nn_warm_rows

#: Rows per task of the parallel query driver (per-row results: any split gives the same bits).
QUERY_TASK_ROWS = 128


# ----------------------------------------------------------------------------- KD-tree build


@njit
def kd_build_fast(Q, leaf):
    """:func:`minegeo.kernels.kdtree.kd_build`, the identical tree (same partition, same node
    numbering, same exact bounding boxes) with the children's boxes kept in registers during the
    partition instead of being read and written in the node array for every point (~2x faster)."""
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
    for c in range(3):
        box[0, c] = np.inf
        box[0, 3 + c] = -np.inf
    for a in range(m):
        _box_add(box, 0, Qs, a)
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
        l0 = np.inf
        l1 = np.inf
        l2 = np.inf
        h0 = -np.inf
        h1 = -np.inf
        h2 = -np.inf
        r0 = np.inf
        r1 = np.inf
        r2 = np.inf
        g0 = -np.inf
        g1 = -np.inf
        g2 = -np.inf
        i = s
        jj = e - 1
        while i <= jj:  # partition: [s, mid) < sv <= [mid, e)
            x = Qs[i, 0]
            y = Qs[i, 1]
            z = Qs[i, 2]
            if Qs[i, k] < sv:
                if x < l0:
                    l0 = x
                if y < l1:
                    l1 = y
                if z < l2:
                    l2 = z
                if x > h0:
                    h0 = x
                if y > h1:
                    h1 = y
                if z > h2:
                    h2 = z
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
                if x < r0:
                    r0 = x
                if y < r1:
                    r1 = y
                if z < r2:
                    r2 = z
                if x > g0:
                    g0 = x
                if y > g1:
                    g1 = y
                if z > g2:
                    g2 = z
                jj -= 1
        box[lc, 0] = l0
        box[lc, 1] = l1
        box[lc, 2] = l2
        box[lc, 3] = h0
        box[lc, 4] = h1
        box[lc, 5] = h2
        box[rc, 0] = r0
        box[rc, 1] = r1
        box[rc, 2] = r2
        box[rc, 3] = g0
        box[rc, 4] = g1
        box[rc, 5] = g2
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
    return (idx, Qs, start[:n_nodes].copy(), end[:n_nodes].copy(), dim[:n_nodes].copy(),
            split[:n_nodes].copy(), left[:n_nodes].copy(), right[:n_nodes].copy(), depth)


# ----------------------------------------------------------------------------- search


@njit_parallel
def warm_nn_parallel(P, Q, idx, Qs, start, end, dim, split, left, right, depth, d2, prev, out_idx, out_sq):
    """``_kernels_gicp._nn_warm_serial`` with ``prange`` over ``QUERY_TASK_ROWS``-row tasks."""
    n = P.shape[0]
    for c in prange((n + QUERY_TASK_ROWS - 1) // QUERY_TASK_ROWS):
        _nn_warm_rows(P, Q, idx, Qs, start, end, dim, split, left, right, depth, d2, prev, out_idx, out_sq,
                      c * QUERY_TASK_ROWS, min(n, (c + 1) * QUERY_TASK_ROWS))

# ----------------------------------------------------------------------------- matches


@njit
def compact_matches(idx, sq, m):
    """``(corr (k, 2), total)``: the pairs ``(i, idx[i])`` with ``idx[i] < m`` in ascending ``i``
    and the fixed-chunk sum of their ``sq`` (partials of ``CHUNK`` pairs added in chunk order
    from 0.0: the bits of ``registration._kernels.sum_kernel`` on ``sq[i]``)."""
    n = idx.shape[0]
    k = 0
    for i in range(n):
        if idx[i] < m:
            k += 1
    corr = np.empty((k, 2), dtype=np.int64)
    total = 0.0
    part = 0.0
    r = 0
    for i in range(n):
        j = idx[i]
        if j < m:
            corr[r, 0] = i
            corr[r, 1] = j
            part += sq[i]
            r += 1
            if r % CHUNK == 0:
                total = total + part
                part = 0.0
    if r % CHUNK != 0:
        total = total + part
    return corr, total


def _warmup() -> None:
    """Compile the kernels of this module on tiny inputs."""
    Q = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 1]])
    prev = np.array([0, 6, 2, 3, 6, 5], dtype=np.int64)
    warm_nn_parallel(Q, Q, *kd_build_fast(Q, 2), 2.0, prev, np.empty(6, dtype=np.int64), np.empty(6))
    compact_matches(np.array([0, 4, 2], dtype=np.int64), np.array([0.5, np.inf, 0.25]), 4)
