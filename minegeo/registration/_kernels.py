"""Numba kernels of :mod:`minegeo.registration` (contiguous float64 arrays in, no checks).

Every reduction over points uses *fixed chunking*: the points are cut into chunks of
``CHUNK`` consecutive rows, each chunk's partial sums are computed independently
(``prange`` over chunks), and the partials are then added serially in chunk order.
The floating-point summation order therefore depends only on the number of points,
never on the number of threads, so results are bit-identical on 1 or N threads.

The public, validated, documented functions live in ``estimation.py``,
``evaluation.py`` and ``icp.py``; read their docstrings for the mathematics.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo._validate import is_permutation

#: Rows per reduction chunk (fixed so that summation order is thread-count independent).
CHUNK = 1024
#: Upper (with diagonal) and strictly lower triangle indices of a 6x6 matrix (row-major order).
_IU6 = np.triu_indices(6)
_IL6 = np.tril_indices(6, -1)


@njit
def n_chunks(m):
    """Number of ``CHUNK``-row chunks covering ``m`` rows (0 for m = 0)."""
    return (m + CHUNK - 1) // CHUNK


#: Below this many rows the serial driver is used. The per-iteration ICP work is a few flops per
#: pair, so a thread launch only pays off for very large clouds (measured on the shared 2-core
#: machine: a prange launch under load can cost tens of ms, the serial pass over 2e4 pairs < 1 ms).
#: Both drivers run the same chunk bodies in the same order, so the results are bit-identical.
PARALLEL_MIN_ROWS = 1 << 18
#: Nearest-neighbour queries cost ~1 µs per row (a tree descent), far more than the reductions'
#: few flops, so the query switches to ``prange`` much earlier. Measured on the idle 2-core machine
#: (the ICP stages of benchmarks/bench_registration.py): serial queries made minegeo's ICP
#: 1.15-1.42x Open3D's time, parallel queries from 4096 rows bring it below 1.
PARALLEL_QUERY_ROWS = 1 << 12


# ----------------------------------------------------------------------------- validation helper


@njit
def finite_max_abs(X):
    """``max |x|`` over all entries of ``X`` (2-D), or ``inf`` as soon as one is NaN or inf (one pass)."""
    m = 0.0
    for i in range(X.shape[0]):
        for c in range(X.shape[1]):
            v = X[i, c]
            if not (v - v == 0.0):  # NaN or +-inf
                return np.inf
            v = abs(v)
            if v > m:
                m = v
    return m


# ----------------------------------------------------------------------------- per-point maps


@njit
def _transform_rows(P, T, out, start, end):
    for i in range(start, end):
        x = P[i, 0]
        y = P[i, 1]
        z = P[i, 2]
        for r in range(3):
            out[i, r] = T[r, 0] * x + T[r, 1] * y + T[r, 2] * z + T[r, 3]


@njit
def _transform_serial(P, T, out):
    _transform_rows(P, T, out, 0, P.shape[0])


@njit_parallel
def _transform_parallel(P, T, out):
    m = P.shape[0]
    for c in prange(n_chunks(m)):
        _transform_rows(P, T, out, c * CHUNK, min(m, (c + 1) * CHUNK))


def transform_points_kernel(P, T):
    """``out_i = R p_i + t`` for (n, 3) ``P`` and a 4x4 ``T`` (sum order x, y, z, t as Eigen)."""
    out = np.empty((P.shape[0], 3))
    if P.shape[0] >= PARALLEL_MIN_ROWS:
        _transform_parallel(P, T, out)
    else:
        _transform_serial(P, T, out)
    return out


def rotate_vectors_kernel(V, R):
    """``out_i = R v_i`` for (n, 3) ``V`` (normals) and a 3x3 ``R``."""
    T = np.eye(4)
    T[:3, :3] = R
    return transform_points_kernel(V, T)


@njit
def _gate_rows(P, Q, nn_idx, d2, sq, valid, start, end):
    m = Q.shape[0]
    for i in range(start, end):
        j = nn_idx[i]
        if j < 0 or j >= m:
            sq[i] = np.inf
            valid[i] = False
            continue
        dx = P[i, 0] - Q[j, 0]
        dy = P[i, 1] - Q[j, 1]
        dz = P[i, 2] - Q[j, 2]
        s = dx * dx + dy * dy + dz * dz
        sq[i] = s
        valid[i] = s < d2


@njit
def _gate_serial(P, Q, nn_idx, d2, sq, valid):
    _gate_rows(P, Q, nn_idx, d2, sq, valid, 0, P.shape[0])


@njit_parallel
def _gate_parallel(P, Q, nn_idx, d2, sq, valid):
    n = P.shape[0]
    for c in prange(n_chunks(n)):
        _gate_rows(P, Q, nn_idx, d2, sq, valid, c * CHUNK, min(n, (c + 1) * CHUNK))


def gate_nearest_kernel(P, Q, nn_idx, d2):
    """Squared distance to the proposed nearest target and the strict gate ``sq < d2``.

    ``nn_idx[i] >= Q.shape[0]`` marks "no neighbour found" (pykdtree convention).
    Returns ``(sq, valid)``; ``sq`` is ``inf`` where there is no neighbour.
    The squared distance is recomputed here as ``dx*dx + dy*dy + dz*dz`` (nanoflann's
    L2 order) so that the gate does not depend on the search library's arithmetic.
    """
    n = P.shape[0]
    sq = np.empty(n)
    valid = np.empty(n, dtype=np.bool_)
    if n >= PARALLEL_MIN_ROWS:
        _gate_parallel(P, Q, nn_idx, float(d2), sq, valid)
    else:
        _gate_serial(P, Q, nn_idx, float(d2), sq, valid)
    return sq, valid


# ----------------------------------------------------------------------------- reductions


@njit
def _sum_rows(x, start, end):
    s = 0.0
    for i in range(start, end):
        s += x[i]
    return s


@njit
def _sum_serial(x, part):
    m = x.shape[0]
    for c in range(part.shape[0]):
        part[c] = _sum_rows(x, c * CHUNK, min(m, (c + 1) * CHUNK))


@njit_parallel
def _sum_parallel(x, part):
    m = x.shape[0]
    for c in prange(part.shape[0]):
        part[c] = _sum_rows(x, c * CHUNK, min(m, (c + 1) * CHUNK))


def _add_partials(part):
    """Serial, in-order sum of chunk partials (rows) -> 1-D totals."""
    tot = np.zeros(part.shape[1:]) if part.ndim > 1 else 0.0
    for c in range(part.shape[0]):
        tot = tot + part[c]
    return tot


def sum_kernel(x):
    """Deterministic chunked sum of a 1-D array."""
    part = np.zeros((n_chunks(x.shape[0]),))
    if x.shape[0] >= PARALLEL_MIN_ROWS:
        _sum_parallel(x, part)
    else:
        _sum_serial(x, part)
    return float(_add_partials(part))


@njit
def _moments1_rows(P, Q, w, part, c, start, end):
    for i in range(start, end):
        wi = w[i]
        part[c, 0] += wi
        for k in range(3):
            part[c, 1 + k] += wi * P[i, k]
            part[c, 4 + k] += wi * Q[i, k]


@njit
def _moments2_rows(P, Q, w, mu_p, mu_q, part, c, start, end):
    for i in range(start, end):
        wi = w[i]
        a0 = P[i, 0] - mu_p[0]
        a1 = P[i, 1] - mu_p[1]
        a2 = P[i, 2] - mu_p[2]
        b0 = Q[i, 0] - mu_q[0]
        b1 = Q[i, 1] - mu_q[1]
        b2 = Q[i, 2] - mu_q[2]
        part[c, 0] += wi * a0 * b0
        part[c, 1] += wi * a0 * b1
        part[c, 2] += wi * a0 * b2
        part[c, 3] += wi * a1 * b0
        part[c, 4] += wi * a1 * b1
        part[c, 5] += wi * a1 * b2
        part[c, 6] += wi * a2 * b0
        part[c, 7] += wi * a2 * b1
        part[c, 8] += wi * a2 * b2
        part[c, 9] += wi * (a0 * a0 + a1 * a1 + a2 * a2)


@njit
def _moments_serial(P, Q, w, part1, part2):
    m = P.shape[0]
    nc = part1.shape[0]
    for c in range(nc):
        _moments1_rows(P, Q, w, part1, c, c * CHUNK, min(m, (c + 1) * CHUNK))
    mu_p, mu_q = _means_from_partials(part1)
    for c in range(nc):
        _moments2_rows(P, Q, w, mu_p, mu_q, part2, c, c * CHUNK, min(m, (c + 1) * CHUNK))
    return mu_p, mu_q


@njit_parallel
def _moments_parallel(P, Q, w, part1, part2):
    m = P.shape[0]
    nc = part1.shape[0]
    for c in prange(nc):
        _moments1_rows(P, Q, w, part1, c, c * CHUNK, min(m, (c + 1) * CHUNK))
    mu_p, mu_q = _means_from_partials(part1)
    for c in prange(nc):
        _moments2_rows(P, Q, w, mu_p, mu_q, part2, c, c * CHUNK, min(m, (c + 1) * CHUNK))
    return mu_p, mu_q


@njit
def _means_from_partials(part1):
    tot = np.zeros(7)
    for c in range(part1.shape[0]):
        for k in range(7):
            tot[k] += part1[c, k]
    mu_p = np.zeros(3)
    mu_q = np.zeros(3)
    if tot[0] > 0.0:
        for k in range(3):
            mu_p[k] = tot[1 + k] / tot[0]
            mu_q[k] = tot[4 + k] / tot[0]
    return mu_p, mu_q


def weighted_moments_kernel(P, Q, w):
    """Weighted means and centred second moments of corresponding rows of ``P`` and ``Q``.

    Returns ``(sum_w, mu_p (3,), mu_q (3,), W (3,3), var_p)`` with
    ``W = sum_i w_i (p_i - mu_p)(q_i - mu_q)^T / sum_w`` ([Baek2022 Eq. 10], centred) and
    ``var_p = sum_i w_i |p_i - mu_p|^2 / sum_w``. Two passes (means, then centred sums).
    """
    nc = n_chunks(P.shape[0])
    part1 = np.zeros((nc, 7))
    part2 = np.zeros((nc, 10))
    if P.shape[0] >= PARALLEL_MIN_ROWS:
        mu_p, mu_q = _moments_parallel(P, Q, w, part1, part2)
    else:
        mu_p, mu_q = _moments_serial(P, Q, w, part1, part2)
    sw = float(_add_partials(part1[:, :1])[0]) if nc else 0.0
    tot2 = _add_partials(part2) if nc else np.zeros(10)
    W = np.zeros((3, 3))
    var_p = 0.0
    if sw > 0.0:
        W = tot2[:9].reshape(3, 3) / sw
        var_p = float(tot2[9] / sw)
    return sw, mu_p, mu_q, W, var_p


@njit
def umeyama_from_moments(mu_p, mu_q, W, var_p, with_scale):
    """Closed-form similarity from the moments ([Baek2022 Eqs. 11-13]; Umeyama 1991).

    ``W = U S V^T`` ([Baek2022 Eq. 11]), ``R = V diag(1, 1, d) U^T`` with ``d = sign det(V U^T)``
    ([Baek2022 Eq. 12] with the reflection fix), ``c = tr(S diag(1,1,d)) / var_p`` if scaling, and
    ``t = mu_q - c R mu_p`` ([Baek2022 Eq. 13]). Returns ``(T 4x4, c, singular values S)``.
    """
    U, S, Vt = np.linalg.svd(W)
    V = Vt.T
    d = 1.0
    if np.linalg.det(V) * np.linalg.det(U) < 0.0:
        d = -1.0
    D = np.eye(3)
    D[2, 2] = d
    R = V @ D @ U.T
    c = 1.0
    if with_scale:
        if var_p > 0.0:
            c = (S[0] + S[1] + d * S[2]) / var_p
        else:
            c = 1.0
    T = np.eye(4)
    for r in range(3):
        for k in range(3):
            T[r, k] = c * R[r, k]
        T[r, 3] = mu_q[r] - c * (R[r, 0] * mu_p[0] + R[r, 1] * mu_p[1] + R[r, 2] * mu_p[2])
    return T, c, S


@njit
def umeyama_small_kernel(P, Q, with_scale):
    """Serial, allocation-light Umeyama for tiny samples (RANSAC minimal sets), unit weights.

    Same mathematics as :func:`weighted_moments_kernel` + :func:`umeyama_from_moments`,
    callable from other njit code. Returns ``(T 4x4, scale)``; identity for 0 rows
    (Open3D semantics).
    """
    m = P.shape[0]
    if m == 0:
        return np.eye(4), 1.0
    mu_p = np.zeros(3)
    mu_q = np.zeros(3)
    for i in range(m):
        for k in range(3):
            mu_p[k] += P[i, k]
            mu_q[k] += Q[i, k]
    for k in range(3):
        mu_p[k] /= m
        mu_q[k] /= m
    W = np.zeros((3, 3))
    var_p = 0.0
    for i in range(m):
        for r in range(3):
            a = P[i, r] - mu_p[r]
            var_p += a * a
            for k in range(3):
                W[r, k] += a * (Q[i, k] - mu_q[k])
    for r in range(3):
        for k in range(3):
            W[r, k] /= m
    var_p /= m
    T, c, _ = umeyama_from_moments(mu_p, mu_q, W, var_p, with_scale)
    return T, c


@njit
def _p2l_add(part, c, J, px, py, pz, qx, qy, qz, nx, ny, nz):
    """Add one point-to-plane pair to row ``c`` of ``part``: the upper triangle of ``JᵀJ``
    (21), ``Jᵀr`` (6) and ``r²`` (1), with ``r = (p − q)·n`` and ``J = [p × n, n]``."""
    r = (px - qx) * nx + (py - qy) * ny + (pz - qz) * nz
    J[0] = py * nz - pz * ny
    J[1] = pz * nx - px * nz
    J[2] = px * ny - py * nx
    J[3] = nx
    J[4] = ny
    J[5] = nz
    k = 0
    for a in range(6):
        for b in range(a, 6):
            part[c, k] += J[a] * J[b]
            k += 1
    for a in range(6):
        part[c, 21 + a] += J[a] * r
    part[c, 27] += r * r


@njit
def _p2l_rows(P, Q, N, part, c, start, end):
    J = np.empty(6)
    for i in range(start, end):
        _p2l_add(part, c, J, P[i, 0], P[i, 1], P[i, 2], Q[i, 0], Q[i, 1], Q[i, 2], N[i, 0], N[i, 1], N[i, 2])


@njit
def _p2l_serial(P, Q, N, part):
    m = P.shape[0]
    for c in range(part.shape[0]):
        _p2l_rows(P, Q, N, part, c, c * CHUNK, min(m, (c + 1) * CHUNK))


@njit_parallel
def _p2l_parallel(P, Q, N, part):
    m = P.shape[0]
    for c in prange(part.shape[0]):
        _p2l_rows(P, Q, N, part, c, c * CHUNK, min(m, (c + 1) * CHUNK))


def point_to_plane_system_kernel(P, Q, N):
    """Gauss-Newton normal equations of point-to-plane ICP (Low 2004; Open3D §7).

    For each pair: ``r_i = (p_i - q_i) . n_i`` and ``J_i = [p_i x n_i, n_i]`` (1x6).
    Returns ``(H = sum J^T J (6x6), g = sum J^T r (6,), sum r^2)``.
    """
    part = np.zeros((n_chunks(P.shape[0]), 28))
    if P.shape[0] >= PARALLEL_MIN_ROWS:
        _p2l_parallel(P, Q, N, part)
    else:
        _p2l_serial(P, Q, N, part)
    tot = _add_partials(part) if part.shape[0] else np.zeros(28)
    H = np.empty((6, 6))
    H[_IU6] = tot[:21]
    H[_IL6] = H[_IL6[1], _IL6[0]]  # mirror the upper triangle (same values as H + triu(H, 1).T)
    return H, tot[21:27].copy(), float(tot[27])


@njit
def _moments_q_rows(Q, part, c, start, end):
    for i in range(start, end):
        x = Q[i, 0]
        y = Q[i, 1]
        z = Q[i, 2]
        part[c, 0] += x
        part[c, 1] += y
        part[c, 2] += z
        part[c, 3] += x * x
        part[c, 4] += y * y
        part[c, 5] += z * z
        part[c, 6] += x * y
        part[c, 7] += x * z
        part[c, 8] += y * z


@njit
def _moments_q_serial(Q, part):
    m = Q.shape[0]
    for c in range(part.shape[0]):
        _moments_q_rows(Q, part, c, c * CHUNK, min(m, (c + 1) * CHUNK))


def point_to_point_information_kernel(Q):
    """``sum_i G_i^T G_i`` with ``G_i = [-[q_i]x, I3]`` (3x6), Open3D's
    ``GetInformationMatrixFromPointClouds`` rows evaluated at the target points ``q_i``.

    Closed form from the moments: top-left ``sum(|q|^2 I - q q^T)``, top-right
    ``[sum q]x``, bottom-left ``-[sum q]x``, bottom-right ``m I``. Computed once per
    registration, so a serial chunked pass is enough.
    """
    m = Q.shape[0]
    part = np.zeros((n_chunks(m), 9))
    _moments_q_serial(Q, part)
    s = _add_partials(part) if part.shape[0] else np.zeros(9)
    H = np.zeros((6, 6))
    H[0, 0] = s[4] + s[5]
    H[1, 1] = s[3] + s[5]
    H[2, 2] = s[3] + s[4]
    H[0, 1] = H[1, 0] = -s[6]
    H[0, 2] = H[2, 0] = -s[7]
    H[1, 2] = H[2, 1] = -s[8]
    # top-right block = [S]x with S = sum q ; bottom-left = its transpose (= -[S]x)
    sx, sy, sz = s[0], s[1], s[2]
    H[0, 4] = -sz
    H[0, 5] = sy
    H[1, 3] = sz
    H[1, 5] = -sx
    H[2, 3] = -sy
    H[2, 4] = sx
    H[3:, :3] = H[:3, 3:].T
    H[3, 3] = H[4, 4] = H[5, 5] = m
    return H


# ----------------------------------------------------------------------------- PCA normals


@njit
def _pca_rows(Q, nb, out, start, end):
    k = nb.shape[1]
    C = np.empty((3, 3))
    for i in range(start, end):
        mx = 0.0
        my = 0.0
        mz = 0.0
        for a in range(k):
            j = nb[i, a]
            mx += Q[j, 0]
            my += Q[j, 1]
            mz += Q[j, 2]
        mx /= k
        my /= k
        mz /= k
        for r in range(3):
            for c in range(3):
                C[r, c] = 0.0
        for a in range(k):
            j = nb[i, a]
            dx = Q[j, 0] - mx
            dy = Q[j, 1] - my
            dz = Q[j, 2] - mz
            C[0, 0] += dx * dx
            C[0, 1] += dx * dy
            C[0, 2] += dx * dz
            C[1, 1] += dy * dy
            C[1, 2] += dy * dz
            C[2, 2] += dz * dz
        C[1, 0] = C[0, 1]
        C[2, 0] = C[0, 2]
        C[2, 1] = C[1, 2]
        _, V = np.linalg.eigh(C)
        out[i, 0] = V[0, 0]
        out[i, 1] = V[1, 0]
        out[i, 2] = V[2, 0]


@njit
def _pca_serial(Q, nb, out):
    _pca_rows(Q, nb, out, 0, nb.shape[0])


@njit_parallel
def _pca_parallel(Q, nb, out):
    m = nb.shape[0]
    for c in prange(n_chunks(m)):
        _pca_rows(Q, nb, out, c * CHUNK, min(m, (c + 1) * CHUNK))


def pca_normals_kernel(Q, nb):
    """Unit normal (eigenvector of the smallest eigenvalue of the neighbourhood covariance) per row
    of the (m, k) neighbour index array ``nb`` into ``Q``; sign as returned by LAPACK."""
    out = np.empty((nb.shape[0], 3))
    if nb.shape[0] >= PARALLEL_MIN_ROWS // 4:
        _pca_parallel(Q, nb, out)
    else:
        _pca_serial(Q, nb, out)
    return out


# ----------------------------------------------------------------------------- gated 1-NN KD-tree

#: Maximum number of points in a KD-tree leaf.
KD_LEAF = 12


@njit
def _grow(a, n):
    """Copy of ``a`` (first axis) with capacity ``n`` (new entries undefined)."""
    out = np.empty((n,) + a.shape[1:], a.dtype)
    out[: a.shape[0]] = a
    return out


@njit
def _box_add(box, b, Qs, a):
    for c in range(3):
        v = Qs[a, c]
        if v < box[b, c]:
            box[b, c] = v
        if v > box[b, 3 + c]:
            box[b, 3 + c] = v


@njit
def kd_build(Q, leaf):
    """Sliding-midpoint KD-tree over ``Q`` (m, 3): split the widest bounding-box side at its middle.

    Returns ``(idx, Qs, start, end, dim, split, left, right, depth)``: ``Qs = Q[idx]`` (points in
    leaf order), per node the ``[start, end)`` range into ``Qs``, the split dimension (-1 = leaf),
    the split value and the children; ``depth`` is the maximum node depth. Coincident points
    (zero spread) stay in one leaf.

    The points are partitioned in a contiguous working copy (rows swapped together with
    ``idx``), and the bounding boxes of both children are accumulated while their parent is
    partitioned, so each tree level costs one sequential pass. Node arrays start at
    ``m // 2 + 64`` entries and grow by doubling (at most ``2 m - 1`` nodes).
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
        for c in range(3):
            box[lc, c] = np.inf
            box[lc, 3 + c] = -np.inf
            box[rc, c] = np.inf
            box[rc, 3 + c] = -np.inf
        i = s
        jj = e - 1
        while i <= jj:  # partition: [s, mid) < sv <= [mid, e)
            if Qs[i, k] < sv:
                _box_add(box, lc, Qs, i)
                i += 1
            else:
                t = idx[i]
                idx[i] = idx[jj]
                idx[jj] = t
                for c in range(3):
                    v = Qs[i, c]
                    Qs[i, c] = Qs[jj, c]
                    Qs[jj, c] = v
                _box_add(box, rc, Qs, jj)
                jj -= 1
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


