"""Numba kernels of Generalized-ICP (contiguous float64 arrays in, no checks).

The public, validated, documented function is :func:`minegeo.registration.gicp.register_gicp`;
read its docstring (and ``docs/registration_gicp.md``) for the mathematics.

Determinism: every reduction over pairs uses the fixed chunking of
:mod:`minegeo.registration._kernels` (``CHUNK`` consecutive pairs per chunk, partial sums per
chunk, partials added serially in chunk order), so the floating-point summation order depends
only on the number of pairs, never on the number of threads. The serial and the parallel
(``prange`` over chunks) drivers run the same chunk bodies and give bit-identical results.
Per-point maps (covariances) write one row per point and are trivially deterministic.
"""

from __future__ import annotations

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.kernels.chunks import CHUNK, PARALLEL_QUERY_ROWS, by_size, n_chunks
from minegeo.kernels.eig3 import (
    centred_covariance,
    fast_eigen3x3,
    jacobi_min3,
    jacobi_min3_x2,
    pca_normal,
    store_normal,
    store_too_few,
)
from minegeo.kernels.kdtree import (
    kd_boxes,
    kd_build,
    kd_knn_leaf_batch,
    kd_nn2_descend,
    kd_nn_descend,
    kd_nn_warm_parallel,
    kd_nn_warm_serial,
    sq_to_row,
    take_nearest2,
    warm_bound,
)
from minegeo.registration._kernels import (
    _add_partials,
    _transform_parallel,
    _transform_serial,
    system_from_partials,
)
from minegeo.registration._kernels_loop import match_stats

#: Below this many pairs (or search queries) the serial driver is used. Measured on the shared
#: 2-core machine under load (load average ~9): for 10^4 pairs the prange drivers made a whole
#: registration 2x slower than the serial ones (554 ms vs 290 ms; threads wait at the barrier
#: for cores the other processes hold), so threads are kept for large clouds only. Both drivers
#: run the same chunk bodies in the same order: results are bit-identical either way.
PARALLEL_MIN_PAIRS = 1 << 16
#: Below this many points the per-point maps (covariances, normals) run serially.
PARALLEL_MIN_POINTS = 1 << 16

#: A neighbourhood is collinear when ``λ1 <= DEGENERATE_RATIO · λ2`` (as ``geometry.NormalParams``).
DEGENERATE_RATIO = 1e-8

#: Number of accumulated values per chunk: 21 (upper triangle of H) + 6 (g) + 1 (cost).
N_ACC = 28


# ----------------------------------------------------------------------------- covariances


@njit
def _plane_cov_rows(N, isotropic, eps, rodrigues, C, start, end):
    for i in range(start, end):
        for r in range(3):
            for c in range(3):
                C[i, r, c] = 0.0
        if isotropic[i]:
            C[i, 0, 0] = 1.0
            C[i, 1, 1] = 1.0
            C[i, 2, 2] = 1.0
            continue
        nx = N[i, 0]
        ny = N[i, 1]
        nz = N[i, 2]
        if rodrigues:
            # Open3D GetRotationFromE1ToX: v = e1 x n, c = e1 . n, R = I + [v]x + [v]x^2 / (1 + c),
            # identity when c < -0.99; then C = R diag(eps, 1, 1) R^T.
            cth = nx
            R = np.eye(3)
            if not cth < -0.99:
                vx = 0.0
                vy = -nz
                vz = ny
                S = np.zeros((3, 3))
                S[0, 1] = -vz
                S[0, 2] = vy
                S[1, 0] = vz
                S[1, 2] = -vx
                S[2, 0] = -vy
                S[2, 1] = vx
                f = 1.0 / (1.0 + cth)
                S2 = S @ S
                for r in range(3):
                    for c in range(3):
                        R[r, c] = R[r, c] + S[r, c] + S2[r, c] * f
            for r in range(3):
                for c in range(3):
                    C[i, r, c] = eps * R[r, 0] * R[c, 0] + R[r, 1] * R[c, 1] + R[r, 2] * R[c, 2]
        else:
            # Segal 2009 / [Ren2019 Eq. 3] with U = [n, u, v] orthonormal:
            # U diag(eps, 1, 1) U^T = I - (1 - eps) n n^T, with n normalised here.
            s = np.sqrt(nx * nx + ny * ny + nz * nz)
            if s > 0.0:
                nx /= s
                ny /= s
                nz /= s
            n = (nx, ny, nz)
            w = 1.0 - eps
            for r in range(3):
                for c in range(3):
                    C[i, r, c] = (1.0 if r == c else 0.0) - w * n[r] * n[c]


@njit
def _plane_cov_serial(N, isotropic, eps, rodrigues, C):
    _plane_cov_rows(N, isotropic, eps, rodrigues, C, 0, N.shape[0])


@njit_parallel
def _plane_cov_parallel(N, isotropic, eps, rodrigues, C):
    m = N.shape[0]
    for c in prange(n_chunks(m)):
        _plane_cov_rows(N, isotropic, eps, rodrigues, C, c * CHUNK, min(m, (c + 1) * CHUNK))


def plane_covariances_kernel(N, isotropic, eps, rodrigues):
    """(n, 3, 3) plane-like covariances from unit normals ``N`` (n, 3).

    ``rodrigues=False``: ``C = I - (1-eps) n nᵀ`` ([Ren2019 Eq. 3]); ``rodrigues=True``: Open3D's
    ``R diag(eps, 1, 1) Rᵀ`` with its Rodrigues rotation e_x -> n (identity when ``n_x < -0.99``).
    Rows with ``isotropic[i]`` get ``C = I`` (no surface model).
    """
    n = N.shape[0]
    C = np.empty((n, 3, 3))
    by_size(n, PARALLEL_MIN_POINTS, _plane_cov_serial, _plane_cov_parallel)(N, isotropic, float(eps), bool(rodrigues), C)
    return C


# ----------------------------------------------------------------------------- kNN + PCA normals (fused)

#: At most this many consecutive points of one KD-tree leaf share one tree traversal in the
#: covariance kernel (:func:`_knn_normals_rows`).
KNN_BATCH = 16


@njit(inline="always")
def _normal_out(e, qi, ratio, out_n, out_eval, out_status):
    """Row ``qi`` of the outputs of :func:`minegeo.kernels.eig3.pca_normal` (mode "minegeo") from
    ``e`` = :func:`minegeo.kernels.eig3.jacobi_min3`'s answer: unit normal, eigenvalues, status."""
    n0, n1, n2, l0, l1, l2 = e
    nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    n0 /= nn
    n1 /= nn
    n2 /= nn
    store_normal(qi, n0, n1, n2, l0, l1, l2, ratio, False, out_n, out_eval, out_status)


