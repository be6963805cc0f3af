"""Naive twin of the pose-graph solver: dense matrices, matrix exponential/logarithm from SciPy,
finite-difference Jacobians and plain Gauss–Newton. Slow and obviously right; for tiny graphs."""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm, logm


def twist_matrix(xi: np.ndarray) -> np.ndarray:
    """4×4 (SE3, ξ = (ω, ρ)) or 3×3 (SE2, ξ = (θ, x, y)) Lie-algebra matrix (rotation first)."""
    if xi.size == 6:
        w, v = xi[:3], xi[3:]
        M = np.zeros((4, 4))
        M[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
        M[:3, 3] = v
        return M
    M = np.zeros((3, 3))
    M[:2, :2] = [[0, -xi[0]], [xi[0], 0]]
    M[:2, 2] = xi[1:]
    return M


def exp(xi):
    return expm(twist_matrix(np.asarray(xi, float)))


def log(T):
    M = np.real(logm(T))
    if T.shape[0] == 4:
        return np.array([M[2, 1], M[0, 2], M[1, 0], *M[:3, 3]])
    return np.array([M[1, 0], M[0, 2], M[1, 2]])


def residual(Ti, Tj, Z):
    return log(np.linalg.inv(Z) @ np.linalg.inv(Ti) @ Tj)


def cost(poses, edges, Z, info_rt):
    return 0.5 * sum(float(r @ O @ r) for r, O in
                     ((residual(poses[i], poses[j], Z[k]), info_rt[k]) for k, (i, j) in enumerate(edges)))


def numeric_jacobians(Ti, Tj, Z, h=1e-6):
    """Central differences of the residual under right perturbations T ← T·Exp(δ)."""
    d = 6 if Ti.shape[0] == 4 else 3
    Ji, Jj = np.zeros((d, d)), np.zeros((d, d))
    for k in range(d):
        e = np.zeros(d)
        e[k] = h
        Ji[:, k] = (residual(Ti @ exp(e), Tj, Z) - residual(Ti @ exp(-e), Tj, Z)) / (2 * h)
        Jj[:, k] = (residual(Ti, Tj @ exp(e), Z) - residual(Ti, Tj @ exp(-e), Z)) / (2 * h)
    return Ji, Jj


def gauss_newton(poses, edges, Z, info_rt, fixed=(0,), iterations=30):
    """Dense Gauss–Newton with finite-difference Jacobians; returns the optimised poses."""
    poses = [p.copy() for p in poses]
    d = 6 if poses[0].shape[0] == 4 else 3
    free = [v for v in range(len(poses)) if v not in fixed]
    col = {v: k * d for k, v in enumerate(free)}
    for _ in range(iterations):
        H = np.zeros((len(free) * d,) * 2)
        g = np.zeros(len(free) * d)
        for k, (i, j) in enumerate(edges):
            r = residual(poses[i], poses[j], Z[k])
            Ji, Jj = numeric_jacobians(poses[i], poses[j], Z[k])
            for a, Ja in ((i, Ji), (j, Jj)):
                if a not in col:
                    continue
                g[col[a]:col[a] + d] += Ja.T @ info_rt[k] @ r
                for b, Jb in ((i, Ji), (j, Jj)):
                    if b in col:
                        H[col[a]:col[a] + d, col[b]:col[b] + d] += Ja.T @ info_rt[k] @ Jb
        delta = np.linalg.solve(H, -g)
        for v in free:
            poses[v] = poses[v] @ exp(delta[col[v]:col[v] + d])
        if np.abs(delta).max() < 1e-12:
            break
    return poses