@njit
def kd_walk_to_leaf(px, py, pz, nd, bound, dim, split, left, right, st_node, st_lb, sp):
    """Descend a :func:`kd_build` tree from node ``nd`` to the leaf holding ``(px, py, pz)``,
    pushing every far child whose squared plane distance is ``<= bound`` (with that distance as
    its lower bound) onto the caller's stacks. Returns ``(leaf, stack size)``."""
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
def kd_nn_descend(px, py, pz, best, best_j, idx, Qs, start, end, dim, split, left, right, d2, st_node, st_lb):
    """Gated nearest neighbour of ``(px, py, pz)`` on a :func:`kd_build` tree.

    ``(best, best_j)`` is the starting bound: ``(d2, m)`` for a cold search, or a known
    point's ``(sq, index)`` with ``sq < d2`` (a warm start: same answer, fewer nodes). Returns
    the lexicographically smallest ``(sq, index)`` with ``sq < d2``
    (``sq = dx*dx + dy*dy + dz*dz``), or the start bound when none is closer. ``st_node`` /
    ``st_lb`` are caller-owned stacks of length ``depth + 2``.
    """
    st_node[0] = 0
    st_lb[0] = 0.0
    sp = 1
    while sp > 0:
        sp -= 1
        nd = st_node[sp]
        if st_lb[sp] > best:
            continue
        nd, sp = kd_walk_to_leaf(px, py, pz, nd, best, dim, split, left, right, st_node, st_lb, sp)
        for a in range(start[nd], end[nd]):
            dx = px - Qs[a, 0]
            dy = py - Qs[a, 1]
            dz = pz - Qs[a, 2]
            sq = dx * dx + dy * dy + dz * dz
            if sq < d2:
                j = idx[a]
                if sq < best or (sq == best and j < best_j):
                    best = sq
                    best_j = j
    return best, best_j


