"""Numba kernels for feature-based RANSAC (Baek et al. 2022, Sec. 2.3.2, [Baek2022 Eqs. 7-8, 10-13, 19]).

Kernels take C-contiguous float64/int64 arrays and do no checking; the public
functions in :mod:`minegeo.registration.ransac` and
:mod:`minegeo.registration.correspondences` validate and document.

Fixed-radius nearest-neighbour search uses a uniform grid of cubic cells with
edge ``cell >= radius`` stored in an open-addressing hash table
(:mod:`minegeo.kernels.hashgrid`; memory proportional to the number of occupied cells, not to
the map's extent): the
nearest point within ``radius`` of a query is always in the 3 x 3 x 3 block of
cells around it, so the search is exact.
"""

from __future__ import annotations

import math

import numpy as np

from minegeo._jit import njit, njit_parallel, prange
from minegeo.kernels import hashgrid as HG
from minegeo.kernels.rigid import umeyama_rigid

# Hypothesis status codes returned by :func:`ransac_batch_kernel`.
ST_EDGE = 0  #: rejected by the edge-length test ([Baek2022 Eq. 7])
ST_DEGENERATE = 1  #: sample (near) collinear: rotation undetermined
ST_DISTANCE = 2  #: rejected by the distance check on the sample
ST_NORMAL = 3  #: rejected by the normal-angle check on the sample
ST_EVALUATED = 4  #: scored on the whole cloud (n_inliers, sse valid)
ST_PRUNED = 5  #: passed the checks; scoring stopped once it could not reach the bound

# ----------------------------------------------------------------------------- grid


@njit
def grid_nearest(x, y, z, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2):
    """Nearest grid point strictly within squared radius ``r2`` of ``(x, y, z)``.

    Two storages of the same grid: *dense* (``dstart.size > 1``: ``dstart[key]`` is
    the first stored point of cell ``key``, so the three cells of a row along x are
    one contiguous range) or *hashed* (``tkeys/tslots`` map an occupied cell to its
    ``cstart/ccount``). Returns ``(index into gpts or -1, squared distance or inf)``;
    ties keep the first point met (storage order).
    """
    best = np.int64(-1)
    bd = np.inf
    nx = gdims[0]
    ny = gdims[1]
    nz = gdims[2]
    fx = (x - gorigin[0]) / gcell
    fy = (y - gorigin[1]) / gcell
    fz = (z - gorigin[2]) / gcell
    if not (fx > -2.0 and fy > -2.0 and fz > -2.0 and fx < nx + 1.0 and fy < ny + 1.0 and fz < nz + 1.0):
        return best, bd
    cx = np.int64(math.floor(fx))
    cy = np.int64(math.floor(fy))
    cz = np.int64(math.floor(fz))
    x0 = max(cx - 1, 0)
    x1 = min(cx + 2, nx)
    if x0 >= x1:
        return best, bd
    dense = dstart.shape[0] > 1
    bits = HG.table_bits_of(tkeys)
    for iz in range(max(cz - 1, 0), min(cz + 2, nz)):
        for iy in range(max(cy - 1, 0), min(cy + 2, ny)):
            base = (iz * ny + iy) * nx
            if dense:
                for j in range(dstart[base + x0], dstart[base + x1]):
                    dx = gpts[j, 0] - x
                    dy = gpts[j, 1] - y
                    dz = gpts[j, 2] - z
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 < r2 and d2 < bd:
                        bd = d2
                        best = j
            else:
                for ix in range(x0, x1):
                    u = HG.lookup(base + ix, bits, tkeys, tslots)
                    if u < 0:
                        continue
                    s0 = cstart[u]
                    for j in range(s0, s0 + ccount[u]):
                        dx = gpts[j, 0] - x
                        dy = gpts[j, 1] - y
                        dz = gpts[j, 2] - z
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < r2 and d2 < bd:
                            bd = d2
                            best = j
    return best, bd


@njit
def _nearest_one(i, queries, R, t, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2, idx, sq):
    px = queries[i, 0]
    py = queries[i, 1]
    pz = queries[i, 2]
    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    j, d2 = grid_nearest(x, y, z, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2)
    idx[i] = j
    sq[i] = d2


@njit_parallel
def grid_nearest_batch(queries, R, t, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2):
    """For every query ``R q + t``: nearest grid point within ``sqrt(r2)`` (index, sq distance); parallel."""
    n = queries.shape[0]
    idx = np.full(n, -1, dtype=np.int64)
    sq = np.full(n, np.inf)
    for i in prange(n):
        _nearest_one(i, queries, R, t, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2, idx, sq)
    return idx, sq


