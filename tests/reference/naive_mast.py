"""Naive (loop/NumPy) twins of the minegeo.mast Numba kernels, for comparison tests."""

from __future__ import annotations

import numpy as np


def naive_cast_rays(origin, directions, segments, max_range):
    """Nearest ray-segment hit per ray by solving the 2x2 system with numpy.linalg."""
    m = len(directions)
    rng = np.full(m, np.nan)
    idx = np.full(m, -1)
    for i, d in enumerate(directions):
        best = max_range
        for j, (ax, ay, bx, by) in enumerate(segments):
            A = np.array([[d[0], -(bx - ax)], [d[1], -(by - ay)]])
            if abs(np.linalg.det(A)) < 1e-15:
                continue
            t, s = np.linalg.solve(A, np.array([ax, ay]) - origin)
            if 0 < t <= best and 0 <= s <= 1:
                best, rng[i], idx[i] = t, t, j
    return rng, idx


def naive_nearest_segment(points, segments, margin):
    """Perpendicular distance to the nearest segment whose interior (minus margin) the point projects on."""
    n = len(points)
    dist = np.full(n, np.inf)
    idx = np.full(n, -1)
    for i, p in enumerate(points):
        for j, (ax, ay, bx, by) in enumerate(segments):
            a, b = np.array([ax, ay]), np.array([bx, by])
            L = np.linalg.norm(b - a)
            u = (b - a) / L
            along = (p - a) @ u
            if along < margin or along > L - margin:
                continue
            q = p - a
            d = abs(u[0] * q[1] - u[1] * q[0])
            if d < dist[i]:
                dist[i], idx[i] = d, j
    return dist, idx


def naive_sse(xy):
    """Orthogonal-regression SSE of a point set (n * smallest covariance eigenvalue)."""
    c = xy - xy.mean(axis=0)
    return float(np.linalg.eigvalsh(c.T @ c)[0])


def naive_point_to_line_system(q, normals, sd):
    """2-D point-to-line normal equations (Low 2004 reduced to lines): per pair the residual
    ``r = sd`` (signed distance along the panel's normal ``n``) and ``J = [q × n, n_x, n_y]`` for
    ``x = (β, τ_x, τ_y)``; returns ``(Σ JᵀJ, Σ Jᵀ r, Σ r²)``."""
    H = np.zeros((3, 3))
    g = np.zeros(3)
    for (x, y), (nx, ny), r in zip(q, normals, sd, strict=True):
        J = np.array([x * ny - y * nx, nx, ny])
        H += np.outer(J, J)
        g += J * r
    return H, g, float(np.dot(sd, sd))