@njit
def _kd_nn_rows(P, idx, Qs, start, end, dim, split, left, right, depth, d2, out_idx, out_sq, r0, r1):
    m = idx.shape[0]
    st_node = np.empty(depth + 2, np.int64)
    st_lb = np.empty(depth + 2)
    for i in range(r0, r1):
        best, best_j = kd_nn_descend(P[i, 0], P[i, 1], P[i, 2], d2, m, idx, Qs, start, end, dim, split, left,
                                     right, d2, st_node, st_lb)
        out_idx[i] = best_j
        out_sq[i] = best if best_j < m else np.inf


@njit
def _kd_nn_serial(P, idx, Qs, start, end, dim, split, left, right, depth, d2, out_idx, out_sq):
    _kd_nn_rows(P, idx, Qs, start, end, dim, split, left, right, depth, d2, out_idx, out_sq, 0, P.shape[0])


@njit_parallel
def _kd_nn_parallel(P, idx, Qs, start, end, dim, split, left, right, depth, d2, out_idx, out_sq):
    n = P.shape[0]
    for c in prange(n_chunks(n)):
        _kd_nn_rows(P, idx, Qs, start, end, dim, split, left, right, depth, d2, out_idx, out_sq,
                    c * CHUNK, min(n, (c + 1) * CHUNK))


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
        self._tree = (idx, np.ascontiguousarray(Q[idx]), start.astype(np.int64), end.astype(np.int64),
                      dim.astype(np.int64), split.astype(np.float64), left.astype(np.int64), right.astype(np.int64),
                      depth)
        return self

    def query(self, P, d2):
        n = P.shape[0]
        idx = np.empty(n, dtype=np.int64)
        sq = np.empty(n)
        if n >= PARALLEL_QUERY_ROWS:
            _kd_nn_parallel(P, *self._tree, float(d2), idx, sq)
        else:
            _kd_nn_serial(P, *self._tree, float(d2), idx, sq)
        return idx, sq


