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
from minegeo.kernels.chunks import CHUNK, by_size, n_chunks
from minegeo.kernels.eig3 import pca_normals_eigh_rows

#: Upper (with diagonal) and strictly lower triangle indices of a 6x6 matrix (row-major order).
_IU6 = np.triu_indices(6)
_IL6 = np.tril_indices(6, -1)

#: Below this many rows the serial driver is used. The per-iteration ICP work is a few flops per
#: pair, so a thread launch only pays off for very large clouds (measured on the shared 2-core
#: machine: a prange launch under load can cost tens of ms, the serial pass over 2e4 pairs < 1 ms).
#: Both drivers run the same chunk bodies in the same order, so the results are bit-identical.
PARALLEL_MIN_ROWS = 1 << 18
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
    by_size(P.shape[0], PARALLEL_MIN_ROWS, _transform_serial, _transform_parallel)(P, T, out)
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
    by_size(n, PARALLEL_MIN_ROWS, _gate_serial, _gate_parallel)(P, Q, nn_idx, float(d2), sq, valid)
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
    by_size(x.shape[0], PARALLEL_MIN_ROWS, _sum_serial, _sum_parallel)(x, part)
    return float(_add_partials(part))


@njit
def _moments1_add(part, c, wi, P, a, Q, b):
    """Add pair ``(P[a], Q[b])`` with weight ``wi`` to the first-pass sums ``part[c]``:
    ``Σ w``, ``Σ w p``, ``Σ w q``."""
    part[c, 0] += wi
    for k in range(3):
        part[c, 1 + k] += wi * P[a, k]
        part[c, 4 + k] += wi * Q[b, k]


@njit
def _moments2_add(part, c, wi, P, a, Q, b, mu_p, mu_q):
    """Add pair ``(P[a], Q[b])`` with weight ``wi`` to the centred second-pass sums ``part[c]``:
    ``Σ w (p - mu_p)(q - mu_q)ᵀ`` (row-major, 9) and ``Σ w |p - mu_p|²``."""
    a0 = P[a, 0] - mu_p[0]
    a1 = P[a, 1] - mu_p[1]
    a2 = P[a, 2] - mu_p[2]
    b0 = Q[b, 0] - mu_q[0]
    b1 = Q[b, 1] - mu_q[1]
    b2 = Q[b, 2] - mu_q[2]
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
def _moments1_rows(P, Q, w, part, c, start, end):
    for i in range(start, end):
        _moments1_add(part, c, w[i], P, i, Q, i)


@njit
def _moments2_rows(P, Q, w, mu_p, mu_q, part, c, start, end):
    for i in range(start, end):
        _moments2_add(part, c, w[i], P, i, Q, i, mu_p, mu_q)


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
    mu_p, mu_q = by_size(P.shape[0], PARALLEL_MIN_ROWS, _moments_serial, _moments_parallel)(P, Q, w, part1, part2)
    sw = float(_add_partials(part1[:, :1])[0]) if nc else 0.0
    tot2 = _add_partials(part2) if nc else np.zeros(10)
    W = np.zeros((3, 3))
    var_p = 0.0
    if sw > 0.0:
        W = tot2[:9].reshape(3, 3) / sw
        var_p = float(tot2[9] / sw)
    return sw, mu_p, mu_q, W, var_p


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
    by_size(P.shape[0], PARALLEL_MIN_ROWS, _p2l_serial, _p2l_parallel)(P, Q, N, part)
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
def _pca_serial(Q, nb, out):
    pca_normals_eigh_rows(Q, nb, out, 0, nb.shape[0])


@njit_parallel
def _pca_parallel(Q, nb, out):
    m = nb.shape[0]
    for c in prange(n_chunks(m)):
        pca_normals_eigh_rows(Q, nb, out, c * CHUNK, min(m, (c + 1) * CHUNK))