@njit
def _pca_normal_minegeo(points, nbr, cnt, qi, ratio, out_n, out_eval, out_status):
    """:func:`minegeo.kernels.eig3.pca_normal` with ``mode_open3d=False`` (two-pass covariance centred
    on the query point, cyclic Jacobi), bit for bit, with the eigen-solve on scalars
    (:func:`minegeo.kernels.eig3.jacobi_min3`) instead of 3x3 arrays; output row ``qi``."""
    if cnt < 3:
        store_too_few(qi, out_n, out_eval, out_status)
        return
    c = centred_covariance(points, nbr, cnt, qi)
    _normal_out(jacobi_min3(c[0], c[1], c[2], c[3], c[4], c[5]), qi, ratio, out_n, out_eval, out_status)


@njit
def _pca_normal_minegeo_x2(points, nbr_a, cnt_a, qa, nbr_b, cnt_b, qb, ratio, out_n, out_eval, out_status):
    """:func:`_pca_normal_minegeo` of two points, their eigen-solves interleaved
    (:func:`minegeo.kernels.eig3.jacobi_min3_x2`; the same bits)."""
    if cnt_a < 3 or cnt_b < 3:
        _pca_normal_minegeo(points, nbr_a, cnt_a, qa, ratio, out_n, out_eval, out_status)
        _pca_normal_minegeo(points, nbr_b, cnt_b, qb, ratio, out_n, out_eval, out_status)
        return
    ea, eb = jacobi_min3_x2(centred_covariance(points, nbr_a, cnt_a, qa), centred_covariance(points, nbr_b, cnt_b, qb))
    _normal_out(ea, qa, ratio, out_n, out_eval, out_status)
    _normal_out(eb, qb, ratio, out_n, out_eval, out_status)


@njit
def _knn_normals_rows(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status, t0, t1, out_nb, out_rk, box,
                      leaf_at):
    """kNN (:func:`minegeo.kernels.kdtree.kd_knn_leaf_batch`, up to :data:`KNN_BATCH` points of a leaf
    per traversal) and PCA normal (:func:`minegeo.kernels.eig3.pca_normal`'s numbers) of the points at
    tree positions ``t0 .. t1-1`` (leaf order: consecutive queries are neighbours); ``box, leaf_at`` =
    :func:`minegeo.kernels.kdtree.kd_boxes`; ``tree`` the :class:`~minegeo.kernels.kdtree.PackedKDTree` of ``Q``."""
    idx = tree.idx
    end = tree.end
    depth = tree.depth
    bi = np.empty((KNN_BATCH, k), np.int64)
    bs = np.empty((KNN_BATCH, k))
    cnt = np.empty(KNN_BATCH, np.int64)
    wq = np.empty(KNN_BATCH)
    st_node = np.empty(2 * depth + 4, np.int64)
    st_lb = np.empty(2 * depth + 4)
    A = np.empty((3, 3))
    V = np.empty((3, 3))
    w = np.empty(3)
    tmp = np.empty(6)
    m = Q.shape[0]
    a0 = t0
    while a0 < t1:
        L = leaf_at[a0]
        nq = min(end[L], t1, a0 + KNN_BATCH) - a0
        kd_knn_leaf_batch(tree, k, box, L, a0, nq, bi, bs, cnt, wq, st_node, st_lb)
        for q in range(nq):
            i = idx[a0 + q]
            c = cnt[q]
            if out_nb.shape[0] > 0:  # the neighbour list and its radius (gicp_fused_search's shortcut)
                for a in range(c):
                    out_nb[i, a] = bi[q, a]
                out_rk[i] = np.inf if c == m else np.sqrt(bs[q, c - 1])  # all nearer points listed
            if mode_open3d:
                pca_normal(Q, bi[q], c, i, i, True, ratio, A, V, w, tmp, out_n, out_eval, out_status)
        if not mode_open3d:  # two points at a time: their eigen-solves overlap
            for q in range(0, nq - 1, 2):
                _pca_normal_minegeo_x2(Q, bi[q], cnt[q], idx[a0 + q], bi[q + 1], cnt[q + 1], idx[a0 + q + 1], ratio,
                                       out_n, out_eval, out_status)
            if nq % 2 == 1:
                _pca_normal_minegeo(Q, bi[nq - 1], cnt[nq - 1], idx[a0 + nq - 1], ratio, out_n, out_eval, out_status)
        a0 += nq


@njit
def _knn_normals_serial(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status):
    box, leaf_at = kd_boxes(tree)
    _knn_normals_rows(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status, 0, Q.shape[0],
                      np.empty((0, k), np.int64), np.empty(0), box, leaf_at)


@njit_parallel
def _knn_normals_parallel(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status):
    m = Q.shape[0]
    box, leaf_at = kd_boxes(tree)
    for c in prange(n_chunks(m)):
        _knn_normals_rows(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status, c * CHUNK,
                          min(m, (c + 1) * CHUNK), np.empty((0, k), np.int64), np.empty(0), box, leaf_at)


def knn_normals_kernel(Q, tree, k, mode_open3d, ratio=DEGENERATE_RATIO):
    """PCA normal of every point of ``Q`` from its ``k`` nearest points (itself included).

    ``tree`` = :func:`minegeo.kernels.kdtree.kd_build` ``(Q, leaf)`` (a :class:`~minegeo.kernels.kdtree.PackedKDTree`). The PCA is
    :func:`minegeo.kernels.eig3.pca_normal` (as :mod:`minegeo.geometry`'s): mode "open3d" = raw moments + FastEigen3x3 (Open3D 0.20),
    otherwise two-pass centred covariance + Jacobi (for mode "minegeo" the same operations on scalars,
    two points at a time: :func:`_pca_normal_minegeo_x2`, the same bits). The kNN is exact and sorted
    as :func:`~minegeo.kernels.kdtree.kd_knn`'s (:func:`minegeo.kernels.kdtree.kd_knn_leaf_batch`).
    Returns ``(normals, eigenvalues, status)`` with the status codes of :mod:`minegeo.geometry.normals`.
    """
    m = Q.shape[0]
    out_n = np.empty((m, 3))
    out_eval = np.empty((m, 3))
    out_status = np.empty(m, dtype=np.int8)
    kk = min(int(k), m)
    args = (Q, tree, kk, bool(mode_open3d), float(ratio), out_n, out_eval, out_status)
    by_size(m, PARALLEL_MIN_POINTS, _knn_normals_serial, _knn_normals_parallel)(*args)
    return out_n, out_eval, out_status


# ----------------------------------------------------------------------------- GICP normal equations