# ----------------------------------------------------------------------------- indexed ICP reductions
# Same sums as point_to_plane_system_kernel / weighted_moments_kernel on the pairs
# (P[si[k]], Q[ti[k]]), without materialising the gathered copies (bit-identical results).


@njit
def _p2l_idx_serial(P, Q, N, si, ti, part):
    m = si.shape[0]
    J = np.empty(6)
    for c in range(part.shape[0]):
        for i in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            a_ = si[i]
            b_ = ti[i]
            _p2l_add(part, c, J, P[a_, 0], P[a_, 1], P[a_, 2], Q[b_, 0], Q[b_, 1], Q[b_, 2], N[b_, 0], N[b_, 1],
                     N[b_, 2])


def point_to_plane_system_idx(P, Q, N, si, ti):
    """:func:`point_to_plane_system_kernel` on the pairs ``(P[si], Q[ti], N[ti])``."""
    part = np.zeros((n_chunks(si.shape[0]), 28))
    _p2l_idx_serial(P, Q, N, si, ti, part)
    tot = _add_partials(part) if part.shape[0] else np.zeros(28)
    H = np.empty((6, 6))
    H[_IU6] = tot[:21]
    H[_IL6] = H[_IL6[1], _IL6[0]]  # mirror the upper triangle (same values as H + triu(H, 1).T)
    return H, tot[21:27].copy(), float(tot[27])