@njit
def grid_nearest_serial(queries, R, t, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2):
    """Serial twin of :func:`grid_nearest_batch` (identical results; no thread launch)."""
    n = queries.shape[0]
    idx = np.full(n, -1, dtype=np.int64)
    sq = np.full(n, np.inf)
    for i in range(n):
        _nearest_one(i, queries, R, t, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2, idx, sq)
    return idx, sq


# ----------------------------------------------------------------------------- model


@njit
def _edge_ok(P, Q, a, b, sim):
    dxs = P[a, 0] - P[b, 0]
    dys = P[a, 1] - P[b, 1]
    dzs = P[a, 2] - P[b, 2]
    dxt = Q[a, 0] - Q[b, 0]
    dyt = Q[a, 1] - Q[b, 1]
    dzt = Q[a, 2] - Q[b, 2]
    ls = math.sqrt(dxs * dxs + dys * dys + dzs * dzs)
    lt = math.sqrt(dxt * dxt + dyt * dyt + dzt * dzt)
    return not (ls < sim * lt or lt < sim * ls)


@njit
def _check_one(h, csrc, ctgt, csrc_n, ctgt_n, samples, sim, all_pairs, dist_thr, use_normals, cos_normal,
               degenerate_tol, distinct, status, Ts):
    n = samples.shape[1]
    if distinct:
        for a in range(n):
            for b in range(a + 1, n):
                if samples[h, a] == samples[h, b]:
                    status[h] = ST_DEGENERATE
                    return
    P = np.empty((n, 3))
    Q = np.empty((n, 3))
    for a in range(n):
        c = samples[h, a]
        for d in range(3):
            P[a, d] = csrc[c, d]
            Q[a, d] = ctgt[c, d]
    if all_pairs:
        for a in range(n):
            for b in range(a + 1, n):
                if not _edge_ok(P, Q, a, b, sim):
                    return
    else:
        for a in range(n):
            if not _edge_ok(P, Q, a, (a + 1) % n, sim):
                return
    R, t, good = umeyama_rigid(P, Q, degenerate_tol)
    for a in range(3):
        for b in range(3):
            Ts[h, a, b] = R[a, b]
        Ts[h, a, 3] = t[a]
    Ts[h, 3, 3] = 1.0
    if not good:
        status[h] = ST_DEGENERATE
        return
    for a in range(n):
        ex = R[0, 0] * P[a, 0] + R[0, 1] * P[a, 1] + R[0, 2] * P[a, 2] + t[0] - Q[a, 0]
        ey = R[1, 0] * P[a, 0] + R[1, 1] * P[a, 1] + R[1, 2] * P[a, 2] + t[1] - Q[a, 1]
        ez = R[2, 0] * P[a, 0] + R[2, 1] * P[a, 1] + R[2, 2] * P[a, 2] + t[2] - Q[a, 2]
        if math.sqrt(ex * ex + ey * ey + ez * ez) > dist_thr:
            status[h] = ST_DISTANCE
            return
    if use_normals:
        for a in range(n):
            c = samples[h, a]
            nx = R[0, 0] * csrc_n[c, 0] + R[0, 1] * csrc_n[c, 1] + R[0, 2] * csrc_n[c, 2]
            ny = R[1, 0] * csrc_n[c, 0] + R[1, 1] * csrc_n[c, 1] + R[1, 2] * csrc_n[c, 2]
            nz = R[2, 0] * csrc_n[c, 0] + R[2, 1] * csrc_n[c, 1] + R[2, 2] * csrc_n[c, 2]
            if ctgt_n[c, 0] * nx + ctgt_n[c, 1] * ny + ctgt_n[c, 2] * nz < cos_normal:
                status[h] = ST_NORMAL
                return
    status[h] = ST_EVALUATED