@njit
def _gicp_chunk(P, Q, Cs, Ct, R, si, ti, part, c, start, end):
    """Accumulate H (upper triangle), g and the Mahalanobis cost of pairs [start, end) into part[c]
    (:func:`_gicp_pair_add` per pair, in pair order)."""
    for k in range(start, end):
        _gicp_pair_add(P, si[k], Q, ti[k], Cs, Ct, R, part, c)


@njit
def _gicp_serial(P, Q, Cs, Ct, R, si, ti, part):
    m = si.shape[0]
    for c in range(part.shape[0]):
        _gicp_chunk(P, Q, Cs, Ct, R, si, ti, part, c, c * CHUNK, min(m, (c + 1) * CHUNK))


@njit_parallel
def _gicp_parallel(P, Q, Cs, Ct, R, si, ti, part):
    m = si.shape[0]
    for c in prange(part.shape[0]):
        _gicp_chunk(P, Q, Cs, Ct, R, si, ti, part, c, c * CHUNK, min(m, (c + 1) * CHUNK))


def gicp_system_kernel(P, Q, Cs, Ct, R, si, ti):
    """GICP Gauss-Newton normal equations on the pairs ``(P[si], Q[ti])``.

    ``P`` are the source points already moved into the target frame by the current transform,
    ``Cs`` the source covariances in the *source* frame and ``R`` the current rotation, so the
    pair covariance is ``M = Ct[ti] + R Cs[si] Rᵀ``. With ``d = p - q``, ``B = M⁻¹`` and
    ``J = [-[p]×, I3]``: returns ``(H = Σ Jᵀ B J (6x6), g = Σ Jᵀ B d (6,), cost = Σ dᵀ B d)``.
    Pairs with ``det M <= 0`` are skipped (impossible for the positive definite covariances
    that the public function admits).
    """
    part = np.zeros((n_chunks(si.shape[0]), N_ACC))
    by_size(si.shape[0], PARALLEL_MIN_PAIRS, _gicp_serial, _gicp_parallel)(P, Q, Cs, Ct, R, si, ti, part)
    tot = _add_partials(part) if part.shape[0] else np.zeros(N_ACC)
    H = np.zeros((6, 6))
    iu = np.triu_indices(6)
    H[iu] = tot[:21]
    H = H + np.triu(H, 1).T
    return H, tot[21:27].copy(), float(tot[27])


# ----------------------------------------------------------------------------- warm-started 1-NN search
# (the kernel is minegeo.kernels.kdtree.kd_nn_warm_rows; this is the allocating wrapper)


def nearest_warm_kernel(P, Q, tree, d2, prev):
    """``(idx, sq)`` of the nearest ``Q`` point with ``sq < d2`` per row of ``P`` (``m``/inf if none).

    ``tree`` is the :class:`~minegeo.kernels.kdtree.PackedKDTree` of ``Q``; ``prev`` (n,)
    int64 holds a candidate partner per row (``m`` = none), typically the previous iteration's
    correspondence.
    """
    n = P.shape[0]
    out_idx = np.empty(n, dtype=np.int64)
    out_sq = np.empty(n)
    by_size(n, PARALLEL_MIN_PAIRS, kd_nn_warm_serial, kd_nn_warm_parallel)(P, Q, tree, float(d2), prev, out_idx, out_sq)
    return out_idx, out_sq


# ----------------------------------------------------------------------------- normals of covariances


@njit
def _min_eigvec_rows(C, sel, out, start, end):
    tmp = np.empty(6)
    for i in range(start, end):
        j = sel[i]
        fast_eigen3x3(C[j, 0, 0], C[j, 0, 1], C[j, 0, 2], C[j, 1, 1], C[j, 1, 2], C[j, 2, 2], tmp)
        out[i, 0] = tmp[0]
        out[i, 1] = tmp[1]
        out[i, 2] = tmp[2]


@njit
def _min_eigvec_serial(C, sel, out):
    _min_eigvec_rows(C, sel, out, 0, sel.shape[0])


@njit_parallel
def _min_eigvec_parallel(C, sel, out):
    m = sel.shape[0]
    for c in prange(n_chunks(m)):
        _min_eigvec_rows(C, sel, out, c * CHUNK, min(m, (c + 1) * CHUNK))


def min_eigvec_kernel(C, sel):
    """Unit eigenvector of the smallest eigenvalue of ``C[sel[i]]`` (closed-form 3x3 solver)."""
    out = np.empty((sel.shape[0], 3))
    by_size(sel.shape[0], PARALLEL_MIN_POINTS, _min_eigvec_serial, _min_eigvec_parallel)(C, sel, out)
    return out


def _warmup() -> None:
    """Compile the kernels of this module on tiny inputs (serial and parallel drivers)."""
    P = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    N = np.tile(np.array([0.0, 0.0, 1.0]), (4, 1))
    iso = np.zeros(4, dtype=np.bool_)
    C = np.empty((4, 3, 3))
    for rod in (False, True):
        _plane_cov_serial(N, iso, 1e-3, rod, C)
        _plane_cov_parallel(N, iso, 1e-3, rod, C)
    idx = np.arange(4, dtype=np.int64)
    R = np.eye(3)
    _gicp_serial(P, P + 0.1, C, C, R, idx, idx, np.zeros((1, N_ACC)))
    _gicp_parallel(P, P + 0.1, C, C, R, idx, idx, np.zeros((1, N_ACC)))
    tree = kd_build(np.vstack([P, P + 2.0, P + 4.0]), 2)
    Q = np.vstack([P, P + 2.0, P + 4.0])
    out_i = np.empty(4, dtype=np.int64)
    out_s = np.empty(4)
    kd_nn_warm_serial(P, Q, tree, 1.0, idx, out_i, out_s)
    kd_nn_warm_parallel(P, Q, tree, 1.0, idx, out_i, out_s)
    for mode in (False, True):
        _knn_normals_serial(Q, tree, 3, mode, DEGENERATE_RATIO, np.empty((12, 3)), np.empty((12, 3)),
                            np.empty(12, dtype=np.int8))
        _knn_normals_parallel(Q, tree, 3, mode, DEGENERATE_RATIO, np.empty((12, 3)), np.empty((12, 3)),
                              np.empty(12, dtype=np.int8))
    out = np.empty((4, 3))
    _min_eigvec_serial(C, idx, out)
    _min_eigvec_parallel(C, idx, out)
    covariances_valid(np.ascontiguousarray(C.reshape(4, 9)), 1e-9)


# GICP kernels. Per pair the arithmetic is that of ``registration._kernels_gicp._gicp_chunk``
# (the same operations in the same order), with the zero and unit entries of ``J = [-[p]x, I3]``
# and the repeated ``Cs Rᵀ`` products left out, which changes no bit of a pair's terms (only the
# sign of an exact zero). Sums: fixed chunks of ``GICP_ROWS`` consecutive rows (source points in
# the fused search, pairs in ``gicp_pairs_system``), partials added serially in chunk order, so
# the bits depend on the number of rows only, never on the thread count.

