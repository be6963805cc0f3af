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
from minegeo.kernels.chunks import CHUNK, PARALLEL_QUERY_ROWS, n_chunks
from minegeo.kernels.eig3 import fast_eigen3x3, pca_normal
from minegeo.kernels.kdtree import (
    _sq_to,
    kd_build,
    kd_knn_one,
    kd_nn2_descend,
    kd_nn_descend,
    kd_nn_warm_parallel,
    kd_nn_warm_serial,
)
from minegeo.registration._kernels import _add_partials, system_from_partials

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
    if n >= PARALLEL_MIN_POINTS:
        _plane_cov_parallel(N, isotropic, float(eps), bool(rodrigues), C)
    else:
        _plane_cov_serial(N, isotropic, float(eps), bool(rodrigues), C)
    return C


# ----------------------------------------------------------------------------- kNN + PCA normals (fused)


@njit
def _knn_normals_rows(Q, idx, Qs, start, end, dim, split, left, right, depth, k, mode_open3d, ratio,
                      out_n, out_eval, out_status, t0, t1):
    bi = np.empty(k, np.int64)
    bs = np.empty(k)
    st_node = np.empty(depth + 2, np.int64)
    st_lb = np.empty(depth + 2)
    A = np.empty((3, 3))
    V = np.empty((3, 3))
    w = np.empty(3)
    tmp = np.empty(6)
    for t in range(t0, t1):
        i = idx[t]  # leaf order: consecutive queries are neighbours (cache locality)
        cnt = kd_knn_one(Q[i, 0], Q[i, 1], Q[i, 2], idx, Qs, start, end, dim, split, left, right, k,
                       bi, bs, st_node, st_lb)
        pca_normal(Q, bi, cnt, i, i, mode_open3d, ratio, A, V, w, tmp, out_n, out_eval, out_status)


@njit
def _knn_normals_serial(Q, idx, Qs, start, end, dim, split, left, right, depth, k, mode_open3d, ratio,
                        out_n, out_eval, out_status):
    _knn_normals_rows(Q, idx, Qs, start, end, dim, split, left, right, depth, k, mode_open3d, ratio,
                      out_n, out_eval, out_status, 0, Q.shape[0])


@njit_parallel
def _knn_normals_parallel(Q, idx, Qs, start, end, dim, split, left, right, depth, k, mode_open3d, ratio,
                          out_n, out_eval, out_status):
    m = Q.shape[0]
    for c in prange(n_chunks(m)):
        _knn_normals_rows(Q, idx, Qs, start, end, dim, split, left, right, depth, k, mode_open3d, ratio,
                          out_n, out_eval, out_status, c * CHUNK, min(m, (c + 1) * CHUNK))


def knn_normals_kernel(Q, tree, k, mode_open3d, ratio=DEGENERATE_RATIO):
    """PCA normal of every point of ``Q`` from its ``k`` nearest points (itself included).

    ``tree`` = :func:`minegeo.kernels.kdtree.kd_build` ``(Q, leaf)``. The PCA is
    :func:`minegeo.kernels.eig3.pca_normal` (as :mod:`minegeo.geometry`'s): mode "open3d" = raw moments + FastEigen3x3 (Open3D 0.20),
    otherwise two-pass centred covariance + Jacobi. Returns ``(normals, eigenvalues, status)``
    with the status codes of :mod:`minegeo.geometry.normals`.
    """
    m = Q.shape[0]
    out_n = np.empty((m, 3))
    out_eval = np.empty((m, 3))
    out_status = np.empty(m, dtype=np.int8)
    kk = min(int(k), m)
    args = (Q, *tree, kk, bool(mode_open3d), float(ratio), out_n, out_eval, out_status)
    if m >= PARALLEL_MIN_POINTS:
        _knn_normals_parallel(*args)
    else:
        _knn_normals_serial(*args)
    return out_n, out_eval, out_status


# ----------------------------------------------------------------------------- GICP normal equations