@njit
def ransac_check_kernel(csrc, ctgt, csrc_n, ctgt_n, samples, sim, all_pairs, dist_thr, use_normals, cos_normal,
                        degenerate_tol, distinct):
    """Prune and fit a batch of RANSAC samples (one hypothesis per row of ``samples``); serial.

    For hypothesis h with sampled correspondence rows ``samples[h]`` (n >= 3):

    0. if ``distinct``, a sample that repeats a correspondence is rejected (ST_DEGENERATE);
    1. edge-length test, [Baek2022 Eq. 7]: every compared edge must satisfy
       ``min(l_s, l_t) >= sim * max(l_s, l_t)`` (polygon edges of [Baek2022 Eq. 7], or all
       pairs when ``all_pairs``);
    2. rigid model by SVD ([Baek2022 Eqs. 10-13]), rejected if the sample is collinear;
    3. distance check ``|R p + t - q| <= dist_thr`` for every sampled pair;
    4. optional normal check ``n_q . (R n_p) >= cos_normal``.

    Returns ``status (B,) int64`` (ST_* codes; ST_EVALUATED means "passed, to be
    scored") and ``T (B, 4, 4)`` (zeros when the edge test failed). Serial on
    purpose: about a microsecond per sample, less than a parallel launch costs.
    """
    B = samples.shape[0]
    status = np.full(B, ST_EDGE, dtype=np.int64)
    Ts = np.zeros((B, 4, 4))
    for h in range(B):
        _check_one(h, csrc, ctgt, csrc_n, ctgt_n, samples, sim, all_pairs, dist_thr, use_normals, cos_normal,
                   degenerate_tol, distinct, status, Ts)
    return status, Ts


@njit
def _score_one(h, src, eval_order, Ts, prune_count, r2, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount,
               n_inl, sse, pruned):
    N = src.shape[0]
    R = Ts[h, :3, :3]
    t0 = Ts[h, 0, 3]
    t1 = Ts[h, 1, 3]
    t2 = Ts[h, 2, 3]
    cnt = np.int64(0)
    acc = 0.0
    for m in range(N):
        if (m & 63) == 0 and cnt + (N - m) < prune_count:
            pruned[h] = 1
            break
        i = eval_order[m]
        px = src[i, 0]
        py = src[i, 1]
        pz = src[i, 2]
        x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t0
        y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t1
        z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t2
        j, d2 = grid_nearest(x, y, z, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart, ccount, r2)
        if j >= 0:
            cnt += 1
            acc += d2
    n_inl[h] = cnt
    sse[h] = acc


@njit_parallel
def ransac_score_kernel(src, eval_order, Ts, prune_count, dist_thr, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots,
                        cstart, ccount):
    """Score hypotheses ``Ts (G, 4, 4)`` on the whole source cloud ([Baek2022 Eq. 19] ingredients); parallel.

    For each source point (in ``eval_order``) the nearest target point strictly
    within ``dist_thr`` after ``R p + t``: ``n_inl`` counts them and ``sse`` sums
    their squared distances (serially within a hypothesis, so the value does not
    depend on threads). Scoring stops early (``pruned = 1``) once
    ``n_inl + remaining < prune_count``: such a hypothesis provably has fewer than
    ``prune_count`` inliers.
    """
    G = Ts.shape[0]
    n_inl = np.zeros(G, dtype=np.int64)
    sse = np.zeros(G)
    pruned = np.zeros(G, dtype=np.int64)
    r2 = dist_thr * dist_thr
    for h in prange(G):
        _score_one(h, src, eval_order, Ts, prune_count, r2, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart,
                   ccount, n_inl, sse, pruned)
    return n_inl, sse, pruned


@njit
def ransac_score_serial(src, eval_order, Ts, prune_count, dist_thr, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots,
                        cstart, ccount):
    """Serial twin of :func:`ransac_score_kernel` (identical results; no thread launch)."""
    G = Ts.shape[0]
    n_inl = np.zeros(G, dtype=np.int64)
    sse = np.zeros(G)
    pruned = np.zeros(G, dtype=np.int64)
    r2 = dist_thr * dist_thr
    for h in range(G):
        _score_one(h, src, eval_order, Ts, prune_count, r2, gpts, gorigin, gcell, gdims, dstart, tkeys, tslots, cstart,
                   ccount, n_inl, sse, pruned)
    return n_inl, sse, pruned


# ----------------------------------------------------------------------------- descriptor nearest neighbour

#: Points per leaf of the descriptor tree.
FEATURE_LEAF = 32
#: Leading rotated coordinates stored per point for the partial-distance test of the tree.
FEATURE_LEAD = 8
#: Rotated coordinates used for the leaf boxes (at most; fewer when dim is smaller).
FEATURE_ROT = 16