#: Steps of the walk on the neighbour lists (:func:`_list_nearest`) before the tree is searched.
LIST_HOPS = 3
#: "No neighbour lists" for :func:`gicp_fused_search` (its tree search only).
NO_LISTS = (np.empty((0, 1), np.int64), np.empty(0))
#: Rows per chunk of the GICP sums: 4,661 pairs are 19 chunks that two threads share evenly.
GICP_ROWS = 256
#: Accumulated values per chunk: 21 (upper triangle of H) + 6 (g) + 1 (cost).
GICP_ACC = 28
#: The fused search also finds a row's second-nearest distance (what lets the next search skip
#: the row) only when the row moved less than this since the previous search (m): a row moving
#: faster will move too far next time to be skipped (measured: the first searches from a start
#: 0.5 m / 10 deg off cost 1.6-2.1 ms with the second distance, ~1.2 ms without). Speed only:
#: the answer is the same either way.
GICP_SECOND_STEP_M = 0.1


@njit
def _gicp_pair_add(P, a_, Q, b_, Cs, Ct, R, part, c):
    """Add the terms of pair ``(P[a_], Q[b_])`` to ``part[c]``: ``M = Ct + R Cs Rᵀ``
    ([Ren2019 Eq. 5]), ``B = M⁻¹``, ``d = p - q`` ([Ren2019 Eq. 4]), ``J = [-[p]×, I3]``;
    ``Jᵀ B J`` (upper triangle), ``Jᵀ B d`` and ``dᵀ B d`` ([Ren2019 Eq. 6]). Skipped when
    ``det M <= 0``."""
    # W = Cs R^T, A = R W = R Cs R^T (carried into the target frame)
    w00 = Cs[a_, 0, 0] * R[0, 0] + Cs[a_, 0, 1] * R[0, 1] + Cs[a_, 0, 2] * R[0, 2]
    w01 = Cs[a_, 0, 0] * R[1, 0] + Cs[a_, 0, 1] * R[1, 1] + Cs[a_, 0, 2] * R[1, 2]
    w02 = Cs[a_, 0, 0] * R[2, 0] + Cs[a_, 0, 1] * R[2, 1] + Cs[a_, 0, 2] * R[2, 2]
    w10 = Cs[a_, 1, 0] * R[0, 0] + Cs[a_, 1, 1] * R[0, 1] + Cs[a_, 1, 2] * R[0, 2]
    w11 = Cs[a_, 1, 0] * R[1, 0] + Cs[a_, 1, 1] * R[1, 1] + Cs[a_, 1, 2] * R[1, 2]
    w12 = Cs[a_, 1, 0] * R[2, 0] + Cs[a_, 1, 1] * R[2, 1] + Cs[a_, 1, 2] * R[2, 2]
    w20 = Cs[a_, 2, 0] * R[0, 0] + Cs[a_, 2, 1] * R[0, 1] + Cs[a_, 2, 2] * R[0, 2]
    w21 = Cs[a_, 2, 0] * R[1, 0] + Cs[a_, 2, 1] * R[1, 1] + Cs[a_, 2, 2] * R[1, 2]
    w22 = Cs[a_, 2, 0] * R[2, 0] + Cs[a_, 2, 1] * R[2, 1] + Cs[a_, 2, 2] * R[2, 2]
    a00 = 0.0 + R[0, 0] * w00 + R[0, 1] * w10 + R[0, 2] * w20
    a01 = 0.0 + R[0, 0] * w01 + R[0, 1] * w11 + R[0, 2] * w21
    a02 = 0.0 + R[0, 0] * w02 + R[0, 1] * w12 + R[0, 2] * w22
    a10 = 0.0 + R[1, 0] * w00 + R[1, 1] * w10 + R[1, 2] * w20
    a11 = 0.0 + R[1, 0] * w01 + R[1, 1] * w11 + R[1, 2] * w21
    a12 = 0.0 + R[1, 0] * w02 + R[1, 1] * w12 + R[1, 2] * w22
    a20 = 0.0 + R[2, 0] * w00 + R[2, 1] * w10 + R[2, 2] * w20
    a21 = 0.0 + R[2, 0] * w01 + R[2, 1] * w11 + R[2, 2] * w21
    a22 = 0.0 + R[2, 0] * w02 + R[2, 1] * w12 + R[2, 2] * w22
    # M = Ct + R Cs R^T, symmetrised
    m00 = Ct[b_, 0, 0] + 0.5 * (a00 + a00)
    m01 = Ct[b_, 0, 1] + 0.5 * (a01 + a10)
    m02 = Ct[b_, 0, 2] + 0.5 * (a02 + a20)
    m10 = Ct[b_, 1, 0] + 0.5 * (a10 + a01)
    m11 = Ct[b_, 1, 1] + 0.5 * (a11 + a11)
    m12 = Ct[b_, 1, 2] + 0.5 * (a12 + a21)
    m20 = Ct[b_, 2, 0] + 0.5 * (a20 + a02)
    m21 = Ct[b_, 2, 1] + 0.5 * (a21 + a12)
    m22 = Ct[b_, 2, 2] + 0.5 * (a22 + a22)
    # B = M^-1 by the adjugate (M symmetric positive definite)
    c00 = m11 * m22 - m12 * m21
    c01 = m12 * m20 - m10 * m22
    c02 = m10 * m21 - m11 * m20
    det = m00 * c00 + m01 * c01 + m02 * c02
    if not det > 0.0:
        return
    inv = 1.0 / det
    b00 = c00 * inv
    b10 = c01 * inv
    b20 = c02 * inv
    b01 = (m02 * m21 - m01 * m22) * inv
    b11 = (m00 * m22 - m02 * m20) * inv
    b21 = (m01 * m20 - m00 * m21) * inv
    b02 = (m01 * m12 - m02 * m11) * inv
    b12 = (m02 * m10 - m00 * m12) * inv
    b22 = (m00 * m11 - m01 * m10) * inv
    px = P[a_, 0]
    py = P[a_, 1]
    pz = P[a_, 2]
    dx = px - Q[b_, 0]
    dy = py - Q[b_, 1]
    dz = pz - Q[b_, 2]
    # e = B d; BJ = B J with J = [-[p]x, I3] (columns 3..5 of BJ are B itself)
    e0 = b00 * dx + b01 * dy + b02 * dz
    e1 = b10 * dx + b11 * dy + b12 * dz
    e2 = b20 * dx + b21 * dy + b22 * dz
    q01 = b00 * pz + b02 * -px
    q02 = b00 * -py + b01 * px
    q10 = b11 * -pz + b12 * py
    q11 = b10 * pz + b12 * -px
    q12 = b10 * -py + b11 * px
    q20 = b21 * -pz + b22 * py
    q21 = b20 * pz + b22 * -px
    q22 = b20 * -py + b21 * px
    # H = J^T (B J), upper triangle row by row: (w,w) block, (w,t) block, (t,t) block = B
    part[c, 0] += -pz * q10 + py * q20
    part[c, 1] += -pz * q11 + py * q21
    part[c, 2] += -pz * q12 + py * q22
    part[c, 3] += -pz * b10 + py * b20
    part[c, 4] += -pz * b11 + py * b21
    part[c, 5] += -pz * b12 + py * b22
    part[c, 6] += pz * q01 + -px * q21
    part[c, 7] += pz * q02 + -px * q22
    part[c, 8] += pz * b00 + -px * b20
    part[c, 9] += pz * b01 + -px * b21
    part[c, 10] += pz * b02 + -px * b22
    part[c, 11] += -py * q02 + px * q12
    part[c, 12] += -py * b00 + px * b10
    part[c, 13] += -py * b01 + px * b11
    part[c, 14] += -py * b02 + px * b12
    part[c, 15] += b00
    part[c, 16] += b01
    part[c, 17] += b02
    part[c, 18] += b11
    part[c, 19] += b12
    part[c, 20] += b22
    part[c, 21] += -pz * e1 + py * e2
    part[c, 22] += pz * e0 + -px * e2
    part[c, 23] += -py * e0 + px * e1
    part[c, 24] += e0
    part[c, 25] += e1
    part[c, 26] += e2
    part[c, 27] += dx * e0 + dy * e1 + dz * e2


