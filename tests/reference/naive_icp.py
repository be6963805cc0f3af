"""Naive NumPy twins of minegeo.registration kernels (brute force, no Numba, no KD-tree).

Written straight from the formulas ([Baek2022 Eqs. 10-13, 19]; Low 2004; Open3D spec §7, §8, §10)
so that the optimised kernels can be checked against an independent, obviously-correct version.
"""

from __future__ import annotations

import numpy as np


def naive_umeyama(P, Q, with_scale=False, w=None):
    """Weighted Umeyama with the reflection fix, via numpy SVD of the paper's W ([Baek2022 Eq. 10])."""
    P = np.asarray(P, float)
    Q = np.asarray(Q, float)
    w = np.ones(len(P)) if w is None else np.asarray(w, float)
    sw = w.sum()
    mp = (w[:, None] * P).sum(0) / sw
    mq = (w[:, None] * Q).sum(0) / sw
    X = P - mp
    Y = Q - mq
    W = (w[:, None, None] * X[:, :, None] * Y[:, None, :]).sum(0) / sw
    U, S, Vt = np.linalg.svd(W)
    V = Vt.T
    d = np.sign(np.linalg.det(V @ U.T))
    D = np.diag([1.0, 1.0, d])
    R = V @ D @ U.T
    c = 1.0
    if with_scale:
        c = np.trace(np.diag(S) @ D) / ((w * (X**2).sum(1)).sum() / sw)
    T = np.eye(4)
    T[:3, :3] = c * R
    T[:3, 3] = mq - c * R @ mp
    return T, c


def naive_nearest(P, Q):
    """Brute-force nearest target index and squared distance for every row of P."""
    D = ((P[:, None, :] - Q[None, :, :]) ** 2).sum(-1)
    j = D.argmin(1)
    return j, D[np.arange(len(P)), j]


def naive_evaluate(P, Q, T, d):
    """Open3D evaluate_registration (§8) by brute force: (fitness, rmse, corr)."""
    Pt = P @ T[:3, :3].T + T[:3, 3]
    j, sq = naive_nearest(Pt, Q)
    ok = sq < d * d
    corr = np.c_[np.flatnonzero(ok), j[ok]].astype(np.int64)
    if not ok.any():
        return 0.0, 0.0, corr
    return ok.sum() / len(P), float(np.sqrt(sq[ok].sum() / ok.sum())), corr


def naive_point_to_plane_system(P, Q, N):
    """H = Σ JᵀJ, g = Σ Jᵀr with J = [p×n, n], r = (p-q)·n (Low 2004)."""
    J = np.c_[np.cross(P, N), N]
    r = ((P - Q) * N).sum(1)
    return J.T @ J, J.T @ r, float(r @ r)


def naive_point_to_point_information(Q):
    """Σ GᵀG with G = [-[q]x, I] stacked row by row, as Open3D's GetInformationMatrixFromPointClouds."""
    H = np.zeros((6, 6))
    for x, y, z in Q:
        for row in ([0, z, -y, 1, 0, 0], [-z, 0, x, 0, 1, 0], [y, -x, 0, 0, 0, 1]):
            g = np.array(row, float)
            H += np.outer(g, g)
    return H


def _rzyx(a, b, c):
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def naive_icp(P, Q, T0, d, max_iterations=30, rel_f=1e-6, rel_r=1e-6, normals=None):
    """Open3D's ICP loop (§10) written plainly; point-to-plane when ``normals`` are given."""
    T = np.array(T0, float)
    Pt = P @ T[:3, :3].T + T[:3, 3]
    f, r, corr = naive_evaluate(Pt, Q, np.eye(4), d)
    it = 0
    for _ in range(max_iterations):
        if len(corr) == 0:
            dT = np.eye(4)
        elif normals is None:
            dT, _ = naive_umeyama(Pt[corr[:, 0]], Q[corr[:, 1]])
        else:
            H, g, _ = naive_point_to_plane_system(Pt[corr[:, 0]], Q[corr[:, 1]], normals[corr[:, 1]])
            x = np.linalg.solve(H, -g)
            dT = np.eye(4)
            dT[:3, :3] = _rzyx(*x[:3])
            dT[:3, 3] = x[3:]
        T = dT @ T
        Pt = Pt @ dT[:3, :3].T + dT[:3, 3]
        it += 1
        f0, r0 = f, r
        f, r, corr = naive_evaluate(Pt, Q, np.eye(4), d)
        if abs(f - f0) < rel_f and abs(r - r0) < rel_r:
            break
    return T, f, r, it


def naive_kd_build(Q, leaf):
    """Plain-Python sliding-midpoint KD-tree, two passes per node (box, then partition).

    The straightforward form of ``_kernels.kd_build`` (same split rule, same in-place
    partition of the index array, same node numbering); returns the same tuple.
    """
    Q = np.asarray(Q, dtype=np.float64)
    m = Q.shape[0]
    idx = np.arange(m)
    start, end, dim, split, left, right, level = [0], [m], [-1], [0.0], [-1], [-1], [0]
    stack = [0]
    depth = 0
    while stack:
        nd = stack.pop()
        s, e = start[nd], end[nd]
        depth = max(depth, level[nd])
        if e - s <= leaf:
            continue
        pts = Q[idx[s:e]]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        k = 0
        spread = hi[0] - lo[0]
        for c in (1, 2):
            if hi[c] - lo[c] > spread:
                k, spread = c, hi[c] - lo[c]
        if not spread > 0.0:
            continue
        sv = 0.5 * (lo[k] + hi[k])
        i, jj = s, e - 1
        while i <= jj:
            if Q[idx[i], k] < sv:
                i += 1
            else:
                idx[i], idx[jj] = idx[jj], idx[i]
                jj -= 1
        if i == s or i == e:
            continue
        dim[nd], split[nd] = k, sv
        lc, rc = len(start), len(start) + 1
        for a, b in ((s, i), (i, e)):
            start.append(a)
            end.append(b)
            dim.append(-1)
            split.append(0.0)
            left.append(-1)
            right.append(-1)
            level.append(level[nd] + 1)
        left[nd], right[nd] = lc, rc
        stack += [lc, rc]
    as_i = lambda v: np.asarray(v, dtype=np.int64)  # noqa: E731
    return (idx, Q[idx], as_i(start), as_i(end), as_i(dim), np.asarray(split), as_i(left), as_i(right), depth)