@njit
def _gicp_chunk(P, Q, Cs, Ct, R, si, ti, part, c, start, end):
    """Accumulate H (upper triangle), g and the Mahalanobis cost of pairs [start, end) into part[c]."""
    A = np.empty((3, 3))
    M = np.empty((3, 3))
    B = np.empty((3, 3))
    J = np.empty((3, 6))
    BJ = np.empty((3, 6))
    e = np.empty(3)
    for k in range(start, end):
        a_ = si[k]
        b_ = ti[k]
        # A = R Cs R^T (source covariance carried into the target frame, [Ren2019 Eq. 5])
        for r in range(3):
            for cc in range(3):
                s = 0.0
                for u in range(3):
                    s += R[r, u] * (Cs[a_, u, 0] * R[cc, 0] + Cs[a_, u, 1] * R[cc, 1]
                                    + Cs[a_, u, 2] * R[cc, 2])
                A[r, cc] = s
        # M = Ct + R Cs R^T, symmetrised
        for r in range(3):
            for cc in range(3):
                M[r, cc] = Ct[b_, r, cc] + 0.5 * (A[r, cc] + A[cc, r])
        # B = M^-1 by the adjugate (M symmetric positive definite)
        c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
        c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
        c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
        det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
        if not det > 0.0:
            continue
        inv = 1.0 / det
        B[0, 0] = c00 * inv
        B[1, 0] = c01 * inv
        B[2, 0] = c02 * inv
        B[0, 1] = (M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2]) * inv
        B[1, 1] = (M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]) * inv
        B[2, 1] = (M[0, 1] * M[2, 0] - M[0, 0] * M[2, 1]) * inv
        B[0, 2] = (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]) * inv
        B[1, 2] = (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) * inv
        B[2, 2] = (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) * inv
        px = P[a_, 0]
        py = P[a_, 1]
        pz = P[a_, 2]
        dx = px - Q[b_, 0]
        dy = py - Q[b_, 1]
        dz = pz - Q[b_, 2]
        # J = [-[p]x, I3]  (left perturbation of T p, Open3D / Segal)
        J[0, 0] = 0.0
        J[0, 1] = pz
        J[0, 2] = -py
        J[1, 0] = -pz
        J[1, 1] = 0.0
        J[1, 2] = px
        J[2, 0] = py
        J[2, 1] = -px
        J[2, 2] = 0.0
        for r in range(3):
            for cc in range(3):
                J[r, 3 + cc] = 1.0 if r == cc else 0.0
        for r in range(3):
            e[r] = B[r, 0] * dx + B[r, 1] * dy + B[r, 2] * dz
            for cc in range(6):
                BJ[r, cc] = B[r, 0] * J[0, cc] + B[r, 1] * J[1, cc] + B[r, 2] * J[2, cc]
        idx = 0
        for a in range(6):
            for b in range(a, 6):
                part[c, idx] += J[0, a] * BJ[0, b] + J[1, a] * BJ[1, b] + J[2, a] * BJ[2, b]
                idx += 1
        for a in range(6):
            part[c, 21 + a] += J[0, a] * e[0] + J[1, a] * e[1] + J[2, a] * e[2]
        part[c, 27] += dx * e[0] + dy * e[1] + dz * e[2]


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
    if si.shape[0] >= PARALLEL_MIN_PAIRS:
        _gicp_parallel(P, Q, Cs, Ct, R, si, ti, part)
    else:
        _gicp_serial(P, Q, Cs, Ct, R, si, ti, part)
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

    ``tree`` is the tuple of :func:`minegeo.kernels.kdtree.kd_build` ``(Q, leaf)``; ``prev`` (n,)
    int64 holds a candidate partner per row (``m`` = none), typically the previous iteration's
    correspondence.
    """
    n = P.shape[0]
    out_idx = np.empty(n, dtype=np.int64)
    out_sq = np.empty(n)
    if n >= PARALLEL_MIN_PAIRS:
        kd_nn_warm_parallel(P, Q, *tree, float(d2), prev, out_idx, out_sq)
    else:
        kd_nn_warm_serial(P, Q, *tree, float(d2), prev, out_idx, out_sq)
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
    if sel.shape[0] >= PARALLEL_MIN_POINTS:
        _min_eigvec_parallel(C, sel, out)
    else:
        _min_eigvec_serial(C, sel, out)
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
    kd_nn_warm_serial(P, Q, *tree, 1.0, idx, out_i, out_s)
    kd_nn_warm_parallel(P, Q, *tree, 1.0, idx, out_i, out_s)
    for mode in (False, True):
        _knn_normals_serial(Q, *tree, 3, mode, DEGENERATE_RATIO, np.empty((12, 3)), np.empty((12, 3)),
                            np.empty(12, dtype=np.int8))
        _knn_normals_parallel(Q, *tree, 3, mode, DEGENERATE_RATIO, np.empty((12, 3)), np.empty((12, 3)),
                              np.empty(12, dtype=np.int8))
    out = np.empty((4, 3))
    _min_eigvec_serial(C, idx, out)
    _min_eigvec_parallel(C, idx, out)


# GICP kernels. Per pair the arithmetic is that of ``registration._kernels_gicp._gicp_chunk``
# (the same operations in the same order), with the zero and unit entries of ``J = [-[p]x, I3]``
# and the repeated ``Cs Rᵀ`` products left out, which changes no bit of a pair's terms (only the
# sign of an exact zero). Sums: fixed chunks of ``GICP_ROWS`` consecutive rows (source points in
# the fused search, pairs in ``gicp_pairs_system``), partials added serially in chunk order, so
# the bits depend on the number of rows only, never on the thread count.

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
def _gicp_fused_rows(P, Q, idx, Qs, start, end, dim, split, left, right, depth, d2, warm, Cs, Ct, R,
                     out_idx, out_sq, part, P_old, r1, r2, moved, c0, c1):
    """Chunks ``c0 .. c1-1`` (``GICP_ROWS`` rows each) of :func:`gicp_fused_search`."""
    m = idx.shape[0]
    n = P.shape[0]
    st_node = np.empty(depth + 2, np.int64)
    st_lb = np.empty(depth + 2)
    keep = P_old.shape[0] == n
    for c in range(c0, c1):
        for i in range(c * GICP_ROWS, min(n, (c + 1) * GICP_ROWS)):
            px = P[i, 0]
            py = P[i, 1]
            pz = P[i, 2]
            j0 = warm[i]
            want_second = True
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
                    sq0 = _sq_to(px, py, pz, Q, j0)
                    if sq0 < d2:
                        out_idx[i] = j0
                        out_sq[i] = sq0
                        _gicp_pair_add(P, i, Q, j0, Cs, Ct, R, part, c)
                    else:
                        out_idx[i] = m
                        out_sq[i] = np.inf
                    continue
            best = d2
            best_j = m
            if j0 < m:
                sq0 = _sq_to(px, py, pz, Q, j0)
                if sq0 < d2:
                    best = sq0
                    best_j = j0
            if want_second:
                best, best_j, second = kd_nn2_descend(px, py, pz, best, best_j, idx, Qs, start, end, dim, split,
                                                      left, right, d2, st_node, st_lb)
                r2[i] = np.sqrt(second)
            else:
                best, best_j = kd_nn_descend(px, py, pz, best, best_j, idx, Qs, start, end, dim, split, left, right,
                                             d2, st_node, st_lb)
                r2[i] = -1.0  # unknown: no skip next time
            moved[i] = 0.0
            out_idx[i] = best_j
            if best_j < m:
                r1[i] = np.sqrt(best)
                out_sq[i] = best
                _gicp_pair_add(P, i, Q, best_j, Cs, Ct, R, part, c)
            else:
                r1[i] = np.inf
                out_sq[i] = np.inf


@njit
def _gicp_fused_serial(P, Q, idx, Qs, start, end, dim, split, left, right, depth, d2, warm, Cs, Ct, R,
                       out_idx, out_sq, part, P_old, r1, r2, moved):
    _gicp_fused_rows(P, Q, idx, Qs, start, end, dim, split, left, right, depth, d2, warm, Cs, Ct, R,
                     out_idx, out_sq, part, P_old, r1, r2, moved, 0, part.shape[0])


@njit_parallel
def _gicp_fused_parallel(P, Q, idx, Qs, start, end, dim, split, left, right, depth, d2, warm, Cs, Ct, R,
                         out_idx, out_sq, part, P_old, r1, r2, moved):
    for c in prange(part.shape[0]):
        _gicp_fused_rows(P, Q, idx, Qs, start, end, dim, split, left, right, depth, d2, warm, Cs, Ct, R,
                         out_idx, out_sq, part, P_old, r1, r2, moved, c, c + 1)


def gicp_fused_search(P, Q, tree, d2, warm, Cs, Ct, R, parallel, state=None):
    """Gated nearest neighbour of every row of ``P`` and the GICP system of the pairs, in one pass.

    ``P`` (n, 3) are the source points moved by the current pose (rotation ``R``), ``tree`` the
    :func:`~minegeo.kernels.kdtree.kd_build` tuple of ``Q``, ``warm`` (n,) the previous partners
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
    """
    n = P.shape[0]
    out_idx = np.empty(n, dtype=np.int64)
    out_sq = np.empty(n)
    part = np.zeros(((n + GICP_ROWS - 1) // GICP_ROWS, GICP_ACC))
    if state is None:
        state = (np.empty((0, 3)), np.empty(n), np.empty(n), np.zeros(n))
    drive = _gicp_fused_parallel if parallel else _gicp_fused_serial
    drive(P, Q, *tree, float(d2), warm, Cs, Ct, R, out_idx, out_sq, part, *state)
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
def knn_normals_tasks(Q, idx, Qs, start, end, dim, split, left, right, depth, k, mode_open3d, ratio, out_n, out_eval,
                       out_status):
    """``_knn_normals_rows`` in ``prange`` over ``GICP_ROWS``-point tasks (leaf order;
    one row per point, so any split gives the same bits)."""
    m = Q.shape[0]
    for c in prange((m + GICP_ROWS - 1) // GICP_ROWS):
        _knn_normals_rows(Q, idx, Qs, start, end, dim, split, left, right, depth, k, mode_open3d, ratio, out_n,
                          out_eval, out_status, c * GICP_ROWS, min(m, (c + 1) * GICP_ROWS))
