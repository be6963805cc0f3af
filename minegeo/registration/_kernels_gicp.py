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
from minegeo.kernels.chunks import CHUNK, n_chunks
from minegeo.kernels.eig3 import fast_eigen3x3, pca_normal
from minegeo.kernels.kdtree import kd_build, kd_knn_one, kd_nn_warm_parallel, kd_nn_warm_serial
from minegeo.registration._kernels import _add_partials

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