def pca_normals_kernel(Q, nb):
    """Unit normal (eigenvector of the smallest eigenvalue of the neighbourhood covariance) per row
    of the (m, k) neighbour index array ``nb`` into ``Q``; sign as returned by LAPACK."""
    out = np.empty((nb.shape[0], 3))
    by_size(nb.shape[0], PARALLEL_MIN_ROWS // 4, _pca_serial, _pca_parallel)(Q, nb, out)
    return out


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


@njit
def _p2l_idx_totals(P, Q, N, si, ti):
    """:func:`_p2l_idx_serial` and the partial sums in one call (chunk order from 0.0, as
    ``_add_partials``); ``H`` filled from the upper triangle row by row and mirrored."""
    nc = n_chunks(si.shape[0])
    part = np.zeros((nc, 28))
    _p2l_idx_serial(P, Q, N, si, ti, part)
    return system_from_partials(part)


@njit
def system_from_partials(part):
    """``(H (6, 6), g (6,), cost)`` from chunk partials ``(c, 28)`` (21 upper-triangle entries of
    ``H`` row by row, 6 of ``g``, the cost) added serially in chunk order; ``H`` mirrored."""
    tot = np.zeros(28)
    for c in range(part.shape[0]):
        for k in range(28):
            tot[k] = tot[k] + part[c, k]
    H = np.empty((6, 6))
    k = 0
    for a in range(6):
        for b in range(a, 6):
            H[a, b] = tot[k]
            H[b, a] = tot[k]
            k += 1
    return H, tot[21:27].copy(), tot[27]


@njit
def constraint_system_idx(P, si, N, ti):
    """The inputs of :func:`minegeo.registration.constraint_analysis` on the pairs ``(P[si], N[ti])`` in
    one pass, without gathering them: ``(H, L)`` with ``H = Σ JᵢᵀJᵢ``, ``Jᵢ = [(pᵢ − c) × nᵢ, nᵢ]``
    (6x6, chunked as :func:`_p2l_idx_serial`), ``c`` the centroid of the points, ``nᵢ`` the normal
    scaled to unit length (0 when it is 0) and ``L`` the RMS distance of the points from ``c``
    (metres; ``k = len(si) >= 1``)."""
    k = si.shape[0]
    c0 = 0.0
    c1 = 0.0
    c2 = 0.0
    for i in range(k):
        a_ = si[i]
        c0 += P[a_, 0]
        c1 += P[a_, 1]
        c2 += P[a_, 2]
    c0 /= k
    c1 /= k
    c2 /= k
    ss = 0.0
    for i in range(k):
        a_ = si[i]
        x = P[a_, 0] - c0
        y = P[a_, 1] - c1
        z = P[a_, 2] - c2
        ss += x * x + y * y + z * z
    part = np.zeros((n_chunks(k), 28))
    J = np.empty(6)
    for c in range(part.shape[0]):
        for i in range(c * CHUNK, min(k, (c + 1) * CHUNK)):
            a_ = si[i]
            b_ = ti[i]
            nx = N[b_, 0]
            ny = N[b_, 1]
            nz = N[b_, 2]
            nn = np.sqrt(nx * nx + ny * ny + nz * nz)
            if nn > 0.0:
                nx /= nn
                ny /= nn
                nz /= nn
            else:
                nx = 0.0
                ny = 0.0
                nz = 0.0
            x = P[a_, 0] - c0
            y = P[a_, 1] - c1
            z = P[a_, 2] - c2
            _p2l_add(part, c, J, x, y, z, x, y, z, nx, ny, nz)
    H, _, _ = system_from_partials(part)
    return H, np.sqrt(ss / k)


def point_to_plane_system_idx(P, Q, N, si, ti):
    """:func:`point_to_plane_system_kernel` on the pairs ``(P[si], Q[ti], N[ti])``."""
    H, g, cost = _p2l_idx_totals(P, Q, N, si, ti)
    return H, g, float(cost)


@njit
def _moments_idx_serial(P, Q, si, ti, part1, part2):
    """:func:`_moments_serial` with unit weights on the pairs ``(P[si[i]], Q[ti[i]])``: the same
    per-pair sums (:func:`_moments1_add`, :func:`_moments2_add` with ``wi = 1.0``)."""
    m = si.shape[0]
    nc = part1.shape[0]
    for c in range(nc):
        for i in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            _moments1_add(part1, c, 1.0, P, si[i], Q, ti[i])
    mu_p, mu_q = _means_from_partials(part1)
    for c in range(nc):
        for i in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            _moments2_add(part2, c, 1.0, P, si[i], Q, ti[i], mu_p, mu_q)
    return mu_p, mu_q


@njit
def _moments_idx_totals(P, Q, si, ti):
    """:func:`_moments_idx_serial` and the partial sums of :func:`weighted_moments_idx` in one call:
    the partials are added in chunk order from 0.0 exactly as ``_add_partials`` does."""
    nc = n_chunks(si.shape[0])
    part1 = np.zeros((nc, 7))
    part2 = np.zeros((nc, 10))
    mu_p, mu_q = _moments_idx_serial(P, Q, si, ti, part1, part2)
    sw = 0.0
    tot2 = np.zeros(10)
    for c in range(nc):
        sw = sw + part1[c, 0]
        for k in range(10):
            tot2[k] = tot2[k] + part2[c, k]
    W = np.zeros((3, 3))
    var_p = 0.0
    if sw > 0.0:
        for r in range(3):
            for k in range(3):
                W[r, k] = tot2[3 * r + k] / sw
        var_p = tot2[9] / sw
    return sw, mu_p, mu_q, W, var_p


def weighted_moments_idx(P, Q, si, ti):
    """:func:`weighted_moments_kernel` with unit weights on the pairs ``(P[si], Q[ti])``."""
    sw, mu_p, mu_q, W, var_p = _moments_idx_totals(P, Q, si, ti)
    return float(sw), mu_p, mu_q, W, float(var_p)
