"""Naive NumPy twin of one RANSAC hypothesis (edge test, SVD model, checks, whole-cloud score)."""

from __future__ import annotations

import numpy as np


def naive_umeyama(P, Q):
    """R, t minimising sum |R p + t - q|^2 ([Baek2022 Eqs. 10-13] with the reflection fix)."""
    pm, qm = P.mean(axis=0), Q.mean(axis=0)
    S = (Q - qm).T @ (P - pm) / P.shape[0]
    U, D, Vt = np.linalg.svd(S)
    s = -1.0 if np.linalg.det(U) * np.linalg.det(Vt) < 0 else 1.0
    R = U @ np.diag([1.0, 1.0, s]) @ Vt
    return R, qm - R @ pm, D


def naive_hypothesis(src, tgt, csrc, ctgt, sample, sim, dist_thr, all_pairs=True):
    """Return (status, n_inliers, sse, T) with the kernel's status codes (no pruning)."""
    P, Q = csrc[sample], ctgt[sample]
    n = len(sample)
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n)] if all_pairs else [(a, (a + 1) % n) for a in range(n)]
    for a, b in pairs:
        ls, lt = np.linalg.norm(P[a] - P[b]), np.linalg.norm(Q[a] - Q[b])
        if ls < sim * lt or lt < sim * ls:
            return 0, 0, 0.0, None
    R, t, D = naive_umeyama(P, Q)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    if not (D[0] > 0 and D[1] > 1e-9 * D[0]):
        return 1, 0, 0.0, T
    if np.any(np.linalg.norm(P @ R.T + t - Q, axis=1) > dist_thr):
        return 2, 0, 0.0, T
    moved = src @ R.T + t
    d2 = ((moved[:, None, :] - tgt[None, :, :]) ** 2).sum(-1).min(axis=1)
    inl = d2 < dist_thr * dist_thr
    return 4, int(inl.sum()), float(d2[inl].sum()), T
