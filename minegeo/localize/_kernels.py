"""Numba kernels of :mod:`minegeo.localize` (contiguous arrays in, no checks).

The correlative search (:mod:`minegeo.localize.correlative`) stores the map's occupied
cells as a *blocked bitmap*: the cells are grouped in blocks of 8 x 8 x 8; a block holds two
512-bit masks (eight uint64 words each: word ``x mod 8``, bit ``8 (y mod 8) + (z mod 8)``),
the dilated occupancy (words 0-7) and the undilated one (words 8-15), and the blocks are
found through an open-addressing hash table of int64 block keys (empty slot = -1, linear
probing, Fibonacci hashing of the key; the bit rows share the slot index) or, when the
map's bounding box is small enough, through a dense int32 directory of slots indexed by the
block's coordinates (:func:`dense_block_table`: one load instead of a probe). Compared with one
hash entry per dilated cell this is ~15 times smaller (a few MB for a 750 m mine at 0.5 m
cells), so the scoring of millions of placements stays in cache. Membership is exactly the
same set as the naive one (``tests/reference/naive_correlative.py``).
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.kernels.hashgrid import find_slot
from minegeo.kernels.kdtree import kd_nn_rows

_BITS = 21
_OFF = 1 << (_BITS - 1)  # cell indices are stored with this offset: |i| < 2^20 cells
_MASK21 = (1 << _BITS) - 1


@njit
def cell_key(ix, iy, iz):
    """Pack three cell indices (each in [-2^20, 2^20)) into one non-negative int64."""
    return ((ix + _OFF) << (2 * _BITS)) | ((iy + _OFF) << _BITS) | (iz + _OFF)


@njit
def block_slot(block_keys, key, log2_blocks):
    """Slot of block ``key`` in the table, or of the empty slot where it would go."""
    return find_slot(block_keys, key, log2_blocks)


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
def build_blocked_occupancy(cells, radius, log2_blocks):
    """Blocked bitmap of the cells within Chebyshev distance ``radius`` of an occupied cell.

    ``cells`` are the occupied cell index triples (:func:`unique_cells`). Returns
    ``(block_keys, bits, n_blocks)``: ``block_keys`` (2^log2_blocks,) int64 (-1 = empty),
    ``bits`` (2^log2_blocks, 16) uint64, dilated mask in words 0-7, undilated in words 8-15.
    Stops early once ``n_blocks`` exceeds half the capacity (the caller then retries larger).
    """
    cap = np.int64(1) << log2_blocks
    block_keys = np.full(cap, -1, dtype=np.int64)
    bits = np.zeros((cap, 16), dtype=np.uint64)
    nb = 0
    one = np.uint64(1)
    for i in range(cells.shape[0]):
        for dx in range(-radius, radius + 1):
            for dy in range(-radius, radius + 1):
                for dz in range(-radius, radius + 1):
                    ix = cells[i, 0] + dx
                    iy = cells[i, 1] + dy
                    iz = cells[i, 2] + dz
                    key = cell_key(ix >> 3, iy >> 3, iz >> 3)  # arithmetic shift: floor(i / 8)
                    s = block_slot(block_keys, key, log2_blocks)
                    if block_keys[s] == -1:
                        block_keys[s] = key
                        nb += 1
                        if nb > cap // 2:
                            return block_keys, bits, nb
                    w = ix & 7
                    b = np.uint64(((iy & 7) << 3) | (iz & 7))
                    bits[s, w] |= one << b
                    if dx == 0 and dy == 0 and dz == 0:
                        bits[s, 8 + w] |= one << b
    return block_keys, bits, nb


@njit
def occupancy_state(block_keys, bits, log2_blocks, ix, iy, iz):
    """0 = free, 1 = in the dilated occupancy only, 2 = occupied (undilated) cell."""
    s = block_slot(block_keys, cell_key(ix >> 3, iy >> 3, iz >> 3), log2_blocks)
    if block_keys[s] == -1:
        return 0
    w = ix & 7
    b = np.uint64(((iy & 7) << 3) | (iz & 7))
    if not (bits[s, w] >> b) & np.uint64(1):
        return 0
    return 2 if (bits[s, 8 + w] >> b) & np.uint64(1) else 1


@njit
def dense_block_table(block_keys, max_entries):
    """Dense directory of the blocked bitmap: ``(table, lo)`` with ``table[bx - lo0, by - lo1,
    bz - lo2]`` the hash slot of block ``(bx, by, bz)`` or an empty slot (zero bits) when the
    block is not stored, ``lo`` the smallest block index on each axis. An empty (0, 0, 0)
    table when the blocks' bounding box holds more than ``max_entries`` blocks (the scoring
    then probes the hash table)."""
    m21 = np.int64(_MASK21)
    lo = np.full(3, np.int64(1) << 40)
    hi = np.full(3, -(np.int64(1) << 40))
    empty = np.int64(-1)
    for s in range(block_keys.shape[0]):
        key = block_keys[s]
        if key == -1:
            if empty < 0:
                empty = s
            continue
        c0 = ((key >> (2 * _BITS)) & m21) - _OFF
        c1 = ((key >> _BITS) & m21) - _OFF
        c2 = (key & m21) - _OFF
        lo[0] = min(lo[0], c0)
        lo[1] = min(lo[1], c1)
        lo[2] = min(lo[2], c2)
        hi[0] = max(hi[0], c0)
        hi[1] = max(hi[1], c1)
        hi[2] = max(hi[2], c2)
    if hi[0] < lo[0]:
        return np.full((1, 1, 1), np.int32(empty)), np.zeros(3, dtype=np.int64)
    if (hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1) > max_entries:
        return np.zeros((0, 0, 0), dtype=np.int32), lo
    table = np.full((hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1), np.int32(empty))
    for s in range(block_keys.shape[0]):
        key = block_keys[s]
        if key != -1:
            table[((key >> (2 * _BITS)) & m21) - _OFF - lo[0], ((key >> _BITS) & m21) - _OFF - lo[1],
                  (key & m21) - _OFF - lo[2]] = np.int32(s)
    return table, lo


@njit_parallel
def score_placements(block_keys, bits, log2_blocks, table, table_lo, RX, RY, SZ, anchors, max_misses, miss_rate,
                     miss_slack):
    """Hit counts of every (anchor, yaw) placement of the levelled scan sample.

    Everything is in cell units (metres / cell size): ``RX[k, i], RY[k, i]`` are the x, y of
    sample point ``s_i`` (relative to the scan's reference floor point) rotated by the k-th
    heading ``ψ_k``, ``SZ[i]`` its z, ``anchors[a]`` the a-th anchor, so placement ``(a, ψ_k)``
    puts the point in cell ``floor(Rz(ψ_k) s_i + a)``. A point *hits* when that cell is in the
    dilated occupancy of the blocked bitmap (:func:`build_blocked_occupancy`). Counting stops
    once ``max_misses`` points missed, or earlier once the misses among the first ``i + 1``
    points exceed ``miss_rate (i + 1) + miss_slack`` (a placement missing that often early on
    is abandoned; its count is then a lower bound that the caller discards). Returns
    ``(hits, tight_hits)``: a hit also counts as *tight* when its cell is occupied before
    dilation, which ranks placements that all hit everything. Independent per anchor
    (``prange``), so the result does not depend on the thread count.

    ``table`` (nx, ny, nz) int32, when not empty, is the dense block directory of
    :func:`dense_block_table` (``table_lo``: block index of its first entry): a block's slot
    is then read directly instead of probing the hash table (same counts, ~20 % faster).
    Branch-free count: an empty slot's bit rows are zero, so a missing block is a miss.
    """
    na, ny, m = anchors.shape[0], RX.shape[0], RX.shape[1]
    one = np.uint64(1)
    out = np.zeros((na, ny), dtype=np.int32)
    out_t = np.zeros((na, ny), dtype=np.int32)
    dense = table.size > 0
    d0, d1, d2 = table.shape[0], table.shape[1], table.shape[2]
    l0, l1, l2 = table_lo[0], table_lo[1], table_lo[2]
    empty = np.int64(0)  # an empty slot of the hash table (its bit rows are zero)
    while block_keys[empty] != -1:
        empty += 1
    for a in prange(na):
        ax, ay, az = anchors[a, 0], anchors[a, 1], anchors[a, 2]
        for k in range(ny):
            hits = 0
            thits = 0
            misses = 0
            for i in range(m):
                ix = np.int64(np.floor(RX[k, i] + ax))
                iy = np.int64(np.floor(RY[k, i] + ay))
                iz = np.int64(np.floor(SZ[i] + az))
                if dense:
                    bx = (ix >> 3) - l0
                    by = (iy >> 3) - l1
                    bz = (iz >> 3) - l2
                    sl = empty
                    if 0 <= bx < d0 and 0 <= by < d1 and 0 <= bz < d2:
                        sl = np.int64(table[bx, by, bz])
                else:
                    sl = block_slot(block_keys, cell_key(ix >> 3, iy >> 3, iz >> 3), log2_blocks)
                w = ix & 7
                b = np.uint64(((iy & 7) << 3) | (iz & 7))
                hit = np.int64((bits[sl, w] >> b) & one)
                hits += hit
                thits += hit & np.int64((bits[sl, 8 + w] >> b) & one)
                misses += 1 - hit
                if misses > max_misses or misses > miss_rate * (i + 1) + miss_slack:
                    break
            out[a, k] = hits
            out_t[a, k] = thits
    return out, out_t


@njit
def _plane_count(X, oi, nq, Q, Nq, tol):
    """Rows of ``X`` paired (``oi < nq``) with a map point whose tangent plane is within ``tol``."""
    cnt = 0
    for i in range(X.shape[0]):
        j = oi[i]
        if j < nq:
            r = (X[i, 0] - Q[j, 0]) * Nq[j, 0] + (X[i, 1] - Q[j, 1]) * Nq[j, 1] + (X[i, 2] - Q[j, 2]) * Nq[j, 2]
            if abs(r) < tol:
                cnt += 1
    return cnt


@njit
def _gn4_step(X, oi, nq, Q, Nq, T, A, b):
    """One damped Gauss-Newton step of the 4-DOF point-to-plane fit, applied to ``T`` in place.

    Rows ``J = [n_y (x − x̄) − n_x (y − ȳ), n_x, n_y, n_z]``, ``r = n·(x − q)`` over the paired
    rows of ``X`` (``oi < nq``); ``T ← [Rz(δψ) | x̄ − Rz(δψ) x̄ + δt] T``. Nothing is done with
    fewer than 8 pairs.
    """
    m = X.shape[0]
    cx = 0.0
    cy = 0.0
    cz = 0.0
    n_ok = 0
    for i in range(m):
        if oi[i] < nq:
            cx += X[i, 0]
            cy += X[i, 1]
            cz += X[i, 2]
            n_ok += 1
    if n_ok < 8:
        return
    cx /= n_ok
    cy /= n_ok
    cz /= n_ok
    A[:, :] = 0.0
    b[:] = 0.0
    for i in range(m):
        j = oi[i]
        if j < nq:
            nx = Nq[j, 0]
            ny = Nq[j, 1]
            nz = Nq[j, 2]
            r = (X[i, 0] - Q[j, 0]) * nx + (X[i, 1] - Q[j, 1]) * ny + (X[i, 2] - Q[j, 2]) * nz
            j0 = ny * (X[i, 0] - cx) - nx * (X[i, 1] - cy)
            J0, J1, J2, J3 = j0, nx, ny, nz
            A[0, 0] += J0 * J0
            A[0, 1] += J0 * J1
            A[0, 2] += J0 * J2
            A[0, 3] += J0 * J3
            A[1, 1] += J1 * J1
            A[1, 2] += J1 * J2
            A[1, 3] += J1 * J3
            A[2, 2] += J2 * J2
            A[2, 3] += J2 * J3
            A[3, 3] += J3 * J3
            b[0] -= J0 * r
            b[1] -= J1 * r
            b[2] -= J2 * r
            b[3] -= J3 * r
    for p in range(4):
        for q in range(p):
            A[p, q] = A[q, p]
    lam = 1e-6 * (A[0, 0] + A[1, 1] + A[2, 2] + A[3, 3]) / 4.0 + 1e-12
    for p in range(4):
        A[p, p] += lam
    dx = np.linalg.solve(A, b)
    ca = np.cos(dx[0])
    sa = np.sin(dx[0])
    tx = cx - (ca * cx - sa * cy) + dx[1]
    ty = cy - (sa * cx + ca * cy) + dx[2]
    tz = dx[3]
    for k in range(4):  # T <- [Rz | t] T, in place (rows 0-1 rotate, row 2 unchanged)
        a0 = T[0, k]
        a1 = T[1, k]
        T[0, k] = ca * a0 - sa * a1
        T[1, k] = sa * a0 + ca * a1
    T[0, 3] += tx
    T[1, 3] += ty
    T[2, 3] += tz


@njit
def _apply(T, S, X):
    for i in range(S.shape[0]):
        for k in range(3):
            X[i, k] = T[k, 0] * S[i, 0] + T[k, 1] * S[i, 1] + T[k, 2] * S[i, 2] + T[k, 3]


@njit_parallel
def refine_placements_4dof(S, T0s, Q, Nq, tree, gates2, tol, final_gate2, out_T, out_count):
    """4-DOF point-to-plane Gauss-Newton of every candidate placement (``prange`` over candidates).

    For candidate ``c`` and each gate ``g`` in ``gates2`` (squared, m²): pair every sample point
    ``x = R s + t`` with its nearest map point ``q`` (normal ``n``) within ``g`` (the
    registration package's gated KD-tree descent), then solve the damped normal equations of
    ``Σ (n·(Rz(δψ)(x − x̄) + x̄ + δt − q))²`` linearised at 0 (:func:`_gn4_step`). Finally
    counts the sample points whose nearest map point lies within ``final_gate2`` and whose
    plane distance is below ``tol``. Candidates are independent, so results do not depend on
    the thread count.
    """
    nc = T0s.shape[0]
    m = S.shape[0]
    nq = tree.idx.shape[0]
    for c in prange(nc):
        T = T0s[c].copy()
        X = np.empty((m, 3))
        oi = np.empty(m, np.int64)
        osq = np.empty(m)
        A = np.empty((4, 4))
        b = np.empty(4)
        for it in range(gates2.shape[0]):
            _apply(T, S, X)
            kd_nn_rows(X, tree, gates2[it], oi, osq, 0, m)
            _gn4_step(X, oi, nq, Q, Nq, T, A, b)
        _apply(T, S, X)
        kd_nn_rows(X, tree, final_gate2, oi, osq, 0, m)
        out_count[c] = _plane_count(X, oi, nq, Q, Nq, tol)
        for p in range(4):
            for q in range(4):
                out_T[c, p, q] = T[p, q]


@njit
def build_nearest_grid(Q, cell, band, log2_blocks):
    """Nearest-point lookup grid: every cell within Chebyshev distance ``band`` of a cell holding
    a point of ``Q`` stores the index of the point of ``Q`` nearest to the cell's centre (ties:
    the lower index), in 8³-cell blocks found by hashing (as :func:`build_blocked_occupancy`).

    Returns ``(block_keys, nearest (2^log2_blocks, 512) int32, n_blocks)``; ``nearest`` is -1
    for cells of a block that no point reaches. Stops early once ``n_blocks`` exceeds half the
    capacity (the caller retries larger). Serial and in point order: deterministic.
    """
    cap = np.int64(1) << log2_blocks
    block_keys = np.full(cap, -1, dtype=np.int64)
    nearest = np.full((cap, 512), -1, dtype=np.int32)
    nb = 0
    for j in range(Q.shape[0]):
        qx, qy, qz = Q[j, 0], Q[j, 1], Q[j, 2]
        cx = np.int64(np.floor(qx / cell))
        cy = np.int64(np.floor(qy / cell))
        cz = np.int64(np.floor(qz / cell))
        for dx in range(-band, band + 1):
            ix = cx + dx
            ex = (ix + 0.5) * cell - qx
            for dy in range(-band, band + 1):
                iy = cy + dy
                ey = (iy + 0.5) * cell - qy
                for dz in range(-band, band + 1):
                    iz = cz + dz
                    ez = (iz + 0.5) * cell - qz
                    key = cell_key(ix >> 3, iy >> 3, iz >> 3)
                    s = block_slot(block_keys, key, log2_blocks)
                    if block_keys[s] == -1:
                        block_keys[s] = key
                        nb += 1
                        if nb > cap // 2:
                            return block_keys, nearest, nb
                    loc = ((ix & 7) << 6) | ((iy & 7) << 3) | (iz & 7)
                    k = nearest[s, loc]
                    if k < 0:
                        nearest[s, loc] = j
                    else:
                        fx = (ix + 0.5) * cell - Q[k, 0]
                        fy = (iy + 0.5) * cell - Q[k, 1]
                        fz = (iz + 0.5) * cell - Q[k, 2]
                        if ex * ex + ey * ey + ez * ez < fx * fx + fy * fy + fz * fz:
                            nearest[s, loc] = j
    return block_keys, nearest, nb


@njit
def _grid_nn_rows(X, block_keys, nearest, log2_blocks, cell, Q, gate2, out_idx):
    """Approximate gated nearest neighbours: the point stored for the cell of each row of ``X``
    (:func:`build_nearest_grid`), if within ``sqrt(gate2)`` of the row; else ``Q.shape[0]``."""
    nq = Q.shape[0]
    for i in range(X.shape[0]):
        ix = np.int64(np.floor(X[i, 0] / cell))
        iy = np.int64(np.floor(X[i, 1] / cell))
        iz = np.int64(np.floor(X[i, 2] / cell))
        s = block_slot(block_keys, cell_key(ix >> 3, iy >> 3, iz >> 3), log2_blocks)
        out_idx[i] = nq
        if block_keys[s] != -1:
            j = nearest[s, ((ix & 7) << 6) | ((iy & 7) << 3) | (iz & 7)]
            if j >= 0:
                dx = X[i, 0] - Q[j, 0]
                dy = X[i, 1] - Q[j, 1]
                dz = X[i, 2] - Q[j, 2]
                if dx * dx + dy * dy + dz * dz <= gate2:
                    out_idx[i] = j


@njit_parallel
def steps_4dof_grid(S, T0s, Q, Nq, block_keys, nearest, log2_blocks, cell, gates2, out_T):
    """The Gauss-Newton steps of :func:`refine_placements_4dof` (one per gate in ``gates2``) with
    the nearest map point taken from the lookup grid of :func:`build_nearest_grid` (the point
    nearest to the centre of the query's cell: an approximation within about a cell). No
    score: the correlative search scores the result with the exact kernel (no step)."""
    nc = T0s.shape[0]
    m = S.shape[0]
    nq = Q.shape[0]
    for c in prange(nc):
        T = T0s[c].copy()
        X = np.empty((m, 3))
        oi = np.empty(m, np.int64)
        A = np.empty((4, 4))
        b = np.empty(4)
        for it in range(gates2.shape[0]):
            _apply(T, S, X)
            _grid_nn_rows(X, block_keys, nearest, log2_blocks, cell, Q, gates2[it], oi)
            _gn4_step(X, oi, nq, Q, Nq, T, A, b)
        for p in range(4):
            for q in range(4):
                out_T[c, p, q] = T[p, q]
