"""Naive NumPy/SciPy twin of minegeo's GICP (Open3D's formulation, whitened residuals).

Written straight from the oracle spec §10-§11: covariances ``I - (1-ε) n nᵀ`` from kNN PCA
normals (two-pass covariance, ``numpy.linalg.eigh``), and per pair the whitening matrix
``W = M^{-1/2}`` (eigen-decomposition), three residuals ``r = W d`` with Jacobian
``W [-[p]×, I]``; ``H = Σ JᵀJ``, ``g = Σ Jᵀr``, ``H x = -g``, exact ZYX Euler update.
minegeo sums ``Jᵀ M⁻¹ J`` instead, which is the same with the L2 loss.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def naive_plane_covariances(X, k=20, eps=1e-3):
    """(n, 3, 3) ``I - (1-ε) n nᵀ`` with n the PCA normal of the k nearest points (self included)."""
    _, nb = cKDTree(X).query(X, k=min(k, len(X)))
    out = np.empty((len(X), 3, 3))
    for i in range(len(X)):
        Y = X[nb[i]] - X[nb[i]].mean(axis=0)
        n = np.linalg.eigh(Y.T @ Y)[1][:, 0]
        out[i] = np.eye(3) - (1 - eps) * np.outer(n, n)
    return out


def _skew(p):
    return np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


def _euler(x):
    a, b, c = x[:3]
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = x[3:]
    return T


def _evaluate(P, tree, d):
    dist, j = tree.query(P, k=1)
    ok = dist**2 < d * d
    src = np.flatnonzero(ok)
    if src.size == 0:
        return 0.0, 0.0, src, j[src]
    sq = ((P[src] - tree.data[j[src]]) ** 2).sum(axis=1)
    return src.size / len(P), float(np.sqrt(sq.sum() / src.size)), src, j[src]


def naive_gicp(P0, Q, T0, d, Cs, Ct, max_iterations=30, rel_f=1e-6, rel_r=1e-6):
    """Returns ``(T, fitness, rmse, iterations)``; Cs/Ct in their clouds' own frames."""
    tree = cKDTree(Q)
    T = T0.copy()
    P = P0 @ T[:3, :3].T + T[:3, 3]
    C = np.einsum("ij,njk,lk->nil", T[:3, :3], Cs, T[:3, :3])  # source covariances, target frame
    f, r, si, ti = _evaluate(P, tree, d)
    it = 0
    for _ in range(max_iterations):
        H = np.zeros((6, 6))
        g = np.zeros(6)
        for a, b in zip(si, ti, strict=True):
            M = Ct[b] + C[a]
            ev, V = np.linalg.eigh(M)
            W = V @ np.diag(ev**-0.5) @ V.T
            J = W @ np.hstack([-_skew(P[a]), np.eye(3)])
            res = W @ (P[a] - Q[b])
            H += J.T @ J
            g += J.T @ res
        dT = _euler(np.linalg.solve(H, -g)) if si.size else np.eye(4)
        T = dT @ T
        P = P @ dT[:3, :3].T + dT[:3, 3]
        C = np.einsum("ij,njk,lk->nil", dT[:3, :3], C, dT[:3, :3])
        it += 1
        f0, r0 = f, r
        f, r, si, ti = _evaluate(P, tree, d)
        if abs(f - f0) < rel_f and abs(r - r0) < rel_r:
            break
    return T, f, r, it


def naive_gicp_system(P, Q, Cs, Ct, R, si, ti):
    """GICP normal equations written plainly ([Ren2019 Eqs. 4-6]): per pair ``d = p - q``,
    ``M = Ct + R Cs Rᵀ``, ``B = M⁻¹`` (``numpy.linalg.inv``), ``J = [-[p]×, I3]``; returns
    ``(Σ Jᵀ B J, Σ Jᵀ B d, Σ dᵀ B d)``."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    cost = 0.0
    for a, b in zip(si, ti, strict=True):
        B = np.linalg.inv(Ct[b] + R @ Cs[a] @ R.T)
        J = np.hstack([-_skew(P[a]), np.eye(3)])
        d = P[a] - Q[b]
        H += J.T @ B @ J
        g += J.T @ B @ d
        cost += float(d @ B @ d)
    return H, g, cost