@njit
def feature_mean_cov(X):
    """Mean ``mu`` (dim,) and scatter matrix ``sum_i (x_i - mu)(x_i - mu)^T`` (dim, dim); serial."""
    n, dim = X.shape
    mu = np.zeros(dim)
    for i in range(n):
        for c in range(dim):
            mu[c] += X[i, c]
    for c in range(dim):
        mu[c] /= n
    C = np.zeros((dim, dim))
    d = np.empty(dim)
    for i in range(n):
        for c in range(dim):
            d[c] = X[i, c] - mu[c]
        for a in range(dim):
            da = d[a]
            for b in range(dim):
                C[a, b] += da * d[b]
    return mu, C


@njit
def feature_rotate(X, mu, V):
    """``(X - mu) V`` row by row (rows independent: the result does not depend on threads)."""
    n, dim = X.shape
    k = V.shape[1]
    out = np.zeros((n, k))
    for i in prange(n):
        for a in range(dim):
            xa = X[i, a] - mu[a]
            for b in range(k):
                out[i, b] += xa * V[a, b]
    return out


@njit
def feature_tree_build(P):
    """Balanced kd partition of the rows of ``P`` into leaves of at most ``FEATURE_LEAF`` rows.

    A node is split on its coordinate of largest spread, at a multiple of the leaf size:
    rows below the split value go left, those above right, equal values fill the left side
    in their current order (a pure function of ``P``, no randomness). Returns the row
    permutation ``perm`` and leaf starts ``lstart`` (nl + 1,) into it.
    """
    n = P.shape[0]
    dim = P.shape[1]
    L = FEATURE_LEAF
    nl = (n + L - 1) // L
    perm = np.arange(n)
    lstart = np.empty(nl + 1, dtype=np.int64)
    lstart[nl] = n
    # explicit stack of (start, end, first leaf, leaf count)
    st = np.empty((2 * nl + 8, 4), dtype=np.int64)
    lo = np.empty(dim)
    hi = np.empty(dim)
    st[0, 0] = 0
    st[0, 1] = n
    st[0, 2] = 0
    st[0, 3] = nl
    top = 1
    while top > 0:
        top -= 1
        s = st[top, 0]
        e = st[top, 1]
        l0 = st[top, 2]
        k = st[top, 3]
        if k == 1:
            lstart[l0] = s
            continue
        for c in range(dim):
            lo[c] = np.inf
            hi[c] = -np.inf
        for r in range(s, e):
            j = perm[r]
            for c in range(dim):
                v = P[j, c]
                if v < lo[c]:
                    lo[c] = v
                if v > hi[c]:
                    hi[c] = v
        best_c = 0
        for c in range(1, dim):
            if hi[c] - lo[c] > hi[best_c] - lo[best_c]:
                best_c = c
        kl = (k + 1) // 2
        m = s + kl * L  # < e because the node holds more than (k - 1) * L rows
        # stable partition around the (m - s)-th smallest value: O(n) per level
        vals = np.empty(e - s)
        for r in range(s, e):
            vals[r - s] = P[perm[r], best_c]
        kth = np.partition(vals, m - s)[m - s]
        seg = perm[s:e].copy()
        n_eq = m - s
        for r in range(e - s):
            if vals[r] < kth:
                n_eq -= 1
        a = s
        b = m
        for r in range(e - s):
            v = vals[r]
            if v < kth or (v == kth and n_eq > 0):
                if v == kth:
                    n_eq -= 1
                perm[a] = seg[r]
                a += 1
            else:
                perm[b] = seg[r]
                b += 1
        st[top, 0] = m
        st[top, 1] = e
        st[top, 2] = l0 + kl
        st[top, 3] = k - kl
        top += 1
        st[top, 0] = s
        st[top, 1] = m
        st[top, 2] = l0
        st[top, 3] = kl
        top += 1
    return perm, lstart


@njit
def feature_tree_pack(B, P, perm, lstart):
    """Leaf storage of the descriptor tree.

    Returns ``lead (nl, FEATURE_LEAF, FEATURE_LEAD)``: the first ``FEATURE_LEAD`` rotated
    coordinates of each leaf's points (zero padded), ``Bp (nl * FEATURE_LEAF, dim)``: the
    original rows in leaf order (for the exact distances), and ``loT, hiT (nrot, nl)``: the
    leaves' bounding boxes in the rotated coordinates ``P (n, nrot)``.
    """
    nl = lstart.shape[0] - 1
    dim = B.shape[1]
    nrot = P.shape[1]
    L = FEATURE_LEAF
    lead = np.zeros((nl, L, FEATURE_LEAD))
    Bp = np.zeros((nl * L, dim))
    loT = np.full((nrot, nl), np.inf)
    hiT = np.full((nrot, nl), -np.inf)
    for l in range(nl):
        for r in range(lstart[l], lstart[l + 1]):
            j = perm[r]
            k = r - lstart[l]
            for c in range(dim):
                Bp[l * L + k, c] = B[j, c]
            for c in range(min(nrot, FEATURE_LEAD)):
                lead[l, k, c] = P[j, c]
            for c in range(nrot):
                v = P[j, c]
                if v < loT[c, l]:
                    loT[c, l] = v
                if v > hiT[c, l]:
                    hiT[c, l] = v
    return lead, Bp, loT, hiT