@njit
def _list_nearest(px, py, pz, Q, nb, rk, j0, d2, tol):
    """Gated nearest neighbour of ``p`` from the target's neighbour lists, when it is certain:
    ``(best, best_j, r2)`` (``best_j = m``: no point within the gate), or ``best_j = -1``.

    ``nb[j]`` holds every target point strictly nearer to ``q_j`` than ``rk[j]``. Starting at the
    previous partner ``j0``, with ``d = |p - q_j|``: the answer (if any) is no farther from ``p``
    than ``q_j`` when ``q_j`` is within the gate, and nearer than the gate ``<= d`` when it is not,
    so it lies within ``2 d`` of ``q_j`` (triangle inequality). So when ``2 d + tol < rk[j]`` (``tol``
    covers rounding) the list of ``j`` holds the answer, and the lexicographic minimum of
    ``(sq, index)`` over it (``sq < d2``) is the tree search's answer, bit for bit. Otherwise the
    walk moves to the list's point nearest to ``p`` (at most :data:`LIST_HOPS` times, only while it
    gets nearer). ``r2`` bounds every other point's distance from below (the list's second
    distance, ``rk[j] - d`` outside it, at most the gate), for the skip test of the next search."""
    m = Q.shape[0]
    k = nb.shape[1]
    j = j0
    sj = sq_to_row(px, py, pz, Q, j)
    for _hop in range(LIST_HOPS + 1):
        dj = np.sqrt(sj)
        if 2.0 * dj + tol < rk[j]:
            best = d2
            best_j = m
            second = d2
            for a in range(k):
                jj = nb[j, a]
                s = sq_to_row(px, py, pz, Q, jj)
                if s < d2:
                    best, best_j, second = take_nearest2(s, jj, best, best_j, second)
            return best, best_j, min(np.sqrt(second), rk[j] - dj)
        # not certain here: walk to the listed point nearest to p
        sn = sj
        jn = j
        for a in range(k):
            jj = nb[j, a]
            s = sq_to_row(px, py, pz, Q, jj)
            if s < sn or (s == sn and jj < jn):
                sn = s
                jn = jj
        if jn == j:
            break
        j = jn
        sj = sn
    return 0.0, -1, 0.0


@njit(inline="always")
def _found(P, i, Q, j, sq, m, Cs, Ct, R, part, c, out_idx, out_sq, r1, moved, last_j):
    """Record the answer ``(sq, j)`` of a full search for row ``i`` of :func:`_gicp_fused_rows`
    (``j = m``: no partner within the gate) and add the pair's terms to ``part[c]``; returns the
    chunk's last partner (``j`` when there is one, else ``last_j``)."""
    moved[i] = 0.0
    out_idx[i] = j
    if j < m:
        r1[i] = np.sqrt(sq)
        out_sq[i] = sq
        _gicp_pair_add(P, i, Q, j, Cs, Ct, R, part, c)
        return j
    r1[i] = np.inf
    out_sq[i] = np.inf
    return last_j


@njit
def _gicp_fused_rows(P, Q, tree, d2, warm, Cs, Ct, R, out_idx, out_sq, part, P_old, r1, r2, moved, c0, c1, nb, rk):
    """Chunks ``c0 .. c1-1`` (``GICP_ROWS`` rows each) of :func:`gicp_fused_search`."""
    m = tree.idx.shape[0]
    n = P.shape[0]
    st_node = np.empty(tree.depth + 2, np.int64)
    st_lb = np.empty(tree.depth + 2)
    keep = P_old.shape[0] == n
    for c in range(c0, c1):
        last_j = m  # the last partner found in this chunk: where a row without a partner starts its list walk
        for i in range(c * GICP_ROWS, min(n, (c + 1) * GICP_ROWS)):
            px = P[i, 0]
            py = P[i, 1]
            pz = P[i, 2]
            j0 = warm[i]
            # the first search finds the second distance only without lists (with them, the next
            # search takes most rows from the lists, which need no second distance)
            want_second = nb.shape[0] == 0
            if keep:
                ex = px - P_old[i, 0]
                ey = py - P_old[i, 1]
                ez = pz - P_old[i, 2]
                step = np.sqrt(ex * ex + ey * ey + ez * ez)
                # a row still moving fast will not be skipped next time: the plain 1-NN suffices
                want_second = step < GICP_SECOND_STEP_M
            if keep and j0 < m:
                # the partner stays the nearest point while no other can have come closer:
                # |p' - q_j| >= r2 - D > r1 + D >= |p' - q_j0| (triangle inequality, D = path since
                # the last full search; the margin covers the rounding of r1, r2 and D)
                moved[i] += step
                tol = 1e-9 * (1.0 + abs(px) + abs(py) + abs(pz))
                if r2[i] - moved[i] > r1[i] + moved[i] + tol:
                    sq0 = sq_to_row(px, py, pz, Q, j0)
                    if sq0 < d2:
                        last_j = j0
                        out_idx[i] = j0
                        out_sq[i] = sq0
                        _gicp_pair_add(P, i, Q, j0, Cs, Ct, R, part, c)
                    else:
                        out_idx[i] = m
                        out_sq[i] = np.inf
                    continue
            js = j0 if j0 < m else last_j  # any target point is a valid start (the answer is certified)
            if js < m and nb.shape[0] > 0:  # the neighbour lists, when they must hold the answer
                tol = 1e-9 * (1.0 + abs(px) + abs(py) + abs(pz))
                lb, lj, lr2 = _list_nearest(px, py, pz, Q, nb, rk, js, d2, tol)
                if lj >= 0:
                    if lj < m:
                        r2[i] = lr2
                    last_j = _found(P, i, Q, lj, lb, m, Cs, Ct, R, part, c, out_idx, out_sq, r1, moved, last_j)
                    continue
            best, best_j = warm_bound(px, py, pz, Q, j0, d2, m)
            if want_second:
                best, best_j, second = kd_nn2_descend(px, py, pz, best, best_j, tree, d2, st_node, st_lb)
                r2[i] = np.sqrt(second)
            else:
                best, best_j = kd_nn_descend(px, py, pz, best, best_j, tree, d2, st_node, st_lb)
                r2[i] = -1.0  # unknown: no skip next time
            last_j = _found(P, i, Q, best_j, best, m, Cs, Ct, R, part, c, out_idx, out_sq, r1, moved, last_j)


