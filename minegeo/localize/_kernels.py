"""Numba kernels of :mod:`minegeo.localize` (contiguous arrays in, no checks).

The correlative search (:mod:`minegeo.localize.correlative`) stores the map's occupied
cells in an open-addressing hash table of int64 cell keys (empty slot = -1, linear probing,
Fibonacci hashing of the key) and scores 4-DOF placements of a levelled scan against it.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange

_BITS = 21
_OFF = 1 << (_BITS - 1)  # cell indices are stored with this offset: |i| < 2^20 cells
_MASK21 = (1 << _BITS) - 1
_GOLD = -7046029254386353131  # 0x9E3779B97F4A7C15 as a signed int64


@njit
def cell_key(ix, iy, iz):
    """Pack three cell indices (each in [-2^20, 2^20)) into one non-negative int64."""
    return ((ix + _OFF) << (2 * _BITS)) | ((iy + _OFF) << _BITS) | (iz + _OFF)


@njit
def _slot(key, shift, mask):
    h = key * np.int64(_GOLD)  # wraps modulo 2^64 (Fibonacci hashing)
    return (h >> shift) & mask


@njit
def hash_insert(table, key, shift, mask):
    """Insert ``key`` (>= 0) into ``table``; returns 1 if it was new, 0 if present."""
    s = _slot(key, shift, mask)
    while True:
        v = table[s]
        if v == key:
            return 0
        if v == -1:
            table[s] = key
            return 1
        s = (s + 1) & mask


@njit
def hash_contains(table, key, shift, mask):
    s = _slot(key, shift, mask)
    while True:
        v = table[s]
        if v == key:
            return True
        if v == -1:
            return False
        s = (s + 1) & mask


@njit
def unique_cells(points, cell):
    """Sorted unique cell index triples ``floor(p / cell)`` of ``points`` as (k, 3) int64."""
    n = points.shape[0]
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        keys[i] = cell_key(np.int64(np.floor(points[i, 0] / cell)), np.int64(np.floor(points[i, 1] / cell)),
                           np.int64(np.floor(points[i, 2] / cell)))
    keys = np.unique(keys)
    out = np.empty((keys.shape[0], 3), dtype=np.int64)
    for i in range(keys.shape[0]):
        k = keys[i]
        out[i, 0] = ((k >> (2 * _BITS)) & _MASK21) - _OFF
        out[i, 1] = ((k >> _BITS) & _MASK21) - _OFF
        out[i, 2] = (k & _MASK21) - _OFF
    return out


@njit
def build_dilated_table(cells, radius, log2_capacity):
    """Hash table of every cell within Chebyshev distance ``radius`` of an occupied cell.

    Returns ``(table, n_keys)``; the caller sizes ``log2_capacity`` so that the load stays
    below 1/2 (``n_keys`` is checked by the caller).
    """
    cap = np.int64(1) << log2_capacity
    mask = cap - 1
    shift = np.int64(64 - log2_capacity)
    table = np.full(cap, -1, dtype=np.int64)
    n = 0
    limit = cap // 2
    for i in range(cells.shape[0]):
        for dx in range(-radius, radius + 1):
            for dy in range(-radius, radius + 1):
                for dz in range(-radius, radius + 1):
                    n += hash_insert(table, cell_key(cells[i, 0] + dx, cells[i, 1] + dy, cells[i, 2] + dz),
                                     shift, mask)
                    if n > limit:
                        return table, n
    return table, n


@njit_parallel
def score_placements(table, log2_capacity, cell, S, anchors, cos_yaw, sin_yaw, max_misses, miss_rate, miss_slack):
    """Hit counts of every (anchor, yaw) placement of the levelled scan sample ``S``.

    Placement ``(a, ψ)`` maps a scan point ``s`` (relative to the scan's reference floor
    point) to ``Rz(ψ) s + a``; a point *hits* when its cell is in the (dilated) map table.
    Counting stops once ``max_misses`` points missed, or earlier once the misses among the
    first ``i + 1`` points exceed ``miss_rate (i + 1) + miss_slack`` (a placement missing
    that often early on is abandoned; its count is then a lower bound that the caller
    discards). Independent per anchor (``prange``),
    so the result does not depend on the thread count.
    """
    na, ny, m = anchors.shape[0], cos_yaw.shape[0], S.shape[0]
    mask = (np.int64(1) << log2_capacity) - 1
    shift = np.int64(64 - log2_capacity)
    out = np.zeros((na, ny), dtype=np.int32)
    for a in prange(na):
        ax, ay, az = anchors[a, 0], anchors[a, 1], anchors[a, 2]
        for k in range(ny):
            c, s = cos_yaw[k], sin_yaw[k]
            hits = 0
            misses = 0
            for i in range(m):
                x = c * S[i, 0] - s * S[i, 1] + ax
                y = s * S[i, 0] + c * S[i, 1] + ay
                z = S[i, 2] + az
                key = cell_key(np.int64(np.floor(x / cell)), np.int64(np.floor(y / cell)),
                               np.int64(np.floor(z / cell)))
                if hash_contains(table, key, shift, mask):
                    hits += 1
                else:
                    misses += 1
                    if misses > max_misses or misses > miss_rate * (i + 1) + miss_slack:
                        break
            out[a, k] = hits
    return out