@njit_parallel
def feature_tree_nn(A, Q, perm, lstart, lead, Bp, loT, hiT, delta):
    """Exact nearest row of ``B`` (stored in the tree) for every row of ``A`` (rows independent).

    ``Q (na, nrot)`` are the rows of ``A`` in the tree's rotated coordinates. With
    ``best`` the smallest exact distance found so far, a rotated partial squared distance
    ``s`` (a box distance ``LB_l`` of a leaf over all ``nrot`` coordinates, or a point's
    distance over its first ``FEATURE_LEAD`` coordinates) rules a point out when
    ``s > T = ((sqrt(best (1 + 1e-12)) + delta)^2 (1 + 1e-12)``: partial sums of an
    orthonormal rotation never exceed the full distance, and ``delta`` bounds the
    rounding of the rotation (distance units), so such a point is provably farther than
    ``best``. The leaf with the smallest ``LB_l`` is scanned first, then the others in
    index order; every point not ruled out gets the direct distance
    ``sum_c (a_c - b_c)^2`` (c in order, as in :func:`feature_nn_brute`), ties to the
    lowest index of ``B``. Returns ``(index (na,), sq distance (na,))``.
    """
    na = A.shape[0]
    dim = A.shape[1]
    nrot = Q.shape[1]
    nl = loT.shape[1]
    L = FEATURE_LEAF
    idx = np.full(na, -1, dtype=np.int64)
    best = np.full(na, np.inf)
    for i in prange(na):
        LB = np.zeros(nl)
        for c in range(nrot):
            q = Q[i, c]
            for l in range(nl):
                e = loT[c, l] - q
                f = q - hiT[c, l]
                e = e if e > f else f
                e = e if e > 0.0 else 0.0
                LB[l] += e * e
        l0 = 0
        for l in range(1, nl):
            if LB[l] < LB[l0]:
                l0 = l
        qv = np.zeros(FEATURE_LEAD)
        for c in range(min(nrot, FEATURE_LEAD)):
            qv[c] = Q[i, c]
        bd = np.inf
        bi = np.int64(-1)
        T = np.inf
        for o in range(-1, nl):
            if o == l0:
                continue
            l = l0 if o < 0 else o
            if LB[l] > T:
                continue
            s0 = lstart[l]
            for k in range(lstart[l + 1] - s0):
                s = 0.0
                for c in range(FEATURE_LEAD):
                    e = qv[c] - lead[l, k, c]
                    s += e * e
                if s > T:
                    continue
                row = l * L + k
                d2 = 0.0
                for c in range(dim):
                    e = A[i, c] - Bp[row, c]
                    d2 += e * e
                j = perm[s0 + k]
                if d2 < bd or (d2 == bd and j < bi):
                    bd = d2
                    bi = j
                    r = math.sqrt(bd * (1.0 + 1e-12)) + delta
                    T = r * r * (1.0 + 1e-12)
        idx[i] = bi
        best[i] = bd
    return idx, best


@njit_parallel
def feature_nn_brute(A, B):
    """Exact nearest row of ``B`` for every row of ``A`` by brute force (float64; ties to the
    lowest index); parallel over rows of ``A``. Returns ``(index (na,), sq distance (na,))``."""
    na = A.shape[0]
    dim = A.shape[1]
    nb = B.shape[0]
    idx = np.full(na, -1, dtype=np.int64)
    best = np.full(na, np.inf)
    for i in prange(na):
        bd = np.inf
        bi = np.int64(-1)
        for j in range(nb):
            d2 = 0.0
            for c in range(dim):
                e = A[i, c] - B[j, c]
                d2 += e * e
            if d2 < bd:
                bd = d2
                bi = j
        idx[i] = bi
        best[i] = bd
    return idx, best
