"""Naive NumPy twins of the minegeo.geometry kernels (slow, obviously correct, small inputs only).

Also holds the seeded synthetic drift (tunnel) section used by the geometry tests.
"""

from __future__ import annotations

import numpy as np


def naive_neighbors(points, queries, radius=None, max_nn=None):
    """Brute force: per query, indices sorted by (sq distance, index); strict radius; cap max_nn."""
    points = np.asarray(points, dtype=np.float64)
    out = []
    for q in np.asarray(queries, dtype=np.float64):
        d = points - q
        sq = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        idx = np.arange(points.shape[0])
        if radius is not None:
            keep = sq < radius * radius
            idx, sq = idx[keep], sq[keep]
        o = np.lexsort((idx, sq))
        idx, sq = idx[o], sq[o]
        if max_nn is not None:
            idx, sq = idx[:max_nn], sq[:max_nn]
        out.append((idx, sq))
    return out


def naive_normals(points, neighbor_lists):
    """Normal = eigenvector of the smallest eigenvalue of the centred covariance (np.linalg.eigh).

    Returns (normals (n,3), eigenvalues (n,3) ascending); NaN rows for < 3 neighbours.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(neighbor_lists)
    normals = np.full((n, 3), np.nan)
    evals = np.full((n, 3), np.nan)
    for i, nb in enumerate(neighbor_lists):
        if len(nb) < 3:
            continue
        X = points[nb] - points[i]
        X = X - X.mean(axis=0)
        C = X.T @ X / len(nb)
        w, V = np.linalg.eigh(C)
        normals[i] = V[:, 0]
        evals[i] = w
    return normals, evals


def naive_voxel(points, voxel, normals=None):
    """Dict voxel key -> (mean point, mean normal or None, count), Open3D rule, input-order sums."""
    points = np.asarray(points, dtype=np.float64)
    o = points.min(axis=0) - voxel * 0.5
    acc = {}
    for i, p in enumerate(points):
        key = tuple(int(np.floor((p[a] - o[a]) / voxel)) for a in range(3))
        s = acc.setdefault(key, [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0])
        for a in range(3):
            s[0][a] += float(p[a])
        if normals is not None and not np.isnan(normals[i]).any():
            for a in range(3):
                s[1][a] += float(normals[i][a])
        s[2] += 1
    out = {}
    for key, (ps, ns, c) in acc.items():
        out[key] = (np.array(ps) / c, None if normals is None else np.array(ns) / c, c)
    return out


def naive_octree_cube(points, size_expand=0.01):
    """Open3D convert_from_point_cloud cube: origin, size."""
    points = np.asarray(points, dtype=np.float64)
    bmin, bmax = points.min(axis=0), points.max(axis=0)
    c = (bmin + bmax) / 2.0
    h = float(np.max(c - bmin))
    origin = np.minimum(bmin, c - h)
    size = size_expand if h == 0 else h * 2 * (1 + size_expand)
    return origin, size


def naive_octree_leaves(points, level, size_expand=0.01):
    """Dict leaf (ix, iy, iz) -> list of point indices, descending by midpoint comparisons."""
    points = np.asarray(points, dtype=np.float64)
    origin, size = naive_octree_cube(points, size_expand)
    leaves = {}
    for i, p in enumerate(points):
        o = origin.copy()
        s = size
        ijk = [0, 0, 0]
        for _ in range(level):
            h = s / 2.0
            for a in range(3):
                b = 0 if p[a] < o[a] + h else 1
                ijk[a] = 2 * ijk[a] + b
                o[a] = o[a] + b * h
            s = h
        leaves.setdefault(tuple(ijk), []).append(i)
    return leaves, origin, size


def naive_octree_downsample(points, level, size_expand=0.01):
    """Set of kept indices: per occupied leaf, the point nearest the leaf centre (lowest index on ties)."""
    points = np.asarray(points, dtype=np.float64)
    leaves, origin, size = naive_octree_leaves(points, level, size_expand)
    cs = size / 2**level
    kept = set()
    for ijk, idx in leaves.items():
        centre = origin + (np.array(ijk, dtype=np.float64) + 0.5) * cs
        d = points[idx] - centre
        sq = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        best = min(zip(sq.tolist(), idx, strict=True))
        kept.add(best[1])
    return kept


def synthetic_tunnel(n=4000, seed=0, radius=2.5, length=12.0, roughness=0.05, noise=0.005):
    """Seeded drift section: an arched wall (cylinder above the floor) plus a flat floor.

    Returns (points (n,3), axis positions (m,3)) with the drift axis along +y at x=z=0;
    the floor is the plane z = -floor_depth. Points are in metres near the origin.
    """
    rng = np.random.default_rng(seed)
    floor_depth = 0.6 * radius
    half_chord = np.sqrt(radius**2 - floor_depth**2)
    n_floor = n // 4
    n_wall = n - n_floor
    # wall: angles above the floor line
    a0 = -np.arcsin(floor_depth / radius)
    th = rng.uniform(a0, np.pi - a0, n_wall)
    y = rng.uniform(0.0, length, n_wall)
    r = radius + roughness * np.sin(3 * th) * np.cos(1.3 * y) + rng.normal(0.0, noise, n_wall)
    wall = np.c_[r * np.cos(th), y, r * np.sin(th)]
    fx = rng.uniform(-half_chord, half_chord, n_floor)
    fy = rng.uniform(0.0, length, n_floor)
    fz = -floor_depth + rng.normal(0.0, noise, n_floor)
    pts = np.vstack([wall, np.c_[fx, fy, fz]])
    axis = np.c_[np.zeros(25), np.linspace(0.0, length, 25), np.zeros(25)]
    return pts, axis