@njit
def _moments_idx_serial(P, Q, si, ti, part1, part2):
    m = si.shape[0]
    nc = part1.shape[0]
    for c in range(nc):
        for i in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            a = si[i]
            b = ti[i]
            part1[c, 0] += 1.0
            for k in range(3):
                part1[c, 1 + k] += 1.0 * P[a, k]
                part1[c, 4 + k] += 1.0 * Q[b, k]
    mu_p, mu_q = _means_from_partials(part1)
    for c in range(nc):
        for i in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            a = si[i]
            b = ti[i]
            a0 = P[a, 0] - mu_p[0]
            a1 = P[a, 1] - mu_p[1]
            a2 = P[a, 2] - mu_p[2]
            b0 = Q[b, 0] - mu_q[0]
            b1 = Q[b, 1] - mu_q[1]
            b2 = Q[b, 2] - mu_q[2]
            part2[c, 0] += 1.0 * a0 * b0
            part2[c, 1] += 1.0 * a0 * b1
            part2[c, 2] += 1.0 * a0 * b2
            part2[c, 3] += 1.0 * a1 * b0
            part2[c, 4] += 1.0 * a1 * b1
            part2[c, 5] += 1.0 * a1 * b2
            part2[c, 6] += 1.0 * a2 * b0
            part2[c, 7] += 1.0 * a2 * b1
            part2[c, 8] += 1.0 * a2 * b2
            part2[c, 9] += 1.0 * (a0 * a0 + a1 * a1 + a2 * a2)
    return mu_p, mu_q


def weighted_moments_idx(P, Q, si, ti):
    """:func:`weighted_moments_kernel` with unit weights on the pairs ``(P[si], Q[ti])``."""
    nc = n_chunks(si.shape[0])
    part1 = np.zeros((nc, 7))
    part2 = np.zeros((nc, 10))
    mu_p, mu_q = _moments_idx_serial(P, Q, si, ti, part1, part2)
    sw = float(_add_partials(part1[:, :1])[0]) if nc else 0.0
    tot2 = _add_partials(part2) if nc else np.zeros(10)
    W = np.zeros((3, 3))
    var_p = 0.0
    if sw > 0.0:
        W = tot2[:9].reshape(3, 3) / sw
        var_p = float(tot2[9] / sw)
    return sw, mu_p, mu_q, W, var_p
