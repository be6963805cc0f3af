"""Numba kernels of :mod:`minegeo.geometry` (contiguous float64/int64 arrays in, no checks).

The public wrappers in ``neighbors.py``, ``normals.py``, ``voxel.py`` and ``octree.py``
validate inputs, document the maths and call these kernels. Everything here is
deterministic: parallel loops (``prange``) only run over independent queries, voxels or
leaves, each writing its own output rows, so the thread count never changes a result.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.kernels.eig3 import pca_normal
from minegeo.kernels.hashgrid import lookup as hash_lookup

# ---------------------------------------------------------------------------------------
# stable radix argsort (grid cells, voxels, Morton codes)
# ---------------------------------------------------------------------------------------

_RADIX_BITS = 11
_RADIX_SIZE = 1 << _RADIX_BITS


@njit
def radix_argsort(keys):
    """Stable argsort of non-negative int64 keys: LSD radix sort with 11-bit digits.

    Equal keys keep ascending index order (identical to ``np.argsort(kind="stable")``).
    Passes = ceil(bit length of max key / 11); each pass is a counting sort, O(n).
    """
    n = keys.shape[0]
    idx = np.arange(n, dtype=np.int64)
    if n <= 1:
        return idx
    maxk = keys.max()
    kcur = keys.copy()
    ktmp = np.empty(n, dtype=np.int64)
    itmp = np.empty(n, dtype=np.int64)
    counts = np.empty(_RADIX_SIZE + 1, dtype=np.int64)
    mask = _RADIX_SIZE - 1
    shift = 0
    while shift < 63 and (maxk >> shift) > 0:
        counts[:] = 0
        for i in range(n):
            counts[((kcur[i] >> shift) & mask) + 1] += 1
        for d in range(_RADIX_SIZE):
            counts[d + 1] += counts[d]
        for i in range(n):
            d = (kcur[i] >> shift) & mask
            p = counts[d]
            counts[d] = p + 1
            itmp[p] = idx[i]
            ktmp[p] = kcur[i]
        idx, itmp = itmp, idx
        kcur, ktmp = ktmp, kcur
        shift += _RADIX_BITS
    return idx


# ---------------------------------------------------------------------------------------
# uniform hash grid (neighbour search; the cell table is minegeo.kernels.hashgrid's)
# ---------------------------------------------------------------------------------------

_BLOCK = 256  # queries per parallel work item (buffers are allocated once per block)


@njit
def _spread21(v):
    """Spread the low 21 bits of ``v`` to every third bit (Morton interleave helper)."""
    v = v & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


@njit
def cell_key(ix, iy, iz, nx, ny, morton):
    """Cell key: Morton code (z-order, for memory locality) when every axis has < 2^21 cells,
    else the linear key ``ix + nx*(iy + ny*iz)``."""
    if morton:
        return _spread21(ix) | (_spread21(iy) << 1) | (_spread21(iz) << 2)
    return ix + nx * (iy + ny * iz)


@njit
def grid_cell_keys(points, origin, inv_cell, nx, ny, nz, morton, out_keys):
    """Cell key of ``i = floor((p - origin) * inv_cell)``, clamped into the grid (for queries
    outside it; indexed points are always inside)."""
    n = points.shape[0]
    for i in prange(n):
        ix = min(max(np.int64(np.floor((points[i, 0] - origin[0]) * inv_cell)), 0), nx - 1)
        iy = min(max(np.int64(np.floor((points[i, 1] - origin[1]) * inv_cell)), 0), ny - 1)
        iz = min(max(np.int64(np.floor((points[i, 2] - origin[2]) * inv_cell)), 0), nz - 1)
        out_keys[i] = cell_key(ix, iy, iz, nx, ny, morton)


@njit
def _insert_sorted(buf_pos, buf_sq, count, cap, pos, sq, order):
    """Insert (sq, original index) into the ascending buffer; keep at most ``cap`` entries.

    Ordering is lexicographic on (squared distance, original point index), so ties are
    broken by the lowest index. Returns the new count.
    """
    idx = order[pos]
    if count == cap:
        wsq = buf_sq[cap - 1]
        if sq > wsq or (sq == wsq and idx > order[buf_pos[cap - 1]]):
            return count
        j = cap - 1
    else:
        j = count
        count += 1
    while j > 0:
        psq = buf_sq[j - 1]
        if psq < sq or (psq == sq and order[buf_pos[j - 1]] < idx):
            break
        buf_sq[j] = psq
        buf_pos[j] = buf_pos[j - 1]
        j -= 1
    buf_sq[j] = sq
    buf_pos[j] = pos
    return count


@njit
def _cell_range(qc, r, o, inv_cell, ncell):
    lo = np.int64(np.floor(((qc - r) - o) * inv_cell))
    hi = np.int64(np.floor(((qc + r) - o) * inv_cell))
    if lo < 0:
        lo = 0
    if hi > ncell - 1:
        hi = ncell - 1
    return lo, hi


@njit
def _sq_to(pts, pos, q0, q1, q2):
    """Squared distance of grid point ``pos`` to the query, ``d0*d0 + d1*d1 + d2*d2``."""
    d0 = pts[pos, 0] - q0
    d1 = pts[pos, 1] - q1
    d2 = pts[pos, 2] - q2
    return d0 * d0 + d1 * d1 + d2 * d2


@njit
def _box_sq(qc, lo_edge, cell):
    """Squared distance from coordinate ``qc`` to the interval [lo_edge, lo_edge + cell]."""
    if qc < lo_edge:
        d = lo_edge - qc
        return d * d
    hi_edge = lo_edge + cell
    if qc > hi_edge:
        d = qc - hi_edge
        return d * d
    return 0.0


@njit
def hybrid_one(q0, q1, q2, r, r2, cap, pts, order, cell_start, origin, cell, inv_cell,
               nx, ny, nz, morton, bits, table_keys, table_vals, buf_pos, buf_sq):
    """The <= ``cap`` nearest grid points with squared distance strictly < ``r2``.

    Results go to ``buf_pos`` (positions in the cell-sorted arrays) and ``buf_sq``,
    ascending in (sq, original index). Returns the count. The query's own cell is
    scanned first so the buffer fills with close points early; a cell is skipped when
    its box is farther than r (or, once the buffer is full, than the current worst).
    """
    x0, x1 = _cell_range(q0, r, origin[0], inv_cell, nx)
    y0, y1 = _cell_range(q1, r, origin[1], inv_cell, ny)
    z0, z1 = _cell_range(q2, r, origin[2], inv_cell, nz)
    if x0 > x1 or y0 > y1 or z0 > z1:
        return 0
    cx = np.int64(np.floor((q0 - origin[0]) * inv_cell))
    cy = np.int64(np.floor((q1 - origin[1]) * inv_cell))
    cz = np.int64(np.floor((q2 - origin[2]) * inv_cell))
    count = 0
    slack = 1.0 + 1e-12
    # pass 0: the query's own cell (if inside the grid); pass 1: all other cells
    for pas in range(2):
        for iz in range(z0, z1 + 1):
            dz = _box_sq(q2, origin[2] + iz * cell, cell)
            for iy in range(y0, y1 + 1):
                dy = _box_sq(q1, origin[1] + iy * cell, cell)
                for ix in range(x0, x1 + 1):
                    own = ix == cx and iy == cy and iz == cz
                    if (pas == 0) != own:
                        continue
                    bd = dz + dy + _box_sq(q0, origin[0] + ix * cell, cell)
                    if bd > r2 * slack:
                        continue
                    if count == cap and bd > buf_sq[cap - 1] * slack:
                        continue
                    c = hash_lookup(cell_key(ix, iy, iz, nx, ny, morton), bits, table_keys, table_vals)
                    if c < 0:
                        continue
                    for pos in range(cell_start[c], cell_start[c + 1]):
                        sq = _sq_to(pts, pos, q0, q1, q2)
                        if sq < r2:
                            count = _insert_sorted(buf_pos, buf_sq, count, cap, pos, sq, order)
    return count


@njit
def search_one(q0, q1, q2, knn, r, rmax, cap, pts, order, cell_start, origin, cell, inv_cell,
               nx, ny, nz, morton, bits, table_keys, table_vals, buf_pos, buf_sq):
    """Hybrid search (``knn`` False) or kNN bounded by ``rmax`` (``knn`` True).

    kNN: hybrid searches with radius R = r, 2r, 4r, ... (capped at ``rmax``) until ``cap``
    points are found strictly inside R or R reaches ``rmax``. Every point outside R has
    sq >= R² > the k-th squared distance, so the result is exactly the hybrid search of
    radius ``rmax`` (``rmax`` = inf: the exact k nearest), ties broken by the lowest index.
    With a grid cell near the k-th neighbour distance this visits far fewer points than
    one hybrid search of a radius much larger than that distance.
    """
    if not knn:
        return hybrid_one(q0, q1, q2, r, r * r, cap, pts, order, cell_start, origin, cell, inv_cell,
                          nx, ny, nz, morton, bits, table_keys, table_vals, buf_pos, buf_sq)
    R = min(r, rmax)
    while True:
        cnt = hybrid_one(q0, q1, q2, R, R * R, cap, pts, order, cell_start, origin, cell, inv_cell,
                         nx, ny, nz, morton, bits, table_keys, table_vals, buf_pos, buf_sq)
        if cnt >= cap or R >= rmax:
            return cnt
        R = min(2.0 * R, rmax)


@njit
def _lex_less(sa, pa, sb, pb, order):
    """(sa, order[pa]) < (sb, order[pb]) lexicographically (index looked up only on a tie)."""
    return sa < sb or (sa == sb and order[pa] < order[pb])


@njit
def select_smallest(buf_pos, buf_sq, m, k, order):
    """Reorder ``buf_*[:m]`` so that its first ``k`` entries are the k smallest by (sq, index).

    Hoare quickselect with the middle element as pivot (deterministic); keys are unique
    because indices are. The first k entries are not sorted.
    """
    lo = 0
    hi = m - 1
    target = k - 1
    while lo < hi:
        mid = (lo + hi) >> 1
        ps = buf_sq[mid]
        pp = buf_pos[mid]
        i = lo
        j = hi
        while i <= j:
            while _lex_less(buf_sq[i], buf_pos[i], ps, pp, order):
                i += 1
            while _lex_less(ps, pp, buf_sq[j], buf_pos[j], order):
                j -= 1
            if i <= j:
                ts = buf_sq[i]
                buf_sq[i] = buf_sq[j]
                buf_sq[j] = ts
                tp = buf_pos[i]
                buf_pos[i] = buf_pos[j]
                buf_pos[j] = tp
                i += 1
                j -= 1
        if target <= j:
            hi = j
        elif target >= i:
            lo = i
        else:
            break


@njit
def _radius_walk(q0, q1, q2, r, r2, pts, cell_start, origin, cell, inv_cell,
                 nx, ny, nz, morton, bits, table_keys, table_vals, buf_pos, buf_sq, store):
    """Every grid point with squared distance strictly < ``r2``, cell by cell (z, y, x): counted,
    and with ``store`` also written to ``buf_*`` in visiting order (``-1`` when they overflow)."""
    x0, x1 = _cell_range(q0, r, origin[0], inv_cell, nx)
    y0, y1 = _cell_range(q1, r, origin[1], inv_cell, ny)
    z0, z1 = _cell_range(q2, r, origin[2], inv_cell, nz)
    cap = buf_pos.shape[0]
    count = 0
    slack = 1.0 + 1e-12
    for iz in range(z0, z1 + 1):
        dz = _box_sq(q2, origin[2] + iz * cell, cell)
        for iy in range(y0, y1 + 1):
            dy = _box_sq(q1, origin[1] + iy * cell, cell)
            for ix in range(x0, x1 + 1):
                if dz + dy + _box_sq(q0, origin[0] + ix * cell, cell) > r2 * slack:
                    continue
                c = hash_lookup(cell_key(ix, iy, iz, nx, ny, morton), bits, table_keys, table_vals)
                if c < 0:
                    continue
                for pos in range(cell_start[c], cell_start[c + 1]):
                    sq = _sq_to(pts, pos, q0, q1, q2)
                    if sq < r2:
                        if store:
                            if count == cap:
                                return -1
                            buf_pos[count] = pos
                            buf_sq[count] = sq
                        count += 1
    return count


@njit
def collect_one(q0, q1, q2, r, r2, pts, cell_start, origin, cell, inv_cell,
                nx, ny, nz, morton, bits, table_keys, table_vals, buf_pos, buf_sq):
    """All grid points with sq < r2, unsorted (cell traversal order) into ``buf_*``.

    Returns the count, or -1 when more than ``len(buf_pos)`` points qualify.
    """
    return _radius_walk(q0, q1, q2, r, r2, pts, cell_start, origin, cell, inv_cell, nx, ny, nz, morton, bits,
                        table_keys, table_vals, buf_pos, buf_sq, True)


@njit
def search_set_one(q0, q1, q2, knn, r, rmax, cap, pts, order, cell_start, origin, cell, inv_cell,
                   nx, ny, nz, morton, bits, table_keys, table_vals, big_pos, big_sq, buf_pos, buf_sq):
    """Same neighbour *set* as :func:`search_one`, in unspecified (deterministic) order.

    Collects every point inside the radius unsorted into ``big_*`` and quickselects the
    ``cap`` smallest by (sq, index) when there are more: O(m) instead of the O(m·cap)
    sorted insertion. Falls back to :func:`search_one` (sorted, into ``buf_*``) when the
    big buffer overflows. Returns (count, use_big).
    """
    R = min(r, rmax) if knn else r
    while True:
        m = collect_one(q0, q1, q2, R, R * R, pts, cell_start, origin, cell, inv_cell, nx, ny, nz,
                        morton, bits, table_keys, table_vals, big_pos, big_sq)
        if m < 0:
            cnt = search_one(q0, q1, q2, knn, R, rmax, cap, pts, order, cell_start, origin, cell, inv_cell,
                             nx, ny, nz, morton, bits, table_keys, table_vals, buf_pos, buf_sq)
            return cnt, False
        if m > cap:
            select_smallest(big_pos, big_sq, m, cap, order)
            return cap, True
        if not knn or m == cap or R >= rmax:
            return m, True
        R = min(2.0 * R, rmax)


@njit
def count_one(q0, q1, q2, r, r2, pts, cell_start, origin, cell, inv_cell,
              nx, ny, nz, morton, bits, table_keys, table_vals):
    """Number of grid points with squared distance strictly < ``r2`` (radius search size)."""
    return _radius_walk(q0, q1, q2, r, r2, pts, cell_start, origin, cell, inv_cell, nx, ny, nz, morton, bits,
                        table_keys, table_vals, np.empty(0, np.int64), np.empty(0), False)


@njit_parallel
def grid_radius_count(queries, qorder, r, pts, cell_start, origin, cell, inv_cell, nx, ny, nz,
                      morton, bits, table_keys, table_vals, out_counts):
    """Radius-search sizes; queries visited in ``qorder`` (grid order, for cache locality)."""
    r2 = r * r
    nq = queries.shape[0]
    nblocks = (nq + _BLOCK - 1) // _BLOCK
    for b in prange(nblocks):
        for t in range(b * _BLOCK, min(nq, (b + 1) * _BLOCK)):
            i = qorder[t]
            out_counts[i] = count_one(queries[i, 0], queries[i, 1], queries[i, 2], r, r2, pts,
                                      cell_start, origin, cell, inv_cell, nx, ny, nz, morton, bits,
                                      table_keys, table_vals)


#: Caps from which :func:`grid_hybrid` selects instead of inserting in sorted order.
_SELECT_MIN_CAP = 48


@njit
def _sort_by_sq_index(src_pos, src_sq, m, order, dst_pos, dst_sq):
    """Write ``src_*[:m]`` into ``dst_*[:m]`` sorted by (squared distance, original index).

    Stable sort by squared distance of the entries pre-sorted by index: ties go to the
    lowest index, as in :func:`hybrid_one`'s sorted insertion.
    """
    ids = np.empty(m, dtype=np.int64)
    for j in range(m):
        ids[j] = order[src_pos[j]]
    by_id = np.argsort(ids, kind="mergesort")
    sqs = np.empty(m, dtype=np.float64)
    for j in range(m):
        sqs[j] = src_sq[by_id[j]]
    by_sq = np.argsort(sqs, kind="mergesort")
    for j in range(m):
        k = by_id[by_sq[j]]
        dst_pos[j] = src_pos[k]
        dst_sq[j] = src_sq[k]


@njit_parallel
def grid_hybrid(queries, qorder, knn, r, rmax, cap, pts, order, cell_start, origin, cell, inv_cell, nx, ny, nz,
                morton, bits, table_keys, table_vals, out_idx, out_sq, out_counts):
    """Hybrid search for every query: rows of ``out_idx``/``out_sq`` padded with -1/inf.

    Queries are visited in ``qorder`` (sorted by grid cell, so consecutive queries touch
    the same memory); each writes only its own output row.
    """
    nq = queries.shape[0]
    nblocks = (nq + _BLOCK - 1) // _BLOCK
    use_select = cap >= _SELECT_MIN_CAP
    big = 16 * cap if use_select else 1
    for b in prange(nblocks):
        buf_pos = np.empty(max(cap, 1), dtype=np.int64)
        buf_sq = np.empty(max(cap, 1), dtype=np.float64)
        big_pos = np.empty(big, dtype=np.int64)
        big_sq = np.empty(big, dtype=np.float64)
        for t in range(b * _BLOCK, min(nq, (b + 1) * _BLOCK)):
            i = qorder[t]
            cnt = 0
            if cap > 0 and use_select:
                # large caps: collect + quickselect + one sort (O(m + cap log cap)) instead of
                # the O(m * cap) sorted insertion; identical rows (same set, same order)
                cnt, use_big = search_set_one(queries[i, 0], queries[i, 1], queries[i, 2], knn, r, rmax, cap,
                                              pts, order, cell_start, origin, cell, inv_cell, nx, ny, nz,
                                              morton, bits, table_keys, table_vals, big_pos, big_sq, buf_pos,
                                              buf_sq)
                if use_big:
                    _sort_by_sq_index(big_pos, big_sq, cnt, order, buf_pos, buf_sq)
            elif cap > 0:
                cnt = search_one(queries[i, 0], queries[i, 1], queries[i, 2], knn, r, rmax, cap, pts,
                                 order, cell_start, origin, cell, inv_cell, nx, ny, nz, morton, bits,
                                 table_keys, table_vals, buf_pos, buf_sq)
            for j in range(cnt):
                out_idx[i, j] = order[buf_pos[j]]
                out_sq[i, j] = buf_sq[j]
            for j in range(cnt, out_idx.shape[1]):
                out_idx[i, j] = -1
                out_sq[i, j] = np.inf
            out_counts[i] = cnt


# ---------------------------------------------------------------------------------------
# normals (PCA of a neighbourhood, [Baek2022 Eq. 2]: minegeo.kernels.eig3.pca_normal)
# ---------------------------------------------------------------------------------------


@njit_parallel
def normals_hybrid_fused(knn, r, rmax, cap, mode_open3d, degenerate_ratio, pts, order, cell_start,
                         origin, cell, inv_cell, nx, ny, nz, morton, bits, table_keys, table_vals,
                         out_n, out_eval, out_status, out_counts):
    """Neighbour search + PCA for every indexed point without materialising the neighbourhoods.

    Points are visited in grid order (``pts`` is the cell-sorted copy, ``order`` maps its
    rows back to input rows), so neighbouring queries share cache lines. Mode "open3d"
    sums neighbours sorted by (distance, index) like Open3D; mode "accurate" uses the same
    neighbour set in collection order (:func:`search_set_one`), which skips the sort.
    """
    n = pts.shape[0]
    nblocks = (n + _BLOCK - 1) // _BLOCK
    big = max(4 * cap, 128)
    for b in prange(nblocks):
        buf_pos = np.empty(cap, dtype=np.int64)
        buf_sq = np.empty(cap, dtype=np.float64)
        big_pos = np.empty(big, dtype=np.int64)
        big_sq = np.empty(big, dtype=np.float64)
        A = np.empty((3, 3))
        V = np.empty((3, 3))
        w = np.empty(3)
        tmp = np.empty(6)
        for t in range(b * _BLOCK, min(n, (b + 1) * _BLOCK)):
            i = order[t]
            if mode_open3d:
                cnt = search_one(pts[t, 0], pts[t, 1], pts[t, 2], knn, r, rmax, cap, pts, order,
                                 cell_start, origin, cell, inv_cell, nx, ny, nz, morton, bits,
                                 table_keys, table_vals, buf_pos, buf_sq)
                pca_normal(pts, buf_pos, cnt, t, i, mode_open3d, degenerate_ratio, A, V,
                                       w, tmp, out_n, out_eval, out_status)
            else:
                cnt, use_big = search_set_one(pts[t, 0], pts[t, 1], pts[t, 2], knn, r, rmax, cap, pts, order,
                                              cell_start, origin, cell, inv_cell, nx, ny, nz, morton,
                                              bits, table_keys, table_vals, big_pos, big_sq, buf_pos,
                                              buf_sq)
                pca_normal(pts, big_pos if use_big else buf_pos, cnt, t, i, mode_open3d,
                                       degenerate_ratio, A, V, w, tmp, out_n, out_eval, out_status)
            out_counts[i] = cnt


@njit_parallel
def normals_from_neighborhoods(points, row0, idx, counts, mode_open3d, degenerate_ratio,
                               out_n, out_eval, out_status):
    """PCA normals of points ``row0 .. row0+len(idx)-1`` from padded neighbourhood rows."""
    nq = idx.shape[0]
    nblocks = (nq + _BLOCK - 1) // _BLOCK
    for b in prange(nblocks):
        A = np.empty((3, 3))
        V = np.empty((3, 3))
        w = np.empty(3)
        tmp = np.empty(6)
        for i in range(b * _BLOCK, min(nq, (b + 1) * _BLOCK)):
            pca_normal(points, idx[i], counts[i], row0 + i, row0 + i, mode_open3d,
                                   degenerate_ratio, A, V, w, tmp, out_n, out_eval, out_status)


@njit
def orient_normals(points, normals, targets, target_index, skip):
    """Flip n_i when n_i . (s_k - p_i) < 0 with s_k = targets[target_index[i]]; skip[i] leaves it."""
    n = points.shape[0]
    for i in prange(n):
        if skip[i]:
            continue
        t = target_index[i]
        d = (normals[i, 0] * (targets[t, 0] - points[i, 0])
             + normals[i, 1] * (targets[t, 1] - points[i, 1])
             + normals[i, 2] * (targets[t, 2] - points[i, 2]))
        if d < 0.0:
            normals[i, 0] = -normals[i, 0]
            normals[i, 1] = -normals[i, 1]
            normals[i, 2] = -normals[i, 2]
        elif d == 0.0:
            # perpendicular to the line of sight: make the largest-magnitude component positive
            a0 = abs(normals[i, 0])
            a1 = abs(normals[i, 1])
            a2 = abs(normals[i, 2])
            k = 0
            if a1 > a0:
                k = 1
                a0 = a1
            if a2 > a0:
                k = 2
            if normals[i, k] < 0.0:
                normals[i, 0] = -normals[i, 0]
                normals[i, 1] = -normals[i, 1]
                normals[i, 2] = -normals[i, 2]


# ---------------------------------------------------------------------------------------
# voxel downsampling (Open3D VoxelDownSample semantics)
# ---------------------------------------------------------------------------------------


@njit_parallel
def voxel_keys(points, origin, voxel, out_keys):
    """Integer voxel coordinates ``floor((p - origin) / voxel)`` (Open3D's formula)."""
    for i in prange(points.shape[0]):
        for a in range(3):
            out_keys[i, a] = np.int64(np.floor((points[i, a] - origin[a]) / voxel))


@njit
def bounds3(points):
    """(min (3,), max (3,)) of an (n, 3) array in one pass (exact, order-independent)."""
    lo = points[0].copy()
    hi = points[0].copy()
    for i in range(1, points.shape[0]):
        for a in range(3):
            v = points[i, a]
            if v < lo[a]:
                lo[a] = v
            if v > hi[a]:
                hi[a] = v
    return lo, hi


@njit
def voxel_linear_keys(points, origin, voxel, d1, d2, out_keys):
    """Linear voxel key ``(kx*d1 + ky)*d2 + kz`` with ``k = floor((p - origin) / voxel)``."""
    for i in prange(points.shape[0]):
        kx = np.int64(np.floor((points[i, 0] - origin[0]) / voxel))
        ky = np.int64(np.floor((points[i, 1] - origin[1]) / voxel))
        kz = np.int64(np.floor((points[i, 2] - origin[2]) / voxel))
        out_keys[i] = (kx * d1 + ky) * d2 + kz


@njit
def group_starts(keys, order):
    """Start offsets (m+1,) of the runs of equal ``keys[order]`` (order sorts the keys)."""
    n = order.shape[0]
    m = 1
    for j in range(1, n):
        if keys[order[j]] != keys[order[j - 1]]:
            m += 1
    starts = np.empty(m + 1, dtype=np.int64)
    starts[0] = 0
    g = 1
    for j in range(1, n):
        if keys[order[j]] != keys[order[j - 1]]:
            starts[g] = j
            g += 1
    starts[m] = n
    return starts


@njit
def group_members(order, starts, out_group):
    """``out_group[order[j]] = g`` for every j in group g."""
    for g in prange(starts.shape[0] - 1):
        for j in range(starts[g], starts[g + 1]):
            out_group[order[j]] = g


@njit
def voxel_reduce(points, normals, has_normals, order, starts, out_points, out_normals):
    """Per-voxel mean in input order; normals summed skipping NaN rows and divided by the count."""
    nv = starts.shape[0] - 1
    for v in prange(nv):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        t0 = 0.0
        t1 = 0.0
        t2 = 0.0
        for j in range(starts[v], starts[v + 1]):
            i = order[j]
            s0 += points[i, 0]
            s1 += points[i, 1]
            s2 += points[i, 2]
            if has_normals:
                a = normals[i, 0]
                b = normals[i, 1]
                c = normals[i, 2]
                if not (np.isnan(a) or np.isnan(b) or np.isnan(c)):
                    t0 += a
                    t1 += b
                    t2 += c
        cnt = float(starts[v + 1] - starts[v])
        out_points[v, 0] = s0 / cnt
        out_points[v, 1] = s1 / cnt
        out_points[v, 2] = s2 / cnt
        if has_normals:
            out_normals[v, 0] = t0 / cnt
            out_normals[v, 1] = t1 / cnt
            out_normals[v, 2] = t2 / cnt


@njit_parallel
def voxel_reduce_columns(values, order, starts, out):
    """Per-voxel mean of the columns of ``values`` (n, k), summed in input order."""
    nv = starts.shape[0] - 1
    k = values.shape[1]
    for v in prange(nv):
        cnt = float(starts[v + 1] - starts[v])
        for c in range(k):
            s = 0.0
            for j in range(starts[v], starts[v + 1]):
                s += values[order[j], c]
            out[v, c] = s / cnt


# ---------------------------------------------------------------------------------------
# linear octree (Morton codes)
# ---------------------------------------------------------------------------------------


@njit(inline="always")
def octree_descend(x, y, z, origin, size, depth):
    """Morton code of the leaf of ``(x, y, z)`` (inside the cube), by Open3D's midpoint descent:
    child ``ix + 2 iy + 4 iz`` with ``i = 1`` when the coordinate is >= ``o + s/2``, child
    origin ``o + i s/2``. Shared by :func:`octree_codes` and the streamed octree
    (:func:`minegeo.geometry._kernels_stream.octree_accumulate`)."""
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    s = size
    code = np.int64(0)
    for _lvl in range(depth):
        h = s / 2.0
        bx = 0 if x < ox + h else 1
        by = 0 if y < oy + h else 1
        bz = 0 if z < oz + h else 1
        code = (code << 3) | (bx + 2 * by + 4 * bz)
        ox = ox + bx * h
        oy = oy + by * h
        oz = oz + bz * h
        s = h
    return code


@njit_parallel
def octree_codes(points, origin, size, depth, out_codes, out_inside):
    """Morton code of the leaf containing each point, descending like Open3D's Octree.

    At each level the child index is ``ix + 2 iy + 4 iz`` with ``i = 1`` when the
    coordinate is >= the cell midpoint ``o + s/2`` (Open3D ``OctreeInternalNode``);
    the child origin is ``o + i * s/2``. Points outside [origin, origin + size) get
    ``out_inside = False`` and code -1.
    """
    for i in prange(points.shape[0]):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        inside = True
        for a in range(3):
            c = points[i, a]
            if not (c >= origin[a] and c < origin[a] + size):
                inside = False
        if not inside:
            out_codes[i] = -1
            out_inside[i] = False
            continue
        out_codes[i] = octree_descend(x, y, z, origin, size, depth)
        out_inside[i] = True


@njit
def morton_decode(code, level):
    """Integer cell coordinates (ix, iy, iz) of a node code at ``level``."""
    ix = np.int64(0)
    iy = np.int64(0)
    iz = np.int64(0)
    for b in range(level):
        c = (code >> (3 * b)) & 7
        ix |= (c & 1) << b
        iy |= ((c >> 1) & 1) << b
        iz |= ((c >> 2) & 1) << b
    return ix, iy, iz


@njit_parallel
def octree_nearest_to_centre(points, order, starts, codes, level, origin, size, out_index):
    """For every occupied node (range ``starts[k]:starts[k+1]`` of ``order``) the point closest
    to the node centre; ties keep the lowest original index."""
    nn = starts.shape[0] - 1
    cs = size / float(np.int64(1) << level)
    for k in prange(nn):
        ix, iy, iz = morton_decode(codes[k], level)
        c0 = origin[0] + (ix + 0.5) * cs
        c1 = origin[1] + (iy + 0.5) * cs
        c2 = origin[2] + (iz + 0.5) * cs
        best = -1
        bsq = np.inf
        for j in range(starts[k], starts[k + 1]):
            i = order[j]
            d0 = points[i, 0] - c0
            d1 = points[i, 1] - c1
            d2 = points[i, 2] - c2
            sq = d0 * d0 + d1 * d1 + d2 * d2
            if sq < bsq or (sq == bsq and i < best):
                bsq = sq
                best = i
        out_index[k] = best


@njit
def octree_region_query(points, order, node_codes, node_pstart, node_pend, node_cstart, node_cend,
                        level_off, depth, origin, size, is_sphere, c0, c1, c2, r2, b_lo, b_hi, out):
    """Indices of points inside a sphere (sq < r2, strict) or an axis-aligned box (closed).

    Depth-first traversal from the root over the flattened linear octree (global node ids;
    ``level_off[l]`` is the first node of level l; a node's points are
    ``order[node_pstart:node_pend]`` and its children the nodes ``node_cstart:node_cend``).
    A node is pruned when its cube does not meet the region (with a 1e-12 relative slack,
    so rounding never prunes a node that holds an answer); every candidate point is then
    tested exactly. Returns the count written to ``out``.
    """
    count = 0
    stack_level = np.empty(8 * depth + 8, dtype=np.int64)
    stack_node = np.empty(8 * depth + 8, dtype=np.int64)
    stack_level[0] = 0
    stack_node[0] = level_off[0]
    top = 1
    slack = 1e-12 * size
    while top > 0:
        top -= 1
        lvl = stack_level[top]
        node = stack_node[top]
        cs = size / float(np.int64(1) << lvl)
        ix, iy, iz = morton_decode(node_codes[node], lvl)
        lo0 = origin[0] + ix * cs - slack
        lo1 = origin[1] + iy * cs - slack
        lo2 = origin[2] + iz * cs - slack
        hi0 = lo0 + cs + 2 * slack
        hi1 = lo1 + cs + 2 * slack
        hi2 = lo2 + cs + 2 * slack
        if is_sphere:
            d = 0.0
            if c0 < lo0:
                d += (lo0 - c0) ** 2
            elif c0 > hi0:
                d += (c0 - hi0) ** 2
            if c1 < lo1:
                d += (lo1 - c1) ** 2
            elif c1 > hi1:
                d += (c1 - hi1) ** 2
            if c2 < lo2:
                d += (lo2 - c2) ** 2
            elif c2 > hi2:
                d += (c2 - hi2) ** 2
            if d >= r2:
                continue
        elif (hi0 < b_lo[0] or lo0 > b_hi[0] or hi1 < b_lo[1] or lo1 > b_hi[1]
              or hi2 < b_lo[2] or lo2 > b_hi[2]):
            continue
        if lvl == depth:
            for j in range(node_pstart[node], node_pend[node]):
                i = order[j]
                if is_sphere:
                    d0 = points[i, 0] - c0
                    d1 = points[i, 1] - c1
                    d2 = points[i, 2] - c2
                    ok = d0 * d0 + d1 * d1 + d2 * d2 < r2
                else:
                    ok = (points[i, 0] >= b_lo[0] and points[i, 0] <= b_hi[0]
                          and points[i, 1] >= b_lo[1] and points[i, 1] <= b_hi[1]
                          and points[i, 2] >= b_lo[2] and points[i, 2] <= b_hi[2])
                if ok:
                    out[count] = i
                    count += 1
        else:
            for c in range(node_cend[node] - 1, node_cstart[node] - 1, -1):
                stack_level[top] = lvl + 1
                stack_node[top] = c
                top += 1
    return count
