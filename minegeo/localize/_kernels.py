"""Numba kernels of :mod:`minegeo.localize` (contiguous arrays in, no checks).

The correlative search (:mod:`minegeo.localize.correlative`) stores the map's occupied
cells in an open-addressing hash table of int64 cell keys (empty slot = -1, linear probing,
Fibonacci hashing of the key) and scores 4-DOF placements of a levelled scan against it.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.registration._kernels import _kd_nn_rows

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
def score_placements(table, log2_capacity, tight, log2_tight, cell, S, anchors, cos_yaw, sin_yaw, max_misses,
                     miss_rate, miss_slack):
    """Hit counts of every (anchor, yaw) placement of the levelled scan sample ``S``.

    Placement ``(a, ψ)`` maps a scan point ``s`` (relative to the scan's reference floor
    point) to ``Rz(ψ) s + a``; a point *hits* when its cell is in the (dilated) map table.
    Counting stops once ``max_misses`` points missed, or earlier once the misses among the
    first ``i + 1`` points exceed ``miss_rate (i + 1) + miss_slack`` (a placement missing
    that often early on is abandoned; its count is then a lower bound that the caller
    discards). Returns ``(hits, tight_hits)``: a hit also counts as *tight* when its cell is in
    ``tight`` (the undilated occupancy), which ranks placements that all hit everything. Independent per anchor (``prange``),
    so the result does not depend on the thread count.
    """
    na, ny, m = anchors.shape[0], cos_yaw.shape[0], S.shape[0]
    mask = (np.int64(1) << log2_capacity) - 1
    shift = np.int64(64 - log2_capacity)
    mask_t = (np.int64(1) << log2_tight) - 1
    shift_t = np.int64(64 - log2_tight)
    out = np.zeros((na, ny), dtype=np.int32)
    out_t = np.zeros((na, ny), dtype=np.int32)
    for a in prange(na):
        ax, ay, az = anchors[a, 0], anchors[a, 1], anchors[a, 2]
        for k in range(ny):
            c, s = cos_yaw[k], sin_yaw[k]
            hits = 0
            thits = 0
            misses = 0
            for i in range(m):
                x = c * S[i, 0] - s * S[i, 1] + ax
                y = s * S[i, 0] + c * S[i, 1] + ay
                z = S[i, 2] + az
                key = cell_key(np.int64(np.floor(x / cell)), np.int64(np.floor(y / cell)),
                               np.int64(np.floor(z / cell)))
                if hash_contains(table, key, shift, mask):
                    hits += 1
                    if hash_contains(tight, key, shift_t, mask_t):
                        thits += 1
                else:
                    misses += 1
                    if misses > max_misses or misses > miss_rate * (i + 1) + miss_slack:
                        break
            out[a, k] = hits
            out_t[a, k] = thits
    return out, out_t


@njit_parallel
def refine_placements_4dof(S, T0s, Q, Nq, idx, Qs, start, end, dim, split, left, right, depth, gates2, tol,
                           final_gate2, out_T, out_count):
    """4-DOF point-to-plane Gauss-Newton of every candidate placement (``prange`` over candidates).

    For candidate ``c`` and each gate ``g`` in ``gates2`` (squared, m²): pair every sample point
    ``x = R s + t`` with its nearest map point ``q`` (normal ``n``) within ``g`` (the
    registration package's gated KD-tree descent), then solve the damped normal equations of
    ``Σ (n·(Rz(δψ)(x − x̄) + x̄ + δt − q))²`` linearised at 0, i.e. rows
    ``J = [n_y (x − x̄) − n_x (y − ȳ), n_x, n_y, n_z]``, ``r = n·(x − q)``, and apply
    ``T ← [Rz(δψ) | x̄ − Rz(δψ) x̄ + δt] T``. Finally counts the sample points whose nearest
    map point lies within ``final_gate2`` and whose plane distance is below ``tol``.
    Candidates are independent, so results do not depend on the thread count.
    """
    nc = T0s.shape[0]
    m = S.shape[0]
    for c in prange(nc):
        T = T0s[c].copy()
        X = np.empty((m, 3))
        oi = np.empty(m, np.int64)
        osq = np.empty(m)
        A = np.empty((4, 4))
        b = np.empty(4)
        for it in range(gates2.shape[0] + 1):
            for i in range(m):
                for k in range(3):
                    X[i, k] = T[k, 0] * S[i, 0] + T[k, 1] * S[i, 1] + T[k, 2] * S[i, 2] + T[k, 3]
            g2 = final_gate2 if it == gates2.shape[0] else gates2[it]
            _kd_nn_rows(X, idx, Qs, start, end, dim, split, left, right, depth, g2, oi, osq, 0, m)
            nq = idx.shape[0]
            if it == gates2.shape[0]:
                cnt = 0
                for i in range(m):
                    j = oi[i]
                    if j < nq:
                        r = ((X[i, 0] - Q[j, 0]) * Nq[j, 0] + (X[i, 1] - Q[j, 1]) * Nq[j, 1]
                             + (X[i, 2] - Q[j, 2]) * Nq[j, 2])
                        if abs(r) < tol:
                            cnt += 1
                out_count[c] = cnt
                break
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
                continue
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
        for p in range(4):
            for q in range(4):
                out_T[c, p, q] = T[p, q]
