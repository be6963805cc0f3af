"""Numba kernels of the chunked (streaming) downsampling in :mod:`minegeo.geometry.stream`.

Open-addressing hash tables (linear probing, ``2^bits`` slots, key ``-1`` = empty, home slot
:func:`minegeo.kernels.hashgrid.hash_slot`) keyed by the voxel key or the octree leaf code.
The kernels are serial: points are visited in input order, so every per-cell sum is formed
in exactly the order of :func:`minegeo.geometry._kernels.voxel_reduce` (ascending input index)
and the octree keeps the first of equally close points (lowest index), as
:func:`minegeo.geometry._kernels.octree_nearest_to_centre` does. Contiguous arrays in, no checks.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit
from minegeo.geometry._kernels import morton_decode, octree_descend
from minegeo.kernels.hashgrid import hash_slot


@njit
def _slot(key, keys, bits):
    """Slot of ``key``: its own, or the empty slot where it goes (the table is never full)."""
    mask = keys.shape[0] - 1
    h = hash_slot(key, bits)
    while True:
        k = keys[h]
        if k == key or k == -1:
            return h
        h = (h + 1) & mask


@njit(inline="always")
def _claim(key, keys, bits, n_used, max_used):
    """``(slot of key, n_used)``: its slot, claimed (``n_used + 1``) when the key is new; ``-1`` when it
    is new and ``n_used`` has reached ``max_used`` (the caller grows the table)."""
    h = _slot(key, keys, bits)
    if keys[h] == -1:
        if n_used >= max_used:
            return -1, n_used
        keys[h] = key
        n_used += 1
    return h, n_used


@njit
def voxel_accumulate(points, origin, voxel, d1, d2, keys, bits, sums, counts, n_used, max_used):
    """Add the points, in order, to their voxels' sums and counts.

    Voxel key ``(kx*d1 + ky)*d2 + kz`` with ``k = floor((p - origin) / voxel)`` (the arithmetic
    of :func:`minegeo.geometry._kernels.voxel_linear_keys`). Stops before a point that would
    make ``n_used`` exceed ``max_used`` (the caller grows the table and goes on).

    Returns
    -------
    (n_used, next_point)
    """
    n = points.shape[0]
    for i in range(n):
        kx = np.int64(np.floor((points[i, 0] - origin[0]) / voxel))
        ky = np.int64(np.floor((points[i, 1] - origin[1]) / voxel))
        kz = np.int64(np.floor((points[i, 2] - origin[2]) / voxel))
        key = (kx * d1 + ky) * d2 + kz
        h, n_used = _claim(key, keys, bits, n_used, max_used)
        if h < 0:
            return n_used, i
        sums[h, 0] += points[i, 0]
        sums[h, 1] += points[i, 1]
        sums[h, 2] += points[i, 2]
        counts[h] += 1
    return n_used, n


@njit
def voxel_rehash(keys, sums, counts, new_keys, new_bits, new_sums, new_counts):
    """Move every used slot into the (empty) larger table."""
    for s in range(keys.shape[0]):
        if keys[s] != -1:
            h = _slot(keys[s], new_keys, new_bits)
            new_keys[h] = keys[s]
            new_sums[h, 0] = sums[s, 0]
            new_sums[h, 1] = sums[s, 1]
            new_sums[h, 2] = sums[s, 2]
            new_counts[h] = counts[s]


@njit
def octree_accumulate(points, first_index, origin, size, depth, keys, bits, best_sq, best_idx, best_pts, counts,
                      n_used, max_used):
    """Keep, per occupied leaf, the point closest to the leaf centre (ties: the earlier point).

    The leaf code is found by the midpoint descent of :func:`minegeo.geometry._kernels.octree_codes`
    and the squared distance computed as in :func:`~minegeo.geometry._kernels.octree_nearest_to_centre`.
    ``first_index`` is the global index of ``points[0]``. A point outside the cube stops the
    kernel with ``next_point = -1 - i``.

    Returns
    -------
    (n_used, next_point)
    """
    n = points.shape[0]
    cs = size / float(np.int64(1) << depth)
    for i in range(n):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        for a in range(3):
            c = points[i, a]
            if not (c >= origin[a] and c < origin[a] + size):
                return n_used, -1 - i
        code = octree_descend(x, y, z, origin, size, depth)
        ix, iy, iz = morton_decode(code, depth)
        c0 = origin[0] + (ix + 0.5) * cs
        c1 = origin[1] + (iy + 0.5) * cs
        c2 = origin[2] + (iz + 0.5) * cs
        d0 = x - c0
        d1 = y - c1
        d2 = z - c2
        sq = d0 * d0 + d1 * d1 + d2 * d2
        n_before = n_used
        h, n_used = _claim(code, keys, bits, n_used, max_used)
        if h < 0:
            return n_used, i
        if n_used != n_before:  # a new leaf
            best_sq[h] = np.inf
        counts[h] += 1
        if sq < best_sq[h]:
            best_sq[h] = sq
            best_idx[h] = first_index + i
            best_pts[h, 0] = x
            best_pts[h, 1] = y
            best_pts[h, 2] = z
    return n_used, n


@njit
def octree_rehash(keys, best_sq, best_idx, best_pts, counts, new_keys, new_bits, new_sq, new_idx, new_pts, new_counts):
    """Move every used slot into the (empty) larger table."""
    for s in range(keys.shape[0]):
        if keys[s] != -1:
            h = _slot(keys[s], new_keys, new_bits)
            new_keys[h] = keys[s]
            new_sq[h] = best_sq[s]
            new_idx[h] = best_idx[s]
            new_pts[h, 0] = best_pts[s, 0]
            new_pts[h, 1] = best_pts[s, 1]
            new_pts[h, 2] = best_pts[s, 2]
            new_counts[h] = counts[s]