@njit
def _gicp_fused_serial(P, Q, tree, d2, warm, Cs, Ct, R, out_idx, out_sq, part, P_old, r1, r2, moved, nb, rk):
    _gicp_fused_rows(P, Q, tree, d2, warm, Cs, Ct, R, out_idx, out_sq, part, P_old, r1, r2, moved, 0, part.shape[0],
                     nb, rk)


@njit_parallel
def _gicp_fused_parallel(P, Q, tree, d2, warm, Cs, Ct, R, out_idx, out_sq, part, P_old, r1, r2, moved, nb, rk):
    for c in prange(part.shape[0]):
        _gicp_fused_rows(P, Q, tree, d2, warm, Cs, Ct, R, out_idx, out_sq, part, P_old, r1, r2, moved, c, c + 1, nb, rk)


def gicp_fused_search(P, Q, tree, d2, warm, Cs, Ct, R, parallel, state=None, lists=None):
    """Gated nearest neighbour of every row of ``P`` and the GICP system of the pairs, in one pass.

    ``P`` (n, 3) are the source points moved by the current pose (rotation ``R``), ``tree`` the
    :class:`~minegeo.kernels.kdtree.PackedKDTree` of ``Q``, ``warm`` (n,) the previous partners
    (``m`` = none). Returns ``(idx, sq, H, g, cost)``: per row the partner (``m`` when none
    within ``sq < d2``) and its squared distance (``inf`` when none), as
    :func:`~minegeo.kernels.kdtree.kd_nn_warm_serial`; ``H = Σ Jᵀ M⁻¹ J``, ``g = Σ Jᵀ M⁻¹ d``,
    ``cost = Σ dᵀ M⁻¹ d`` over the pairs ([Ren2019 Eqs. 4-6]). ``parallel`` runs the chunks in
    ``prange`` (the same bits).

    ``state`` = ``(P_old, r1, r2, moved)`` of the previous call on the same rows (``warm`` its
    partners) skips the tree for a row whose partner is certainly still its nearest point: the
    last full search found the partner at ``r1`` and every other point at ``>= r2``, the row has
    moved by ``moved`` since, and ``r2 - moved > r1 + moved``. The answer is that of the full
    search, bit for bit. ``r1``, ``r2``, ``moved`` (n,) are updated in place; an empty ``P_old``
    searches every row.

    ``lists`` = ``(nb (m, k), rk (m,))``: every target point's ``k`` nearest target points and
    the distance of the last (:func:`knn_normals_tasks`). A row whose previous partner ``j0`` is
    within ``rk[j0] / 2`` takes its partner from ``nb[j0]`` instead of the tree
    (:func:`_list_nearest`): the same answer, bit for bit.
    """
    n = P.shape[0]
    out_idx = np.empty(n, dtype=np.int64)
    out_sq = np.empty(n)
    part = np.zeros(((n + GICP_ROWS - 1) // GICP_ROWS, GICP_ACC))
    if state is None:
        state = (np.empty((0, 3)), np.empty(n), np.empty(n), np.zeros(n))
    if lists is None:
        lists = NO_LISTS
    drive = _gicp_fused_parallel if parallel else _gicp_fused_serial
    drive(P, Q, tree, float(d2), warm, Cs, Ct, R, out_idx, out_sq, part, *state, *lists)
    H, g, cost = system_from_partials(part)
    return out_idx, out_sq, H, g, float(cost)


@njit
def _gicp_pairs_rows(P, Q, Cs, Ct, R, si, ti, part, c0, c1):
    k = si.shape[0]
    for c in range(c0, c1):
        for r in range(c * GICP_ROWS, min(k, (c + 1) * GICP_ROWS)):
            _gicp_pair_add(P, si[r], Q, ti[r], Cs, Ct, R, part, c)


@njit_parallel
def _gicp_pairs_parallel(P, Q, Cs, Ct, R, si, ti, part):
    for c in prange(part.shape[0]):
        _gicp_pairs_rows(P, Q, Cs, Ct, R, si, ti, part, c, c + 1)


def gicp_pairs_system(P, Q, Cs, Ct, R, si, ti):
    """``(H, g, cost)`` of :func:`gicp_fused_search` on given pairs ``(P[si], Q[ti])``: the same
    bits as the fused pass when the pairs are every row of ``P`` with a partner, in row order
    and the rows all have one (each chunk holds ``GICP_ROWS`` pairs here, ``GICP_ROWS`` source
    rows there)."""
    part = np.zeros(((si.shape[0] + GICP_ROWS - 1) // GICP_ROWS, GICP_ACC))
    if si.shape[0] >= PARALLEL_QUERY_ROWS:
        _gicp_pairs_parallel(P, Q, Cs, Ct, R, si, ti, part)
    else:
        _gicp_pairs_rows(P, Q, Cs, Ct, R, si, ti, part, 0, part.shape[0])
    H, g, cost = system_from_partials(part)
    return H, g, float(cost)


@njit_parallel
def knn_normals_tasks(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status, out_nb, out_rk):
    """``_knn_normals_rows`` in ``prange`` over ``GICP_ROWS``-point tasks (leaf order;
    one row per point, so any split gives the same bits); ``out_nb`` (m, k) / ``out_rk`` (m,)
    receive each point's neighbour list and the distance of its last neighbour (empty: not kept)."""
    m = Q.shape[0]
    box, leaf_at = kd_boxes(tree)
    for c in prange((m + GICP_ROWS - 1) // GICP_ROWS):
        _knn_normals_rows(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status, c * GICP_ROWS,
                          min(m, (c + 1) * GICP_ROWS), out_nb, out_rk, box, leaf_at)


@njit_parallel
def knn_normals_pair_tasks(QA, treeA, kA, QB, treeB, kB, mode_open3d, ratio, nA, eA, sA, nbA, rkA, nB, eB, sB, nbB,
                           rkB):
    """:func:`knn_normals_tasks` of two clouds in one ``prange`` region (the tasks of A, then those
    of B): both clouds' normals on the Numba threads at once, with no Python thread beside them
    (which would compete with the threads of the last ``prange`` region while they spin). Per-row
    outputs: the bits of one cloud at a time."""
    ta = (QA.shape[0] + GICP_ROWS - 1) // GICP_ROWS
    tb = (QB.shape[0] + GICP_ROWS - 1) // GICP_ROWS
    boxA, leafA = kd_boxes(treeA)
    boxB, leafB = kd_boxes(treeB)
    for c in prange(ta + tb):
        if c < ta:
            _knn_normals_rows(QA, treeA, kA, mode_open3d, ratio, nA, eA, sA, c * GICP_ROWS,
                              min(QA.shape[0], (c + 1) * GICP_ROWS), nbA, rkA, boxA, leafA)
        else:
            cb = c - ta
            _knn_normals_rows(QB, treeB, kB, mode_open3d, ratio, nB, eB, sB, cb * GICP_ROWS,
                              min(QB.shape[0], (cb + 1) * GICP_ROWS), nbB, rkB, boxB, leafB)


@njit
def knn_normals_lists_serial(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status, out_nb, out_rk):
    """:func:`knn_normals_tasks` without ``prange``."""
    box, leaf_at = kd_boxes(tree)
    _knn_normals_rows(Q, tree, k, mode_open3d, ratio, out_n, out_eval, out_status, 0, Q.shape[0], out_nb, out_rk, box,
                      leaf_at)


# ----------------------------------------------------------------------------- checks of given covariances


@njit
def covariances_valid(f, rtol):
    """True when every row of ``f`` (n, 9) (row-major 3x3 matrices) is finite, symmetric to
    ``rtol`` times its largest absolute entry and positive definite by Sylvester's criterion
    (``a00 > 0``, ``a00 a11 - a01² > 0``, ``det > 0``): the checks of
    ``registration.gicp._as_covariances``, with the same arithmetic, in one pass. False sends the
    caller to its NumPy checks, which name the failing rows."""
    for i in range(f.shape[0]):
        scale = 0.0
        for c in range(9):
            v = f[i, c]
            if not np.isfinite(v):
                return False
            if abs(v) > scale:
                scale = abs(v)
        asym = max(max(abs(f[i, 1] - f[i, 3]), abs(f[i, 2] - f[i, 6])), abs(f[i, 5] - f[i, 7]))
        if asym > rtol * max(scale, 1e-300):
            return False
        a00 = f[i, 0]
        a01 = f[i, 1]
        a02 = f[i, 2]
        a11 = f[i, 4]
        a12 = f[i, 5]
        a22 = f[i, 8]
        m2 = a00 * a11 - a01 * a01
        m3 = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
        if not (a00 > 0 and m2 > 0 and m3 > 0):
            return False
    return True


# ----------------------------------------------------------------------------- the whole GICP loop (step test)
# The default GICP loop (``convergence="step"``) in one kernel: the same sequence as
# ``registration.loop.run_loop`` with ``GICPNearestInGate`` / ``GICPFactor`` / ``SE3Euler`` and the
# step and 2-cycle tests, without a return to Python per iteration. Its 6x6 solve, Euler matrix and
# pose products are compiled (LAPACK through Numba, libm cos/sin, explicit 3x3/4x4 products), so its
# bits may differ from the Python loop's (NumPy/BLAS) in the last place; the pairs, the fixed-chunk
# sums and the search are the same kernels.

#: ``gicp_step_loop`` stop codes: budget ran out, step test held, 2-cycle of correspondence sets.
LOOP_NONE = 0
LOOP_STEP = 1
LOOP_CYCLE = 2


@njit
def _solve6(H, g, out):
    """``H x = -g`` as :func:`minegeo.registration.loop.solve_normal_equations` (eigenvalues of ``H``;
    ``solve`` when the smallest exceeds 1e-12 of the largest, else the minimum-norm step); ``x`` into
    ``out``, returns ``singular``."""
    for a in range(6):
        for b in range(6):
            if not np.isfinite(H[a, b]):
                out[:] = 0.0
                return True
    ev, V = np.linalg.eigh(H)
    if not ev[-1] > 0.0:
        out[:] = 0.0
        return True
    if ev[0] > 1e-12 * ev[-1]:
        x = np.linalg.solve(H, -g)
        out[:] = x
        return False
    for a in range(6):
        out[a] = 0.0
    for j in range(6):
        if ev[j] > 1e-12 * ev[-1]:
            s = 0.0
            for a in range(6):
                s += V[a, j] * g[a]
            s = s * (1.0 / (ev[j] if ev[j] > 0 else 1.0))
            for a in range(6):
                out[a] -= V[a, j] * s
    return True


@njit
def _euler6_transform(x, D):
    """Open3D's ``TransformVector6dToMatrix4d``: ``D = [[R_z(x2) R_y(x1) R_x(x0), x[3:]], [0, 1]]``."""
    cx = np.cos(x[0])
    sx = np.sin(x[0])
    cy = np.cos(x[1])
    sy = np.sin(x[1])
    cz = np.cos(x[2])
    sz = np.sin(x[2])
    # R_z R_y, then (R_z R_y) R_x
    a00 = cz * cy
    a01 = -sz
    a02 = cz * sy
    a10 = sz * cy
    a11 = cz
    a12 = sz * sy
    a20 = -sy
    a21 = 0.0
    a22 = cy
    D[0, 0] = a00
    D[0, 1] = a01 * cx + a02 * sx
    D[0, 2] = -a01 * sx + a02 * cx
    D[1, 0] = a10
    D[1, 1] = a11 * cx + a12 * sx
    D[1, 2] = -a11 * sx + a12 * cx
    D[2, 0] = a20
    D[2, 1] = a21 * cx + a22 * sx
    D[2, 2] = -a21 * sx + a22 * cx
    D[0, 3] = x[3]
    D[1, 3] = x[4]
    D[2, 3] = x[5]
    D[3, 0] = 0.0
    D[3, 1] = 0.0
    D[3, 2] = 0.0
    D[3, 3] = 1.0


@njit
def _compose4(D, T):
    """``D @ T`` (4x4), sums in index order."""
    out = np.empty((4, 4))
    for r in range(4):
        for c in range(4):
            out[r, c] = D[r, 0] * T[0, c] + D[r, 1] * T[1, c] + D[r, 2] * T[2, c] + D[r, 3] * T[3, c]
    return out


@njit
def _step_below(D, step_t, step_r):
    """The step test of ``SE3Euler.step_below``: ``|Δt| < step_t`` and ``angle(ΔR) < step_r``, the
    angle as ``atan2(|v|/2, (tr ΔR - 1)/2)``."""
    tn = np.sqrt(D[0, 3] * D[0, 3] + D[1, 3] * D[1, 3] + D[2, 3] * D[2, 3])
    if not tn < step_t:
        return False
    v0 = D[2, 1] - D[1, 2]
    v1 = D[0, 2] - D[2, 0]
    v2 = D[1, 0] - D[0, 1]
    ang = np.arctan2(0.5 * np.sqrt(v0 * v0 + v1 * v1 + v2 * v2), 0.5 * (D[0, 0] + D[1, 1] + D[2, 2] - 1.0))
    return ang < step_r


@njit
def _loop_search(P, Q, tree, d2, warm, Cs, Ct, T, parallel, P_old, r1, r2, moved, nb, rk):
    """One fused search + sums at the pose ``T`` (:func:`gicp_fused_search` inside a kernel)."""
    n = P.shape[0]
    out_idx = np.empty(n, dtype=np.int64)
    out_sq = np.empty(n)
    part = np.zeros(((n + GICP_ROWS - 1) // GICP_ROWS, GICP_ACC))
    R = np.ascontiguousarray(T[:3, :3])
    if parallel:
        _gicp_fused_parallel(P, Q, tree, d2, warm, Cs, Ct, R, out_idx, out_sq, part, P_old, r1, r2, moved, nb, rk)
    else:
        _gicp_fused_serial(P, Q, tree, d2, warm, Cs, Ct, R, out_idx, out_sq, part, P_old, r1, r2, moved, nb, rk)
    H, g, cost = system_from_partials(part)
    return out_idx, out_sq, H, g, cost


@njit
def _move(P, D, parallel):
    out = np.empty((P.shape[0], 3))
    if parallel:
        _transform_parallel(P, D, out)
    else:
        _transform_serial(P, D, out)
    return out


@njit
def gicp_step_loop(P, Q, tree, d2, Cs, Ct, T0, max_iterations, step_t, step_r, stop_on_cycle, parallel, parallel_move,
                   hist, nb, rk):
    """The GICP registration loop with the step test (see the comment above this block).

    ``P`` (n, 3) are the source points moved by ``T0`` (the 4x4 initial ``T_target_source``),
    ``tree`` the :class:`~minegeo.kernels.kdtree.PackedKDTree` of ``Q``, ``d2`` the squared
    gate, ``Cs``/``Ct`` the covariances in their own frames. Per iteration: the Gauss-Newton step of
    the current pairs ([Ren2019 Eq. 6], ``H x = -g`` by :func:`_solve6`; the identity without pairs),
    ``T ← ΔT T``, ``P ← ΔT P``, the fused search + sums at the new pose, then the step test (``|Δt|
    < step_t`` and ``angle(ΔR) < step_r``) and, with ``stop_on_cycle``, the 2-cycle test (partners
    equal to those of two searches before and not to the last; the state of lower mean Mahalanobis
    cost of the two is kept). ``hist`` (max_iterations + 2, 2) receives ``(fitness, rmse)`` per
    search; ``nb``, ``rk``: the target's neighbour lists of :func:`gicp_fused_search` (empty: none).

    Returns ``(T, P, partners (n,), sq (n,), H, g, cost, iterations, stop code, singular,
    cycle ΔT, history length)``; ``H, g, cost`` are the sums of the returned pairs at ``T``.
    """
    n = P.shape[0]
    m = Q.shape[0]
    T = T0.copy()
    P_old = np.empty((0, 3))
    r1 = np.empty(n)
    r2 = np.empty(n)
    moved = np.zeros(n)
    warm = np.full(n, m, dtype=np.int64)
    cur_i, cur_sq, H, g, cost = _loop_search(P, Q, tree, d2, warm, Cs, Ct, T, parallel, P_old, r1, r2, moved, nb, rk)
    k, total = match_stats(cur_i, cur_sq, m)
    nh = 0
    hist[nh, 0] = k / n if k > 0 else 0.0
    hist[nh, 1] = np.sqrt(total / k) if k > 0 else 0.0
    nh += 1
    prev_i = cur_i
    prev2_i = cur_i
    have_prev = False
    prev_sq = cur_sq
    prev_H = H
    prev_g = g
    prev_cost = cost
    prev_k = k
    iterations = 0
    reason = LOOP_NONE
    singular = False
    cycle_delta = np.eye(4)
    D = np.eye(4)
    x = np.zeros(6)
    for _it in range(max_iterations):
        if k == 0:
            D = np.eye(4)
        else:
            singular |= _solve6(H, g, x)
            D = np.empty((4, 4))
            _euler6_transform(x, D)
        T_before = T
        P_before = P
        T = _compose4(D, T)
        P_old = P
        P = _move(P, D, parallel_move)
        iterations += 1
        have_prev2 = have_prev
        prev2_i = prev_i
        prev_i, prev_sq, prev_H, prev_g, prev_cost, prev_k = cur_i, cur_sq, H, g, cost, k
        have_prev = True
        cur_i, cur_sq, H, g, cost = _loop_search(P, Q, tree, d2, prev_i, Cs, Ct, T, parallel, P_old, r1, r2, moved, nb,
                                                rk)
        k, total = match_stats(cur_i, cur_sq, m)
        hist[nh, 0] = k / n if k > 0 else 0.0
        hist[nh, 1] = np.sqrt(total / k) if k > 0 else 0.0
        nh += 1
        if _step_below(D, step_t, step_r):
            reason = LOOP_STEP
            break
        if stop_on_cycle and have_prev2 and np.array_equal(cur_i, prev2_i) and not np.array_equal(cur_i, prev_i):
            reason = LOOP_CYCLE
            cycle_delta = D
            mean_prev = prev_cost / prev_k if prev_k > 0 else np.inf
            mean_cur = cost / k if k > 0 else np.inf
            if mean_prev < mean_cur:
                T = T_before
                P = P_before
                cur_i, cur_sq, H, g, cost, k = prev_i, prev_sq, prev_H, prev_g, prev_cost, prev_k
                hist[nh, 0] = hist[nh - 2, 0]
                hist[nh, 1] = hist[nh - 2, 1]
                nh += 1
            break
    return T, P, cur_i, cur_sq, H, g, cost, iterations, reason, singular, cycle_delta, nh
